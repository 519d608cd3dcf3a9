"""The project speaks of itself alone: code, tests and docs name a measurement or a change by
its date, version or benchmark (benchmarks/RESULTS.md), never by how the work on it was
organised: no numbered sessions or stops ("the ninth session", "the fourth stop", "stop 27"),
no "this session", no issue numbers ("issue 17", "#17").

"session" stays legitimate for a Blender, bpy, HTTP or Python session, and "stop" for a run,
a pixel or a job that stops: the patterns below only take the process sense (an ordinal, or
this / that / last / next / previous, before "session"; an ordinal or a number with "stop").
"""
from __future__ import annotations

import re
import subprocess

import pytest

from conftest import ROOT

#: Files scanned: every tracked file with one of these endings.
SUFFIXES = (".py", ".md", ".toml", ".sh", ".txt")

_ORDINAL = (r"(?:first|second|third|fourth|fifth|sixth|seventh|eighth|ninth|tenth|eleventh|"
            r"twelfth|thirteenth|fourteenth|fifteenth|sixteenth|seventeenth|eighteenth|"
            r"nineteenth|twentieth|\d+(?:st|nd|rd|th))")

#: (pattern, what it finds). Case-insensitive.
PATTERNS = [
    (re.compile(rf"\b{_ORDINAL}[\s-]+sessions?\b", re.I), "a numbered session"),
    (re.compile(r"\b(?:this|that|last|next|previous)\s+sessions?\b", re.I), "a session of the work"),
    (re.compile(rf"\b{_ORDINAL}\s+stops?\b", re.I), "a numbered stop"),
    (re.compile(r"\b(?:this|next|previous)\s+stop\b(?!s)", re.I), "a stop of the work"),
    # "stop 27", but not "stop 30 steps into ..." (a run stopping after an amount)
    (re.compile(r"\bstop\s+#?\d+\b(?!\s*(?:steps?|s|ms|seconds?|minutes?|iterations?|rounds?|"
                r"px|pixels?|%)\b)", re.I), "a numbered stop"),
    (re.compile(r"\bissues?\s+#?\d+\b", re.I), "an issue number"),
    (re.compile(r"(?<![\w&#/])#\d{1,5}\b(?![\w-])"), "an issue number"),
]

#: Files left out, each with its reason. This test's own examples are the only entry.
ALLOWED_FILES = {
    "tests/test_no_process_words.py": "its examples of what the patterns find",
}


def process_words(text: str) -> list[tuple[int, str, str]]:
    """(line number, the words found, what they are) for every process-sense phrase in
    ``text``, line by line."""
    found = []
    for number, line in enumerate(text.splitlines(), 1):
        spans = []
        for pattern, what in PATTERNS:
            for m in pattern.finditer(line):
                if not any(a <= m.start() and m.end() <= b for a, b in spans):   # "#17" of "issue #17"
                    spans.append(m.span())
                    found.append((number, m.group(0), what))
    return found


def tracked_files() -> list[str]:
    try:
        out = subprocess.run(["git", "ls-files", "-z"], cwd=ROOT, capture_output=True, check=True).stdout
    except (OSError, subprocess.CalledProcessError):
        pytest.skip("not a git checkout: no list of tracked files")
    return [p for p in out.decode().split("\0") if p.endswith(SUFFIXES)]


@pytest.mark.parametrize("text", [
    "The ninth session's measurements are below.",
    "## Where the caustics go (seventh session)",
    "made in the 2nd session",
    "on this session's machine",
    "runs from previous sessions",
    "the fourth stop, below, built both",
    "Own threads (third stop of issue 17)",
    "22.88 on two threads, stop 27",
    "the issue 19 trial",
    "see issue #17",
    "fixed in #17.",
    "this stop's two changes",
])
def test_process_phrases_are_found(text):
    assert process_words(text), text


@pytest.mark.parametrize("text", [
    "A Blender session with the add-on registered.",
    "def test_x(bpy_session): the bpy session fixture",
    "an HTTP session, requests.Session(), a Python session",
    "a second Blender session opens the file",
    "the plateau stop; SIGTERM stops the job cleanly",
    "stop the run 30 steps into the first recurrence",
    "stop 30 steps into the recurrence; a stop 5 s later",
    "conditions that stop the run, and training stops when held-out PSNR has plateaued",
    "a pixel stops at the first Gaussian for which T (1 - alpha) < 1e-4 (the stop rule)",
    "measured 2026-11-25, benchmarks/RESULTS.md#caustics-six-surveys",
    "issues with large photos; colour #ffcc00",
    "x = a[1]  # 2 threads",
])
def test_ordinary_words_pass(text):
    assert process_words(text) == [], process_words(text)


def test_found_with_line_numbers_once_each():
    assert process_words("a Blender session\nthe ninth session\n") == [(2, "ninth session", "a numbered session")]
    assert process_words("see issue #17") == [(1, "issue #17", "an issue number")]


def test_no_process_words_in_the_project():
    bad = []
    for rel in tracked_files():
        if rel in ALLOWED_FILES:
            continue
        path = ROOT / rel
        if not path.is_file():    # deleted in the work tree, not yet in the index
            continue
        text = path.read_text(encoding="utf-8", errors="replace")
        bad.extend(f"{rel}:{n}: {words!r} ({what})" for n, words, what in process_words(text))
    assert not bad, ("name the date, version or benchmark instead of the work's sessions, stops or "
                     "issues:\n" + "\n".join(bad))
