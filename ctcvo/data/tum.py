"""TUM RGB-D reader (Sturm et al., IROS 2012).

Layout of a sequence folder (e.g. ``rgbd_dataset_freiburg1_xyz``)::

    rgb.txt          "timestamp rgb/<timestamp>.png" per line, '#' comments
    depth.txt        "timestamp depth/<timestamp>.png" per line, '#' comments
    groundtruth.txt  "timestamp tx ty tz qx qy qz qw" (T_world_cam), optional
    camera.txt       "fx fy cx cy [width height [k1 k2 p1 p2 [k3]]]", optional, overrides
                     the built-in tables

How the frames are built (docs/formats.md, "TUM RGB-D input"):

* **Association.** Each RGB image is paired with at most one depth image and vice versa,
  nearest first, only if ``|t_rgb - t_depth| < max_dt`` (0.02 s) - the greedy scheme of
  TUM's ``associate.py``. Unpaired images are dropped. A frame's timestamp is its RGB
  timestamp; its depth image's timestamp is kept too (``Sequence.depth_times()``: on
  fr1/xyz 8.4 ms before the RGB one in the median, 5-95 % 3.6-15.9 ms); frame ids are the
  positions ``0..N-1`` after association (and after the GT restriction below).
* **Ground truth** (motion capture, ~100 Hz) is interpolated to the RGB timestamps: linear
  in position, Slerp in rotation. Frames before the first or after the last GT sample
  have no GT: if *some* frames lie inside the GT time span, the sequence is restricted to
  them (logged at INFO); if *none* do, the sequence has no GT (logged as a WARNING). A
  frame whose two bracketing GT samples are more than ``max_gt_gap`` apart is counted and
  reported in a WARNING (its GT is interpolated across the gap regardless). A GT row with a
  non-finite pose is left out, and the frames interpolated across it have no GT
  (``Sequence.groundtruth_dropped``: the teacher leaves them out of its evaluation).
* **Depth** PNGs are 16-bit with 5000 units per metre; 0 is invalid.
* **Intrinsics** come from ``camera.txt`` in the folder if present, else from the
  ``freiburgN`` / ``frN`` part of the folder name (table :data:`TUM_INTRINSICS`, the
  values published with the dataset, images 640x480); anything else is a
  :class:`~data.errors.DataError` asking for ``camera.txt``.
* **Distortion.** fr1 and fr2 images are recorded raw, with the lens distortion TUM
  publishes (:data:`TUM_DISTORTION`; fr3's images are already undistorted), and their
  depth is registered to those raw colour pixels. The reader undistorts both
  (:mod:`data.undistort`), so frames are pinhole images of the camera matrix above.
  ``camera.txt``'s optional ``k1 k2 p1 p2 [k3]`` do the same for another camera.

Malformed files raise :class:`~data.errors.DataError` naming the file and line.
"""

from __future__ import annotations

import logging
import re
import tempfile
from pathlib import Path

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation, Slerp

from ctcvo.data.errors import DataError, FormatError
from ctcvo.data.formats import read_tum, read_tum_rows
from ctcvo.data.sensor import KINECT_V1_READOUT_S, Sensor
from ctcvo.data.sequence import Intrinsics, Sequence, read_depth, read_rgb
from ctcvo.data.sevenscenes import read_intrinsics_file
from ctcvo.data.undistort import COEFF_COUNTS, Undistortion, undistortion

log = logging.getLogger(__name__)

#: Raw depth units per metre in TUM RGB-D depth PNGs.
DEPTH_SCALE = 5000.0
#: The Freiburg Kinects as recorded: depth registered to colour, Kinect v1's row readout.
SENSOR = Sensor(None, KINECT_V1_READOUT_S, synchronous=False, depth_scale=DEPTH_SCALE)
#: Default RGB-to-depth association window, seconds (as in TUM's associate.py).
MAX_ASSOC_DT = 0.02
#: GT samples further apart than this (s) around a frame are reported as a GT gap. The
#: motion capture runs at ~100 Hz, with occasional dropouts of ~0.1 s (fr1/xyz has 0.11 s
#: gaps) that interpolation bridges well at hand-held speeds; longer ones are reported.
MAX_GT_GAP = 0.25
#: Published intrinsics of the three Freiburg Kinects (fx, fy, cx, cy), images 640x480.
TUM_INTRINSICS: dict[str, Intrinsics] = {
    "fr1": Intrinsics(517.3, 516.5, 318.6, 255.3, 640, 480),
    "fr2": Intrinsics(520.9, 521.0, 325.1, 249.7, 640, 480),
    "fr3": Intrinsics(535.4, 539.2, 320.1, 247.6, 640, 480),
}
#: Published lens distortion of the Freiburg Kinects' colour cameras (OpenCV k1 k2 p1 p2 k3):
#: fr1 and fr2 images are raw, fr3's were undistorted before publication.
TUM_DISTORTION: dict[str, tuple[float, ...]] = {
    "fr1": (0.2624, -0.9531, -0.0054, 0.0026, 1.1633),
    "fr2": (0.2312, -0.7849, -0.0033, -0.0001, 0.9172),
    "fr3": (),
}
_CAMERA_RE = re.compile(r"(?:freiburg|(?<![a-z])fr)([123])(?![0-9])")


