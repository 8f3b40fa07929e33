"""Two-frame RGB-D odometry: the edge estimator, a short sequence of named steps.

1. the keypoint estimate (:mod:`teacher.matching`, :mod:`teacher.sparse`): feature tracks,
   guided, exhaustive, then wide matching, each followed by PnP-RANSAC and the two-way
   refinement, until one passes its checks;
2. a gap-1 edge beside a frame whose colour shows an earlier moment than its depth: the
   depth alone (:func:`teacher.fallbacks.rgbd_edge`, ``depth_only``);
3. no keypoint estimate: the dense fallbacks (:mod:`teacher.fallbacks`);
4. a good one: the dense step (:func:`teacher.dense.dense_refine`), and where its depth stage
   disagrees with the keypoints, the rgbd fallback in their place. Not on a gap-1 edge whose
   dense step would be the depth alone (no photometric maps) and whose colour is registered
   to the depth (TUM RGB-D): between consecutive frames the point-to-plane alignment is
   pulled towards the identity, while the keypoints measure the same moments. On TUM
   fr3/teddy (motion capture, validation) the step took about 14 % of the yaw off every gap-1
   edge (the keypoint estimate 3 %, the ground truth's own noise); without it the teacher pose
   graph's ATE falls from 8.0 to 6.8 mm. The longer window edges keep the step: without it,
   with their feature tracks bundle-adjusted (:mod:`teacher.observations`), teddy's teacher
   graph went from 4.26 / 6.55 / 2.39 to 4.34 / 6.25 / 2.68 mm (ATE / 1 s / gap-1 RPE), worse
   in two figures of three, for a teacher 19 % faster. Where a separate colour camera is
   exposed at other moments than the depth (7-Scenes, whose ground truth follows the depth)
   the step measures the depth's moments and stays: without it redkitchen 0:450's gap-1 RPE
   rose 3.68 -> 3.88 mm (``python -m bench.dense_gap1``, record dense-gap1).

Conventions (docs/conventions.md): ``T_i_j`` maps frame-j camera coordinates into frame i;
the covariance is in the project tangent order (v, w), right perturbation at ``T_i_j``.
"""

from __future__ import annotations

import logging

import numpy as np
from numpy.typing import NDArray

from ctcvo.data.sequence import Intrinsics
from ctcvo.teacher.config import TeacherConfig
from ctcvo.teacher.dense import dense_disagrees, dense_refine
from ctcvo.teacher.fallbacks import dense_edge, rgbd_edge, rgbd_starts
from ctcvo.teacher.features import FrameFeatures, beside_colour_repeat
from ctcvo.teacher.matching import match, match_wide
from ctcvo.teacher.record import EdgeEstimate
from ctcvo.teacher.sparse import MIN_MATCHES, sparse_estimate
from ctcvo.teacher.timing import cov_to_depth_moments, depth_moved, rolling_shutter_views, to_colour_moments, to_depth_moments

log = logging.getLogger(__name__)


def estimate_edge(i: int, j: int, fi: FrameFeatures, fj: FrameFeatures, intr: Intrinsics,
                  cfg: TeacherConfig, dt: float, T_pred: NDArray | None = None,
                  tracks: NDArray[np.int64] | None = None,
                  T_alt: NDArray | None = None, span: float | None = None, gap1: bool = False) -> EdgeEstimate:
    """:func:`_estimate_edge`, with a debug line per edge (``-v``): how it was made."""
    res = _estimate_edge(i, j, fi, fj, intr, cfg, dt, T_pred, tracks, T_alt, span, gap1)
    if log.isEnabledFor(logging.DEBUG):
        log.debug("edge %d->%d: %s", i, j, describe(res))
    return res


def describe(res: EdgeEstimate) -> str:
    """One line on an edge: status, matches, inliers, the path (which fallback), why the
    steps before it did not take it, and the dense step's fitness."""
    d = res.diag
    parts = [res.status, f"{res.matches} matches, {res.inliers} inliers", f"path {d.path}"]
    parts += [f"{k} {v}" for k, v in (("keypoints", d.sparse_status), ("depth step", d.depth_step),
                                      ("rgbd fallback", d.rgbd_fallback), ("dense fallback", d.dense_fallback),
                                      ("error", d.error)) if v]
    if d.dense is not None:
        parts.append(f"dense step {'taken' if d.dense.accepted else 'rejected'}, fitness {d.dense.fitness:.3f}, "
                     f"moved {1000 * d.dense.shift_m:.1f} mm / {d.dense.shift_deg:.2f} deg")
    return ", ".join(parts)


