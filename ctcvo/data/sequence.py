"""One sequence interface for every dataset (7-Scenes, TUM RGB-D, synthetic).

A :class:`Sequence` knows its name, intrinsics, timestamps (a frame's timestamp is its
colour image's; its depth image's, where that differs, is ``depth_times()``) and
(optionally) ground-truth ``T_world_cam`` poses, and reads frames lazily: ``seq.rgb(k)`` and ``seq.depth(k)`` decode
one image each, and a bad file raises :class:`~data.errors.DataError` naming it.

Frame *positions* ``k`` run over ``0..len(seq)-1``; ``seq.frame_ids[k]`` is the frame's
index in the full recording (the id written to edge and trajectory files), so a
sub-range ``seq.select(450, 600)`` keeps the ids 450..599.
"""

from __future__ import annotations

import abc
import copy
import functools
from collections.abc import Sequence as TypingSequence
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
from numpy.typing import NDArray

from ctcvo.data.errors import ConfigError, DataError
from ctcvo.data.sensor import Sensor

cv2.setNumThreads(1)  # frames are decoded in a thread pool; keep OpenCV single-threaded


@dataclass(frozen=True)
class Intrinsics:
    """Pinhole intrinsics of the (depth-registered) camera, pixels."""

    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int

    @property
    def K(self) -> NDArray[np.float64]:
        """3x3 camera matrix."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    def scaled(self, width: int, height: int) -> Intrinsics:
        """Intrinsics of the same camera resampled to ``width x height``."""
        sx, sy = width / self.width, height / self.height
        return Intrinsics(self.fx * sx, self.fy * sy, self.cx * sx, self.cy * sy, width, height)


@dataclass(frozen=True)
class Frame:
    """One RGB-D frame.

    ``rgb`` is (H, W, 3) uint8 in RGB order; ``depth`` is (H, W) float32 metres with 0 for
    invalid pixels; ``T_world_cam`` is the ground-truth pose (4x4) or ``None``.
    ``timestamp`` is the colour image's; ``depth_timestamp`` the depth image's when the
    source records one (TUM RGB-D: the two streams are not taken at the same moment), else
    ``None`` (the same moment).
    """

    frame_id: int
    timestamp: float
    rgb: NDArray[np.uint8]
    depth: NDArray[np.float32]
    T_world_cam: NDArray[np.float64] | None
    depth_timestamp: float | None = None

    @property
    def depth_offset(self) -> float:
        """Depth minus colour timestamp, seconds (0 when the source records none)."""
        return 0.0 if self.depth_timestamp is None else float(self.depth_timestamp - self.timestamp)


def _decode(path: Path, what: str, flags: int, intr: Intrinsics | None) -> NDArray:
    """``cv2.imdecode`` of an image file; :class:`DataError` if it is missing, unreadable
    or not of the intrinsics' size."""
    if not path.is_file():
        raise DataError(f"missing {what} image {path}")
    buf = np.fromfile(path, dtype=np.uint8)
    img = cv2.imdecode(buf, flags) if buf.size else None
    if img is None:
        raise DataError(f"corrupt or unreadable {what} image {path}")
    if what == "depth" and (img.dtype != np.uint16 or img.ndim != 2):
        raise DataError(f"depth image {path} must be single-channel 16-bit, got {img.dtype} with shape {img.shape}")
    if intr is not None and img.shape[:2] != (intr.height, intr.width):
        raise DataError(f"{what} image {path} is {img.shape[1]}x{img.shape[0]}, expected {intr.width}x{intr.height}")
    return img


def read_rgb(path: Path, intr: Intrinsics | None = None) -> NDArray[np.uint8]:
    """Decode a colour image to (H, W, 3) uint8 RGB; clear error if unreadable or mis-sized."""
    return cv2.cvtColor(_decode(Path(path), "colour", cv2.IMREAD_COLOR, intr), cv2.COLOR_BGR2RGB)


def read_depth(
    path: Path, scale: float, intr: Intrinsics | None = None, invalid: TypingSequence[int] = (0,)
) -> NDArray[np.float32]:
    """Decode a 16-bit depth PNG to float32 metres (``raw / scale``; ``invalid`` raw values -> 0)."""
    raw = _decode(Path(path), "depth", cv2.IMREAD_UNCHANGED, intr)
    return _depth_table(float(scale), tuple(invalid))[raw]


