"""ROS1 ``.bag`` files and ROS2 bag folders (sqlite3 or mcap) as sequences, read with
`rosbags <https://gitlab.com/ternaris/rosbags>`_.

What is read (docs/formats.md, "ROS bags"):

* **Colour**: ``sensor_msgs/Image`` with encoding ``rgb8``, ``bgr8``, ``mono8`` (also
  ``rgba8``/``bgra8``), or ``sensor_msgs/CompressedImage`` (any format OpenCV decodes).
* **Depth**: ``sensor_msgs/Image`` ``16UC1`` (or ``mono16``) in millimetres, 0 invalid;
  ``32FC1`` in metres, NaN/inf/<= 0 invalid.
* **Intrinsics**: the first ``sensor_msgs/CameraInfo`` message (``K``, width, height) of
  the camera-info topic. They are taken as those of the registered depth image, as for the
  folder datasets.
* **Ground truth** (optional): a ``geometry_msgs/PoseStamped`` or
  ``geometry_msgs/TransformStamped`` topic, or a ``tf2_msgs/TFMessage`` topic (``/tf``)
  restricted to one parent/child pair; the message gives ``T_parent_child``, taken as
  ``T_world_cam``. It is interpolated to the frame times as for TUM RGB-D.

**Topics** are found automatically when that is unambiguous (one colour and one depth
image topic, judged by each topic's first message's encoding; the camera info next to the
colour topic, else the only one), otherwise named in the scene spec (see
:func:`parse_spec`; the CLIs' ``--rgb-topic``, ``--depth-topic``, ``--camera-info-topic``
and ``--gt-topic`` write it).

**Timestamps** are the messages' ``header.stamp``; colour and depth are associated as in
:func:`data.tum.associate` (nearest first within 0.02 s). Frame ids are positions
``0..N-1`` after association.

**Streaming.** Opening a bag reads every message's header once (to associate frames) and
keeps only timestamps; images are decoded when a frame is read. Frames read in order are
served by one forward pass over the bag (a small look-ahead buffer, never the whole
recording); a jump backwards restarts the pass at that frame.
"""

from __future__ import annotations

import contextlib
import logging
import sqlite3
import struct
import threading
from collections import OrderedDict
from collections.abc import Iterator
from dataclasses import dataclass, fields, replace
from pathlib import Path
from urllib.parse import parse_qsl, urlencode

import cv2
import numpy as np
from numpy.typing import NDArray

from ctcvo.data import geometry as geo
from ctcvo.data import tum
from ctcvo.data.errors import ConfigError, DataError
from ctcvo.data.sensor import KINECT_V1_READOUT_S, Sensor
from ctcvo.data.sequence import Intrinsics, Sequence, _depth_table
from ctcvo.data.undistort import COEFF_COUNTS, Undistortion, undistortion

log = logging.getLogger(__name__)

IMAGE = "sensor_msgs/msg/Image"
COMPRESSED = "sensor_msgs/msg/CompressedImage"
CAMERA_INFO = "sensor_msgs/msg/CameraInfo"
POSE_STAMPED = "geometry_msgs/msg/PoseStamped"
TRANSFORM_STAMPED = "geometry_msgs/msg/TransformStamped"
TF_MESSAGE = "tf2_msgs/msg/TFMessage"
GT_TYPES = (POSE_STAMPED, TRANSFORM_STAMPED, TF_MESSAGE)

COLOUR_ENCODINGS = ("rgb8", "bgr8", "mono8", "rgba8", "bgra8")
DEPTH_ENCODINGS = ("16UC1", "mono16", "32FC1")
#: Raw 16-bit depth units per metre (``16UC1`` is millimetres by ROS convention, REP 118).
DEPTH_SCALE_16U = 1000.0
#: Frames decoded ahead of the reader and kept until used (forward pass look-ahead).
LOOKAHEAD = 16
#: Separator between a bag path and its topic options in a scene spec.
SPEC_SEP = "?"


