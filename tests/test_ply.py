"""PLY: exact INRIA layout on write; any layout from other tools on read; clear refusals."""
import warnings

import numpy as np
import pytest

from recgs_addon.core.errors import PlyError, RecGSError
from recgs_addon.core.model.gaussians import GaussianSet
from recgs_addon.core.io.ply import (gaussians_to_records, ply_property_names, read_gaussian_ply,
                                  write_gaussian_ply)

FIELDS = ("means", "log_scales", "quats", "logit_opacities", "sh")


def random_gaussians(n=50, degree=3, seed=0):
    rng = np.random.default_rng(seed)
    return GaussianSet(rng.normal(size=(n, 3)), rng.normal(size=(n, 3)) - 3, rng.normal(size=(n, 4)),
                       rng.normal(size=n), rng.normal(size=(n, (degree + 1) ** 2, 3)))


def assert_same(a, b):
    for f in FIELDS:
        assert np.array_equal(getattr(a, f), getattr(b, f)), f


@pytest.mark.parametrize("degree", [0, 1, 2, 3])
def test_round_trip_identical(tmp_path, degree):
    g = random_gaussians(degree=degree)
    write_gaussian_ply(tmp_path / "g.ply", g)
    assert_same(g, read_gaussian_ply(tmp_path / "g.ply"))


