"""Video clips (MP4, MOV, MKV, ...) into a survey's photos, with PyAV (FFmpeg in its wheels).

:func:`probe` reads what a clip is (codec, size, frame rate, duration) and refuses what is no
video; :func:`import_frames` decodes it once, chooses frames with
:mod:`.frame_choice` (the sharpest of each window of time, no near-duplicates, nothing too
dark), and writes them to ``SURVEY/images/`` (``frame_000123.jpg``: the source frame index,
zero-padded, so sorted names are time order; long side capped, JPEG or PNG) with
``SURVEY/frames.json``::

    {"source": "/abs/clip.mp4", "fps": 29.97, "duration_s": 61.2, "frame_count": 1834,
     "source_size": [1920, 1080], "size": [1920, 1080], "settings": {...}, "stats": {...},
     "frames": [{"name": "frame_000004.jpg", "time_s": 0.133, "index": 4, "sharpness": 812.5}, ...]}

``time_s`` is the frame's presentation time in seconds from the clip's first frame (frames
close in time saw nearly the same light); ``sharpness`` the variance of the Laplacian of its
grey image (levels 0-255) at the analysis size. The frames go to a temporary folder that is
renamed to ``images/`` only when all are written, and ``frames.json`` is written last: a
folder with ``frames.json`` holds a complete, reusable frame choice, one without it none.
PyAV is imported only here, lazily: it comes with the training engine.
"""
from __future__ import annotations

import json
import shutil
import time
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Callable, Optional

import numpy as np

from ..errors import Cancelled, VideoError
from ..io.atomic import atomic_path, make_folder
from ..io.images import write_image
from ..io.looks import LOOKS_DIR, LOOKS_FILE
from . import frame_choice as fc

#: Suffixes offered by file dialogs (FFmpeg reads many more; the content decides, not the name).
VIDEO_SUFFIXES = (".mp4", ".mov", ".mkv", ".m4v", ".avi", ".mts", ".webm")
#: Long side of the written frames (px): the size desktop splat trainers cap photos at; more
#: only costs SfM and training time (the trainer caps at 1600 px by default).
DEFAULT_MAX_SIDE = 1920
#: JPEG quality of the written frames: no visible loss, ~1/5 of a PNG's size.
JPEG_QUALITY = 95
IMAGE_FORMATS = ("jpg", "png")
FRAMES_JSON = "frames.json"
#: Seconds between two progress reports while decoding.
PROGRESS_EVERY_S = 0.5
#: Name digits of the frames at least (a 60 fps clip of 4.6 hours fits 6 digits).
NAME_DIGITS = 6
#: Look frames (core/io/looks.py): a frame of the clip is kept beside the keyframes every this
#: many seconds (caustics forget themselves in 0.1-0.5 s: a frame a tenth of a second after the
#: last is a new look at the light, or nearly), ...
LOOKS_EVERY_S = 0.1
#: ... with its long side at most this (px; the caustic work reads them at the training size or
#: below), ...
LOOK_MAX_SIDE = 1280
#: ... and at most this many of them (a thinned, even spread of the rest): 10 a second of a
#: 3-minute clip, some 300-500 MB of JPEGs at 1280 px.
MAX_LOOKS = 1800


@dataclass
class VideoOptions:
    """How frames are chosen and written."""

    #: At most this many frames (:data:`~.frame_choice.MAX_FRAMES`); with ``every_s``, about
    #: this many, one every ``every_s`` seconds instead of by motion.
    frames: int = fc.MAX_FRAMES
    every_s: Optional[float] = None
    #: A new frame each time the view has moved this share of the image
    #: (:data:`~.frame_choice.MOTION_STEP`; not used with ``every_s``).
    step: float = fc.MOTION_STEP
    #: Long side of the written images at most (px; 0: the clip's own size).
    max_side: int = DEFAULT_MAX_SIDE
    image_format: str = "jpg"
    jpeg_quality: int = JPEG_QUALITY
    #: Decoder threads.
    threads: int = 2
    duplicate_mad: float = fc.DUPLICATE_MAD
    dark_level: float = fc.DARK_LEVEL
    #: Look frames beside the keyframes, one every this many seconds (0: none; :data:`LOOKS_EVERY_S`).
    looks_every_s: float = LOOKS_EVERY_S

    def settings(self) -> dict:
        """What the frame choice depends on (a rerun reuses frames only when these match; the
        look frames do not change which frames train)."""
        return {k: v for k, v in asdict(self).items()
                if k not in ("threads", "looks_every_s") and not (k == "step" and self.every_s)}

    @property
    def by_motion(self) -> bool:
        """Windows by how far the view moved (the default), not by a spacing in seconds."""
        return self.every_s is None


