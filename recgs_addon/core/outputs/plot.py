"""Small PNG charts and image strips for the reports, drawn with OpenImageIO (already a
dependency; its ``render_text`` carries its own font), so reports need no plotting library.
"""
from __future__ import annotations

import math
from pathlib import Path
from typing import Optional, Sequence

import numpy as np

from ..io.images import _oiio, write_image

PALETTE = [(0.12, 0.47, 0.71), (1.0, 0.5, 0.05), (0.17, 0.63, 0.17), (0.84, 0.15, 0.16),
           (0.58, 0.4, 0.74), (0.55, 0.34, 0.29), (0.89, 0.47, 0.76), (0.5, 0.5, 0.5)]


def nice_ticks(lo: float, hi: float, n: int = 5) -> list[float]:
    """About ``n`` round tick values covering [lo, hi]."""
    if not (math.isfinite(lo) and math.isfinite(hi)):
        return []
    if hi <= lo:
        hi = lo + 1.0
    raw = (hi - lo) / max(n, 1)
    mag = 10 ** math.floor(math.log10(raw))
    step = min((m * mag for m in (1, 2, 2.5, 5, 10) if m * mag >= raw), default=10 * mag)
    start = math.ceil(lo / step - 1e-9) * step
    return [start + i * step for i in range(int((hi - start) / step + 1e-9) + 1)]


def _fmt(v: float) -> str:
    if v == 0:
        return "0"
    if abs(v) >= 100:
        return f"{v:.0f}"
    if abs(v) >= 1:
        return f"{v:.1f}".rstrip("0").rstrip(".")
    return f"{v:.3g}"


def line_chart(path: str | Path, series: Sequence[tuple[str, Sequence[float], Sequence[float]]], *,
               title: str = "", xlabel: str = "", ylabel: str = "", log_y: bool = False,
               width: int = 720, height: int = 420, markers: bool = True) -> Path:
    """Write a line chart of ``(label, xs, ys)`` series to ``path`` (PNG)."""
    oiio = _oiio()
    alg = oiio.ImageBufAlgo
    buf = oiio.ImageBuf(oiio.ImageSpec(width, height, 3, oiio.FLOAT))
    alg.fill(buf, (1.0, 1.0, 1.0))
    left, right, top, bottom = 70, 190, 48, 52
    x0, x1, y0, y1 = left, width - right, top, height - bottom

    def tr(v):
        return math.log10(v) if log_y else v

    pts = [(x, tr(y)) for _, xs, ys in series for x, y in zip(xs, ys)
           if y is not None and math.isfinite(x) and math.isfinite(y) and (not log_y or y > 0)]
    if pts:
        xs_all, ys_all = zip(*pts)
        xlo, xhi = min(xs_all), max(xs_all)
        ylo, yhi = min(ys_all), max(ys_all)
    else:
        xlo, xhi, ylo, yhi = 0.0, 1.0, 0.0, 1.0
    if xhi <= xlo:
        xhi = xlo + 1.0
    pad = 0.05 * (yhi - ylo) if yhi > ylo else 0.5
    ylo, yhi = ylo - pad, yhi + pad

    def px(x, y):
        return (int(round(x0 + (x - xlo) / (xhi - xlo) * (x1 - x0))),
                int(round(y1 - (y - ylo) / (yhi - ylo) * (y1 - y0))))

    grey, black = (0.85, 0.85, 0.85), (0.0, 0.0, 0.0)
    for t in nice_ticks(xlo, xhi):
        xp, _ = px(t, ylo)
        alg.render_line(buf, xp, y0, xp, y1, grey)
        alg.render_text(buf, xp - 10, y1 + 18, _fmt(t), 13, "", black)
    yticks = ([v for v in range(math.floor(ylo), math.ceil(yhi) + 1)] if log_y else nice_ticks(ylo, yhi))
    for t in yticks:
        if not ylo <= t <= yhi:
            continue
        _, yp = px(xlo, t)
        alg.render_line(buf, x0, yp, x1, yp, grey)
        alg.render_text(buf, 6, yp + 5, _fmt(10 ** t if log_y else t), 13, "", black)
    alg.render_box(buf, x0, y0, x1, y1, black)
    for k, (label, xs, ys) in enumerate(series):
        col = PALETTE[k % len(PALETTE)]
        prev = None
        for x, y in zip(xs, ys):
            if y is None or not math.isfinite(y) or (log_y and y <= 0):
                prev = None
                continue
            p = px(x, tr(y))
            if prev is not None:
                alg.render_line(buf, prev[0], prev[1], p[0], p[1], col)
            if markers:
                alg.render_box(buf, p[0] - 2, p[1] - 2, p[0] + 2, p[1] + 2, col, fill=True)
            prev = p
        ly = y0 + 14 + 20 * k
        alg.render_box(buf, x1 + 12, ly - 9, x1 + 24, ly + 1, col, fill=True)
        alg.render_text(buf, x1 + 30, ly, label[:22], 13, "", black)
    alg.render_text(buf, x0, 20, title, 16, "", black)
    alg.render_text(buf, 6, 40, ylabel, 13, "", black)
    alg.render_text(buf, (x0 + x1) // 2 - 4 * len(xlabel), height - 12, xlabel, 14, "", black)
    path = Path(path)
    write_image(path, np.asarray(buf.get_pixels(oiio.FLOAT)).reshape(height, width, 3))
    return path


def labelled_strip(path: str | Path, images: Sequence[np.ndarray], labels: Sequence[str],
                   gap: int = 6, band: int = 22, scale: Optional[int] = None) -> Path:
    """Images (H, W, 3) in [0, 1] side by side under their labels, written as PNG."""
    h = max(im.shape[0] for im in images)
    if scale is None:
        scale = max(1, 240 // h)
    ims = [np.repeat(np.repeat(np.clip(im, 0, 1), scale, 0), scale, 1) for im in images]
    h = max(im.shape[0] for im in ims)
    w = sum(im.shape[1] for im in ims) + gap * (len(ims) - 1)
    canvas = np.ones((h + band, w, 3), np.float32)
    x = 0
    for im in ims:
        canvas[band:band + im.shape[0], x:x + im.shape[1]] = im
        x += im.shape[1] + gap
    oiio = _oiio()
    buf = oiio.ImageBuf(oiio.ImageSpec(w, h + band, 3, oiio.FLOAT))
    buf.set_pixels(oiio.ROI(0, w, 0, h + band, 0, 1, 0, 3), canvas)
    x = 0
    for im, label in zip(ims, labels):
        oiio.ImageBufAlgo.render_text(buf, x + 4, band - 6, label, 14, "", (0.0, 0.0, 0.0))
        x += im.shape[1] + gap
    path = Path(path)
    write_image(path, np.asarray(buf.get_pixels(oiio.FLOAT)).reshape(h + band, w, 3))
    return path


def signed_map(c: np.ndarray, span: Optional[float] = None) -> np.ndarray:
    """A signed map (H, W, C) shown as grey 0.5 + c / (2 span) (span: 99th percentile of |c|)."""
    c = np.asarray(c, np.float32)
    if span is None:
        span = float(np.percentile(np.abs(c), 99)) or 1.0
    return np.clip(0.5 + c / (2 * span), 0, 1)
