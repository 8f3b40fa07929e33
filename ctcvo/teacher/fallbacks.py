"""Dense fallbacks of an edge no keypoint estimate made: hybrid RGB-D odometry, then the depth alone."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from ctcvo.data import geometry as geo
from ctcvo.data.open3d_import import o3d
from ctcvo.data.sequence import Intrinsics
from ctcvo.teacher.config import TeacherConfig
from ctcvo.teacher.covariance import conditioning, point_to_plane_covariance
from ctcvo.teacher.dense import (
    ALIGN_STOP_DEG,
    ALIGN_STOP_M,
    DENSE_MIN_FITNESS,
    hybrid_align,
    hybrid_steps,
    iterate,
    photo_pair,
    point_to_plane_kernel,
)
from ctcvo.teacher.features import FrameFeatures
from ctcvo.teacher.maps import DEPTH_MAX, DenseMaps
from ctcvo.teacher.record import DenseOutcome, EdgeDiagnostics, EdgeEstimate

# 'the validation ranges': redkitchen 350:450 and synthetic/lab 0:150 (bench/README.md, seventh session)
FALLBACK_LEVELS = ((8, 10), (4, 5))  # (scale, iterations) coarse to fine; a priori after Open3D's schedule
FALLBACK_FINISH_ITERS = 3  # full resolution after them; by hand (d8a3094); 2 and 5 change no label on the validation ranges
FALLBACK_CHAINED_ITERS = 3  # longer edges (no coarse levels); stress-lowfreq: same labels as 5 (c57b866)
DEPTH_LEVELS = ((8, 30), (4, 30), (2, 20))  # depth alone beside a colour repeat; office, lab, stress-textureless (a33e490)
DEPTH_FINISH_ITERS = 20  # chosen with DEPTH_LEVELS
FALLBACK_DENSE_ITERS = 20  # dense-alone fallback; a priori, not tuned
FALLBACK_MAX_SIGMA_M = 0.01  # dense fallback sanity bound (b8a2c06), not tuned
FALLBACK_MAX_SIGMA_DEG = 0.5  # dense fallback sanity bound (b8a2c06), not tuned
FALLBACK_MIN_CONDITIONING = 0.002  # between synthetic/office gap-1 pairs (0.013-0.023) and one noisy plane (0.0005)


def pyramid_align(T_init: NDArray, di: DenseMaps, dj: DenseMaps,
                  coarse: bool = True, depth_only: bool = False) -> tuple[NDArray, float]:
    """Coarse-to-fine hybrid alignment of frame j to frame i from ``T_init`` (``T_i_j``):
    Open3D's hybrid kernel at the scales and iteration counts of ``FALLBACK_LEVELS``
    (frames at the same scale; the maps of each frame are built once and kept, so the
    frame's other edges reuse them), then :func:`hybrid_align` against frame i at full
    resolution (``FALLBACK_FINISH_ITERS``). Returns (T_i_j, fitness). Raises
    RuntimeError when no pixel pairs up. The multi-scale function of Open3D rebuilds both
    frames' pyramids on every call; on synthetic/stress-lowfreq, where this fallback makes
    nearly every edge at every gap, that cost ~4 times the alignment itself.
    ``depth_only``: the depth term alone (:func:`photo_pair`, which also picks it when
    either frame's grey is void), at the scales and iteration counts of ``DEPTH_LEVELS``
    and ``DEPTH_FINISH_ITERS``."""
    pi, pj = photo_pair(di, dj, depth_only)
    levels, finish = (DEPTH_LEVELS, DEPTH_FINISH_ITERS) if depth_only else (FALLBACK_LEVELS, FALLBACK_FINISH_ITERS)
    T = o3d.core.Tensor(np.asarray(T_init, np.float64))
    for s, iters in levels if coarse else ():
        ti, tj = pi.level(s), pj.level(s)
        T, _, _, _ = hybrid_steps(tj[0], tj[1], ti[:6], tj[6], ti[7], T, iters)
    T_h = geo.orthonormalize(T.numpy())
    T_h, fitness, _, _ = hybrid_align(T_h, di, dj, max(finish if coarse else FALLBACK_CHAINED_ITERS, 1),
                                      depth_only)
    return T_h, fitness


def rgbd_starts(i: int, j: int, fi: FrameFeatures, fj: FrameFeatures, intr: Intrinsics, cfg: TeacherConfig,
                 dt: float, T0: NDArray, T_alt: NDArray | None, chained: bool) -> EdgeEstimate:
    """:func:`rgbd_edge` from ``T0`` and, when given and different, from ``T_alt`` too: of
    the results that pass the checks, the one whose alignment paired more pixels (fitness;
    ``diag.start`` ``span`` when ``T_alt``'s); the first's result when neither passes. A
    start far from the motion can end in a wrong minimum that still passes the checks (on
    synthetic/stress-fast 116 mm off at fitness 0.60, the right one 0.70)."""
    rgbd = rgbd_edge(i, j, fi, fj, intr, cfg, dt, T0, chained=chained)
    if T_alt is not None and not np.allclose(T_alt, T0, rtol=0.0, atol=1e-9):
        alt = rgbd_edge(i, j, fi, fj, intr, cfg, dt, T_alt, chained=chained)
        if alt.ok and (not rgbd.ok or alt.diag.dense.fitness > rgbd.diag.dense.fitness):
            alt.diag.start = "span"
            return alt
    return rgbd


def dense_edge(i: int, j: int, di: DenseMaps, dj: DenseMaps, cfg: TeacherConfig, dt: float,
               T_init: NDArray) -> EdgeEstimate:
    """Fallback 2, second step, when :func:`rgbd_edge` fails too: ``T_i_j`` from the dense
    point-to-plane depth alignment alone, started at
    ``T_init`` (the motion prediction), ``path`` ``dense``.

    The same Open3D projective ICP kernel as :func:`dense_refine`, up to
    ``FALLBACK_DENSE_ITERS`` iterations. The covariance is ``sigma^2 (J^T W J)^-1`` of
    the point-to-plane residuals at the result (:func:`point_to_plane_covariance`). Failed
    (status ``few_matches`` / ``degenerate`` / ``implausible_motion``) when too few pixels
    pair up, when the iteration has not settled, when the covariance leaves a direction
    undetermined (``FALLBACK_MAX_SIGMA_M`` / ``_deg``: e.g. a single plane in view) or
    when the motion is implausibly fast."""
    try:
        T, last, n_it, converged = iterate(point_to_plane_kernel(di, dj), o3d.core.Tensor(np.asarray(T_init, np.float64)),
                                           FALLBACK_DENSE_ITERS, ALIGN_STOP_M, ALIGN_STOP_DEG)
    except RuntimeError as exc:  # no pixel pairs up, or a singular system (e.g. an exact plane)
        return EdgeEstimate(i, j, "degenerate" if "Singular" in str(exc) else "few_matches",
                            diag=EdgeDiagnostics(dense=DenseOutcome(False, 0.0)))
    fitness = 0.0 if last is None else float(last.fitness)
    T_d = geo.orthonormalize(T.numpy())
    res = EdgeEstimate(i, j, "ok", T_i_j=T_d, diag=EdgeDiagnostics("dense", dense=DenseOutcome(True, fitness, n_it)))
    if not np.all(np.isfinite(T_d)) or fitness < DENSE_MIN_FITNESS:
        res.status, res.diag.path = "few_matches", "none"
        return res
    if not converged:  # still sliding after all iterations: what the depth leaves free
        res.status, res.diag.path = "degenerate", "none"
        return res
    cov, n_pairs, rmse = point_to_plane_covariance(T_d, di, dj)
    res.cov, res.matches = cov, n_pairs
    res.inliers, res.inlier_ratio = n_pairs, float(fitness)
    trans, rot = float(np.linalg.norm(T_d[:3, 3])), geo.rotation_angle_deg(T_d)
    res.diag.trans_m, res.diag.rot_deg, res.diag.rmse_m = trans, rot, rmse
    if cov is None:
        res.status = "degenerate"
        return res
    ev = np.linalg.eigvalsh(cov[:3, :3]), np.linalg.eigvalsh(cov[3:, 3:])
    res.diag.conditioning = conditioning(cov, dj)
    if (ev[0].min() <= 0 or np.sqrt(ev[0].max()) > FALLBACK_MAX_SIGMA_M
            or ev[1].min() <= 0 or np.degrees(np.sqrt(ev[1].max())) > FALLBACK_MAX_SIGMA_DEG
            or res.diag.conditioning < FALLBACK_MIN_CONDITIONING):
        res.status = "degenerate"
    elif trans > cfg.max_speed * dt or rot > cfg.max_angular_speed_deg * dt:
        res.status = "implausible_motion"
    if not res.ok:
        res.diag.path = "none"
    return res


def _rgbd_image(f: FrameFeatures, s: int) -> o3d.t.geometry.RGBDImage:
    """Open3D RGB-D image (intensity in [0, 1], depth in m) of every ``s``-th pixel of a frame."""
    g = np.repeat(f.gray[::s, ::s, None].astype(np.float32) / 255.0, 3, axis=2)  # Open3D wants 3 channels
    d = np.ascontiguousarray(f.depth[::s, ::s], dtype=np.float32)
    return o3d.t.geometry.RGBDImage(o3d.t.geometry.Image(o3d.core.Tensor(g)), o3d.t.geometry.Image(o3d.core.Tensor(d)))


def rgbd_edge(i: int, j: int, fi: FrameFeatures, fj: FrameFeatures, intr: Intrinsics, cfg: TeacherConfig,
              dt: float, T_init: NDArray, chained: bool = False, depth_only: bool = False) -> EdgeEstimate:
    """Fallback 2, first step, for a pair whose colour gave no usable
    sparse estimate; it also holds where the depth alone does not pin the motion down (e.g.
    a bare wall and the ceiling, slid along their corner): Open3D's hybrid RGB-D
    odometry (photometric and depth terms, coarse to fine at 1/2, 1/4 and 1/8 resolution),
    started at ``T_init``, ``path`` ``rgbd``. Its covariance is the point-to-plane one of
    :func:`point_to_plane_covariance` at the result: large along what the depth leaves free
    (the colour term that fixed it is not counted, so it errs on the safe side). Failed
    when too few pixels pair up, when that covariance cannot be formed or is as poorly
    conditioned as one plane's (``FALLBACK_MIN_CONDITIONING``: a textured single plane
    is refused too, conservatively), or when the motion is implausibly fast. With the hybrid
    maps and ``depth_only`` (or a frame whose grey is void, :func:`photo_pair`) the kernel's
    depth term alone aligns them."""
    if fi.dense.photo is not None and fj.dense.photo is not None:
        try:
            T, fitness = pyramid_align(T_init, fi.dense, fj.dense, coarse=not chained, depth_only=depth_only)
        except RuntimeError as exc:
            return EdgeEstimate(i, j, "degenerate" if "Singular" in str(exc) else "few_matches",
                                diag=EdgeDiagnostics(error=str(exc)[-200:]))
        return _rgbd_checked(i, j, T, fitness, fi, fj, cfg, dt)
    s = 2
    K = np.array(intr.K, dtype=np.float64)
    K[:2] /= s
    crit = [o3d.t.pipelines.odometry.OdometryConvergenceCriteria(n) for n in (10, 5, 3)]
    try:
        out = o3d.t.pipelines.odometry.rgbd_odometry_multi_scale(
            _rgbd_image(fj, s), _rgbd_image(fi, s), o3d.core.Tensor(K), o3d.core.Tensor(np.asarray(T_init, np.float64)),
            1.0, DEPTH_MAX, crit, o3d.t.pipelines.odometry.Method.Hybrid)
    except RuntimeError as exc:
        return EdgeEstimate(i, j, "degenerate" if "Singular" in str(exc) else "few_matches",
                            diag=EdgeDiagnostics(error=str(exc)[-200:]))
    return _rgbd_checked(i, j, geo.orthonormalize(out.transformation.numpy()), float(out.fitness), fi, fj, cfg, dt)


def _rgbd_checked(i: int, j: int, T: NDArray, fitness: float, fi: FrameFeatures, fj: FrameFeatures,
                  cfg: TeacherConfig, dt: float) -> EdgeEstimate:
    """The ``rgbd`` edge of a hybrid alignment's result, with its covariance and checks."""
    res = EdgeEstimate(i, j, "ok", T_i_j=T, diag=EdgeDiagnostics("rgbd", dense=DenseOutcome(True, fitness, 0)))
    if not np.all(np.isfinite(T)) or fitness < DENSE_MIN_FITNESS:
        res.status, res.diag.path = "few_matches", "none"
        return res
    # every 2nd point on the hybrid path (it runs for every edge of a starved scene); all
    # of them on Open3D's multi-scale path, as before
    stride = 2 if fi.dense.photo is not None else 1
    cov, n_pairs, rmse = point_to_plane_covariance(T, fi.dense, fj.dense, stride=stride)
    trans, rot = float(np.linalg.norm(T[:3, 3])), geo.rotation_angle_deg(T)
    res.cov, res.matches, res.inliers, res.inlier_ratio = cov, n_pairs, n_pairs, fitness
    res.diag.trans_m, res.diag.rot_deg, res.diag.rmse_m = trans, rot, rmse
    if cov is not None:
        res.diag.conditioning = conditioning(cov, fj.dense)
    if cov is None or np.linalg.eigvalsh(cov).min() <= 0 or res.diag.conditioning < FALLBACK_MIN_CONDITIONING:
        res.status = "degenerate"  # e.g. one plane of one colour: nothing pins the slide along it
    elif trans > cfg.max_speed * dt or rot > cfg.max_angular_speed_deg * dt:
        res.status = "implausible_motion"
    if not res.ok:
        res.diag.path = "none"
    return res

