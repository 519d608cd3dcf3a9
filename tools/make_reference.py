"""Write docs/reference.md: every command-line option and every sidebar setting, from the code.

    python tools/make_reference.py            # (re)write docs/reference.md
    python tools/make_reference.py --check    # exit 1 if docs/reference.md is out of date

The command line comes from its argument parsers (``recgs_addon.cli.build_parser``; each
command's options from its ``add_*_arguments`` in ``recgs_addon.commands``, batch mode's from
``recgs_addon.batch``): flags, help text, default, choices. The Blender settings come from the
bpy property definitions (``recgs_addon/blender/properties.py``, the per-object preview
settings in ``preview.py`` and the add-on preferences in ``engine.py``), read from the
PropertyGroup annotations, so no Blender data is made; the panel each one is drawn in, and
the name it is drawn with, come from the panels' ``draw`` code. The help texts and tooltips
in the code are the source: change them there and run this again (tests/test_reference.py
fails while the page differs).
"""
from __future__ import annotations

import argparse
import ast
import inspect
import sys
import textwrap
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

PAGE = ROOT / "docs" / "reference.md"
COMMAND = "python -m recgs_addon"

HEADER = f"""\
# Reference: command-line options and Blender settings

Every option of `{COMMAND}` and of batch mode, and every setting of the RecGS sidebar, with
what it does and its default. Generated from the code by `tools/make_reference.py`: do not edit
this page by hand; change the help text or tooltip in the code and run
`python tools/make_reference.py`.
"""


# ---------------------------------------------------------------------------------------
# Markdown helpers
# ---------------------------------------------------------------------------------------

def _cell(text) -> str:
    """Text for one table cell: one line, pipes escaped."""
    return " ".join(str(text).split()).replace("|", "\\|")


def _table(header: list[str], rows: list[list[str]]) -> list[str]:
    lines = ["| " + " | ".join(header) + " |", "|" + "|".join("---" for _ in header) + "|"]
    lines += ["| " + " | ".join(_cell(c) for c in row) + " |" for row in rows]
    return lines


def _code(value) -> str:
    return f"`{value}`"


def _rst_to_md(text: str) -> str:
    return " ".join(text.replace("``", "`").split())


def _sentence(text: str) -> str:
    """The text on one line, ending with a full stop (help texts are written without)."""
    text = " ".join(text.split())
    return text if not text or text.endswith((".", "!", "?")) else text + "."


# ---------------------------------------------------------------------------------------
# Command line
# ---------------------------------------------------------------------------------------

def commands(parser: argparse.ArgumentParser) -> list[tuple[str, argparse.ArgumentParser, str]]:
    """(name, subparser, one-line help) of every command of ``parser``, in the order added."""
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            helps = {a.dest: a.help or "" for a in action._choices_actions}
            return [(name, sub, helps.get(name, "")) for name, sub in action.choices.items()]
    return []


def options(parser: argparse.ArgumentParser) -> list[argparse.Action]:
    """The parser's arguments as a user gives them (``-h`` left out)."""
    return [a for a in parser._actions if not isinstance(a, argparse._HelpAction)]


def _metavar(a: argparse.Action) -> str:
    return a.metavar if isinstance(a.metavar, str) else a.dest.upper()


def invocation(a: argparse.Action) -> str:
    """``--max-side MAX_SIDE``, ``--overwrite``, ``SCENE_DIR``."""
    if not a.option_strings:
        return _metavar(a)
    flags = ", ".join(a.option_strings)
    return flags if a.nargs == 0 else f"{flags} {_metavar(a)}"


def _is_required(a: argparse.Action) -> bool:
    return a.required or (not a.option_strings and a.nargs not in ("?", "*"))


def _default(a: argparse.Action) -> str:
    if _is_required(a):
        return "required"
    if a.nargs == 0:  # a switch
        return "off" if a.default in (False, None) else "on"
    if a.default is None:
        return "not set"
    return _code(a.default)


def _help(parser: argparse.ArgumentParser, a: argparse.Action) -> str:
    text = a.help or ""
    if "%" in text:
        text = parser._get_formatter()._expand_help(a)
    return _sentence(text)


