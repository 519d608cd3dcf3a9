"""The capture jobs' options: ``sfm`` (photos into a COLMAP model) and ``video`` (a clip into a
survey): :data:`SFM_OPTIONS`, :data:`VIDEO_OPTIONS`."""
from __future__ import annotations

from pathlib import Path

from ..capture.frame_choice import MAX_FRAMES, MIN_FRAMES
from ..capture.sfm import SfmOptions
from ..capture.video import DEFAULT_MAX_SIDE, IMAGE_FORMATS, JPEG_QUALITY, VideoOptions
from .table import Option, OptionTable, Setting

#: Options both commands take.
_CAMERA_MODEL = Option("--camera-model", "COLMAP camera model (one camera shared by every photo or frame)",
                       default=SfmOptions.camera_model)
_THREADS = Option("--threads", "CPU threads for structure from motion (and for decoding a clip)", type=int,
                  default=SfmOptions.threads)

SFM_OPTIONS = OptionTable([
    Option("photo_dir", "Folder of overlapping photos", type=Path),
    Option("--out", "Scene folder to write (images/, sparse/0)", type=Path, required=True),
    Option("--link", "Symlink the photos into the scene folder instead of copying them", type=bool,
           setting=Setting("Link Photos", default=False)),
    Option("--overwrite", "Replace an existing sparse/0", type=bool),
    _CAMERA_MODEL,
    _THREADS,
])

VIDEO_OPTIONS = OptionTable([
    Option("clip", "Video file (MP4, MOV, MKV, ...)", type=Path),
    Option("--out", "Survey folder to write (images/, frames.json, sparse/0)", type=Path, required=True),
    Option("--frames", "At most this many frames; where the camera's motion gives more, an even "
                       "selection of them", type=int,
           default=MAX_FRAMES, setting=Setting("Max Frames", minimum=MIN_FRAMES, soft_max=1000)),
    Option("--step", "A new frame each time the view has moved this share of the image (more frames "
                     "where the camera moves fast or turns, fewer where it is slow)", type=float,
           default=VideoOptions.step, metavar="SHARE", exclusive="spacing"),
    Option("--every", "One frame every this many seconds instead of by the camera's motion", type=float,
           metavar="SECONDS", exclusive="spacing",
           setting=Setting("Every", default=0.0, minimum=0.0, soft_max=10.0,
                           why="0 = by the camera's motion, up to Max Frames")),
    Option("--max-side", "Long side of the written frames at most this many pixels (0: the clip's own size)",
           type=int, default=DEFAULT_MAX_SIDE, setting=Setting("Max Frame Side", minimum=0, soft_max=8192)),
    Option("--look-every", "Keep a look frame (looks/, looks.json) every this many seconds between the keyframes: "
                           "further looks at the light for caustic removal, which do not train (0: none)",
           type=float, default=VideoOptions.looks_every_s, metavar="SECONDS"),
    Option("--format", "Image format of the frames", default=VideoOptions.image_format, choices=IMAGE_FORMATS),
    Option("--quality", "JPEG quality", type=int, default=JPEG_QUALITY),
    _CAMERA_MODEL,
    Option("--overlap", "Match each frame with the next N frames", type=int, default=SfmOptions.overlap),
    Option("--loop-detection", "Also match frames that look alike anywhere in the clip, with this COLMAP "
                               "vocabulary tree file (off by default)", type=Path, metavar="VOCAB_TREE"),
    Option("--min-registered", "Fail unless SfM registers at least this share of the frames", type=float,
           default=0.5, metavar="SHARE"),
    _THREADS,
    Option("--overwrite", "Start again: replace the folder's frames, database and model", type=bool),
    Option("--verbose", "Keep COLMAP's own log lines on stderr", type=bool),
])
