"""Two-frame RGB-D odometry: ORB matching, depth back-projection, PnP-RANSAC, a robust
two-way refinement that yields ``T_i_j`` with a 6x6 covariance, and a dense point-to-plane
depth alignment (Open3D's projective ICP kernel) started from that estimate.

Conventions (docs/conventions.md): ``T_i_j`` maps frame-j camera coordinates into frame i;
the covariance is in the project tangent order (v, w), right perturbation at ``T_i_j``.
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass, field

import cv2
import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from ctcvo.data import geometry as geo
from ctcvo.data.open3d_import import o3d
from ctcvo.data.sensor import ColourCamera
from ctcvo.data.sequence import Intrinsics
from ctcvo.teacher.config import TeacherConfig


@dataclass
class FrameFeatures:
    """Everything the teacher needs of one frame; computed once, reused by all its edges.

    ``uv`` (N, 2) keypoint pixels, ``desc`` (N, 32) ORB descriptors, ``z`` (N,) depth at the
    keypoint (0 where invalid or on a depth edge, see :func:`depth_at`), ``gray`` (H, W)
    uint8 for sub-pixel tracking, ``depth`` (H, W) float32 metres. ``dense`` holds the Open3D
    vertex and normal maps of the depth subsampled by ``cfg.dense_scale`` (None when the
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
    unknown.
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
    _tree: cKDTree | None = None
    _rolling: dict = field(default_factory=dict, repr=False)

    @property
    def desc64(self) -> NDArray[np.uint64]:
        """Descriptors as (N, 4) uint64 words for vectorised Hamming distances."""
        return self.desc.view(np.uint64)

    def tree(self) -> cKDTree:
        """k-d tree over the keypoint positions (built on first use, then reused)."""
        if self._tree is None:
            self._tree = cKDTree(self.uv)
        return self._tree


def make_orb(cfg: TeacherConfig) -> cv2.ORB:
    return cv2.ORB_create(nfeatures=cfg.n_features, scaleFactor=1.2, nlevels=cfg.orb_levels,
                          fastThreshold=cfg.fast_threshold, edgeThreshold=19, patchSize=19)


_OFFS = np.array([(dy, dx) for dy in range(-2, 3) for dx in range(-2, 3)])  # 5x5 window


def depth_at(depth: NDArray[np.float32], uv: NDArray, cfg: TeacherConfig) -> NDArray[np.float32]:
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
    thr = np.maximum(cfg.depth_edge_abs, cfg.depth_edge_rel * zc)
    idx = idx[(lo > 0) & (hi - lo <= thr) & (zc >= cfg.depth_min) & (zc <= cfg.depth_max)]
    x, y = uv[idx, 0].astype(np.float64), uv[idx, 1].astype(np.float64)
    x0, y0 = np.floor(x).astype(np.int64), np.floor(y).astype(np.int64)
    fx, fy = x - x0, y - y0
    z[idx] = ((1 - fx) * (1 - fy) * depth[y0, x0] + fx * (1 - fy) * depth[y0, x0 + 1]
              + (1 - fx) * fy * depth[y0 + 1, x0] + fx * fy * depth[y0 + 1, x0 + 1])
    return z


@dataclass
class DenseMaps:
    """Open3D tensors of one frame for the dense depth alignment (float32, NaN where invalid).

    ``points`` (h4, w4, 3): vertex map of every ``cfg.dense_scale``-th pixel, used when the
    frame is the one moved (j); ``vertex`` and ``normal`` (h2, w2, 3): vertex and normal maps
    of every ``cfg.dense_target_scale``-th pixel, used when the frame is the one aligned to
    (i), with ``K`` (3x3 float64) their camera matrix.
    """

    points: o3d.core.Tensor
    vertex: o3d.core.Tensor | None
    normal: o3d.core.Tensor | None
    K: o3d.core.Tensor
    photo: PhotoMaps | None = None
    _cache: dict = field(default_factory=dict, repr=False)
    """What the covariances of :func:`point_to_plane_covariance` take from this frame on
    every edge it is part of, computed on its first edge (:meth:`moved_points`,
    :meth:`surface`)."""

    def moved_points(self, stride: int) -> NDArray[np.float64]:
        """(N, 3) the finite points of ``points``, every ``stride``-th in both axes, float64
        (the frame as the one moved, j; the same for all its edges)."""
        key = ("points", stride)
        if key not in self._cache:
            q = self.points.numpy()[::stride, ::stride].reshape(-1, 3)
            self._cache[key] = np.compress(np.isfinite(q).all(axis=1), q, axis=0).astype(np.float64)
        return self._cache[key]

    def surface(self) -> tuple[NDArray[np.float32], NDArray[np.float32], int, int, NDArray[np.float64]]:
        """The frame as the one aligned to (i): (h * w, 3) vertex and normal of each pixel of
        ``vertex`` / ``normal`` (row-major views of Open3D's float32 maps, NaN where
        invalid), h, w and the camera matrix. An edge gathers the rows of the pixels it
        hits and tests and converts those alone: cheaper than one (h * w, 6) float64 table
        and its finiteness per frame (3.7 ms, more than the ~5 edges' gathers)."""
        if "surface" not in self._cache:
            vert, nrm = self.vertex.numpy(), self.normal.numpy()
            h, w = vert.shape[:2]
            self._cache["surface"] = (vert.reshape(-1, 3), nrm.reshape(-1, 3), h, w, self.K.numpy())
        return self._cache["surface"]


@dataclass
class PhotoMaps:
    """Open3D tensors of one frame for the hybrid (photometric + depth) alignment of
    :func:`hybrid_align` (float32, (rows, cols, 1) unless noted, NaN depth where invalid).

    As the frame moved (j): ``src_depth`` and ``src_intensity`` at the pixels of
    ``DenseMaps.points`` (every ``cfg.dense_scale``-th). As the frame aligned to (i), at
    full resolution: ``depth``, ``intensity`` (grey in [0, 1], registered to the depth
    camera), their unnormalised 3x3 Sobel derivatives ``depth_dx`` ... ``intensity_dy``, and
    ``K`` (3x3 float64). Full resolution on that side is what makes the alignment precise:
    Open3D's kernel pairs each point with the nearest target pixel, and at half resolution
    the gap-1 error on synthetic/stress-far doubled (2.1-2.5 against 0.9-1.3 mm)."""

    src_depth: o3d.core.Tensor
    src_intensity: o3d.core.Tensor
    depth: o3d.core.Tensor
    intensity: o3d.core.Tensor
    depth_dx: o3d.core.Tensor
    depth_dy: o3d.core.Tensor
    intensity_dx: o3d.core.Tensor
    intensity_dy: o3d.core.Tensor
    K: o3d.core.Tensor
    levels: dict = field(default_factory=dict)
    """Coarser levels for :func:`pyramid_align`, built on first use: scale -> (depth,
    intensity, depth_dx, depth_dy, intensity_dx, intensity_dy, vertex map, K) at that scale."""
    grey: bool = True
    """False: the intensity maps are zeros (:meth:`depth_only`), so the kernel's photometric
    term is void and only its depth term acts."""
    _depth_only: PhotoMaps | None = field(default=None, repr=False)

    def depth_only(self) -> PhotoMaps:
        """These maps with every intensity map zero (``grey`` False; built once, kept): for
        a frame whose colour shows another moment than its depth, and for the frame it is
        paired with, so Open3D's hybrid kernel aligns the depth alone (the projective depth
        term, coarse to fine in :func:`pyramid_align`)."""
        if not self.grey:
            return self
        if self._depth_only is None:
            z_src = o3d.core.Tensor(np.zeros(tuple(self.src_intensity.shape), np.float32))
            z = o3d.core.Tensor(np.zeros(tuple(self.intensity.shape), np.float32))
            self._depth_only = PhotoMaps(self.src_depth, z_src, self.depth, z, self.depth_dx, self.depth_dy, z, z,
                                         self.K, grey=False)
        return self._depth_only

    def level(self, s: int) -> tuple:
        """The maps of every ``s``-th pixel (intensity averaged over ``s x s`` blocks, depth
        subsampled), both as source and as target of the kernel."""
        if s not in self.levels:
            d = self.depth.numpy()[::s, ::s, 0].copy()
            full = self.intensity.numpy()[..., 0]
            inten = cv2.resize(full, (d.shape[1], d.shape[0]), interpolation=cv2.INTER_AREA)
            K = self.K.numpy().copy()
            K[:2] /= s
            Kt = o3d.core.Tensor(K)
            maps = _kernel_maps(d, inten)
            vertex = o3d.t.geometry.Image(maps[0]).create_vertex_map(Kt, float("nan")).as_tensor()
            self.levels[s] = (*maps, vertex, Kt)
        return self.levels[s]


def _image_tensor(a: NDArray) -> o3d.core.Tensor:
    """(H, W) array -> (H, W, 1) float32 Open3D tensor, as the odometry kernels take images."""
    return o3d.core.Tensor(np.ascontiguousarray(a[..., None], dtype=np.float32))


def _kernel_maps(depth: NDArray[np.float32], inten: NDArray[np.float32]) -> tuple[o3d.core.Tensor, ...]:
    """What Open3D's hybrid kernel takes of a frame as its target: depth, intensity and
    their unnormalised 3x3 Sobel derivatives (depth_dx, depth_dy, intensity_dx,
    intensity_dy), each an (H, W, 1) float32 tensor."""
    return (_image_tensor(depth), _image_tensor(inten),
            *(_image_tensor(cv2.Sobel(a, cv2.CV_32F, dx, 1 - dx, ksize=3)) for a in (depth, inten) for dx in (1, 0)))


def _subsampled(depth: NDArray[np.float32], K: NDArray, s: int,
                cfg: TeacherConfig) -> tuple[o3d.t.geometry.Image, o3d.core.Tensor]:
    """Every ``s``-th pixel of ``depth`` (NaN outside ``[depth_min, depth_max]``) as an Open3D
    image, with its camera matrix ``K / s`` (pixel centres stay on the grid)."""
    d = np.array(depth[::s, ::s], dtype=np.float32)
    d[~((d >= cfg.depth_min) & (d <= cfg.depth_max))] = np.nan
    Ks = np.array(K, dtype=np.float64)
    Ks[:2] /= s
    return o3d.t.geometry.Image(o3d.core.Tensor(d)), o3d.core.Tensor(Ks)


def dense_maps(depth: NDArray[np.float32], K: NDArray, cfg: TeacherConfig,
               gray: NDArray[np.uint8] | None = None, surface: bool = True) -> DenseMaps:
    """The maps of :class:`DenseMaps` for one depth image (metres, 0 = invalid).

    The points moved are sparse (every 4th pixel: the cost of an iteration is proportional
    to their number), the surface they are aligned to is denser (every 2nd pixel): at 1/4
    resolution on both sides the alignment of noise-free frames was biased by ~1.5 mm
    (edges and curved surfaces are coarsely sampled), at 2 / 4 it is ~0.2 mm. Normals come
    from a Gaussian-smoothed copy of the depth (``filter_bilateral`` with a 5 m value sigma,
    which skips holes), as in Open3D's own point-to-plane odometry; Kinect noise makes
    unsmoothed normals useless.

    ``surface`` False leaves ``vertex`` and ``normal`` (the frame as the one aligned to, i:
    about two thirds of the time here) to :func:`add_surface`: a frame is i only in the
    edges of the frames after it, so ``vo-online`` builds them after handing the frame over.
    """
    img, Kt = _subsampled(depth, K, cfg.dense_scale, cfg)
    points = img.create_vertex_map(Kt, float("nan")).as_tensor()
    img, Kt = _subsampled(depth, K, cfg.dense_target_scale, cfg)
    maps = DenseMaps(points, None, None, Kt, photo_maps(gray, depth, K, cfg) if gray is not None else None)
    if surface:
        _fill_surface(maps, img, cfg)
    return maps


def add_surface(maps: DenseMaps, depth: NDArray[np.float32], K: NDArray, cfg: TeacherConfig) -> None:
    """Fill ``maps.vertex`` and ``maps.normal`` (see :func:`dense_maps`) when they are missing."""
    if maps.vertex is None:
        _fill_surface(maps, _subsampled(depth, K, cfg.dense_target_scale, cfg)[0], cfg)


def _fill_surface(maps: DenseMaps, img: o3d.t.geometry.Image, cfg: TeacherConfig) -> None:
    smooth = img.filter_bilateral(cfg.dense_normal_kernel, 5.0, 10.0)
    maps.vertex = img.create_vertex_map(maps.K, float("nan")).as_tensor()
    maps.normal = smooth.create_vertex_map(maps.K, float("nan")).create_normal_map(float("nan")).as_tensor()


def photo_maps(gray: NDArray[np.uint8], depth: NDArray[np.float32], K: NDArray, cfg: TeacherConfig) -> PhotoMaps:
    """The maps of :class:`PhotoMaps` for one frame: ``gray`` (H, W) uint8, registered to the
    depth camera (:meth:`ColourCamera.to_depth_image`), ``depth`` (H, W) metres."""
    d = np.array(depth, dtype=np.float32)
    d[~((d >= cfg.depth_min) & (d <= cfg.depth_max))] = np.nan
    inten = gray.astype(np.float32) * np.float32(1 / 255)
    if cfg.photo_normalise:  # undo the auto-exposure gain; a dark frame's contrast counts as a bright one's
        inten *= np.float32(0.5 / max(float(inten[::4, ::4].mean()), 1e-3))
    if cfg.photo_blur_px > 0:
        inten = cv2.GaussianBlur(inten, (0, 0), cfg.photo_blur_px)
    if cfg.photo_weight != 1.0:  # the kernel weighs both residuals alike: scale the grey instead
        inten *= np.float32(np.sqrt(cfg.photo_weight))
    s = cfg.dense_scale
    return PhotoMaps(_image_tensor(d[::s, ::s]), _image_tensor(inten[::s, ::s]), *_kernel_maps(d, inten),
                     o3d.core.Tensor(np.asarray(K, dtype=np.float64)))


def _photo_huber(cfg: TeacherConfig) -> float:
    """Huber threshold of the photometric residual in the units of the scaled grey maps of
    :func:`photo_maps` (``cfg.photo_huber`` times ``sqrt(cfg.photo_weight)``)."""
    return cfg.photo_huber * float(np.sqrt(cfg.photo_weight))


def _photo_pair(di: DenseMaps, dj: DenseMaps, depth_only: bool = False) -> tuple[PhotoMaps, PhotoMaps]:
    """The photometric maps of an edge's two frames for Open3D's hybrid kernel: both
    :meth:`PhotoMaps.depth_only` when ``depth_only`` or when either frame's grey is void
    (its colour shows another moment than its depth), else both as they are."""
    pi, pj = di.photo, dj.photo
    if depth_only or not (pi.grey and pj.grey):
        return pi.depth_only(), pj.depth_only()
    return pi, pj


def hybrid_align(T_init: NDArray, di: DenseMaps, dj: DenseMaps, cfg: TeacherConfig,
                 iters: int, depth_only: bool = False) -> tuple[NDArray, float, int, bool]:
    """Align frame j to frame i with Open3D's hybrid RGB-D odometry kernel (photometric and
    depth residuals, Huber-weighted Gauss-Newton; Park, Zhou & Koltun 2017) at one level:
    frame j's points of ``dj.points`` (every ``cfg.dense_scale``-th pixel) against frame i's
    full-resolution maps, from ``T_init`` (``T_i_j``), at most ``iters`` iterations,
    stopping at ``cfg.align_stop_m`` / ``cfg.align_stop_deg`` updates. Returns (T_i_j,
    fitness, iterations, converged). Raises RuntimeError when no point pairs up.
    ``depth_only``: the depth term alone (:func:`_photo_pair`)."""
    pi, pj = _photo_pair(di, dj, depth_only)
    target = (pi.depth, pi.intensity, pi.depth_dx, pi.depth_dy, pi.intensity_dx, pi.intensity_dy)
    T, fitness, n_it, converged = _hybrid_steps(pj.src_depth, pj.src_intensity, target, dj.points, pi.K,
                                                o3d.core.Tensor(np.asarray(T_init, np.float64)), iters, cfg)
    return geo.orthonormalize(T.numpy()), fitness, n_it, converged


def _small_step(delta: NDArray, stop_m: float, stop_deg: float) -> bool:
    """An iteration's update ``delta`` (4x4) moves the pose by less than ``stop_m`` and
    ``stop_deg``: ``cfg.dense_stop_m`` / ``_deg`` in the point-to-plane refinement of a keypoint
    estimate, ``cfg.align_stop_m`` / ``_deg`` in every other dense alignment."""
    return bool(np.linalg.norm(delta[:3, 3]) < stop_m and geo.rotation_angle_deg(delta) < stop_deg)


def _hybrid_steps(src_depth: o3d.core.Tensor, src_intensity: o3d.core.Tensor, target: tuple, points: o3d.core.Tensor,
                  K: o3d.core.Tensor, T: o3d.core.Tensor, iters: int,
                  cfg: TeacherConfig) -> tuple[o3d.core.Tensor, float, int, bool]:
    """At most ``iters`` Gauss-Newton iterations of Open3D's hybrid kernel from ``T``
    (``target``: :func:`_kernel_maps` of the frame aligned to), stopping at a small update
    (:func:`_small_step` at ``cfg.align_stop_m`` / ``_deg``). Returns (T, fitness, iterations,
    converged)."""
    fitness, converged, it = 0.0, False, 0
    for it in range(iters):
        step = o3d.t.pipelines.odometry.compute_odometry_result_hybrid(
            src_depth, target[0], src_intensity, target[1], *target[2:6], points, K, T, cfg.dense_trunc_m,
            cfg.dense_huber_m, _photo_huber(cfg))
        T = step.transformation.matmul(T)
        fitness = float(step.fitness)
        if _small_step(step.transformation.numpy(), cfg.align_stop_m, cfg.align_stop_deg):
            converged = True
            break
    return T, fitness, it + 1, converged


def pyramid_align(T_init: NDArray, di: DenseMaps, dj: DenseMaps, cfg: TeacherConfig,
                  coarse: bool = True, depth_only: bool = False) -> tuple[NDArray, float]:
    """Coarse-to-fine hybrid alignment of frame j to frame i from ``T_init`` (``T_i_j``):
    Open3D's hybrid kernel at the scales and iteration counts of ``cfg.fallback_levels``
    (frames at the same scale; the maps of each frame are built once and kept, so the
    frame's other edges reuse them), then :func:`hybrid_align` against frame i at full
    resolution (``cfg.fallback_finish_iters``). Returns (T_i_j, fitness). Raises
    RuntimeError when no pixel pairs up. The multi-scale function of Open3D rebuilds both
    frames' pyramids on every call; on synthetic/stress-lowfreq, where this fallback makes
    nearly every edge at every gap, that cost ~4 times the alignment itself.
    ``depth_only``: the depth term alone (:func:`_photo_pair`, which also picks it when
    either frame's grey is void), at the scales and iteration counts of ``cfg.depth_levels``
    and ``cfg.depth_finish_iters``."""
    pi, pj = _photo_pair(di, dj, depth_only)
    levels, finish = (cfg.depth_levels, cfg.depth_finish_iters) if depth_only else (cfg.fallback_levels,
                                                                                     cfg.fallback_finish_iters)
    T = o3d.core.Tensor(np.asarray(T_init, np.float64))
    for s, iters in levels if coarse else ():
        ti, tj = pi.level(s), pj.level(s)
        T, _, _, _ = _hybrid_steps(tj[0], tj[1], ti[:6], tj[6], ti[7], T, iters, cfg)
    T_h = geo.orthonormalize(T.numpy())
    T_h, fitness, _, _ = hybrid_align(T_h, di, dj, cfg, max(finish if coarse else cfg.fallback_chained_iters, 1),
                                      depth_only)
    return T_h, fitness


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


def dense_method(cfg: TeacherConfig, colour: ColourCamera | None) -> str:
    """``cfg.dense_method`` resolved for a colour camera model: ``auto`` is ``hybrid`` for a
    synchronous one (:attr:`ColourCamera.synchronous`), else ``point-to-plane``."""
    if cfg.dense_method != "auto":
        return cfg.dense_method
    return "hybrid" if colour is not None and colour.synchronous else "point-to-plane"


def extract(rgb: NDArray[np.uint8], depth: NDArray[np.float32], cfg: TeacherConfig,
            orb: cv2.ORB | None = None, K: NDArray | None = None,
            colour: ColourCamera | None = None, surface: bool = True) -> FrameFeatures:
    """ORB keypoints and descriptors of one frame, with the depth at each keypoint; with the
    camera matrix ``K`` and ``cfg.dense_iters > 0`` also the maps of the dense step (``surface``
    False: without the ones it needs as the older frame of an edge, for :func:`add_surface`
    to add before a later frame's edges). With a ``colour`` camera model (and ``K``),
    keypoints are moved into depth-camera pixels (``uv`` is then in depth-camera pixels;
    None: colour registered to depth)."""
    gray = cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY)
    dense = None
    if K is not None and cfg.dense_iters > 0:
        photo = None
        if dense_method(cfg, colour) == "hybrid":
            photo = colour.to_depth_image(gray, depth, K) if colour is not None else gray
        dense = dense_maps(depth, K, cfg, photo, surface)
    orb = orb or make_orb(cfg)
    kps, desc = orb.detectAndCompute(gray, None)
    keys = image_keys(rgb, depth)
    if not kps or desc is None:
        return FrameFeatures(np.zeros((0, 2), np.float32), np.zeros((0, 32), np.uint8),
                             np.zeros(0, np.float32), gray, depth, dense, keys)
    uv = np.array([k.pt for k in kps], dtype=np.float32)
    if colour is not None and K is not None:
        uv = colour.to_depth_pixels(uv, depth, K)
    return FrameFeatures(uv, desc, depth_at(depth, uv, cfg), gray, depth, dense, keys)