def _exclusions(parser: argparse.ArgumentParser) -> dict:
    """dest -> the flags it may not be given with."""
    out: dict = {}
    for group in parser._mutually_exclusive_groups:
        for a in group._group_actions:
            others = [max(b.option_strings, key=len) for b in group._group_actions if b is not a]
            out.setdefault(a.dest, []).extend(others)
    return out


def _option_rows(parser: argparse.ArgumentParser, actions) -> list[list[str]]:
    excl = _exclusions(parser)
    rows = []
    for a in actions:
        text = _help(parser, a)
        if a.dest in excl:
            text += " Not together with " + ", ".join(_code(f) for f in excl[a.dest]) + "."
        choices = ", ".join(_code(c) for c in a.choices) if a.choices is not None else ""
        rows.append([_code(invocation(a)), text, _default(a), choices])
    return rows


def synopsis(parser: argparse.ArgumentParser) -> str:
    """``python -m recgs_addon train SCENE_DIR --out OUT [options]``."""
    words = [parser.prog]
    acts = options(parser)
    words += [invocation(a) for a in acts if not a.option_strings]
    words += [invocation(a) for a in acts if a.option_strings and a.required]
    if any(a.option_strings and not a.required for a in acts):
        words.append("[options]")
    return " ".join(words)


def command_section(name: str, parser: argparse.ArgumentParser, summary: str, level: str = "###") -> list[str]:
    header = ["Option", "What it does", "Default", "Choices"]
    lines = [f"{level} `{name}`", "", _sentence(parser.description or summary), "",
             f"    {synopsis(parser)}", ""]
    main_groups = {"positional arguments", "options", "optional arguments"}
    grouped = {id(a) for g in parser._action_groups if g.title not in main_groups for a in g._group_actions}
    lines += _table(header, _option_rows(parser, [a for a in options(parser) if id(a) not in grouped]))
    for g in parser._action_groups:
        acts = [a for a in g._group_actions if not isinstance(a, argparse._HelpAction)]
        if g.title in main_groups or not acts:
            continue
        lines += ["", f"{level}# `{name}`: {g.title}", ""]
        if g.description:
            lines += [_sentence(g.description), ""]
        lines += _table(header, _option_rows(parser, acts))
    return lines + [""]


def cli_reference() -> str:
    """The page's command-line part (needs no Blender)."""
    from recgs_addon import batch
    from recgs_addon.cli import build_parser

    top = build_parser()
    cmds = commands(top)
    lines = ["## Command line", "",
             f"    {COMMAND} COMMAND [options]", "",
             "Every command also takes `-h` (`--help`), which prints its options in the terminal.", "",
             "Commands: " + ", ".join(f"[`{name}`](#{name})" for name, _, _ in cmds)
             + ", and [batch mode](#batch-mode).", ""]
    for name, sub, summary in cmds:
        lines += command_section(name, sub, summary)

    bp = batch._parser()
    train = dict((name, sub) for name, sub, _ in cmds).get("train")
    lines += ["### Batch mode", "", _sentence(bp.description or ""), "",
              textwrap.indent(textwrap.dedent(batch.__doc__.split("\n\n")[1]).strip("\n"), "    "), ""]
    same = train is not None and [invocation(a) for a in options(bp)] == [invocation(a) for a in options(train)]
    if same:
        lines += ["It takes the same arguments as [`train`](#train); see [the user guide](user_guide.md#without-the-user-interface).", ""]
    else:
        lines += command_section("batch.py", bp, "", level="####")[2:]
    return "\n".join(lines)


# ---------------------------------------------------------------------------------------
# Blender settings
# ---------------------------------------------------------------------------------------

def properties_of(cls) -> dict:
    """identifier -> (bpy.props function name, keywords) of a PropertyGroup's annotations."""
    out = {}
    for ident, deferred in inspect.get_annotations(cls, eval_str=True).items():
        fn = getattr(deferred, "function", None)
        if fn is None:
            continue
        out[ident] = (fn.__name__, dict(deferred.keywords))
    return out


