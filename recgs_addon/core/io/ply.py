"""PLY reading (any layout) and writing (the INRIA 3DGS layout) with numpy structured arrays.

Writing follows INRIA exactly: binary little-endian float32, properties
``x y z nx ny nz f_dc_0..2 f_rest_0..M-1 opacity scale_0..2 rot_0..3`` with normals zero and
``f_rest`` channel-major (all red coefficients 1..K-1, then green, then blue), as INRIA
stores ``features_rest.transpose(1, 2)``.

Reading accepts files from other tools: properties are found by name in any order, binary
little- or big-endian or ASCII, any numeric type; the SH degree comes from the ``f_rest``
count. Rows with NaN/Inf are dropped with a warning saying how many.
"""
from __future__ import annotations

import os
import warnings
from pathlib import Path

import numpy as np

from ..errors import PlyError
from .atomic import atomic_path
from ..model.gaussians import GaussianSet, num_sh_coeffs, sh_degree_from_coeffs

_TYPES = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1",
    "short": "i2", "int16": "i2", "ushort": "u2", "uint16": "u2",
    "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
    "float": "f4", "float32": "f4", "double": "f8", "float64": "f8",
}
_FORMATS = {"ascii": None, "binary_little_endian": "<", "binary_big_endian": ">"}
#: Properties a Gaussian PLY must have (f_rest_* is optional: degree 0).
REQUIRED = ["f_dc_0", "f_dc_1", "f_dc_2", "opacity", "scale_0", "scale_1", "scale_2",
            "rot_0", "rot_1", "rot_2", "rot_3"]


def _parse_header(path: Path, f):
    first = f.readline()
    if first.strip() != b"ply":
        raise PlyError(f"{path}: not a PLY file (it does not start with 'ply')")
    fmt, elements = None, []
    while True:
        line = f.readline()
        if not line:
            raise PlyError(f"{path}: PLY header has no 'end_header' line (file truncated?)")
        tok = line.decode("ascii", errors="replace").split()
        if not tok or tok[0] in ("comment", "obj_info"):
            continue
        if tok[0] == "end_header":
            break
        if tok[0] == "format":
            if len(tok) < 2 or tok[1] not in _FORMATS:
                raise PlyError(f"{path}: unknown PLY format {' '.join(tok[1:])!r}")
            fmt = tok[1]
        elif tok[0] == "element":
            if len(tok) != 3 or not tok[2].isdigit():
                raise PlyError(f"{path}: malformed PLY header line {line.strip()!r}")
            elements.append((tok[1], int(tok[2]), []))
        elif tok[0] == "property":
            if not elements:
                raise PlyError(f"{path}: PLY property before any element")
            if len(tok) > 1 and tok[1] == "list":
                if len(tok) != 5 or tok[2] not in _TYPES or tok[3] not in _TYPES:
                    raise PlyError(f"{path}: malformed PLY header line {line.strip()!r}")
                elements[-1][2].append((tok[4], "list", _TYPES[tok[2]], _TYPES[tok[3]]))
            else:
                if len(tok) != 3 or tok[1] not in _TYPES:
                    raise PlyError(f"{path}: unknown PLY property type in {line.strip()!r}")
                elements[-1][2].append((tok[2], _TYPES[tok[1]]))
            names = [p[0] for p in elements[-1][2]]
            if names.count(names[-1]) > 1:
                raise PlyError(f"{path}: element '{elements[-1][0]}' declares the property '{names[-1]}' twice")
        else:
            raise PlyError(f"{path}: unexpected PLY header line {line.strip()!r}")
    if fmt is None:
        raise PlyError(f"{path}: PLY header has no 'format' line")
    return fmt, elements