# ----------------------------------------------------------------------------------
# scene spec: a bag path plus its topics
# ----------------------------------------------------------------------------------
@dataclass(frozen=True)
class BagTopics:
    """Topics to read; ``None`` = detect automatically (``gt``: no ground truth)."""

    rgb: str | None = None
    """Colour topic (``sensor_msgs/Image`` or ``CompressedImage``)."""
    depth: str | None = None
    """Depth topic (``sensor_msgs/Image``, ``16UC1`` mm or ``32FC1`` m)."""
    camera_info: str | None = None
    """``sensor_msgs/CameraInfo`` topic giving the intrinsics."""
    gt: str | None = None
    """Ground-truth topic: PoseStamped, TransformStamped, or ``TOPIC[:PARENT:CHILD]`` for tf."""

    def query(self) -> str:
        return urlencode({f.name: v for f in fields(self) if (v := getattr(self, f.name))}, safe="/:")


def parse_spec(spec: str) -> tuple[Path, BagTopics]:
    """Split ``path/rec.bag?rgb=/cam/rgb&depth=/cam/depth&camera_info=...&gt=...`` into the
    bag path and its :class:`BagTopics` (every key optional)."""
    path, _, query = spec.partition(SPEC_SEP)
    names = {f.name for f in fields(BagTopics)}
    opts: dict[str, str] = {}
    for k, v in parse_qsl(query, keep_blank_values=True, strict_parsing=False):
        if k not in names:
            raise ConfigError(f"unknown bag option {k!r} in scene {spec!r} (known: {', '.join(sorted(names))})")
        if not v:
            raise ConfigError(f"empty bag option {k!r} in scene {spec!r}")
        opts[k] = v
    return Path(path), BagTopics(**opts)


def with_topics(spec: str, topics: BagTopics) -> str:
    """``spec`` with the non-empty ``topics`` added (they override topics already in it)."""
    path, have = parse_spec(spec) if SPEC_SEP in spec else (Path(spec), BagTopics())
    merged = replace(have, **{f.name: v for f in fields(topics) if (v := getattr(topics, f.name))})
    q = merged.query()
    return spec.partition(SPEC_SEP)[0] + (SPEC_SEP + q if q else "")


def is_bag(path: Path) -> bool:
    """A ROS1 ``.bag`` file, or a ROS2 bag folder (``metadata.yaml``)."""
    path = Path(path)
    return (path.suffix == ".bag" and not path.is_dir()) or (path.is_dir() and (path / "metadata.yaml").is_file())


# ----------------------------------------------------------------------------------
# reading
# ----------------------------------------------------------------------------------
def _reader_errors() -> tuple[type[BaseException], ...]:
    from rosbags.highlevel import AnyReaderError
    from rosbags.rosbag1 import ReaderError as ReaderError1
    from rosbags.rosbag2 import ReaderError as ReaderError2
    from rosbags.serde import SerdeError
    from rosbags.typesys import TypesysError

    return (AnyReaderError, ReaderError1, ReaderError2, SerdeError, TypesysError, sqlite3.Error, struct.error,
            EOFError, OSError, ValueError, KeyError, IndexError, AssertionError, UnicodeDecodeError)


@contextlib.contextmanager
def _bag_errors(path: Path, what: str = "") -> Iterator[None]:
    """Turn whatever rosbags (or sqlite, or the decoder) raises on a damaged bag into a
    one-line :class:`DataError`."""
    try:
        yield
    except DataError:
        raise
    except _reader_errors() as exc:
        msg = " ".join(str(exc).split()) or type(exc).__name__
        raise DataError(f"{path}: {what or 'unreadable ROS bag'} ({msg[:200]})") from None


def _open_reader(path: Path):
    """An opened ``rosbags`` ``AnyReader`` (caller closes it)."""
    from rosbags.highlevel import AnyReader
    from rosbags.typesys import Stores, get_typestore

    path = Path(path)
    ros2 = path.is_dir()
    store = get_typestore(Stores.ROS2_HUMBLE if ros2 else Stores.ROS1_NOETIC)
    with _bag_errors(path):
        reader = AnyReader([path], default_typestore=store)
        reader.open()
    return reader


