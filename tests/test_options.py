"""Every ``train`` option is declared once (core/options/train.py): the command line's parser
and the sidebar's settings are built from that declaration and nothing adds one of its own."""
import ast
import inspect
from dataclasses import fields
from pathlib import Path

import pytest

from recgs_addon.cli import build_parser
from recgs_addon.core.options.capture import SFM_OPTIONS, VIDEO_OPTIONS
from recgs_addon.core.options.table import SAME, Option, OptionTable, Setting
from recgs_addon.core.options.scene import IMPORT_OPTIONS, INFO_OPTIONS, RENDER_OPTIONS, SCENE_DIR
from recgs_addon.core.options.train import TRAIN_OPTIONS
from recgs_addon.core.train.config import TrainConfig

PKG = Path(__file__).resolve().parents[1] / "recgs_addon"


TABLES = {"train": TRAIN_OPTIONS, "sfm": SFM_OPTIONS, "video": VIDEO_OPTIONS, "import": IMPORT_OPTIONS,
          "info": INFO_OPTIONS, "render": RENDER_OPTIONS}
#: sidebar settings of the capture commands' options: property -> (table, option)
CAPTURE_SETTINGS = {"link_photos": (SFM_OPTIONS, "link"), "video_frames": (VIDEO_OPTIONS, "frames"),
                    "video_every": (VIDEO_OPTIONS, "every"), "video_max_side": (VIDEO_OPTIONS, "max_side")}


def _parser(command):
    parser = build_parser()
    sub = next(a for a in parser._actions if a.dest == "command")
    return sub.choices[command]


@pytest.mark.parametrize("command", sorted(TABLES))
def test_the_parsers_are_the_tables(command):
    table = TABLES[command]
    actions = [a for a in _parser(command)._actions if a.dest != "help"]
    assert [a.dest for a in actions] == [o.dest for o in table], "an option the table does not declare"
    for a in actions:
        opt = table[a.dest]
        assert a.help == opt.cli_help()
        assert (a.default, tuple(a.choices or ())) == ((False if opt.type is bool else opt.default), opt.values), a.dest


def test_option_defaults_are_the_configs():
    """An option that sets a TrainConfig field takes that field's default (or leaves it to it)."""
    defaults = {f.name: f.default for f in fields(TrainConfig)}
    text = {"budget": {"auto": None}}   # options given as text: their value in the config
    checked = 0
    for opt in TRAIN_OPTIONS:
        if opt.dest in defaults and opt.default is not None:
            assert text.get(opt.dest, {}).get(opt.default, opt.default) == defaults[opt.dest], opt.dest
            checked += 1
    assert checked >= 4


def test_shared_options_are_one_declaration():
    """The survey folder and the plain-PyTorch switch are one declaration each, wherever taken."""
    assert TRAIN_OPTIONS["scene_dir"] is SCENE_DIR is IMPORT_OPTIONS["scene_dir"]
    assert RENDER_OPTIONS["eager"] is TRAIN_OPTIONS["eager"]
    assert SFM_OPTIONS["camera_model"] is VIDEO_OPTIONS["camera_model"]


def test_a_table_refuses_a_second_declaration_and_says_why_a_sidebar_default_differs():
    with pytest.raises(ValueError, match="declared twice"):
        OptionTable([Option("--seed", "a"), Option("--seed", "b")])
    for opt in TRAIN_OPTIONS.settings():
        if opt.setting.default is not SAME and opt.setting.default != opt.default and opt.default is not None:
            assert opt.setting.why, f"{opt.dest}: the sidebar's default differs without a reason"
    assert Option("--x", "y", default=3, setting=Setting("X")).setting_default() == 3


def test_the_sidebar_settings_are_the_table():
    bpy = pytest.importorskip("bpy")
    from recgs_addon.blender import properties

    props = {k: v for k, v in inspect.get_annotations(properties.RecGSSettings, eval_str=True).items()
             if hasattr(v, "function")}
    # the options a job takes from the sidebar (the scene folder is the job's positional argument)
    assert set(properties.SETTINGS) == {o.dest for o in TRAIN_OPTIONS.settings() if o.flag.startswith("-")}
    pairs = [(o.dest, o) for o in TRAIN_OPTIONS.settings()]
    pairs += [(prop, table[dest]) for prop, (table, dest) in CAPTURE_SETTINGS.items()]
    assert {d for t in (SFM_OPTIONS, VIDEO_OPTIONS) for d in (o.dest for o in t.settings())} == \
        {dest for _, dest in CAPTURE_SETTINGS.values()}
    for prop, opt in pairs:
        kw = props[prop].keywords
        assert (kw["name"], kw["description"], kw["default"]) == (opt.setting.label, opt.setting_help(),
                                                                  opt.setting_default()), prop
    assert bpy is not None


def test_no_option_is_declared_outside_the_table():
    """No ``add_argument`` in the train and capture commands' modules, and each sidebar setting
    of an option is made by ``_setting`` from its table, not by a property call of its own."""
    for name in ("train.py", "capture.py", "render.py", "scene.py"):
        tree = ast.parse((PKG / "commands" / name).read_text())
        calls = [n for n in ast.walk(tree) if isinstance(n, ast.Call) and getattr(n.func, "attr", "") == "add_argument"]
        assert not calls, name
    tree = ast.parse((PKG / "blender" / "properties.py").read_text())
    cls = next(n for n in tree.body if isinstance(n, ast.ClassDef) and n.name == "RecGSSettings")
    dests = {o.dest for o in TRAIN_OPTIONS.settings()} | set(CAPTURE_SETTINGS)
    own = [n.target.id for n in cls.body if isinstance(n, ast.AnnAssign) and n.target.id in dests
           and not (isinstance(n.annotation, ast.Call) and getattr(n.annotation.func, "id", "") == "_setting")]
    assert not own, own