def match(fi: FrameFeatures, fj: FrameFeatures, cfg: TeacherConfig,
          T_i_j_pred: NDArray | None = None, K: NDArray | None = None) -> NDArray[np.int64]:
    """Mutual-nearest ORB matches passing the ratio test: (M, 2) index pairs (into i, into j).

    Only keypoints of frame i with a valid depth take part. With a motion prediction
    ``T_i_j_pred`` (and ``K``), each is compared only with the keypoints of frame j within
    ``cfg.search_radius_px`` of its predicted position (guided matching, as ORB-SLAM's
    search by projection); without one, with all of them.
    """
    src = np.flatnonzero(fi.z > 0)
    if len(src) < 2 or len(fj.desc) < 2:
        return np.zeros((0, 2), np.int64)
    if T_i_j_pred is None:
        return _match_exhaustive(fi, fj, src, cfg)
    P = _backproject(np.take(fi.uv, src, axis=0), fi.z[src], K)
    Tji = geo.inv_T(T_i_j_pred)
    Y = P @ Tji[:3, :3].T + Tji[:3, 3]
    front = Y[:, 2] > 1e-3
    src = src[front]
    pred = _project(np.compress(front, Y, axis=0), K)
    near = cKDTree(pred).sparse_distance_matrix(fj.tree(), cfg.search_radius_px, output_type="ndarray")
    if len(near) == 0:
        return np.zeros((0, 2), np.int64)
    qi, cj = src[near["i"]], near["j"].astype(np.int64)
    x = np.take(fi.desc64, qi, axis=0)  # np.take: 4 times faster than fancy indexing here
    x ^= np.take(fj.desc64, cj, axis=0)
    d = np.add.reduce(np.bitwise_count(x), axis=1, dtype=np.int64)
    # best and second best in j for each i (one sort on the key (i, distance); d < 512)
    o = _stable_argsort((qi << 9) | d)
    qi_s, cj_s, d_s = qi[o], cj[o], d[o]
    first = np.flatnonzero(np.r_[True, qi_s[1:] != qi_s[:-1]])
    has2 = np.r_[first[1:], len(qi_s)] - first >= 2
    second = np.where(has2, d_s[np.minimum(first + 1, len(d_s) - 1)], 256)
    best_i, best_j, best_d = qi_s[first], cj_s[first], d_s[first]
    ok = (best_d <= cfg.max_hamming) & (best_d < cfg.ratio * second)
    # mutual check: the best i for each j among the compared pairs
    o2 = _stable_argsort((cj << 9) | d)
    cj2, qi2 = cj[o2], qi[o2]
    first2 = np.flatnonzero(np.r_[True, cj2[1:] != cj2[:-1]])
    back = np.full(len(fj.desc), -1, np.int64)
    back[cj2[first2]] = qi2[first2]
    ok &= back[best_j] == best_i
    return np.stack([best_i[ok], best_j[ok]], axis=1)


