"""Frame sources: the frames of a sequence one at a time, or of a folder still being written
(a 7-Scenes-layout or a TUM RGB-D folder), as they become complete.

A followed folder is polled; a 7-Scenes-layout one gives ``frame-NNNNNN.color.{png,jpg}`` +
``frame-NNNNNN.depth.png`` (optional ``.pose.txt``), a TUM one grows ``rgb.txt`` and
``depth.txt`` (colour and depth paired by timestamp as for a finished TUM folder). A
followed frame's arrival is when its last file was written.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from ctcvo.data import sevenscenes, tum
from ctcvo.data.errors import DataError
from ctcvo.data.sensor import Sensor
from ctcvo.data.sequence import Frame, Intrinsics, Sequence, read_rgb

log = logging.getLogger(__name__)


class FrameSource:
    """Frames in order, one at a time, with the camera's intrinsics and sensor."""

    name: str
    intrinsics: Intrinsics
    sensor: Sensor
    skipped: int = 0
    """Frames passed over to hand out a newer one (``drop_late``)."""

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

    def __init__(self, seq: Sequence) -> None:
        self.seq, self.name, self.intrinsics, self.sensor = seq, seq.name, seq.intrinsics, seq.sensor

    def __iter__(self) -> Iterator[Frame]:
        for k in range(len(self.seq)):
            yield self.seq.frame(k)


class FollowFolder(FrameSource):
    """A folder still being written (:func:`follow_folder` picks the layout), looked at every
    ``poll_s`` seconds: frames are taken in order as they become complete (with
    ``drop_late``, the newest complete one, passing over older ones not taken yet); a frame
    whose files exist but do not decode yet (written without a rename) is retried until
    ``timeout_s``; the frames end when no new one came for ``timeout_s``. A frame's arrival
    is when the last of its files was written (their modification time). Subclasses say
    which frames are ready."""

    def __init__(self, folder: Path, poll_s: float, timeout_s: float, drop_late: bool = False) -> None:
        self.folder, self.poll_s, self.timeout_s, self.drop_late = Path(folder), poll_s, timeout_s, drop_late
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
        if not self.drop_late:
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
                    if time.monotonic() - waited_since > self.timeout_s:
                        raise
                    time.sleep(self.poll_s)
                    continue
                self.skipped += passed_over
                yield frame
                taken, waited_since = taken + 1, time.monotonic()
                continue
            if final:
                return
            if time.monotonic() - waited_since > self.timeout_s:
                log.info("%s: no new frame for %.1f s, ending", self.folder, self.timeout_s)
                final = True  # what is there now is all there is
                continue
            time.sleep(self.poll_s)


class FollowSevenScenes(FollowFolder):
    """A 7-Scenes-layout folder being written: frame ids in increasing order as their
    ``frame-NNNNNN.color.{png,jpg}`` and ``frame-NNNNNN.depth.png`` appear (timestamps
    ``id / 30`` s; ground truth from ``.pose.txt``; intrinsics from
    ``camera-intrinsics.txt`` of the folder or its parent, else the 7-Scenes default)."""

    def __init__(self, folder: Path, poll_s: float, timeout_s: float, drop_late: bool = False) -> None:
        super().__init__(folder, poll_s, timeout_s, drop_late)
        self.intrinsics = sevenscenes.folder_intrinsics(self.folder)
        self.sensor = sevenscenes.folder_sensor(self.folder)
        self.last = -1

    def _ready(self, final: bool) -> Iterator[object]:
        for k in (k for k in sevenscenes.frame_ids(self.folder) if k > self.last):
            colour = sevenscenes.colour_file(self.folder, k)
            if colour is None:
                return
            yield k, colour

    def _read(self, taken: int, item: object) -> Frame:
        k, colour = item
        rgb = read_rgb(colour, self.intrinsics)
        depth = sevenscenes.read_depth_file(sevenscenes.depth_file(self.folder, k), self.intrinsics)
        self._stamp(colour, sevenscenes.depth_file(self.folder, k))
        pose_file = self.folder / f"frame-{k:06d}.pose.txt"
        pose = sevenscenes.read_pose_file(pose_file) if pose_file.is_file() else None
        self.last = k
        return Frame(k, k / sevenscenes.FPS, rgb, depth, pose)

    def present_ids(self) -> NDArray[np.int64]:
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

    def __init__(self, folder: Path, poll_s: float, timeout_s: float, drop_late: bool = False) -> None:
        super().__init__(folder, poll_s, timeout_s, drop_late)
        self.intrinsics, self.undistortion = tum.camera_for(self.folder)
        self.sensor = tum.SENSOR
        self.last_t = -np.inf
        self._pairs_key: tuple | None = None
        self._pairs_cache: list[tuple[float, str, str, float]] = []
        self._gt_key: tuple | None = None
        self._gt: tuple | None = None

    def _pairs(self, final: bool) -> list[tuple[float, str, str, float]]:
        """(RGB timestamp, RGB file, depth file, depth timestamp) of the settled pairings, in
        time order."""
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
        t, rgb_file, depth_file, t_depth = item
        rgb = tum.read_rgb_file(self.folder / rgb_file, self.intrinsics, self.undistortion)
        depth = tum.read_depth_file(self.folder / depth_file, self.intrinsics, self.undistortion)
        self._stamp(self.folder / rgb_file, self.folder / depth_file)
        pose = self._groundtruth(t)
        self.last_t = t
        return Frame(taken, t, rgb, depth, pose, depth_timestamp=t_depth)

    def present_ids(self) -> NDArray[np.int64]:
        return np.arange(len(self._pairs(final=True)), dtype=np.int64)


def follow_folder(folder: Path, poll_s: float, timeout_s: float, drop_late: bool = False) -> FollowFolder:
    """The source of a folder being written: a TUM RGB-D folder once it has ``rgb.txt`` or
    ``depth.txt``, a 7-Scenes-layout one once it has a ``frame-NNNNNN.depth.png``; a folder
    with neither yet is watched for up to ``timeout_s``."""
    folder = Path(folder)
    if not folder.is_dir():
        raise DataError(f"--follow needs a folder, {folder} is not one")
    since = time.monotonic()
    while True:
        if (folder / "rgb.txt").is_file() or (folder / "depth.txt").is_file():
            return FollowTum(folder, poll_s, timeout_s, drop_late)
        if sevenscenes.frame_ids(folder):
            return FollowSevenScenes(folder, poll_s, timeout_s, drop_late)
        if time.monotonic() - since > timeout_s:
            raise DataError(f"{folder}: no frame arrived within {timeout_s:g} s (neither a TUM rgb.txt / "
                            "depth.txt nor 7-Scenes frame-NNNNNN.depth.png files)")
        time.sleep(poll_s)
