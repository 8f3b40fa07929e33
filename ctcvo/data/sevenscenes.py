"""Microsoft 7-Scenes reader (also reads the project's synthetic scenes, which use its layout).

Layout: ``<scene>/seq-XX/frame-NNNNNN.color.png`` (or ``.color.jpg``),
``frame-NNNNNN.depth.png`` (uint16 millimetres; 0 and 65535 invalid),
``frame-NNNNNN.pose.txt`` (4x4 ``T_world_cam``, metres). ``<scene>/TrainSplit.txt`` and
``TestSplit.txt`` list ``sequence1``-style names (-> ``seq-01``). Intrinsics come from
``camera-intrinsics.txt`` (3x3 matrix, or ``fx fy cx cy [w h]``) in the sequence folder or the
scene folder, else the dataset's 585/585/320/240 at 640x480. Frames are at 30 Hz.
An optional ``seq-XX/depth-offsets.txt`` (``frame_id offset_s`` per frame, ``#`` comments;
written by the synthetic renderer with a colour-depth time offset) gives each frame's depth
image time minus its colour image time; without it both are ``frame_id / 30``.
"""

from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from ctcvo.data.errors import DataError
from ctcvo.data.geometry import is_rigid, orthonormalize
from ctcvo.data.sensor import KINECT_V1_COLOUR, KINECT_V1_READOUT_S, ColourCamera, Sensor
from ctcvo.data.sequence import Intrinsics, Sequence, read_depth, read_rgb

DEFAULT_INTRINSICS = Intrinsics(585.0, 585.0, 320.0, 240.0, 640, 480)
FPS = 30.0
DEPTH_SCALE = 1000.0  # raw units per metre
#: a 7-Scenes recording: Kinect v1, its colour not registered to depth and exposed at other times
KINECT_V1 = Sensor(KINECT_V1_COLOUR, KINECT_V1_READOUT_S, synchronous=False, depth_scale=DEPTH_SCALE)
_FRAME_RE = re.compile(r"^frame-(\d{6})\.depth\.png$")


def read_intrinsics_file(path: Path, width: int = 640, height: int = 480) -> Intrinsics:
    """Parse a ``camera-intrinsics.txt``: a 3x3 camera matrix, or ``fx fy cx cy [w h]``."""
    try:
        vals = np.array(Path(path).read_text().split(), dtype=np.float64)
    except ValueError:
        raise DataError(f"{path}: intrinsics must be numbers") from None
    if not np.all(np.isfinite(vals)):
        raise DataError(f"{path}: non-finite intrinsics")
    if vals.size == 9:
        K = vals.reshape(3, 3)
        return Intrinsics(K[0, 0], K[1, 1], K[0, 2], K[1, 2], width, height)
    if vals.size in (4, 6):
        w, h = (int(vals[4]), int(vals[5])) if vals.size == 6 else (width, height)
        return Intrinsics(*vals[:4], w, h)
    raise DataError(f"{path}: expected a 3x3 matrix or 'fx fy cx cy [w h]', got {vals.size} numbers")


class NonFinitePose(DataError):
    """A pose file holds NaN or inf (7-Scenes marks frames KinectFusion lost this way): the
    sequence keeps the frame, and its ground truth drops it (``Sequence.groundtruth_dropped``)."""


def read_pose_file(path: Path) -> NDArray[np.float64]:
    """A 4x4 ``T_world_cam`` from a 7-Scenes ``.pose.txt``; clear error if missing or bad."""
    path = Path(path)
    if not path.is_file():
        raise DataError(f"missing pose file {path}")
    try:
        T = np.array(path.read_text().split(), dtype=np.float64)
    except ValueError:
        raise DataError(f"pose file {path} must contain 16 numbers") from None
    if T.size != 16:
        raise DataError(f"pose file {path} must contain 16 numbers, got {T.size}")
    T = T.reshape(4, 4)
    if not np.all(np.isfinite(T)):
        raise NonFinitePose(f"pose file {path} contains non-finite values")
    if not is_rigid(T, atol=1e-2):
        raise DataError(f"pose file {path} is not a rigid transform")
    return orthonormalize(T)