def _stable_argsort(key: NDArray[np.int64]) -> NDArray[np.int64]:
    """``np.argsort(key, kind="stable")`` for non-negative int64 keys, as an unstable sort of
    keys made unique by their position in the low bits (the same order: ties keep their
    order). NumPy sorts int64 with timsort when stable and with a SIMD quicksort otherwise:
    on guided matching's ~9,000 candidates 0.3 instead of 0.5-2.7 ms."""
    n = len(key)
    bits = max(n.bit_length(), 1)
    if n == 0 or int(key.max()) >= 1 << (62 - bits):
        return np.argsort(key, kind="stable")
    return np.argsort((key << bits) | np.arange(n, dtype=np.int64))


def match_wide(fi: FrameFeatures, fj: FrameFeatures, cfg: TeacherConfig,
               T_i_j_pred: NDArray | None = None, K: NDArray | None = None) -> NDArray[np.int64]:
    """Fallback matching (``cfg.fallback_wide``): cross-checked nearest neighbours (each the
    other's best) within ``cfg.max_hamming``, without the ratio test. With a motion prediction,
    candidates lie within ``cfg.fallback_radius_scale * cfg.search_radius_px`` of the predicted
    position; without one, all keypoints of frame j (OpenCV's brute-force cross-check).
    Repeated or low-contrast texture gives close best and second-best distances, which the
    ratio test discards; RANSAC then sorts the right matches from the wrong ones."""
    src = np.flatnonzero(fi.z > 0)
    if len(src) < 2 or len(fj.desc) < 2:
        return np.zeros((0, 2), np.int64)
    if T_i_j_pred is None:
        ms = cv2.BFMatcher(cv2.NORM_HAMMING, crossCheck=True).match(fi.desc[src], fj.desc)
        p = np.array([(src[m.queryIdx], m.trainIdx) for m in ms if m.distance <= cfg.max_hamming],
                     np.int64).reshape(-1, 2)
        return p
    P = _backproject(fi.uv[src], fi.z[src], K)
    Tji = geo.inv_T(T_i_j_pred)
    Y = P @ Tji[:3, :3].T + Tji[:3, 3]
    src = src[Y[:, 2] > 1e-3]
    pred = _project(Y[Y[:, 2] > 1e-3], K)
    near = cKDTree(pred).sparse_distance_matrix(fj.tree(), cfg.fallback_radius_scale * cfg.search_radius_px,
                                                output_type="ndarray")
    if len(near) == 0:
        return np.zeros((0, 2), np.int64)
    qi, cj = src[near["i"]], near["j"].astype(np.int64)
    d = np.bitwise_count(fi.desc64[qi] ^ fj.desc64[cj]).sum(axis=1, dtype=np.int64)
    o = np.argsort((qi << 9) | d, kind="stable")  # best j of each i
    first = np.flatnonzero(np.r_[True, qi[o][1:] != qi[o][:-1]])
    best_i, best_j, best_d = qi[o][first], cj[o][first], d[o][first]
    o2 = np.argsort((cj << 9) | d, kind="stable")  # best i of each j
    first2 = np.flatnonzero(np.r_[True, cj[o2][1:] != cj[o2][:-1]])
    back = np.full(len(fj.desc), -1, np.int64)
    back[cj[o2][first2]] = qi[o2][first2]
    ok = (best_d <= cfg.max_hamming) & (back[best_j] == best_i)
    return np.stack([best_i[ok], best_j[ok]], axis=1)


def _match_exhaustive(fi: FrameFeatures, fj: FrameFeatures, src: NDArray[np.int64],
                      cfg: TeacherConfig) -> NDArray[np.int64]:
    """Brute-force mutual-nearest + ratio-test matching of keypoints ``src`` of frame i."""
    bf = cv2.BFMatcher(cv2.NORM_HAMMING)
    di = fi.desc[src]
    fwd = bf.knnMatch(di, fj.desc, k=2)
    back = np.full(len(fj.desc), -1, np.int64)
    for m in bf.match(fj.desc, di):
        back[m.queryIdx] = m.trainIdx
    pairs = [(a.queryIdx, a.trainIdx) for a, b in (ms for ms in fwd if len(ms) == 2)
             if a.distance <= cfg.max_hamming and a.distance < cfg.ratio * b.distance
             and back[a.trainIdx] == a.queryIdx]
    p = np.array(pairs, dtype=np.int64).reshape(-1, 2)
    p[:, 0] = src[p[:, 0]]
    return p


@dataclass
class EdgeEstimate:
    """Result of one pair. ``status`` is ``ok`` or the reason of failure."""

    i: int
    j: int
    status: str
    T_i_j: NDArray[np.float64] | None = None
    cov: NDArray[np.float64] | None = None
    matches: int = 0
    inliers: int = 0
    inlier_ratio: float = 0.0
    rmse_px: float = float("nan")
    info: dict = field(default_factory=dict)
    inlier_pairs: NDArray[np.int64] | None = None
    """(M, 2) keypoint indices (in i, in j) of the inlier correspondences."""

    @property
    def ok(self) -> bool:
        return self.status == "ok"


def _backproject(uv: NDArray, z: NDArray, K: NDArray) -> NDArray[np.float64]:
    x = (uv[:, 0] - K[0, 2]) / K[0, 0] * z
    y = (uv[:, 1] - K[1, 2]) / K[1, 1] * z
    return np.stack([x, y, z], axis=1).astype(np.float64)


def _project(X: NDArray, K: NDArray) -> NDArray[np.float64]:
    z = X[:, 2]
    return np.stack([K[0, 0] * X[:, 0] / z + K[0, 2], K[1, 1] * X[:, 1] / z + K[1, 2]], axis=1)


def _moved(fi: FrameFeatures, fj: FrameFeatures, dt: float) -> bool:
    """Whether the edge's depth maps were taken at other moments than its colour images."""
    return (fi.depth_offset != 0.0 or fj.depth_offset != 0.0) and dt > 0


def _depth_moments(T: NDArray, fi: FrameFeatures, fj: FrameFeatures, dt: float) -> NDArray:
    """``T_i_j`` between the frames' colour moments, ``dt`` seconds apart -> between their
    depth moments (``depth_offset`` later each): ``C_i^-1 T C_j``, ``C = exp(o xi)`` for
    the constant velocity ``xi = log(T) / dt`` of the motion itself (unchanged without
    offsets)."""
    if not _moved(fi, fj, dt):
        return T
    xi = geo.se3_log(T) / dt
    return geo.se3_exp(-fi.depth_offset * xi) @ T @ geo.se3_exp(fj.depth_offset * xi)


def _depth_span(fi: FrameFeatures, fj: FrameFeatures, dt: float) -> float:
    """Seconds between the edge's depth moments (its colour moments are ``dt`` apart);
    ``dt`` where that is under a quarter of it."""
    span = dt + fj.depth_offset - fi.depth_offset
    return span if span > dt / 4 else dt


def _to_colour_moments(res: EdgeEstimate, fi: FrameFeatures, fj: FrameFeatures, dt: float) -> EdgeEstimate:
    """An estimate between the frames' depth moments (a dense alignment) -> between their
    colour moments, ``dt`` seconds apart, in place: ``T = C_i T_d C_j^-1``, ``C = exp(o xi)``
    at the constant velocity of the result itself, ``xi = log(T_d) / (dt + o_j - o_i)`` (the
    depth moments' time apart; ``dt`` where that is under a quarter of it). The velocity is
    the edge's own: neither an earlier motion's lag nor its noise enters. The covariance is
    moved with ``C_j`` and scaled by the ratio of the two time spans (first order)."""
    if not _moved(fi, fj, dt) or res.T_i_j is None:
        return res
    span = _depth_span(fi, fj, dt)
    xi = geo.se3_log(res.T_i_j) / span
    C_j = geo.se3_exp(fj.depth_offset * xi)
    res.T_i_j = geo.orthonormalize(geo.se3_exp(fi.depth_offset * xi) @ res.T_i_j @ geo.inv_T(C_j))
    if res.cov is not None:
        Ad = geo.adjoint(C_j)
        res.cov = (dt / span) ** 2 * (Ad @ res.cov @ Ad.T)
    return res


