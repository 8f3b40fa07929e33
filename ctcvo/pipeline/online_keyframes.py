"""The keyframe and loop edges of ``ctcvo online`` (:mod:`teacher.keyframes`, as ``teacher
generate`` adds them), off the frames' critical path.

After a frame's pose is written, the frame loop offers the frame with that pose
(:meth:`KeyframeWorker.offer`): :class:`teacher.keyframes.KeyframeSelector` decides there
whether it is a keyframe (its depth points against the last keyframe: well under a
millisecond). A keyframe goes to a helper thread, which extracts its features (as
``teacher generate``'s keyframe pass does), finds its covisible keyframes and loop
candidates (:class:`teacher.keyframes.KeyframeHistory`) and estimates their edges
(:func:`teacher.keyframes.estimate_work`). The frame loop takes the finished edges after a
later frame's pose (:meth:`KeyframeWorker.take`) and adds them to the ISAM2 graph; at the end
of the run (and after Ctrl-C) :meth:`KeyframeWorker.close` waits for the keyframes still in
hand, so the final solve has every edge (another Ctrl-C drops the rest: ``report.json``,
``keyframes.dropped``).

Keyframes are picked on the window's edges chained (:meth:`pipeline.online_loop.OnlineTeacher.chain`),
as the batch pass picks them, and their features are extracted as it extracts them: the
keyframe and loop edges are ``teacher generate``'s bit for bit (unless a frame's window edges
all failed), whenever they are estimated. What depends on the timing is the causal
trajectory, into which they enter a few frames late, and through the ISAM2 estimate the
final solve starts from, the final trajectory at the solver's tolerance.
"""

from __future__ import annotations

import logging
import queue
import threading
import time

import numpy as np
from threadpoolctl import threadpool_limits

from ctcvo.data.sequence import Frame, Intrinsics
from ctcvo.teacher.features import FrameFeatures, image_keys
from ctcvo.teacher.keyframes import (
    Keyframe,
    KeyframeHistory,
    KeyframeSelector,
    depth_points,
    estimate_work,
    keyframe_features,
    keyframe_orb,
)
from ctcvo.teacher.loops import thumbnail

log = logging.getLogger(__name__)


class KeyframeWorker:
    """Keyframe work of an online run in a helper thread (see the module's docstring).
    ``cfg``, ``colour``: the online teacher's config and colour camera model (the window's)."""

    def __init__(self, intr: Intrinsics, cfg, colour=None) -> None:
        self.intr, self.cfg, self.colour = intr, cfg, colour
        self.selector = KeyframeSelector(intr)
        self.history = KeyframeHistory(intr, cfg.gaps)
        self.queue: queue.Queue = queue.Queue()  # keyframes only: a frame's arrays until its work starts
        self.stop = threading.Event()
        self.lock = threading.Lock()
        self.done: list[tuple[int, list]] = []  # (keyframe position, its (EdgeEstimate, kind) list)
        self.error: BaseException | None = None
        self.picked = 0
        self.finished = 0
        self.lag_frames: list[int] = []
        """Per keyframe: frames posed after it until its edges were taken into the graph."""
        self.wait_s = 0.0
        self.thread = threading.Thread(target=self._work, name="vo-online-keyframes", daemon=True)
        self.thread.start()

    def offer(self, pos: int, frame: Frame, T_world_cam: np.ndarray) -> bool:
        """Frame ``frame``, the ``pos``-th taken, with its pose estimate (the chained one):
        whether it is a keyframe (then queued for the helper thread)."""
        pts = depth_points(frame.depth, self.intr)
        if not self.selector.offer(T_world_cam, pts, image_keys(frame.rgb, frame.depth), float(frame.timestamp)):
            return False
        self.picked += 1
        self.queue.put((pos, frame, np.array(T_world_cam), pts, self.selector.velocity))
        return True

    def take(self, posed: int) -> list:
        """The (EdgeEstimate, kind) pairs finished since the last call (``posed``: frames
        posed so far); raises what the helper thread raised."""
        if self.error is not None:
            raise self.error
        with self.lock:
            done, self.done = self.done, []
        self.lag_frames += [posed - 1 - pos for pos, _ in done]
        return [x for _, edges in done for x in edges]

    def close(self, asked: threading.Event | None = None) -> int:
        """Wait for the keyframes in hand (``asked``, set by a Ctrl-C during the wait, or a
        second Ctrl-C: drop those not started); returns how many were dropped."""
        t0 = time.perf_counter()
        before = asked is not None and asked.is_set()
        self.queue.put(None)
        try:
            while self.thread.is_alive() and not self.stop.is_set():
                self.thread.join(timeout=0.1)
                if asked is not None and asked.is_set() and not before:
                    self.stop.set()
        except KeyboardInterrupt:
            self.stop.set()
        self.thread.join()  # the keyframe in hand: at most one estimate_work
        self.wait_s = time.perf_counter() - t0
        dropped = self.picked - self.finished
        if dropped:
            log.warning("keyframe work of %d keyframes dropped", dropped)
        return dropped

    def abandon(self) -> None:
        """End the helper thread after the keyframe in hand, without waiting (an error)."""
        self.stop.set()
        self.queue.put(None)

    def _work(self) -> None:
        # OpenMP's thread count is per thread: Open3D's kernels here on the teacher's count
        threadpool_limits(self.cfg.threads, user_api="openmp")
        orb, feats = keyframe_orb(self.cfg, self.colour), {}  # ORB detectors are not shared between threads
        try:
            while (item := self.queue.get()) is not None and not self.stop.is_set():
                pos, frame, T, pts, velocity = item
                feats[pos] = self._features(frame, orb)
                kf = Keyframe(pos, int(frame.frame_id), float(frame.timestamp), T, pts, thumbnail(frame.rgb), velocity)
                edges = estimate_work(self.history.add(kf), feats.__getitem__, self.intr, self.cfg)
                if self.colour is not None:  # the final solve adjusts sightings of registered colour only
                    for e, _ in edges:
                        e.inlier_pairs = e.inlier_points = None
                with self.lock:
                    self.done.append((pos, edges))
                    self.finished += 1
        except BaseException as exc:  # noqa: BLE001 - handed to the frame loop
            self.error = exc

    def _features(self, frame: Frame, orb) -> FrameFeatures:
        """A keyframe's features as ``teacher generate``'s keyframe pass extracts them
        (:func:`teacher.generate.features_of`: not the window's, which the window annotates)."""
        return keyframe_features(frame.rgb, frame.depth, self.cfg, orb, self.intr.K, self.colour)

    def report(self, dropped: int) -> dict:
        """``report.json``'s ``keyframes``."""
        lag = self.lag_frames
        return {"keyframes": self.picked, "dropped": dropped, "wait_at_end_s": self.wait_s,
                "lag_frames": {"p50": float(np.percentile(lag, 50)), "max": int(max(lag))} if lag else None}
