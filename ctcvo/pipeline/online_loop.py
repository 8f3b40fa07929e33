"""The frame loop of ``ctcvo online``: a helper thread takes each frame from the source and
prepares it (:class:`Prefetcher`); this thread estimates its edges, adds them to the graph
and writes its pose (:class:`Estimator`), while a second helper thread gives the learner's
edges of the same frame."""

from __future__ import annotations

import contextlib
import logging
import queue
import signal
import sys
import threading
import time
from collections.abc import Iterator
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from typing import TextIO

import numpy as np
from threadpoolctl import ThreadpoolController, threadpool_limits

from ctcvo.data import geometry as geo
from ctcvo.data.formats import Edge
from ctcvo.data.live import FollowFolder, FrameSource
from ctcvo.data.open3d_import import open3d_follows_openmp
from ctcvo.data.sequence import Frame, Intrinsics
from ctcvo.learner.online import OnlineLearner
from ctcvo.pipeline.online_keyframes import KeyframeWorker
from ctcvo.posegraph.online import OnlineGraph
from ctcvo.teacher.covariance_model import gap_scale
from ctcvo.teacher.features import extract, make_orb
from ctcvo.teacher.maps import add_surface
from ctcvo.teacher.window import EdgeWindow

log = logging.getLogger(__name__)


#: The online teacher's window K when none is asked for (``ctcvo online --gaps``; ``teacher
#: generate`` keeps 5): the smallest K whose final ATE stays within 10 % of K = 5's on every
#: validation range (both with the pose after the gap-1 edge, keyframe edges on; records
#: val-*-pag1, val-*-g4, val-*-low, bench/README.md, online). K = 4: redkitchen 350:450 13.5 ->
#: 13.4, fr3/teddy 4.9 -> 5.2, lab 0:200 10.1 -> 9.6 mm, p95 latency 52-57 -> 37-55 ms; K = 3
#: (28-48 ms) lost teddy 4.9 -> 5.6 mm once its keyframes had more features.
ONLINE_GAPS = 4


@dataclass(frozen=True)
class OnlineConfig:
    """How frames arrive and how often the progress line is drawn."""

    poll_s: float = 0.02
    """``--follow``: seconds between looks at the folder for a new frame."""
    timeout_s: float = 10.0
    """``--follow``: the run ends when no new frame arrived for this long."""
    progress_every_s: float = 0.5
    """Seconds between progress lines (redrawn in place on a terminal, logged otherwise)."""
    prefetch: int = 2
    """Frames read and prepared (teacher features, learner inputs) ahead of the estimator
    by a helper thread (at least 1)."""
    pose_after_gap1: bool = True
    """Write each frame's pose once its gap-1 teacher edge (and its learner edges) are in
    the graph; its longer teacher edges (k-g, k), g >= 2, are estimated after that and
    enter the graph in a second ISAM2 update, before the next frame. The same edges as
    without it (the final trajectory solves the same graph); the helper thread builds a
    frame's surface maps only once its pose is out, one frame ahead, not ``prefetch``. On by
    default: on the validation ranges (redkitchen 350:450, fr3/teddy 0:200, lab 0:200), at K = 5,
    the final ATE stays that of the run without it and the causal ATE within 0.3 mm, and the
    p95 latency falls from 156-327 to 51-57 ms (bench/README.md, online)."""
    drop_late: bool = False
    """For a live source (``--follow``): when frames arrive faster than they are processed,
    take the newest complete one and pass over those in between, and let a newer prepared
    frame replace one still waiting for the estimator (``report.json``: ``frames_skipped``).
    One frame is prepared ahead (not ``prefetch``). Off: every frame is taken, in order."""


