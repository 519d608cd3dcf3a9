"""Draw the RecGS sidebar as pictures for the user guide, from the panels' own drawing code.

    .venv/bin/python tools/make_panel_figure.py [--scene data/dive] [--out docs/images] [--scale 1.25]

Blender without a window takes no screenshots, so the panels' ``draw`` runs against the
recording layout of ``tools/panel_snapshot.py`` (its ``Recorder``, extended here to note which
items share a row and what each one is), after the COLMAP survey ``--scene`` is imported, as
the sidebar looks idle and while a job runs. The recorded labels, settings with their values,
buttons, boxes and sub-panel headers are then drawn in a Blender-like dark theme with numpy,
and the text with OpenImageIO (``ImageBufAlgo.render_text``: DejaVu Sans where the system has
it, else the font OpenImageIO ships with). Writes to ``--out``:

* ``panel_idle.png``: the whole sidebar after *Import COLMAP*, sub-panels folded as they start;
* ``panel_running.png``: the RecGS header and the Training panel while a job runs;
* ``panel_advanced.png``: the Training panel with *Advanced* open;
* ``panel_preview.png``: the Output and Preview panels, *Preview* open.
"""
from __future__ import annotations

import argparse
import glob
import itertools
import shutil
import subprocess
import sys
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from tools import panel_snapshot as ps  # noqa: E402

# -- recording ---------------------------------------------------------------------------------

_ROW_IDS = itertools.count(1)
_CAPTURED: list[list] = []   # the line lists of the snapshots taken, in order


class _Tagged(str):
    """A recorded line that also carries what was drawn (``info``)."""
    info: dict


class FigureRecorder(ps.Recorder):
    """panel_snapshot's Recorder that also notes, per line, the kind of item and its row."""

    _row = None       # items drawn into one ``row()`` share its number
    _pending = None   # what the next emitted line is

    def __init__(self, lines, depth=0):
        super().__init__(lines, depth)
        if not any(seen is lines for seen in _CAPTURED):
            _CAPTURED.append(lines)

    def _child(self, kind, indent):
        child = super()._child(kind, indent)
        child._c._row = None if kind == "box" else self._row
        return child

    def row(self, **kw):
        child = super().row(**kw)
        if self._row is None:
            child._c._row = next(_ROW_IDS)
        return child

    def _emit(self, text):
        super()._emit(text)
        info = dict(self._pending or {"kind": "label", "text": text}, row=self._row, line=text,
                    greyed=not (self.enabled and self.active))
        tagged = _Tagged(self._lines[-1])
        tagged.info = info
        self._lines[-1] = tagged
        self._pending = None

    def label(self, text="", icon="NONE", **kw):
        self._pending = {"kind": "label", "text": text}
        return super().label(text=text, icon=icon, **kw)

    def prop(self, data, prop, text=None, icon="NONE", **kw):
        rna = data.bl_rna.properties[prop]
        info = {"kind": "prop", "name": rna.name if text is None else text, "type": rna.type,
                "subtype": rna.subtype if rna.type == "STRING" else "", "slider": bool(kw.get("slider")), "expand": bool(kw.get("expand")),
                "icon_only": text == "" and icon != "NONE"}
        if rna.type == "ENUM":
            info["items"] = [i.name for i in rna.enum_items]
        self._pending = info
        return super().prop(data, prop, text=text, icon=icon, **kw)

    def operator(self, idname, text=None, icon="NONE", **kw):
        self._pending = {"kind": "button", "icon_only": text == "", "icon": icon}
        return super().operator(idname, text=text, icon=icon, **kw)


@dataclass
class Item:
    kind: str               # header, box, sep, label, prop, button
    depth: int
    path: tuple = ()        # labels of the panels it is in (a header's includes its own)
    info: dict = field(default_factory=dict)
    text: str = ""
    closed: bool = False