def _cov_to_depth_moments(cov: NDArray | None, T: NDArray, fi: FrameFeatures, fj: FrameFeatures,
                          dt: float) -> NDArray | None:
    """The covariance of ``T`` (between colour moments) as one of :func:`_depth_moments`'s
    result (the inverse of :func:`_to_colour_moments`'s, first order)."""
    if cov is None or not _moved(fi, fj, dt):
        return cov
    span = _depth_span(fi, fj, dt)
    Ad = geo.adjoint(geo.se3_exp(-fj.depth_offset * geo.se3_log(T) / dt))
    return (span / dt) ** 2 * (Ad @ cov @ Ad.T)


def _residuals(T: NDArray, P_i: NDArray, uv_j: NDArray, Q_j: NDArray, uv_i: NDArray, K: NDArray,
               with_jac: bool, P_b: NDArray | None = None, w3: float = 0.0) -> tuple[NDArray, NDArray | None]:
    """Two-way reprojection residuals of ``T = T_i_j`` and their Jacobians w.r.t. a right
    perturbation ``T @ exp(delta)``, delta = (v, w).

    Forward: points ``P_i`` (frame i) projected into j vs ``uv_j``. Backward: points ``Q_j``
    (frame j) projected into i vs ``uv_i``. With ``w3 > 0`` also the 3-D term of
    :func:`refine_two_way` (``Q_j`` moved into i vs ``P_b``). Returns r (2F+2B[+3B],) ordered
    (u, v) per point, then (x, y, z) per point, and J (len(r), 6); points behind a camera
    are dropped. The Jacobian rows are written out in closed form (this function is most of
    the teacher's refinement time: a few whole-array operations, no (N, 2, 3) products).
    """
    R, t = T[:3, :3], T[:3, 3]
    Y = (P_i - t) @ R
    X = Q_j @ R.T + t
    front_f, front_b = Y[:, 2] > 1e-6, X[:, 2] > 1e-6
    if not (front_f.all() and front_b.all()):
        Y, uv_j, X, Q_j, uv_i = Y[front_f], uv_j[front_f], X[front_b], Q_j[front_b], uv_i[front_b]
        if w3 > 0:
            P_b = P_b[front_b]
    F, B = len(Y), len(X)
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    n3 = 3 * B if w3 > 0 else 0
    r = np.empty(2 * F + 2 * B + n3)
    # the points' coordinates as contiguous rows (x, y, z): whole-row operations, not
    # strided columns (the same arithmetic, element by element)
    Yt, Xt = Y.T.copy(), X.T.copy()
    izf = 1.0 / Yt[2]
    xf, yf = Yt[0] * izf, Yt[1] * izf  # normalised coordinates
    rf = r[:2 * F].reshape(F, 2)
    uvt = uv_j.T
    rf[:, 0] = fx * xf + cx - uvt[0]
    rf[:, 1] = fy * yf + cy - uvt[1]
    izb = 1.0 / Xt[2]
    xb, yb = Xt[0] * izb, Xt[1] * izb
    rb = r[2 * F:2 * F + 2 * B].reshape(B, 2)
    uvt = uv_i.T
    rb[:, 0] = fx * xb + cx - uvt[0]
    rb[:, 1] = fy * yb + cy - uvt[1]
    if w3 > 0:
        s3 = w3 / (P_b[:, 2] ** 2)  # Kinect depth noise grows with z^2
        r[2 * F + 2 * B:] = ((X - P_b) * s3[:, None]).ravel()
    if not with_jac:
        return r, None
    J = np.empty((len(r), 6))
    # forward, right perturbation: Y(delta) = exp(-delta) Y -> dY = [-I | hat(Y)]; the rows
    # (u, v) of each point built as (2, 6, F) contiguous rows, then moved into place
    Gf = np.empty((2, 6, F))
    a, b = fx * izf, fy * izf
    Gf[0, 0] = -a
    Gf[0, 1] = 0.0
    Gf[0, 2] = a * xf
    Gf[0, 3] = fx * xf * yf
    Gf[0, 4] = -fx * (1.0 + xf * xf)
    Gf[0, 5] = fx * yf
    Gf[1, 0] = 0.0
    Gf[1, 1] = -b
    Gf[1, 2] = b * yf
    Gf[1, 3] = fy * (1.0 + yf * yf)
    Gf[1, 4] = -fy * xf * yf
    Gf[1, 5] = -fy * xf
    J[:2 * F].reshape(F, 2, 6)[:] = Gf.transpose(2, 0, 1)
    # backward: X(delta) = R exp(delta) Q + t -> dX = R [I | -hat(Q)]; rows b = A R,
    # [b | -b hat(Q)] = [b | Q x b]
    Gb = np.empty((2, 6, B))
    Qt = Q_j.T.copy()
    for k, (fk, nk) in enumerate(((fx * izb, xb), (fy * izb, yb))):
        bb = Gb[k]
        for c in range(3):
            np.multiply(fk, R[k, c] - nk * R[2, c], out=bb[c])
        bb[3] = Qt[1] * bb[2] - Qt[2] * bb[1]
        bb[4] = Qt[2] * bb[0] - Qt[0] * bb[2]
        bb[5] = Qt[0] * bb[1] - Qt[1] * bb[0]
    J[2 * F:2 * F + 2 * B].reshape(B, 2, 6)[:] = Gb.transpose(2, 0, 1)
    if w3 > 0:
        # X(delta) - P_b, dX = R [I | -hat(Q)] = [R | -hat(R Q) R]
        J3 = J[2 * F + 2 * B:].reshape(B, 3, 6)
        J3[:, :, :3] = R
        q = Q_j @ R.T
        J3[:, 0, 3:] = q[:, 2:3] * R[1] - q[:, 1:2] * R[2]
        J3[:, 1, 3:] = q[:, 0:1] * R[2] - q[:, 2:3] * R[0]
        J3[:, 2, 3:] = q[:, 1:2] * R[0] - q[:, 0:1] * R[1]
        J3 *= s3[:, None, None]
    return r, J


def refine_two_way(T0: NDArray, P_i: NDArray, uv_j: NDArray, Q_j: NDArray, uv_i: NDArray, K: NDArray,
                   huber: float, iters: int = 10, min_sigma_px: float = 0.0, P_b: NDArray | None = None,
                   w3: float = 0.0) -> tuple[NDArray, NDArray, NDArray]:
    """Minimise the Huber cost of the two-way reprojection error, plus (``w3 > 0``) the
    z^2-weighted 3-D distance between the backward points ``Q_j`` moved into frame i and
    their frame-i counterparts ``P_b``. Returns (T_i_j, covariance (6, 6) in (v, w) order,
    final residual vector).

    Newton steps on the Huber cost with Levenberg damping: gradient ``J^T psi(r)``,
    curvature ``J^T diag(rho''(r)) J`` (residuals in the quadratic zone only). Unlike
    iteratively reweighted least squares (curvature ``J^T diag(psi(r)/r) J``), which converges
    linearly when many residuals lie in the linear zone (on redkitchen it still moved the
    pose by ~0.1 mm after 5 steps), this converges in 3-4 steps; it stops when a step moves
    the pose by less than 0.3 mm / 0.3 mrad. The reweighted curvature (larger: a majoriser
    of the Huber cost) is used when too few residuals lie in the quadratic zone to fix all
    six directions, and for the retry after a rejected Newton step: far from the optimum
    the quadratic-zone curvature is too small and its steps overshoot.

    The covariance is ``sigma^2 (J^T W J)^-1``, W the Huber weights ``psi(r)/r`` at the
    solution and ``sigma^2`` the weighted residual variance, floored at ``min_sigma_px^2``."""
    T = T0.copy()
    lam = 1e-4
    r, J = _residuals(T, P_i, uv_j, Q_j, uv_i, K, True, P_b, w3)
    cost, w, quad = _huber(r, huber)
    newton = True
    for _ in range(iters):
        Jq = np.compress(quad, J, axis=0) if newton and quad.sum() >= 12 else J * np.sqrt(w)[:, None]
        H = Jq.T @ Jq
        g = J.T @ (w * r)  # psi(r) = w r
        step = -np.linalg.solve(H + lam * np.diag(np.diag(H)) + 1e-12 * np.eye(6), g)
        T_new = T @ geo.se3_exp(step)
        r_new, J_new = _residuals(T_new, P_i, uv_j, Q_j, uv_i, K, True, P_b, w3)
        c_new, w_new, quad_new = _huber(r_new, huber)
        if c_new <= cost and len(r_new) == len(r):
            T, r, J, cost, w, quad = T_new, r_new, J_new, c_new, w_new, quad_new
            lam = max(lam / 10, 1e-7)
            newton = True
            if np.linalg.norm(step) < 3e-4:  # 0.3 mm / 0.3 mrad, far below the label noise
                break
        elif newton:  # far from the optimum the quadratic-zone curvature is too small:
            newton = False  # retry with the reweighted one (a majoriser of the Huber cost)
        else:
            lam *= 10
            if lam > 1e4:
                break
    H = J.T @ (J * w[:, None])
    dof = max(len(r) - 6, 1)
    sigma2 = max(float(np.sum(w * r * r) / dof), min_sigma_px ** 2)
    cov = sigma2 * np.linalg.inv(H)
    return geo.orthonormalize(T), 0.5 * (cov + cov.T), r


def _huber(r: NDArray, k: float) -> tuple[float, NDArray, NDArray]:
    """Huber cost of the residuals ``r`` (threshold ``k``), the IRLS weights ``psi(r)/r`` and
    the mask of residuals in the quadratic zone."""
    a = np.abs(r)
    quad = a <= k
    cost = float(np.sum(np.where(quad, 0.5 * a * a, k * (a - 0.5 * k))))
    return cost, np.where(quad, 1.0, k / np.maximum(a, 1e-12)), quad


def _to_middle_row(X: NDArray, rows: NDArray, height: int, xi: NDArray, readout_s: float) -> NDArray:
    """Points ``X`` (..., 3) seen by the image rows ``rows`` (...,) of a rolling-shutter frame,
    moved to the frame's middle-row moment, to first order: ``X + s (w x X + v)``, ``s`` the
    row's time after the middle row's, ``xi = (v, w)`` the camera's body velocity (per s)."""
    s = ((np.asarray(rows, np.float64) / (height - 1) - 0.5) * readout_s).astype(X.dtype)[..., None]
    v, w = (float(a) for a in xi[:3]), (float(a) for a in xi[3:])
    (vx, vy, vz), (wx, wy, wz) = v, w
    x, y, z = X[..., 0], X[..., 1], X[..., 2]
    # w x X + v, written out (np.cross copies its operands into its own layout)
    m = np.stack([wy * z - wz * y + vx, wz * x - wx * z + vy, wx * y - wy * x + vz], axis=-1)
    return X + s * m


def map_to_middle_row(maps: o3d.core.Tensor, row_step: int, height: int, xi: NDArray,
                      readout_s: float) -> o3d.core.Tensor:
    """A vertex map (h, w, 3) of every ``row_step``-th row of a ``height``-row image, each
    point moved to the middle row's moment (:func:`_to_middle_row`)."""
    X = maps.numpy()
    rows = (np.arange(X.shape[0]) * row_step)[:, None]
    return o3d.core.Tensor(np.ascontiguousarray(_to_middle_row(X, rows, height, xi, readout_s)))


