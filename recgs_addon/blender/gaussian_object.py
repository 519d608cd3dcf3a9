"""Gaussians on a Blender mesh: POINT-domain float attributes with the INRIA PLY names.

The mesh has one vertex per Gaussian (its position is the mean, in object space) and the
attributes ``f_dc_0..2``, ``f_rest_*``, ``opacity``, ``scale_0..2``, ``rot_0..3``, so Blender's
own PLY importer, other 3DGS add-ons and ours agree. Data moves with ``foreach_get`` /
``foreach_set`` and numpy only. Edits (deleting or moving vertices in Edit Mode) carry the
attributes along, so reading the object back always gives the artist's current Gaussians.
"""
from __future__ import annotations

from contextlib import contextmanager

import bpy
import numpy as np

from ..core.model.gaussians import GaussianSet, num_sh_coeffs
from ..core.io.ply import gaussians_to_records, ply_property_names
from ..core.io.transform import transform_gaussians

#: Custom property marking an object as a Gaussian object.
FLAG = "recgs_gaussians"
_SKIP = ("x", "y", "z", "nx", "ny", "nz")


def attribute_names(sh_degree: int) -> list[str]:
    return [n for n in ply_property_names(sh_degree) if n not in _SKIP]


def is_gaussian_object(obj) -> bool:
    return (obj is not None and obj.type == "MESH"
            and all(n in obj.data.attributes for n in attribute_names(0)))


def sh_degree_of(mesh) -> int:
    n_rest = 0
    while f"f_rest_{n_rest}" in mesh.attributes:
        n_rest += 1
    for d in range(3, -1, -1):
        if n_rest >= 3 * (num_sh_coeffs(d) - 1):
            return d
    return 0


def write_mesh(mesh, g: GaussianSet) -> None:
    """Replace the mesh's geometry and attributes with the Gaussian set ``g``."""
    mesh.clear_geometry()
    for name in [a.name for a in mesh.attributes if a.name.startswith(("f_dc_", "f_rest_", "scale_", "rot_"))
                 or a.name == "opacity"]:
        mesh.attributes.remove(mesh.attributes[name])
    mesh.vertices.add(len(g))
    mesh.attributes["position"].data.foreach_set("vector", g.means.astype(np.float32).ravel())
    rec = gaussians_to_records(g)
    for name in attribute_names(g.sh_degree):
        attr = mesh.attributes.new(name, "FLOAT", "POINT")
        attr.data.foreach_set("value", np.ascontiguousarray(rec[name], dtype=np.float32))
    mesh.update()


def read_mesh(mesh) -> GaussianSet:
    """The Gaussian set stored on a mesh (object space)."""
    from ..core.io.ply import records_to_gaussians

    n = len(mesh.vertices)
    degree = sh_degree_of(mesh)
    names = attribute_names(degree)
    missing = [x for x in names if x not in mesh.attributes]
    if missing:
        raise ValueError(f"mesh '{mesh.name}' is missing Gaussian attributes {', '.join(missing)}")
    rec = np.zeros(n, dtype=np.dtype([(x, "<f4") for x in ["x", "y", "z"] + names]))
    pos = np.empty(3 * n, np.float32)
    mesh.attributes["position"].data.foreach_get("vector", pos)
    pos = pos.reshape(n, 3)
    rec["x"], rec["y"], rec["z"] = pos[:, 0], pos[:, 1], pos[:, 2]
    buf = np.empty(n, np.float32)
    for x in names:
        attr = mesh.attributes[x]
        if attr.domain != "POINT" or attr.data_type != "FLOAT":
            raise ValueError(f"mesh '{mesh.name}': attribute {x} must be a FLOAT on points")
        attr.data.foreach_get("value", buf)
        rec[x] = buf
    return records_to_gaussians(rec, f"object mesh '{mesh.name}'", drop_nonfinite=False)[0]


def create_gaussian_object(name: str, g: GaussianSet, collection) -> "bpy.types.Object":
    """A new mesh object holding ``g``, linked to ``collection``."""
    mesh = bpy.data.meshes.new(name)
    write_mesh(mesh, g)
    obj = bpy.data.objects.new(name, mesh)
    obj[FLAG] = True
    collection.objects.link(obj)
    return obj


def gaussians_from_object(obj, world: bool = True) -> GaussianSet:
    """The object's Gaussians; with ``world`` the object transform is baked in.

    Raises RecGSError for a transform that cannot be baked (non-uniform scale, mirror, shear).
    """
    g = read_mesh(obj.data)
    if not world:
        return g
    m = np.array(obj.matrix_world, dtype=np.float64)
    if np.array_equal(m, np.eye(4)):
        return g
    return transform_gaussians(g, m)


@contextmanager
def edits_flushed(obj):
    """Make Edit Mode changes readable: mesh attributes cannot be read in Edit Mode, so step
    to Object Mode (which writes the edit mesh back) and return to Edit Mode afterwards."""
    if obj.mode != "EDIT":
        yield
        return
    bpy.ops.object.mode_set(mode="OBJECT")
    try:
        yield
    finally:
        bpy.ops.object.mode_set(mode="EDIT")
