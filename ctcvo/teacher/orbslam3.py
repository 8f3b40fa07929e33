"""ORB-SLAM3 RGB-D (through ``pyorbslam3``, GPL-3.0) as a teacher backend.

:func:`run_orbslam3` tracks a sequence and keeps, per frame, the tracking state and the
causal ``T_world_cam`` ORB-SLAM3 returned then, and after shutdown its keyframe-refined
final trajectory; :func:`edges_from` turns either into relative-pose labels
``T_i_j = inv(T_world_i) @ T_world_j`` for gaps 1..K, and :func:`write_outputs` writes the
teacher's file set (docs/formats.md). ORB-SLAM3 is multithreaded: runs differ, and
``report.json`` says ``deterministic: false``.

An edge is good only when both frames were tracked ``OK`` in one unbroken stretch: a frame
not initialised or lost fails its edges (status the state, lower case), and so does an
edge across a break (``relocalised``: tracking came back in the same map; ``new_map``:
ORB-SLAM3 started a map afresh) and, for causal labels, across a loop closure or global
bundle adjustment (``map_changed``).
"""

from __future__ import annotations

import logging
import multiprocessing
import os
import sys
import tempfile
import time
from collections import Counter
from concurrent.futures import ProcessPoolExecutor
from concurrent.futures.process import BrokenProcessPool
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from ctcvo.data import geometry as geo
from ctcvo.data.errors import ConfigError, DataError, FormatError, VOError
from ctcvo.data.formats import Edge, Trajectory, write_edges_csv, write_g2o, write_tum
from ctcvo.data.io import ensure_dir, git_revision, json_safe, write_json, write_text
from ctcvo.data.metrics import label_errors_by_gap, trajectory_report
from ctcvo.data.sequence import Sequence
from ctcvo.teacher.orbslam3_settings import settings_yaml
from ctcvo.teacher.vocabulary import read_vocabulary

log = logging.getLogger(__name__)

MODES = ("slam", "localization")
LABELS = ("causal", "final")
#: chosen on redkitchen 350:450 and fr3/teddy, 3 SLAM runs each: final gap-1 / gap-5 label error
#: 4.5 / 7.5 mm against causal 5.1 / 9.3 mm on fr3/teddy, equal on redkitchen
DEFAULT_LABELS = "final"
#: ORB-SLAM3 states that start a map afresh (after a loss, or before the first frame)
_FRESH = ("NOT_INITIALIZED", "NO_IMAGES_YET", "SYSTEM_NOT_READY")
#: the state of a frame that could not be read (not given to ORB-SLAM3, which tracks on over it)
UNREADABLE = "UNREADABLE"
#: how long to wait, after shutdown, for the final trajectory to stop changing: ORB-SLAM3
#: v1.0's shutdown returns before its threads finish (/work/shared/ORBSLAM3.md)
FINAL_WAIT_S, FINAL_POLL_S = 30.0, 0.5
#: frames looked at for valid depth before starting (a recording without depth is an error)
DEPTH_CHECK_FRAMES = 10

# Per-gap covariance model, a diagonal in the project tangent order (v, w): sigma(g) =
# sigma_gap1 * g ** GAP_EXPONENT for translation and rotation. Fitted against ground truth on
# redkitchen 350:450 and fr3/teddy 0:200, 2 SLAM runs each (bench/orbslam3_covariance.py, median
# NEES per gap consistent; record bench/results/orbslam3-covariance.json). A tracked-map-points
# factor was rejected there: it helped with teddy left out of the fit and hurt with redkitchen.
# Refitted once each run had a process of its own (:func:`_in_own_process`; teddy's runs had
# followed redkitchen's in one process): 2.2 mm, 0.145 deg, exponent 0.38 before. The record's
# rerun at 24d1cac fitted 1.84 mm, 0.131 deg, 0.36 (ORB-SLAM3's runs differ): within 4 %, kept.
SIGMA_TRANS_GAP1_M = 0.0019
SIGMA_ROT_GAP1_DEG = 0.135
GAP_EXPONENT = 0.34


