"""Capture: from photos or a clip to a COLMAP survey. Structure from motion on a photo folder
(``sfm``, pycolmap: features, matching, mapping, resumable and cancellable) and video import
(``video``, PyAV: decoding a clip and writing the frames ``frame_choice`` picks, the sharpest of
each window of time, with their times in ``frames.json``, and the look frames between them,
which ``look_poses`` places against the solved survey). No torch."""