class OnlineTeacher:
    """The edges (k-g, k), g = 1..cfg.gaps, of each new frame k: the window of ``teacher
    generate`` (:class:`teacher.window.EdgeWindow`, the same code) over the frames as they
    arrive, and the frame ids and timestamps so far."""

    def __init__(self, intr: Intrinsics, cfg, colour=None, noise_model: str = "kinect-v1") -> None:
        """``colour``: the colour camera model (``data.sensor.ColourCamera``; None:
        colour registered to depth), as :func:`teacher.config.colour_camera_for` picks it;
        ``noise_model``: the sensor's (``data.sensor.Sensor.noise_model``), whose per-gap
        covariance scales the edges get (:mod:`teacher.covariance_model`), as in ``teacher generate``."""
        self.intr, self.cfg, self.colour, self.noise_model = intr, cfg, colour, noise_model
        self._pos: dict[int, int] = {}
        self.orb = make_orb(cfg)
        self.window = EdgeWindow(intr, cfg, sightings=colour is None)  # as teacher generate's
        self.ids: list[int] = []
        self.times: list[float] = []
        self.chained: list[np.ndarray] = []
        """Per frame: its pose in the chained window edges (:meth:`chain`)."""

    def features(self, frame: Frame):
        """Per-frame work (safe to run in one helper thread ahead of :meth:`add`), without
        the maps the frame's dense step needs only as the older frame of a later edge:
        :meth:`finish` adds them, in the same thread, before the next frame's features."""
        return extract(frame.rgb, frame.depth, self.cfg, self.orb, self.intr.K, self.colour, surface=False)

    def finish(self, fk) -> None:
        """The rest of :meth:`features` (:func:`teacher.odometry.add_surface`): called after
        the frame is handed over, so its own edges do not wait for it."""
        if fk.dense is not None:
            add_surface(fk.dense, fk.depth, self.intr.K)

    def add(self, frame: Frame, fk) -> list:
        """The edges ending at ``frame`` (``EdgeEstimate``; failed ones included)."""
        return self.add_gap1(frame, fk) + self.add_longer()

    def add_gap1(self, frame: Frame, fk) -> list:
        """The first half of :meth:`add`: the gap-1 edge ending at ``frame`` (a list of it,
        empty for the first frame); :meth:`add_longer` follows before the next frame."""
        self.ids.append(int(frame.frame_id))
        self.times.append(float(frame.timestamp))
        self._pos[self.ids[-1]] = len(self.ids) - 1
        return self.window.add_gap1(self.ids[-1], self.times[-1], fk, frame.depth_offset)

    def add_longer(self) -> list:
        """The second half of :meth:`add`: the longer edges ending at the newest frame."""
        return self.window.add_longer()


    def chain(self, estimates: list) -> np.ndarray:
        """The newest frame's pose (``T_world_cam``) in the window's edges chained as
        :func:`teacher.generate.chain_trajectory` chains them, from the frame's estimates
        (``estimates``: every one ending at it): through its shortest good edge, else by
        constant velocity. The batch chain's pose bit for bit, unless the frame's edges all
        failed and the batch chain reached it through a later frame."""
        k, pos = len(self.ids) - 1, self._pos
        good = [e for e in estimates if e.ok and e.j == self.ids[-1]]
        if k == 0:
            T = np.eye(4)
        elif good:
            e = max(good, key=lambda e: pos[e.i])
            T = self.chained[pos[e.i]] @ e.T_i_j
        else:
            step = geo.relative_pose(self.chained[k - 2], self.chained[k - 1]) if k >= 2 else np.eye(4)
            T = self.chained[k - 1] @ step
        self.chained.append(T)
        return T

    def cov_scale(self, e, kind: str = "window") -> float:
        """The factor of the covariance of estimate ``e`` (``EdgeEstimate``) of edges.csv
        ``kind``: its gap's scale, the gap counted in frames taken."""
        return gap_scale(self.noise_model, self._pos[e.j] - self._pos[e.i], self.cfg.covariance, kind,
                         e.diag.mixed_moments)


def teacher_edges(estimates: list, teacher: OnlineTeacher, kinds: dict[tuple[int, int], str] | None = None) -> list[Edge]:
    """The graph edges of the good teacher estimates (``EdgeEstimate``; ``kinds``: edges.csv
    kind by (i, j), else ``window``), covariances scaled as ``teacher generate`` writes them."""
    kinds = kinds or {}
    return [Edge(e.i, e.j, e.T_i_j, e.cov * teacher.cov_scale(e, kinds.get((e.i, e.j), "window")), {"source": "teacher"})
            for e in estimates if e.ok]