def _prop_calls(func) -> list[tuple[str, object]]:
    """(identifier, ``text=`` or None) of each ``layout.prop(data, "identifier", ...)`` in a
    function's source, in order: string constants, both arms of ``a if c else b``, and names
    bound by a ``for`` over a tuple of strings."""
    tree = ast.parse(textwrap.dedent(inspect.getsource(func)))
    found: list = []

    def strings(node, env) -> list[str]:
        if isinstance(node, ast.Constant) and isinstance(node.value, str):
            return [node.value]
        if isinstance(node, ast.IfExp):
            return strings(node.body, env) + strings(node.orelse, env)
        if isinstance(node, ast.Name):
            return env.get(node.id, [])
        return []

    def visit(node, env):
        if isinstance(node, ast.For) and isinstance(node.target, ast.Name) and isinstance(node.iter, (ast.Tuple, ast.List)):
            env = {**env, node.target.id: [s for e in node.iter.elts for s in strings(e, env)]}
        if isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute) and node.func.attr == "prop" \
                and len(node.args) >= 2:
            text = next((kw.value.value for kw in node.keywords
                         if kw.arg == "text" and isinstance(kw.value, ast.Constant)), None)
            found.extend((ident, text) for ident in strings(node.args[1], env))
        for child in ast.iter_child_nodes(node):
            visit(child, env)

    visit(tree, {})
    return found


def _calls(func, name: str) -> bool:
    """Whether ``func`` calls a function called ``name`` (``name(...)`` or ``x.name(...)``)."""
    for node in ast.walk(ast.parse(textwrap.dedent(inspect.getsource(func)))):
        if isinstance(node, ast.Call):
            f = node.func
            if (isinstance(f, ast.Name) and f.id == name) or (isinstance(f, ast.Attribute) and f.attr == name):
                return True
    return False


def panel_paths(panel_classes) -> dict:
    """Panel class -> ``RecGS > Training > Advanced`` (its label under its parents')."""
    by_id = {getattr(c, "bl_idname", c.__name__): c for c in panel_classes}

    def path(c):
        parent = by_id.get(getattr(c, "bl_parent_id", ""))
        return (path(parent) + " > " if parent else "") + c.bl_label
    return {c: path(c) for c in panel_classes}


def _shown_name(kw: dict, text) -> str:
    name = kw.get("name", "")
    if text is None:
        return name
    return f"{name} (icon button)" if text == "" else text


def _enum_items(kw: dict) -> list:
    items = kw.get("items", [])
    return list(items) if isinstance(items, (list, tuple)) else []


def _prop_default(fn: str, kw: dict):
    if "default" in kw:
        return kw["default"]
    getter = kw.get("get")
    if getter is not None:   # a view of stored data: the getter's own fallback
        value = inspect.getclosurevars(getter).nonlocals.get("default")
        if value is not None:
            return value
    if fn == "EnumProperty":
        items = _enum_items(kw)
        return items[0][0] if items else ""
    return {"BoolProperty": False, "IntProperty": 0, "FloatProperty": 0.0, "StringProperty": ""}.get(fn, "")


def _format_default(fn: str, kw: dict) -> str:
    value = _prop_default(fn, kw)
    if fn == "BoolProperty":
        return "on" if value else "off"
    if fn == "EnumProperty":
        names = {i[0]: i[1] for i in _enum_items(kw)}
        return f"{names.get(value, value)} ({_code(value)})"
    if fn == "StringProperty" and value == "":
        return "empty"
    return _code(value)


def _range(fn: str, kw: dict) -> str:
    if fn == "EnumProperty":
        return ", ".join(f"{i[1]} ({_code(i[0])})" for i in _enum_items(kw))
    if fn == "StringProperty":
        return {"DIR_PATH": "a folder", "FILE_PATH": "a file"}.get(kw.get("subtype"), "text")
    if fn == "BoolProperty":
        return "on / off"
    lo, hi = kw.get("min"), kw.get("max")
    if lo is not None and hi is not None:
        text = f"{lo} to {hi}"
    elif lo is not None:
        text = f"at least {lo}"
    elif hi is not None:
        text = f"at most {hi}"
    else:
        text = "any number"
    if kw.get("soft_max") is not None and hi is None:
        text += f" (slider to {kw['soft_max']})"
    return text


def _describe(fn: str, kw: dict) -> str:
    text = _sentence(kw.get("description", ""))
    if fn == "EnumProperty":
        parts = [_sentence(f"**{i[1]}**: {i[2]}") for i in _enum_items(kw) if len(i) > 2 and i[2]]
        text = " ".join([text] + parts if text else parts)
    return text