def test_inria_header_and_layout(tmp_path):
    g = random_gaussians(n=3, degree=3)
    write_gaussian_ply(tmp_path / "g.ply", g)
    raw = (tmp_path / "g.ply").read_bytes()
    head, body = raw.split(b"end_header\n", 1)
    lines = head.decode().splitlines()
    assert lines[:3] == ["ply", "format binary_little_endian 1.0", "element vertex 3"]
    props = [ln.split()[2] for ln in lines[3:]]
    assert all(ln.split()[1] == "float" for ln in lines[3:])
    expected = (["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
                + [f"f_rest_{i}" for i in range(45)]
                + ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"])
    assert props == expected == ply_property_names(3)
    table = np.frombuffer(body, dtype="<f4").reshape(3, 62)
    assert np.all(table[:, 3:6] == 0)  # normals
    # f_rest channel-major: f_rest_0..14 are red coefficients 1..15 (INRIA's transpose)
    assert np.array_equal(table[:, 9:24], g.sh[:, 1:, 0])
    assert np.array_equal(table[:, 24:39], g.sh[:, 1:, 1])
    assert np.array_equal(table[:, 54], g.logit_opacities)
    assert np.array_equal(table[:, 58:62], g.quats)


def _write_custom(path, g, order=None, fmt="binary_little_endian", dtype="f4", extra=()):
    rec = gaussians_to_records(g)
    names = list(order or rec.dtype.names) + [e[0] for e in extra]
    ptype = {"f4": "float", "f8": "double"}[dtype]
    header = ["ply", f"format {fmt} 1.0", "comment made by another tool", f"element vertex {len(g)}"]
    header += [f"property {ptype} {n}" for n in names[: len(names) - len(extra)]]
    header += [f"property uchar {e[0]}" for e in extra]
    header += ["element face 0", "property list uchar int vertex_indices", "end_header"]
    with open(path, "wb") as f:
        f.write(("\n".join(header) + "\n").encode())
        if fmt == "ascii":
            for i in range(len(g)):
                vals = [repr(float(rec[n][i])) for n in names[: len(names) - len(extra)]]
                vals += [str(e[1]) for e in extra]
                f.write((" ".join(vals) + "\n").encode())
        else:
            end = "<" if fmt == "binary_little_endian" else ">"
            dt = np.dtype([(n, end + dtype) for n in names[: len(names) - len(extra)]]
                          + [(e[0], "u1") for e in extra])
            out = np.zeros(len(g), dt)
            for n in names[: len(names) - len(extra)]:
                out[n] = rec[n]
            for e in extra:
                out[e[0]] = e[1]
            f.write(out.tobytes())


@pytest.mark.parametrize("fmt", ["binary_big_endian", "ascii", "binary_little_endian"])
def test_other_tools_layouts(tmp_path, fmt):
    g = random_gaussians(n=20, degree=1)
    names = list(ply_property_names(1))
    rng = np.random.default_rng(3)
    order = [names[i] for i in rng.permutation(len(names)) if names[i] not in ("nx", "ny", "nz")]
    p = tmp_path / "other.ply"
    _write_custom(p, g, order=order, fmt=fmt, dtype="f8", extra=[("red", 7)])
    h = read_gaussian_ply(p)
    assert h.sh_degree == 1
    assert_same(g, h)  # float64 copies of float32 values convert back exactly


def test_nan_rows_dropped_with_count(tmp_path):
    g = random_gaussians(n=10, degree=0)
    g.means[2, 0] = np.nan
    g.sh[5, 0, 1] = np.inf
    write_gaussian_ply(tmp_path / "g.ply", g)
    with pytest.warns(UserWarning, match="dropped 2 of 10 Gaussians with NaN or Inf"):
        h = read_gaussian_ply(tmp_path / "g.ply")
    keep = np.ones(10, bool)
    keep[[2, 5]] = False
    assert_same(g.subset(keep), h)


def test_missing_properties_named(tmp_path):
    p = tmp_path / "cloud.ply"
    p.write_bytes(b"ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nproperty float y\n"
                  b"property float z\nproperty uchar red\nproperty uchar green\nproperty uchar blue\n"
                  b"end_header\n0 0 0 255 0 0\n")
    with pytest.raises(PlyError, match=r"cloud.ply: not a 3D Gaussian Splatting PLY: missing properties "
                                       r"f_dc_0, f_dc_1, f_dc_2, opacity, scale_0.*plain point cloud"):
        read_gaussian_ply(p)
    g = random_gaussians(n=2, degree=0)
    names = [n for n in ply_property_names(0) if n != "rot_3"]
    _write_custom(tmp_path / "norot.ply", g, order=names)
    with pytest.raises(PlyError, match=r"missing properties rot_3\."):
        read_gaussian_ply(tmp_path / "norot.ply")


@pytest.mark.parametrize("content,msg", [
    (b"hello", "not a PLY file"),
    (b"ply\nformat binary_little_endian 1.0\nelement vertex 5\nproperty float x\n", "no 'end_header'"),
    (b"ply\nformat weird 1.0\nend_header\n", "unknown PLY format"),
    (b"ply\nformat binary_little_endian 1.0\nelement vertex 5\nproperty float x\nend_header\n\0\0",
     "file is truncated"),
])
def test_malformed_files(tmp_path, content, msg):
    p = tmp_path / "bad file é.ply"
    p.write_bytes(content)
    with pytest.raises(PlyError, match=msg) as info:
        read_gaussian_ply(p)
    assert "bad file é.ply" in str(info.value)


def test_missing_file(tmp_path):
    with pytest.raises(PlyError, match="does not exist"):
        read_gaussian_ply(tmp_path / "nope.ply")


def test_write_is_atomic(tmp_path, monkeypatch):
    """A write that fails after the data is on disk leaves the old file and no temporary behind."""
    g = random_gaussians(n=5, degree=0)
    write_gaussian_ply(tmp_path / "g.ply", g)
    before = (tmp_path / "g.ply").read_bytes()
    import recgs_addon.core.io.ply as plymod

    def failing_replace(src, dst):
        assert plymod.Path(src).stat().st_size > len(before)  # the new data was fully written
        raise OSError("disk full")

    monkeypatch.setattr(plymod.os, "replace", failing_replace)
    with pytest.raises(RecGSError, match="g.ply: could not write the PLY: disk full .the previous one is kept"):
        write_gaussian_ply(tmp_path / "g.ply", random_gaussians(n=7, degree=0))
    assert (tmp_path / "g.ply").read_bytes() == before
    assert [p.name for p in tmp_path.iterdir()] == ["g.ply"]


def test_no_warning_for_clean_file(tmp_path):
    write_gaussian_ply(tmp_path / "g.ply", random_gaussians())
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        read_gaussian_ply(tmp_path / "g.ply")


def test_duplicated_property_is_refused(tmp_path):
    p = tmp_path / "dup.ply"
    write_gaussian_ply(p, random_gaussians(n=3, degree=0))
    data = p.read_bytes()
    head, body = data.split(b"end_header\n", 1)
    head = head.replace(b"property float opacity\n", b"property float scale_0\n")   # same size, a name twice
    p.write_bytes(head + b"end_header\n" + body)
    with pytest.raises(PlyError, match="property 'scale_0' twice") as e:
        read_gaussian_ply(p)
    assert "dup.ply" in str(e.value)


def test_count_short_of_the_body_is_refused(tmp_path):
    """A header that declares fewer vertices than the body holds: the rest would be dropped
    without a word (or the body is not what the header says)."""
    p = tmp_path / "short.ply"
    write_gaussian_ply(p, random_gaussians(n=5, degree=0))
    p.write_bytes(p.read_bytes().replace(b"element vertex 5\n", b"element vertex 4\n"))
    with pytest.raises(PlyError, match=r"bytes follow the last element.*count \(4\)") as e:
        read_gaussian_ply(p)
    assert "short.ply" in str(e.value)


def test_all_rows_nan_is_an_error_not_an_empty_model(tmp_path):
    """Regression (outside trial): a PLY whose every row had NaN read as 0 Gaussians with a
    warning, and `info` called it fine; now it is an error naming the file."""
    g = random_gaussians(n=6, degree=0)
    g.means[:, 1] = np.nan
    write_gaussian_ply(tmp_path / "void.ply", g)
    with pytest.raises(PlyError, match="void.ply: all 6 Gaussians have NaN or Inf values"):
        read_gaussian_ply(tmp_path / "void.ply")


def test_a_folder_is_not_called_missing(tmp_path):
    (tmp_path / "model.ply").mkdir()
    with pytest.raises(PlyError, match="model.ply: is a folder, not a PLY file"):
        read_gaussian_ply(tmp_path / "model.ply")