class Prefetcher:
    """A helper thread that takes frames from the source (decoding them), stamps their
    arrival and prepares them (teacher features, learner inputs) up to ``cfg.prefetch``
    frames ahead, then adds what a frame's dense step needs only as the older frame of
    later edges."""

    def __init__(self, source: FrameSource, teacher: OnlineTeacher, learner: OnlineLearner | None,
                 cfg: OnlineConfig, max_frames: int | None) -> None:
        self.source, self.teacher, self.learner, self.cfg, self.max_frames = source, teacher, learner, cfg, max_frames
        self.queue: queue.Queue = queue.Queue(maxsize=1 if cfg.drop_late else max(cfg.prefetch, 1))
        self.stop = threading.Event()
        self.replaced = 0
        """Prepared frames a newer one replaced in the queue (``drop_late``)."""
        self.posed = threading.Semaphore(0)
        """Released when a frame's pose is written (``pose_after_gap1``)."""
        self.thread = threading.Thread(target=self._produce, name="vo-online-frames", daemon=True)

    def _prepare(self, frame: Frame) -> tuple:
        feats = self.teacher.features(frame)
        return frame, feats, (self.learner.inputs(frame) if self.learner is not None else None)

    def _produce(self) -> None:
        try:
            # OpenMP's thread count is per calling thread: this one builds the dense maps
            # (per-pixel kernels, whose results do not depend on it) on the teacher's count,
            # as the feature thread of a batch run does; the main one aligns (the labels do)
            threadpool_limits(self.teacher.cfg.threads, user_api="openmp")
            for k, frame in enumerate(self.source):
                t_take, c_arr = time.perf_counter(), time.thread_time()
                t_arr = self.source.arrival()  # the frame is here: latency counts from then
                t_arr = t_take if t_arr is None else min(t_arr, t_take)
                item = (t_arr, *self._prepare(frame), time.perf_counter() - t_take, time.thread_time() - c_arr)
                self._put(item)
                # what frame k's dense step needs only in later frames' edges: built here,
                # before frame k+1 is handed over (so before the estimator can need it);
                # with pose_after_gap1 once frame k's pose is out, so that Open3D's filters,
                # which hold the GIL, do not hold up that pose
                while self.cfg.pose_after_gap1 and not self.stop.is_set() and not self.posed.acquire(timeout=0.1):
                    pass
                self.teacher.finish(item[2])
                if self.stop.is_set() or (self.max_frames is not None and k + 1 >= self.max_frames):
                    break
            self.queue.put(None)
        except BaseException as exc:  # noqa: BLE001 - handed to the main thread
            self.queue.put(exc)

    def _put(self, item: tuple) -> None:
        while not self.stop.is_set():
            try:
                self.queue.put(item, timeout=0.1)
                return
            except queue.Full:
                if self.cfg.drop_late:  # the estimator has not taken the older one yet: replace it
                    try:
                        self.queue.get_nowait()
                        self.replaced += 1
                    except queue.Empty:
                        pass

    def drain(self) -> None:
        """Drop the frames prepared but not taken (an interrupted run): their Open3D buffers
        would otherwise outlive the interpreter, and Open3D lists each one at exit."""
        while True:
            try:
                self.queue.get_nowait()
            except queue.Empty:
                return

    def get(self, asked: threading.Event) -> tuple | None:
        """The next prepared frame (None: the source has no more); raises what the helper
        thread raised, and KeyboardInterrupt once ``asked`` is set."""
        while True:
            if asked.is_set():
                raise KeyboardInterrupt
            try:
                item = self.queue.get(timeout=0.1)
            except queue.Empty:
                continue
            if isinstance(item, BaseException):
                raise item
            return item


@dataclass
class Timings:
    """Per-frame durations, seconds."""

    latency: list[float] = field(default_factory=list)
    """From the frame's arrival to its pose written."""
    work: list[float] = field(default_factory=list)
    """Prepare + estimate + update + write, without any wait in the queue."""
    to_pose: list[float] = field(default_factory=list)
    """The same until the frame's pose is written."""
    cpu_to_pose: list[float] = field(default_factory=list)
    """The CPU time of that work (every thread's share: prepare, teacher, learner): what a core each gives."""