@dataclass
class ClipInfo:
    """What :func:`probe` found in a clip. ``frames`` is the container's count, or an estimate
    from duration x frame rate (0 when neither is known)."""

    path: Path
    codec: str
    width: int
    height: int
    fps: float
    duration_s: float
    frames: int


# -- opening ------------------------------------------------------------------------------------

def _av():
    try:
        import av
    except ImportError as exc:
        raise ImportError("PyAV is not installed", name="av") from exc
    return av


def _open(path: Path):
    """(container, video stream) of a clip; VideoError naming the file for what is no video."""
    av = _av()
    if path.is_dir():
        raise VideoError(f"{path}: is a folder, not a video file")
    if not path.is_file():
        raise VideoError(f"{path}: video file is missing")
    try:
        container = av.open(str(path), metadata_errors="ignore")
    except av.error.FFmpegError as exc:
        raise VideoError(f"{path}: not a video FFmpeg can read ({_ffmpeg_reason(exc)}); "
                         "choose an MP4, MOV or MKV clip, or convert it with a video editor") from exc
    if not container.streams.video:
        container.close()
        raise VideoError(f"{path}: holds no video stream (audio or data only); choose the clip itself")
    stream = container.streams.video[0]
    if stream.codec_context is None:
        container.close()
        raise VideoError(f"{path}: FFmpeg has no decoder for its video codec; convert the clip to H.264 "
                         "MP4 (any video editor, or ffmpeg -i CLIP -c:v libx264 -crf 18 OUT.mp4)")
    return container, stream


def _ffmpeg_reason(exc) -> str:
    return str(getattr(exc, "strerror", None) or exc).strip().rstrip(".") or "unknown error"


def _seconds(value, time_base) -> Optional[float]:
    if value is None or time_base is None:
        return None
    return float(value * time_base)


def probe(path: str | Path) -> ClipInfo:
    """Read a clip's header (nothing decoded unless the duration is missing: then its packets
    are counted). Raises VideoError naming the file for a file that is no readable video."""
    path = Path(path)
    container, stream = _open(path)
    try:
        ctx = stream.codec_context
        rate = stream.average_rate or stream.guessed_rate or stream.base_rate
        fps = float(rate) if rate else 0.0
        duration = _seconds(stream.duration, stream.time_base)
        if not duration and container.duration:
            duration = container.duration / 1_000_000   # AV_TIME_BASE: microseconds
        frames = int(stream.frames or 0)
        if not duration or (not frames and not fps):
            frames, duration = _count_packets(container, stream)
        if not fps and duration:
            fps = frames / duration
        if not frames and fps and duration:
            frames = int(round(duration * fps))
        return ClipInfo(path, ctx.name, int(ctx.width or 0), int(ctx.height or 0), fps, float(duration or 0.0),
                        frames)
    finally:
        container.close()


def _count_packets(container, stream) -> tuple[int, float]:
    """Frames and duration (s) of a clip whose header lacks them, from its packets."""
    av = _av()
    n, first, last, step = 0, None, None, 0.0
    try:
        for packet in container.demux(stream):
            if packet.size == 0 or packet.pts is None:
                continue
            t = float(packet.pts * packet.time_base)
            first = t if first is None else min(first, t)
            last = t if last is None else max(last, t)
            step = float(packet.duration * packet.time_base) if packet.duration else step
            n += 1
    except av.error.FFmpegError as exc:
        raise VideoError(f"{Path(container.name)}: the clip is damaged ({_ffmpeg_reason(exc)})") from exc
    if n == 0:
        return 0, 0.0
    return n, (last - first) + step


# -- choosing and writing -------------------------------------------------------------------------

