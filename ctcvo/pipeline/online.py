"""``vo-online``: odometry frame by frame, as the frames arrive.

    vo-online --scene SCENE [--checkpoint CKPT] [--out DIR] [--frames A:B] [--follow [--drop-late]]

Frames come from any ``--scene`` (a folder, a ROS bag, ``synthetic/NAME``), read one at a
time in order, or, with ``--follow``, from a folder that is still being written, polled
every ``--poll`` s and ending after ``--timeout`` s without a new frame: a 7-Scenes-layout
folder (``frame-NNNNNN.color.{png,jpg}`` + ``frame-NNNNNN.depth.png``, optional
``.pose.txt``) or a TUM RGB-D folder (``rgb.txt`` and ``depth.txt`` growing, colour and
depth paired by timestamp as for a finished TUM folder). A followed frame's latency counts
from when its last file was written; with ``--drop-late`` a run that falls behind takes
the newest complete frame and skips the ones in between (bounded latency, fewer frames).

For each new frame k:

1. the teacher's window (:class:`teacher.window.EdgeWindow`, the code ``teacher generate``
   runs) gives the edges (k-g, k), g = 1..K, with the same feature tracks and
   constant-velocity prediction;
2. with ``--checkpoint``, the learner (:class:`learner.online.OnlineLearner`) adds
   MC-dropout edges (k-g, k), g = 1..max_gap (the network and calibration of ``learner
   predict``; the LSTM head over the same chunks of ``window_max`` pairs);
3. GTSAM's ISAM2 (:class:`posegraph.online.OnlineGraph`) is updated with the new pose
   (predicted through its shortest good edge) and its edges (the robust factors of
   :mod:`posegraph.graph`);
4. the new pose's current estimate is appended to ``trajectory.tum`` and flushed.

With ``--pose-after-gap1`` step 1 gives the gap-1 edge only, and the longer teacher edges
follow step 4 in a second ISAM2 update (the same edges; a frame's pose waits for less).
``--dense-max-gap N`` runs the teacher's dense step on edges of at most N frames only (a
cheaper teacher; bench/README.md, "Online mode", measures what it costs in accuracy).

This module only composes them (frame sources, the hand-over thread, outputs, command
line); it is, with pipeline/demo.py, where every stage is imported.

At the end (or on Ctrl-C) the smoothed estimate of every pose is written to
``trajectory_final.tum``, the edges to ``teacher/`` and ``learner/`` (the layout of
``teacher generate`` / ``learner predict``, so ``posegraph optimize --teacher DIR/teacher``
solves the same edges in batch) and ``report.json`` (fps, latency percentiles, ATE when
there is ground truth). Formats: docs/formats.md, "Online mode".

:func:`online` (the command) follows the rerun rule of :mod:`data.runs`: beside its outputs
it writes ``fingerprint.json`` (scene, frames, the teacher, learner and graph settings,
``--pose-after-gap1``, the checkpoint's digest); a rerun of the same inputs keeps a
finished run (with ``--follow``: when the folder holds no frame the run did not take),
recomputes an interrupted or killed one, and stops with a one-line error for other inputs
unless ``--overwrite``.
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import logging
import queue
import signal
import sys
import threading
import time
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TextIO

import numpy as np
from numpy.typing import NDArray
from threadpoolctl import ThreadpoolController, threadpool_limits

from ctcvo.data import geometry as geo
from ctcvo.data.errors import ConfigError, DataError, VOError
from ctcvo.data.sensor import Sensor
from ctcvo.data.sequence import Frame, Intrinsics
from ctcvo.posegraph.online import OnlineGraph

log = logging.getLogger(__name__)

TRAJECTORY = "trajectory.tum"
FINAL_TRAJECTORY = "trajectory_final.tum"
REPORT = "report.json"
#: every file a run writes (report.json first: removed first, written last, it marks a finished run)
OUTPUT_FILES = (REPORT, TRAJECTORY, FINAL_TRAJECTORY, "teacher/edges.g2o", "teacher/trajectory.tum",
                "teacher/groundtruth.tum", "learner/edges.g2o")


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
    pose_after_gap1: bool = False
    """Write each frame's pose once its gap-1 teacher edge (and its learner edges) are in
    the graph; its longer teacher edges (k-g, k), g >= 2, are estimated after that and
    enter the graph in a second ISAM2 update, before the next frame. The same edges as
    without it (the final trajectory solves the same graph); the latency a frame waits
    for its own pose no longer includes its longer edges (bench/README.md, "Online mode").
    The helper thread then builds a frame's surface maps only once its pose is out (Open3D's
    filters hold Python's GIL and would hold up the gap-1 edge), and prepares the next frame
    after that: one frame ahead, not ``prefetch``."""
    drop_late: bool = False
    """For a live source (``--follow``: frames arrive whether or not they are taken): when
    frames arrive faster than they are processed, take the newest complete one and pass
    over those in between, and let a newer prepared frame replace one still waiting for
    the estimator. The latency stays bounded at the cost of frames (``report.json``:
    ``frames_skipped``); the edges then join the frames taken (a gap-1 edge may span
    several camera frames). One frame is prepared ahead (not ``prefetch``). Off: every
    frame is taken, in order, however late."""


# ----------------------------------------------------------------------------------
# frame sources
# ----------------------------------------------------------------------------------
class FrameSource:
    """Frames in order, one at a time, with the camera's intrinsics and sensor."""

    name: str
    intrinsics: Intrinsics
    sensor: Sensor
    skipped: int = 0
    """Frames passed over to hand out a newer one (``OnlineConfig.drop_late``)."""

    def __iter__(self) -> Iterator[Frame]:
        raise NotImplementedError

    def arrival(self) -> float | None:
        """When the frame just yielded reached the system (``time.perf_counter()``), for a
        source whose frames come at their own pace whether or not they are taken (a camera,
        a folder being written); a frame's latency counts from then. None: from when it was
        yielded (a recording read as fast as it is taken)."""
        return None