# ----------------------------------------------------------------------------------
# file parsing
# ----------------------------------------------------------------------------------
def read_image_list(path: Path, growing: bool = False) -> tuple[NDArray[np.float64], list[str]]:
    """Parse ``rgb.txt`` / ``depth.txt``: timestamps (N,) and relative file names.
    ``growing``: the file is still being written (see :func:`data.formats.read_tum_rows`;
    a file not there yet has no rows)."""
    path = Path(path)
    if not path.is_file():
        if growing:
            return np.zeros(0), []
        raise DataError(f"missing TUM file {path}")
    try:
        rows = read_tum_rows(path, "timestamp filename", "images", growing=growing)
    except FormatError as exc:
        raise DataError(str(exc)) from None
    return np.array([vals[0] for _, _, vals in rows], dtype=np.float64), [toks[1] for _, toks, _ in rows]


def read_groundtruth(path: Path) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Parse ``groundtruth.txt`` (a TUM trajectory file, read by
    :func:`data.formats.read_tum`): timestamps (M,) and ``T_world_cam`` poses (M, 4, 4)."""
    try:
        traj = read_tum(path)
    except FormatError as exc:
        raise DataError(str(exc)) from None
    return traj.timestamps, traj.poses


def read_groundtruth_rows(path: Path) -> tuple[NDArray[np.float64], NDArray[np.float64], list[tuple[float, str]]]:
    """:func:`read_groundtruth`, with the rows whose pose is non-finite (a finite timestamp)
    left out: also returns ``(timestamp, "file:line")`` of each of those."""
    path = Path(path)
    try:
        return (*read_groundtruth(path), [])
    except DataError as exc:
        if "non-finite" not in str(exc):
            raise
    kept, dropped, prev = [], [], -np.inf
    for lineno, line in enumerate(path.read_text().splitlines(), 1):
        toks = line.split()
        if len(toks) == 8 and not toks[0].startswith("#"):
            try:
                vals = np.array(toks, dtype=np.float64)
            except ValueError:
                vals = np.full(8, np.nan)
            # a row in order with a non-finite pose is left out; anything else stays an error
            if vals[0] > prev and not np.isfinite(vals[1:]).all():
                dropped.append((float(vals[0]), f"{path}:{lineno}"))
                line = "#"  # keeps the line numbers of the messages
            prev = vals[0] if np.isfinite(vals[0]) else prev
        kept.append(line)
    with tempfile.TemporaryDirectory(prefix="ctcvo-gt-") as tmp:
        p = Path(tmp) / path.name
        p.write_text("\n".join(kept) + "\n")
        try:
            t, T = read_groundtruth(p)
        except DataError as exc:
            raise DataError(str(exc).replace(str(p), str(path))) from None
    return t, T, dropped


def across_dropped(times: NDArray[np.float64], t_gt: NDArray[np.float64],
                   dropped: list[tuple[float, str]]) -> dict[int, str]:
    """{position: why} of the frames whose two bracketing GT samples have a dropped
    (non-finite) row between them: their interpolated pose would be made up."""
    if not dropped or len(t_gt) < 2:
        return {}
    k = np.clip(np.searchsorted(t_gt, times), 1, len(t_gt) - 1)
    out = {}
    for t_bad, where in dropped:
        for p in np.flatnonzero((t_gt[k - 1] < t_bad) & (t_bad < t_gt[k])):
            out[int(p)] = f"{where}: non-finite ground-truth pose (frame at {times[p]:.6f} s interpolated across it)"
    return dict(sorted(out.items()))


# ----------------------------------------------------------------------------------
# association and interpolation
# ----------------------------------------------------------------------------------
def associate(t_a: NDArray[np.float64], t_b: NDArray[np.float64],
              max_dt: float = MAX_ASSOC_DT) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
    """One-to-one nearest-first matching of two sorted timestamp lists.

    Every candidate pair with ``|t_a - t_b| < max_dt`` is considered in order of increasing
    difference; a pair is accepted if neither member is taken yet (TUM ``associate.py``).
    Returns index arrays ``(ia, ib)`` of equal length, sorted by ``ia``.
    """
    t_a = np.asarray(t_a, dtype=np.float64)
    t_b = np.asarray(t_b, dtype=np.float64)
    lo = np.searchsorted(t_b, t_a - max_dt, side="left")
    hi = np.searchsorted(t_b, t_a + max_dt, side="right")
    cand_a = np.repeat(np.arange(len(t_a)), hi - lo)
    cand_b = np.concatenate([np.arange(l, h) for l, h in zip(lo, hi)]) if len(t_a) else np.empty(0, int)
    cand_b = cand_b.astype(np.int64)
    diff = np.abs(t_a[cand_a] - t_b[cand_b])
    keep = diff < max_dt
    cand_a, cand_b, diff = cand_a[keep], cand_b[keep], diff[keep]
    order = np.argsort(diff, kind="stable")
    used_a = np.zeros(len(t_a), bool)
    used_b = np.zeros(len(t_b), bool)
    ia, ib = [], []
    for k in order:
        a, b = cand_a[k], cand_b[k]
        if not used_a[a] and not used_b[b]:
            used_a[a] = used_b[b] = True
            ia.append(a)
            ib.append(b)
    ia_arr, ib_arr = np.asarray(ia, dtype=np.int64), np.asarray(ib, dtype=np.int64)
    srt = np.argsort(ia_arr)
    return ia_arr[srt], ib_arr[srt]


def interpolate_poses(t_gt: NDArray[np.float64], T_gt: NDArray[np.float64],
                      t_query: NDArray[np.float64]) -> NDArray[np.float64]:
    """Poses (Q, 4, 4) at ``t_query`` (all within ``[t_gt[0], t_gt[-1]]``).

    Position is interpolated linearly, rotation by Slerp (shortest arc, so ``q``/``-q``
    sign flips in the file do not matter). Exact at a GT timestamp.
    """
    t_gt = np.asarray(t_gt, dtype=np.float64)
    t_query = np.asarray(t_query, dtype=np.float64)
    if len(t_query) and (t_query.min() < t_gt[0] or t_query.max() > t_gt[-1]):
        raise ValueError("query timestamps outside the ground-truth time span")
    # subtract a common origin: timestamps are ~1.3e9 s, keep the arithmetic well scaled
    t0 = t_gt[0]
    tg, tq = t_gt - t0, t_query - t0
    out = np.tile(np.eye(4), (len(t_query), 1, 1))
    if len(t_gt) == 1:
        out[:] = T_gt[0]
        return out
    for ax in range(3):
        out[:, ax, 3] = np.interp(tq, tg, T_gt[:, ax, 3])
    out[:, :3, :3] = Slerp(tg, Rotation.from_matrix(T_gt[:, :3, :3]))(tq).as_matrix()
    return out


def intrinsics_for(folder: Path) -> Intrinsics:
    """``camera.txt`` in ``folder`` if present, else the Freiburg camera named by the folder."""
    return camera_for(folder)[0]


def camera_for(folder: Path) -> tuple[Intrinsics, Undistortion | None]:
    """The camera matrix of ``folder``'s frames and the undistortion its raw images need
    (None: none): ``camera.txt`` if present, else the Freiburg camera named by the folder."""
    folder = Path(folder)
    cam = folder / "camera.txt"
    if cam.is_file():
        return _read_camera_file(cam)
    m = _CAMERA_RE.search(folder.resolve().name.lower())
    if m:
        key = f"fr{m.group(1)}"
        return TUM_INTRINSICS[key], undistortion(TUM_INTRINSICS[key], TUM_DISTORTION[key])
    raise DataError(
        f"cannot tell the camera of TUM sequence {folder}: its name contains no freiburg1/2/3 "
        f"(or fr1/2/3); put a camera.txt with 'fx fy cx cy' in the folder"
    )


def _read_camera_file(path: Path) -> tuple[Intrinsics, Undistortion | None]:
    """``camera.txt``: ``fx fy cx cy [width height [k1 k2 p1 p2 [k3]]]``."""
    words = path.read_text().split()
    if len(words) - 6 not in COEFF_COUNTS:
        return read_intrinsics_file(path, 640, 480), None
    try:
        vals = [float(w) for w in words]
    except ValueError:
        raise DataError(f"{path}: camera values must be numbers") from None
    if not np.all(np.isfinite(vals)):
        raise DataError(f"{path}: non-finite camera values")
    intr = Intrinsics(*vals[:4], int(vals[4]), int(vals[5]))
    return intr, undistortion(intr, tuple(vals[6:]))


# ----------------------------------------------------------------------------------
# the sequence
# ----------------------------------------------------------------------------------
class TumSequence(Sequence):
    """A TUM RGB-D sequence folder, RGB and depth associated, GT interpolated to RGB times."""

    def __init__(self, folder: Path, name: str | None = None, max_dt: float = MAX_ASSOC_DT,
                 max_gt_gap: float = MAX_GT_GAP) -> None:
        folder = Path(folder)
        if not folder.is_dir():
            raise DataError(f"TUM sequence folder {folder} does not exist")
        self.root = folder
        intr, self.undistortion = camera_for(folder)
        t_rgb, rgb_names = read_image_list(folder / "rgb.txt")
        t_depth, depth_names = read_image_list(folder / "depth.txt")
        ia, ib = associate(t_rgb, t_depth, max_dt)
        if len(ia) == 0:
            raise DataError(f"{folder}: no RGB image has a depth image within {max_dt} s")
        log.info("%s: %d of %d RGB / %d depth images associated (|dt| < %.3f s)",
                 folder.name, len(ia), len(t_rgb), len(t_depth), max_dt)
        times = t_rgb[ia]
        depth_times = t_depth[ib]
        rgb_files = [rgb_names[k] for k in ia]
        depth_files = [depth_names[k] for k in ib]
        #: |t_rgb - t_depth| of every frame, seconds (N,)
        self.assoc_dt = np.abs(times - t_depth[ib])

        gt: NDArray[np.float64] | None = None
        problems: dict[int, str] = {}
        gt_file = folder / "groundtruth.txt"
        if gt_file.is_file():
            t_gt, T_gt, dropped = read_groundtruth_rows(gt_file)
            inside = (times >= t_gt[0]) & (times <= t_gt[-1])
            if not inside.any():
                log.warning("%s: no frame lies within the ground-truth time span [%.3f, %.3f]; "
                            "the sequence has no ground truth", gt_file, t_gt[0], t_gt[-1])
            else:
                if not inside.all():
                    log.info("%s: %d of %d frames lie outside the ground-truth time span; "
                             "the sequence is restricted to the %d inside", folder.name,
                             int((~inside).sum()), len(times), int(inside.sum()))
                    times = times[inside]
                    depth_times = depth_times[inside]
                    rgb_files = [f for f, ok in zip(rgb_files, inside) if ok]
                    depth_files = [f for f, ok in zip(depth_files, inside) if ok]
                    self.assoc_dt = self.assoc_dt[inside]
                gt = interpolate_poses(t_gt, T_gt, times)
                problems = across_dropped(times, t_gt, dropped)
                gt[list(problems)] = np.nan
                k = np.clip(np.searchsorted(t_gt, times), 1, len(t_gt) - 1) if len(t_gt) > 1 else None
                if k is not None:
                    gaps = t_gt[k] - t_gt[k - 1]
                    n_gap = int((gaps > max_gt_gap).sum())
                    if n_gap:
                        log.warning("%s: %d frames fall in ground-truth gaps longer than %.3f s "
                                    "(GT interpolated across them)", gt_file, n_gap, max_gt_gap)
        self._rgb_files = rgb_files
        self._depth_files = depth_files
        ids = np.arange(len(times), dtype=np.int64)
        super().__init__(name or folder.resolve().name, intr, times, ids, gt, depth_times, sensor=SENSOR)
        self.gt_problems = problems

    def _read_rgb(self, pos: int) -> NDArray[np.uint8]:
        return read_rgb(self.root / self._rgb_files[pos], self.intrinsics)  # undistorted by Sequence.rgb

    def _read_depth(self, pos: int) -> NDArray[np.float32]:
        return read_depth_file(self.root / self._depth_files[pos], self.intrinsics)


def read_rgb_file(path: Path, intr: Intrinsics, undistort: Undistortion | None = None) -> NDArray[np.uint8]:
    """A TUM RGB-D colour image, RGB, undistorted by ``undistort`` (None: as recorded)."""
    rgb = read_rgb(path, intr)
    return rgb if undistort is None else undistort.rgb(rgb)


def read_depth_file(path: Path, intr: Intrinsics, undistort: Undistortion | None = None) -> NDArray[np.float32]:
    """A TUM RGB-D depth PNG in metres (5000 units per metre on file; 0 invalid), undistorted
    by ``undistort`` (None: as recorded)."""
    depth = read_depth(path, DEPTH_SCALE, intr, invalid=(0,))
    return depth if undistort is None else undistort.depth(depth)