def analysis_size(width: int, height: int, side: int = fc.ANALYSIS_SIDE) -> tuple[int, int]:
    """(width, height) frames are judged at: long side at most ``side``, even numbers."""
    scale = min(1.0, side / max(width, height))
    return max(2, int(round(width * scale / 2)) * 2), max(2, int(round(height * scale / 2)) * 2)


def output_size(width: int, height: int, max_side: int) -> tuple[int, int]:
    """(width, height) a frame is written at: long side at most ``max_side`` (0: as is)."""
    if max_side <= 0 or max(width, height) <= max_side:
        return width, height
    scale = max_side / max(width, height)
    return max(1, int(round(width * scale))), max(1, int(round(height * scale)))


def read_frames_json(survey: str | Path) -> Optional[dict]:
    """``SURVEY/frames.json`` as a dict, or None when there is none (or it is unreadable)."""
    path = Path(survey) / FRAMES_JSON
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None
    return data if isinstance(data, dict) and isinstance(data.get("frames"), list) else None


def existing_frames(survey: str | Path, clip: str | Path, options: VideoOptions) -> Optional[dict]:
    """The frame choice already in ``survey`` for this clip and these settings (every image
    present), else None. Raises VideoError when the folder holds frames of another clip or
    other settings, or photos that no frame choice wrote."""
    survey, clip = Path(survey), Path(clip)
    record = read_frames_json(survey)
    if record is None:
        if (survey / "images").exists():
            raise VideoError(f"{survey / 'images'}: already holds photos that are not frames of a video "
                             "import; choose another survey folder (or pass --overwrite to replace them)")
        return None
    if record.get("source") != str(clip.resolve()) or record.get("settings") != options.settings():
        changed = [k for k, v in options.settings().items() if (record.get("settings") or {}).get(k) != v]
        what = (f"frames of {record.get('source')}" if record.get("source") != str(clip.resolve())
                else f"frames chosen with other settings ({', '.join(changed)})")
        raise VideoError(f"{survey}: already holds {what}; pass --overwrite to choose the frames again, "
                         "or choose another survey folder")
    missing = [f["name"] for f in record["frames"] if not (survey / "images" / f["name"]).is_file()]
    if missing:
        raise VideoError(f"{survey / 'images'}: {len(missing)} of the chosen frames are missing "
                         f"({missing[0]}, ...); pass --overwrite to choose the frames again")
    return record


def plan_windows(info: ClipInfo, options: "VideoOptions"):
    """Where the clip's windows fall (:class:`~.frame_choice.MotionWindows`, or with a spacing in
    seconds :class:`~.frame_choice.TimeWindows`); VideoError naming the clip when the clip or the
    settings give too few frames for a survey."""
    o, clip = options, info.path
    if info.frames and info.frames < fc.MIN_FRAMES:
        raise VideoError(f"{clip}: only {info.frames} frame(s) ({info.duration_s:.2f} s); a survey needs at least "
                         f"{fc.MIN_FRAMES} distinct views: use a longer clip")
    if o.frames < fc.MIN_FRAMES:
        raise VideoError(f"{clip}: a survey needs at least {fc.MIN_FRAMES} distinct frames, but {o.frames} "
                         "were asked for at most")
    if o.by_motion:
        try:
            return fc.MotionWindows(o.step)
        except ValueError as exc:
            raise VideoError(f"{clip}: {exc}") from exc
    n_windows = fc.window_count(info.duration_s, info.frames or 10 ** 9, o.frames, o.every_s)
    if n_windows < fc.MIN_FRAMES:
        why = f"one frame every {o.every_s:g} s of its {info.duration_s:.1f} s gives {n_windows}; choose a shorter spacing"
        raise VideoError(f"{clip}: a survey needs at least {fc.MIN_FRAMES} distinct frames, but {why}")
    return fc.TimeWindows(np.linspace(0.0, info.duration_s, n_windows + 1))


def lost_ranges(record: dict, registered: set) -> list[dict]:
    """The stretches of the clip whose chosen frames structure from motion did not register:
    runs of consecutive unregistered frames of ``record`` (what frames.json holds), each
    ``{"from_s", "to_s", "frames"}`` (the first and last such frame's time)."""
    runs: list[dict] = []
    last = None
    for i, f in enumerate(record["frames"]):
        if f["name"] in registered:
            continue
        if last is not None and last == i - 1:
            runs[-1]["to_s"], runs[-1]["frames"] = f["time_s"], runs[-1]["frames"] + 1
        else:
            runs.append({"from_s": f["time_s"], "to_s": f["time_s"], "frames": 1})
        last = i
    return runs