class SequenceSource(FrameSource):
    """The frames of a :class:`data.sequence.Sequence` (folder, bag, synthetic), read lazily."""

    def __init__(self, seq) -> None:
        self.seq, self.name, self.intrinsics, self.sensor = seq, seq.name, seq.intrinsics, seq.sensor

    def __iter__(self) -> Iterator[Frame]:
        for k in range(len(self.seq)):
            yield self.seq.frame(k)


class FollowFolder(FrameSource):
    """A folder still being written (:func:`follow_folder` picks the layout): frames are
    taken in order as they become complete (with ``cfg.drop_late``, the newest complete
    one, passing over older ones not taken yet); a frame whose files exist but do not
    decode yet (written without a rename) is retried until ``timeout_s``; the run ends
    when no new frame came for ``timeout_s``. A frame's arrival is when the last of its
    files was written (their modification time). Subclasses say which frames are ready."""

    def __init__(self, folder: Path, cfg: OnlineConfig) -> None:
        self.folder, self.cfg = Path(folder), cfg
        self.name = self.folder.resolve().name
        self.stop = threading.Event()
        self._arrived: float | None = None

    def _ready(self, final: bool) -> Iterator[object]:
        """The frames after the last one read that the folder holds complete, in order, up
        to the first one that is not. ``final``: the folder has stopped growing (frames
        held back until later files settle them are final now)."""
        raise NotImplementedError

    def _next(self, final: bool) -> tuple[object | None, int]:
        """The frame to read next (None: none ready) and how many ready ones it passes over:
        the oldest ready one, or with ``drop_late`` the newest (the ones before it count as
        skipped once it is read)."""
        if not self.cfg.drop_late:
            return next(iter(self._ready(final)), None), 0
        ready = list(self._ready(final))
        return (ready[-1], len(ready) - 1) if ready else (None, 0)

    def _read(self, taken: int, item: object) -> Frame:
        """The frame ``item`` (from :meth:`_ready`); :class:`DataError` while it does not decode."""
        raise NotImplementedError

    def _stamp(self, *files: Path) -> None:
        """The arrival of the frame just read: when the last of ``files`` was written."""
        written = max(f.stat().st_mtime for f in files)
        self._arrived = time.perf_counter() - max(0.0, time.time() - written)

    def arrival(self) -> float | None:
        return self._arrived

    def present_ids(self) -> NDArray[np.int64]:
        """The frame ids the folder holds now: what a run starting now would take."""
        raise NotImplementedError

    def __iter__(self) -> Iterator[Frame]:
        taken, final, waited_since = 0, False, time.monotonic()
        while not self.stop.is_set():
            item, passed_over = self._next(final)
            if item is not None:
                try:
                    frame = self._read(taken, item)
                except DataError:
                    if time.monotonic() - waited_since > self.cfg.timeout_s:
                        raise
                    time.sleep(self.cfg.poll_s)
                    continue
                self.skipped += passed_over
                yield frame
                taken, waited_since = taken + 1, time.monotonic()
                continue
            if final:
                return
            if time.monotonic() - waited_since > self.cfg.timeout_s:
                log.info("%s: no new frame for %.1f s, ending", self.folder, self.cfg.timeout_s)
                final = True  # what is there now is all there is
                continue
            time.sleep(self.cfg.poll_s)


class FollowSevenScenes(FollowFolder):
    """A 7-Scenes-layout folder being written: frame ids in increasing order as their
    ``frame-NNNNNN.color.{png,jpg}`` and ``frame-NNNNNN.depth.png`` appear (timestamps
    ``id / 30`` s; ground truth from ``.pose.txt``; intrinsics from
    ``camera-intrinsics.txt`` of the folder or its parent, else the 7-Scenes default)."""

    def __init__(self, folder: Path, cfg: OnlineConfig) -> None:
        from ctcvo.data import sevenscenes

        super().__init__(folder, cfg)
        self.intrinsics = sevenscenes.folder_intrinsics(self.folder)
        self.sensor = sevenscenes.folder_sensor(self.folder)
        self.last = -1

    def _ready(self, final: bool) -> Iterator[object]:
        from ctcvo.data import sevenscenes

        for k in (k for k in sevenscenes.frame_ids(self.folder) if k > self.last):
            colour = sevenscenes.colour_file(self.folder, k)
            if colour is None:
                return
            yield k, colour

    def _read(self, taken: int, item: object) -> Frame:
        from ctcvo.data import sevenscenes
        from ctcvo.data.sequence import read_rgb

        k, colour = item
        rgb = read_rgb(colour, self.intrinsics)
        depth = sevenscenes.read_depth_file(sevenscenes.depth_file(self.folder, k), self.intrinsics)
        self._stamp(colour, sevenscenes.depth_file(self.folder, k))
        pose_file = self.folder / f"frame-{k:06d}.pose.txt"
        pose = sevenscenes.read_pose_file(pose_file) if pose_file.is_file() else None
        self.last = k
        return Frame(k, k / sevenscenes.FPS, rgb, depth, pose)

    def present_ids(self) -> NDArray[np.int64]:
        from ctcvo.data import sevenscenes

        return np.array([k for k in sevenscenes.frame_ids(self.folder)
                         if sevenscenes.colour_file(self.folder, k) is not None], dtype=np.int64)