@functools.lru_cache(maxsize=8)
def _depth_table(scale: float, invalid: tuple[int, ...]) -> NDArray[np.float32]:
    """Metres of every raw 16-bit value (``raw / scale``, ``invalid`` -> 0): one look-up per
    pixel instead of a conversion, a division and a mask per invalid value (0.85 -> 0.3 ms
    at 640x480)."""
    table = np.arange(65536, dtype=np.float32) / np.float32(scale)
    table[list(invalid)] = 0.0
    table.setflags(write=False)
    return table


class Sequence(abc.ABC):
    """An RGB-D sequence read lazily. Subclasses implement the ``_``-prefixed readers."""

    #: short name, used for output folders (e.g. ``redkitchen-seq-01``)
    name: str
    intrinsics: Intrinsics
    #: the camera that recorded it, as the reader knows it
    sensor: Sensor
    #: the lens undistortion applied to every frame read (:class:`data.undistort.Undistortion`),
    #: None for frames used as recorded
    undistortion = None

    def __init__(self, name: str, intrinsics: Intrinsics, timestamps: NDArray[np.float64],
                 frame_ids: NDArray[np.int64], gt: NDArray[np.float64] | None,
                 depth_timestamps: NDArray[np.float64] | None = None, *, sensor: Sensor) -> None:
        """``timestamps``: each frame's colour image's; ``depth_timestamps``: its depth
        image's (None: the same moments)."""
        if len(timestamps) == 0:
            raise DataError(f"sequence {name} has no frames")
        self.name = name
        self.intrinsics = intrinsics
        self.sensor = sensor
        self.timestamps = np.asarray(timestamps, dtype=np.float64)
        self.depth_timestamps = None if depth_timestamps is None else np.asarray(depth_timestamps, dtype=np.float64)
        if self.depth_timestamps is not None and (self.depth_timestamps.shape != self.timestamps.shape
                                                  or not np.all(np.isfinite(self.depth_timestamps))):
            raise DataError(f"sequence {name}: {len(self.depth_timestamps)} depth timestamps for "
                            f"{len(self.timestamps)} frames, or not all finite")
        self.frame_ids = np.asarray(frame_ids, dtype=np.int64)
        self._gt = gt
        self._positions = np.arange(len(self.timestamps))
        #: why a frame's ground-truth pose is unusable (NaN in ``_gt``), by position in the full sequence
        self.gt_problems: dict[int, str] = {}

    # -- readers implemented per dataset, addressed by position in the *full* sequence
    @abc.abstractmethod
    def _read_rgb(self, pos: int) -> NDArray[np.uint8]: ...

    @abc.abstractmethod
    def _read_depth(self, pos: int) -> NDArray[np.float32]: ...

    # -- public API, addressed by position in this (possibly selected) view
    def __len__(self) -> int:
        return len(self._positions)

    @property
    def has_groundtruth(self) -> bool:
        return self._gt is not None

    def rgb(self, k: int) -> NDArray[np.uint8]:
        """(H, W, 3) uint8 RGB of frame position ``k`` (undistorted by :attr:`undistortion`)."""
        img = self._read_rgb(int(self._positions[k]))
        return img if self.undistortion is None else self.undistortion.rgb(img)

    def depth(self, k: int) -> NDArray[np.float32]:
        """(H, W) float32 depth in metres of frame position ``k`` (0 = invalid; undistorted by
        :attr:`undistortion`)."""
        depth = self._read_depth(int(self._positions[k]))
        return depth if self.undistortion is None else self.undistortion.depth(depth)

    def ids(self) -> NDArray[np.int64]:
        """Frame ids (indices in the full recording) of this view, (N,)."""
        return self.frame_ids[self._positions]

    def times(self) -> NDArray[np.float64]:
        """Timestamps in seconds of this view (the colour images'), (N,)."""
        return self.timestamps[self._positions]

    def depth_times(self) -> NDArray[np.float64]:
        """Timestamps in seconds of this view's depth images, (N,): :meth:`times` where the
        source records none (7-Scenes; synthetic scenes rendered without a colour-depth
        time offset)."""
        src = self.timestamps if self.depth_timestamps is None else self.depth_timestamps
        return src[self._positions]

    def depth_offsets(self) -> NDArray[np.float64]:
        """Depth minus colour timestamp of each frame of this view, seconds (N,); zeros
        where the source records no depth timestamps (the same moments)."""
        if self.depth_timestamps is None:
            return np.zeros(len(self._positions))
        return self.depth_timestamps[self._positions] - self.timestamps[self._positions]

    def groundtruth(self, partial: bool = False) -> NDArray[np.float64] | None:
        """Ground-truth ``T_world_cam`` of this view, (N, 4, 4), or ``None``. A frame whose
        pose the reader found unusable (:meth:`groundtruth_dropped`) is a
        :class:`DataError` naming it, or with ``partial`` a NaN row."""
        if self._gt is None:
            return None
        if not partial and (dropped := self.groundtruth_dropped()):
            more = f" (and {len(dropped) - 1} more frames)" if len(dropped) > 1 else ""
            raise DataError(dropped[0]["why"] + more)
        return self._gt[self._positions]

    def groundtruth_dropped(self) -> list[dict]:
        """``{"frame": id, "why": ...}`` of every frame of this view whose ground-truth pose
        is unusable (a non-finite pose file): the teacher leaves it out of its evaluation."""
        return [{"frame": int(self.frame_ids[p]), "why": self.gt_problems[int(p)]}
                for p in self._positions if int(p) in self.gt_problems]

    def frame(self, k: int) -> Frame:
        gt = self.groundtruth(partial=True)
        return Frame(
            frame_id=int(self.ids()[k]), timestamp=float(self.times()[k]), rgb=self.rgb(k),
            depth=self.depth(k), T_world_cam=None if gt is None else gt[k],
            depth_timestamp=None if self.depth_timestamps is None else float(self.depth_times()[k]),
        )

    def select(self, start: int | None = None, stop: int | None = None, step: int | None = None) -> Sequence:
        """A view of frame positions ``start:stop:step`` of this view (ids are kept)."""
        view = copy.copy(self)
        view._positions = self._positions[slice(start, stop, step)]
        if len(view._positions) == 0:
            raise DataError(f"frame range {start}:{stop} of {self.name} is empty ({len(self)} frames)")
        return view

    def without(self, ids: TypingSequence[int]) -> Sequence:
        """A view of this view without the frames of the given ids (frames the teacher skipped)."""
        view = copy.copy(self)
        view._positions = self._positions[~np.isin(self.ids(), np.asarray(list(ids), dtype=np.int64))]
        if len(view._positions) == 0:
            raise DataError(f"no frame of {self.name} is left")
        return view

    def __repr__(self) -> str:
        return f"{type(self).__name__}({self.name!r}, {len(self)} frames, gt={self.has_groundtruth})"