def describe_ranges(runs: list[dict]) -> str:
    """``0.0-1.2 s, 6.4 s`` for :func:`lost_ranges`' runs (the first five, then a count)."""
    parts = [f"{r['from_s']:.1f} s" if r["to_s"] == r["from_s"] else f"{r['from_s']:.1f}-{r['to_s']:.1f} s"
             for r in runs[:5]]
    return ", ".join(parts) + (f" and {len(runs) - 5} more" if len(runs) > 5 else "")


def import_frames(clip: str | Path, survey: str | Path, options: Optional[VideoOptions] = None,
                  on_progress: Optional[Callable[[int, int, int], None]] = None,
                  should_stop: Optional[Callable[[], bool]] = None) -> dict:
    """Choose frames of ``clip`` and write them to ``survey/images`` and ``survey/frames.json``;
    returns what frames.json holds.

    ``on_progress(decoded, total, kept)``: frames decoded so far, of about ``total`` (the
    clip's count, an estimate), and frames kept so far; called every
    :data:`PROGRESS_EVERY_S` seconds and at the end. ``should_stop()`` true stops the import
    (Cancelled; nothing of it is left). Raises VideoError naming the clip for a file that is
    no readable video, a clip too short or too dark, or too few distinct frames.
    """
    av = _av()
    o = options or VideoOptions()
    if o.image_format not in IMAGE_FORMATS:
        raise VideoError(f"unknown image format {o.image_format!r} (one of {', '.join(IMAGE_FORMATS)})")
    clip, survey = Path(clip), Path(survey)
    report = on_progress or (lambda decoded, total, kept: None)
    stop = should_stop or (lambda: False)
    info = probe(clip)
    windows = plan_windows(info, o)
    created = not survey.exists()
    make_folder(survey, "survey folder")
    staging = survey / ".images.partial"
    look_staging = survey / ".looks.partial"
    looks = None
    try:
        tries = []
        while True:
            for d in (staging, look_staging):
                shutil.rmtree(d, ignore_errors=True)
                d.mkdir()
            record, looks = _decode_and_write(av, info, staging, o, windows, report, stop, look_staging)
            tries.append({"step": o.step, "frames": len(record["frames"])})
            step = shorter_step(record, o)
            if step is None:
                break
            o = replace(o, step=step)
            windows = fc.MotionWindows(step)
        if len(tries) > 1:
            record["stats"]["short_clip"] = tries
            record["settings"] = (options or VideoOptions()).settings()   # what a rerun is matched by
        _enough_frames(info, record)
        record["source"] = str(clip.resolve())
        images = survey / "images"
        if images.exists():
            shutil.rmtree(images)
        staging.rename(images)
        _keep_looks(survey, look_staging, record, looks, o)
    finally:
        shutil.rmtree(staging, ignore_errors=True)
        shutil.rmtree(look_staging, ignore_errors=True)
        if created and not any(survey.iterdir()):   # a failed first import leaves no empty folder
            survey.rmdir()
    with atomic_path(survey / FRAMES_JSON, "frame list") as tmp:
        tmp.write_text(json.dumps(record, indent=1), encoding="utf-8")
    return record


