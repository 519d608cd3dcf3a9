"""The user docs stay true: the guide's panel figures are the sidebar as drawn, its pictures and
links exist, every command it and the README show parses, and the short ones run."""
from __future__ import annotations

import importlib.util
import re
import shlex
import subprocess
import sys

import numpy as np
import pytest

from conftest import ROOT

USER_DOCS = [ROOT / "README.md", ROOT / "docs" / "user_guide.md", ROOT / "docs" / "method.md",
             ROOT / "docs" / "reference.md"]
ALL_DOCS = sorted(set(USER_DOCS) | set((ROOT / "docs").glob("**/*.md")) | {ROOT / "benchmarks" / "RESULTS.md"})


def _tool():
    spec = importlib.util.spec_from_file_location("make_doc_images", ROOT / "tools" / "make_doc_images.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_the_guides_panel_figures_are_the_sidebar_as_drawn():
    pytest.importorskip("bpy")
    tool = _tool()
    held = tool.guide_panels(tool.GUIDE.read_text())
    assert set(held) == {"idle", "running"}, held.keys()
    live = tool.panel_snapshots(ROOT / "data" / "dive")
    for state in held:
        assert held[state] == live[state], (
            f"docs/user_guide.md's {state} panel is out of date: run `python tools/make_doc_images.py --panels-only`")


def test_update_guide_replaces_only_the_marked_blocks():
    tool = _tool()
    text = "a\n<!-- panel idle -->\n```\nold\n```\n<!-- /panel -->\nb ```x```\n"
    new = tool.update_guide(text, {"idle": "new\n"})
    assert new == "a\n<!-- panel idle -->\n```\nnew\n```\n<!-- /panel -->\nb ```x```\n"
    assert tool.guide_panels(new) == {"idle": "new\n"}
    with pytest.raises(KeyError, match="running"):
        tool.update_guide(text.replace("idle", "running"), {"idle": "x\n"})


def test_side_by_side_puts_a_white_gap_between_pictures():
    tool = _tool()
    a, b = np.zeros((3, 2, 3), np.float32), np.full((3, 5, 4), 0.5, np.float32)
    row = tool.side_by_side([a, b], gap=1)
    assert row.shape == (3, 8, 3)
    assert (row[:, :2] == 0).all() and (row[:, 2] == 1).all() and (row[:, 3:] == 0.5).all()
    with pytest.raises(ValueError, match="heights"):
        tool.side_by_side([a, np.zeros((4, 2, 3))])


def _slug(heading: str) -> str:
    """GitHub's anchor for a heading."""
    s = re.sub(r"[^\w\- ]", "", heading.strip().lower())
    return s.replace(" ", "-")


@pytest.mark.parametrize("doc", ALL_DOCS, ids=lambda p: p.name)
def test_links_and_pictures_resolve(doc):
    text = re.sub(r"```.*?```", "", doc.read_text(), flags=re.S)
    bad = []
    for target in re.findall(r"\]\(([^)\s]+)\)", text):
        if re.match(r"[a-z]+://", target):
            continue
        path, _, anchor = target.partition("#")
        file = (doc.parent / path).resolve() if path else doc
        if not file.exists():
            bad.append(f"{target}: no such file")
        elif anchor and file.suffix == ".md":
            slugs = {_slug(h) for h in re.findall(r"^#+ (.*)$", file.read_text(), re.M)}
            slugs |= set(re.findall(r'<a id="([^"]+)"></a>', file.read_text()))
            if anchor not in slugs:
                bad.append(f"{target}: no heading with that anchor")
    assert not bad, f"{doc.relative_to(ROOT)}: " + "; ".join(bad)


PREFIXES = ("blender -b --python recgs_addon/batch.py --", "blender -b --factory-startup --python recgs_addon/batch.py --",
            "python -m recgs_addon", ".venv/bin/python -m recgs_addon", "python recgs_addon/batch.py",
            ".venv/bin/python recgs_addon/batch.py")


def _commands(doc):
    """Command lines shown in a doc's code (indented blocks and fenced blocks), continuation
    lines joined, comments dropped."""
    out = []
    lines = doc.read_text().splitlines()
    for i, line in enumerate(lines):
        j = i
        while lines[j].rstrip().endswith("\\") and j + 1 < len(lines):
            j += 1
            line = line.rstrip().rstrip("\\") + " " + lines[j].strip()
        for part in line.strip().split(" && "):
            part = part.split("  #")[0].split("  (")[0]
            prefix = next((p for p in PREFIXES if part.startswith(p + " ")), None)
            if prefix and "COMMAND" not in part:
                out.append(("batch" if "batch.py" in prefix else "cli", shlex.split(part[len(prefix):])))
    return out


def _optional_brackets(args):
    """``[--a X] [--b|--c]`` in a usage line: keep the first alternative of each."""
    text = " ".join(args)
    text = re.sub(r"\[([^\[\]]*)\]", lambda m: m.group(1).split("|")[0], text)
    return [PLACEHOLDERS.get(a.split("|")[0], a.split("|")[0]) for a in text.split()]


#: numbers a usage line names by a letter
PLACEHOLDERS = {"N": "2", "M": "1", "S": "1", "PX": "1600", "Q": "90", "GB": "4", "SHARE": "0.5"}


@pytest.mark.parametrize("doc", [ROOT / "README.md", ROOT / "docs" / "user_guide.md"], ids=lambda p: p.name)
def test_every_command_shown_parses(doc):
    from recgs_addon import batch, cli

    cmds = _commands(doc)
    assert cmds, f"{doc.name}: no commands found"
    for kind, args in cmds:
        args = _optional_brackets(args)
        parser = batch._parser() if kind == "batch" else cli.build_parser()
        try:
            parser.parse_args(args)
        except SystemExit:
            pytest.fail(f"{doc.relative_to(ROOT)}: `{' '.join(args)}` does not parse")


def test_the_guides_info_command_runs(tmp_path):
    from recgs_addon.core.io.ply import write_gaussian_ply
    from recgs_addon.core.model.gaussians import GaussianSet

    n = 3
    g = GaussianSet(means=np.zeros((n, 3), np.float32), log_scales=np.full((n, 3), -3, np.float32),
                quats=np.tile(np.float32([1, 0, 0, 0]), (n, 1)), logit_opacities=np.zeros(n, np.float32),
                sh=np.zeros((n, 1, 3), np.float32))
    write_gaussian_ply(tmp_path / "point_cloud.ply", g)
    line = next(a for k, a in _commands(ROOT / "docs" / "user_guide.md") if a and a[0] == "info")
    r = subprocess.run([sys.executable, "-m", "recgs_addon", *[a.replace("OUT/", f"{tmp_path}/") for a in line]],
                       cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    import json
    assert json.loads(r.stdout)["gaussians"] == 3, r.stdout