def rolling_shutter_views(fi: FrameFeatures, fj: FrameFeatures, intr: Intrinsics,
                          cfg: TeacherConfig) -> tuple | None:
    """For an edge (i, j) with ``cfg.rolling_shutter_s``: frame i's keypoints (pixels, depths)
    and dense maps moved to its middle row's moment at ``fi.velocity_out``, frame j's at
    ``fj.velocity_in`` (:func:`_to_middle_row`; each frame's are built once per role and
    kept). Returns ``((uv_i, z_i), (uv_j, z_j), dense_i, dense_j)``; None without the
    correction (off, or a velocity unknown). Keypoints without depth keep their pixel; the
    dense maps keep their normals and carry no photometric maps, so with ``hybrid_all_gaps``
    such an edge skips the hybrid stage (gap-1 edges, the only ones it runs on by default,
    are never corrected)."""
    if not cfg.rolling_shutter_s or fi.velocity_out is None or fj.velocity_in is None:
        return None  # off, auto not resolved (teacher.generate.rolling_shutter_for), or a velocity unknown
    (kp_i, dense_i), (kp_j, dense_j) = _rolling_view(fi, "out", intr, cfg), _rolling_view(fj, "in", intr, cfg)
    return kp_i, kp_j, dense_i, dense_j


def _rolling_view(f: FrameFeatures, role: str, intr: Intrinsics, cfg: TeacherConfig) -> tuple:
    """``((uv, z), dense)`` of :func:`rolling_shutter_views` for frame ``f`` as an edge's
    older (``out``) or newer (``in``) frame."""
    if role not in f._rolling:
        xi = f.velocity_out if role == "out" else f.velocity_in
        K, h = intr.K, intr.height
        uv, z = f.uv.astype(np.float64), f.z.astype(np.float64)
        ok = z > 0
        X = _to_middle_row(_backproject(uv[ok], z[ok], K), uv[ok, 1], h, xi, cfg.rolling_shutter_s)
        uv, z = uv.copy(), z.copy()
        uv[ok], z[ok] = _project(X, K), X[:, 2]
        dense, d = None, f.dense
        if d is not None and role == "out" and d.vertex is not None:  # the frame aligned to
            vertex = map_to_middle_row(d.vertex, cfg.dense_target_scale, h, xi, cfg.rolling_shutter_s)
            dense = DenseMaps(d.points, vertex, d.normal, d.K)
        elif d is not None and role == "in":  # the frame moved
            dense = DenseMaps(map_to_middle_row(d.points, cfg.dense_scale, h, xi, cfg.rolling_shutter_s), d.vertex,
                              d.normal, d.K)
        f._rolling[role] = ((uv, z), dense)
    return f._rolling[role]


def estimate_edge(i: int, j: int, fi: FrameFeatures, fj: FrameFeatures, intr: Intrinsics,
                  cfg: TeacherConfig, dt: float, T_pred: NDArray | None = None,
                  tracks: NDArray[np.int64] | None = None, dense: bool = True,
                  T_alt: NDArray | None = None, span: float | None = None) -> EdgeEstimate:
    """Estimate ``T_i_j`` between two frames (ids ``i``, ``j``, ``dt`` seconds apart).

    ``dt`` bounds the keypoint estimates' plausibility tests (``cfg.max_speed`` /
    ``cfg.max_angular_speed_deg``), ``span`` (default ``dt``) the dense alignments' (the
    ``depth``, ``rgbd`` and ``dense`` paths): the most seconds the motion can span, from the
    earliest moment frame i's images show (before its timestamp when one of them repeats an
    earlier frame's) to frame j's timestamp. The keypoint estimates keep the timestamps'
    bound: on synthetic/stress-repetitive two guided estimates out of repeated frames, aliases
    of the texture 91 and 94 mm off, passed the span's bound, which the timestamps' refused
    (the exhaustive matching then found them 2.2-2.3 mm off).

    Correspondences come from ``tracks`` ((M, 2) keypoint index pairs chained along the
    gap-1 matches) when given and numerous enough, else from matching: guided by the motion
    prediction ``T_pred`` when given, exhaustive otherwise or when the guided estimate fails.
    When none passes, the fallback chain (``cfg.fallback_*``); a good estimate gets the dense
    step (:func:`dense_refine`) unless ``dense`` is False, and with photometric maps, when its
    depth stage moved it too far (:func:`_dense_disagrees`), the rgbd fallback from ``T_pred``
    replaces it. ``T_alt``: a second start of the rgbd fallback (and of that replacement) of a
    gap-1 edge (``cfg.fallback_span_start``) when it differs from ``T_pred``; of the two
    results that pass its checks, the one that pairs more pixels (fitness) is taken
    (:func:`_rgbd_starts`).

    ``T_pred``, ``T_alt`` and the result are motions between the frames' colour moments. Where
    a frame's depth was taken at another moment (``depth_offset``, see :class:`FrameFeatures`),
    the dense steps and fallbacks, which align depth maps, start from the motion between the
    depth moments and their results are moved back, both at the constant velocity of the
    edge's own motion (:func:`_depth_moments`, :func:`_to_colour_moments`). The keypoints
    keep the depth read at their pixels: moving them to the colour moment too (by the last
    gap-1 motion's velocity, or by the PnP estimate's) made synthetic/lab's gap-1 labels
    at most 4 % better and its trajectory worse (``depth_time_compensation``).
    """
    span = dt if span is None else span
    rolling = rolling_shutter_views(fi, fj, intr, cfg) if not cfg.subpixel else None
    attempts = []
    if tracks is not None and len(tracks) >= cfg.min_matches:
        attempts.append(("tracks", tracks, None))
    if T_pred is not None:
        attempts.append(("guided", None, T_pred))
    attempts.append(("exhaustive", None, None))
    if cfg.fallback_wide:
        if T_pred is not None:
            attempts.append(("wide", None, T_pred))
        attempts.append(("crosscheck", None, None))
    best: EdgeEstimate | None = None
    for source, pairs, pred in attempts:
        if pairs is None:
            if source in ("wide", "crosscheck"):
                pairs = match_wide(fi, fj, cfg, pred, intr.K)
            else:
                pairs = match(fi, fj, cfg, pred, intr.K)
        res = _estimate(i, j, fi, fj, intr, cfg, dt, pairs, rolling)
        res.info["source"] = source
        if best is None or res.inliers > best.inliers or res.ok:
            best = res
        if res.ok:
            break
    best.info["path"] = best.info["source"] if best.ok else "none"
    # the dense alignments' starts, between the depth moments
    T0 = _depth_moments(np.eye(4) if T_pred is None else T_pred, fi, fj, dt)
    alt = None if tracks is not None or T_alt is None else _depth_moments(T_alt, fi, fj, dt)
    if (tracks is None and cfg.depth_beside_colour_repeat and beside_colour_repeat(fi, fj)
            and fi.dense is not None and fj.dense is not None
            and fi.dense.photo is not None and fj.dense.photo is not None):
        # a gap-1 edge beside a frame whose colour shows an earlier moment than its depth:
        # neither its keypoints nor its grey belong to its depth; the depth term alone (a
        # repeated depth map is left to the keypoints: the same image, the identity)
        depth = _to_colour_moments(rgbd_edge(i, j, fi, fj, intr, cfg, span, T0, depth_only=True), fi, fj, dt)
        if depth.ok:
            depth.info["path"], depth.info["sparse_status"] = "depth", best.status
            depth.info["dense"]["stale_stream"] = fi.stale or fj.stale
            depth.inlier_pairs = best.inlier_pairs if best.ok else None  # the feature tracks go on
            return depth
        best.info["depth_step"] = depth.status
    if not best.ok and cfg.fallback_dense and fi.dense is not None and fj.dense is not None:
        if cfg.fallback_rgbd:
            rgbd = _to_colour_moments(_rgbd_starts(i, j, fi, fj, intr, cfg, span, T0, alt,
                                                   chained=tracks is not None and T_pred is not None), fi, fj, dt)
            rgbd.info["sparse_status"] = best.status
            if rgbd.ok:
                return rgbd
            best.info["rgbd_fallback"] = rgbd.status
        depth_only = _to_colour_moments(dense_edge(i, j, fi.dense, fj.dense, cfg, span, T0), fi, fj, dt)
        depth_only.info["sparse_status"] = best.status
        if depth_only.ok:
            return depth_only
        best.info["dense_fallback"] = depth_only.status
    if dense and best.ok and fi.dense is not None and fj.dense is not None:
        stale = fi.stale or fj.stale
        moved = _moved(fi, fj, dt)
        if moved:  # the dense step aligns the depth maps: between their moments
            best.cov = _cov_to_depth_moments(best.cov, best.T_i_j, fi, fj, dt)
            best.T_i_j = _depth_moments(best.T_i_j, fi, fj, dt)
        di, dj = (rolling[2], rolling[3]) if rolling is not None and rolling[2] is not None \
            and rolling[3] is not None else (fi.dense, fj.dense)
        dense_refine(best, di, dj, cfg, blend=1.0 if stale and cfg.dense_on_stale else None,
                     hybrid=tracks is None or cfg.hybrid_all_gaps)
        if moved:
            _to_colour_moments(best, fi, fj, dt)
        if "dense" in best.info:
            best.info["dense"]["stale_stream"] = stale
        if (cfg.fallback_rgbd and T_pred is not None and _dense_disagrees(best.info.get("dense", {}), cfg)
                and fi.dense.photo is not None and fj.dense.photo is not None):
            # the depth, started at the keypoints' estimate, moved too far from it: the
            # keypoints may agree on a wrong motion; the rgbd fallback from the prediction
            rgbd = _to_colour_moments(_rgbd_starts(i, j, fi, fj, intr, cfg, span, T0, alt, chained=tracks is not None),
                                      fi, fj, dt)
            if rgbd.ok:
                rgbd.info["sparse_status"] = "dense_disagrees"
                return rgbd
    return best


def _rgbd_starts(i: int, j: int, fi: FrameFeatures, fj: FrameFeatures, intr: Intrinsics, cfg: TeacherConfig,
                 dt: float, T0: NDArray, T_alt: NDArray | None, chained: bool) -> EdgeEstimate:
    """:func:`rgbd_edge` from ``T0`` and, when given and different, from ``T_alt`` too: of
    the results that pass the checks, the one whose alignment paired more pixels (fitness;
    ``info["start"]`` ``span`` when ``T_alt``'s); the first's result when neither passes. A
    start far from the motion can end in a wrong minimum that still passes the checks (on
    synthetic/stress-fast 116 mm off at fitness 0.60, the right one 0.70)."""
    rgbd = rgbd_edge(i, j, fi, fj, intr, cfg, dt, T0, chained=chained)
    if T_alt is not None and not np.allclose(T_alt, T0, rtol=0.0, atol=1e-9):
        alt = rgbd_edge(i, j, fi, fj, intr, cfg, dt, T_alt, chained=chained)
        if alt.ok and (not rgbd.ok or alt.info["dense"]["fitness"] > rgbd.info["dense"]["fitness"]):
            alt.info["start"] = "span"
            return alt
    return rgbd