def frame_ranges_overlap(a: str | None, b: str | None) -> bool:
    """Whether two frame ranges (``START:STOP[:STEP]`` specs of one sequence; ``None`` = all
    frames) can share a frame position. Steps are ignored (a shared interval counts), and
    negative bounds (counted from the end) are assumed to overlap."""
    a0, a1, _ = parse_frame_range(a)
    b0, b1, _ = parse_frame_range(b)
    if any(v is not None and v < 0 for v in (a0, a1, b0, b1)):
        return True
    lo = max(a0 or 0, b0 or 0)
    hi = min(float("inf") if a1 is None else a1, float("inf") if b1 is None else b1)
    return lo < hi


def parse_frame_range(spec: str | None) -> tuple[int | None, int | None, int | None]:
    """Parse ``A:B`` / ``A:B:S`` / ``A:`` (Python slice syntax over frame positions)."""
    if spec is None or spec == "":
        return None, None, None
    parts = spec.split(":")
    if len(parts) not in (2, 3):
        raise ConfigError(f"frame range must look like START:STOP[:STEP], got {spec!r}")
    try:
        vals = [int(p) if p.strip() else None for p in parts]
    except ValueError:
        raise ConfigError(f"frame range must contain integers, got {spec!r}") from None
    if len(vals) == 2:
        vals.append(None)
    if vals[2] is not None and vals[2] <= 0:
        raise ConfigError(f"frame range step must be positive, got {spec!r}")
    return vals[0], vals[1], vals[2]
