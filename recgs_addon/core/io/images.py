"""Image reading and writing with OpenImageIO.

Images are returned as float32 arrays of shape (H, W, 3) (RGB; grey is expanded, alpha
dropped). 8- and 16-bit integer files (PNG, JPEG, TIFF) are normalised to [0, 1]; float
files (EXR, float TIFF) keep their values, and one with NaN or infinite pixels is refused.
A training run asks for the compact form instead (``read_image(..., compact=True)``): 8-bit
files as uint8, others as float16, decoded once at the training size (:func:`training_size`),
so that its memory grows with the training resolution and not with the photos' own.
"""
from __future__ import annotations

import os
from pathlib import Path
from typing import Optional

import numpy as np

from ..errors import ImageError
from .atomic import atomic_path

#: File extensions treated as images when listing a folder.
IMAGE_EXTENSIONS = (".png", ".jpg", ".jpeg", ".tif", ".tiff", ".exr", ".bmp")
#: Largest finite float16 value: float images beyond it stay float32 in compact form.
FLOAT16_MAX = 65504.0



def _first_line(message: str) -> str:
    """OpenImageIO's error text repeats itself over several lines; the first says what happened."""
    lines = [ln.strip() for ln in str(message).splitlines() if ln.strip()]
    return lines[0] if lines else "unknown error"

def _oiio():
    import OpenImageIO as oiio  # imported lazily: the Blender layer loads without it

    return oiio


def _image_file(path: str | os.PathLike) -> Path:
    """``path`` as a Path, if it is an image file that exists (ImageError naming it otherwise)."""
    path = Path(path)
    if path.is_dir():
        raise ImageError(f"{path}: is a folder, not an image file")
    if not path.is_file():
        raise ImageError(f"{path}: image file is missing")
    return path


def image_size(path: str | os.PathLike) -> tuple[int, int]:
    """(width, height) of an image file, read from its header only."""
    oiio = _oiio()
    path = _image_file(path)
    inp = oiio.ImageInput.open(str(path))
    if inp is None:
        raise ImageError(f"{path}: cannot read image ({oiio.geterror() or 'unknown format'})")
    try:
        spec = inp.spec()
        return int(spec.width), int(spec.height)
    finally:
        inp.close()


def training_size(width: int, height: int, downscale: int = 1, max_side: int = 0) -> tuple[int, int]:
    """(width, height) an image of ``width x height`` is trained at: divided by ``downscale``,
    then reduced (aspect kept) so that its long side is at most ``max_side`` px (0: no cap).
    The reference 3DGS code caps photos at 1600 px the same way: a 24 MP photo holds far more
    pixels than a model of a few million Gaussians can use, and memory and step time grow
    with the pixels."""
    scale = 1.0 / downscale
    if max_side and max(width, height) * scale > max_side:
        scale = max_side / max(width, height)
    return max(1, int(round(width * scale))), max(1, int(round(height * scale)))