class FollowTum(FollowFolder):
    """A TUM RGB-D folder being written: ``rgb.txt`` and ``depth.txt`` grow (a line counts
    once its newline is written; the image it names may appear later). RGB and depth are
    paired as for a TUM folder (:func:`data.tum.associate`, nearest first within 0.02 s);
    a pairing is final once both lists reach ``2 * 0.02`` s past the RGB timestamp (no
    later line can change it), and every pairing is final when the folder has stopped
    growing. Frame ids count the frames taken (``0..N-1``, as for a TUM folder), the
    timestamp is the RGB one; ground truth is ``groundtruth.txt`` interpolated to it when
    that file already spans it (frames outside are kept, without ground truth);
    intrinsics as for a TUM folder (``camera.txt``, else the Freiburg camera its name names)."""

    def __init__(self, folder: Path, cfg: OnlineConfig) -> None:
        from ctcvo.data import tum

        super().__init__(folder, cfg)
        self.intrinsics = tum.intrinsics_for(self.folder)
        self.sensor = tum.SENSOR
        self.last_t = -np.inf
        self._pairs_key: tuple | None = None
        self._pairs_cache: list[tuple[float, str, str, float]] = []
        self._gt_key: tuple | None = None
        self._gt: tuple | None = None

    def _pairs(self, final: bool) -> list[tuple[float, str, str, float]]:
        """(RGB timestamp, RGB file, depth file, depth timestamp) of the settled pairings, in
        time order."""
        from ctcvo.data import tum

        lists = [self.folder / "rgb.txt", self.folder / "depth.txt"]
        key = (final, *(f.stat().st_size if f.is_file() else -1 for f in lists))
        if key == self._pairs_key:  # polled again, nothing written since
            return self._pairs_cache
        (t_rgb, rgb), (t_dep, dep) = (tum.read_image_list(f, growing=True) for f in lists)
        pairs = []
        if len(t_rgb) and len(t_dep):
            ia, ib = tum.associate(t_rgb, t_dep)
            horizon = np.inf if final else min(t_rgb[-1], t_dep[-1]) - 2 * tum.MAX_ASSOC_DT
            pairs = [(float(t_rgb[a]), rgb[a], dep[b], float(t_dep[b])) for a, b in zip(ia.tolist(), ib.tolist())
                     if t_rgb[a] <= horizon]
        self._pairs_key, self._pairs_cache = key, pairs
        return pairs

    def _ready(self, final: bool) -> Iterator[object]:
        return (p for p in self._pairs(final) if p[0] > self.last_t)

    def _groundtruth(self, t: float) -> NDArray[np.float64] | None:
        from ctcvo.data import tum

        path = self.folder / "groundtruth.txt"
        if not path.is_file():
            return None
        st = path.stat()
        if self._gt_key != (st.st_mtime_ns, st.st_size):
            self._gt = tum.read_groundtruth(path)
            self._gt_key = (st.st_mtime_ns, st.st_size)
        t_gt, T_gt = self._gt
        if not t_gt[0] <= t <= t_gt[-1]:
            return None
        return tum.interpolate_poses(t_gt, T_gt, np.array([t]))[0]

    def _read(self, taken: int, item: object) -> Frame:
        from ctcvo.data import tum
        from ctcvo.data.sequence import read_rgb

        t, rgb_file, depth_file, t_depth = item
        rgb = read_rgb(self.folder / rgb_file, self.intrinsics)
        depth = tum.read_depth_file(self.folder / depth_file, self.intrinsics)
        self._stamp(self.folder / rgb_file, self.folder / depth_file)
        pose = self._groundtruth(t)
        self.last_t = t
        return Frame(taken, t, rgb, depth, pose, depth_timestamp=t_depth)

    def present_ids(self) -> NDArray[np.int64]:
        return np.arange(len(self._pairs(final=True)), dtype=np.int64)


def follow_folder(folder: Path, cfg: OnlineConfig) -> FollowFolder:
    """The source of a folder being written: a TUM RGB-D folder once it has ``rgb.txt`` or
    ``depth.txt``, a 7-Scenes-layout one once it has a ``frame-NNNNNN.depth.png``; a folder
    with neither yet is watched for up to ``cfg.timeout_s``."""
    from ctcvo.data import sevenscenes

    folder = Path(folder)
    if not folder.is_dir():
        raise DataError(f"--follow needs a folder, {folder} is not one")
    since = time.monotonic()
    while True:
        if (folder / "rgb.txt").is_file() or (folder / "depth.txt").is_file():
            return FollowTum(folder, cfg)
        if sevenscenes.frame_ids(folder):
            return FollowSevenScenes(folder, cfg)
        if time.monotonic() - since > cfg.timeout_s:
            raise DataError(f"{folder}: no frame arrived within {cfg.timeout_s:g} s (neither a TUM rgb.txt / "
                            "depth.txt nor 7-Scenes frame-NNNNNN.depth.png files)")
        time.sleep(cfg.poll_s)


