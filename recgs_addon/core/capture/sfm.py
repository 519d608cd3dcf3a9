"""Structure from motion with pycolmap: SIFT features, matching, incremental mapping.

Used by ``python -m recgs_addon sfm`` (the add-on's *Reconstruct from Photos*), by
``python -m recgs_addon video`` (*Import Video*) and by ``tools/make_survey.py --sfm``. The
settings are COLMAP's defaults except where small, low-contrast underwater photos need
otherwise (see :class:`SfmOptions`). Photos in any order are matched exhaustively (every
pair: quadratic in their number, fine for up to a few hundred); the frames of a video,
whose sorted names are their time order, sequentially (each with the next few), which
grows linearly with the clip.

A run in steps (``reconstruct(..., resume=True)``): features, matches, mapping. The step
marker beside the database (``database.steps.json``) records which steps are complete and
with which settings, so a run that was stopped continues where it stopped: complete steps
are reused, a stopped feature extraction or matching goes on from the images and pairs
already in the database (COLMAP skips those), and a stopped mapping, whose result is the
model folder written whole at its end, runs again; a finished one (the model there, made
from the same features and matches with the same settings) is reused, for a caller stopped
after it. Every pycolmap call
can be cancelled (``should_stop``): it raises :class:`~recgs_addon.core.errors.Cancelled`.
"""
from __future__ import annotations

import contextlib
import json
import shutil
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Optional

from ..errors import Cancelled, SceneError
from ..io.atomic import atomic_path

#: File endings taken as photos (case-insensitive).
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".tif", ".tiff", ".bmp")
#: Ways of choosing the image pairs to match.
MATCHING = ("exhaustive", "sequential")
#: Seconds between two looks at a running pycolmap call (progress, cancel requests).
POLL_S = 0.25
#: Feature extraction and sequential matching run in about this many calls, each a progress
#: report. Progress is never read from the database while COLMAP writes it: a second SQLite
#: library in the process (Python's sqlite3) breaks SQLite's file locks there.
PROGRESS_STEPS = 25


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
    #: ``exhaustive`` (every pair) or ``sequential`` (images in name order: each with the next
    #: ``overlap`` ones; with ``quadratic_overlap`` instead with the ones 1, 2, 4, ...
    #: 2^(overlap - 1) later, COLMAP's default, which reaches far but holds only 4 of the next 10).
    matching: str = "exhaustive"
    overlap: int = 10
    quadratic_overlap: bool = False
    #: Sequential matching only: a COLMAP vocabulary tree file; when set, each image is also
    #: matched with the most similar images anywhere in the sequence (loop detection).
    vocab_tree: Optional[str] = None
    #: SIFT on images downscaled to this long side (px; keypoints are given at full size), its
    #: first octave (-1: COLMAP's default, the image upsampled twice first; 0: not upsampled,
    #: ~3x faster on large frames) and its feature cap; None: pycolmap's defaults.
    max_image_size: Optional[int] = None
    first_octave: Optional[int] = None
    max_num_features: Optional[int] = None
    #: Fewest registered images a model needs to be written (fewer: SceneError, nothing written).
    min_registered: int = 1

    def feature_key(self, names: list[str]) -> dict:
        """What the features in a database depend on (compared when a run resumes)."""
        return {"images": names, "camera_model": self.camera_model, "camera_mode": "single",
                "peak_threshold": self.peak_threshold, "max_image_size": self.max_image_size,
                "first_octave": self.first_octave, "max_num_features": self.max_num_features}

    def match_key(self) -> dict:
        """What the matches in a database depend on (besides the features)."""
        return {"matching": self.matching, "overlap": self.overlap, "quadratic_overlap": self.quadratic_overlap,
                "vocab_tree": self.vocab_tree}

    def mapping_key(self) -> dict:
        """What the model depends on (besides the features and matches)."""
        return {"seed": self.seed, "init_min_num_inliers": self.init_min_num_inliers,
                "abs_pose_min_num_inliers": self.abs_pose_min_num_inliers, "min_model_size": self.min_model_size,
                "min_registered": self.min_registered}


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
    #: Seconds spent in each step (``features``, ``matching``, ``mapping``; 0 for a reused step).
    step_seconds: Optional[dict] = None
    #: The steps taken over from an earlier run.
    reused: tuple = ()

    def summary(self) -> dict:
        return {"model": str(self.model_dir), "images": self.images, "registered": self.registered,
                "models": self.models, "points": self.points,
                "mean_reprojection_error_px": self.mean_reprojection_error_px,
                "camera": self.camera, "seconds": round(self.seconds, 2),
                "step_seconds": {k: round(v, 2) for k, v in (self.step_seconds or {}).items()},
                "reused": list(self.reused)}


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