def record(scene: Path | None, states: list[str]) -> dict[str, list[Item]]:
    """The sidebar's items in each state, recorded by panel_snapshot's ``snapshots``."""
    _CAPTURED.clear()
    real = ps.Recorder
    ps.Recorder = FigureRecorder   # panel_snapshot builds its layouts from this name
    try:
        texts = ps.snapshots(scene, states)
    finally:
        ps.Recorder = real
    if len(_CAPTURED) != len(states):
        raise RuntimeError(f"recorded {len(_CAPTURED)} sidebars for {len(states)} states")
    out = {}
    for state, lines in zip(states, _CAPTURED):
        assert "\n".join(lines) == texts[state]   # the same recording as the text snapshot
        out[state] = parse(lines)
    return out


def parse(lines: list[str]) -> list[Item]:
    items, stack = [], []   # stack: (depth, label) of the enclosing panels
    for line in lines:
        depth = (len(line) - len(line.lstrip(" "))) // 2
        body = line.strip()
        if isinstance(line, _Tagged):
            info = line.info
            items.append(Item(info["kind"], depth, tuple(label for _, label in stack), info))
        elif body.startswith("== ") and body.endswith(" =="):
            label = body[3:-3]
            closed = label.endswith(" (closed)")
            label = label.removesuffix(" (closed)")
            while stack and stack[-1][0] >= depth:
                stack.pop()
            stack.append((depth, label))
            items.append(Item("header", depth, tuple(lbl for _, lbl in stack), text=label, closed=closed))
        elif body == "box:":
            items.append(Item("box", depth, tuple(lbl for _, lbl in stack)))
        elif not body:
            items.append(Item("sep", items[-1].depth if items else 0, tuple(lbl for _, lbl in stack)))
        else:
            raise ValueError(f"unrecognised panel line {line!r}")
    return items


def select(items: list[Item], show: list[tuple], open_: set[str] = frozenset()) -> list[Item]:
    """The items of the root panel and of the panels under the paths in ``show``; folded
    panels keep only their header unless their label is in ``open_``."""
    out = []
    for it in items:
        p = it.path
        if len(p) > 1 and not any(p[:len(s)] == s for s in show):
            continue
        folded = [i for i in range(1, len(p) + 1) if _closed(items, p[:i]) and p[i - 1] not in open_]
        if folded and not (it.kind == "header" and folded == [len(p)]):
            continue
        out.append(it)
    return out


def _closed(items, path) -> bool:
    return any(it.kind == "header" and it.path == path and it.closed for it in items)


# -- drawing -----------------------------------------------------------------------------------

def _hex(h: str) -> np.ndarray:
    return np.array([int(h[i:i + 2], 16) for i in (1, 3, 5)], np.float32) / 255.0


THEME = {
    "region": _hex("#232323"), "panel": _hex("#303030"), "header": _hex("#3a3a3a"),
    "box": _hex("#2a2a2a"), "box_line": _hex("#444444"), "button": _hex("#545454"),
    "field": _hex("#1d1d1d"), "menu": _hex("#282828"), "select": _hex("#4772b3"),
    "text": _hex("#e6e6e6"), "text_dim": _hex("#8c8c8c"), "check": _hex("#ffffff"),
}


def find_font() -> str:
    """A TrueType font for render_text: DejaVu Sans where found, else '' (OpenImageIO's own)."""
    if shutil.which("fc-match"):
        r = subprocess.run(["fc-match", "-f", "%{file}", "DejaVu Sans:style=Book"], capture_output=True, text=True)
        if r.returncode == 0 and r.stdout.endswith("DejaVuSans.ttf") and Path(r.stdout).is_file():
            return r.stdout
    for pattern in ("/usr/share/fonts/**/DejaVuSans.ttf", "/usr/local/share/fonts/**/DejaVuSans.ttf",
                    "/Library/Fonts/DejaVuSans.ttf", "C:/Windows/Fonts/DejaVuSans.ttf"):
        hits = glob.glob(pattern, recursive=True)
        if hits:
            return hits[0]
    return ""


