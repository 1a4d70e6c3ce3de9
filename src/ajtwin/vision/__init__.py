"""Alignment-camera vision: linewidth and overspray from video (paper §5, App. A; model reference
§9).

* :mod:`ajtwin.vision.profile` — line cross-section model, slope -> brightness optics and the
  reference definitions applied to a true profile (:func:`profile_features`).
* :mod:`ajtwin.vision.render` — realistic frames, videos (+ ground truth) and CNN columns.
* :mod:`ajtwin.vision.extract` — the paper's Canny -> Hough -> rotate -> batch algorithm.
* :mod:`ajtwin.vision.join` — frame times -> print time, filling a print record.
* :mod:`ajtwin.vision.camera` — the camera's geometry over a part (camera.toml).
* :mod:`ajtwin.vision.part_render` — a part under the camera, rendered from a job print.
* :mod:`ajtwin.vision.part_extract` — program-guided readings across every trace of a part;
  :mod:`ajtwin.vision.part_video` runs it over a video.
* :mod:`ajtwin.vision.calibrate` — the camera's geometry fitted to frames of known strokes.

Submodules are imported lazily so ``import ajtwin.vision`` stays cheap (no OpenCV).
"""

from __future__ import annotations

import importlib

_EXPORTS = {
    "line_profile": "ajtwin.vision.profile",
    "profile_features": "ajtwin.vision.profile",
    "brightness_from_profile": "ajtwin.vision.profile",
    "render_frame": "ajtwin.vision.render",
    "render_video": "ajtwin.vision.render",
    "render_columns": "ajtwin.vision.render",
    "LineExtractor": "ajtwin.vision.extract",
}


def __getattr__(name):
    if name in _EXPORTS:
        return getattr(importlib.import_module(_EXPORTS[name]), name)
    raise AttributeError(f"module 'ajtwin.vision' has no attribute {name!r}")


__all__ = sorted(_EXPORTS)
