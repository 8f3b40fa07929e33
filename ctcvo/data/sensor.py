"""What a reader knows about the camera that recorded a sequence (:class:`Sensor`): how
its colour pixels map onto the depth camera's, how long its rows take to read out, whether
colour and depth are exposed together, and the raw depth units per metre. Each reader sets
``Sequence.sensor``; the stages read it instead of guessing from the folder."""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray


@dataclass(frozen=True)
class ColourCamera:
    """How the colour camera's pixels map onto the depth camera's, for RGB-D sensors whose
    colour is not registered to depth (Kinect v1 as recorded in 7-Scenes): the colour pixel
    ``(u, v)`` sees the depth pixel
    ``(cx + (u - cx - shift_x) / focal_scale + fx * baseline_m / z, cy + (v - cy - shift_y) / focal_scale)``,
    z the depth there (the model of :class:`data.synthetic.config.SensorConfig`'s ``rgb_*``
    fields). Keypoints are moved into depth-camera pixels with it, so their bearings use the
    camera matrix their depth and the ground truth belong to; treated as depth-camera pixels
    unmoved, a 0.91 focal scale makes every sparse rotation ~10 % too small."""

    focal_scale: float
    shift_px: tuple[float, float]
    baseline_m: float
    synchronous: bool = False
    """Colour and depth are exposed at the same instant (the synthetic sensor model); a
    real Kinect v1 exposes them at different times. ``dense_method="auto"`` uses the hybrid
    (photometric + depth) dense step only for a synchronous camera."""

    def to_depth_pixels(self, uv: NDArray, depth: NDArray[np.float32], K: NDArray) -> NDArray[np.float32]:
        """(N, 2) colour pixels -> (N, 2) depth-camera pixels (the parallax term uses the depth
        at the pixel without it, as the sensor model does; none where that depth is 0)."""
        cx, cy = K[0, 2], K[1, 2]
        x = cx + (uv[:, 0] - cx - self.shift_px[0]) / self.focal_scale
        y = cy + (uv[:, 1] - cy - self.shift_px[1]) / self.focal_scale
        if self.baseline_m:
            h, w = depth.shape
            z = depth[np.clip(np.rint(y).astype(np.int64), 0, h - 1), np.clip(np.rint(x).astype(np.int64), 0, w - 1)]
            x = x + np.where(z > 0, K[0, 0] * self.baseline_m / np.maximum(z, 0.4), 0.0)
        return np.stack([x, y], axis=1).astype(np.float32)

    def to_depth_image(self, img: NDArray[np.uint8], depth: NDArray[np.float32], K: NDArray) -> NDArray[np.uint8]:
        """(H, W) colour-camera image resampled onto the depth camera's pixels (bilinear): the
        depth pixel ``(x, y)`` takes the colour pixel ``(cx + shift_x + s (x - cx - fx b / z),
        cy + shift_y + s (y - cy))``, the inverse of :meth:`to_depth_pixels`, with z the depth
        at ``(x, y)`` (where it is 0, the median depth of the frame sets the parallax)."""
        h, w = depth.shape
        cx, cy, fx = K[0, 2], K[1, 2], K[0, 0]
        xs = np.arange(w, dtype=np.float32)
        my = np.broadcast_to((cy + self.shift_px[1] + self.focal_scale * (np.arange(h, dtype=np.float32) - cy))[:, None],
                             (h, w))
        if self.baseline_m:
            valid = depth > 0
            z0 = float(np.median(depth[::8, ::8][valid[::8, ::8]])) if valid[::8, ::8].any() else 2.0
            par = np.float32(fx * self.baseline_m) / np.maximum(np.where(valid, depth, np.float32(z0)), np.float32(0.4))
            mx = cx + self.shift_px[0] + self.focal_scale * (xs[None, :] - par - cx)
        else:
            mx = np.broadcast_to(cx + self.shift_px[0] + self.focal_scale * (xs - cx), (h, w))
        return cv2.remap(img, np.ascontiguousarray(mx, dtype=np.float32), np.ascontiguousarray(my, dtype=np.float32),
                         cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)


#: the Kinect v1 colour camera of 7-Scenes, as fitted on the redkitchen sample for the
#: synthetic sensor model (data/synthetic/config.py: ``rgb_focal_scale``, ``rgb_shift_px``,
#: ``rgb_baseline_m``)
KINECT_V1_COLOUR = ColourCamera(0.91, (-3.5, -1.0), 0.016)
#: Kinect v1's row readout, top to bottom (s): its free-running 30 Hz sensors read out over
#: most of the frame period; the synthetic sensor model's ``rolling_shutter_s``
#: (``TeacherConfig.rolling_shutter_s``'s auto value for real recordings)
KINECT_V1_READOUT_S = 0.027


@dataclass(frozen=True)
class Sensor:
    """The camera of a sequence, as its reader knows it."""

    colour: ColourCamera | None
    """How colour pixels map onto the depth camera's; None: colour registered to depth."""
    readout_s: float
    """Rolling-shutter readout of the rows, top to bottom, seconds (0: a global shutter)."""
    synchronous: bool
    """Colour and depth are exposed at the same instant (a synthetic scene's renderer)."""
    depth_scale: float
    """Raw depth units per metre in the recorded depth images."""
    noise_model: str = "kinect-v1"
    """Whose errors the teacher's covariances are calibrated to (:mod:`teacher.covariance_model`):
    ``kinect-v1`` (real recordings: 7-Scenes, TUM RGB-D, bags), ``synthetic`` (the renderer's
    noisy sensor model) or ``none`` (a noise-free rendering)."""
