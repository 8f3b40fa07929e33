"""Two-frame RGB-D odometry: ORB matching, depth back-projection, PnP-RANSAC, a robust
two-way refinement that yields ``T_i_j`` with a 6x6 covariance, and a dense point-to-plane
depth alignment (Open3D's projective ICP kernel) started from that estimate.

Conventions (docs/conventions.md): ``T_i_j`` maps frame-j camera coordinates into frame i;
the covariance is in the project tangent order (v, w), right perturbation at ``T_i_j``.
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass, field
from typing import Optional

import cv2
import numpy as np
import open3d as o3d
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from data import geometry as geo
from data.sequence import Intrinsics
from teacher.config import TeacherConfig



@dataclass
class FrameFeatures:
    """Everything the teacher needs of one frame; computed once, reused by all its edges.

    ``uv`` (N, 2) keypoint pixels, ``desc`` (N, 32) ORB descriptors, ``z`` (N,) depth at the
    keypoint (0 where invalid or on a depth edge, see :func:`depth_at`), ``gray`` (H, W)
    uint8 for sub-pixel tracking, ``depth`` (H, W) float32 metres. ``dense`` holds the Open3D
    vertex and normal maps of the depth subsampled by ``cfg.dense_scale`` (None when the
    dense step is off). ``keys`` fingerprints the colour and the depth image (to find
    repeated images); ``stale`` is set by the caller when exactly one of the two streams
    repeats the previous frame's image (see :func:`stale_stream`).
    """

    uv: NDArray[np.float32]
    desc: NDArray[np.uint8]
    z: NDArray[np.float32]
    gray: NDArray[np.uint8]
    depth: NDArray[np.float32]
    dense: Optional["DenseMaps"] = None
    keys: tuple[bytes, bytes] = (b"", b"")
    stale: bool = False
    _tree: Optional[cKDTree] = None

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
    win = depth[v[idx, None] + _OFFS[:, 0], u[idx, None] + _OFFS[:, 1]]  # (M, 25)
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
    vertex: o3d.core.Tensor
    normal: o3d.core.Tensor
    K: o3d.core.Tensor


def _subsampled(depth: NDArray[np.float32], K: NDArray, s: int,
                cfg: TeacherConfig) -> tuple[o3d.t.geometry.Image, o3d.core.Tensor]:
    """Every ``s``-th pixel of ``depth`` (NaN outside ``[depth_min, depth_max]``) as an Open3D
    image, with its camera matrix ``K / s`` (pixel centres stay on the grid)."""
    d = np.array(depth[::s, ::s], dtype=np.float32)
    d[~((d >= cfg.depth_min) & (d <= cfg.depth_max))] = np.nan
    Ks = np.array(K, dtype=np.float64)
    Ks[:2] /= s
    return o3d.t.geometry.Image(o3d.core.Tensor(d)), o3d.core.Tensor(Ks)


def dense_maps(depth: NDArray[np.float32], K: NDArray, cfg: TeacherConfig) -> DenseMaps:
    """The maps of :class:`DenseMaps` for one depth image (metres, 0 = invalid).

    The points moved are sparse (every 4th pixel: the cost of an iteration is proportional
    to their number), the surface they are aligned to is denser (every 2nd pixel): at 1/4
    resolution on both sides the alignment of noise-free frames was biased by ~1.5 mm
    (edges and curved surfaces are coarsely sampled), at 2 / 4 it is ~0.2 mm. Normals come
    from a Gaussian-smoothed copy of the depth (``filter_bilateral`` with a 5 m value sigma,
    which skips holes), as in Open3D's own point-to-plane odometry; Kinect noise makes
    unsmoothed normals useless.
    """
    img, Kt = _subsampled(depth, K, cfg.dense_scale, cfg)
    points = img.create_vertex_map(Kt, float("nan")).as_tensor()
    img, Kt = _subsampled(depth, K, cfg.dense_target_scale, cfg)
    vertex = img.create_vertex_map(Kt, float("nan")).as_tensor()
    smooth = img.filter_bilateral(cfg.dense_normal_kernel, 5.0, 10.0)
    normal = smooth.create_vertex_map(Kt, float("nan")).create_normal_map(float("nan")).as_tensor()
    return DenseMaps(points, vertex, normal, Kt)


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


def extract(rgb: NDArray[np.uint8], depth: NDArray[np.float32], cfg: TeacherConfig,
            orb: Optional[cv2.ORB] = None, K: Optional[NDArray] = None) -> FrameFeatures:
    """ORB keypoints and descriptors of one frame, with the depth at each keypoint; with the
    camera matrix ``K`` and ``cfg.dense_iters > 0`` also the maps of the dense step."""
    gray = cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY)
    dense = dense_maps(depth, K, cfg) if K is not None and cfg.dense_iters > 0 else None
    orb = orb or make_orb(cfg)
    kps, desc = orb.detectAndCompute(gray, None)
    keys = image_keys(rgb, depth)
    if not kps or desc is None:
        return FrameFeatures(np.zeros((0, 2), np.float32), np.zeros((0, 32), np.uint8),
                             np.zeros(0, np.float32), gray, depth, dense, keys)
    uv = np.array([k.pt for k in kps], dtype=np.float32)
    return FrameFeatures(uv, desc, depth_at(depth, uv, cfg), gray, depth, dense, keys)


def match(fi: FrameFeatures, fj: FrameFeatures, cfg: TeacherConfig,
          T_i_j_pred: Optional[NDArray] = None, K: Optional[NDArray] = None) -> NDArray[np.int64]:
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
    P = _backproject(fi.uv[src], fi.z[src], K)
    Tji = geo.inv_T(T_i_j_pred)
    Y = P @ Tji[:3, :3].T + Tji[:3, 3]
    src = src[Y[:, 2] > 1e-3]
    pred = _project(Y[Y[:, 2] > 1e-3], K)
    near = cKDTree(pred).sparse_distance_matrix(fj.tree(), cfg.search_radius_px, output_type="ndarray")
    if len(near) == 0:
        return np.zeros((0, 2), np.int64)
    qi, cj = src[near["i"]], near["j"].astype(np.int64)
    d = np.bitwise_count(fi.desc64[qi] ^ fj.desc64[cj]).sum(axis=1, dtype=np.int64)
    # best and second best in j for each i (one sort on the key (i, distance); d < 512)
    o = np.argsort((qi << 9) | d, kind="stable")
    qi_s, cj_s, d_s = qi[o], cj[o], d[o]
    first = np.flatnonzero(np.r_[True, qi_s[1:] != qi_s[:-1]])
    has2 = np.r_[first[1:], len(qi_s)] - first >= 2
    second = np.where(has2, d_s[np.minimum(first + 1, len(d_s) - 1)], 256)
    best_i, best_j, best_d = qi_s[first], cj_s[first], d_s[first]
    ok = (best_d <= cfg.max_hamming) & (best_d < cfg.ratio * second)
    # mutual check: the best i for each j among the compared pairs
    o2 = np.argsort((cj << 9) | d, kind="stable")
    cj2, qi2 = cj[o2], qi[o2]
    first2 = np.flatnonzero(np.r_[True, cj2[1:] != cj2[:-1]])
    back = np.full(len(fj.desc), -1, np.int64)
    back[cj2[first2]] = qi2[first2]
    ok &= back[best_j] == best_i
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
    T_i_j: Optional[NDArray[np.float64]] = None
    cov: Optional[NDArray[np.float64]] = None
    matches: int = 0
    inliers: int = 0
    inlier_ratio: float = 0.0
    rmse_px: float = float("nan")
    info: dict = field(default_factory=dict)
    inlier_pairs: Optional[NDArray[np.int64]] = None
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


def _residuals(T: NDArray, P_i: NDArray, uv_j: NDArray, Q_j: NDArray, uv_i: NDArray, K: NDArray,
               with_jac: bool, P_b: Optional[NDArray] = None, w3: float = 0.0) -> tuple[NDArray, Optional[NDArray]]:
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
    # forward: Y projected into j; backward: X projected into i (rows (u, v) per point)
    izf = 1.0 / Y[:, 2]
    xf, yf = Y[:, 0] * izf, Y[:, 1] * izf  # normalised coordinates
    rf = r[:2 * F].reshape(F, 2)
    rf[:, 0] = fx * xf + cx - uv_j[:, 0]
    rf[:, 1] = fy * yf + cy - uv_j[:, 1]
    izb = 1.0 / X[:, 2]
    xb, yb = X[:, 0] * izb, X[:, 1] * izb
    rb = r[2 * F:2 * F + 2 * B].reshape(B, 2)
    rb[:, 0] = fx * xb + cx - uv_i[:, 0]
    rb[:, 1] = fy * yb + cy - uv_i[:, 1]
    if w3 > 0:
        s3 = w3 / (P_b[:, 2] ** 2)  # Kinect depth noise grows with z^2
        r[2 * F + 2 * B:] = ((X - P_b) * s3[:, None]).ravel()
    if not with_jac:
        return r, None
    J = np.empty((len(r), 6))
    # forward, right perturbation: Y(delta) = exp(-delta) Y -> dY = [-I | hat(Y)]
    Jf = J[:2 * F].reshape(F, 2, 6)
    a, b = fx * izf, fy * izf
    Jf[:, 0, 0] = -a
    Jf[:, 0, 1] = 0.0
    Jf[:, 0, 2] = a * xf
    Jf[:, 0, 3] = fx * xf * yf
    Jf[:, 0, 4] = -fx * (1.0 + xf * xf)
    Jf[:, 0, 5] = fx * yf
    Jf[:, 1, 0] = 0.0
    Jf[:, 1, 1] = -b
    Jf[:, 1, 2] = b * yf
    Jf[:, 1, 3] = fy * (1.0 + yf * yf)
    Jf[:, 1, 4] = -fy * xf * yf
    Jf[:, 1, 5] = -fy * xf
    # backward: X(delta) = R exp(delta) Q + t -> dX = R [I | -hat(Q)]; rows b = A R,
    # [b | -b hat(Q)] = [b | Q x b]
    Jb = J[2 * F:2 * F + 2 * B].reshape(B, 2, 6)
    Bu = (fx * izb)[:, None] * (R[0] - xb[:, None] * R[2])
    Bv = (fy * izb)[:, None] * (R[1] - yb[:, None] * R[2])
    Bb = np.stack([Bu, Bv], axis=1)  # (B, 2, 3)
    Jb[:, :, :3] = Bb
    Q = Q_j[:, None, :]
    Jb[:, :, 3] = Q[..., 1] * Bb[..., 2] - Q[..., 2] * Bb[..., 1]
    Jb[:, :, 4] = Q[..., 2] * Bb[..., 0] - Q[..., 0] * Bb[..., 2]
    Jb[:, :, 5] = Q[..., 0] * Bb[..., 1] - Q[..., 1] * Bb[..., 0]
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
                   huber: float, iters: int = 10, min_sigma_px: float = 0.0, P_b: Optional[NDArray] = None,
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
        Jq = J[quad] if newton and quad.sum() >= 12 else J * np.sqrt(w)[:, None]
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


def estimate_edge(i: int, j: int, fi: FrameFeatures, fj: FrameFeatures, intr: Intrinsics,
                  cfg: TeacherConfig, dt: float, T_pred: Optional[NDArray] = None,
                  tracks: Optional[NDArray[np.int64]] = None) -> EdgeEstimate:
    """Estimate ``T_i_j`` between two frames (ids ``i``, ``j``, ``dt`` seconds apart).

    Correspondences come from ``tracks`` ((M, 2) keypoint index pairs chained along the
    gap-1 matches) when given and numerous enough, else from matching: guided by the motion
    prediction ``T_pred`` when given, exhaustive otherwise or when the guided estimate fails.
    """
    attempts = []
    if tracks is not None and len(tracks) >= cfg.min_matches:
        attempts.append(("tracks", tracks, None))
    if T_pred is not None:
        attempts.append(("guided", None, T_pred))
    attempts.append(("exhaustive", None, None))
    best: Optional[EdgeEstimate] = None
    for source, pairs, pred in attempts:
        if pairs is None:
            pairs = match(fi, fj, cfg, pred, intr.K)
        res = _estimate(i, j, fi, fj, intr, cfg, dt, pairs)
        res.info["source"] = source
        if best is None or res.inliers > best.inliers or res.ok:
            best = res
        if res.ok:
            break
    if best.ok and fi.dense is not None and fj.dense is not None:
        stale = fi.stale or fj.stale
        dense_refine(best, fi.dense, fj.dense, cfg, blend=1.0 if stale and cfg.dense_on_stale else None)
        if "dense" in best.info:
            best.info["dense"]["stale_stream"] = stale
    return best


def dense_refine(res: EdgeEstimate, di: DenseMaps, dj: DenseMaps, cfg: TeacherConfig,
                 blend: Optional[float] = None) -> None:
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
    """
    if cfg.dense_iters <= 0:
        return
    T = o3d.core.Tensor(res.T_i_j)
    fitness, rmse = 0.0, float("nan")
    try:
        for it in range(cfg.dense_iters):
            step = o3d.t.pipelines.odometry.compute_odometry_result_point_to_plane(
                dj.points, di.vertex, di.normal, di.K, T, cfg.dense_trunc_m, cfg.dense_huber_m)
            T = step.transformation.matmul(T)
            fitness, rmse = float(step.fitness), float(step.inlier_rmse)
            delta = step.transformation.numpy()
            if (np.linalg.norm(delta[:3, 3]) < cfg.dense_stop_m
                    and geo.rotation_angle_deg(delta) < cfg.dense_stop_deg):
                break
    except RuntimeError:  # Open3D raises when no pixel pairs up
        res.info["dense"] = {"accepted": False, "fitness": 0.0}
        return
    T_d = T.numpy()
    d = geo.inv_T(res.T_i_j) @ T_d
    shift_m, shift_deg = float(np.linalg.norm(d[:3, 3])), geo.rotation_angle_deg(d)
    ok = (np.all(np.isfinite(T_d)) and fitness >= cfg.dense_min_fitness
          and shift_m <= cfg.dense_max_shift_m and shift_deg <= cfg.dense_max_shift_deg)
    res.info["dense"] = {"accepted": bool(ok), "iterations": it + 1, "fitness": fitness, "rmse_m": rmse,
                         "shift_m": shift_m, "shift_deg": shift_deg}
    if ok:
        res.T_i_j = res.T_i_j @ geo.se3_exp((cfg.dense_blend if blend is None else blend) * geo.se3_log(d))


