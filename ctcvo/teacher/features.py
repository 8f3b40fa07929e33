"""What the teacher keeps of one frame: ORB keypoints with their depth, image keys, dense maps."""

from __future__ import annotations

import dataclasses
import hashlib
from dataclasses import dataclass, field

import cv2
import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from ctcvo.data.sensor import ColourCamera
from ctcvo.teacher.config import TeacherConfig, dense_method
from ctcvo.teacher.maps import DEPTH_MAX, DEPTH_MIN, DenseMaps, dense_maps

# 'the validation ranges': redkitchen 350:450 and synthetic/lab 0:150 (bench/README.md, seventh session)
FAST_THRESHOLD = 12  # set by hand (fa44eca); kept against 8 and 20 on the validation ranges
ORB_LEVELS = 6  # set by hand (fa44eca); kept against 4 and 8 on the validation ranges
DEPTH_EDGE_REL = 0.02  # depth-discontinuity test; by hand (fa44eca); 0.01, 0.04 within noise on the validation ranges
DEPTH_EDGE_ABS = 0.02  # m; by hand (fa44eca); 0.01 and 0.04 level on the validation ranges and redkitchen 200:350

@dataclass
class FrameFeatures:
    """Everything the teacher needs of one frame; computed once, reused by all its edges.

    ``uv`` (N, 2) keypoint pixels, ``desc`` (N, 32) ORB descriptors, ``z`` (N,) depth at the
    keypoint (0 where invalid or on a depth edge, see :func:`depth_at`), ``gray`` (H, W)
    uint8, ``depth`` (H, W) float32 metres. ``dense`` holds the Open3D
    vertex and normal maps of the depth subsampled by ``DENSE_SCALE`` (None when the
    dense step is off). ``keys`` fingerprints the colour and the depth image (to find
    repeated images); ``stale`` is set by the caller when exactly one of the two streams
    repeats the previous frame's image (see :func:`stale_stream`); ``colour_behind`` by
    :class:`teacher.window.EdgeWindow` when the colour image shows an earlier moment than
    the depth (a repeated colour image, or a whole repeat of such a frame), with photometric
    maps only. ``depth_offset`` (s), set by the window for a frame whose depth was taken at
    another moment than its colour (``cfg.depth_time_compensation``), is the depth's time
    minus the colour's: the dense steps of its edges align the depth maps between their
    moments and move the result to the colour moments (:func:`estimate_edge`). 0: the same
    moment. ``velocity_in`` / ``velocity_out`` (6,) ``(v, w)`` per second, set by the window:
    the camera's velocity from the frame's gap-1 edge in and out of it, for the rolling
    shutter correction (``cfg.rolling_shutter_s``, :func:`rolling_shutter_views`); None when
    unknown. ``registered``: the colour camera is the depth camera's (no colour camera model
    moved the keypoints). ``searched``: the keypoints come strongest first and the searches
    without a prediction, and the wide one, take only this many (:meth:`strongest`; None: all).
    """

    uv: NDArray[np.float32]
    desc: NDArray[np.uint8]
    z: NDArray[np.float32]
    gray: NDArray[np.uint8]
    depth: NDArray[np.float32]
    dense: DenseMaps | None = None
    keys: tuple[bytes, bytes] = (b"", b"")
    stale: bool = False
    colour_behind: bool = False
    depth_offset: float = 0.0
    velocity_in: NDArray[np.float64] | None = None
    velocity_out: NDArray[np.float64] | None = None
    registered: bool = True
    searched: int | None = None
    _tree: cKDTree | None = None
    _rolling: dict = field(default_factory=dict, repr=False)
    _strongest: FrameFeatures | None = field(default=None, repr=False)

    @property
    def desc64(self) -> NDArray[np.uint64]:
        """Descriptors as (N, 4) uint64 words for vectorised Hamming distances."""
        return self.desc.view(np.uint64)

    def strongest(self) -> FrameFeatures:
        """The frame with its first ``searched`` keypoints alone (itself when None): a keypoint
        index of the view is the same keypoint's here, so its matches index this frame too."""
        if self.searched is None or self.searched >= len(self.uv):
            return self
        if self._strongest is None:
            n = self.searched
            self._strongest = dataclasses.replace(self, uv=self.uv[:n], desc=self.desc[:n], z=self.z[:n], searched=None,
                                                  _tree=None, _rolling={}, _strongest=None)
        return self._strongest

    def tree(self) -> cKDTree:
        """k-d tree over the keypoint positions (built on first use, then reused)."""
        if self._tree is None:
            self._tree = cKDTree(self.uv)
        return self._tree


def make_orb(cfg: TeacherConfig) -> cv2.ORB:
    return cv2.ORB_create(nfeatures=cfg.n_features, scaleFactor=1.2, nlevels=ORB_LEVELS,
                          fastThreshold=FAST_THRESHOLD, edgeThreshold=19, patchSize=19)


_OFFS = np.array([(dy, dx) for dy in range(-2, 3) for dx in range(-2, 3)])  # 5x5 window