def open_source(spec: str, frames: str | None = None, follow: bool = False,
                cfg: OnlineConfig = OnlineConfig()) -> FrameSource:
    """The frame source of ``spec`` (``follow``: a folder still being written)."""
    if follow:
        if frames:
            raise ConfigError("--frames does not apply with --follow (frames are taken as they arrive)")
        return follow_folder(Path(spec), cfg)
    from ctcvo.data.scenes import open_scene

    seqs = open_scene(spec, frames=frames)
    if len(seqs) != 1:
        raise ConfigError(f"{spec} holds {len(seqs)} sequences; give one sequence folder")
    return SequenceSource(seqs[0])


# ----------------------------------------------------------------------------------
# teacher edges, frame by frame
# ----------------------------------------------------------------------------------
class OnlineTeacher:
    """The edges (k-g, k), g = 1..cfg.gaps, of each new frame k: the window of ``teacher
    generate`` (:class:`teacher.window.EdgeWindow`, the same code) over the frames as they
    arrive, and the frame ids and timestamps so far."""

    def __init__(self, intr: Intrinsics, cfg, colour=None) -> None:
        """``colour``: the colour camera model (``teacher.odometry.ColourCamera``; None:
        colour registered to depth), as :func:`teacher.generate.colour_camera_for` picks it."""
        from ctcvo.teacher.odometry import make_orb
        from ctcvo.teacher.window import EdgeWindow

        self.intr, self.cfg, self.colour = intr, cfg, colour
        self.orb = make_orb(cfg)
        self.window = EdgeWindow(intr, cfg)
        self.ids: list[int] = []
        self.times: list[float] = []

    def features(self, frame: Frame):
        """Per-frame work (safe to run in one helper thread ahead of :meth:`add`), without
        the maps the frame's dense step needs only as the older frame of a later edge:
        :meth:`finish` adds them, in the same thread, before the next frame's features."""
        from ctcvo.teacher.odometry import extract

        return extract(frame.rgb, frame.depth, self.cfg, self.orb, self.intr.K, self.colour, surface=False)

    def finish(self, fk) -> None:
        """The rest of :meth:`features` (:func:`teacher.odometry.add_surface`): called after
        the frame is handed over, so its own edges do not wait for it."""
        from ctcvo.teacher.odometry import add_surface

        if fk.dense is not None:
            add_surface(fk.dense, fk.depth, self.intr.K, self.cfg)

    def add(self, frame: Frame, fk) -> list:
        """The edges ending at ``frame`` (``EdgeEstimate``; failed ones included)."""
        return self.add_gap1(frame, fk) + self.add_longer()

    def add_gap1(self, frame: Frame, fk) -> list:
        """The first half of :meth:`add`: the gap-1 edge ending at ``frame`` (a list of it,
        empty for the first frame); :meth:`add_longer` follows before the next frame."""
        self.ids.append(int(frame.frame_id))
        self.times.append(float(frame.timestamp))
        return self.window.add_gap1(self.ids[-1], self.times[-1], fk, frame.depth_offset)

    def add_longer(self) -> list:
        """The second half of :meth:`add`: the longer edges ending at the newest frame."""
        return self.window.add_longer()


# ----------------------------------------------------------------------------------
# the run
# ----------------------------------------------------------------------------------
@dataclass
class OnlineResult:
    """What a run did (also in ``report.json``)."""

    out: Path
    frames: int
    fps: float
    latency_ms: dict[str, float]
    interrupted: bool
    report: dict = field(default_factory=dict)
    kept: bool = False
    """A finished run of the same inputs was found and kept (nothing was computed)."""


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