class Canvas:
    """An RGB float picture: shapes drawn at once with numpy, text queued for OpenImageIO."""

    def __init__(self, width: int, height: int, font: str, size: float):
        self.img = np.empty((height, width, 3), np.float32)
        self.img[:] = THEME["region"]
        self.font, self.size = font, size
        self.texts = []

    def _blend(self, y0, y1, x0, x1, cover, color):
        h, w = self.img.shape[:2]
        sy, sx = slice(max(y0, 0), min(y1, h)), slice(max(x0, 0), min(x1, w))
        cover = cover[sy.start - y0:sy.stop - y0, sx.start - x0:sx.stop - x0, None]
        self.img[sy, sx] = self.img[sy, sx] * (1 - cover) + np.asarray(color) * cover

    def rect(self, x0, y0, x1, y1, color, radius=3.0, outline=None):
        """A rounded rectangle, anti-aliased; ``outline``: a 1-pixel border of that colour."""
        r = max(radius, 1.0)
        X0, Y0, X1, Y1 = int(np.floor(x0)), int(np.floor(y0)), int(np.ceil(x1)), int(np.ceil(y1))
        ys, xs = np.mgrid[Y0:Y1, X0:X1].astype(np.float32) + 0.5
        dx = np.maximum(np.maximum(x0 + r - xs, xs - (x1 - r)), 0)
        dy = np.maximum(np.maximum(y0 + r - ys, ys - (y1 - r)), 0)
        d = np.hypot(dx, dy)
        if outline is not None:
            self._blend(Y0, Y1, X0, X1, np.clip(r - d + 0.5, 0, 1), outline)
            r -= 1.0
        self._blend(Y0, Y1, X0, X1, np.clip(r - d + 0.5, 0, 1), color)

    def polygon(self, points, color, samples=4):
        """A convex polygon (points in order), 4x4 supersampled."""
        pts = np.asarray(points, np.float32)
        X0, Y0 = np.floor(pts.min(0)).astype(int)
        X1, Y1 = np.ceil(pts.max(0)).astype(int)
        off = (np.arange(samples) + 0.5) / samples
        ys = (np.arange(Y0, Y1)[:, None] + off[None]).reshape(-1)
        xs = (np.arange(X0, X1)[:, None] + off[None]).reshape(-1)
        X, Y = np.meshgrid(xs, ys)
        inside = np.ones_like(X, bool)
        sign = None
        for (ax, ay), (bx, by) in zip(pts, np.roll(pts, -1, 0)):
            c = (bx - ax) * (Y - ay) - (by - ay) * (X - ax)
            sign = np.sign(c.sum()) if sign is None else sign
            inside &= c * sign >= 0
        cover = inside.reshape(Y1 - Y0, samples, X1 - X0, samples).mean((1, 3)).astype(np.float32)
        self._blend(Y0, Y1, X0, X1, cover, color)

    def line(self, p, q, width, color):
        p, q = np.asarray(p, np.float32), np.asarray(q, np.float32)
        X0, Y0 = np.floor(np.minimum(p, q) - width).astype(int)
        X1, Y1 = np.ceil(np.maximum(p, q) + width).astype(int)
        ys, xs = np.mgrid[Y0:Y1, X0:X1].astype(np.float32) + 0.5
        v = q - p
        t = np.clip(((xs - p[0]) * v[0] + (ys - p[1]) * v[1]) / max(float(v @ v), 1e-6), 0, 1)
        d = np.hypot(xs - p[0] - t * v[0], ys - p[1] - t * v[1])
        self._blend(Y0, Y1, X0, X1, np.clip(width / 2 - d + 0.5, 0, 1), color)

    def text_width(self, text: str) -> float:
        import OpenImageIO as oiio

        if not text:
            return 0.0
        roi = oiio.ImageBufAlgo.text_size(text, int(round(self.size)), self.font)
        return float(roi.width) if roi.defined else len(text) * self.size * 0.55

    def fit(self, text: str, width: float, keep_end: bool = False) -> str:
        """``text`` shortened with '...' (at its start for paths) to fit ``width`` pixels."""
        if self.text_width(text) <= width:
            return text
        while len(text) > 1:
            text = text[1:] if keep_end else text[:-1]
            shown = "..." + text if keep_end else text + "..."
            if self.text_width(shown) <= width:
                return shown
        return ""

    def text(self, x, y, text, color, align="left"):
        if text:
            self.texts.append((x, y, text, color, align))

    def finish(self) -> np.ndarray:
        import OpenImageIO as oiio

        buf = oiio.ImageBuf(np.ascontiguousarray(self.img))
        for x, y, text, color, align in self.texts:
            base = y + 0.36 * self.size   # the baseline, so that letters with and without descenders line up
            ok = oiio.ImageBufAlgo.render_text(buf, int(round(x)), int(round(base)), text, int(round(self.size)),
                                               self.font, [float(c) for c in color], align, "baseline")
            if not ok:
                raise SystemExit(f"make_panel_figure: OpenImageIO cannot draw text ({buf.geterror()}); "
                                 "install a font such as DejaVu Sans")
        return buf.get_pixels(oiio.FLOAT)[..., :3]


