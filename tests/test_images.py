import numpy as np
import pytest

from recgs_addon.core.errors import ImageError
from recgs_addon.core.io.images import image_size, read_image, training_size, write_image


def _smooth(h=48, w=64):
    y, x = np.mgrid[0:h, 0:w]
    return np.stack([x / w, y / h, 0.5 + 0.4 * np.sin(x / 7.0) * np.cos(y / 5.0)], -1).astype(np.float32)


@pytest.mark.parametrize("ext,tol", [(".png", 0.5 / 255 + 1e-6), (".tif", 0.5 / 65535 + 1e-6),
                                     (".exr", 0.0), (".jpg", 0.06)])
def test_round_trip_formats(tmp_path, ext, tol):
    a = _smooth()
    write_image(tmp_path / f"a{ext}", a)
    b = read_image(tmp_path / f"a{ext}")
    assert b.dtype == np.float32 and b.shape == a.shape
    assert np.abs(a - b).max() <= tol
    assert image_size(tmp_path / f"a{ext}") == (64, 48)


def test_16bit_png_keeps_precision(tmp_path):
    import OpenImageIO as oiio

    a = (np.arange(64 * 48 * 3).reshape(48, 64, 3) * 7 % 65536).astype(np.uint16)
    out = oiio.ImageOutput.create(str(tmp_path / "a.png"))
    out.open(str(tmp_path / "a.png"), oiio.ImageSpec(64, 48, 3, oiio.UINT16))
    out.write_image(a)
    out.close()
    b = read_image(tmp_path / "a.png")
    assert np.abs(b - a / 65535.0).max() < 1e-6


def test_downscale_is_area_average(tmp_path):
    rng = np.random.default_rng(0)
    a = rng.random((48, 64, 3)).astype(np.float32)
    write_image(tmp_path / "a.exr", a)
    for f in (2, 4):
        b = read_image(tmp_path / "a.exr", downscale=f)
        ref = a.reshape(48 // f, f, 64 // f, f, 3).mean((1, 3))
        assert np.abs(b - ref).max() < 1e-6


def test_grey_and_alpha_become_rgb(tmp_path):
    g = np.linspace(0, 1, 48 * 64, dtype=np.float32).reshape(48, 64, 1)
    write_image(tmp_path / "g.exr", g)
    assert read_image(tmp_path / "g.exr").shape == (48, 64, 3)
    rgba = np.concatenate([_smooth(), np.ones((48, 64, 1), np.float32)], -1)
    write_image(tmp_path / "rgba.png", rgba)
    assert read_image(tmp_path / "rgba.png").shape == (48, 64, 3)


def test_errors_name_the_file(tmp_path):
    with pytest.raises(ImageError, match="missing.png: image file is missing"):
        read_image(tmp_path / "missing.png")
    (tmp_path / "bad.png").write_bytes(b"this is not a png")
    with pytest.raises(ImageError, match="bad.png: cannot read image"):
        read_image(tmp_path / "bad.png")
    with pytest.raises(ImageError, match="bad.png"):
        image_size(tmp_path / "bad.png")


def test_non_ascii_path_with_spaces(tmp_path):
    p = tmp_path / "fonds marins é" / "vue 1 ß.png"
    write_image(p, _smooth())
    assert read_image(p).shape == (48, 64, 3)


@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
def test_float_image_with_nan_or_inf_pixels_is_refused(tmp_path, bad):
    """Regression (outside trial): an EXR with NaN/Inf pixels was read as it was; training on
    it skipped every step that saw it (NaN loss) and said nothing. Now it names the file."""
    a = _smooth()
    a[5, 7, 1] = bad
    a[9:11, 2] = bad
    write_image(tmp_path / "hdr.exr", a)
    with pytest.raises(ImageError, match=r"hdr.exr: 3 pixels are NaN or infinite \(the first at x=7, y=5\)"):
        read_image(tmp_path / "hdr.exr")
    with pytest.raises(ImageError, match=r"hdr.exr: 3 pixels are NaN or infinite \(the first at x=3, y=2\)"):
        read_image(tmp_path / "hdr.exr", 2)


def test_training_size_caps_the_long_side_and_keeps_the_aspect():
    assert training_size(5600, 4200, 1, 1600) == (1600, 1200)
    assert training_size(4200, 5600, 1, 1600) == (1200, 1600)          # portrait: the long side is the height
    assert training_size(320, 240, 1, 1600) == (320, 240)             # small photos stay as they are
    assert training_size(320, 240, 2, 1600) == (160, 120)
    assert training_size(6000, 4000, 2, 1600) == (1600, 1067)         # downscale first, then the cap
    assert training_size(6000, 4000, 1, 0) == (6000, 4000)            # 0: no cap


def test_compact_read_keeps_8_bit_values_and_reduces_once(tmp_path):
    a = _smooth(96, 128)
    write_image(tmp_path / "a.png", a)
    full = read_image(tmp_path / "a.png")
    small = read_image(tmp_path / "a.png", compact=True)
    assert small.dtype == np.uint8 and small.shape == (96, 128, 3)
    assert np.allclose(small.astype(np.float32) / 255.0, full, rtol=0, atol=1e-7)   # the file's own 8-bit values
    half = read_image(tmp_path / "a.png", size=(64, 48), compact=True)
    ref = full.reshape(48, 2, 64, 2, 3).mean((1, 3))                  # area average, rounded to 8 bits
    assert half.dtype == np.uint8 and np.abs(half / 255.0 - ref).max() <= 0.5 / 255 + 1e-6
    write_image(tmp_path / "a.exr", 3.0 * a)                          # float files: float16, values kept
    f16 = read_image(tmp_path / "a.exr", compact=True)
    assert f16.dtype == np.float16 and np.abs(f16.astype(np.float32) - 3.0 * a).max() <= 3.0 * 2 ** -11
    write_image(tmp_path / "hdr.exr", np.full((8, 8, 3), 1e6, np.float32))   # beyond float16: float32
    assert read_image(tmp_path / "hdr.exr", compact=True).dtype == np.float32