def _import_pyorbslam3():
    """``pyorbslam3``, the optional dependency (the one import made inside a function, so
    that the rest of the project runs without it)."""
    try:
        import pyorbslam3
    except ImportError:
        raise ConfigError("the orbslam3 backend needs pyorbslam3: pip install ctcvo[orbslam3]") from None
    return pyorbslam3


@dataclass
class OrbResult:
    """One ORB-SLAM3 run over a sequence, per frame position (N frames).

    ``states``: ORB-SLAM3's tracking state names; ``pose_valid`` (N,) bool; ``T_world_cam_causal``
    (N, 4, 4) as returned while tracking, NaN where not valid; ``T_world_cam_final`` (N, 4, 4) from
    the keyframe-refined trajectory saved after shutdown, NaN for frames it lacks;
    ``tracked_points`` (N,) map points tracked in each frame; ``map_changed`` (N,) a loop closure
    or global bundle adjustment reported after the frame; ``track_seconds`` the time in tracking
    calls, ``seconds`` the whole run's; ``log`` ORB-SLAM3's own output.
    """

    frame_ids: NDArray[np.int64]
    timestamps: NDArray[np.float64]
    mode: str
    states: list[str]
    pose_valid: NDArray[np.bool_]
    T_world_cam_causal: NDArray[np.float64]
    T_world_cam_final: NDArray[np.float64]
    tracked_points: NDArray[np.int64]
    map_changed: NDArray[np.bool_]
    track_seconds: float
    seconds: float
    log: str = ""
    skipped: dict[int, str] = field(default_factory=dict)
    """Why each unreadable frame (state ``UNREADABLE``, by position) could not be read."""

    @property
    def ok(self) -> NDArray[np.bool_]:
        """Frames tracked ``OK`` with a valid pose, (N,)."""
        return np.array([s == "OK" for s in self.states]) & self.pose_valid

    @property
    def fps(self) -> float:
        return len(self.states) / self.seconds if self.seconds > 0 else float("nan")

    def segments(self) -> NDArray[np.int64]:
        """Stretch number of each frame, (N,): a new stretch starts at every frame after a
        frame not tracked OK (its own poses then come from a relocalisation or a new map)."""
        breaks = ~self.ok & np.array([s != UNREADABLE for s in self.states])  # ORB-SLAM3 never saw those
        return np.cumsum(np.concatenate([[True], breaks[:-1]]))

    def poses(self, use: str) -> NDArray[np.float64]:
        """``T_world_cam`` (N, 4, 4) of the ``causal`` or ``final`` labels."""
        if use not in LABELS:
            raise ConfigError(f"labels must be one of {', '.join(LABELS)}, got {use!r}")
        return self.T_world_cam_causal if use == "causal" else self.T_world_cam_final


@dataclass
class OrbEdge:
    """A label between frame ids i and j: ``T_i_j`` and ``cov`` (6x6, tangent order (v, w))
    where ``status`` is ``ok``, else None; ``points``: the fewer tracked map points of the two frames."""

    i: int
    j: int
    gap: int
    status: str
    points: int
    T_i_j: NDArray[np.float64] | None = None
    cov: NDArray[np.float64] | None = None

    @property
    def good(self) -> bool:
        return self.status == "ok"


class _Stdout:
    """Send file descriptor 1 (ORB-SLAM3 prints there) to a temporary file; ``text`` then holds it."""

    def __enter__(self) -> _Stdout:
        sys.stdout.flush()
        self._file = tempfile.TemporaryFile(mode="w+")
        self._saved = os.dup(1)
        os.dup2(self._file.fileno(), 1)
        return self

    def __exit__(self, *exc) -> None:
        os.dup2(self._saved, 1)
        os.close(self._saved)
        self._file.seek(0)
        self.text = self._file.read()
        self._file.close()