def run(source: FrameSource, out: Path, teacher_cfg=None, checkpoint: Path | None = None,
        predict_cfg=None, graph_cfg=None, cfg: OnlineConfig = OnlineConfig(), device: str = "cpu",
        max_frames: int | None = None, progress: bool = True) -> OnlineResult:
    """Run the online pipeline over ``source`` (see the module docstring); KeyboardInterrupt
    ends it early with every output written for the frames so far (``interrupted``)."""
    from ctcvo.data.formats import Edge
    from ctcvo.data.io import ensure_dir
    from ctcvo.data.open3d_import import open3d_follows_openmp
    from ctcvo.teacher.config import DEFAULT as TEACHER_DEFAULT
    from ctcvo.teacher.generate import colour_camera_for, rolling_shutter_for

    teacher_cfg = teacher_cfg or TEACHER_DEFAULT
    out = ensure_dir(Path(out))
    learner = None
    if checkpoint is not None:
        from ctcvo.learner.online import OnlineLearner  # torch: only with a checkpoint

        learner = OnlineLearner(checkpoint, predict_cfg, device)
    graph = OnlineGraph(graph_cfg)
    teacher = OnlineTeacher(source.intrinsics,
                            dataclasses.replace(teacher_cfg, rolling_shutter_s=rolling_shutter_for(source.sensor, teacher_cfg)),
                            colour_camera_for(source.sensor, teacher_cfg))
    t_edges: list = []
    l_edges: list[Edge] = []
    gts: list[NDArray | None] = []
    lat: list[float] = []
    work: list[float] = []  # prepare + estimate + update + write, without any wait in the queue
    to_pose: list[float] = []  # the same until the frame's pose is written
    cpu_to_pose: list[float] = []  # the CPU time of that work (both threads' shares): what a core each gives
    bar = _Progress(cfg.progress_every_s) if progress else None

    def prepare(frame: Frame):
        feats = teacher.features(frame)
        return frame, feats, (learner.inputs(frame) if learner is not None else None)

    # A helper thread takes frames from the source (decoding them), stamps their arrival and
    # prepares them (teacher features, learner inputs) up to cfg.prefetch frames ahead,
    # then adds what a frame's dense step needs only as the older frame of later edges;
    # this thread estimates edges, updates the graph and writes.
    ahead: queue.Queue = queue.Queue(maxsize=1 if cfg.drop_late else max(cfg.prefetch, 1))
    stop = threading.Event()

    replaced = [0]  # prepared frames a newer one replaced in the queue (drop_late)
    posed = threading.Semaphore(0)  # pose_after_gap1: a frame's pose is written

    def produce() -> None:
        try:
            # OpenMP's thread count is per calling thread: this one builds the dense maps
            # (per-pixel kernels, whose results do not depend on it) on the teacher's count,
            # as the feature thread of a batch run does; the main one aligns (the labels do)
            threadpool_limits(teacher_cfg.threads, user_api="openmp")
            for k, frame in enumerate(source):
                t_take, c_arr = time.perf_counter(), time.thread_time()
                t_arr = source.arrival()  # the frame is here: latency counts from then
                t_arr = t_take if t_arr is None else min(t_arr, t_take)
                item = (t_arr, *prepare(frame), time.perf_counter() - t_take, time.thread_time() - c_arr)
                while not stop.is_set():
                    try:
                        ahead.put(item, timeout=0.1)
                        break
                    except queue.Full:
                        if cfg.drop_late:  # the estimator has not taken the older one yet: replace it
                            try:
                                ahead.get_nowait()
                                replaced[0] += 1
                            except queue.Empty:
                                pass
                        continue
                # what frame k's dense step needs only in later frames' edges: built here,
                # before frame k+1 is handed over (so before the estimator can need it);
                # with pose_after_gap1 once frame k's pose is out, so that Open3D's filters,
                # which hold the GIL, do not hold up that pose
                while cfg.pose_after_gap1 and not stop.is_set() and not posed.acquire(timeout=0.1):
                    pass
                teacher.finish(item[2])
                if stop.is_set() or (max_frames is not None and k + 1 >= max_frames):
                    break
            ahead.put(None)
        except BaseException as exc:  # noqa: BLE001 - handed to the main thread
            ahead.put(exc)

    producer = threading.Thread(target=produce, name="vo-online-frames", daemon=True)
    interrupted = False
    # Ctrl-C ends the run after the frame in hand (a second one at once): a frame cut short
    # would leave the teacher, the graph and the trajectory file with different frames
    asked = threading.Event()

    def on_sigint(signum, frame_) -> None:
        if asked.is_set():
            raise KeyboardInterrupt
        asked.set()

    handler = (signal.signal(signal.SIGINT, on_sigint) if threading.current_thread() is threading.main_thread()
               else None)
    t_start = time.perf_counter()
    fh = open(out / TRAJECTORY, "w")
    fh.write("# timestamp tx ty tz qx qy qz qw  (T_world_cam, metres; each frame's estimate when it arrived)\n")
    n = 0
    # the teacher's Open3D kernels on teacher_cfg.threads threads, as in batch runs
    # (teacher.generate); only around the teacher's calls, so the learner's torch, which
    # shares OpenMP, keeps its threads
    omp_env = contextlib.ExitStack()
    omp_env.enter_context(open3d_follows_openmp(teacher_cfg.threads))
    omp = ThreadpoolController()
    producer.start()
    try:
        while True:
            if asked.is_set():
                raise KeyboardInterrupt
            try:
                item = ahead.get(timeout=0.1)
            except queue.Empty:
                continue
            if item is None:
                break
            if isinstance(item, BaseException):
                raise item
            t_arr, frame, feats, inputs, t_prep, c_prep = item
            t_take, c_take = time.perf_counter(), time.thread_time()
            with omp.limit(limits=teacher_cfg.threads, user_api="openmp"):
                edges = teacher.add_gap1(frame, feats) if cfg.pose_after_gap1 else teacher.add(frame, feats)
            t_edges += edges
            new = _teacher_edges(edges)
            if learner is not None:
                for g, mean, cov, head in learner.add(inputs):
                    e = Edge(teacher.ids[-1 - g], teacher.ids[-1], geo.se3_exp(mean), cov,
                             {"source": "learner", "head": head})
                    l_edges.append(e)
                    new.append(e)
            T = graph.add(int(frame.frame_id), new)
            fh.write(f"{frame.timestamp:.6f} " + " ".join(f"{x:.9f}" for x in geo.T_to_tum(T)) + "\n")
            fh.flush()
            gts.append(frame.T_world_cam)
            n += 1
            t_pose = time.perf_counter()
            lat.append(t_pose - t_arr)
            to_pose.append(t_prep + t_pose - t_take)
            cpu_to_pose.append(c_prep + time.thread_time() - c_take)
            if cfg.pose_after_gap1:  # the longer edges of this frame, after its pose
                posed.release()
                with omp.limit(limits=teacher_cfg.threads, user_api="openmp"):
                    later = teacher.add_longer()
                t_edges += later
                graph.add_edges(_teacher_edges(later))
            work.append(t_prep + time.perf_counter() - t_take if cfg.pose_after_gap1 else to_pose[-1])
            if bar is not None:
                bar.show(n, n / (time.perf_counter() - t_start), lat, len(t_edges) + len(l_edges),
                         source.skipped + replaced[0])
    except KeyboardInterrupt:
        interrupted = True
    finally:
        if handler is not None:
            signal.signal(signal.SIGINT, handler)
        stop.set()
        if isinstance(source, FollowFolder):
            source.stop.set()
        fh.close()
        if bar is not None:
            bar.close()
        producer.join(timeout=5.0)
        omp_env.close()
    seconds = time.perf_counter() - t_start
    if n == 0:
        (out / TRAJECTORY).unlink(missing_ok=True)  # nothing to keep
        raise DataError(f"{source.name}: no frame arrived")
    if len(teacher.ids) > n:  # interrupted inside a frame: keep the frames whose rows were written
        del teacher.ids[n:], teacher.times[n:]
        kept = set(teacher.ids)
        t_edges = [e for e in t_edges if e.j in kept]
        l_edges = [e for e in l_edges if e.j in kept]
    lat_ms = _percentiles_ms(lat)
    report = _finish(out, source, teacher, graph, t_edges, l_edges, gts, teacher_cfg, seconds,
                     {"latency_ms": lat_ms, "frames_skipped": source.skipped + replaced[0],
                      "work_ms": _percentiles_ms(work),
                      "work_to_pose_ms": _percentiles_ms(to_pose), "work_to_pose_cpu_ms": _percentiles_ms(cpu_to_pose)},
                     interrupted, checkpoint)
    return OnlineResult(out, n, n / seconds, lat_ms, interrupted, report)


