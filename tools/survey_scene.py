"""The survey generator's Blender scene: meshes (terrain, rocks, the man-made structure), lights,
Cycles and compositor settings, the camera, rendering to linear EXRs, the scene's triangles, and
:func:`build_scene`, which puts them together.

bpy is imported lazily, so that importing this module needs no Blender.
"""
from __future__ import annotations

import contextlib
import math
import os
import sys
from pathlib import Path

import numpy as np

from survey_geometry import Heightfield   # (puts the repository on sys.path for recgs_addon)
from survey_materials import (_bpy, build_caustic_group, concrete_material, rock_material, rust_material,
                              sand_material, tile_material)

from recgs_addon.core.model.cameras import Camera, blender_matrix_from_pose


def log(msg: str) -> None:
    """Progress line (flushed, so it shows up promptly inside Blender too)."""
    print(f"[make_survey] {msg}", flush=True)


# ---------------------------------------------------------------------------------------------
# Meshes: terrain, rocks, the man-made structure
# ---------------------------------------------------------------------------------------------

def mesh_object(name: str, verts: np.ndarray, faces: np.ndarray, material, smooth: bool = False,
                matrix=None):
    """Create and link a mesh object from numpy vertices (V, 3) and faces (F, k) (foreach_set, no loops)."""
    bpy = _bpy()
    me = bpy.data.meshes.new(name)
    nv, (nf, k) = len(verts), faces.shape
    me.vertices.add(nv)
    me.vertices.foreach_set("co", np.asarray(verts, np.float32).ravel())
    me.loops.add(nf * k)
    me.loops.foreach_set("vertex_index", np.asarray(faces, np.int32).ravel())
    me.polygons.add(nf)
    me.polygons.foreach_set("loop_start", np.arange(0, nf * k, k, dtype=np.int32))
    me.polygons.foreach_set("use_smooth", np.full(nf, smooth, bool))
    me.update(calc_edges=True)
    me.validate()
    me.materials.append(material)
    ob = bpy.data.objects.new(name, me)
    if matrix is not None:
        import mathutils
        ob.matrix_world = mathutils.Matrix(np.asarray(matrix).tolist())
    bpy.context.scene.collection.objects.link(ob)
    return ob


def _bmesh_arrays(make) -> tuple[np.ndarray, np.ndarray]:
    """Vertices and triangle faces of a bmesh primitive built by ``make(bm)``."""
    import bmesh
    bpy = _bpy()
    bm = bmesh.new()
    make(bm)
    bmesh.ops.triangulate(bm, faces=bm.faces[:])
    me = bpy.data.meshes.new("_primitive")
    bm.to_mesh(me)
    bm.free()
    verts = np.empty(len(me.vertices) * 3, np.float32)
    me.vertices.foreach_get("co", verts)
    faces = np.empty(len(me.polygons) * 3, np.int32)
    me.polygons.foreach_get("vertices", faces)
    bpy.data.meshes.remove(me)
    return verts.reshape(-1, 3).astype(np.float64), faces.reshape(-1, 3)


def make_terrain(hf: Heightfield, size: tuple[float, float], spacing: float, material):
    nx, ny = int(round(size[0] / spacing)) + 1, int(round(size[1] / spacing)) + 1
    x = np.linspace(-size[0] / 2, size[0] / 2, nx)
    y = np.linspace(-size[1] / 2, size[1] / 2, ny)
    X, Y = np.meshgrid(x, y)
    verts = np.stack([X, Y, hf(X, Y)], -1).reshape(-1, 3)
    i = np.arange(ny - 1)[:, None] * nx + np.arange(nx - 1)[None, :]
    faces = np.stack([i, i + 1, i + nx + 1, i + nx], -1).reshape(-1, 4)
    return mesh_object("Terrain", verts, faces, material, smooth=True)