def _stamp(msg) -> float:
    """``header.stamp`` in seconds."""
    st = msg.header.stamp
    return float(st.sec) + 1e-9 * float(st.nanosec)


def _field(msg, name: str):
    """A message field under its ROS2 (lower-case) or ROS1 (upper-case) name (``k``/``K``)."""
    return getattr(msg, name.lower()) if hasattr(msg, name.lower()) else getattr(msg, name.upper())


def decode_colour(msg, msgtype: str, where: str) -> NDArray[np.uint8]:
    """(H, W, 3) uint8 RGB of an ``Image`` (rgb8, bgr8, mono8, rgba8, bgra8) or ``CompressedImage``."""
    if msgtype == COMPRESSED:
        buf = np.asarray(msg.data, dtype=np.uint8)
        img = cv2.imdecode(buf, cv2.IMREAD_COLOR) if buf.size else None
        if img is None:
            raise DataError(f"{where}: compressed colour image ({msg.format!r}) cannot be decoded")
        return cv2.cvtColor(img, cv2.COLOR_BGR2RGB)
    enc = str(msg.encoding)
    if enc not in COLOUR_ENCODINGS:
        raise DataError(f"{where}: colour image encoding {enc!r} is not supported "
                        f"(expected {', '.join(COLOUR_ENCODINGS)})")
    ch = {"mono8": 1, "rgb8": 3, "bgr8": 3, "rgba8": 4, "bgra8": 4}[enc]
    raw = _pixels(msg, np.uint8, ch, where)
    if enc == "rgb8":
        return np.ascontiguousarray(raw)
    code = {"bgr8": cv2.COLOR_BGR2RGB, "mono8": cv2.COLOR_GRAY2RGB, "rgba8": cv2.COLOR_RGBA2RGB,
            "bgra8": cv2.COLOR_BGRA2RGB}[enc]
    return cv2.cvtColor(raw, code)


def decode_depth(msg, msgtype: str, where: str) -> NDArray[np.float32]:
    """(H, W) float32 metres (0 = invalid) of a ``16UC1`` (mm) or ``32FC1`` (m) ``Image``."""
    if msgtype != IMAGE:
        raise DataError(f"{where}: depth must be a sensor_msgs/Image (16UC1 or 32FC1), got {msgtype}")
    enc = str(msg.encoding)
    if enc in ("16UC1", "mono16"):
        raw = _pixels(msg, np.dtype(">u2" if msg.is_bigendian else "<u2"), 1, where)
        return _depth_table(DEPTH_SCALE_16U, (0,))[raw.astype(np.uint16)]
    if enc == "32FC1":
        d = _pixels(msg, np.dtype(">f4" if msg.is_bigendian else "<f4"), 1, where).astype(np.float32)
        d[~np.isfinite(d) | (d <= 0)] = 0.0
        return d
    raise DataError(f"{where}: depth image encoding {enc!r} is not supported (expected 16UC1 in mm or 32FC1 in m)")


def _pixels(msg, dtype, ch: int, where: str) -> NDArray:
    """(H, W[, ch]) view of an Image's pixel rows (``step`` bytes per row, padding dropped)."""
    dtype = np.dtype(dtype)
    h, w, step = int(msg.height), int(msg.width), int(msg.step)
    data = np.asarray(msg.data, dtype=np.uint8)
    row = w * ch * dtype.itemsize
    if h <= 0 or w <= 0 or step < row or data.size < h * step:
        raise DataError(f"{where}: image data ({data.size} bytes) does not match {w}x{h}, step {step}, "
                        f"encoding {msg.encoding}")
    rows = data[: h * step].reshape(h, step)[:, :row]
    px = np.ascontiguousarray(rows).view(dtype).reshape(h, w, ch)
    return px[..., 0] if ch == 1 else px


@dataclass
class _Stream:
    """One image topic: log times (ns) of its messages in bag order and their stamps (s)."""

    topic: str
    msgtype: str
    log_ns: NDArray[np.int64]
    stamps: NDArray[np.float64]