@dataclass
class Metrics:
    scale: float = 1.25

    def __post_init__(self):
        s = self.scale
        self.width = round(330 * s)      # the sidebar's width
        self.row = round(20 * s)         # one widget's height
        self.gap = round(3 * s)          # between rows
        self.header = round(24 * s)      # a panel header
        self.indent = round(9 * s)       # per nesting level, on the left
        self.inset = round(4 * s)        # per nesting level, on the right
        self.pad = round(7 * s)          # inside a panel, around its widgets
        self.sep = round(8 * s)
        self.font = 11.5 * s
        self.radius = 4 * s


def _rows(items: list[Item]) -> list[list[Item]]:
    """Items grouped into lines: neighbours of one ``row()`` share a line."""
    lines: list[list[Item]] = []
    for it in items:
        r = it.info.get("row")
        if lines and r is not None and lines[-1][-1].info.get("row") == r and lines[-1][-1].kind in ("prop", "button", "label"):
            lines[-1].append(it)
        else:
            lines.append([it])
    return lines


def draw(items: list[Item], m: Metrics, font: str) -> np.ndarray:
    """The items as a picture of the sidebar."""
    lines = _rows(items)

    def left(depth):
        return m.pad + depth * m.indent

    def right(depth):
        return m.width - m.pad - depth * m.inset

    def last_inside(i):
        """Index of the last line inside the header or box at line i."""
        head, j = lines[i][0], i
        while j + 1 < len(lines):
            nxt = lines[j + 1][0]
            if nxt.depth <= head.depth or (head.kind == "box" and nxt.kind == "header"):
                break
            j += 1
        return j

    # pass 1: where each line starts, and where each panel and box ends
    ends: dict[int, list[int]] = {}
    for i, ln in enumerate(lines):
        if ln[0].kind in ("header", "box"):
            ends.setdefault(last_inside(i), []).insert(0, i)   # innermost first
    ys, bottoms, y = [], {}, m.pad
    for i, ln in enumerate(lines):
        it = ln[0]
        if it.kind == "header" and i:
            y += m.gap
        ys.append(y)
        y += {"header": m.header, "sep": m.sep, "box": m.gap}.get(it.kind, m.row) + m.gap
        for c in ends.get(i, []):
            if c != i:
                bottoms[c] = y
                y += m.gap
            else:
                bottoms[c] = ys[i] + (m.header if it.kind == "header" else 0)
    height = int(np.ceil(y + m.pad))
    cv = Canvas(m.width, height, font, m.font)

    # pass 2: panel and box backgrounds, outer first
    for i, ln in enumerate(lines):
        it = ln[0]
        if it.kind == "header":
            x0, x1 = left(it.depth), right(it.depth)
            if bottoms[i] > ys[i] + m.header:
                cv.rect(x0, ys[i], x1, bottoms[i], THEME["panel"] + 0.025 * it.depth, m.radius)
            cv.rect(x0, ys[i], x1, ys[i] + m.header, THEME["header"] + 0.025 * it.depth, m.radius)
            cx, cy, a = x0 + m.pad + 3 * m.scale, ys[i] + m.header / 2, 3.5 * m.scale
            tri = ([(cx - a, cy - a / 2), (cx + a, cy - a / 2), (cx, cy + a * 0.7)] if last_inside(i) > i
                   else [(cx - a / 2, cy - a), (cx + a * 0.7, cy), (cx - a / 2, cy + a)])
            cv.polygon(tri, THEME["text"] * 0.85)
            cv.text(cx + 2.6 * a, cy, it.text, THEME["text"])
        elif it.kind == "box":
            cv.rect(left(it.depth), ys[i], right(it.depth), bottoms[i], THEME["box"], m.radius,
                    outline=THEME["box_line"])

    # pass 3: the widgets, side by side where they share a row
    for i, ln in enumerate(lines):
        if ln[0].kind in ("header", "box", "sep"):
            continue
        x0, x1 = left(ln[0].depth), right(ln[0].depth)
        fixed = sum(m.row for it in ln if it.info.get("icon_only"))
        share = (x1 - x0 - fixed) / max(sum(1 for it in ln if not it.info.get("icon_only")), 1)
        x = x0
        for it in ln:
            w = m.row if it.info.get("icon_only") else share
            _widget(cv, it, x, ys[i], w, m)
            x += w
    return cv.finish()