def run_orbslam3(seq: Sequence, vocabulary: Path, mode: str = "slam", settings: Path | None = None,
                 n_features: int = 1000, strict: bool = False) -> OrbResult:
    """Track ``seq`` with ORB-SLAM3 RGB-D. ``settings``: the user's ORB-SLAM3 YAML (default:
    :func:`settings_yaml` of the sequence); ``localization`` stops mapping after the first
    tracked frame (no new keyframes, no loop closure). A frame that cannot be read is not
    given to ORB-SLAM3 (state ``UNREADABLE``; its edges fail, those over it are kept), or with
    ``strict`` its :class:`DataError` stops the run. The run has a process of its own
    (:func:`_in_own_process`)."""
    if mode not in MODES:
        raise ConfigError(f"ORB-SLAM3 mode must be one of {', '.join(MODES)}, got {mode!r}")
    read_vocabulary(vocabulary)  # a malformed file would crash ORB-SLAM3's reader
    if settings is not None and not Path(settings).is_file():
        raise ConfigError(f"ORB-SLAM3 settings file {settings} not found")
    if not any(np.any(_depth_or_none(seq, k, strict) > 0) for k in range(min(len(seq), DEPTH_CHECK_FRAMES))):
        raise DataError(f"{seq.name}: no valid depth in the first {min(len(seq), DEPTH_CHECK_FRAMES)} frames "
                        "(ORB-SLAM3 RGB-D needs depth)")
    _import_pyorbslam3()  # a missing dependency is the caller's one-line error, before any process starts
    res = _in_own_process(seq.name, _session, seq, vocabulary, mode, settings, n_features, strict)
    if not res.ok.any():
        raise VOError(f"{seq.name}: ORB-SLAM3 never initialised ({len(seq)} frames; states "
                      f"{dict(Counter(res.states))})")
    if not np.isfinite(res.T_world_cam_final).any():
        log.warning("%s: ORB-SLAM3 ended without a map (reset after a loss): no final trajectory", seq.name)
    return res


def _in_own_process(name: str, fn, *args):
    """``fn(*args)`` in a fresh interpreter of its own (multiprocessing ``spawn``).

    ORB-SLAM3 keeps per-process state it computes once from the first camera it sees (the
    image bounds and the camera constants of its frames), so a second sequence of another
    camera in the same process is tracked with the first one's: fr1/xyz 0:100 after
    redkitchen 0:100 had an ATE of 117 mm, 11 mm on its own. A crash of ORB-SLAM3 then ends
    that process only, as a one-line error."""
    with ProcessPoolExecutor(max_workers=1, mp_context=multiprocessing.get_context("spawn")) as pool:
        try:
            return pool.submit(fn, *args).result()
        except BrokenProcessPool:
            raise VOError(f"{name}: ORB-SLAM3's process ended without a result (it crashed, or a script without "
                          "`if __name__ == '__main__':` started it)") from None


def _session(seq: Sequence, vocabulary: Path, mode: str, settings: Path | None, n_features: int,
             strict: bool) -> OrbResult:
    """One ORB-SLAM3 run over ``seq`` in this process: settings, tracking, shutdown, the final
    trajectory, its own output in ``log`` (:func:`run_orbslam3` runs it in a process of its own)."""
    P = _import_pyorbslam3()
    start = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="orbslam3-") as tmp, _Stdout() as out:
        yaml = Path(settings) if settings is not None else Path(tmp) / "settings.yaml"
        if settings is None:
            yaml.write_text(settings_yaml(seq, n_features))
        slam = P.Slam(str(vocabulary), str(yaml), P.Sensor.RGBD, use_viewer=False)
        try:
            res = _track(slam, seq, mode, strict)
        finally:
            slam.shutdown()
        if _has_keyframes(res.states):
            res.T_world_cam_final = _final_poses(slam, Path(tmp) / "final.tum", res)
    res.seconds = time.perf_counter() - start
    res.log = out.text
    return res


