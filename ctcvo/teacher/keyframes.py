"""Keyframe and loop edges: constraints that reach back seconds, not the window's K frames.

After the window's edges (:mod:`teacher.window`) are chained into a trajectory, a pass over
the sequence picks keyframes and adds edges between them, each estimated by the same
estimator as the window's (:func:`teacher.odometry.estimate_edge`: matching, PnP,
refinement, dense step, covariance and the fallbacks):

1. keyframes: frame 0, then a frame whose chained motion from the last keyframe exceeds
   :data:`KF_TRANS_M` or :data:`KF_ROT_DEG`, or whose depth, projected into the last keyframe,
   overlaps it less than :data:`KF_MIN_OVERLAP`;
2. ``keyframe`` edges: from each keyframe to up to :data:`MAX_COVISIBLE` earlier keyframes
   within :data:`REACH_S` seconds (and beyond the window's gaps) that still see the same
   surfaces: the projected overlap of the depth, by the chained poses, at least
   :data:`COVISIBLE_OVERLAP`; predicted by the chained motion;
3. ``loop`` edges (:mod:`teacher.loops`): keyframes older than :data:`REACH_S` that look
   alike (place recognition), verified geometrically.

The constants were swept one at a time on the validation ranges (redkitchen 0:450 and
350:450, fr3/teddy, synthetic/lab) by ``python -m bench.keyframes`` (record
``bench/results/keyframes.json``); only :data:`KF_TRANS_M` moved (0.10 -> 0.05 m), the others
stayed where no value was better on every range. On by default (``TeacherConfig.keyframes``).
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
from numpy.typing import NDArray

from ctcvo.data import geometry as geo
from ctcvo.data.sequence import Intrinsics, Sequence
from ctcvo.teacher.config import TeacherConfig
from ctcvo.teacher.features import FrameFeatures
from ctcvo.teacher.loops import find_loops, thumbnail
from ctcvo.teacher.odometry import estimate_edge
from ctcvo.teacher.record import EdgeEstimate

KF_TRANS_M = 0.05  # new keyframe after this much translation (m); swept on validation, see the module doc
KF_ROT_DEG = 10.0  # ... or this much rotation (deg)
KF_MIN_OVERLAP = 0.7  # ... or when less of its depth projects into the last keyframe
COVISIBLE_OVERLAP = 0.4  # an earlier keyframe still sees this much of a keyframe's depth
REACH_S = 6.0  # keyframe edges reach this far back (s); older keyframes are loop candidates
MAX_COVISIBLE = 3  # keyframe edges per keyframe
_STRIDE = 8  # depth pixels sampled for the overlap (every 8th row and column)


def depth_points(depth: NDArray[np.float32], intr: Intrinsics) -> NDArray[np.float64]:
    """(M, 3) camera points of every :data:`_STRIDE`-th valid depth pixel."""
    d = depth[::_STRIDE, ::_STRIDE].astype(np.float64)
    v, u = np.mgrid[0:depth.shape[0]:_STRIDE, 0:depth.shape[1]:_STRIDE]
    ok = np.isfinite(d) & (d > 0)
    z, u, v = d[ok], u[ok], v[ok]
    return np.stack([(u - intr.cx) * z / intr.fx, (v - intr.cy) * z / intr.fy, z], axis=1)


def overlap(pts_a: NDArray[np.float64], T_b_a: NDArray[np.float64], intr: Intrinsics) -> float:
    """The fraction of frame a's depth points that land in front of camera b, in its image."""
    if len(pts_a) == 0:
        return 0.0
    p = pts_a @ T_b_a[:3, :3].T + T_b_a[:3, 3]
    z = p[:, 2]
    front = z > 1e-6
    u = intr.fx * p[front, 0] / z[front] + intr.cx
    v = intr.fy * p[front, 1] / z[front] + intr.cy
    inside = (u >= 0) & (u < intr.width) & (v >= 0) & (v < intr.height)
    return float(np.count_nonzero(inside)) / len(pts_a)


def pick_keyframes(seq: Sequence, poses: NDArray[np.float64]) -> tuple[list[int], dict[int, NDArray]]:
    """Positions of the keyframes, and their depth points (see the module's docstring)."""
    intr = seq.intrinsics
    kfs, pts = [0], {0: depth_points(seq.depth(0), intr)}
    for k in range(1, len(seq)):
        last = kfs[-1]
        T = geo.relative_pose(poses[last], poses[k])  # T_last_k
        t, r = float(np.linalg.norm(T[:3, 3])), geo.rotation_angle_deg(T)
        moved = t > KF_TRANS_M or r > KF_ROT_DEG
        pk = depth_points(seq.depth(k), intr)
        if moved or overlap(pk, T, intr) < KF_MIN_OVERLAP:
            kfs.append(k)
            pts[k] = pk
    return kfs, pts


def add_keyframe_edges(seq: Sequence, cfg: TeacherConfig, edges: list[EdgeEstimate], poses: NDArray[np.float64],
                       features_of: Callable[[int], FrameFeatures]) -> dict[tuple[int, int], str]:
    """Append the :func:`keyframe_edges` of a frame pair ``edges`` does not hold yet to
    ``edges``; returns their kinds by (i, j)."""
    have = {(e.i, e.j) for e in edges}
    kinds: dict[tuple[int, int], str] = {}
    for e, kind in keyframe_edges(seq, cfg, poses, features_of):
        if (e.i, e.j) not in have:
            have.add((e.i, e.j))
            edges.append(e)
            kinds[(e.i, e.j)] = kind
    return kinds


def keyframe_edges(seq: Sequence, cfg: TeacherConfig, poses: NDArray[np.float64],
                   features_of: Callable[[int], FrameFeatures]) -> list[tuple[EdgeEstimate, str]]:
    """The ``keyframe`` and ``loop`` edges of a sequence whose window edges chained to
    ``poses`` (T_world_cam by position); ``features_of(k)``: a frame's features (extracted
    as the window extracts them). Returns (edge, kind) pairs; failed edges are kept."""
    intr, ids, times = seq.intrinsics, seq.ids(), seq.times()
    kfs, pts = pick_keyframes(seq, poses)
    feats: dict[int, FrameFeatures] = {}

    def f(k: int) -> FrameFeatures:
        if k not in feats:
            feats[k] = features_of(k)
        return feats[k]

    out: list[tuple[EdgeEstimate, str]] = []
    thumbs: dict[int, NDArray] = {}
    for n, b in enumerate(kfs):
        thumbs[b] = thumbnail(seq.rgb(b))
        near = [a for a in reversed(kfs[:n]) if b - a > cfg.gaps and times[b] - times[a] <= REACH_S]
        covisible = [a for a in near
                     if overlap(pts[b], geo.relative_pose(poses[a], poses[b]), intr) >= COVISIBLE_OVERLAP]
        for a in covisible[:MAX_COVISIBLE]:
            T_pred = geo.relative_pose(poses[a], poses[b])
            e = estimate_edge(int(ids[a]), int(ids[b]), f(a), f(b), intr, cfg,
                              float(times[b] - times[a]), T_pred=T_pred)
            out.append((e, "keyframe"))
        old = [a for a in kfs[:n] if times[b] - times[a] > REACH_S]
        for e in find_loops(b, old, thumbs, poses, seq, cfg, f):
            out.append((e, "loop"))
    return out