def _widget(cv: Canvas, it: Item, x: float, y: float, w: float, m: Metrics) -> None:
    info, h, r, s = it.info, m.row, m.radius, m.scale
    grey = info.get("greyed")
    text_c = THEME["text_dim"] if grey else THEME["text"]

    def fill(c):
        return c * 0.6 + THEME["panel"] * 0.4 if grey else c

    cy, inner = y + h / 2, 5 * s
    if it.kind == "label":
        cv.text(x + 2 * s, cy, cv.fit(info["text"], w - 4 * s), text_c)
        return
    if it.kind == "button":
        cv.rect(x + 1, y, x + w - 1, y + h, fill(THEME["button"]), r)
        if info.get("icon_only"):
            c, a = (x + w / 2, cy), 3.5 * s
            cv.line((c[0] - a, c[1] - a), (c[0] + a, c[1] + a), 1.4 * s, text_c)
            cv.line((c[0] - a, c[1] + a), (c[0] + a, c[1] - a), 1.4 * s, text_c)
        else:
            label = info["line"][2:info["line"].rindex(" ]  (")]
            cv.text(x + w / 2, cy, cv.fit(label, w - 2 * inner), text_c, "center")
        return
    # a setting
    name, kind = info["name"], info["type"]
    value = info["line"][len(name) + 2:] if name else info["line"]
    if kind == "BOOLEAN":
        on = value == "[x]"
        if info.get("icon_only"):
            cv.rect(x + 1, y, x + w - 1, y + h, fill(THEME["select"] if on else THEME["button"]), r)
            cv.rect(x + w / 2 - 3 * s, cy - 3 * s, x + w / 2 + 3 * s, cy + 3 * s, text_c, 3 * s)
            return
        b = 13 * s
        cv.rect(x + 2 * s, cy - b / 2, x + 2 * s + b, cy + b / 2, fill(THEME["select"] if on else THEME["button"]), 3 * s)
        if on:
            cv.line((x + 5 * s, cy), (x + 7.5 * s, cy + 3 * s), 1.6 * s, THEME["check"])
            cv.line((x + 7.5 * s, cy + 3 * s), (x + 12 * s, cy - 3.5 * s), 1.6 * s, THEME["check"])
        cv.text(x + 2 * s + b + 5 * s, cy, cv.fit(name, w - b - 9 * s), text_c)
    elif kind == "ENUM" and info.get("expand"):
        n = len(info["items"])
        for k, item in enumerate(info["items"]):
            a, b = x + 1 + k * (w - 2) / n, x + 1 + (k + 1) * (w - 2) / n
            cv.rect(a, y, b - 1, y + h, fill(THEME["select"] if item == value else THEME["button"]), r)
            cv.text((a + b) / 2, cy, cv.fit(item, b - a - 2 * inner), text_c, "center")
    elif kind in ("ENUM", "STRING"):
        split = x + w * 0.4
        cv.text(split - 6 * s, cy, cv.fit(name, split - x - 8 * s), text_c, "right")
        if kind == "STRING":
            value = value[1:-1] if value.startswith('"') else value
        color = THEME["menu"] if kind == "ENUM" else THEME["field"]
        cv.rect(split, y, x + w - 1, y + h, fill(color), r)
        room = x + w - split - 2 * inner - (10 * s if kind == "ENUM" else 0)
        cv.text(split + inner, cy, cv.fit(value, room, keep_end=info["subtype"] in ("DIR_PATH", "FILE_PATH")), text_c)
        if kind == "ENUM":
            ax = x + w - inner - 4 * s
            cv.line((ax - 3 * s, cy - 1.5 * s), (ax, cy + 1.5 * s), 1.2 * s, text_c)
            cv.line((ax, cy + 1.5 * s), (ax + 3 * s, cy - 1.5 * s), 1.2 * s, text_c)
    else:   # a number
        cv.rect(x + 1, y, x + w - 1, y + h, fill(THEME["button"]), r)
        if info.get("slider"):
            share = float(np.clip(float(value), 0, 1))
            cv.rect(x + 1, y, x + 1 + max((w - 2) * share, 2 * r), y + h, fill(THEME["select"]), r)
        shown = cv.fit(value, (w - 2 * inner) * 0.45)
        cv.text(x + inner, cy, cv.fit(name, w - 3 * inner - cv.text_width(shown)), text_c)
        cv.text(x + w - inner, cy, shown, text_c, "right")