def _setting_rows(props: dict, drawn: list, cli_flags: dict | None = None) -> list[list[str]]:
    rows = []
    for ident, text in drawn:
        fn, kw = props[ident]
        row = [_shown_name(kw, text), _code(ident), _describe(fn, kw), _format_default(fn, kw), _range(fn, kw)]
        if cli_flags is not None:
            row.append(_code(cli_flags[ident]) if ident in cli_flags else "")
        rows.append(row)
    return rows


def settings_reference() -> str:
    """The page's Blender part (imports bpy: the property definitions need it)."""
    from recgs_addon.blender import engine, panel, preview, properties
    from recgs_addon.cli import build_parser

    train = dict((n, s) for n, s, _ in commands(build_parser()))["train"]
    flags = {a.dest: max(a.option_strings, key=len) for a in options(train) if a.option_strings}
    cli_flags = {d: flags[d] for d in properties.SETTINGS_OPTIONS if d in flags}

    header = ["Setting", "Identifier", "What it does", "Default", "Range / choices"]
    lines = ["## Blender settings", "",
             "The **RecGS** tab of the 3D viewport's sidebar (N). Panels are listed as they nest; "
             "*Identifier* is the Python name, for scripts.", ""]

    # scene.recgs: the panels in the order they are registered, each setting where it is drawn
    props = properties_of(properties.RecGSSettings)
    paths = panel_paths(panel.classes)
    seen: set = set()
    lines += ["### Scene and training settings (`scene.recgs`)", "",
              _sentence(_rst_to_md(properties.__doc__.split("\n\n")[0])) + " The *`train` option* column names "
              "the command-line option each one becomes when the sidebar starts a job.", ""]
    for cls in panel.classes:
        drawn = [(i, t) for i, t in _prop_calls(cls.draw) if i in props and i not in seen]
        seen.update(i for i, _ in drawn)
        if drawn:
            lines += [f"#### {paths[cls]}", ""]
            lines += _table(header + ["`train` option"], _setting_rows(props, drawn, cli_flags)) + [""]
    status = [(i, None) for i in props if i not in seen]
    if status:
        lines += ["#### Job status", "",
                  "Written by the running job and shown in the Training panel's progress box; not settings "
                  "to change by hand.", ""]
        rows = [[r[0], r[1], r[2], r[3]] for r in _setting_rows(props, status)]
        lines += _table(["Field", "Identifier", "What it holds", "Initial value"], rows) + [""]

    # per-object preview settings: drawn by preview.draw_panel inside a panel of panel.py
    props = properties_of(preview.RecGSPreviewSettings)
    where = next((paths[c] for c in panel.classes if _calls(c.draw, preview.draw_panel.__name__)), "RecGS")
    drawn = [(i, t) for i, t in _prop_calls(preview.draw_panel) if i in props]
    drawn += [(i, None) for i in props if i not in {d for d, _ in drawn}]
    lines += [f"### Preview settings (`object.recgs_preview`), panel {where}", "",
              _sentence(_rst_to_md(inspect.getdoc(preview.RecGSPreviewSettings) or "")), ""]
    lines += _table(header, _setting_rows(props, drawn)) + [""]

    # add-on preferences
    prefs = engine.RECGS_AddonPreferences
    props = properties_of(prefs)
    drawn = [(i, t) for i, t in _prop_calls(prefs.draw) if i in props]
    drawn += [(i, None) for i in props if i not in {d for d, _ in drawn}]
    lines += ["### Add-on preferences", "",
              "*Edit > Preferences > Add-ons > RecGS*, below the training engine's status.", ""]
    lines += _table(header, _setting_rows(props, drawn)) + [""]
    return "\n".join(lines)


def build() -> str:
    """The whole page."""
    return "\n".join([HEADER, cli_reference(), settings_reference()]).rstrip("\n") + "\n"


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--check", action="store_true", help="only check that the page is up to date (exit 1 if not)")
    args = p.parse_args(argv)
    text = build()
    if args.check:
        if not PAGE.is_file() or PAGE.read_text() != text:
            print(f"{PAGE.relative_to(ROOT)} is out of date: run python tools/make_reference.py", file=sys.stderr)
            return 1
        return 0
    PAGE.write_text(text)
    print(f"wrote {PAGE.relative_to(ROOT)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
