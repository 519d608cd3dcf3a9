"""Structure from motion with pycolmap: SIFT features, exhaustive matching, incremental mapping.

Used by ``python -m recgs_addon sfm`` (the add-on's *Reconstruct from Photos*) and by
``tools/make_survey.py --sfm``. The settings are COLMAP's defaults except where small,
low-contrast underwater photos need otherwise (see :class:`SfmOptions`). Exhaustive matching
is quadratic in the number of photos: fine for surveys of up to a few hundred images.
"""
from __future__ import annotations

import shutil
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Optional

from ..errors import SceneError

#: File endings taken as photos (case-insensitive).
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".tif", ".tiff", ".bmp")


@dataclass
class SfmOptions:
    """Settings of one SfM run (COLMAP's defaults unless noted)."""

    #: One shared camera for all photos (one physical camera on the survey vehicle).
    camera_model: str = "SIMPLE_RADIAL"
    threads: int = 2
    #: SIFT peak threshold (COLMAP: 0.0067); lower finds features on low-contrast seafloor.
    peak_threshold: float = 0.004
    #: Inliers needed for the first image pair (COLMAP: 100) and to register a new image
    #: (COLMAP: 30): small (~256 px) photos with caustics have fewer matches.
    init_min_num_inliers: int = 30
    abs_pose_min_num_inliers: int = 15
    #: Smallest model kept (COLMAP: 10 images).
    min_model_size: int = 3
    seed: int = 0


@dataclass
class SfmResult:
    """What :func:`reconstruct` produced. ``reconstruction`` is the pycolmap model written."""

    reconstruction: object
    model_dir: Path
    images: int
    registered: int
    models: int
    points: int
    mean_reprojection_error_px: float
    camera: str
    seconds: float

    def summary(self) -> dict:
        return {"model": str(self.model_dir), "images": self.images, "registered": self.registered,
                "models": self.models, "points": self.points,
                "mean_reprojection_error_px": self.mean_reprojection_error_px,
                "camera": self.camera, "seconds": round(self.seconds, 2)}


def list_images(folder: str | Path) -> list[str]:
    """Sorted names of the photos directly inside ``folder``."""
    folder = Path(folder)
    if not folder.is_dir():
        raise SceneError(f"{folder}: photo folder is missing")
    names = sorted(p.name for p in folder.iterdir() if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES)
    if len(names) < 2:
        raise SceneError(f"{folder}: found {len(names)} photo(s) ({', '.join(IMAGE_SUFFIXES)}); "
                         "structure from motion needs at least 2 overlapping photos")
    return names


def reconstruct(image_dir: str | Path, model_dir: str | Path, database: str | Path,
                options: Optional[SfmOptions] = None,
                on_progress: Optional[Callable[[str, int, int], None]] = None) -> SfmResult:
    """Run SfM on the photos in ``image_dir``; write the largest model to ``model_dir``.

    ``database`` is COLMAP's feature database (replaced if it exists). ``on_progress(phase,
    done, total)`` is called with phase ``features`` / ``matching`` (0 of 1, then 1 of 1) and
    ``mapping`` (images registered so far of all photos). Raises SceneError when no model
    could be built; ``model_dir`` is only written on success (under a temporary name first).
    """
    import pycolmap

    o = options or SfmOptions()
    image_dir, model_dir, database = Path(image_dir), Path(model_dir), Path(database)
    names = list_images(image_dir)
    report = on_progress or (lambda phase, done, total: None)
    t0 = time.perf_counter()
    database.parent.mkdir(parents=True, exist_ok=True)
    if database.exists():
        database.unlink()

    report("features", 0, len(names))
    reader = pycolmap.ImageReaderOptions()
    reader.camera_model = o.camera_model
    ext = pycolmap.FeatureExtractionOptions()
    ext.num_threads = o.threads
    ext.sift.peak_threshold = o.peak_threshold
    pycolmap.extract_features(database, image_dir, image_names=names, camera_mode=pycolmap.CameraMode.SINGLE,
                              reader_options=reader, extraction_options=ext, device=pycolmap.Device.cpu)
    report("features", len(names), len(names))

    report("matching", 0, 1)
    match = pycolmap.FeatureMatchingOptions()
    match.num_threads = o.threads
    pycolmap.match_exhaustive(database, matching_options=match, device=pycolmap.Device.cpu)
    report("matching", 1, 1)

    opts = pycolmap.IncrementalPipelineOptions()
    opts.num_threads = o.threads
    opts.random_seed = o.seed
    opts.mapper.init_min_num_inliers = o.init_min_num_inliers
    opts.mapper.abs_pose_min_num_inliers = o.abs_pose_min_num_inliers
    opts.min_model_size = o.min_model_size
    registered = [0]

    def registered_more(k):
        def callback():
            registered[0] += k
            report("mapping", min(registered[0], len(names)), len(names))
        return callback

    work = model_dir.parent / f".{model_dir.name}.sfm_tmp"
    shutil.rmtree(work, ignore_errors=True)
    work.mkdir(parents=True)
    try:
        report("mapping", 0, len(names))
        recs = pycolmap.incremental_mapping(database, image_dir, work / "models", opts,
                                            initial_image_pair_callback=registered_more(2),
                                            next_image_callback=registered_more(1))
        if not recs:
            raise SceneError(f"{image_dir}: structure from motion registered none of the {len(names)} "
                             "photos (too little overlap or texture, or too small)")
        best = max(recs.values(), key=lambda r: r.num_reg_images())
        staged = work / "best"
        staged.mkdir()
        best.write(str(staged))
        if model_dir.exists():
            shutil.rmtree(model_dir)
        model_dir.parent.mkdir(parents=True, exist_ok=True)
        staged.rename(model_dir)
    finally:
        shutil.rmtree(work, ignore_errors=True)
    return SfmResult(reconstruction=best, model_dir=model_dir, images=len(names),
                     registered=int(best.num_reg_images()), models=len(recs), points=int(best.num_points3D()),
                     mean_reprojection_error_px=float(best.compute_mean_reprojection_error()),
                     camera=str(next(iter(best.cameras.values()))), seconds=time.perf_counter() - t0)
