"""Keyframe and loop edges: constraints that reach back seconds, not the window's K frames.

After the window's edges (:mod:`teacher.window`) are chained into a trajectory, a pass over
the sequence picks keyframes and adds edges between them, each estimated by the same
estimator as the window's (:func:`teacher.odometry.estimate_edge`: matching, PnP,
refinement, dense step, covariance and the fallbacks):

1. keyframes: frame 0, then a frame whose chained motion from the last keyframe exceeds
   :data:`KF_TRANS_M` or :data:`KF_ROT_DEG`, or whose depth, projected into the last keyframe,
   overlaps it less than :data:`KF_MIN_OVERLAP`; never a frame of which one image repeats
   the previous frame's and the other does not (a dropped image of one stream,
   :func:`teacher.features.stale_stream`): its keypoints would be lifted with the depth of
   another moment, and every edge it makes would carry that motion (synthetic/lab 0:300,
   validation: the 6 keyframe edges of frame 19, a repeated colour image, 12-14 mm off the
   ground truth against 1-2 mm for the others; the window aligns such frames by the depth);
2. ``keyframe`` edges: from each keyframe to up to :data:`MAX_COVISIBLE` earlier keyframes
   within :data:`REACH_S` seconds (and beyond the window's gaps) that still see the same
   surfaces: the projected overlap of the depth, by the chained poses, at least
   :data:`COVISIBLE_OVERLAP`; predicted by the chained motion;
3. ``loop`` edges (:mod:`teacher.loops`): keyframes older than :data:`REACH_S` that look
   alike (place recognition), verified geometrically.

Keyframe and loop edges are corrected for the rolling shutter as the window's longer edges
are (:func:`teacher.timing.rolling_shutter_views`), at each keyframe's velocity from the pose
estimates (:attr:`KeyframeSelector.velocity`, in and out of the keyframe alike, as online has
no later frame yet). On the validation ranges the keyframe edges' median error fell (synthetic/
lab 0:300 4.1 -> 2.8 mm, 0.18 -> 0.11 deg) and the graph's 1 s RPE with it (then over
non-overlapping pairs: lab 4.8 -> 4.0 mm, redkitchen 350:450 17.3 -> 16.2, fr3/teddy 11.4 ->
11.2; redkitchen 0:450 20.6 -> 21.0), its ATE on the real ranges too (0:450 27.6 -> 25.7,
350:450 13.8 -> 13.6, teddy 5.7 -> 5.1).

A keyframe edge made by a dense fallback (``diag.path`` ``depth``, ``rgbd`` or ``dense``: the
keypoints starved) must agree with its prediction within :data:`FALLBACK_GATE_M` /
:data:`FALLBACK_GATE_DEG` (:func:`gate_fallback`; else status ``fallback_disagrees``). A depth
alignment seconds long can converge to a wrong minimum the pose graph's rules do not catch:
on fr3/teddy (validation) 4 of the 7 fallback keyframe edges were 97-172 mm off the ground
truth, and the gate took the graph's ATE there from 6.8 to 6.0 mm with keyframe edges
weighed as window edges; redkitchen 0:450, 350:450 and synthetic/lab were unchanged (record
``keyframes`` at b9df11e, variant "no fallback gate"). At kinect-v1's keyframe factor 0.5
(:data:`teacher.covariance_model.KEYFRAME_SCALES`) the graph's outlier pass rejected those
edges too; at 0.25 it does not, and without the gate teddy's ATE is 6.1 mm, not 4.9 (record
``keyframes`` at 410f99c). Dropping every fallback keyframe edge instead cost lab 1.1 mm; a
0.1 m gate gives the same figures. Since TUM's keyframes extract more features
(:func:`keyframe_orb`) no teddy keyframe edge falls back, and the gate changes no validation
range (record ``keyframes`` at 3807a40); it stays for the edges that still starve.

The constants were swept one at a time on the validation ranges (redkitchen 0:450 and
350:450, fr3/teddy, synthetic/lab) by ``python -m bench.keyframes`` (record
``bench/results/keyframes.json``); only :data:`KF_TRANS_M` moved (0.10 -> 0.05 m), the others
stayed where no value was better on every range. On by default (``TeacherConfig.keyframes``).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from ctcvo.data import geometry as geo
from ctcvo.data.sequence import Intrinsics, Sequence
from ctcvo.teacher.config import TeacherConfig
from ctcvo.teacher.features import FrameFeatures, extract, image_keys, make_orb, stale_stream
from ctcvo.teacher.loops import loop_candidates, thumbnail, verify
from ctcvo.teacher.observations import attach_points
from ctcvo.teacher.odometry import estimate_edge
from ctcvo.teacher.record import EdgeEstimate
from ctcvo.teacher.timing import rolling_shutter_for

KF_TRANS_M = 0.05  # new keyframe after this much translation (m); swept on validation, see the module doc
KF_ROT_DEG = 10.0  # ... or this much rotation (deg)
KF_MIN_OVERLAP = 0.7  # ... or when less of its depth projects into the last keyframe
COVISIBLE_OVERLAP = 0.4  # an earlier keyframe still sees this much of a keyframe's depth
REACH_S = 6.0  # keyframe edges reach this far back (s); older keyframes are loop candidates
MAX_COVISIBLE = 3  # keyframe edges per keyframe
FALLBACK_GATE_M = 0.05  # a fallback's keyframe edge may disagree with its prediction this much (m) ...
FALLBACK_GATE_DEG = 3.0  # ... and this much (deg)
_FALLBACK_PATHS = ("depth", "rgbd", "dense")
REGISTERED_FEATURE_FACTOR = 3  # keyframe features over cfg.n_features, colour registered to the depth (keyframe_orb)
SEPARATE_FEATURE_FACTOR = 1  # ... with a separate colour camera (7-Scenes, the synthetic rooms)
_STRIDE = 8  # depth pixels sampled for the overlap (every 8th row and column)


class KeyframeORB:
    """The keyframes' ORB detector (:func:`keyframe_orb`): keypoints strongest first (by
    response) when there is a surplus, ``searched`` of them for the searches without a
    prediction (None: all)."""

    def __init__(self, cfg: TeacherConfig, factor: int) -> None:
        self.orb = make_orb(dataclasses.replace(cfg, n_features=cfg.n_features * factor))
        self.searched = cfg.n_features if factor > 1 else None

    def detectAndCompute(self, gray: NDArray[np.uint8], mask: None) -> tuple:  # noqa: N802 - OpenCV's name
        kps, desc = self.orb.detectAndCompute(gray, mask)
        if self.searched is None or desc is None or not kps:
            return kps, desc
        order = np.argsort([-k.response for k in kps], kind="stable")
        return [kps[k] for k in order], desc[order]


def keyframe_orb(cfg: TeacherConfig, colour: object | None) -> KeyframeORB:
    """The ORB detector of the keyframes' features: ``cfg.n_features`` times
    :data:`REGISTERED_FEATURE_FACTOR` where the colour is registered to the depth (``colour``
    None: TUM RGB-D), times :data:`SEPARATE_FEATURE_FACTOR` with a separate colour camera.
    The surplus serves the guided search, which a prediction keeps cheap; the searches without
    one (a loop candidate's, a starved edge's) take the strongest ``cfg.n_features``, as the
    window's frames have (:meth:`FrameFeatures.strongest`): all of 3000 made the keyframe pass
    on fr1/xyz twice as long (5.8 -> 12.1 s) for the exhaustive matching.

    Why: a keyframe edge's rotation over seconds rests on how many keypoints it matches where
    the dense step is the depth alone and the ground truth does not follow the depth. On
    fr3/teddy 0:200 (validation, motion capture) 1000 features left 4 keyframe edges to the
    dense fallbacks and others on 60-90 matches; with 3000 none fell back, the keyframe edges'
    RMS error fell 0.75 -> 0.61 deg and 14.1 -> 5.2 mm, and the graph's 1 s RPE 8.7 -> 7.3 mm
    (2000: 7.7; 4000: 7.3), gap-1 2.66 -> 2.64, ATE level (4.9). On redkitchen (a separate
    colour camera exposed at other moments than the depth, ground truth from the depth) more
    keypoints weigh the dense step down: with 2000, 0:450's ATE 24.0 -> 25.0 and 1 s RPE 21.7
    -> 24.0 mm; the synthetic rooms were level (record ``keyframes`` at 3807a40, variants
    ``*_FEATURE_FACTOR``)."""
    factor = REGISTERED_FEATURE_FACTOR if colour is None else SEPARATE_FEATURE_FACTOR
    return KeyframeORB(cfg, factor)


def keyframe_features(rgb: NDArray[np.uint8], depth: NDArray[np.float32], cfg: TeacherConfig, orb: KeyframeORB,
                      K: NDArray[np.float64], colour: object | None) -> FrameFeatures:
    """A keyframe's features: :func:`teacher.features.extract` with the detector of
    :func:`keyframe_orb`, its ``searched`` count noted."""
    f = extract(rgb, depth, cfg, orb, K, colour)
    f.searched = orb.searched
    return f


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


def is_new_keyframe(T_last_k: NDArray[np.float64], pts_k: NDArray[np.float64], intr: Intrinsics) -> bool:
    """Whether frame k, at ``T_last_k`` from the last keyframe, with depth points ``pts_k``
    (:func:`depth_points`), is a new keyframe (the criteria of the module's docstring)."""
    t, r = float(np.linalg.norm(T_last_k[:3, 3])), geo.rotation_angle_deg(T_last_k)
    return t > KF_TRANS_M or r > KF_ROT_DEG or overlap(pts_k, T_last_k, intr) < KF_MIN_OVERLAP


@dataclass(frozen=True)
class Keyframe:
    """A keyframe as :class:`KeyframeHistory` keeps it."""

    pos: int
    """Its position among the frames (taken, online)."""
    frame_id: int
    time: float
    T_world_cam: NDArray[np.float64]
    """The pose estimate it was picked with (batch: the chained pose; online: its causal estimate)."""
    pts: NDArray[np.float64]
    """(M, 3) :func:`depth_points`."""
    thumb: NDArray[np.float64]
    """:func:`teacher.loops.thumbnail` of its colour image."""
    velocity: NDArray[np.float64] | None = None
    """(6,) the camera's body velocity ``(v, w)`` per second into it, from the pose estimates
    (:attr:`KeyframeSelector.velocity`), for the rolling shutter correction of its edges;
    None: unknown (then uncorrected)."""


@dataclass(frozen=True)
class KeyframeWork:
    """The edges a new keyframe ``b`` asks for, to be estimated (:func:`estimate_work`)."""

    b: Keyframe
    covisible: list[Keyframe]
    """``keyframe`` edges: earlier keyframes within :data:`REACH_S`, beyond the window's gaps,
    that see at least :data:`COVISIBLE_OVERLAP` of b's depth; newest first, at most
    :data:`MAX_COVISIBLE`."""
    loops: list[Keyframe]
    """``loop`` edges: keyframes older than :data:`REACH_S` that look like b
    (:func:`teacher.loops.loop_candidates`), best first."""


class KeyframeSelector:
    """Frame by frame, which frames are keyframes: frame 0, then each frame that
    :func:`is_new_keyframe` against the last keyframe, but for a frame with one stream's image
    repeated (see the module's docstring). Holds only the last keyframe, so it can decide on a
    frame's critical path while a :class:`KeyframeHistory` elsewhere (e.g. in a helper
    thread) works on the keyframes it picked."""

    def __init__(self, intr: Intrinsics) -> None:
        self.intr = intr
        self.last: tuple[NDArray[np.float64], NDArray[np.float64]] | None = None
        self.prev: tuple[NDArray[np.float64], tuple[bytes, bytes] | None, float | None, bool] | None = None
        self.velocity: NDArray[np.float64] | None = None
        """After :meth:`offer`: the body velocity into the frame offered, ``log(T_prev^-1 T) / dt``
        from the previous frame's pose estimate, where both frames show new images (neither
        repeats an image of the frame before it) and the time between them is known (as the
        window measures it from the gap-1 edge); else None."""

    def offer(self, T_world_cam: NDArray[np.float64], pts: NDArray[np.float64],
              keys: tuple[bytes, bytes] | None = None, time: float | None = None) -> bool:
        """Whether the next frame (its pose estimate, its :func:`depth_points`, the
        :func:`teacher.features.image_keys` of its images and its timestamp; None: unknown,
        taken as new) is a keyframe; if so it becomes the last one."""
        prev, fresh = self.prev, True
        if prev is not None and keys is not None and prev[1] is not None:
            fresh = keys[0] != prev[1][0] and keys[1] != prev[1][1]
        self.velocity = None
        if prev is not None and fresh and prev[3] and time is not None and prev[2] is not None and time > prev[2]:
            self.velocity = geo.se3_log(geo.relative_pose(prev[0], T_world_cam)) / (time - prev[2])
        self.prev = (np.asarray(T_world_cam), keys, time, fresh)
        if prev is not None and keys is not None and prev[1] is not None and stale_stream(prev[1], keys):
            return False
        if self.last is not None and not is_new_keyframe(geo.relative_pose(self.last[0], T_world_cam), pts,
                                                         self.intr):
            return False
        self.last = (T_world_cam, pts)
        return True


class KeyframeHistory:
    """The keyframes so far, and for each new one the work that gives its edges
    (:class:`KeyframeWork`): covisible keyframes by the projected overlap of the depth under
    the keyframes' pose estimates, loop candidates by place recognition. ``gaps``: the
    window's (keyframe edges reach beyond it)."""

    def __init__(self, intr: Intrinsics, gaps: int) -> None:
        self.intr, self.gaps = intr, gaps
        self.keyframes: list[Keyframe] = []

    def add(self, b: Keyframe) -> KeyframeWork:
        """Record keyframe ``b`` (after every earlier one) and return its work."""
        covisible = []
        for a in reversed(self.keyframes):
            if len(covisible) == MAX_COVISIBLE:
                break
            if (b.pos - a.pos > self.gaps and b.time - a.time <= REACH_S
                    and overlap(b.pts, geo.relative_pose(a.T_world_cam, b.T_world_cam), self.intr) >= COVISIBLE_OVERLAP):
                covisible.append(a)
        old = {a.pos: a for a in self.keyframes if b.time - a.time > REACH_S}
        thumbs = {p: a.thumb for p, a in old.items()} | {b.pos: b.thumb}
        loops = [old[p] for p in loop_candidates(b.pos, list(old), thumbs)]
        self.keyframes.append(b)
        return KeyframeWork(b, covisible, loops)


def gate_fallback(e: EdgeEstimate, T_pred: NDArray[np.float64]) -> EdgeEstimate:
    """``e`` as a keyframe edge: a good edge made by a dense fallback that disagrees with the
    chained prediction ``T_pred`` by more than :data:`FALLBACK_GATE_M` or
    :data:`FALLBACK_GATE_DEG` is marked ``fallback_disagrees``; any other edge is returned
    as it is."""
    if not e.ok or e.diag.path not in _FALLBACK_PATHS or geo.agrees(T_pred, e.T_i_j, FALLBACK_GATE_M, FALLBACK_GATE_DEG):
        return e
    return dataclasses.replace(e, status="fallback_disagrees")


def _moving(f: FrameFeatures, kf: Keyframe) -> FrameFeatures:
    """Keyframe ``kf``'s features ``f`` with its velocity, in and out (a constant velocity over
    its readout), for the rolling shutter correction (:func:`teacher.timing.rolling_shutter_views`)."""
    if f.velocity_in is None and f.velocity_out is None and kf.velocity is not None:
        f.velocity_in = f.velocity_out = kf.velocity
    return f


def estimate_work(work: KeyframeWork, features_of: Callable[[int], FrameFeatures], intr: Intrinsics,
                  cfg: TeacherConfig) -> list[tuple[EdgeEstimate, str]]:
    """The edges of a :class:`KeyframeWork` by :func:`teacher.odometry.estimate_edge`
    (``features_of(pos)``: a keyframe's features, extracted as the window extracts them):
    ``keyframe`` edges predicted by the pose estimates, ``loop`` edges verified against them
    (:func:`teacher.loops.verify`), fallbacks' keyframe edges gated (:func:`gate_fallback`).
    Good edges carry their inliers' points (:func:`teacher.observations.attach_points`).
    Returns (edge, kind) pairs; failed edges are kept."""
    b, out = work.b, []
    for a in work.covisible:
        T_pred = geo.relative_pose(a.T_world_cam, b.T_world_cam)
        fa, fb = _moving(features_of(a.pos), a), _moving(features_of(b.pos), b)
        e = estimate_edge(a.frame_id, b.frame_id, fa, fb, intr, cfg, b.time - a.time, T_pred=T_pred)
        out.append((attach_points(gate_fallback(e, T_pred), fa, fb, intr, cfg), "keyframe"))
    for a in work.loops:
        fa, fb = _moving(features_of(a.pos), a), _moving(features_of(b.pos), b)
        e = estimate_edge(a.frame_id, b.frame_id, fa, fb, intr, cfg, b.time - a.time)
        out.append((attach_points(verify(e, geo.relative_pose(a.T_world_cam, b.T_world_cam)), fa, fb, intr, cfg), "loop"))
    return out


def keyframe_works(seq: Sequence, cfg: TeacherConfig, poses: NDArray[np.float64],
                   looks: dict[int, tuple[NDArray, NDArray, tuple]] | None = None) -> list[KeyframeWork]:
    """The keyframes of a sequence whose window edges chained to ``poses`` (T_world_cam by
    position) and the work of each, in order, none estimated yet: the frames are fed one by
    one to :class:`KeyframeSelector` and :class:`KeyframeHistory`, as ``ctcvo online`` feeds
    them. ``looks``: by frame id, the :func:`depth_points`, :func:`teacher.loops.thumbnail`
    and :func:`teacher.features.image_keys` the window pass computed while it had the images
    (a frame without one is read again)."""
    intr, ids, times = seq.intrinsics, seq.ids(), seq.times()
    sel, history, works = KeyframeSelector(intr), KeyframeHistory(intr, cfg.gaps), []
    for k in range(len(seq)):
        look = (looks or {}).get(int(ids[k]))
        if look is None:
            rgb, depth = seq.rgb(k), seq.depth(k)
            pts, thumb, keys = depth_points(depth, intr), None, image_keys(rgb, depth)
        else:
            (pts, thumb, keys), rgb = look, None
        if sel.offer(poses[k], pts, keys, float(times[k])):
            thumb = thumb if thumb is not None else thumbnail(rgb)
            works.append(history.add(Keyframe(k, int(ids[k]), float(times[k]), poses[k], pts, thumb, sel.velocity)))
    return works


def estimate_works(works: list[KeyframeWork], features_of: Callable[[int], FrameFeatures], intr: Intrinsics,
                   cfg: TeacherConfig) -> list[tuple[EdgeEstimate, str]]:
    """:func:`estimate_work` of each of ``works`` in order, each keyframe's features
    extracted once (``features_of(pos)``, as the window extracts them)."""
    feats: dict[int, FrameFeatures] = {}

    def f(k: int) -> FrameFeatures:
        if k not in feats:
            feats[k] = features_of(k)
        return feats[k]

    return [x for w in works for x in estimate_work(w, f, intr, cfg)]


def merge_keyframe_edges(edges: list[EdgeEstimate], found: list[tuple[EdgeEstimate, str]]) -> dict[tuple[int, int], str]:
    """Append the edges of ``found`` ((edge, kind) pairs) whose frame pair ``edges`` does not
    hold yet to ``edges``; returns their kinds by (i, j)."""
    have = {(e.i, e.j) for e in edges}
    kinds: dict[tuple[int, int], str] = {}
    for e, kind in found:
        if (e.i, e.j) not in have:
            have.add((e.i, e.j))
            edges.append(e)
            kinds[(e.i, e.j)] = kind
    return kinds


def add_keyframe_edges(seq: Sequence, cfg: TeacherConfig, edges: list[EdgeEstimate], poses: NDArray[np.float64],
                       features_of: Callable[[int], FrameFeatures]) -> dict[tuple[int, int], str]:
    """Append the :func:`keyframe_edges` of a frame pair ``edges`` does not hold yet to
    ``edges``; returns their kinds by (i, j)."""
    return merge_keyframe_edges(edges, keyframe_edges(seq, cfg, poses, features_of))


def keyframe_edges(seq: Sequence, cfg: TeacherConfig, poses: NDArray[np.float64],
                   features_of: Callable[[int], FrameFeatures]) -> list[tuple[EdgeEstimate, str]]:
    """The ``keyframe`` and ``loop`` edges of a sequence whose window edges chained to
    ``poses`` (:func:`keyframe_works`, then :func:`estimate_works`); ``features_of(k)``: a
    frame's features. Returns (edge, kind) pairs; failed edges are kept."""
    cfg = dataclasses.replace(cfg, rolling_shutter_s=rolling_shutter_for(seq.sensor, cfg))
    return estimate_works(keyframe_works(seq, cfg, poses), features_of, seq.intrinsics, cfg)