def _percentiles_ms(seconds: list[float]) -> dict[str, float]:
    """p50, p95, p99 and max of durations in seconds, in milliseconds (report.json's form)."""
    return {f"p{q}": 1000 * float(np.percentile(seconds, q)) for q in (50, 95, 99)} | {"max": 1000 * max(seconds)}


def _teacher_edges(estimates: list) -> list:
    """The graph edges (``data.formats.Edge``) of the good teacher estimates (``EdgeEstimate``)."""
    from ctcvo.data.formats import Edge

    return [Edge(e.i, e.j, e.T_i_j, e.cov, {"source": "teacher"}) for e in estimates if e.ok]


def fingerprint(spec: str, source: FrameSource, teacher_cfg, checkpoint: Path | None = None, predict_cfg=None,
                graph_cfg=None, cfg: OnlineConfig = OnlineConfig()):
    """The inputs of an online run (``data.runs.Fingerprint``): scene, sequence, frames (with
    ``--follow``: as they arrive), the teacher's config (without its process settings), the
    checkpoint and the calibration beside it (content digests), the MC-dropout settings and
    the graph's config."""
    from ctcvo.data.runs import STAGE_VERSIONS, Fingerprint, file_digest, frames_id, scene_id
    from ctcvo.posegraph.config import ONLINE

    tconf = teacher_cfg.to_dict()
    for k in ("workers", "chunk_frames"):  # how batch runs share the work; no effect here
        tconf.pop(k, None)
    follow = isinstance(source, FollowFolder)
    cal = Path(checkpoint).parent / "calibration.json" if checkpoint is not None else None
    if checkpoint is not None:
        from ctcvo.learner.config import PredictConfig, to_dict

        pconf = to_dict(predict_cfg or PredictConfig())
    return Fingerprint("online", {
        "scene": scene_id(spec), "sequence": source.name,
        "frames": "as they arrive" if follow else frames_id(source.seq.ids()) if isinstance(source, SequenceSource)
        else None, "follow": follow, "teacher": tconf, "teacher_version": STAGE_VERSIONS["teacher"],
        "checkpoint": file_digest(checkpoint) if checkpoint is not None else None,
        "calibration": file_digest(cal) if cal is not None and cal.is_file() else None,
        "predict": pconf if checkpoint is not None else None, "graph": (graph_cfg or ONLINE).to_dict(),
        "pose_after_gap1": cfg.pose_after_gap1,
        **({"drop_late": True} if cfg.drop_late else {})})  # absent when off: earlier runs stay valid