# -- the guide's figures -----------------------------------------------------------------------

FIGURES = {
    # name: (state, sub-panel paths shown, folded panels drawn open)
    "panel_idle": ("idle", [("RecGS",)], set()),
    "panel_running": ("running", [("RecGS", "Training")], set()),
    "panel_advanced": ("idle", [("RecGS", "Training")], {"Advanced"}),
    "panel_preview": ("idle", [("RecGS", "Output"), ("RecGS", "Preview")], {"Preview"}),
}


def write_png(path: Path, img: np.ndarray) -> None:
    import OpenImageIO as oiio

    px = np.clip(np.round(img * 255), 0, 255).astype(np.uint8)
    out = oiio.ImageOutput.create(str(path))
    if out is None or not out.open(str(path), oiio.ImageSpec(px.shape[1], px.shape[0], 3, oiio.UINT8)):
        raise SystemExit(f"{path}: cannot write ({oiio.geterror()})")
    out.write_image(px)
    out.close()


def main(argv=None) -> int:
    if argv is None:
        argv = sys.argv[sys.argv.index("--") + 1:] if "--" in sys.argv else sys.argv[1:]
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scene", type=Path, default=ROOT / "data" / "dive", help="COLMAP survey imported first")
    ap.add_argument("--out", type=Path, default=ROOT / "docs" / "images")
    ap.add_argument("--scale", type=float, default=1.25, help="size of the sidebar (1 = Blender at 100 %%)")
    args = ap.parse_args(argv)
    recorded = record(args.scene, ["idle", "running"])
    font, m = find_font(), Metrics(args.scale)
    args.out.mkdir(parents=True, exist_ok=True)
    for name, (state, show, open_) in FIGURES.items():
        items = select(recorded[state], show, open_)
        for it in items:   # a folder of this machine reads as one of the user's
            if it.info.get("line"):
                it.info["line"] = it.info["line"].replace(str(ROOT), "/path/to")
        path = args.out / f"{name}.png"
        write_png(path, draw(items, m, font))
        print(f"{path.relative_to(ROOT) if path.is_relative_to(ROOT) else path}  {path.stat().st_size / 1024:.0f} KB")
    print("font:", font or "OpenImageIO's own")
    return 0


if __name__ == "__main__":
    sys.exit(main())
