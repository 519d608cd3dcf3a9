"""docs/reference.md is what tools/make_reference.py makes from the code, and it lists every
command-line option and every sidebar setting."""
from __future__ import annotations

import importlib.util
import re

import pytest

from conftest import ROOT

PAGE = ROOT / "docs" / "reference.md"
SCRIPT = ROOT / "tools" / "make_reference.py"
STALE = "docs/reference.md is out of date: run `python tools/make_reference.py` and commit the page"


def _tool():
    spec = importlib.util.spec_from_file_location("make_reference", SCRIPT)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


@pytest.fixture(scope="module")
def tool():
    return _tool()


@pytest.fixture(scope="module")
def page():
    assert PAGE.is_file(), STALE
    return PAGE.read_text()


def _section(page: str, heading: str) -> str:
    """The page from ``heading`` to the next heading of the same or a higher level."""
    level = len(heading) - len(heading.lstrip("#"))
    start = page.index(heading + "\n")
    end = re.compile(rf"^#{{1,{level}}} ", re.M).search(page, start + len(heading))
    return page[start:end.start() if end else len(page)]


def test_command_line_part_is_current(tool, page):
    """Needs no Blender: the command-line part, regenerated, is in the page as it stands."""
    assert tool.cli_reference() in page, STALE


def test_every_option_of_every_command_is_listed(tool, page):
    from recgs_addon.cli import build_parser

    cmds = tool.commands(build_parser())
    assert {name for name, _, _ in cmds} >= {"import", "info", "train", "render", "sfm", "video"}
    for name, sub, _ in cmds:
        text = _section(page, f"### `{name}`")
        for action in tool.options(sub):
            words = action.option_strings or [tool.invocation(action)]
            for word in words:
                assert f"`{word}" in text, f"{name}: {word} is not on the page. {STALE}"


@pytest.mark.blender
def test_whole_page_is_current(tool, page):
    pytest.importorskip("bpy")
    assert tool.build() == page, STALE


@pytest.mark.blender
def test_every_setting_is_listed(tool, page):
    pytest.importorskip("bpy")
    from recgs_addon.blender import engine, preview, properties

    for cls in (properties.RecGSSettings, preview.RecGSPreviewSettings, engine.RECGS_AddonPreferences):
        props = tool.properties_of(cls)
        assert props, cls.__name__
        for ident, (_, kw) in props.items():
            assert f"| `{ident}` |" in page, f"{cls.__name__}.{ident} is not on the page. {STALE}"


@pytest.mark.blender
def test_settings_sit_under_the_panel_that_draws_them(page):
    """Spot checks of what the panel code says: Advanced settings under Advanced, the panel's
    own label where it overrides the property's name, job status fields apart."""
    pytest.importorskip("bpy")
    advanced = _section(page, "#### RecGS > Training > Advanced")
    assert "| `preset` |" in advanced and "| `out_dir` |" in advanced
    training = _section(page, "#### RecGS > Training")
    assert "| Time Limit (min) | `max_minutes` |" in training
    assert "| `--max-minutes` |" in training
    assert "| `progress` |" in _section(page, "#### Job status")