class Estimator:
    """Each prepared frame's edges (teacher and learner) into the ISAM2 graph, and its
    current pose appended to the open trajectory file ``fh``. The learner's edges of a frame
    are estimated in a helper thread while this one estimates the teacher's (torch and
    Open3D release the GIL; the learner sees the same frames in the same order, so its
    edges are those of a serial run); :meth:`close` ends that thread."""

    def __init__(self, teacher: OnlineTeacher, learner: OnlineLearner | None, graph: OnlineGraph,
                 cfg: OnlineConfig, fh: TextIO, keyframes: KeyframeWorker | None = None) -> None:
        self.teacher, self.learner, self.graph, self.cfg, self.fh = teacher, learner, graph, cfg, fh
        self.keyframes = keyframes
        self.kinds: dict[tuple[int, int], str] = {}
        """``keyframe`` or ``loop`` for the keyframe worker's edges in ``t_edges``; others are ``window``."""
        self.dropped_keyframes = 0
        self.omp = ThreadpoolController()
        self.pool = (ThreadPoolExecutor(1, thread_name_prefix="vo-online-learner") if learner is not None else None)
        self.t_edges: list = []
        self.pairs: set[tuple[int, int]] = set()  # of t_edges
        self.l_edges: list[Edge] = []
        self.gts: list = []
        self.n = 0
        self.timings = Timings()

    def _teacher(self, add, *args) -> list:
        """``add(*args)`` of the teacher, its Open3D kernels on the teacher's threads only
        around its calls (the learner's torch shares OpenMP and keeps its threads)."""
        with self.omp.limit(limits=self.teacher.cfg.threads, user_api="openmp"):
            edges = add(*args)
        self.t_edges += edges
        self.pairs.update((e.i, e.j) for e in edges)
        return edges

    def _learner(self, inputs: tuple) -> tuple[list, float]:
        """The learner's edges of a frame and the CPU time they took (in the helper thread)."""
        c0 = time.thread_time()
        return self.learner.add(inputs), time.thread_time() - c0

    def close(self) -> None:
        """End the learner's helper thread (after the frame it holds)."""
        if self.pool is not None:
            self.pool.shutdown(wait=True, cancel_futures=True)

    def step(self, item: tuple, posed: threading.Semaphore) -> None:
        """Frame ``item`` (from :meth:`Prefetcher.get`): edges, graph, pose, timings."""
        t_arr, frame, feats, inputs, t_prep, c_prep = item
        t_take, c_take = time.perf_counter(), time.thread_time()
        teacher, after_gap1 = self.teacher, self.cfg.pose_after_gap1
        learned = self.pool.submit(self._learner, inputs) if self.pool is not None else None
        new = teacher_edges(self._teacher(teacher.add_gap1 if after_gap1 else teacher.add, frame, feats), teacher)
        if self.learner is not None:
            estimates, c_learn = learned.result() if learned is not None else self._learner(inputs)
            c_prep += c_learn
            for g, mean, cov, head in estimates:
                e = Edge(teacher.ids[-1 - g], teacher.ids[-1], geo.se3_exp(mean), cov, {"source": "learner", "head": head})
                self.l_edges.append(e)
                new.append(e)
        T = self.graph.add(int(frame.frame_id), new)
        self.fh.write(f"{frame.timestamp:.6f} " + " ".join(f"{x:.9f}" for x in geo.T_to_tum(T)) + "\n")
        self.fh.flush()
        self.gts.append(frame.T_world_cam)
        self.n += 1
        t_pose, tm = time.perf_counter(), self.timings
        tm.latency.append(t_pose - t_arr)
        tm.to_pose.append(t_prep + t_pose - t_take)
        tm.cpu_to_pose.append(c_prep + time.thread_time() - c_take)
        if after_gap1:  # the longer edges of this frame, after its pose
            posed.release()
            self.graph.add_edges(teacher_edges(self._teacher(teacher.add_longer), teacher))
        if self.keyframes is not None:  # after its pose and longer edges: decide on the chain, take finished work
            mine = [e for e in self.t_edges[-teacher.cfg.gaps:] if e.j == teacher.ids[-1]]
            self.keyframes.offer(self.n - 1, frame, teacher.chain(mine))
            self._take_keyframe_edges()
        tm.work.append(t_prep + time.perf_counter() - t_take if after_gap1 else tm.to_pose[-1])

    def _take_keyframe_edges(self) -> None:
        """The keyframe worker's finished edges into ``t_edges`` and the graph (one ISAM2
        update); a frame pair the window has is skipped, as ``teacher generate`` skips it."""
        new = []
        for e, kind in self.keyframes.take(self.n):
            if (e.i, e.j) not in self.pairs:
                self.pairs.add((e.i, e.j))
                new.append(e)
                self.kinds[(e.i, e.j)] = kind
        self.t_edges += new
        self.graph.add_edges(teacher_edges(new, self.teacher, self.kinds))

    def finish_keyframes(self, asked: threading.Event | None = None) -> None:
        """At the end of the run: wait for the keyframe work in hand (Ctrl-C: see
        :meth:`KeyframeWorker.close`) and take its edges."""
        if self.keyframes is not None:
            self.dropped_keyframes = self.keyframes.close(asked)
            self._take_keyframe_edges()

    def trim(self) -> None:
        """Interrupted inside a frame: keep the frames whose rows were written."""
        teacher, n = self.teacher, self.n
        if len(teacher.ids) > n:
            del teacher.ids[n:], teacher.times[n:]
            kept = set(teacher.ids)
            self.t_edges = [e for e in self.t_edges if e.j in kept]
            self.l_edges = [e for e in self.l_edges if e.j in kept]