def read_ply_elements(path: str | os.PathLike, wanted: str = "vertex") -> dict[str, np.ndarray]:
    """Read a PLY file's elements without list properties as numpy structured arrays.

    Returns ``{name: array}`` for every element up to and including ``wanted``. Elements with
    list properties (faces) are only allowed after ``wanted`` (they are not read).
    """
    path = Path(path)
    if path.is_dir():
        raise PlyError(f"{path}: is a folder, not a PLY file")
    if not path.is_file():
        raise PlyError(f"{path}: file does not exist")
    out = {}
    with open(path, "rb") as f:
        fmt, elements = _parse_header(path, f)
        body_start = f.tell()
        if fmt == "ascii":
            text = f.read().decode("ascii", errors="replace").split("\n")
            line_no = 0
            for name, count, props in elements:
                if any(p[1] == "list" for p in props):
                    if name == wanted or wanted not in out:
                        raise PlyError(f"{path}: element '{name}' with list properties comes before "
                                       f"'{wanted}'; not supported")
                    break
                rows = [ln for ln in text[line_no:line_no + count]]
                line_no += count
                dtype = np.dtype([(p[0], p[1]) for p in props])
                try:
                    flat = np.array(" ".join(rows).split(), dtype=np.float64)
                    flat = flat.reshape(count, len(props))
                except ValueError as exc:
                    raise PlyError(f"{path}: ASCII PLY element '{name}' does not have {count} rows "
                                   f"of {len(props)} numbers (file truncated or malformed)") from exc
                arr = np.empty(count, dtype=dtype)
                for i, p in enumerate(props):
                    arr[p[0]] = flat[:, i]
                out[name] = arr
                if name == wanted:
                    break
        else:
            endian = _FORMATS[fmt]
            size = path.stat().st_size
            offset = body_start
            for name, count, props in elements:
                if any(p[1] == "list" for p in props):
                    if wanted not in out:
                        raise PlyError(f"{path}: element '{name}' with list properties comes before "
                                       f"'{wanted}'; not supported")
                    break
                dtype = np.dtype([(p[0], endian + p[1]) for p in props])
                need = dtype.itemsize * count
                if offset + need > size:
                    raise PlyError(f"{path}: file is truncated: element '{name}' needs {need} bytes "
                                   f"but only {size - offset} remain")
                arr = np.fromfile(f, dtype=dtype, count=count, offset=offset - f.tell()) if count else np.zeros(0, dtype)
                offset += need
                if name == wanted:
                    _check_byte_order(path, fmt, arr)
                out[name] = arr.astype(arr.dtype.newbyteorder("=")) if endian == ">" else arr
                if name == wanted:
                    break
            if elements and elements[-1][0] == wanted and offset != size:
                name, count, _ = elements[-1]
                raise PlyError(f"{path}: {size - offset} bytes follow the last element: the header's "
                               f"'{name}' count ({count}) is short of the file's body")
    if wanted not in out:
        raise PlyError(f"{path}: PLY file has no '{wanted}' element")
    return out


def _f_rest_names(k_rest: int) -> list[str]:
    return [f"f_rest_{i}" for i in range(3 * k_rest)]