def _estimate_edge(i: int, j: int, fi: FrameFeatures, fj: FrameFeatures, intr: Intrinsics,
                   cfg: TeacherConfig, dt: float, T_pred: NDArray | None = None,
                   tracks: NDArray[np.int64] | None = None,
                   T_alt: NDArray | None = None, span: float | None = None, gap1: bool = False) -> EdgeEstimate:
    """Estimate ``T_i_j`` between two frames (ids ``i``, ``j``, ``dt`` seconds apart).

    ``dt`` bounds the keypoint estimates' plausibility tests (``cfg.max_speed`` /
    ``cfg.max_angular_speed_deg``), ``span`` (default ``dt``) the dense alignments': the most
    seconds the motion can span, from the earliest moment frame i's images show to frame j's
    timestamp. ``tracks``: (M, 2) keypoint index pairs chained along the gap-1 matches (a
    longer edge); ``T_pred``: the motion prediction; ``T_alt``: a second start of a gap-1
    edge's rgbd fallback (:func:`teacher.fallbacks.rgbd_starts`). ``gap1``: the frames are
    consecutive; a good keypoint estimate of a registered colour camera then skips a dense
    step that would be the depth alone (step 4 of the module's docstring).

    ``T_pred``, ``T_alt`` and the result are motions between the frames' colour moments; the
    dense steps align depth maps, so they start from the motion between the depth moments
    and their results are moved back (:mod:`teacher.timing`).
    """
    span = dt if span is None else span
    rolling = rolling_shutter_views(fi, fj, intr, cfg)
    best = _keypoint_estimate(i, j, fi, fj, intr, cfg, dt, T_pred, tracks, rolling)
    if fi.dense is None or fj.dense is None:
        return best
    T0 = to_depth_moments(np.eye(4) if T_pred is None else T_pred, fi, fj, dt)
    alt = None if tracks is not None or T_alt is None else to_depth_moments(T_alt, fi, fj, dt)
    if tracks is None and _has_photo(fi, fj) and beside_colour_repeat(fi, fj):
        depth = _depth_alone(i, j, fi, fj, intr, cfg, dt, span, T0, best)
        if depth is not None:
            return depth
    if not best.ok:
        return _dense_fallbacks(i, j, fi, fj, intr, cfg, dt, span, T0, alt, best,
                                chained=tracks is not None and T_pred is not None)
    if gap1 and fi.registered and fj.registered and not _has_photo(fi, fj):
        return best  # no point-to-plane step over one frame (the module's docstring, step 4)
    _dense_step(best, fi, fj, cfg, dt, rolling, hybrid=tracks is None)
    if T_pred is not None and dense_disagrees(best.diag.dense) and _has_photo(fi, fj):
        # the depth, started at the keypoints' estimate, moved too far from it: the
        # keypoints may agree on a wrong motion; the rgbd fallback from the prediction
        rgbd = to_colour_moments(rgbd_starts(i, j, fi, fj, intr, cfg, span, T0, alt, chained=tracks is not None),
                                 fi, fj, dt)
        if rgbd.ok:
            rgbd.diag.sparse_status = "dense_disagrees"
            return rgbd
    return best


def _keypoint_estimate(i: int, j: int, fi: FrameFeatures, fj: FrameFeatures, intr: Intrinsics, cfg: TeacherConfig,
                       dt: float, T_pred: NDArray | None, tracks: NDArray[np.int64] | None,
                       rolling: tuple | None) -> EdgeEstimate:
    """Step 1: the first keypoint estimate that passes its checks, of the feature tracks (when
    numerous enough), guided matching (with a prediction), exhaustive matching, then the wide
    matching without the ratio test (guided, then cross-checked over all keypoints); else the
    attempt with the most inliers. All but the guided matching take the frames'
    :meth:`FrameFeatures.strongest` keypoints (a keyframe's surplus is for the guided search)."""
    attempts = []
    if tracks is not None and len(tracks) >= MIN_MATCHES:
        attempts.append(("tracks", tracks, None))
    if T_pred is not None:
        attempts.append(("guided", None, T_pred))
    attempts.append(("exhaustive", None, None))
    if T_pred is not None:
        attempts.append(("wide", None, T_pred))
    attempts.append(("crosscheck", None, None))
    best: EdgeEstimate | None = None
    for source, pairs, pred in attempts:
        if pairs is None:
            matcher = match_wide if source in ("wide", "crosscheck") else match
            a, b = (fi, fj) if source == "guided" else (fi.strongest(), fj.strongest())
            pairs = matcher(a, b, pred, intr.K)
        res = sparse_estimate(i, j, fi, fj, intr, cfg, dt, pairs, rolling)
        res.diag.source = source
        if best is None or res.inliers > best.inliers or res.ok:
            best = res
        if res.ok:
            break
    best.diag.path = best.diag.source if best.ok else "none"
    return best


