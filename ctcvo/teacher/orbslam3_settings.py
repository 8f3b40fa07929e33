"""ORB-SLAM3's settings file (OpenCV YAML, ORB-SLAM2-style keys) for a sequence.

Frames go to ORB-SLAM3 as :class:`~ctcvo.data.sequence.Sequence` reads them, whatever the
dataset: colour in RGB order (``Camera.RGB: 1``) and depth as float32 metres, so
``DepthMapFactor`` is 1 (ORB-SLAM3 then converts nothing) and every reader's own depth
scale (TUM 5000, 7-Scenes and the synthetic scenes 1000, bags mm or m) is already applied.
The intrinsics are the depth-registered camera's, without distortion: a reader that knows a
lens distortion undistorts the frames first (data/undistort.py).
"""

from __future__ import annotations

import numpy as np

from ctcvo.data.errors import DataError
from ctcvo.data.sequence import Sequence

#: ORB-SLAM3's stereo baseline times fx for RGB-D, pixels x metres (TUM1.yaml's 40.0);
#: with THRESHOLD_DEPTH it puts the close/far point split at 40 * 40 / fx (2.7-3.1 m)
CAMERA_BF = 40.0
THRESHOLD_DEPTH = 40.0
#: ORB extractor parameters of ORB-SLAM3's own TUM settings
ORB_SCALE_FACTOR, ORB_LEVELS, ORB_INI_FAST, ORB_MIN_FAST = 1.2, 8, 20, 7


def sequence_fps(seq: Sequence) -> float:
    """Frame rate from the timestamps (the median step), rounded to a whole number; 30 for one frame."""
    steps = np.diff(seq.times())
    steps = steps[steps > 0]
    if not len(steps):
        return 30.0
    return float(max(1, round(1.0 / float(np.median(steps)))))


def settings_yaml(seq: Sequence, n_features: int = 1000) -> str:
    """The text of an ORB-SLAM3 RGB-D settings file for ``seq``."""
    if n_features < 100:
        raise DataError(f"ORB-SLAM3 needs at least 100 ORB features per frame, got {n_features}")
    i = seq.intrinsics
    keys = {
        "Camera.type": '"PinHole"',
        "Camera.fx": i.fx, "Camera.fy": i.fy, "Camera.cx": i.cx, "Camera.cy": i.cy,
        "Camera.k1": 0.0, "Camera.k2": 0.0, "Camera.p1": 0.0, "Camera.p2": 0.0, "Camera.k3": 0.0,
        "Camera.width": int(i.width), "Camera.height": int(i.height),
        "Camera.fps": sequence_fps(seq), "Camera.bf": CAMERA_BF, "Camera.RGB": 1,
        "ThDepth": THRESHOLD_DEPTH, "DepthMapFactor": 1.0,
        "ORBextractor.nFeatures": int(n_features), "ORBextractor.scaleFactor": ORB_SCALE_FACTOR,
        "ORBextractor.nLevels": ORB_LEVELS, "ORBextractor.iniThFAST": ORB_INI_FAST,
        "ORBextractor.minThFAST": ORB_MIN_FAST,
        # read even with the viewer off
        "Viewer.KeyFrameSize": 0.05, "Viewer.KeyFrameLineWidth": 1.0, "Viewer.GraphLineWidth": 0.9,
        "Viewer.PointSize": 2.0, "Viewer.CameraSize": 0.08, "Viewer.CameraLineWidth": 3.0,
        "Viewer.ViewpointX": 0.0, "Viewer.ViewpointY": -0.7, "Viewer.ViewpointZ": -1.8, "Viewer.ViewpointF": 500.0,
    }
    return "%YAML:1.0\n" + "".join(f"{k}: {_fmt(v)}\n" for k, v in keys.items())


def _fmt(v) -> str:
    return v if isinstance(v, str) else repr(float(v)) if isinstance(v, float) else str(v)