class BagSequence(Sequence):
    """A colour + depth camera in a ROS1 or ROS2 bag (see the module docstring)."""

    def __init__(self, path: Path, topics: BagTopics = BagTopics(), name: str | None = None,
                 max_dt: float | None = None) -> None:
        path = Path(path)
        if not path.exists():
            raise DataError(f"ROS bag {path} not found")
        self.path = self.root = path  # ``root``: what the learner's frame cache is keyed by, as for folders
        self.undistortion: Undistortion | None = None  # set from the camera info's distortion
        max_dt = tum.MAX_ASSOC_DT if max_dt is None else max_dt
        reader = _open_reader(path)
        try:
            with _bag_errors(path):
                self.topics = self._resolve_topics(reader, topics)
                intr = self._intrinsics(reader)
                rgb = self._scan(reader, self.topics.rgb)
                depth = self._scan(reader, self.topics.depth)
                metres = str(_first(reader, self.topics.depth).encoding) == "32FC1"
                gt_samples = self._read_gt(reader) if self.topics.gt else None
        finally:
            with contextlib.suppress(Exception):
                reader.close()
        for s in (rgb, depth):
            if len(s.stamps) == 0:
                raise DataError(f"{path}: topic {s.topic} has no messages")
            if np.any(np.diff(s.stamps) < 0):
                log.warning("%s: header stamps of %s are not in bag order; frames follow the stamps", path, s.topic)
        o_rgb, o_depth = np.argsort(rgb.stamps, kind="stable"), np.argsort(depth.stamps, kind="stable")
        ia, ib = tum.associate(rgb.stamps[o_rgb], depth.stamps[o_depth], max_dt)
        if len(ia) == 0:
            raise DataError(f"{path}: no colour image on {rgb.topic} has a depth image on {depth.topic} "
                            f"within {max_dt} s")
        log.info("%s: %d of %d colour / %d depth images associated (|dt| < %.3f s)", path.name, len(ia),
                 len(rgb.stamps), len(depth.stamps), max_dt)
        m_rgb, m_depth = o_rgb[ia], o_depth[ib]  # message ordinals within each topic
        times = rgb.stamps[m_rgb]
        gt = None
        if gt_samples is not None:
            t_gt, T_gt = gt_samples
            inside = (times >= t_gt[0]) & (times <= t_gt[-1])
            if not inside.any():
                raise DataError(f"{path}: no frame lies within the time span of ground-truth topic {self.topics.gt}")
            if not inside.all():
                log.info("%s: %d of %d frames lie outside the ground-truth time span; the sequence is "
                         "restricted to the %d inside", path.name, int((~inside).sum()), len(times), int(inside.sum()))
                times, m_rgb, m_depth = times[inside], m_rgb[inside], m_depth[inside]
            gt = tum.interpolate_poses(t_gt, T_gt, times)
        self._streams = (rgb, depth)
        self._msg = (m_rgb.astype(np.int64), m_depth.astype(np.int64))
        #: |t_rgb - t_depth| of every frame, seconds (N,)
        self.assoc_dt = np.abs(times - depth.stamps[m_depth])
        self._lock = threading.Lock()
        self._cursor: _Cursor | None = None
        ids = np.arange(len(times), dtype=np.int64)
        default_name = path.stem if path.suffix == ".bag" else path.resolve().name
        # as for a recording that is not a 7-Scenes folder: colour registered, Kinect v1's readout
        sensor = Sensor(None, KINECT_V1_READOUT_S, synchronous=False, depth_scale=1.0 if metres else DEPTH_SCALE_16U)
        super().__init__(name or default_name, intr, times, ids, gt, depth.stamps[m_depth], sensor=sensor)

    # -- opening ------------------------------------------------------------------
    def _resolve_topics(self, reader, want: BagTopics) -> BagTopics:
        types = {t: info.msgtype for t, info in reader.topics.items()}
        have = ", ".join(f"{t} ({types[t]})" for t in sorted(types)) or "none"

        def check(topic: str | None, allowed: tuple[str, ...], what: str) -> None:
            if topic is None:
                return
            if topic not in types:
                raise DataError(f"{self.path}: {what} topic {topic} is not in the bag (topics: {have})")
            if types[topic] not in allowed:
                raise DataError(f"{self.path}: {what} topic {topic} is {types[topic]}, expected "
                                f"{' or '.join(allowed)}")

        gt_topic = want.gt.split(":")[0] if want.gt else None
        check(want.rgb, (IMAGE, COMPRESSED), "colour")
        check(want.depth, (IMAGE,), "depth")
        check(want.camera_info, (CAMERA_INFO,), "camera-info")
        check(gt_topic, GT_TYPES, "ground-truth")
        rgb, depth = want.rgb, want.depth
        if rgb is None or depth is None:
            colour, depths = [], []
            for t, ty in sorted(types.items()):
                if ty == COMPRESSED:
                    # compressedDepth (PNG with a header) is not read; image_transport's
                    # ``T/compressed`` beside a raw ``T`` is the same stream: the raw one is used
                    if "compresseddepth" not in _first(reader, t).format.lower().replace(" ", "") and not (
                            t.endswith("/compressed") and types.get(t[: -len("/compressed")]) == IMAGE):
                        colour.append(t)
                elif ty == IMAGE:
                    enc = str(_first(reader, t).encoding)
                    (depths if enc in DEPTH_ENCODINGS else colour if enc in COLOUR_ENCODINGS else []).append(t)
            if rgb is None:
                rgb = self._only(colour, "colour image", "--rgb-topic", have)
            if depth is None:
                depth = self._only(depths, "depth image (16UC1 or 32FC1)", "--depth-topic", have)
        cam = want.camera_info
        if cam is None:
            infos = sorted(t for t, ty in types.items() if ty == CAMERA_INFO)
            near = [t for t in infos if t.rsplit("/", 1)[0] == rgb.rsplit("/", 1)[0]]
            cam = near[0] if len(near) == 1 else self._only(infos, "sensor_msgs/CameraInfo", "--camera-info-topic", have)
        log.info("%s: colour %s, depth %s, camera info %s%s", self.path.name, rgb, depth, cam,
                 f", ground truth {want.gt}" if want.gt else "")
        return BagTopics(rgb, depth, cam, want.gt)

    def _only(self, cands: list[str], what: str, option: str, have: str) -> str:
        if len(cands) == 1:
            return cands[0]
        if not cands:
            raise DataError(f"{self.path}: no {what} topic (topics: {have})")
        raise DataError(f"{self.path}: several {what} topics ({', '.join(cands)}); choose one with {option}")

    def _intrinsics(self, reader) -> Intrinsics:
        msg = _first(reader, self.topics.camera_info)
        K = np.asarray(_field(msg, "k"), dtype=np.float64).reshape(3, 3)
        w, h = int(msg.width), int(msg.height)
        if not np.all(np.isfinite(K)) or K[0, 0] <= 0 or K[1, 1] <= 0 or w <= 0 or h <= 0:
            raise DataError(f"{self.path}: camera info on {self.topics.camera_info} has no valid K/width/height "
                            f"(K diagonal {K[0, 0]:g}, {K[1, 1]:g}, {w}x{h})")
        intr = Intrinsics(float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2]), w, h)
        D = np.asarray(_field(msg, "d"), dtype=np.float64)
        model = str(getattr(msg, "distortion_model", "") or "plumb_bob")
        if D.size and np.any(np.abs(D) > 1e-9):
            if model == "plumb_bob" and D.size in COEFF_COUNTS and np.all(np.isfinite(D)):
                self.undistortion = undistortion(intr, tuple(D))
                log.info("%s: frames undistorted with camera info %s's %s %s", self.path.name,
                         self.topics.camera_info, model, np.round(D, 4).tolist())
            else:
                log.warning("%s: camera info %s has %s distortion %s; the images are used as they are (rectify "
                            "them for best results)", self.path.name, self.topics.camera_info, model,
                            np.round(D, 4).tolist())
        return intr

    def _scan(self, reader, topic: str) -> _Stream:
        """Log times and header stamps of every message of ``topic`` (one pass, headers only kept)."""
        conns = [c for c in reader.connections if c.topic == topic]
        log_ns, stamps = [], []
        for conn, t, raw in reader.messages(connections=conns):
            stamps.append(_stamp(reader.deserialize(raw, conn.msgtype)))
            log_ns.append(t)
        return _Stream(topic, conns[0].msgtype, np.asarray(log_ns, np.int64), np.asarray(stamps, np.float64))

    def _read_gt(self, reader) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        topic, *frames = self.topics.gt.split(":")
        if frames and len(frames) != 2:
            raise DataError(f"ground-truth topic must be TOPIC or TOPIC:PARENT:CHILD, got {self.topics.gt!r}")
        conns = [c for c in reader.connections if c.topic == topic]
        samples: dict[tuple[str, str], list[tuple[float, NDArray]]] = {}
        for conn, _, raw in reader.messages(connections=conns):
            msg = reader.deserialize(raw, conn.msgtype)
            if conn.msgtype == POSE_STAMPED:
                p = msg.pose
                key = (msg.header.frame_id, "")
                T = _pose_T(p.position, p.orientation)
                samples.setdefault(key, []).append((_stamp(msg), T))
            else:
                for tr in (msg.transforms if conn.msgtype == TF_MESSAGE else [msg]):
                    key = (tr.header.frame_id.lstrip("/"), tr.child_frame_id.lstrip("/"))
                    samples.setdefault(key, []).append(
                        (_stamp(tr), _pose_T(tr.transform.translation, tr.transform.rotation)))
        if frames:
            key = (frames[0].lstrip("/"), frames[1].lstrip("/"))
            if key not in samples:
                raise DataError(f"{self.path}: no transform {key[0]} -> {key[1]} on {topic} "
                                f"(pairs: {', '.join(f'{a}:{b}' for a, b in sorted(samples)) or 'none'})")
        elif len(samples) == 1:
            key = next(iter(samples))
        elif not samples:
            raise DataError(f"{self.path}: ground-truth topic {topic} has no messages")
        else:
            raise DataError(f"{self.path}: {topic} holds several transforms; name one with --gt-topic "
                            f"{topic}:PARENT:CHILD ({', '.join(f'{a}:{b}' for a, b in sorted(samples))})")
        rows = sorted(samples[key], key=lambda r: r[0])
        t = np.array([r[0] for r in rows])
        keep = np.concatenate([[True], np.diff(t) > 0])  # repeated stamps: keep the first
        return t[keep], np.stack([r[1] for r in rows])[keep]

    # -- frames -------------------------------------------------------------------
    def __getstate__(self) -> dict:
        state = self.__dict__.copy()
        state["_cursor"] = None  # an open bag does not cross processes; reopened on use
        state["_lock"] = None
        return state

    def __setstate__(self, state: dict) -> None:
        self.__dict__.update(state)
        self._lock = threading.Lock()

    def __copy__(self) -> BagSequence:
        new = BagSequence.__new__(BagSequence)
        new.__setstate__(self.__getstate__())  # a view gets its own reader
        return new

    def _message(self, which: int, pos: int):
        """The deserialised message of stream ``which`` (0 colour, 1 depth) for frame ``pos``."""
        m = int(self._msg[which][pos])
        with self._lock:
            if self._cursor is None:
                self._cursor = _Cursor(self.path, self._streams)
            with _bag_errors(self.path, f"cannot read frame {pos}"):
                return self._cursor.get(which, m, self._wanted)

    @property
    def _wanted(self) -> tuple[set[int], set[int]]:
        """Message ordinals of each stream that frames use (others are skipped, not buffered)."""
        w = getattr(self, "_wanted_sets", None)
        if w is None:
            w = self._wanted_sets = (set(self._msg[0].tolist()), set(self._msg[1].tolist()))
        return w

    def _read_rgb(self, pos: int) -> NDArray[np.uint8]:
        msg, ty = self._message(0, pos)
        img = decode_colour(msg, ty, f"{self.path} {self.topics.rgb} frame {pos}")
        self._check_size(img.shape[:2], "colour", pos)
        return img  # undistorted by Sequence.rgb

    def _read_depth(self, pos: int) -> NDArray[np.float32]:
        msg, ty = self._message(1, pos)
        d = decode_depth(msg, ty, f"{self.path} {self.topics.depth} frame {pos}")
        self._check_size(d.shape, "depth", pos)
        return d

    def _check_size(self, shape: tuple[int, ...], what: str, pos: int) -> None:
        intr = self.intrinsics
        if tuple(shape) != (intr.height, intr.width):
            raise DataError(f"{self.path}: {what} image of frame {pos} is {shape[1]}x{shape[0]}, camera info "
                            f"says {intr.width}x{intr.height}")

    def close(self) -> None:
        """Close the bag (it reopens when a frame is read again)."""
        with self._lock:
            if self._cursor is not None:
                self._cursor.close()
                self._cursor = None