def ply_property_names(sh_degree: int) -> list[str]:
    """Property names in the INRIA order for a given SH degree."""
    k_rest = num_sh_coeffs(sh_degree) - 1
    return (["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"] + _f_rest_names(k_rest)
            + ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"])


def gaussians_to_records(g: GaussianSet) -> np.ndarray:
    """The INRIA vertex table (structured float32 array) for a Gaussian set."""
    names = ply_property_names(g.sh_degree)
    rec = np.zeros(len(g), dtype=np.dtype([(n, "<f4") for n in names]))
    for i, a in enumerate("xyz"):
        rec[a] = g.means[:, i]
    for c in range(3):
        rec[f"f_dc_{c}"] = g.sh[:, 0, c]
    k_rest = g.sh.shape[1] - 1
    rest = g.sh[:, 1:, :].transpose(0, 2, 1).reshape(len(g), -1)  # channel-major, as INRIA
    for i in range(3 * k_rest):
        rec[f"f_rest_{i}"] = rest[:, i]
    rec["opacity"] = g.logit_opacities
    for i in range(3):
        rec[f"scale_{i}"] = g.log_scales[:, i]
    for i in range(4):
        rec[f"rot_{i}"] = g.quats[:, i]
    return rec


def records_to_gaussians(rec: np.ndarray, source: str = "<records>", drop_nonfinite: bool = True):
    """Gaussian set from a table with INRIA property names. Returns (GaussianSet, n_dropped)."""
    names = set(rec.dtype.names or ())
    missing = [n for n in ["x", "y", "z"] + REQUIRED if n not in names]
    if missing:
        hint = ""
        if {"red", "green", "blue"} & names or not (set(REQUIRED) & names):
            hint = (" It looks like a plain point cloud or mesh, not a 3D Gaussian Splatting file;"
                    " import a COLMAP model instead to make Gaussians from points.")
        raise PlyError(f"{source}: not a 3D Gaussian Splatting PLY: missing properties "
                       f"{', '.join(missing)}.{hint}")
    n_rest = 0
    while f"f_rest_{n_rest}" in names:
        n_rest += 1
    if n_rest % 3:
        raise PlyError(f"{source}: {n_rest} f_rest properties is not a multiple of 3")
    try:
        degree = sh_degree_from_coeffs(1 + n_rest // 3)
    except ValueError as exc:
        raise PlyError(f"{source}: {n_rest} f_rest properties do not match an SH degree 0..3") from exc
    n = len(rec)
    col = lambda name: np.asarray(rec[name], dtype=np.float32)  # noqa: E731
    means = np.stack([col("x"), col("y"), col("z")], 1)
    sh = np.zeros((n, num_sh_coeffs(degree), 3), np.float32)
    for c in range(3):
        sh[:, 0, c] = col(f"f_dc_{c}")
    if n_rest:
        rest = np.stack([col(f"f_rest_{i}") for i in range(n_rest)], 1)
        sh[:, 1:, :] = rest.reshape(n, 3, n_rest // 3).transpose(0, 2, 1)
    g = GaussianSet(means, np.stack([col(f"scale_{i}") for i in range(3)], 1),
                    np.stack([col(f"rot_{i}") for i in range(4)], 1), col("opacity"), sh)
    dropped = 0
    if drop_nonfinite:
        ok = g.finite_mask()
        dropped = int(n - ok.sum())
        if dropped and dropped == n:
            raise PlyError(f"{source}: all {n} Gaussians have NaN or Inf values; there is nothing to import")
        if dropped:
            warnings.warn(f"{source}: dropped {dropped} of {n} Gaussians with NaN or Inf values", stacklevel=2)
            g = g.subset(ok)
    return g, dropped


def _plausible_share(values: np.ndarray) -> float:
    """Share of float values that look like data: 0, or finite with 1e-30 < |v| < 1e10 (bytes
    read in the wrong order give huge, NaN or denormal numbers)."""
    if values.size == 0:
        return 1.0
    with np.errstate(invalid="ignore", over="ignore"):
        a = np.abs(values.astype(np.float64))
        return float(np.mean((a == 0) | (np.isfinite(a) & (a > 1e-30) & (a < 1e10))))


def _check_byte_order(path: Path, fmt: str, arr: np.ndarray) -> None:
    """A header whose byte order is wrong for its body reads as huge or NaN numbers: refuse it
    (naming the order the body reads well in) rather than import garbage."""
    floats = [n for n in arr.dtype.names if arr.dtype[n].kind == "f" and arr.dtype[n].itemsize > 1]
    if not floats or len(arr) == 0:
        return
    sample = arr[: min(len(arr), 4096)]
    declared = np.concatenate([sample[n].astype(sample[n].dtype.newbyteorder("=")).ravel() for n in floats])
    swapped = np.concatenate([np.ascontiguousarray(sample[n]).view(sample[n].dtype.newbyteorder()).astype(
        sample[n].dtype.newbyteorder("=")).ravel() for n in floats])   # the same bytes, the other order
    if _plausible_share(declared) < 0.9 and _plausible_share(swapped) > 0.99:
        other = "binary_big_endian" if fmt == "binary_little_endian" else "binary_little_endian"
        raise PlyError(f"{path}: the header says '{fmt}' but the data reads as '{other}' "
                       "(huge or NaN values the declared way, plausible the other): the header is wrong")


def read_gaussian_ply(path: str | os.PathLike) -> GaussianSet:
    """Read a 3DGS PLY (INRIA or another tool's). Rows with NaN/Inf are dropped (warning)."""
    path = Path(path)
    vertex = read_ply_elements(path, "vertex")["vertex"]
    return records_to_gaussians(vertex, str(path))[0]


def write_gaussian_ply(path: str | os.PathLike, g: GaussianSet) -> None:
    """Write the INRIA layout. The file appears atomically (temporary name, then rename)."""
    path = Path(path)
    rec = gaussians_to_records(g)
    header = ["ply", "format binary_little_endian 1.0", f"element vertex {len(g)}"]
    header += [f"property float {n}" for n in rec.dtype.names] + ["end_header"]
    with atomic_path(path, "PLY") as tmp:
        with open(tmp, "wb") as f:
            f.write(("\n".join(header) + "\n").encode("ascii"))
            f.write(rec.tobytes())