def _keep_looks(survey: Path, staging: Path, record: dict, looks: list[dict], o: VideoOptions) -> None:
    """Put the look frames (``looks``, written to ``staging``) in ``survey/looks`` with
    ``looks.json``: those between the first keyframe and the last that are no keyframe, thinned
    evenly to :data:`MAX_LOOKS`; ``record["looks"]`` says how many and how they were taken. An
    import without look frames removes any an earlier import left."""
    folder, listing = survey / LOOKS_DIR, survey / LOOKS_FILE
    listing.unlink(missing_ok=True)
    if folder.exists():
        shutil.rmtree(folder)
    keys = record["frames"]
    if not o.looks_every_s or not keys:
        return
    first, last = keys[0]["time_s"], keys[-1]["time_s"]
    taken = {f["index"] for f in keys}
    between = [lk for lk in looks if first < lk["time_s"] < last and lk["index"] not in taken]
    kept = [between[i] for i in fc.thin(len(between), MAX_LOOKS)] if len(between) > MAX_LOOKS else between
    names = {lk["name"] for lk in kept}
    for f in staging.iterdir():
        if f.name not in names:
            f.unlink()
    staging.rename(folder)
    record["looks"] = {"frames": len(kept), "every_s": o.looks_every_s, "thinned": len(between) - len(kept),
                       "max_side": LOOK_MAX_SIDE}
    with atomic_path(listing, "look frame list") as tmp:
        tmp.write_text(json.dumps({"source": record["source"], "fps": record["fps"], "every_s": o.looks_every_s,
                                   "looks": kept}, indent=1), encoding="utf-8")


def shorter_step(record: dict, o: VideoOptions) -> Optional[float]:
    """The motion step to choose a short clip's frames again with, or None: where the step gave
    fewer than :data:`~.frame_choice.SHORT_CLIP_FRAMES` frames, one that gives about a quarter
    more than that from the motion the clip showed (``moved / step`` windows), at least halving
    the step and never below :data:`~.frame_choice.MIN_STEP`; None when the frames are chosen by
    time, enough were chosen, the step is at its floor, or every frame decoded was a window."""
    st = record["stats"]
    n = len(record["frames"])
    if not o.by_motion or n >= fc.SHORT_CLIP_FRAMES or o.step <= fc.MIN_STEP:
        return None
    if st["windows"] >= record["frame_count"] - st["dark_frames"]:
        return None      # each frame was a window of its own: a smaller step gives nothing more
    want = st["moved"] / (1.25 * fc.SHORT_CLIP_FRAMES)
    return max(fc.MIN_STEP, min(0.5 * o.step, want))


def _enough_frames(info: ClipInfo, record: dict) -> None:
    """VideoError naming the clip, its length, the motion measured and what to change, where
    fewer than :data:`~.frame_choice.MIN_FRAMES` distinct frames were chosen."""
    st, n = record["stats"], len(record["frames"])
    if n >= fc.MIN_FRAMES:
        return
    why = (f"only {n} distinct frame(s) in its {info.duration_s:.1f} s ({record['frame_count']} decoded, "
           f"{st['near_duplicates']} near-duplicates of the frame before, {st['dark_windows']} windows too dark)")
    if st.get("by") == "motion":
        steps = [t["step"] for t in st.get("short_clip", [])] or [st["step"]]
        why += (f"; the view moved about {st['moved']:.2f} of the image in all, and a step of "
                f"{min(steps):.3g} of the image between frames found no more")
        todo = ("film a longer pass over the seabed, or take frames by time instead (--every 0.1 for ten a "
                "second)")
    else:
        todo = "take frames closer in time (a smaller --every), or by motion (leave --every out)"
    raise VideoError(f"{info.path}: {why}; a survey needs at least {fc.MIN_FRAMES}: {todo}")