def _has_photo(fi: FrameFeatures, fj: FrameFeatures) -> bool:
    """Both frames carry photometric maps (the hybrid dense method)."""
    return fi.dense.photo is not None and fj.dense.photo is not None


def _depth_alone(i: int, j: int, fi: FrameFeatures, fj: FrameFeatures, intr: Intrinsics, cfg: TeacherConfig,
                 dt: float, span: float, T0: NDArray, best: EdgeEstimate) -> EdgeEstimate | None:
    """Step 2: a gap-1 edge beside a frame whose colour shows an earlier moment than its depth:
    neither its keypoints nor its grey belong to its depth, so the depth term alone aligns
    the pair (``path`` ``depth``). None when that fails (noted in ``best.diag.depth_step``)."""
    depth = to_colour_moments(rgbd_edge(i, j, fi, fj, intr, cfg, span, T0, depth_only=True), fi, fj, dt)
    if not depth.ok:
        best.diag.depth_step = depth.status
        return None
    depth.diag.path, depth.diag.sparse_status = "depth", best.status
    depth.diag.dense.stale_stream = fi.stale or fj.stale
    depth.inlier_pairs = best.inlier_pairs if best.ok else None  # the feature tracks go on
    return depth


def _dense_fallbacks(i: int, j: int, fi: FrameFeatures, fj: FrameFeatures, intr: Intrinsics, cfg: TeacherConfig,
                     dt: float, span: float, T0: NDArray, alt: NDArray | None, best: EdgeEstimate,
                     chained: bool) -> EdgeEstimate:
    """Step 3, no keypoint estimate passed: the rgbd fallback, then the depth alignment alone;
    ``best`` (with both failures noted) when neither passes."""
    rgbd = to_colour_moments(rgbd_starts(i, j, fi, fj, intr, cfg, span, T0, alt, chained=chained), fi, fj, dt)
    rgbd.diag.sparse_status = best.status
    if rgbd.ok:
        return rgbd
    best.diag.rgbd_fallback = rgbd.status
    depth_only = to_colour_moments(dense_edge(i, j, fi.dense, fj.dense, cfg, span, T0), fi, fj, dt)
    depth_only.diag.sparse_status = best.status
    if depth_only.ok:
        return depth_only
    best.diag.dense_fallback = depth_only.status
    return best


def _dense_step(best: EdgeEstimate, fi: FrameFeatures, fj: FrameFeatures, cfg: TeacherConfig, dt: float,
                rolling: tuple | None, hybrid: bool) -> None:
    """Step 4: the dense step on a good keypoint estimate, in place, between the depth moments
    (on the rolling shutter's middle-row points where they exist); taken whole on a pair with
    a stale stream (``cfg.dense_on_stale``)."""
    stale = fi.stale or fj.stale
    moved = depth_moved(fi, fj, dt)
    if moved:  # the dense step aligns the depth maps: between their moments
        best.cov = cov_to_depth_moments(best.cov, best.T_i_j, fi, fj, dt)
        best.T_i_j = to_depth_moments(best.T_i_j, fi, fj, dt)
    di, dj = (rolling[2], rolling[3]) if rolling is not None and rolling[2] is not None \
        and rolling[3] is not None else (fi.dense, fj.dense)
    dense_refine(best, di, dj, cfg, blend=1.0 if stale and cfg.dense_on_stale else None, hybrid=hybrid)
    if moved:
        to_colour_moments(best, fi, fj, dt)
    if best.diag.dense is not None:
        best.diag.dense.stale_stream = stale