def frame_ids(seq_dir: Path) -> list[int]:
    """The ids of the ``frame-NNNNNN.depth.png`` files in ``seq_dir``, sorted."""
    return sorted(int(m.group(1)) for p in Path(seq_dir).iterdir() if (m := _FRAME_RE.match(p.name)))


def colour_file(seq_dir: Path, frame_id: int) -> Path | None:
    """Frame ``frame_id``'s colour image (``.color.png``, else ``.color.jpg``); None when neither exists."""
    for ext in (".color.png", ".color.jpg"):
        if (path := Path(seq_dir) / f"frame-{frame_id:06d}{ext}").is_file():
            return path
    return None


def depth_file(seq_dir: Path, frame_id: int) -> Path:
    return Path(seq_dir) / f"frame-{frame_id:06d}.depth.png"


def read_depth_file(path: Path, intr: Intrinsics) -> NDArray[np.float32]:
    """A 7-Scenes depth PNG in metres (millimetres on file; 0 and 65535 invalid)."""
    return read_depth(path, DEPTH_SCALE, intr, invalid=(0, 65535))


def read_depth_offsets(path: Path, ids: NDArray[np.int64]) -> NDArray[np.float64] | None:
    """Depth minus colour time (s) of the frames ``ids`` from ``depth-offsets.txt`` (rows
    ``frame_id offset_s``; None when the file is absent). A :class:`DataError` naming the
    file and line for a malformed row, a non-finite offset, one of a frame period or more,
    or a frame the file does not list."""
    if not path.is_file():
        return None
    table: dict[int, float] = {}
    for lineno, line in enumerate(path.read_text().splitlines(), 1):
        s = line.strip()
        if not s or s.startswith("#"):
            continue
        toks = s.split()
        try:
            if len(toks) != 2:
                raise ValueError
            fid, off = int(toks[0]), float(toks[1])
        except ValueError:
            raise DataError(f"{path}:{lineno}: a row needs 'frame_id offset_s', got {s!r}") from None
        if not np.isfinite(off) or abs(off) >= 1.0 / FPS:
            raise DataError(f"{path}:{lineno}: offset {toks[1]} s must be finite and under a frame period")
        table[fid] = off
    missing = [int(k) for k in ids if int(k) not in table]
    if missing:
        raise DataError(f"{path} lists no offset for frame {missing[0]} ({len(missing)} frames missing)")
    return np.array([table[int(k)] for k in ids], dtype=np.float64)


def folder_intrinsics(seq_dir: Path) -> Intrinsics:
    """``camera-intrinsics.txt`` of the sequence folder or its parent, else the 7-Scenes default."""
    for cand in (Path(seq_dir) / "camera-intrinsics.txt", Path(seq_dir).parent / "camera-intrinsics.txt"):
        if cand.is_file():
            return read_intrinsics_file(cand)
    return DEFAULT_INTRINSICS


def folder_sensor(seq_dir: Path) -> Sensor:
    """The sensor of a 7-Scenes-layout sequence folder: a synthetic scene's own sensor model
    when the renderer's ``config.json`` is one level up (registered, readout 0 when
    noise-free), else :data:`KINECT_V1` (a real 7-Scenes folder)."""
    rendered = Path(seq_dir).parent / "config.json"
    if rendered.is_file():
        try:
            return _rendered_sensor(json.loads(rendered.read_text())["config"]["sensor"])
        except (ValueError, KeyError, TypeError):
            pass  # not a synthetic scene's config: a real 7-Scenes folder
    return KINECT_V1


def _rendered_sensor(sensor: dict) -> Sensor:
    """The :class:`Sensor` of a synthetic scene's sensor model (its ``config.json`` entry)."""
    if sensor["noise_free"]:
        return Sensor(None, 0.0, synchronous=True, depth_scale=DEPTH_SCALE, noise_model="none")
    colour = ColourCamera(float(sensor["rgb_focal_scale"]), tuple(map(float, sensor["rgb_shift_px"])),
                          float(sensor["rgb_baseline_m"]), synchronous=True)
    return Sensor(colour, float(sensor["rolling_shutter_s"]), synchronous=True, depth_scale=DEPTH_SCALE,
                  noise_model="synthetic")