def _decode_and_write(av, info: ClipInfo, folder: Path, o: VideoOptions, windows, report, stop,
                      look_folder: Optional[Path] = None) -> tuple[dict, list[dict]]:
    container, stream = _open(info.path)
    stream.thread_type = "AUTO"
    stream.thread_count = max(1, o.threads)
    digits = max(NAME_DIGITS, len(str(info.frames)))
    turns = 0    # quarter turns counter-clockwise that display the frames upright (phones' portrait clips)
    aw, ah = analysis_size(info.width, info.height)
    chooser = fc.FrameChooser(windows, o.duplicate_mad, o.dark_level)
    written: list[dict] = []
    out_size = None
    t_report = time.monotonic()
    index, t_first, brightness = 0, None, []
    looks: list[dict] = []
    last_look = -float("inf")

    def write_look(frame, t: float) -> None:
        lw, lh = output_size(frame.width, frame.height, min(o.max_side or LOOK_MAX_SIDE, LOOK_MAX_SIDE))
        rgb = frame.reformat(width=lw, height=lh, format="rgb24", interpolation="AREA").to_ndarray()
        if turns:
            rgb = np.ascontiguousarray(np.rot90(rgb, turns))
        name = f"frame_{index:0{digits}d}.jpg"
        write_image(look_folder / name, rgb, quality=90)
        looks.append({"name": name, "time_s": round(t, 4), "index": index})

    def write(cand: fc.Candidate) -> None:
        nonlocal out_size
        frame = cand.payload
        w, h = (frame.width, frame.height)
        ow, oh = output_size(w, h, o.max_side)
        rgb = frame.reformat(width=ow, height=oh, format="rgb24", interpolation="AREA").to_ndarray()
        if turns:
            rgb = np.ascontiguousarray(np.rot90(rgb, turns))
        name = f"frame_{cand.index:0{digits}d}.{o.image_format}"
        write_image(folder / name, rgb, quality=o.jpeg_quality)
        out_size = [int(rgb.shape[1]), int(rgb.shape[0])]
        written.append({"name": name, "time_s": round(cand.time_s, 4), "index": cand.index,
                        "sharpness": round(cand.sharpness, 2)})

    try:
        try:
            for frame in container.decode(stream):
                if stop():
                    raise Cancelled(f"{info.path}: frame choice was stopped")
                t = frame.time if frame.time is not None else (index / info.fps if info.fps else float(index))
                t_first = t if t_first is None else t_first
                if index == 0:   # the display matrix: what FFmpeg's players turn the frames by
                    turns = int(round((frame.rotation or 0) / 90)) % 4
                grey = frame.reformat(width=aw, height=ah, format="gray").to_ndarray().astype(np.float32)
                level = float(grey.mean()) / 255.0
                brightness.append(level)
                cand = fc.Candidate(index, t - t_first, fc.sharpness(grey), level, fc.thumbnail(grey), frame,
                                    fc.thumbnail(grey, fc.MOTION_SIDE) if o.by_motion else None)
                if look_folder is not None and o.looks_every_s and t - t_first - last_look >= o.looks_every_s \
                        and level >= o.dark_level:
                    last_look = t - t_first
                    write_look(frame, last_look)
                for kept in chooser.add(cand):
                    write(kept)
                index += 1
                if time.monotonic() - t_report >= PROGRESS_EVERY_S:
                    t_report = time.monotonic()
                    report(index, max(index, info.frames), len(written))
        except av.error.FFmpegError as exc:
            raise VideoError(f"{info.path}: frame {index} cannot be decoded ({_ffmpeg_reason(exc)}); the clip "
                             "is damaged or its codec is not supported: convert it to H.264 MP4") from exc
        for kept in chooser.close():
            write(kept)
    finally:
        container.close()
    report(index, index, len(written))
    s = chooser.stats
    if index < fc.MIN_FRAMES:
        raise VideoError(f"{info.path}: only {index} frame(s) could be decoded; a survey needs at least "
                         f"{fc.MIN_FRAMES} distinct views: use a longer clip")
    if index - s.dark_frames < fc.MIN_FRAMES:
        raise VideoError(f"{info.path}: too dark: {s.dark_frames} of its {index} frames have a mean brightness below "
                         f"{100 * o.dark_level:g} % (median {100 * float(np.median(brightness)):.1f} %); film with "
                         "lights on, or brighten the clip first")
    keep = fc.thin(len(written), o.frames) if o.by_motion else list(range(len(written)))
    thinned = len(written) - len(keep)
    if thinned:
        for i in sorted(set(range(len(written))) - set(keep)):
            (folder / written[i]["name"]).unlink()
        written = [written[i] for i in keep]
    fps = info.fps or (index / info.duration_s if info.duration_s else 0.0)
    return {"source": str(info.path), "fps": round(fps, 4), "duration_s": round(info.duration_s, 4),
            "frame_count": index, "codec": info.codec, "source_size": [info.width, info.height],
            "size": out_size, "settings": o.settings(),
            "stats": {"windows": s.windows, "kept": s.kept, "near_duplicates": s.duplicates,
                      "dark_windows": s.dark, "dark_frames": s.dark_frames, "thinned": thinned,
                      "by": "motion" if o.by_motion else "time",
                      **({"moved": round(windows.moved, 4), "step": o.step} if o.by_motion else {})},
            "frames": written}, looks