def online(spec: str, out: Path | None = None, *, frames: str | None = None, follow: bool = False,
           teacher_cfg=None, checkpoint: Path | None = None, predict_cfg=None, graph_cfg=None,
           cfg: OnlineConfig = OnlineConfig(), device: str = "cpu", overwrite: bool = False,
           progress: bool = True) -> OnlineResult:
    """``vo-online``: :func:`run` over the scene ``spec`` into ``out`` (default
    ``runs/<scene-slug>/online``), under the rerun rule of :mod:`data.runs`.

    A finished run of the same inputs is kept (returned from its ``report.json``; with
    ``follow``, only while the folder holds no frame the run did not take); an interrupted
    or killed one is run again; outputs of other inputs are replaced with ``overwrite``,
    otherwise :class:`data.runs.StaleOutputError` says what differs. A run is finished when
    its ``report.json`` (written last) says it was not interrupted."""
    import json

    from ctcvo.data.runs import FINGERPRINT_FILE, claim, output_folder, stage_dir, write_fingerprint
    from ctcvo.teacher.config import DEFAULT as TEACHER_DEFAULT

    teacher_cfg = teacher_cfg or TEACHER_DEFAULT
    out = Path(out) if out is not None else stage_dir(spec, "online")
    with output_folder(out):
        source = open_source(spec, frames, follow, cfg)
        fp = fingerprint(spec, source, teacher_cfg, checkpoint, predict_cfg, graph_cfg, cfg)
        report = None
        if (out / REPORT).is_file():
            try:
                report = json.loads((out / REPORT).read_text())
            except (OSError, ValueError):
                report = None  # unreadable: not a finished run
        done = isinstance(report, dict) and report.get("interrupted") is False
        if done and follow:
            from ctcvo.data.runs import frames_id

            done = report.get("frame_ids") == frames_id(source.present_ids())
        if claim(out, fp, done=done, has_outputs=report is not None, overwrite=overwrite, outputs=OUTPUT_FILES):
            log.info("%s: online run of the same inputs: kept", out)
            lat = report.get("latency_ms") or {}
            return OnlineResult(out, int(report["frames"]), float(report.get("fps") or 0.0), lat, False, report,
                                kept=True)
        for name in OUTPUT_FILES:  # an unfinished run of the same inputs: start afresh, report.json first
            (out / name).unlink(missing_ok=True)
        from ctcvo.data.io import ensure_dir

        write_fingerprint(ensure_dir(out), fp)
        try:
            return run(source, out, teacher_cfg, checkpoint, predict_cfg, graph_cfg, cfg, device, progress=progress)
        except BaseException:
            if not (out / TRAJECTORY).exists():  # not one frame taken: leave nothing behind
                (out / FINGERPRINT_FILE).unlink(missing_ok=True)
            raise


def _finish(out: Path, source: FrameSource, teacher: OnlineTeacher, graph: OnlineGraph, t_edges: list,
            l_edges: list, gts: list, teacher_cfg, seconds: float, timing: dict, interrupted: bool,
            checkpoint: Path | None) -> dict:
    """Write the final trajectory, the edge folders and report.json (all atomically)."""
    from ctcvo.data.formats import Edge, Trajectory, write_g2o, write_tum
    from ctcvo.data.io import ensure_dir, git_revision, json_safe, write_json
    from ctcvo.data.metrics import trajectory_report
    from ctcvo.data.runs import frames_id
    from ctcvo.teacher.generate import chain_trajectory

    ids = np.array(teacher.ids, dtype=np.int64)
    times = np.array(teacher.times)
    n = len(ids)
    final = graph.final()[:n]  # the graph may hold a frame an interrupt cut short
    write_tum(out / FINAL_TRAJECTORY, Trajectory(times, final))
    t_edges = sorted(t_edges, key=lambda e: (e.i, e.j))  # the order of teacher generate's files
    good = [Edge(e.i, e.j, e.T_i_j, e.cov) for e in t_edges if e.ok]
    chained, _ = chain_trajectory(ids, t_edges)
    tdir = ensure_dir(out / "teacher")
    write_g2o(tdir / "edges.g2o", good, {int(f): T for f, T in zip(ids, chained)})
    write_tum(tdir / "trajectory.tum", Trajectory(times, chained))
    has_gt = n >= 2 and all(g is not None for g in gts)
    if has_gt:
        gt = Trajectory(times, np.stack(gts))
        write_tum(tdir / "groundtruth.tum", gt)
    if l_edges:
        ldir = ensure_dir(out / "learner")
        write_g2o(ldir / "edges.g2o", [Edge(e.i, e.j, e.T_i_j, e.cov) for e in sorted(l_edges, key=lambda e: (e.i, e.j))],
                  {int(f): T for f, T in zip(ids, final)})
    report: dict = {
        "sequence": source.name, "frames": n, "seconds": seconds, "fps": n / seconds if seconds > 0 else None,
        **timing, "interrupted": interrupted,
        "teacher_edges": len(good), "teacher_failed_edges": len(t_edges) - len(good),
        "learner_edges": len(l_edges), "checkpoint": str(checkpoint) if checkpoint else None,
        "covariance_scales": graph.scale, "graph_reviews": graph.reviews, "final_polish": graph.polish,
        "outlier_edges": {"removed": int((graph.status == 2).sum()), "downweighted": int((graph.status == 1).sum())},
        "frame_ids": frames_id(ids), "teacher": teacher_cfg.to_dict(), "git_revision": git_revision(),
    }
    if has_gt:
        report["final"] = trajectory_report(gt, Trajectory(times, final))
        if graph.polish is not None:
            report["final_isam2"] = trajectory_report(gt, Trajectory(times, graph.isam2_poses[:n]))
        report["online"] = trajectory_report(gt, Trajectory(times, _read_rows(out / TRAJECTORY, n)))
        report["teacher_chain"] = trajectory_report(gt, Trajectory(times, chained))
    report = json_safe(report)  # what a later run reads back from the file (tuples as lists)
    write_json(out / REPORT, report)
    return report