def _has_keyframes(states: list[str]) -> bool:
    """Whether ORB-SLAM3 surely ends with keyframes: a frame tracked OK after the last fresh start
    (saving a trajectory without any keyframe crashes it)."""
    fresh = [k for k, s in enumerate(states) if s in _FRESH]
    return "OK" in states[(fresh[-1] + 1) if fresh else 0:]


def _depth_or_none(seq: Sequence, k: int, strict: bool) -> NDArray[np.float32]:
    """Frame ``k``'s depth, or an empty one for an unreadable frame (unless ``strict``)."""
    try:
        return seq.depth(k)
    except DataError:
        if strict:
            raise
        return np.zeros(0, np.float32)


def _track(slam, seq: Sequence, mode: str, strict: bool = False) -> OrbResult:
    """Feed every frame to ``slam``; the per-frame fields of an :class:`OrbResult`."""
    n = len(seq)
    times = seq.times()
    states, valid = [], np.zeros(n, bool)
    causal = np.full((n, 4, 4), np.nan)
    points, changed = np.zeros(n, np.int64), np.zeros(n, bool)
    tracking = 0.0
    localizing = False
    skipped: dict[int, str] = {}
    for k in range(n):
        try:
            rgb, depth = seq.rgb(k), seq.depth(k)
        except DataError as exc:
            if strict:
                raise
            skipped[k] = str(exc)
            states.append(UNREADABLE)
            continue
        t0 = time.perf_counter()
        r = slam.track_rgbd(rgb, depth, float(times[k]))
        tracking += time.perf_counter() - t0
        states.append(r.state.name)
        valid[k] = bool(r.pose_valid)
        if valid[k]:
            causal[k] = np.asarray(r.pose_wc, dtype=np.float64)
        points[k] = int(r.num_tracked_points)
        changed[k] = bool(slam.map_changed())
        if mode == "localization" and not localizing and r.state.name == "OK":
            slam.activate_localization_mode()
            localizing = True
    return OrbResult(seq.ids(), times, mode, states, valid, causal, np.full((n, 4, 4), np.nan), points,
                     changed, tracking, 0.0, skipped=skipped)


def _final_poses(slam, path: Path, res: OrbResult) -> NDArray[np.float64]:
    """The keyframe-refined trajectory after shutdown, (N, 4, 4) (NaN where it lacks a frame):
    saved again until two saves agree and every tracked frame is in it, or :data:`FINAL_WAIT_S`."""
    deadline = time.monotonic() + FINAL_WAIT_S
    prev = None
    while True:
        slam.save_trajectory_tum(str(path))
        text = path.read_text() if path.is_file() else ""
        poses = _match_rows(path, res.timestamps) if text.strip() else np.full((len(res.states), 4, 4), np.nan)
        complete = bool(np.all(np.isfinite(poses[res.ok]).all(axis=(1, 2))))
        if (text == prev and complete) or time.monotonic() > deadline:
            if not complete:
                log.warning("ORB-SLAM3's final trajectory lacks %d tracked frames after %.0f s",
                            int((~np.isfinite(poses[res.ok]).all(axis=(1, 2))).sum()), FINAL_WAIT_S)
            return poses
        prev = text
        time.sleep(FINAL_POLL_S)


def _match_rows(path: Path, timestamps: NDArray[np.float64]) -> NDArray[np.float64]:
    """Poses of ORB-SLAM3's TUM file at ``timestamps`` (it writes them with 6 decimals), NaN for a
    frame it lacks, or lists twice with different poses (seen once on fr1/xyz)."""
    try:
        rows = np.loadtxt(path, ndmin=2, comments="#")
    except ValueError as exc:
        raise FormatError(f"ORB-SLAM3's trajectory {path}: {exc}") from None
    if rows.size and (rows.shape[1] != 8 or not np.isfinite(rows).all()):
        raise FormatError(f"ORB-SLAM3's trajectory {path}: rows must be 8 finite numbers 'timestamp tx ty tz qx qy qz qw'")
    rows = rows[np.argsort(rows[:, 0], kind="stable")] if rows.size else np.zeros((0, 8))
    lo = np.searchsorted(rows[:, 0], timestamps - 5e-6)
    hi = np.searchsorted(rows[:, 0], timestamps + 5e-6)
    poses = np.full((len(timestamps), 4, 4), np.nan)
    for k in np.flatnonzero(hi > lo):
        match = rows[lo[k]:hi[k], 1:]
        if np.all(match == match[0]):
            poses[k] = geo.orthonormalize(geo.tum_to_T(match[0]))
    return poses