def steps_path(database: str | Path) -> Path:
    """The step marker of a database: ``DIR/NAME.steps.json`` beside ``DIR/NAME.db``."""
    database = Path(database)
    return database.with_name(database.stem + ".steps.json")


def _read_steps(path: Path) -> dict:
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return {}
    return data if isinstance(data, dict) else {}


def _write_steps(path: Path, steps: dict) -> None:
    with atomic_path(path, "SfM step marker") as tmp:
        tmp.write_text(json.dumps(steps, indent=1), encoding="utf-8")


def _sequential_pairing(o: "SfmOptions", loop_detection: bool = True):
    import pycolmap

    pairing = pycolmap.SequentialPairingOptions()
    pairing.overlap = o.overlap
    pairing.quadratic_overlap = o.quadratic_overlap
    pairing.num_threads = o.threads
    if o.vocab_tree and loop_detection:
        pairing.loop_detection = True
        pairing.vocab_tree_path = str(o.vocab_tree)
    return pairing


def sequential_pairs(database: Path, o: "SfmOptions") -> list[tuple[str, str]]:
    """The image pairs (names) sequential matching forms, in COLMAP's order (loop detection's
    pairs left out): what pycolmap's own generator gives for the database's images."""
    import pycolmap

    with contextlib.closing(pycolmap.Database.open(str(database))) as db:
        names = {im.image_id: im.name for im in db.read_all_images()}
        pairs = pycolmap.SequentialPairGenerator(_sequential_pairing(o, loop_detection=False), db).all_pairs()
    return [(names[a], names[b]) for a, b in pairs]


def _images_with_features(database: Path) -> set:
    """Names of the images the database holds keypoints and descriptors of."""
    import pycolmap

    if not database.exists():
        return set()
    with contextlib.closing(pycolmap.Database.open(str(database))) as db:
        return {im.name for im in db.read_all_images()
                if db.exists_keypoints(im.image_id) and db.exists_descriptors(im.image_id)}


def _camera_id(database: Path) -> Optional[int]:
    """The id of the database's (first) camera, None when it has none yet."""
    import pycolmap

    if not database.exists():
        return None
    with contextlib.closing(pycolmap.Database.open(str(database))) as db:
        cameras = db.read_all_cameras()
    return min(c.camera_id for c in cameras) if cameras else None


def _unmatched(database: Path, pairs: list[tuple[str, str]]) -> list[tuple[str, str]]:
    """The pairs of ``pairs`` whose matches and two-view geometry the database lacks."""
    import pycolmap

    with contextlib.closing(pycolmap.Database.open(str(database))) as db:
        ids = {im.name: im.image_id for im in db.read_all_images()}
        return [(a, b) for a, b in pairs
                if not (db.exists_matches(ids[a], ids[b]) and db.exists_two_view_geometry(ids[a], ids[b]))]


