"""The commands of ``python -m recgs_addon COMMAND ...``: ``cli.py`` parses the command line and
calls them here. ``scene`` holds ``import`` and ``info``, ``train`` and ``render`` their own, and
``capture`` holds ``sfm`` and ``video``; each module's ``add_*_arguments`` declares its options.

Commands
--------
``import SCENE_DIR --out OUT_DIR``
    Imports a COLMAP survey into a new .blend (cameras + initial Gaussians) with the add-on's
    own operators (needs the ``bpy`` module), exports the Gaussians as a 3DGS PLY, and writes
    a report of the time taken and of the camera conversion error (sparse points projected
    through the Blender cameras versus the COLMAP cameras).
``info FILE.ply``
    Prints what a Gaussian PLY holds (count, SH degree, bounds). No Blender needed.
``train SCENE_DIR --out OUT_DIR [options]``
    Trains 3D Gaussian Splatting (see ``train``); progress as JSON lines.
``render MODEL.ply SCENE_DIR --out DIR [--names a.png,b.png]``
    Renders a model from the survey's cameras (PNG and float EXR) and reports PSNR.
``sfm PHOTO_DIR --out SCENE_DIR [--link] [--overwrite]``
    Structure from motion with pycolmap (``recgs_addon.core.capture.sfm``): copies (or links) the
    photos to SCENE_DIR/images and writes the COLMAP model to SCENE_DIR/sparse/0, ready for
    ``import`` and ``train``. Progress as JSON lines, like ``train``.
``video CLIP --out SURVEY [--frames N | --every S] [--max-side PX] [--format jpg|png] [--overwrite]``
    A video clip into a survey (``recgs_addon.core.capture.video``): the sharpest frame of each
    window of time, near-duplicates and dark frames left out, written to SURVEY/images with
    their time stamps in SURVEY/frames.json; then SfM with sequential matching and one shared
    camera into SURVEY/sparse/0. Progress as JSON lines (phases ``frames``, ``features``,
    ``matching``, ``mapping``); SIGTERM/SIGINT stop it cleanly, and running it again on the
    same SURVEY continues where it stopped.

JSON-lines events and the error path (an ``error`` event, ``error: ...`` on stderr, exit
status 1) are ``events.emit`` and ``events.fail``, shared by every command.
"""