def edge_covariance(gap: int) -> NDArray[np.float64]:
    """The per-gap model's 6x6 diagonal covariance of an edge of ``gap`` frames (tangent order (v, w))."""
    scale = gap ** GAP_EXPONENT
    sig_t, sig_r = SIGMA_TRANS_GAP1_M * scale, np.deg2rad(SIGMA_ROT_GAP1_DEG) * scale
    return np.diag([sig_t ** 2] * 3 + [sig_r ** 2] * 3)


def edges_from(result: OrbResult, gaps: int = 5, use: str = DEFAULT_LABELS) -> list[OrbEdge]:
    """Labels ``T_i_j`` for every frame pair (k, k + g), g = 1..``gaps``, from the ``use``
    poses, failed edges flagged (module docstring)."""
    if gaps < 1:
        raise ConfigError(f"gaps must be >= 1, got {gaps}")
    poses = result.poses(use)
    ok, seg = result.ok, result.segments()
    have = np.isfinite(poses).all(axis=(1, 2))
    changes = np.concatenate([[0], np.cumsum(result.map_changed)])  # changes[k]: map changes reported after frames < k
    ids, n = result.frame_ids, len(result.states)
    edges = []
    for a in range(n):
        for g in range(1, gaps + 1):
            b = a + g
            if b >= n:
                break
            pts = int(min(result.tracked_points[a], result.tracked_points[b]))
            status = _status(result.states, ok, seg, a, b)
            if status == "ok" and use == "causal" and changes[b + 1] != changes[a]:  # a change after a, .., b
                status = "map_changed"
            if status == "ok" and not (have[a] and have[b]):
                status = "no_final_pose"
            e = OrbEdge(int(ids[a]), int(ids[b]), g, status, pts)
            if e.good:
                e.T_i_j = geo.orthonormalize(geo.relative_pose(poses[a], poses[b]))
                e.cov = edge_covariance(g)
            edges.append(e)
    return edges


def _status(states: list[str], ok: NDArray[np.bool_], seg: NDArray[np.int64], a: int, b: int) -> str:
    """``ok``, the state of the first of frames a, b not tracked OK, or why a break between them fails."""
    for k in (a, b):
        if not ok[k]:
            return states[k].lower()
    if seg[a] == seg[b]:
        return "ok"
    return "new_map" if any(s in _FRESH for s in states[a:b]) else "relocalised"


def _edge_rows(edges: list[OrbEdge], ts: dict[int, float], use: str) -> list[dict]:
    rows = []
    for e in edges:
        r = {"i": e.i, "j": e.j, "t_i": f"{ts[e.i]:.6f}", "t_j": f"{ts[e.j]:.6f}", "status": e.status,
             "matches": e.points, "path": f"orbslam3-{use}" if e.good else "none"}
        if e.good:
            r["trans_m"] = float(np.linalg.norm(e.T_i_j[:3, 3]))
            r["rot_deg"] = float(geo.rotation_angle_deg(e.T_i_j))
        rows.append(r)
    return rows