def _dense_disagrees(d: dict, cfg: TeacherConfig) -> bool:
    """The depth stage of :func:`dense_refine` (``d`` = ``info["dense"]``) paired enough
    pixels but was rejected for moving the pose farther than ``cfg.dense_max_shift_m`` /
    ``cfg.dense_max_shift_deg`` from the sparse estimate."""
    return (bool(d) and not d.get("accepted", True) and d.get("fitness", 0.0) >= cfg.dense_min_fitness
            and (d.get("shift_m", 0.0) > cfg.dense_max_shift_m or d.get("shift_deg", 0.0) > cfg.dense_max_shift_deg))


def dense_refine(res: EdgeEstimate, di: DenseMaps, dj: DenseMaps, cfg: TeacherConfig,
                 blend: float | None = None, hybrid: bool = True) -> None:
    """Align the depth of frame j to that of frame i, point to plane, started at the sparse
    estimate ``res.T_i_j``, and keep the result if it is plausible (in place).

    Open3D's projective ICP kernel (KinectFusion): each valid vertex of j, moved by the
    current ``T_i_j`` and projected into i, is paired with i's vertex at that pixel; pairs
    farther apart than ``dense_trunc_m`` are dropped, the others enter a Huber-weighted
    point-to-plane Gauss-Newton step. Why: the sparse estimate rests on colour keypoints, and
    7-Scenes-like sensors expose colour and depth at slightly different times, while depth
    is what the ground truth (KinectFusion) follows; on redkitchen the depth alignment alone
    lowers the gap-1 error from 5.6 to about 3.8 mm. It is rejected (the sparse estimate
    stays) when too few pixels pair up (``dense_min_fitness``) or when it moves the pose
    farther from the sparse estimate than ``dense_max_shift_m`` / ``dense_max_shift_deg``
    (a sliding or diverging alignment, e.g. on one plane). ``res.info["dense"]`` records
    the outcome.
    The edge's pose then moves ``cfg.dense_blend`` of the way from the sparse to the dense
    estimate: the depth alignment is locally better on real data but drifts (see the
    config field); ``blend`` overrides it (1 for a frame whose colour and depth were taken
    at different times, see ``cfg.dense_on_stale``). The covariance stays the sparse
    refinement's.

    With photometric maps on both frames (``cfg.dense_method`` hybrid) and ``hybrid``, the
    hybrid stage follows (:func:`hybrid_align`), information-fused with the estimate so far.
    On a stale pair too when ``cfg.hybrid_on_stale``: the caller (:class:`teacher.window.EdgeWindow`)
    gives a frame whose depth repeats the previous frame's that frame's photometric maps
    (the colour taken with that depth) and a frame whose colour repeats none, so maps that
    exist match their depth; the prior is then the depth stage's own covariance (times
    ``cfg.dense_cov_scale``), as the sparse estimate was dropped.
    """
    if cfg.dense_iters <= 0:
        return
    # a stale pair's keypoints show another moment than its depth: depth alone there, then
    # the hybrid stage where both frames' photometric maps match their depth (see above)
    hybrid = (hybrid and di.photo is not None and dj.photo is not None and di.photo.grey and dj.photo.grey
              and (blend is None or cfg.hybrid_on_stale))
    cov = _dense_stage(res, di, dj, cfg, blend, False, res.cov)
    if hybrid and blend is not None:
        # the sparse estimate was dropped: the depth stage's own covariance is the prior
        cov, _, _ = point_to_plane_covariance(res.T_i_j, di, dj, cfg, stride=cfg.dense_cov_stride)
        if cov is None:
            return
        cov = cov * cfg.dense_cov_scale
    if hybrid:
        _dense_stage(res, di, dj, cfg, None, True, cov)


def _dense_stage(res: EdgeEstimate, di: DenseMaps, dj: DenseMaps, cfg: TeacherConfig, blend: float | None,
                 hybrid: bool, cov_prior: NDArray | None) -> NDArray | None:
    """One dense stage of :func:`dense_refine` (point-to-plane, or ``hybrid``), started at
    ``res.T_i_j``, fused with it (prior covariance ``cov_prior``) in place; records the
    outcome in ``res.info["dense"]`` (``["dense"]["hybrid"]`` for the hybrid stage).
    Returns the covariance of the fused estimate (information fusion; else ``cov_prior``)."""
    T = o3d.core.Tensor(res.T_i_j)
    fitness, rmse = 0.0, float("nan")
    try:
        if hybrid:
            T_h, fitness, n_it, _ = hybrid_align(res.T_i_j, di, dj, cfg, cfg.hybrid_iters)
            T = o3d.core.Tensor(T_h)
        for it in range(0 if hybrid else cfg.dense_iters):
            step = o3d.t.pipelines.odometry.compute_odometry_result_point_to_plane(
                dj.points, di.vertex, di.normal, di.K, T, cfg.dense_trunc_m, cfg.dense_huber_m)
            T = step.transformation.matmul(T)
            fitness, rmse = float(step.fitness), float(step.inlier_rmse)
            if _small_step(step.transformation.numpy(), cfg.dense_stop_m, cfg.dense_stop_deg):
                break
    except RuntimeError:  # Open3D raises when no pixel pairs up
        out = {"accepted": False, "fitness": 0.0}
        if hybrid:
            res.info.setdefault("dense", {})["hybrid"] = out
        else:
            res.info["dense"] = out
        return cov_prior
    if hybrid:
        it = n_it - 1
    T_d = T.numpy()
    d = geo.inv_T(res.T_i_j) @ T_d
    shift_m, shift_deg = float(np.linalg.norm(d[:3, 3])), geo.rotation_angle_deg(d)
    ok = (np.all(np.isfinite(T_d)) and fitness >= cfg.dense_min_fitness
          and shift_m <= cfg.dense_max_shift_m and shift_deg <= cfg.dense_max_shift_deg)
    out = {"accepted": bool(ok), "iterations": it + 1, "fitness": fitness, "rmse_m": rmse,
           "shift_m": shift_m, "shift_deg": shift_deg}
    if hybrid:
        res.info.setdefault("dense", {})["hybrid"] = out
    else:
        res.info["dense"] = out
    if not ok:
        return cov_prior
    x = geo.se3_log(d)
    if blend is None and cfg.dense_fusion == "whole":
        blend = 1.0
    if blend is None and cfg.dense_fusion == "information" and cov_prior is not None:
        # weigh the two by their information: (S_s^-1 + S_d^-1)^-1 S_d^-1 x
        if hybrid:
            cov_d = hybrid_covariance(T_d, di, dj, cfg, stride=2 * cfg.dense_cov_stride)
        else:
            cov_d, _, _ = point_to_plane_covariance(T_d, di, dj, cfg, stride=cfg.p2p_cov_stride)
        if cov_d is not None:
            scale = cfg.hybrid_cov_scale if hybrid else cfg.dense_cov_scale
            info_s, info_d = np.linalg.inv(cov_prior), np.linalg.inv(cov_d * scale)
            step = np.linalg.solve(info_s + info_d, info_d @ x)
            out["weight"] = float(step @ x / max(x @ x, 1e-30))
            res.T_i_j = res.T_i_j @ geo.se3_exp(step)
            return np.linalg.inv(info_s + info_d)
    res.T_i_j = res.T_i_j @ geo.se3_exp((cfg.dense_blend if blend is None else blend) * x)
    return cov_prior


def dense_edge(i: int, j: int, di: DenseMaps, dj: DenseMaps, cfg: TeacherConfig, dt: float,
               T_init: NDArray) -> EdgeEstimate:
    """Fallback 2, second step (``cfg.fallback_dense``), when :func:`rgbd_edge` fails too (or
    is off): ``T_i_j`` from the dense point-to-plane depth alignment alone, started at
    ``T_init`` (the motion prediction), ``path`` ``dense``.

    The same Open3D projective ICP kernel as :func:`dense_refine`, up to
    ``cfg.fallback_dense_iters`` iterations. The covariance is ``sigma^2 (J^T W J)^-1`` of
    the point-to-plane residuals at the result (:func:`point_to_plane_covariance`). Failed
    (status ``few_matches`` / ``degenerate`` / ``implausible_motion``) when too few pixels
    pair up, when the iteration has not settled, when the covariance leaves a direction
    undetermined (``cfg.fallback_max_sigma_m`` / ``_deg``: e.g. a single plane in view) or
    when the motion is implausibly fast."""
    T = o3d.core.Tensor(np.asarray(T_init, np.float64))
    fitness, converged, it = 0.0, False, 0
    try:
        for it in range(cfg.fallback_dense_iters):
            step = o3d.t.pipelines.odometry.compute_odometry_result_point_to_plane(
                dj.points, di.vertex, di.normal, di.K, T, cfg.dense_trunc_m, cfg.dense_huber_m)
            T = step.transformation.matmul(T)
            fitness = float(step.fitness)
            if _small_step(step.transformation.numpy(), cfg.align_stop_m, cfg.align_stop_deg):
                converged = True
                break
    except RuntimeError as exc:  # no pixel pairs up, or a singular system (e.g. an exact plane)
        return EdgeEstimate(i, j, "degenerate" if "Singular" in str(exc) else "few_matches",
                            info={"path": "none", "dense": {"accepted": False, "fitness": 0.0}})
    T_d = geo.orthonormalize(T.numpy())
    info = {"path": "dense", "dense": {"accepted": True, "iterations": it + 1, "fitness": fitness, "shift_m": 0.0,
                                       "shift_deg": 0.0, "stale_stream": False}}
    res = EdgeEstimate(i, j, "ok", T_i_j=T_d, info=info)
    if not np.all(np.isfinite(T_d)) or fitness < cfg.dense_min_fitness:
        res.status, res.info["path"] = "few_matches", "none"
        return res
    if not converged:  # still sliding after all iterations: what the depth leaves free
        res.status, res.info["path"] = "degenerate", "none"
        return res
    cov, n_pairs, rmse = point_to_plane_covariance(T_d, di, dj, cfg)
    res.cov, res.matches = cov, n_pairs
    res.inliers, res.inlier_ratio = n_pairs, float(fitness)
    trans, rot = float(np.linalg.norm(T_d[:3, 3])), geo.rotation_angle_deg(T_d)
    res.info.update(trans_m=trans, rot_deg=rot, rmse_m=rmse)
    if cov is None:
        res.status = "degenerate"
        return res
    ev = np.linalg.eigvalsh(cov[:3, :3]), np.linalg.eigvalsh(cov[3:, 3:])
    res.info["conditioning"] = _conditioning(cov, dj)
    if (ev[0].min() <= 0 or np.sqrt(ev[0].max()) > cfg.fallback_max_sigma_m
            or ev[1].min() <= 0 or np.degrees(np.sqrt(ev[1].max())) > cfg.fallback_max_sigma_deg
            or res.info["conditioning"] < cfg.fallback_min_conditioning):
        res.status = "degenerate"
    elif trans > cfg.max_speed * dt or rot > cfg.max_angular_speed_deg * dt:
        res.status = "implausible_motion"
    if not res.ok:
        res.info["path"] = "none"
    return res