def _estimate(i: int, j: int, fi: FrameFeatures, fj: FrameFeatures, intr: Intrinsics,
              cfg: TeacherConfig, dt: float, pairs: NDArray[np.int64]) -> EdgeEstimate:
    K = intr.K
    n_match = len(pairs)
    if n_match < cfg.min_matches:
        return EdgeEstimate(i, j, "few_matches", matches=n_match)
    uv_i = fi.uv[pairs[:, 0]].astype(np.float64)
    uv_j = fj.uv[pairs[:, 1]].astype(np.float64)
    if cfg.subpixel:
        uv_j = _subpixel(fi, fj, uv_i, uv_j, cfg.lk_window)
    P_i = _backproject(uv_i, fi.z[pairs[:, 0]].astype(np.float64), K)
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
    z_j = (depth_at(fj.depth, uv_j, cfg) if cfg.subpixel else fj.z[pairs[:, 1]]).astype(np.float64)
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
        T, cov, r = refine_two_way(T, P_i[sf], uv_j[sf], Q_all[sb], uv_i[sb], K, cfg.huber_px, iters,
                                   cfg.min_sigma_px, P_i[sb], w3)
    n_in = int(in_f.sum())
    res = EdgeEstimate(i, j, "ok", matches=n_match, inliers=n_in, inlier_ratio=n_in / n_match,
                       inlier_pairs=pairs[in_f])
    n_px = 2 * (len(sf) + len(sb))  # the pixel residuals lead r (unless a point fell behind a camera)
    r_px = r[:n_px] if len(r) == n_px + (3 * len(sb) if w3 > 0 else 0) else \
        _residuals(T, P_i[sf], uv_j[sf], Q_all[sb], uv_i[sb], K, False)[0]
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
    err = np.full(len(P_i), np.inf)
    front = Y[:, 2] > 1e-6
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


__all__ = ["FrameFeatures", "DenseMaps", "EdgeEstimate", "extract", "dense_maps", "dense_refine", "match",
           "image_keys", "stale_stream",
           "estimate_edge", "refine_two_way", "make_orb"]