def _read_rows(path: Path, n: int) -> NDArray[np.float64]:
    from ctcvo.data.formats import read_tum

    return read_tum(path).poses[:n]


# ----------------------------------------------------------------------------------
# command line
# ----------------------------------------------------------------------------------
def build_parser() -> argparse.ArgumentParser:
    from ctcvo.data.scenes import add_topic_options
    from ctcvo.teacher.config import PRESETS as TEACHER_PRESETS

    p = argparse.ArgumentParser(prog="ctcvo online", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--scene", required=True, help="sequence folder, ROS bag or synthetic/NAME; with --follow "
                   "a 7-Scenes-layout or TUM RGB-D folder being written")
    p.add_argument("--checkpoint", type=Path, help="learner checkpoint: add its MC-dropout edges")
    p.add_argument("--out", type=Path, help="output folder (default runs/<scene>/online)")
    p.add_argument("--overwrite", action="store_true",
                   help="replace the outputs of other inputs in --out instead of stopping with an error")
    p.add_argument("--frames", help="frame range START:STOP[:STEP]")
    p.add_argument("--follow", action="store_true", help="the folder is still being written: wait for new frames")
    p.add_argument("--timeout", type=float, default=OnlineConfig.timeout_s,
                   help="--follow: end after this many seconds without a new frame")
    p.add_argument("--poll", type=float, default=OnlineConfig.poll_s, help="--follow: seconds between polls")
    p.add_argument("--gaps", type=int, help="teacher edges to the last K frames (default: the preset's)")
    p.add_argument("--preset", default="default", choices=sorted(TEACHER_PRESETS), help="teacher preset")
    p.add_argument("--pose-after-gap1", action="store_true",
                   help="write each frame's pose once its gap-1 edge is in the graph; its longer edges follow")
    p.add_argument("--drop-late", action="store_true",
                   help="--follow: when frames come faster than they are processed, take the newest and skip "
                   "the ones in between (bounded latency, fewer frames)")
    p.add_argument("--dense-max-gap", type=int, help="teacher: dense step only on edges of at most this many "
                   "frames (0: every edge; default: the preset's); less work per frame, see bench/README.md")
    p.add_argument("--samples", type=int, help="MC-dropout passes K (default 10)")
    p.add_argument("--max-gap", type=int, help="learner edges to the last frames (default 5)")
    p.add_argument("--device", default="cpu", choices=["auto", "cpu", "cuda"], help="learner device")
    p.add_argument("-v", "--verbose", action="store_true")
    add_topic_options(p)
    return p


def main(argv: Sequence[str] | None = None) -> int:
    from ctcvo.data.io import setup_logging

    args = build_parser().parse_args(argv)
    setup_logging(args.verbose, "%(message)s")
    try:
        from ctcvo.data.scenes import scene_with_topics
        from ctcvo.learner.config import PredictConfig
        from ctcvo.teacher.config import PRESETS as TEACHER_PRESETS

        scene = scene_with_topics(args.scene, args)
        tcfg = TEACHER_PRESETS[args.preset]
        if args.gaps is not None:
            if args.gaps < 1:
                raise ConfigError(f"--gaps must be >= 1, got {args.gaps}")
            tcfg = dataclasses.replace(tcfg, gaps=args.gaps)
        if args.dense_max_gap is not None:
            if args.dense_max_gap < 0:
                raise ConfigError(f"--dense-max-gap must be >= 0 (0: every edge), got {args.dense_max_gap}")
            tcfg = dataclasses.replace(tcfg, dense_max_gap=args.dense_max_gap)
        pcfg = PredictConfig(**{k: v for k, v in (("samples", args.samples), ("max_gap", args.max_gap)) if v is not None})
        if args.timeout <= 0 or args.poll <= 0:
            raise ConfigError("--timeout and --poll must be positive")
        if args.drop_late and not args.follow:
            raise ConfigError("--drop-late needs --follow (a recording read from disk has every frame taken)")
        ocfg = OnlineConfig(poll_s=args.poll, timeout_s=args.timeout, pose_after_gap1=args.pose_after_gap1,
                            drop_late=args.drop_late)
        res = online(scene, args.out, frames=args.frames, follow=args.follow, teacher_cfg=tcfg,
                     checkpoint=args.checkpoint, predict_cfg=pcfg if args.checkpoint else None, cfg=ocfg,
                     device=args.device, overwrite=args.overwrite)
    except VOError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:  # outside the frame loop (opening, writing)
        print("error: interrupted", file=sys.stderr)
        return 130
    rep = res.report
    line = (f"{res.frames} frames, {res.fps:.1f} fps, latency p50 {res.latency_ms['p50']:.0f} ms / "
            f"p95 {res.latency_ms['p95']:.0f} ms")
    if "final" in rep:
        line += f", ATE {1000 * rep['final']['ate_rmse_m']:.1f} mm"
    if res.interrupted:
        print(f"interrupted after {line}; trajectory so far in {res.out / TRAJECTORY}", file=sys.stderr)
        return 130
    print(f"{line} -> {res.out}" + (" (kept: a finished run of the same inputs)" if res.kept else ""))
    return 0


if __name__ == "__main__":
    sys.exit(main())