def _conditioning(cov: NDArray, dj: DenseMaps) -> float:
    """Smallest over largest eigenvalue of a dense covariance with rotations scaled by the
    median depth of frame j (a rotation of 1 rad moves the points by ~z metres); small when
    the depth leaves a direction nearly free (``cfg.fallback_min_conditioning``)."""
    z = float(np.nanmedian(dj.points.numpy()[..., 2]))
    S = np.diag([1.0, 1.0, 1.0, z, z, z])
    ev = np.linalg.eigvalsh(S @ cov @ S)
    return float(ev[0] / ev[-1]) if ev[-1] > 0 else 0.0


def _rgbd_image(f: FrameFeatures, s: int) -> o3d.t.geometry.RGBDImage:
    """Open3D RGB-D image (intensity in [0, 1], depth in m) of every ``s``-th pixel of a frame."""
    g = np.repeat(f.gray[::s, ::s, None].astype(np.float32) / 255.0, 3, axis=2)  # Open3D wants 3 channels
    d = np.ascontiguousarray(f.depth[::s, ::s], dtype=np.float32)
    return o3d.t.geometry.RGBDImage(o3d.t.geometry.Image(o3d.core.Tensor(g)), o3d.t.geometry.Image(o3d.core.Tensor(d)))


def rgbd_edge(i: int, j: int, fi: FrameFeatures, fj: FrameFeatures, intr: Intrinsics, cfg: TeacherConfig,
              dt: float, T_init: NDArray, chained: bool = False, depth_only: bool = False) -> EdgeEstimate:
    """Fallback 2, first step (``cfg.fallback_rgbd``), for a pair whose colour gave no usable
    sparse estimate; it also holds where the depth alone does not pin the motion down (e.g.
    a bare wall and the ceiling, slid along their corner): Open3D's hybrid RGB-D
    odometry (photometric and depth terms, coarse to fine at 1/2, 1/4 and 1/8 resolution),
    started at ``T_init``, ``path`` ``rgbd``. Its covariance is the point-to-plane one of
    :func:`point_to_plane_covariance` at the result: large along what the depth leaves free
    (the colour term that fixed it is not counted, so it errs on the safe side). Failed
    when too few pixels pair up, when that covariance cannot be formed or is as poorly
    conditioned as one plane's (``cfg.fallback_min_conditioning``: a textured single plane
    is refused too, conservatively), or when the motion is implausibly fast. With the hybrid
    maps and ``depth_only`` (or a frame whose grey is void, :func:`_photo_pair`) the kernel's
    depth term alone aligns them."""
    if fi.dense.photo is not None and fj.dense.photo is not None:
        try:
            T, fitness = pyramid_align(T_init, fi.dense, fj.dense, cfg, coarse=not chained, depth_only=depth_only)
        except RuntimeError as exc:
            return EdgeEstimate(i, j, "degenerate" if "Singular" in str(exc) else "few_matches",
                                info={"path": "none", "error": str(exc)[-200:]})
        return _rgbd_checked(i, j, T, fitness, fi, fj, cfg, dt)
    s = 2
    K = np.array(intr.K, dtype=np.float64)
    K[:2] /= s
    crit = [o3d.t.pipelines.odometry.OdometryConvergenceCriteria(n) for n in (10, 5, 3)]
    try:
        out = o3d.t.pipelines.odometry.rgbd_odometry_multi_scale(
            _rgbd_image(fj, s), _rgbd_image(fi, s), o3d.core.Tensor(K), o3d.core.Tensor(np.asarray(T_init, np.float64)),
            1.0, cfg.depth_max, crit, o3d.t.pipelines.odometry.Method.Hybrid)
    except RuntimeError as exc:
        return EdgeEstimate(i, j, "degenerate" if "Singular" in str(exc) else "few_matches",
                            info={"path": "none", "error": str(exc)[-200:]})
    return _rgbd_checked(i, j, geo.orthonormalize(out.transformation.numpy()), float(out.fitness), fi, fj, cfg, dt)


def _rgbd_checked(i: int, j: int, T: NDArray, fitness: float, fi: FrameFeatures, fj: FrameFeatures,
                  cfg: TeacherConfig, dt: float) -> EdgeEstimate:
    """The ``rgbd`` edge of a hybrid alignment's result, with its covariance and checks."""
    res = EdgeEstimate(i, j, "ok", T_i_j=T, info={"path": "rgbd", "dense": {
        "accepted": True, "iterations": 0, "fitness": fitness, "shift_m": 0.0, "shift_deg": 0.0, "stale_stream": False}})
    if not np.all(np.isfinite(T)) or fitness < cfg.dense_min_fitness:
        res.status, res.info["path"] = "few_matches", "none"
        return res
    # every 2nd point on the hybrid path (it runs for every edge of a starved scene); all
    # of them on Open3D's multi-scale path, as before
    stride = 2 if fi.dense.photo is not None else 1
    cov, n_pairs, rmse = point_to_plane_covariance(T, fi.dense, fj.dense, cfg, stride=stride)
    trans, rot = float(np.linalg.norm(T[:3, 3])), geo.rotation_angle_deg(T)
    res.cov, res.matches, res.inliers, res.inlier_ratio = cov, n_pairs, n_pairs, fitness
    res.info.update(trans_m=trans, rot_deg=rot, rmse_m=rmse)
    if cov is not None:
        res.info["conditioning"] = _conditioning(cov, fj.dense)
    if cov is None or np.linalg.eigvalsh(cov).min() <= 0 or res.info["conditioning"] < cfg.fallback_min_conditioning:
        res.status = "degenerate"  # e.g. one plane of one colour: nothing pins the slide along it
    elif trans > cfg.max_speed * dt or rot > cfg.max_angular_speed_deg * dt:
        res.status = "implausible_motion"
    if not res.ok:
        res.info["path"] = "none"
    return res


def point_to_plane_covariance(T_i_j: NDArray, di: DenseMaps, dj: DenseMaps, cfg: TeacherConfig,
                              stride: int = 1) -> tuple[NDArray | None, int, float]:
    """Covariance (6, 6), (v, w) order, right perturbation at ``T_i_j``, of the dense
    point-to-plane alignment of frame j's points to frame i's surface; also the number of
    pixel pairs and their RMS distance (m).

    The pairs are formed as Open3D's projective kernel forms them (j's point moved into i,
    projected with ``di.K``, paired with i's vertex at the rounded pixel, kept within
    ``cfg.dense_trunc_m``). Residual ``r = n^T (T q - p)``; with ``m = R^T n`` its Jacobian
    is ``[m^T, (q x m)^T]``. ``sigma^2`` is the Huber-weighted residual variance, floored at
    ``cfg.dense_min_sigma_m`` squared (two images of one repeated depth map agree exactly). The
    pixels' errors are correlated (smooth depth bias, correlated noise), so this is a lower
    bound of the real uncertainty. None when fewer than 6 pairs or a singular system.
    ``stride``: use every ``stride``-th point of j in both axes (the covariance is then
    scaled back to all of them)."""
    q = dj.moved_points(stride)
    R, t = T_i_j[:3, :3], T_i_j[:3, 3]
    X = q @ R.T + t
    vert, nrm, h, w, K = di.surface()
    # rows are selected with np.take / np.compress: the same rows as fancy or boolean
    # indexing, which NumPy does 4-10 times slower on (N, 3) arrays
    front = X[:, 2] > 1e-6
    if not front.all():
        q, X = np.compress(front, q, axis=0), np.compress(front, X, axis=0)
    u = np.rint(K[0, 0] * X[:, 0] / X[:, 2] + K[0, 2]).astype(np.int64)
    v = np.rint(K[1, 1] * X[:, 1] / X[:, 2] + K[1, 2]).astype(np.int64)
    idx = np.flatnonzero((u >= 0) & (u < w) & (v >= 0) & (v < h))
    pix = v[idx] * w + u[idx]
    p, n = np.take(vert, pix, axis=0), np.take(nrm, pix, axis=0)
    use = np.isfinite(p).all(axis=1) & np.isfinite(n).all(axis=1)
    idx = idx[use]
    p, n = np.compress(use, p, axis=0).astype(np.float64), np.compress(use, n, axis=0).astype(np.float64)
    Xs = np.take(X, idx, axis=0)
    d = Xs - p
    ok = np.sqrt(np.add.reduce(d * d, axis=1)) < cfg.dense_trunc_m  # np.linalg.norm's formula
    q, X = np.take(q, idx[ok], axis=0), np.compress(ok, Xs, axis=0)
    p, n = np.compress(ok, p, axis=0), np.compress(ok, n, axis=0)
    if len(q) < 6:
        return None, len(q), float("nan")
    r = np.einsum("ij,ij->i", n, X - p)
    m = n @ R
    J = np.empty((len(q), 6))
    J[:, :3] = m
    J[:, 3] = q[:, 1] * m[:, 2] - q[:, 2] * m[:, 1]  # q x m, written out (np.cross's formula)
    J[:, 4] = q[:, 2] * m[:, 0] - q[:, 0] * m[:, 2]
    J[:, 5] = q[:, 0] * m[:, 1] - q[:, 1] * m[:, 0]
    _, wts, _ = _huber(r, cfg.dense_huber_m)
    H = J.T @ (J * wts[:, None])
    sigma2 = max(float(np.sum(wts * r * r) / max(len(r) - 6, 1)), cfg.dense_min_sigma_m ** 2)
    try:
        cov = sigma2 * np.linalg.inv(H) / stride ** 2
    except np.linalg.LinAlgError:
        return None, len(q), float(np.sqrt(np.mean(r * r)))
    if not np.all(np.isfinite(cov)):
        return None, len(q), float(np.sqrt(np.mean(r * r)))
    return 0.5 * (cov + cov.T), len(q), float(np.sqrt(np.mean(r * r)))