def _chunks(items: list, n: int) -> list[list]:
    size = max(1, -(-len(items) // max(1, n)))
    return [items[i:i + size] for i in range(0, len(items), size)]


def _changes_only(report: Callable[[str, int, int], None]) -> Callable[[str, int, int], None]:
    """``report`` called only when its arguments differ from the last call's."""
    last = [None]

    def call(phase: str, done: int, total: int) -> None:
        if (phase, done, total) != last[0]:
            last[0] = (phase, done, total)
            report(phase, done, total)
    return call


def _run(fn, should_stop: Callable[[], bool], poll: Callable[[], None] = lambda: None, **kwargs):
    """``fn(**kwargs, cancellation_token=...)`` in a worker thread (pycolmap releases the GIL),
    while this thread calls ``poll`` and cancels the call once ``should_stop()`` is true (so
    SIGTERM/SIGINT handlers run here at once). Raises Cancelled when it was cancelled."""
    import pycolmap

    token = pycolmap.CancellationToken()
    box: dict = {}

    def work():
        try:
            box["result"] = fn(**kwargs, cancellation_token=token)
        except BaseException as exc:  # noqa: BLE001 - handed to the calling thread
            box["error"] = exc

    worker = threading.Thread(target=work, name="recgs-sfm", daemon=True)
    worker.start()
    while worker.is_alive():
        worker.join(POLL_S)
        if should_stop() and not token.is_cancelled:
            token.cancel()
        poll()
    if token.is_cancelled:
        raise Cancelled("structure from motion was stopped")
    if "error" in box:
        raise box["error"]
    return box.get("result")


def reconstruct(image_dir: str | Path, model_dir: str | Path, database: str | Path,
                options: Optional[SfmOptions] = None,
                on_progress: Optional[Callable[[str, int, int], None]] = None,
                resume: bool = False, should_stop: Optional[Callable[[], bool]] = None) -> SfmResult:
    """Run SfM on the photos in ``image_dir``; write the largest model to ``model_dir``.

    ``database`` is COLMAP's feature database: replaced unless ``resume``, in which case the
    steps its marker (:func:`steps_path`) records as complete with the same settings are
    reused and a stopped step continues. ``on_progress(phase, done, total)`` is called with
    phase ``features`` (images with features of all photos), ``matching`` (image pairs
    matched of all pairs to match; exhaustive matching reports only its start and end) and
    ``mapping`` (images registered so far of all photos), from the calling thread. ``should_stop()``, asked a few times a second, stops the run:
    Cancelled is raised, the database keeps what was done. Raises SceneError when no model of
    at least ``options.min_registered`` images could be built; ``model_dir`` is only written
    on success (under a temporary name first).
    """
    import pycolmap

    o = options or SfmOptions()
    if o.matching not in MATCHING:
        raise SceneError(f"unknown matching {o.matching!r} (one of {', '.join(MATCHING)})")
    image_dir, model_dir, database = Path(image_dir), Path(model_dir), Path(database)
    names = list_images(image_dir)
    report = _changes_only(on_progress or (lambda phase, done, total: None))
    stop = should_stop or (lambda: False)
    t0 = time.perf_counter()
    marker = steps_path(database)
    database.parent.mkdir(parents=True, exist_ok=True)
    steps = _read_steps(marker) if resume and database.exists() else {}
    if steps.get("features", {}).get("key") != o.feature_key(names):
        steps = {}
    if not steps:   # SQLite's -wal and -shm files go too: a new database must not replay them
        for path in (database, marker, database.with_name(database.name + "-wal"),
                     database.with_name(database.name + "-shm")):
            if path.exists():
                path.unlink()
    seconds = {"features": 0.0, "matching": 0.0, "mapping": 0.0}
    reused = []
    n = len(names)

    # -- features ----------------------------------------------------------------------------
    if steps.get("features", {}).get("done"):
        reused.append("features")
        report("features", n, n)
    else:
        t = time.perf_counter()
        steps["features"] = {"key": o.feature_key(names), "done": False}
        _write_steps(marker, steps)
        have = _images_with_features(database)      # a stopped extraction's images are kept
        todo = [name for name in names if name not in have]
        done = n - len(todo)
        report("features", done, n)
        ext = pycolmap.FeatureExtractionOptions()
        ext.num_threads = o.threads
        ext.sift.peak_threshold = o.peak_threshold
        if o.max_image_size is not None:
            ext.max_image_size = o.max_image_size
        if o.first_octave is not None:
            ext.sift.first_octave = o.first_octave
        if o.max_num_features is not None:
            ext.sift.max_num_features = o.max_num_features
        for chunk in _chunks(todo, PROGRESS_STEPS):
            reader = pycolmap.ImageReaderOptions()
            reader.camera_model = o.camera_model
            camera = _camera_id(database)
            if camera is not None:      # later calls add their images to the one camera
                reader.existing_camera_id = camera
            _run(pycolmap.extract_features, stop, database_path=database, image_path=image_dir, image_names=chunk,
                 camera_mode=pycolmap.CameraMode.SINGLE, reader_options=reader, extraction_options=ext,
                 device=pycolmap.Device.cpu)
            done += len(chunk)
            report("features", done, n)
        steps["features"]["done"] = True
        _write_steps(marker, steps)
        seconds["features"] = time.perf_counter() - t

    # -- matches -----------------------------------------------------------------------------
    pair_list = sequential_pairs(database, o) if o.matching == "sequential" else []
    total = n * (n - 1) // 2 if o.matching == "exhaustive" else len(pair_list)
    done_matches = steps.get("matches", {})
    if done_matches.get("key") == o.match_key() and done_matches.get("done"):
        reused.append("matching")
        report("matching", total, total)
    else:
        t = time.perf_counter()
        if done_matches.get("key") != o.match_key():   # other pairs were matched: start afresh
            with contextlib.closing(pycolmap.Database.open(str(database))) as db:
                db.clear_matches()
                db.clear_two_view_geometries()
        steps["matches"] = {"key": o.match_key(), "done": False}
        _write_steps(marker, steps)
        match = pycolmap.FeatureMatchingOptions()
        match.num_threads = o.threads
        common = dict(database_path=database, matching_options=match, device=pycolmap.Device.cpu)
        if o.matching == "exhaustive":
            report("matching", 0, total)
            _run(pycolmap.match_exhaustive, stop, **common)
        elif any(c.isspace() for a, b in pair_list for c in a + b):
            report("matching", 0, total)   # a pair list cannot name these images: one call
            _run(pycolmap.match_sequential, stop, pairing_options=_sequential_pairing(o), **common)
        else:
            todo = _unmatched(database, pair_list)      # a stopped matching's pairs are kept
            done = total - len(todo)
            report("matching", done, total)
            listing = database.with_name(database.stem + ".pairs.txt")
            try:
                for chunk in _chunks(todo, PROGRESS_STEPS):
                    listing.write_text("".join(f"{a} {b}\n" for a, b in chunk), encoding="utf-8")
                    pairing = pycolmap.ImportedPairingOptions()
                    pairing.match_list_path = str(listing)
                    _run(pycolmap.match_image_pairs, stop, pairing_options=pairing, **common)
                    done += len(chunk)
                    report("matching", done, total)
            finally:
                listing.unlink(missing_ok=True)
            if o.vocab_tree:   # the loop-detection pairs (the sequential ones are matched: skipped)
                _run(pycolmap.match_sequential, stop, pairing_options=_sequential_pairing(o), **common)
        steps["matches"]["done"] = True
        _write_steps(marker, steps)
        seconds["matching"] = time.perf_counter() - t
        report("matching", total, total)

    # -- mapping -----------------------------------------------------------------------------
    done_mapping = steps.get("mapping", {})
    if ("features" in reused and "matching" in reused and done_mapping.get("done")
            and done_mapping.get("key") == o.mapping_key() and model_dir.is_dir()):
        # the model of an earlier run on the same features and matches (stopped after it, in
        # whatever the caller does next): mapping again would only take its time
        best = pycolmap.Reconstruction(str(model_dir))
        reused.append("mapping")
        report("mapping", int(best.num_reg_images()), n)
        return _result(best, model_dir, n, int(done_mapping.get("models", 1)), t0, seconds, reused)
    t = time.perf_counter()
    opts = pycolmap.IncrementalPipelineOptions()
    opts.num_threads = o.threads
    opts.random_seed = o.seed
    opts.mapper.init_min_num_inliers = o.init_min_num_inliers
    opts.mapper.abs_pose_min_num_inliers = o.abs_pose_min_num_inliers
    opts.min_model_size = o.min_model_size
    registered = [0]

    def registered_more(k):
        def callback():   # runs in pycolmap's thread: only counts
            registered[0] += k
        return callback

    work = model_dir.parent / f".{model_dir.name}.sfm_tmp"
    parent_made = not model_dir.parent.exists()
    shutil.rmtree(work, ignore_errors=True)
    work.mkdir(parents=True)
    try:
        report("mapping", 0, n)
        recs = _run(pycolmap.incremental_mapping, stop, lambda: report("mapping", min(registered[0], n), n),
                    database_path=database, image_path=image_dir, output_path=work / "models", options=opts,
                    initial_image_pair_callback=registered_more(2), next_image_callback=registered_more(1))
        if not recs:
            raise SceneError(f"{image_dir}: structure from motion registered none of the {n} "
                             "photos (too little overlap or texture, or too small)")
        best = max(recs.values(), key=lambda r: r.num_reg_images())
        if best.num_reg_images() < o.min_registered:
            raise SceneError(f"{image_dir}: structure from motion registered only {best.num_reg_images()} of the "
                             f"{n} photos in one model ({len(recs)} model(s)); at least {o.min_registered} "
                             "are needed (too little overlap between neighbours, blur, or too little texture)")
        staged = work / "best"
        staged.mkdir()
        best.write(str(staged))
        if model_dir.exists():
            shutil.rmtree(model_dir)
        model_dir.parent.mkdir(parents=True, exist_ok=True)
        staged.rename(model_dir)
    finally:
        shutil.rmtree(work, ignore_errors=True)
        if parent_made and not model_dir.exists():   # a failed run leaves no empty sparse/ behind
            shutil.rmtree(model_dir.parent, ignore_errors=True)
    seconds["mapping"] = time.perf_counter() - t
    steps["mapping"] = {"done": True, "key": o.mapping_key(), "registered": int(best.num_reg_images()),
                        "models": len(recs), "model": str(model_dir)}
    _write_steps(marker, steps)
    report("mapping", int(best.num_reg_images()), n)
    return _result(best, model_dir, n, len(recs), t0, seconds, reused)


def _result(best, model_dir: Path, images: int, models: int, t0: float, seconds: dict, reused: list) -> SfmResult:
    """:func:`reconstruct`'s result: the model ``best`` written to ``model_dir`` (the largest of
    ``models``), of ``images`` photos, after ``time.perf_counter() - t0`` seconds."""
    return SfmResult(reconstruction=best, model_dir=model_dir, images=images,
                     registered=int(best.num_reg_images()), models=models, points=int(best.num_points3D()),
                     mean_reprojection_error_px=float(best.compute_mean_reprojection_error()),
                     camera=str(next(iter(best.cameras.values()))), seconds=time.perf_counter() - t0,
                     step_seconds=seconds, reused=tuple(reused))