def read_image(path: str | os.PathLike, downscale: int = 1, size: tuple[int, int] | None = None,
               compact: bool = False) -> np.ndarray:
    """Read an image as (H, W, 3), decoded once and reduced to the size asked for.

    Args:
        path: image file (PNG/JPEG/TIFF 8 or 16 bit, EXR, ...).
        downscale: integer factor >= 1; the image is reduced with OIIO's box-filter resize,
            which averages exactly the source pixels under each output pixel (area-correct)
            when the size divides evenly. Output size is round(W / downscale) x round(H / downscale).
        size: ``(width, height)`` to reduce to instead (the box filter too); None: ``downscale``.
        compact: keep the pixels small: an 8-bit file comes back as uint8 (0-255, its own
            values at its own size, rounded after a resize), any other as float16 where its
            values fit (float32 otherwise). What a training run holds in memory.
    Returns:
        (H, W, 3) float32 (values in [0, 1] for integer formats), or the compact form.
    """
    oiio = _oiio()
    path = _image_file(path)
    buf = oiio.ImageBuf(str(path))
    if buf.has_error or buf.spec().width <= 0:
        raise ImageError(f"{path}: cannot read image ({buf.geterror() or 'unknown format'})")
    # decode every pixel now: a file cut short fails here, once (read lazily, a resize of it
    # retries the missing tiles over and over, and OpenImageIO prints each failure)
    if not buf.read(0, 0, True):
        raise ImageError(f"{path}: cannot decode image pixels ({_first_line(buf.geterror())})")
    spec = buf.spec()
    eight_bit = spec.format == oiio.UINT8
    if size is None:
        if downscale < 1 or int(downscale) != downscale:
            raise ImageError(f"{path}: downscale must be an integer >= 1, got {downscale}")
        size = (max(1, int(round(spec.width / downscale))), max(1, int(round(spec.height / downscale))))
    w, h = int(size[0]), int(size[1])
    if w < 1 or h < 1:
        raise ImageError(f"{path}: cannot reduce to {w}x{h} pixels")
    if (w, h) != (spec.width, spec.height):
        roi = oiio.ROI(0, w, 0, h, 0, 1, 0, spec.nchannels)
        small = oiio.ImageBufAlgo.resize(buf, filtername="box", roi=roi)
        if small.has_error:
            raise ImageError(f"{path}: cannot resize image ({_first_line(small.geterror())})")
        buf = small
    pixels = buf.get_pixels(oiio.UINT8 if compact and eight_bit else oiio.FLOAT)
    if pixels is None or buf.has_error:
        raise ImageError(f"{path}: cannot decode image pixels ({_first_line(buf.geterror())})")
    arr = np.asarray(pixels)
    if arr.ndim == 2:
        arr = arr[:, :, None]
    if arr.ndim == 4:  # (depth, H, W, C) for volume images: take the first slice
        arr = arr[0]
    c = arr.shape[2]
    if c == 1 or c == 2:  # grey or grey+alpha
        arr = np.repeat(arr[:, :, :1], 3, axis=2)
    elif c >= 3:
        arr = arr[:, :, :3]
    if arr.dtype == np.uint8:
        return np.ascontiguousarray(arr)
    bad = ~np.isfinite(arr).all(axis=2)
    if bad.any():   # float files (EXR, float TIFF) can hold them; no loss or score survives one
        y, x = np.argwhere(bad)[0]
        raise ImageError(f"{path}: {int(bad.sum())} pixels are NaN or infinite (the first at x={x}, y={y}); "
                         "replace them before training on this image")
    if compact and float(np.abs(arr).max(initial=0.0)) < FLOAT16_MAX:
        return np.ascontiguousarray(arr, dtype=np.float16)
    return np.ascontiguousarray(arr, dtype=np.float32)


def write_image(path: str | os.PathLike, image: np.ndarray, quality: Optional[int] = None) -> None:
    """Write (H, W, C) float image. PNG/JPEG/TIFF get 8-bit values clipped to [0, 1]
    (16-bit for .tif); EXR keeps float32 (half is not used so values survive exactly). A
    uint8 image is written to PNG/JPEG as it is. ``quality``: JPEG quality 1-100 (None:
    OpenImageIO's default).

    The file is written to a temporary name first and renamed, so a crash never leaves a
    half-written image under the final name.
    """
    oiio = _oiio()
    path = Path(path)
    ext = path.suffix.lower()
    if np.asarray(image).dtype == np.uint8 and ext not in (".exr", ".tif", ".tiff"):
        image = np.asarray(image)
    else:
        image = np.asarray(image, dtype=np.float32)
    if image.ndim == 2:
        image = image[:, :, None]
    h, w, c = image.shape
    if image.dtype == np.uint8:
        fmt, data = oiio.UINT8, image
    elif ext == ".exr":
        fmt, data = oiio.FLOAT, image
    elif ext in (".tif", ".tiff"):
        fmt, data = oiio.UINT16, np.clip(image, 0.0, 1.0)
    else:
        fmt, data = oiio.UINT8, np.clip(image, 0.0, 1.0)
    spec = oiio.ImageSpec(w, h, c, fmt)
    if quality is not None and ext in (".jpg", ".jpeg"):
        spec.attribute("Compression", f"jpeg:{int(quality)}")
    with atomic_path(path, "image") as tmp:
        out = oiio.ImageOutput.create(str(tmp))
        if out is None:
            raise ImageError(f"{path}: cannot write images of this type ({oiio.geterror()})")
        if not out.open(str(tmp), spec):
            raise ImageError(f"{path}: cannot open for writing ({out.geterror()})")
        ok = out.write_image(np.ascontiguousarray(data))
        out.close()
        if not ok:
            raise ImageError(f"{path}: writing failed ({out.geterror()})")
