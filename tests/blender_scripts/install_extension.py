"""Run in a fresh Blender session (bpy module): install the extension zip given as argv[1],
then disable and enable it twice, and check the operators come and go. Exits non-zero on error."""
import sys

import bpy  # noqa: I001  (bpy first: it makes Blender's own modules importable)
import addon_utils

zip_path = sys.argv[1]
bpy.ops.extensions.package_install_files(filepath=zip_path, repo="user_default", enable_on_install=True)
module = "bl_ext.user_default.recgs"
assert module in bpy.context.preferences.addons, sorted(bpy.context.preferences.addons.keys())
assert hasattr(bpy.types, "RECGS_OT_import_colmap"), "operators not registered after install"
for _ in range(2):
    addon_utils.disable(module, default_set=True)
    assert not hasattr(bpy.types, "RECGS_OT_import_colmap"), "operators left after disable"
    addon_utils.enable(module, default_set=True)
    assert hasattr(bpy.types, "RECGS_OT_import_colmap"), "operators missing after enable"
    assert hasattr(bpy.types, "RECGS_OT_export_ply") and hasattr(bpy.types, "RECGS_OT_import_ply")
if len(sys.argv) > 2:  # a COLMAP scene: import it through the installed package
    bpy.ops.recgs.import_colmap(directory=sys.argv[2])
    obj = bpy.context.active_object
    assert obj is not None and len(obj.data.vertices) > 0 and "f_dc_0" in obj.data.attributes
    installed = [m for m in sys.modules if m.startswith(module + ".recgs_addon.core")]
    assert installed, "core was not loaded from the installed extension"
    # background jobs run the installed package (python -m recgs_addon, PYTHONPATH set)
    import os
    import subprocess
    import tempfile

    jobs = sys.modules[module + ".recgs_addon.blender.jobs"]
    ext_dir = os.path.dirname(sys.modules[module].__file__)
    assert str(jobs.PACKAGE_PARENT) == ext_dir, (jobs.PACKAGE_PARENT, ext_dir)
    with tempfile.TemporaryDirectory() as tmp:
        ply = os.path.join(tmp, "g.ply")
        bpy.ops.recgs.export_ply(filepath=ply)
        job = jobs.Job("info", jobs.command("info", ply), cwd=tmp)
        assert job.wait(120) == 0, list(job.stderr_tail)
        where = subprocess.run([sys.executable, "-c", "import recgs_addon; print(recgs_addon.__file__)"],
                               env=jobs.job_env(), cwd=tmp, capture_output=True, text=True)
        assert where.stdout.strip().startswith(ext_dir), (where.stdout, where.stderr)
addon_utils.disable(module, default_set=True)
print("EXTENSION-OK")