def depth_at(depth: NDArray[np.float32], uv: NDArray) -> NDArray[np.float32]:
    """Depth (m) at sub-pixel points, 0 where unusable.

    A point is usable if its nearest pixel lies 2+ px inside the image, every pixel of its
    5x5 neighbourhood has a depth, the depth range there is within
    ``max(depth_edge_abs, depth_edge_rel * z)`` (no discontinuity) and ``z`` is within
    ``[depth_min, depth_max]``. Usable points get the bilinear depth (safe: no edge nearby).
    Checked per point, not per image: a few thousand look-ups instead of two 640x480
    morphology passes.
    """
    h, w = depth.shape
    z = np.zeros(len(uv), np.float32)
    if len(uv) == 0:
        return z
    u = np.rint(uv[:, 0]).astype(np.int64)
    v = np.rint(uv[:, 1]).astype(np.int64)
    idx = np.flatnonzero((u >= 2) & (u < w - 2) & (v >= 2) & (v < h - 2))
    # (M, 25): one flat np.take (the same pixels as 2-D fancy indexing, a few times faster)
    win = np.take(depth.reshape(-1), (v[idx, None] + _OFFS[:, 0]) * w + (u[idx, None] + _OFFS[:, 1]))
    lo, hi, zc = win.min(axis=1), win.max(axis=1), win[:, 12]
    thr = np.maximum(DEPTH_EDGE_ABS, DEPTH_EDGE_REL * zc)
    idx = idx[(lo > 0) & (hi - lo <= thr) & (zc >= DEPTH_MIN) & (zc <= DEPTH_MAX)]
    x, y = uv[idx, 0].astype(np.float64), uv[idx, 1].astype(np.float64)
    x0, y0 = np.floor(x).astype(np.int64), np.floor(y).astype(np.int64)
    fx, fy = x - x0, y - y0
    z[idx] = ((1 - fx) * (1 - fy) * depth[y0, x0] + fx * (1 - fy) * depth[y0, x0 + 1]
              + (1 - fx) * fy * depth[y0 + 1, x0] + fx * fy * depth[y0 + 1, x0 + 1])
    return z


def image_keys(rgb: NDArray[np.uint8], depth: NDArray[np.float32]) -> tuple[bytes, bytes]:
    """Fingerprints (colour, depth) of a frame: BLAKE2b of every 4th pixel in both axes. Two
    frames share a key only when that image was written twice (a dropped frame): sensor
    noise makes two real exposures differ in thousands of the sampled pixels."""
    return (hashlib.blake2b(np.ascontiguousarray(rgb[::4, ::4]).tobytes(), digest_size=8).digest(),
            hashlib.blake2b(np.ascontiguousarray(depth[::4, ::4]).tobytes(), digest_size=8).digest())


def stale_stream(prev: tuple[bytes, bytes], cur: tuple[bytes, bytes]) -> bool:
    """True when exactly one of the colour and depth images of a frame repeats the previous
    frame's (keys from :func:`image_keys`): the two images were then taken at different
    times. (Both repeated is a whole dropped frame: consistent.)"""
    return (prev[0] == cur[0]) != (prev[1] == cur[1])


def beside_colour_repeat(fi: FrameFeatures, fj: FrameFeatures) -> bool:
    """True for a pair one of whose frames shows its colour from an earlier moment than its
    depth (``colour_behind``) while the pair's depths differ: neither the keypoints nor the
    grey of that frame belong to its depth, so the depth alone aligns the pair (a repeated
    depth map is the same image: left to the keypoints)."""
    return (fi.colour_behind or fj.colour_behind) and fi.keys[1] != fj.keys[1]


def extract(rgb: NDArray[np.uint8], depth: NDArray[np.float32], cfg: TeacherConfig,
            orb: cv2.ORB | None = None, K: NDArray | None = None,
            colour: ColourCamera | None = None, surface: bool = True) -> FrameFeatures:
    """ORB keypoints and descriptors of one frame, with the depth at each keypoint; with the
    camera matrix ``K`` and ``cfg.dense`` also the maps of the dense step (``surface``
    False: without the ones it needs as the older frame of an edge, for :func:`add_surface`
    to add before a later frame's edges). With a ``colour`` camera model (and ``K``),
    keypoints are moved into depth-camera pixels (``uv`` is then in depth-camera pixels;
    None: colour registered to depth)."""
    gray = cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY)
    dense = None
    if K is not None and cfg.dense:
        photo = None
        if dense_method(cfg, colour) == "hybrid":
            photo = colour.to_depth_image(gray, depth, K) if colour is not None else gray
        dense = dense_maps(depth, K, photo, surface)
    orb = orb or make_orb(cfg)
    kps, desc = orb.detectAndCompute(gray, None)
    keys = image_keys(rgb, depth)
    if not kps or desc is None:
        return FrameFeatures(np.zeros((0, 2), np.float32), np.zeros((0, 32), np.uint8),
                             np.zeros(0, np.float32), gray, depth, dense, keys, registered=colour is None)
    uv = np.array([k.pt for k in kps], dtype=np.float32)
    if colour is not None and K is not None:
        uv = colour.to_depth_pixels(uv, depth, K)
    return FrameFeatures(uv, desc, depth_at(depth, uv), gray, depth, dense, keys, registered=colour is None)


def backproject(uv: NDArray, z: NDArray, K: NDArray) -> NDArray[np.float64]:
    x = (uv[:, 0] - K[0, 2]) / K[0, 0] * z
    y = (uv[:, 1] - K[1, 2]) / K[1, 1] * z
    return np.stack([x, y, z], axis=1).astype(np.float64)


def project(X: NDArray, K: NDArray) -> NDArray[np.float64]:
    z = X[:, 2]
    return np.stack([K[0, 0] * X[:, 0] / z + K[0, 2], K[1, 1] * X[:, 1] / z + K[1, 2]], axis=1)