class _Cursor:
    """A forward pass over the colour and depth messages of a bag with a small look-ahead
    buffer: reading frames in order reads each message once; a message behind the pass
    restarts it at that message's log time."""

    def __init__(self, path: Path, streams: tuple[_Stream, _Stream]) -> None:
        self.path, self.streams = path, streams
        self.reader = _open_reader(path)
        self.conns = [[c for c in self.reader.connections if c.topic == s.topic] for s in streams]
        self.conn_stream = {c.id: k for k, cs in enumerate(self.conns) for c in cs}
        self.it: Iterator | None = None
        self.next_ord = [0, 0]  # ordinal of the next message the pass yields, per stream
        self.buf: OrderedDict[tuple[int, int], tuple[bytes, str]] = OrderedDict()

    def _restart(self, which: int, m: int) -> None:
        t = int(self.streams[which].log_ns[m])
        self.it = self.reader.messages(connections=self.conns[0] + self.conns[1], start=t)
        self.next_ord = [int(np.searchsorted(s.log_ns, t, side="left")) for s in self.streams]
        self.buf.clear()

    def get(self, which: int, m: int, wanted: tuple[set[int], set[int]]):
        key = (which, m)
        if key not in self.buf:
            if self.it is None or self.next_ord[which] > m or m - self.next_ord[which] > 4 * LOOKAHEAD:
                self._restart(which, m)
            while key not in self.buf:
                try:
                    conn, _, raw = next(self.it)
                except StopIteration:
                    raise DataError(f"{self.path}: message {m} of {self.streams[which].topic} is missing "
                                    "(truncated bag?)") from None
                k = self.conn_stream[conn.id]
                o = self.next_ord[k]
                self.next_ord[k] += 1
                if o in wanted[k]:
                    self.buf[(k, o)] = (raw, conn.msgtype)
                    while len(self.buf) > 2 * LOOKAHEAD:
                        self.buf.popitem(last=False)
        raw, ty = self.buf.pop(key)
        return self.reader.deserialize(raw, ty), ty

    def close(self) -> None:
        with contextlib.suppress(Exception):
            self.reader.close()


def _first(reader, topic: str):
    """The first message of ``topic``, deserialised."""
    conns = [c for c in reader.connections if c.topic == topic]
    for conn, _, raw in reader.messages(connections=conns):
        return reader.deserialize(raw, conn.msgtype)
    raise DataError(f"topic {topic} has no messages")


def _pose_T(t, q) -> NDArray[np.float64]:
    """4x4 transform of a ROS translation/position and quaternion (x, y, z, w)."""
    qv = np.array([q.x, q.y, q.z, q.w], dtype=np.float64)
    tv = np.array([t.x, t.y, t.z], dtype=np.float64)
    if not (np.all(np.isfinite(qv)) and np.all(np.isfinite(tv))) or np.linalg.norm(qv) < 1e-6:
        raise DataError(f"non-finite or zero-norm ground-truth pose {tv.tolist()} {qv.tolist()}")
    return geo.make_T(geo.quat_xyzw_to_R(qv / np.linalg.norm(qv)), tv)