def build_report(seq: Sequence, result: OrbResult, edges: list[OrbEdge], use: str) -> dict:
    """``report.json``: the teacher's keys where they apply, and ORB-SLAM3's own."""
    status = Counter(e.status for e in edges)
    ok = result.ok
    rep: dict = {
        "sequence": seq.name, "frames": len(seq), "backend": "orbslam3", "mode": result.mode, "labels": use,
        "deterministic": False,
        "edges": int(status.get("ok", 0)),
        "failed_edges": int(sum(v for s, v in status.items() if s != "ok")),
        "failed_gap1_edges": sum(1 for e in edges if e.gap == 1 and not e.good),
        "failures_by_reason": {s: int(v) for s, v in status.items() if s != "ok"},
        "tracking_states": dict(Counter(result.states)),
        "tracked_frames": int(ok.sum()),
        "map_changes": int(result.map_changed.sum()),
        "fps": result.fps, "tracking_fps": len(seq) / result.track_seconds if result.track_seconds > 0 else float("nan"),
        "seconds": result.seconds,
        "frames_skipped": [{"frame": int(result.frame_ids[p]), "why": why} for p, why in sorted(result.skipped.items())],
        "covariance_model": {"sigma_trans_gap1_m": SIGMA_TRANS_GAP1_M, "sigma_rot_gap1_deg": SIGMA_ROT_GAP1_DEG,
                             "gap_exponent": GAP_EXPONENT, "calibrated": True,
                             "fitted_on": "redkitchen 350:450, TUM fr3/teddy 0:200 (bench/orbslam3_covariance.py)"},
    }
    gt, poses = seq.groundtruth(partial=True), result.poses(use)
    have = ok & np.isfinite(poses).all(axis=(1, 2))
    if gt is not None:
        rep["groundtruth_dropped"] = seq.groundtruth_dropped()
        have &= np.isfinite(gt).all(axis=(1, 2))
    if gt is not None and have.sum() >= 2:
        times = seq.times()
        rep.update(trajectory_report(Trajectory(times[have], gt[have]), Trajectory(times[have], poses[have])))
        gt_ok = {int(f) for f in seq.ids()[np.isfinite(gt).all(axis=(1, 2))]}
        rep["label_error_by_gap"] = label_errors_by_gap(
            [(e.i, e.j, e.T_i_j) for e in edges if e.good and e.i in gt_ok and e.j in gt_ok], gt, seq.ids())
    return rep


def write_outputs(out_dir: Path, seq: Sequence, result: OrbResult, edges: list[OrbEdge], use: str = DEFAULT_LABELS,
                  extra: dict | None = None) -> dict:
    """Write ``edges.g2o`` (good edges; vertices: the tracked frames' poses), ``edges.csv`` (every
    edge), ``trajectory.tum`` (the ``use`` poses of the tracked frames), ``groundtruth.tum``,
    ``orbslam3.log``, ``config.json`` and ``report.json`` last (it marks completion)."""
    out = ensure_dir(Path(out_dir))
    ids, times = seq.ids(), seq.times()
    poses = result.poses(use)
    have = result.ok & np.isfinite(poses).all(axis=(1, 2))
    if not have.any():
        raise FormatError(f"{seq.name}: no tracked frame has a {use} pose to write")
    write_g2o(out / "edges.g2o", [Edge(e.i, e.j, e.T_i_j, e.cov) for e in edges if e.good],
              {int(f): T for f, T, h in zip(ids, poses, have) if h})
    write_edges_csv(out / "edges.csv", _edge_rows(edges, {int(f): float(t) for f, t in zip(ids, times)}, use))
    write_tum(out / "trajectory.tum", Trajectory(times[have], poses[have]))
    gt = seq.groundtruth(partial=True)
    if gt is not None and (known := np.isfinite(gt).all(axis=(1, 2))).any():
        write_tum(out / "groundtruth.tum", Trajectory(times[known], gt[known]))  # without the dropped frames
    write_text(out / "orbslam3.log", result.log)
    write_json(out / "config.json", {"backend": "orbslam3", "mode": result.mode, "labels": use,
                                     "git_revision": git_revision(), **(extra or {})})
    report = build_report(seq, result, edges, use)
    write_json(out / "report.json", json_safe(report))
    return report