@contextlib.contextmanager
def sigint_after_frame() -> Iterator[threading.Event]:
    """Ctrl-C sets the event, which ends the run after the frame in hand (a second Ctrl-C
    at once): a frame cut short would leave the teacher, the graph and the trajectory file
    with different frames. Only in the main thread (elsewhere the event is never set)."""
    asked = threading.Event()

    def on_sigint(signum, frame_) -> None:
        if asked.is_set():
            raise KeyboardInterrupt
        asked.set()

    handler = (signal.signal(signal.SIGINT, on_sigint) if threading.current_thread() is threading.main_thread()
               else None)
    try:
        yield asked
    finally:
        if handler is not None:
            signal.signal(signal.SIGINT, handler)


def drive(source: FrameSource, est: Estimator, cfg: OnlineConfig, max_frames: int | None = None,
          progress: bool = True) -> tuple[bool, float, int]:
    """Every frame of ``source`` through ``est``, prepared ahead by a :class:`Prefetcher`;
    KeyboardInterrupt ends it early. Returns (interrupted, seconds, frames skipped)."""
    pre = Prefetcher(source, est.teacher, est.learner, cfg, max_frames)
    bar = _Progress(cfg.progress_every_s) if progress else None
    interrupted = False
    with sigint_after_frame() as asked, open3d_follows_openmp(est.teacher.cfg.threads):
        t_start = time.perf_counter()
        pre.thread.start()
        try:
            while (item := pre.get(asked)) is not None:
                est.step(item, pre.posed)
                if bar is not None:
                    bar.show(est.n, est.n / (time.perf_counter() - t_start), est.timings.latency,
                             len(est.t_edges) + len(est.l_edges), source.skipped + pre.replaced)
        except KeyboardInterrupt:
            interrupted = True
        except BaseException:
            if est.keyframes is not None:  # an error: do not wait for the keyframe work
                est.keyframes.abandon()
            raise
        finally:
            pre.stop.set()
            if isinstance(source, FollowFolder):
                source.stop.set()
            if bar is not None:
                bar.close()
            pre.thread.join(timeout=5.0)
            pre.drain()
            est.close()
            seconds = time.perf_counter() - t_start
        # inside the blocks: Open3D's thread count holds for the worker, a Ctrl-C during the wait is heard
        est.finish_keyframes(asked)
    return interrupted, seconds, source.skipped + pre.replaced


class _Progress:
    def __init__(self, every_s: float, stream: TextIO = sys.stderr) -> None:
        self.every, self.stream, self.tty = every_s, stream, stream.isatty()
        self.last = 0.0

    def show(self, n: int, fps: float, lat_s: list[float], edges: int, skipped: int = 0) -> None:
        now = time.monotonic()
        if now - self.last < self.every:
            return
        self.last = now
        recent = lat_s[-300:]  # the percentile of the last 10 s at 30 Hz
        line = (f"online: {n} frames, {fps:.1f} fps, latency {1000 * lat_s[-1]:.0f} ms "
                f"(p95 {1000 * float(np.percentile(recent, 95)):.0f} ms), {edges} edges"
                + (f", {skipped} skipped" if skipped else ""))
        if self.tty:
            self.stream.write("\r" + line + "\x1b[K")
            self.stream.flush()
        else:
            log.info("%s", line)

    def close(self) -> None:
        if self.tty and self.last:
            self.stream.write("\n")
            self.stream.flush()