def _read_poses(seq_dir: Path, ids: list[int]) -> tuple[NDArray[np.float64], dict[int, str]]:
    """The (N, 4, 4) poses of the frames ``ids``, NaN for a non-finite pose file, and why
    (by position); any other bad pose file is a :class:`DataError`."""
    poses, problems = np.full((len(ids), 4, 4), np.nan), {}
    for p, k in enumerate(ids):
        try:
            poses[p] = read_pose_file(seq_dir / f"frame-{k:06d}.pose.txt")
        except NonFinitePose as exc:
            problems[p] = str(exc)
    return poses, problems


class SevenScenesSequence(Sequence):
    """One ``seq-XX`` folder of a 7-Scenes-layout scene."""

    def __init__(self, seq_dir: Path, name: str | None = None) -> None:
        seq_dir = Path(seq_dir)
        if not seq_dir.is_dir():
            raise DataError(f"sequence folder {seq_dir} does not exist")
        ids = frame_ids(seq_dir)
        if not ids:
            raise DataError(f"sequence folder {seq_dir} has no frame-NNNNNN.depth.png files")
        self.root = seq_dir
        first = colour_file(seq_dir, ids[0])
        if first is None:
            raise DataError(f"no colour image frame-{ids[0]:06d}.color.png/.jpg in {seq_dir}")
        self._color_ext = first.name[len(f"frame-{ids[0]:06d}"):]
        intr = folder_intrinsics(seq_dir)
        gt, problems = None, {}
        if (seq_dir / f"frame-{ids[0]:06d}.pose.txt").is_file():
            gt, problems = _read_poses(seq_dir, ids)
        ids_arr = np.asarray(ids, dtype=np.int64)
        offsets = read_depth_offsets(seq_dir / "depth-offsets.txt", ids_arr)
        super().__init__(name or f"{seq_dir.parent.name}-{seq_dir.name}", intr, ids_arr / FPS, ids_arr, gt,
                         None if offsets is None else ids_arr / FPS + offsets, sensor=folder_sensor(seq_dir))
        self.gt_problems = problems

    def _read_rgb(self, pos: int) -> NDArray[np.uint8]:
        fid = int(self.frame_ids[pos])
        return read_rgb(self.root / f"frame-{fid:06d}{self._color_ext}", self.intrinsics)

    def _read_depth(self, pos: int) -> NDArray[np.float32]:
        fid = int(self.frame_ids[pos])
        return read_depth_file(depth_file(self.root, fid), self.intrinsics)


def _split_names(scene_dir: Path, split: str) -> list[str]:
    files = {"train": ["TrainSplit.txt"], "test": ["TestSplit.txt"], "all": ["TrainSplit.txt", "TestSplit.txt"]}
    if split not in files:
        raise DataError(f"unknown split {split!r} (train, test, all)")
    names: list[str] = []
    for fname in files[split]:
        f = scene_dir / fname
        if not f.is_file():
            raise DataError(f"scene folder {scene_dir} has no {fname}")
        for tok in f.read_text().split():
            m = re.fullmatch(r"sequence(\d+)", tok.strip())
            if not m:
                raise DataError(f"{f}: expected lines like 'sequence1', got {tok!r}")
            names.append(f"seq-{int(m.group(1)):02d}")
    return names


def open_scene_folder(scene_dir: Path, split: str = "all") -> list[SevenScenesSequence]:
    """Sequences of a 7-Scenes scene folder for a split (``train``, ``test`` or ``all``).

    Without split files, ``all`` opens every ``seq-*`` folder.
    """
    scene_dir = Path(scene_dir)
    has_splits = (scene_dir / "TrainSplit.txt").is_file() or (scene_dir / "TestSplit.txt").is_file()
    if has_splits:
        names = _split_names(scene_dir, split)
    elif split == "all":
        names = sorted(p.name for p in scene_dir.glob("seq-*") if p.is_dir())
    else:
        raise DataError(f"scene folder {scene_dir} has no TrainSplit.txt/TestSplit.txt for --split {split}")
    if not names:
        raise DataError(f"scene folder {scene_dir} has no sequences")
    return [SevenScenesSequence(scene_dir / n) for n in names]


def is_sequence_folder(path: Path) -> bool:
    return Path(path).is_dir() and any(_FRAME_RE.match(p.name) for p in Path(path).iterdir())