def make_rock(name: str, rng: np.random.Generator, center_xy, radius: float, hf: Heightfield, material):
    import bmesh
    verts, faces = _bmesh_arrays(lambda bm: bmesh.ops.create_icosphere(bm, subdivisions=4, radius=1.0))
    n = verts / np.linalg.norm(verts, axis=1, keepdims=True)
    m = 16
    d = rng.normal(size=(m, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    freq = rng.uniform(1.5, 12.0, m)
    r = 1 + ((0.2 / freq ** 0.8) * np.sin(freq * (n @ d.T) * 2 + rng.uniform(0, 6.3, m))).sum(-1)
    planes = rng.normal(size=(4, 3))
    planes /= np.linalg.norm(planes, axis=1, keepdims=True)
    r = np.minimum(r, (0.85 / np.maximum(n @ planes.T, 1e-3)).min(-1))   # a few flat fracture faces
    scale = radius * np.array([1.0, rng.uniform(0.6, 1.0), rng.uniform(0.45, 0.75)])
    v = n * r[:, None] * scale
    ang = rng.uniform(0, 2 * np.pi)
    Rz = np.array([[math.cos(ang), -math.sin(ang), 0], [math.sin(ang), math.cos(ang), 0], [0, 0, 1]])
    ground = float(hf.mean_around(center_xy[0], center_xy[1], radius * 0.7))
    M = np.eye(4)
    M[:3, :3] = Rz
    M[:3, 3] = (center_xy[0], center_xy[1], ground + 0.15 * scale[2])
    return mesh_object(name, v, faces, material, smooth=True, matrix=M)


def make_structure(rng: np.random.Generator, center_xy, hf: Heightfield, mat_rust, mat_concrete):
    """Man-made debris: a rusty pipe segment resting next to a concrete block with a painted stripe.

    Returns (objects, discs (K, 3) covering the footprint as centre x, y and radius).
    """
    import bmesh
    ang = rng.uniform(0, np.pi)
    cz = math.cos(ang)
    sz = math.sin(ang)
    # pipe: cylinder along its local z, laid along direction ang
    radius, length = 0.11, 2.0
    verts, faces = _bmesh_arrays(lambda bm: bmesh.ops.create_cone(
        bm, cap_ends=True, segments=32, radius1=radius, radius2=radius, depth=length))
    dirv = np.array([cz, sz, 0.0])
    Rp = np.stack([np.array([-sz, cz, 0.0]), np.array([0.0, 0.0, 1.0]), dirv], 1)   # local z -> dirv
    along = np.linspace(-length / 2, length / 2, 9)
    px = center_xy[0] + along * cz + 0.45 * -sz
    py = center_xy[1] + along * sz + 0.45 * cz
    M = np.eye(4)
    M[:3, :3] = Rp
    M[:3, 3] = (px.mean(), py.mean(), float(hf(px, py).mean()) + 0.5 * radius)
    pipe = mesh_object("Pipe", verts, faces, mat_rust, smooth=True, matrix=M)
    # block, rotated a bit relative to the pipe
    bx, by, bz = 0.8, 0.55, 0.4
    verts, faces = _bmesh_arrays(lambda bm: bmesh.ops.create_cube(bm, size=1.0))
    verts = verts * np.array([bx, by, bz])
    a2 = ang + rng.uniform(-0.4, 0.4)
    Rb = np.array([[math.cos(a2), -math.sin(a2), 0], [math.sin(a2), math.cos(a2), 0], [0, 0, 1]])
    cx, cy = center_xy[0] - 0.35 * -sz, center_xy[1] - 0.35 * cz
    ground = float(hf.mean_around(cx, cy, 0.4))
    M = np.eye(4)
    M[:3, :3] = Rb
    M[:3, 3] = (cx, cy, ground + bz / 2 - 0.1)
    block = mesh_object("ConcreteBlock", verts, faces, mat_concrete, smooth=False, matrix=M)
    # footprint as discs (centre x, y, radius) so that rocks can be kept clear of it
    discs = np.concatenate([np.stack([px, py, np.full_like(px, radius + 0.05)], 1),
                            [[cx, cy, 0.5 * math.hypot(bx, by)]]])
    return [pipe, block], discs


# ---------------------------------------------------------------------------------------------
# Lights, render settings, camera, compositor
# ---------------------------------------------------------------------------------------------

def setup_lighting(light_dir: np.ndarray, args) -> None:
    """Sun along ``light_dir`` plus a blue-green ambient world (no volumetrics)."""
    bpy = _bpy()
    import mathutils
    sun = bpy.data.lights.new("Sun", "SUN")
    sun.energy = args.sun_strength
    sun.color = (0.85, 0.97, 1.0)
    sun.angle = math.radians(2.0)
    ob = bpy.data.objects.new("Sun", sun)
    ob.rotation_euler = mathutils.Vector((-light_dir).tolist()).to_track_quat("Z", "Y").to_euler()
    bpy.context.scene.collection.objects.link(ob)
    world = bpy.data.worlds.new("Water")
    nt = world.node_tree
    bg = nt.nodes.get("Background") or nt.nodes.new("ShaderNodeBackground")
    bg.inputs["Color"].default_value = (0.06, 0.24, 0.27, 1.0)
    bg.inputs["Strength"].default_value = args.ambient_strength
    out = nt.nodes.get("World Output") or nt.nodes.new("ShaderNodeOutputWorld")
    if not bg.outputs[0].links:
        nt.links.new(bg.outputs[0], out.inputs["Surface"])
    bpy.context.scene.world = world


def configure_render(args) -> bool:
    """Cycles on the CPU, few samples + OIDN when the build has it, deterministic seed, colour and
    depth written by the compositor as float EXRs. Returns whether denoising is on."""
    bpy = _bpy()
    scene = bpy.context.scene
    scene.render.engine = "CYCLES"
    cy = scene.cycles
    cy.device = "CPU"
    cy.samples = args.samples
    cy.use_adaptive_sampling = False
    cy.seed = args.seed
    cy.use_animated_seed = False
    cy.max_bounces = args.bounces
    cy.diffuse_bounces = args.bounces
    cy.glossy_bounces = min(1, args.bounces)
    cy.transmission_bounces = 0
    cy.volume_bounces = 0
    cy.transparent_max_bounces = 2
    cy.caustics_reflective = False
    cy.caustics_refractive = False
    denoise = False
    if args.denoise:
        try:
            import _cycles
            if getattr(_cycles, "with_openimagedenoise", False):
                cy.use_denoising = True
                cy.denoiser = "OPENIMAGEDENOISE"
                cy.denoising_prefilter = args.denoise_prefilter
                cy.denoising_quality = args.denoise_quality
                denoise = True
        except Exception as exc:  # pragma: no cover - depends on the Blender build
            log(f"denoiser unavailable ({exc}); rendering without")
    if not denoise:
        cy.use_denoising = False
    r = scene.render
    r.resolution_x, r.resolution_y, r.resolution_percentage = args.width, args.height, 100
    r.pixel_aspect_x = r.pixel_aspect_y = 1.0
    r.threads_mode = "FIXED"
    r.threads = max(1, args.threads)
    r.use_persistent_data = True
    r.film_transparent = False
    r.dither_intensity = 0.0
    scene.view_settings.view_transform = "Standard"
    scene.view_settings.look = "None"
    scene.view_settings.exposure = 0.0
    scene.view_settings.gamma = 1.0
    vl = scene.view_layers[0]
    vl.use_pass_combined = True
    vl.use_pass_z = True
    setup_compositor_outputs(scene)
    return denoise


def add_camera(cam0: Camera):
    """Blender camera with PINHOLE intrinsics equal to ``cam0`` (sensor fit horizontal, no shift)."""
    bpy = _bpy()
    cd = bpy.data.cameras.new("SurveyCam")
    cd.sensor_fit = "HORIZONTAL"
    cd.sensor_width = 36.0
    cd.lens_unit = "MILLIMETERS"
    cd.lens = cam0.fx * cd.sensor_width / cam0.width
    cd.shift_x = cd.shift_y = 0.0
    cd.clip_start, cd.clip_end = 0.05, 200.0
    ob = bpy.data.objects.new("SurveyCam", cd)
    bpy.context.scene.collection.objects.link(ob)
    bpy.context.scene.camera = ob
    return ob


def set_camera_pose(ob, cam: Camera) -> None:
    import mathutils
    ob.matrix_world = mathutils.Matrix(blender_matrix_from_pose(cam.R, cam.t).tolist())


def setup_compositor_outputs(scene) -> None:
    """Compositor writing the denoised linear colour and the z-depth pass as float EXRs.

    (Blender 5.0 does not put the depth pass into a render written with ``write_still`` and drops
    non-colour inputs of a multilayer File Output node, so two single-layer outputs are used.)
    """
    bpy = _bpy()
    ng = bpy.data.node_groups.new("SurveyOutputs", "CompositorNodeTree")
    scene.compositing_node_group = ng
    scene.render.use_compositing = True
    rl = ng.nodes.new("CompositorNodeRLayers")
    rl.scene = scene
    for item, sock, mode in (("rgb", "Image", "RGB"), ("depth", "Depth", "BW")):
        fo = ng.nodes.new("CompositorNodeOutputFile")
        fo.name = f"out_{item}"
        fo.format.media_type = "IMAGE"
        fo.format.file_format = "OPEN_EXR"
        fo.format.color_depth = "32"
        fo.format.color_mode = mode
        fo.format.exr_codec = "ZIP"
        fo.save_as_render = False                      # keep scene-linear values
        fo.file_output_items.new("RGBA" if mode == "RGB" else "FLOAT", item)
        ng.links.new(rl.outputs[sock], fo.inputs[item])


# ---------------------------------------------------------------------------------------------
# Rendering and the scene's triangles
# ---------------------------------------------------------------------------------------------

def _read_exr(path: Path) -> np.ndarray:
    import OpenImageIO as oiio
    inp = oiio.ImageInput.open(str(path))
    if inp is None:
        raise RuntimeError(f"cannot open {path}: {oiio.geterror()}")
    data = inp.read_image(0, 0, 0, inp.spec().nchannels, "float")
    inp.close()
    return np.asarray(data, np.float32)


@contextlib.contextmanager
def _quiet_stdout():
    """Silence Blender's per-file 'Saved: ...' lines (C-level stdout) during a render."""
    sys.stdout.flush()
    try:
        fd = sys.stdout.fileno()
    except (AttributeError, OSError, ValueError):
        yield
        return
    saved = os.dup(fd)
    devnull = os.open(os.devnull, os.O_WRONLY)
    try:
        os.dup2(devnull, fd)
        yield
    finally:
        os.dup2(saved, fd)
        os.close(saved)
        os.close(devnull)


def render_exr(folder: Path, prefix: str) -> tuple[np.ndarray, np.ndarray]:
    """Render the current camera; return (linear RGB (H, W, 3), planar z depth (H, W)), row 0 = top."""
    bpy = _bpy()
    ng = bpy.context.scene.compositing_node_group
    for item in ("rgb", "depth"):
        fo = ng.nodes[f"out_{item}"]
        fo.directory = str(folder) + "/"
        fo.file_name = prefix
    with _quiet_stdout():
        bpy.ops.render.render(write_still=False)
    rgb = _read_exr(folder / f"{prefix}rgb.exr")[..., :3]
    depth = _read_exr(folder / f"{prefix}depth.exr")[..., 0]
    return rgb, depth



def scene_triangles(objects) -> tuple[np.ndarray, np.ndarray]:
    """World-space triangles (T, 3, 3) of the evaluated objects and the object index of each."""
    bpy = _bpy()
    dg = bpy.context.evaluated_depsgraph_get()
    tris, owner = [], []
    for k, ob in enumerate(objects):
        ev = ob.evaluated_get(dg)
        me = ev.to_mesh()
        me.calc_loop_triangles()
        co = np.empty(len(me.vertices) * 3, np.float32)
        me.vertices.foreach_get("co", co)
        tri = np.empty(len(me.loop_triangles) * 3, np.int32)
        me.loop_triangles.foreach_get("vertices", tri)
        M = np.array(ev.matrix_world, dtype=np.float64)
        co = co.reshape(-1, 3).astype(np.float64) @ M[:3, :3].T + M[:3, 3]
        tris.append(co[tri.reshape(-1, 3)])
        owner.append(np.full(len(tri) // 3, k))
        ev.to_mesh_clear()
    return np.concatenate(tris), np.concatenate(owner)


# ---------------------------------------------------------------------------------------------
# The whole scene
# ---------------------------------------------------------------------------------------------

def build_scene(args, hf: Heightfield, cams: list[Camera], terrain_size, light_dir):
    """All Blender data: materials, terrain, rocks, structure, lights, caustic rig. Returns (rig, objects, info)."""
    bpy = _bpy()
    rng = np.random.default_rng([args.seed, 3])
    rig = build_caustic_group(light_dir, args.caustic_scale)
    floor = getattr(args, "floor", "sand")
    gloss = getattr(args, "gloss", 0.0)
    if floor == "sand":
        ground = sand_material(rig, args.seed, gloss)
    else:   # tiles of 0.3 m with thin grout, or a grid of bars 0.3 m apart
        ground = tile_material(rig, 0.3, 0.06 if floor == "tiles" else 0.4, gloss)
    terrain = make_terrain(hf, terrain_size, 0.05, ground)
    centres = np.array([c.center[:2] for c in cams])
    half = 0.35 * 2 * args.altitude * math.tan(math.radians(args.hfov) / 2)   # ~ 0.7 x half footprint
    lo, hi = centres.min(0) - half, centres.max(0) + half                     # area seen by the survey
    struct_xy = lo + (hi - lo) * rng.uniform(0.35, 0.65, 2)
    structure, discs = make_structure(rng, struct_xy, hf, rust_material(rig), concrete_material(rig))
    palettes = [  # (three colours, encrusting growth colour)
        (((0.04, 0.04, 0.04), (0.11, 0.10, 0.09), (0.24, 0.22, 0.19)), (0.60, 0.25, 0.40)),  # basalt
        (((0.25, 0.12, 0.05), (0.45, 0.25, 0.12), (0.62, 0.44, 0.28)), (0.15, 0.30, 0.10)),  # sandstone
        (((0.14, 0.14, 0.14), (0.34, 0.32, 0.29), (0.56, 0.53, 0.48)), (0.45, 0.20, 0.50)),  # granite
        (((0.12, 0.14, 0.06), (0.25, 0.30, 0.12), (0.40, 0.42, 0.25)), (0.80, 0.45, 0.10)),  # mossy
    ]
    rock_mats = [rock_material(rig, f"Rock{i}", pal, crust) for i, (pal, crust) in enumerate(palettes)]
    rocks, placed = [], discs
    for i in range(args.rocks):
        radius = rng.uniform(0.2, 0.5)
        for _ in range(200):  # rejection sampling: keep rocks clear of each other and the structure
            xy = lo + (hi - lo) * rng.uniform(0, 1, 2)
            if np.all(np.hypot(*(placed[:, :2] - xy).T) > placed[:, 2] + radius + 0.2):
                break
        else:
            continue  # no room left (tiny survey): fewer rocks
        placed = np.concatenate([placed, [[xy[0], xy[1], radius]]])
        rocks.append(make_rock(f"Rock_{i:02d}", rng, xy, radius, hf, rock_mats[i % len(rock_mats)]))
    setup_lighting(light_dir, args)
    objects = [terrain] + structure + rocks
    info = [{"name": ob.name, "location": list(ob.matrix_world.translation),
             "material": ob.data.materials[0].name} for ob in objects]
    bpy.context.view_layer.update()
    return rig, objects, info