def hybrid_covariance(T_i_j: NDArray, di: DenseMaps, dj: DenseMaps, cfg: TeacherConfig,
                      stride: int = 2) -> NDArray | None:
    """Covariance (6, 6), (v, w) order, right perturbation at ``T_i_j``, of the hybrid
    alignment of :func:`hybrid_align`: the inverse of the summed information of its two
    residuals at the result, each pixel pair formed as Open3D's kernel forms it (frame j's
    point ``q`` moved into i, the nearest pixel of i's full-resolution maps, kept within
    ``cfg.dense_trunc_m`` in depth). Photometric ``r_I = I_i(u) - I_j(q)`` and depth
    ``r_D = D_i(u) - z(T q)``, their Jacobians through the Sobel derivatives of frame i
    (``/ 8``: per pixel) and the projection; each term Huber-weighted (``cfg.photo_huber``,
    ``cfg.dense_huber_m``) and divided by its own weighted residual variance (floored at
    ``cfg.dense_min_sigma_m`` squared for depth). Pixel errors are correlated, so, like
    :func:`point_to_plane_covariance`, a lower bound. ``stride``: every ``stride``-th point
    of j in both axes (scaled back to all). None without photometric maps, with fewer
    than 12 pairs or a singular system."""
    pi, pj = di.photo, dj.photo
    if pi is None or pj is None or not (pi.grey and pj.grey):
        return None
    q = dj.points.numpy()[::stride, ::stride].reshape(-1, 3)
    Ij = pj.src_intensity.numpy()[::stride, ::stride].reshape(-1)
    ok = np.all(np.isfinite(q), axis=1)
    q, Ij = q[ok].astype(np.float64), Ij[ok].astype(np.float64)
    R, t = T_i_j[:3, :3], T_i_j[:3, 3]
    X = q @ R.T + t
    K = pi.K.numpy()
    Di = pi.depth.numpy()[..., 0]
    h, w = Di.shape
    front = X[:, 2] > 1e-6
    X, q, Ij = X[front], q[front], Ij[front]
    uf = K[0, 0] * X[:, 0] / X[:, 2] + K[0, 2]
    vf = K[1, 1] * X[:, 1] / X[:, 2] + K[1, 2]
    u, v = np.rint(uf).astype(np.int64), np.rint(vf).astype(np.int64)
    inside = (u >= 1) & (u < w - 1) & (v >= 1) & (v < h - 1)
    X, q, Ij, u, v = X[inside], q[inside], Ij[inside], u[inside], v[inside]
    d = Di[v, u].astype(np.float64)
    g = [a.numpy()[..., 0][v, u].astype(np.float64) / 8.0 for a in (pi.depth_dx, pi.depth_dy, pi.intensity_dx, pi.intensity_dy)]
    rD = d - X[:, 2]
    ok = np.isfinite(d) & (np.abs(rD) <= cfg.dense_trunc_m) & np.all(np.isfinite(np.stack(g)), axis=0)
    if ok.sum() < 12:
        return None
    X, q, rD = X[ok], q[ok], rD[ok]
    gDx, gDy, gIx, gIy = (a[ok] for a in g)
    rI = pi.intensity.numpy()[..., 0][v[ok], u[ok]].astype(np.float64) - Ij[ok]
    iz = 1.0 / X[:, 2]
    # d(u, v)/dX of the pinhole projection, rows (3,) per pixel
    du = np.stack([K[0, 0] * iz, np.zeros_like(iz), -K[0, 0] * X[:, 0] * iz * iz], axis=1)
    dv = np.stack([np.zeros_like(iz), K[1, 1] * iz, -K[1, 1] * X[:, 1] * iz * iz], axis=1)
    bI = gIx[:, None] * du + gIy[:, None] * dv
    bD = gDx[:, None] * du + gDy[:, None] * dv
    bD[:, 2] -= 1.0
    info = np.zeros((6, 6))
    a = float(np.sqrt(cfg.photo_weight))  # the grey maps' scale (photo_maps)
    for b, r, k, floor in ((bI, rI, _photo_huber(cfg), a / 255), (bD, rD, cfg.dense_huber_m, cfg.dense_min_sigma_m)):
        m = b @ R  # R^T b per pixel
        J = np.concatenate([m, np.cross(q, m)], axis=1)
        _, wts, _ = _huber(r, k)
        sigma2 = max(float(np.sum(wts * r * r) / max(len(r) - 6, 1)), floor ** 2)
        info += J.T @ (J * wts[:, None]) / sigma2
    try:
        cov = np.linalg.inv(info) / stride ** 2
    except np.linalg.LinAlgError:
        return None
    if not np.all(np.isfinite(cov)):
        return None
    return 0.5 * (cov + cov.T)


def _estimate(i: int, j: int, fi: FrameFeatures, fj: FrameFeatures, intr: Intrinsics,
              cfg: TeacherConfig, dt: float, pairs: NDArray[np.int64],
              rolling: tuple | None = None) -> EdgeEstimate:
    """The keypoint estimate of ``T_i_j`` from the matches ``pairs`` (PnP-RANSAC, then the
    two-way refinement); ``rolling``: :func:`rolling_shutter_views`, whose keypoints it then
    takes (``cfg.subpixel`` off)."""
    K = intr.K
    n_match = len(pairs)
    if n_match < cfg.min_matches:
        return EdgeEstimate(i, j, "few_matches", matches=n_match)
    (uv_fi, z_fi), (uv_fj, z_fj) = (rolling[0], rolling[1]) if rolling is not None else ((fi.uv, fi.z), (fj.uv, fj.z))
    uv_i = np.take(uv_fi, pairs[:, 0], axis=0).astype(np.float64)
    uv_j = np.take(uv_fj, pairs[:, 1], axis=0).astype(np.float64)
    if cfg.subpixel:
        uv_j = _subpixel(fi, fj, uv_i, uv_j, cfg.lk_window)
    P_i = _backproject(uv_i, z_fi[pairs[:, 0]].astype(np.float64), K)
    ok, rvec, tvec, inl = cv2.solvePnPRansac(
        P_i, uv_j, K, None, iterationsCount=cfg.ransac_iters, reprojectionError=cfg.ransac_reproj_px,
        confidence=0.999, flags=cv2.SOLVEPNP_SQPNP)
    if not ok or inl is None or len(inl) < 6:
        return EdgeEstimate(i, j, "few_inliers", matches=n_match, inliers=0 if inl is None else len(inl))
    inl = inl.ravel()
    rvec, tvec = cv2.solvePnPRefineLM(P_i[inl], uv_j[inl], K, None, rvec, tvec)
    R_j_i, _ = cv2.Rodrigues(rvec)
    T0 = geo.inv_T(geo.make_T(R_j_i, tvec.ravel()))

    # points of frame j with valid depth give the backward term
    z_j = (depth_at(fj.depth, uv_j, cfg) if cfg.subpixel else z_fj[pairs[:, 1]]).astype(np.float64)
    Q_all = _backproject(uv_j, z_j, K)
    has_b = (z_j > 0) if cfg.two_way and cfg.refine else np.zeros(len(z_j), bool)
    iters, w3 = (cfg.refine_iters, cfg.depth_weight) if cfg.refine else (0, 0.0)  # 0: covariance at T0 only
    T, r, cov = T0, None, None
    for _ in range(cfg.refine_rounds):  # select inliers with the current pose, refine
        in_f = _reproj_err(geo.inv_T(T), P_i, uv_j, K) < cfg.refine_inlier_px
        in_b = has_b & in_f
        in_b[in_b] = _reproj_err(T, Q_all[in_b], uv_i[in_b], K) < cfg.refine_inlier_px
        if in_f.sum() < max(6, cfg.min_inliers):
            return EdgeEstimate(i, j, "few_inliers", matches=n_match, inliers=int(in_f.sum()))
        sf, sb = _even(np.flatnonzero(in_f), cfg.refine_max_points), _even(np.flatnonzero(in_b), cfg.refine_max_points)
        P_f, uv_f = np.take(P_i, sf, axis=0), np.take(uv_j, sf, axis=0)
        Q_b, uv_b, P_b = np.take(Q_all, sb, axis=0), np.take(uv_i, sb, axis=0), np.take(P_i, sb, axis=0)
        T, cov, r = refine_two_way(T, P_f, uv_f, Q_b, uv_b, K, cfg.huber_px, iters, cfg.min_sigma_px, P_b, w3)
    n_in = int(in_f.sum())
    res = EdgeEstimate(i, j, "ok", matches=n_match, inliers=n_in, inlier_ratio=n_in / n_match,
                       inlier_pairs=pairs[in_f])
    n_px = 2 * (len(sf) + len(sb))  # the pixel residuals lead r (unless a point fell behind a camera)
    r_px = r[:n_px] if len(r) == n_px + (3 * len(sb) if w3 > 0 else 0) else \
        _residuals(T, P_f, uv_f, Q_b, uv_b, K, False)[0]
    res.rmse_px = float(np.sqrt(np.mean(r_px * r_px)))
    res.T_i_j, res.cov = T, cov
    trans = float(np.linalg.norm(T[:3, 3]))
    rot = geo.rotation_angle_deg(T)
    res.info = {"trans_m": trans, "rot_deg": rot}
    spread = np.std(uv_j[in_f], axis=0) / np.array([intr.width, intr.height])
    if res.inlier_ratio < cfg.min_inlier_ratio:
        res.status = "low_inlier_ratio"
    elif res.rmse_px > cfg.max_rmse_px:
        res.status = "high_rmse"
    elif spread.min() < cfg.min_spread or not np.all(np.isfinite(cov)) or np.linalg.eigvalsh(cov).min() <= 0:
        res.status = "degenerate"
    elif trans > cfg.max_speed * dt or rot > cfg.max_angular_speed_deg * dt:
        res.status = "implausible_motion"
    return res


def _even(idx: NDArray[np.int64], n: int) -> NDArray[np.int64]:
    """At most ``n`` evenly spaced entries of ``idx``."""
    if len(idx) <= n:
        return idx
    return idx[np.linspace(0, len(idx) - 1, n).astype(np.int64)]


def _reproj_err(T_j_i: NDArray, P_i: NDArray, uv_j: NDArray, K: NDArray) -> NDArray:
    Y = P_i @ T_j_i[:3, :3].T + T_j_i[:3, 3]
    front = Y[:, 2] > 1e-6
    if front.all():  # the usual case: no masks
        return np.linalg.norm(_project(Y, K) - uv_j, axis=1)
    err = np.full(len(P_i), np.inf)
    err[front] = np.linalg.norm(_project(Y[front], K) - uv_j[front], axis=1)
    return err


def _subpixel(fi: FrameFeatures, fj: FrameFeatures, uv_i: NDArray, uv_j: NDArray, win: int = 11) -> NDArray:
    """Track ``uv_i`` into frame j with pyramidal LK, started at the ORB match ``uv_j``.

    Points the tracker loses, or moves by more than 2 px from the match, keep the ORB position.
    """
    p0 = uv_i.astype(np.float32).reshape(-1, 1, 2)
    p1 = uv_j.astype(np.float32).reshape(-1, 1, 2).copy()
    p1, st, _ = cv2.calcOpticalFlowPyrLK(
        fi.gray, fj.gray, p0, p1, winSize=(win, win), maxLevel=1,
        criteria=(cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 20, 0.01),
        flags=cv2.OPTFLOW_USE_INITIAL_FLOW)
    p1 = p1.reshape(-1, 2).astype(np.float64)
    good = (st.ravel() == 1) & (np.linalg.norm(p1 - uv_j, axis=1) < 2.0)
    out = uv_j.copy()
    out[good] = p1[good]
    return out


__all__ = ["FrameFeatures", "DenseMaps", "EdgeEstimate", "extract", "dense_maps", "add_surface", "photo_maps", "dense_method", "hybrid_align", "pyramid_align", "hybrid_covariance", "PhotoMaps", "dense_refine", "match",
           "match_wide", "dense_edge", "rgbd_edge", "point_to_plane_covariance",
           "image_keys", "stale_stream",
           "estimate_edge", "refine_two_way", "make_orb"]
