"""The teacher's window over the last K frames of a stream: each new frame's edges.

One implementation for ``teacher generate`` (each chunk of a sequence,
:func:`teacher.generate.run_sequence`) and ``vo-online`` (frame by frame as frames
arrive, pipeline/online.py), so the two give the same edges bit for bit.

For each new frame k (features from :func:`teacher.features.extract`):

1. the gap-1 edge (k-1, k) is estimated with the constant-velocity prediction (the last
   good gap-1 motion, scaled to the time between the frames when a frame is missing:
   :meth:`EdgeWindow.motion_over`) guiding the matching;
2. its inlier matches extend the feature tracks of every frame in the window, and the
   gap-1 motion (or the constant-velocity guess when it failed) extends each frame's
   chained motion to the newest frame;
3. each longer edge (k-g, k), g = 2..K, is estimated from the tracks that survived from
   k-g to k, predicted by the chained motion;
4. frames more than K - 1 behind the newest leave the window.

Photometric maps (synthetic scenes' hybrid dense step) always pair a colour with the depth
of its own moment. A frame whose depth repeats the previous frame's while its colour is new
(a dropped depth frame: the depth, and the ground truth that follows it, belong to the
previous moment) takes the previous frame's photometric maps, the colour taken with that
depth; a frame whose colour repeats while its depth is new keeps only the depth of its maps
(:meth:`teacher.maps.PhotoMaps.depth_only`: nothing shows its colour's moment in depth)
and is marked ``colour_behind``, so its gap-1 edges are aligned by the depth alone; a whole
repeat of a frame takes that frame's maps and mark.

Each frame's colour and depth show a moment: the frame's timestamp, or for an image that
repeats the previous frame's, the moment it showed there (:meth:`EdgeWindow._moments_of`). The
dense alignments' plausibility bound spans from the earliest moment of an edge's first frame
to the timestamp of its last (the keypoint estimates keep the timestamps'), and the gap-1 rgbd
fallback also starts from the constant velocity between the two depth moments
(:meth:`EdgeWindow.motion_between`): out of a repeated frame the
edge spans two periods of the depth while the prediction is the repeat's identity.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from ctcvo.data import geometry as geo
from ctcvo.data.sequence import Intrinsics
from ctcvo.teacher.config import TeacherConfig
from ctcvo.teacher.features import FrameFeatures, beside_colour_repeat, stale_stream
from ctcvo.teacher.maps import PhotoMaps
from ctcvo.teacher.observations import attach_points
from ctcvo.teacher.odometry import estimate_edge
from ctcvo.teacher.record import EdgeEstimate


@dataclass
class _Entry:
    pos: int  # how many frames were added before this one
    frame_id: int
    timestamp: float
    feats: FrameFeatures
    link: NDArray[np.int64]  # keypoint of this frame -> keypoint in the newest frame (-1: lost)
    T_k_cur: NDArray[np.float64]  # chained gap-1 motion from this frame to the newest
    since: float  # the earliest moment its images show (s; before its timestamp when one repeats)
    mixed: bool  # its colour and depth show different moments (its longer edges' ``diag.mixed_moments``)


class EdgeWindow:
    """The last ``cfg.gaps`` frames of a stream, their feature tracks and chained motions.

    ``prev_keys``: the image keys (:func:`teacher.features.image_keys`) of the frame before
    the first one added, when there is one (a chunk that starts inside a sequence), so that
    a repeated image at the first frame is caught. ``until``: only edges whose first frame
    is among the first ``until`` frames added are estimated and returned (a chunk reads
    ``gaps`` frames past its end for the edges that start inside it); None: every edge.
    ``prev_photo``: with ``prev_keys``, returns the photometric maps and the ``colour_behind``
    mark of the frame before the first one, as a window that had seen the sequence from its
    start would hold them (see the module's docstring; called only when the first frame
    repeats that frame's depth). ``prev_moments``: with ``prev_keys``, returns the moments
    (colour, depth; seconds) that the frame before the first one shows (:meth:`_moments_of`; called
    only when the first frame repeats an image of that frame). ``sightings``: good gap-1
    edges between two frames of new images keep their inlier pairs and points
    (:func:`teacher.observations.attach_points`), the feature tracks of ``observations.csv``.
    """

    def __init__(self, intr: Intrinsics, cfg: TeacherConfig, prev_keys: tuple[bytes, bytes] | None = None,
                 until: int | None = None,
                 prev_photo: Callable[[], tuple[PhotoMaps | None, bool]] | None = None,
                 prev_moments: Callable[[], tuple[float, float]] | None = None, sightings: bool = False) -> None:
        self.intr, self.cfg, self.until, self.sightings = intr, cfg, until, sightings
        self.prev_keys = prev_keys
        self._prev_photo = prev_photo or (lambda: (None, False))
        self.entries: deque[_Entry] = deque()
        self.v_prev: NDArray[np.float64] | None = None  # last good gap-1 motion (constant-velocity prior)
        self.dt_prev = 0.0  # its time (s)
        # the last good gap-1 motion over one frame period of the depth (see _prediction)
        self.v_moving: NDArray[np.float64] | None = None
        self._depth_repeat = False  # the newest frame's depth repeats the one before it
        self._prev_moments = prev_moments
        self._moments: tuple[float, float] | None = None  # (colour, depth) moments of the newest frame
        # the last good gap-1 motion between two depth moments, and the time between them
        self.v_span: NDArray[np.float64] | None = None
        self.span_prev = 0.0
        self.added = 0
        self._pending: tuple | None = None  # the frame add_gap1 took, until add_longer
        # the newest frame's images are both new (:meth:`add_gap1`); the first frame's
        # predecessor is unknown here, and a frame without one is taken as new
        self._fresh = True

    def _starts_inside(self, pos: int) -> bool:
        return self.until is None or pos < self.until

    def add(self, frame_id: int, timestamp: float, fk: FrameFeatures, depth_offset: float = 0.0) -> list[EdgeEstimate]:
        """The edges ending at the new frame (failed ones included: ``e.ok`` False), the
        gap-1 edge first, then the longer ones from the oldest frame on. Sets ``fk.stale``.
        (:meth:`add_gap1` then :meth:`add_longer`.)"""
        return self.add_gap1(frame_id, timestamp, fk, depth_offset) + self.add_longer()

    def skip(self) -> None:
        """A frame of the stream that could not be read (:mod:`teacher.skips`): it takes a
        position, so the window still spans ``cfg.gaps`` frames of the stream, and the next
        frame's edges start at the frames before it (the edge from the frame before it is
        the next one's shortest, estimated as :meth:`add_gap1` estimates a gap-1 edge, with
        the constant velocity scaled to its time as for a dropped frame)."""
        if self._pending is not None:
            raise RuntimeError("EdgeWindow.add_longer() must follow add_gap1() before the next frame")
        pos, self.added = self.added, self.added + 1
        while self.entries and pos - self.entries[0].pos >= self.cfg.gaps:
            self.entries.popleft()

    def add_gap1(self, frame_id: int, timestamp: float, fk: FrameFeatures,
                 depth_offset: float = 0.0) -> list[EdgeEstimate]:
        """The first half of :meth:`add`: the gap-1 edge ending at the new frame (a list of
        it; empty for the first frame or one before ``until``'s range), and the feature
        tracks and chained motions extended to the new frame. :meth:`add_longer` must follow
        before the next frame (``vo-online`` writes the frame's pose in between).
        ``timestamp`` is the frame's colour image's; ``depth_offset`` its depth image's time
        minus that (s; see :meth:`_to_colour_moment`)."""
        if self._pending is not None:
            raise RuntimeError("EdgeWindow.add_longer() must follow add_gap1() before the next frame")
        cfg, intr = self.cfg, self.intr
        pos, self.added = self.added, self.added + 1
        prev_depth_repeat, self._depth_repeat = self._depth_repeat, False
        moments = self._moments_of(timestamp, fk)
        # both images new (not a repeat of the previous frame's): its gap-1 edges measure its velocity
        fresh = self.prev_keys is None or (fk.keys[0] != self.prev_keys[0] and fk.keys[1] != self.prev_keys[1])
        fresh_prev, self._fresh = self._fresh, fresh
        if self.prev_keys is not None:
            self._depth_repeat = fk.keys[1] == self.prev_keys[1]
            fk.stale = stale_stream(self.prev_keys, fk.keys)
            if fk.dense is not None and fk.dense.photo is not None:
                # which moments its colour and depth show (see the module's docstring)
                same_colour = fk.keys[0] == self.prev_keys[0]
                if self._depth_repeat:  # the previous frame's depth: its maps (and mark, for a whole repeat)
                    photo, behind = self._prev_photo()
                    fk.dense.photo, fk.colour_behind = photo, behind and same_colour
                elif same_colour:
                    fk.dense.photo, fk.colour_behind = fk.dense.photo.depth_only(), True
        self.prev_keys = fk.keys
        self._to_colour_moment(fk, depth_offset)
        photo = fk.dense.photo if fk.dense is not None else None
        state = (photo, fk.colour_behind)
        self._prev_photo = lambda: state
        edges: list[EdgeEstimate] = []
        e = None
        if self.entries:
            prev = self.entries[-1]
            dt = timestamp - prev.timestamp
            cv = self.motion_over(dt)
            span = moments[1] - self._moments[1]
            e = estimate_edge(prev.frame_id, frame_id, prev.feats, fk, intr, cfg, dt,
                              T_pred=self._prediction(prev.feats, fk, prev_depth_repeat, cv),
                              T_alt=self.motion_between(span),
                              span=timestamp - prev.since, gap1=True)
            if self._starts_inside(prev.pos):
                edges.append(e)
            step = e.T_i_j if e.ok else (cv if cv is not None else np.eye(4))
            if e.ok and fresh and fresh_prev and dt > 0:  # for the rolling shutter correction
                fk.velocity_in = prev.feats.velocity_out = geo.se3_log(e.T_i_j) / dt
                if self.sightings:  # at those velocities
                    attach_points(e, prev.feats, fk, intr, cfg)
            if e.ok:
                self.v_prev, self.dt_prev = e.T_i_j, dt
                if not (self._depth_repeat or prev_depth_repeat):
                    self.v_moving = e.T_i_j
                if span > 0:
                    self.v_span, self.span_prev = e.T_i_j, span
            m = np.full(len(prev.feats.uv) + 1, -1, np.int64)  # last slot maps -1 -> -1
            if e.ok and e.inlier_pairs is not None:
                m[e.inlier_pairs[:, 0]] = e.inlier_pairs[:, 1]
            for w in self.entries:
                w.link = m[w.link]
                w.T_k_cur = w.T_k_cur @ step
        self._moments = moments
        self._pending = (pos, frame_id, timestamp, fk, e)
        return edges

    def _moments_of(self, timestamp: float, fk: FrameFeatures) -> tuple[float, float]:
        """The moments (colour, depth; seconds) the new frame's images show: its timestamp, or
        for an image that repeats the previous frame's (a dropped frame of that stream) the
        moment that image showed there. The depth's moment is the ground truth's (7-Scenes'
        KinectFusion and the synthetic sensor both follow the depth camera)."""
        if self.prev_keys is None:
            return timestamp, timestamp
        same = fk.keys[0] == self.prev_keys[0], fk.keys[1] == self.prev_keys[1]
        if (same[0] or same[1]) and self._moments is None:
            self._moments = self._prev_moments() if self._prev_moments is not None else None
        if self._moments is None:
            return timestamp, timestamp
        return tuple(m if s else timestamp for m, s in zip(self._moments, same))

    def motion_between(self, span: float) -> NDArray[np.float64] | None:
        """The constant-velocity motion between two depth moments ``span`` seconds apart: the
        last good gap-1 motion between two different depth moments (``v_span``), scaled along
        its twist to ``span`` as :meth:`motion_over` scales (timestamp jitter left alone); the
        identity for a depth image that repeats the previous one (``span`` 0). Unlike
        :meth:`motion_over` it skips the identity a repeated frame's edge measured: after a
        whole or a depth repeat the edge out of it spans two periods of the depth, which the
        identity (the constant velocity then) is farthest from. None before the first such
        motion."""
        if span <= 0:
            return np.eye(4)
        if self.v_span is None or self.span_prev <= 0:
            return None
        return _scaled(self.v_span, span / self.span_prev)

    def motion_over(self, dt: float) -> NDArray[np.float64] | None:
        """The constant-velocity prediction over ``dt`` seconds: the last good gap-1 motion,
        scaled along its twist when ``dt`` is at least half again as long as that motion's
        time, or at most two thirds of it (a dropped frame; frames ``vo-online --drop-late``
        skipped). Timestamp jitter below that is left alone: it is the clock's, not the
        camera's (TUM stamps frames on arrival). None before the first good gap-1 edge."""
        if self.v_prev is None or self.dt_prev <= 0 or dt <= 0:
            return self.v_prev
        return _scaled(self.v_prev, dt / self.dt_prev)

    def _to_colour_moment(self, fk: FrameFeatures, depth_offset: float) -> None:
        """A frame whose depth was taken ``depth_offset`` seconds after its colour (before,
        when negative), with ``cfg.depth_time_compensation``: ``fk.depth_offset``, so its
        edges' dense steps align the depth maps between their moments and return to the
        colour moments at the edge's own velocity (:func:`teacher.odometry.estimate_edge`),
        and no photometric maps (they would pair the colour of one moment with the depth of
        another: its dense steps take the depth alone). Nothing changes without an offset."""
        if depth_offset == 0.0 or not self.cfg.depth_time_compensation:
            return
        fk.depth_offset = float(depth_offset)
        if fk.dense is not None:
            fk.dense.photo = None

    def _prediction(self, fi: FrameFeatures, fj: FrameFeatures, i_repeats_depth: bool,
                    cv: NDArray[np.float64] | None) -> NDArray[np.float64] | None:
        """The motion prediction of the gap-1 edge (i, j): ``cv``, the constant-velocity one
        (:meth:`motion_over`); for an edge aligned by the depth alone
        (:func:`teacher.features.beside_colour_repeat`), which converges slowly along plain
        walls and so leans on its start, the last good motion over one frame period of the
        depth instead, twice when frame i's depth (and pose) repeats the frame's before it (a
        dropped frame: the edge spans two periods). On the office and lab scenes a whole
        repeat's identity as the start left such edges 5.6-15 mm off."""
        if not beside_colour_repeat(fi, fj) or self.v_moving is None:
            return cv
        return self.v_moving @ self.v_moving if i_repeats_depth else self.v_moving

    def add_longer(self) -> list[EdgeEstimate]:
        """The second half of :meth:`add`: the edges (k-g, k), g = 2..K, of the frame
        :meth:`add_gap1` took, from the oldest frame on; the frame then enters the window."""
        if self._pending is None:
            raise RuntimeError("EdgeWindow.add_longer() without a frame from add_gap1()")
        pos, frame_id, timestamp, fk, e = self._pending
        self._pending = None
        cfg, intr = self.cfg, self.intr
        edges: list[EdgeEstimate] = []
        mixed = self._moments[0] != self._moments[1]
        if e is not None:
            for w in list(self.entries)[:-1]:  # gaps >= 2
                if not self._starts_inside(w.pos):
                    continue
                tracks = np.flatnonzero(w.link >= 0)
                tracks = np.stack([tracks, w.link[tracks]], axis=1)
                x = estimate_edge(w.frame_id, frame_id, w.feats, fk, intr, cfg, timestamp - w.timestamp,
                                  w.T_k_cur.copy(), tracks, span=timestamp - w.since)
                x.diag.mixed_moments = w.mixed or mixed
                edges.append(x)
            if e.inlier_points is None:
                e.inlier_pairs = None  # only needed for the tracks above
        self.entries.append(_Entry(pos, int(frame_id), timestamp, fk, np.arange(len(fk.uv)), np.eye(4),
                                   min(self._moments), mixed))
        while self.entries and pos - self.entries[0].pos >= cfg.gaps:
            self.entries.popleft()
        for x in edges:
            x.inlier_pairs = None  # keeps results small
        return edges


def _scaled(T: NDArray[np.float64], r: float) -> NDArray[np.float64]:
    """A motion ``T`` scaled along its twist to ``r`` times its time (:meth:`EdgeWindow.motion_over`,
    :meth:`EdgeWindow.motion_between`); ``T`` itself for ratios within 2/3-1.5, timestamp
    jitter, which is the clock's and not the camera's."""
    return T if 2 / 3 < r < 1.5 else geo.se3_exp(r * geo.se3_log(T))
