"""Read edge sources (teacher / learner folders, bare g2o files) and line up their frames.

A source folder holds ``edges.g2o`` (required) and optionally ``edges.csv`` (its
``i, j, t_i, t_j`` columns give every frame's timestamp), ``trajectory.tum`` (the
chained trajectory of that source) and ``groundtruth.tum``. Frames are identified by
their ids (the g2o vertex ids). Trajectory rows are paired with frames by timestamp when
timestamps are known, otherwise by order when the row count equals the frame count.
"""

from __future__ import annotations

import json
import logging
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from ctcvo.data.errors import DataError, FormatError
from ctcvo.data.formats import Edge, Trajectory, read_edges_csv, read_g2o, read_observations, read_tum

log = logging.getLogger(__name__)

EDGES_FILE = "edges.g2o"
EDGES_CSV = "edges.csv"
OBSERVATIONS_CSV = "observations.csv"
TRAJECTORY_FILE = "trajectory.tum"
GROUNDTRUTH_FILE = "groundtruth.tum"
REPORT_FILE = "report.json"
#: Timestamps closer than this (s) are the same frame.
TIME_TOL = 1e-4
#: Frame rate (Hz) assumed when no timestamps are known (a bare edges file): the sensors' 30 Hz.
FALLBACK_FPS = 30.0


@dataclass
class Source:
    """One set of edges with whatever frame information came with it."""

    name: str
    """``teacher``, ``learner`` or the stem of an edges file."""
    path: Path
    edges: list[Edge]
    vertices: dict[int, NDArray[np.float64]] = field(default_factory=dict)
    """Vertex id -> ``T_world_cam`` from ``VERTEX_SE3:QUAT`` lines."""
    times: dict[int, float] = field(default_factory=dict)
    """Frame id -> timestamp (s) from ``edges.csv``."""
    trajectory: Trajectory | None = None
    groundtruth: Trajectory | None = None
    skill: dict | None = None
    """The source's accuracy against zero motion on validation data, when its folder says
    (a learner's ``report.json`` -> ``calibration.json`` -> ``validation.skill``): ``ratio``
    = its se(3) L2 error over zero motion's on the validation pairs (below 1: better than
    a camera that never moves), ``reference`` (what the error was measured against),
    ``pairs`` and ``from`` (the file)."""
    observations: NDArray[np.float64] | None = None
    """The folder's ``observations.csv`` (landmark sightings, the teacher's on a
    registered-colour sensor) for the bundle adjustment (:mod:`posegraph.bundle`)."""


@dataclass
class Frames:
    """The frames of the graph."""

    ids: NDArray[np.int64]
    """(N,) sorted frame ids."""
    times: NDArray[np.float64]
    """(N,) timestamps in seconds."""
    listed_by: str
    """Where the frame list came from (for error messages)."""
    synthetic_times: bool = False
    """True when no timestamps were known and ``id / FALLBACK_FPS`` was used."""


def load_dir(path: Path, name: str) -> Source:
    """Load a teacher or learner output folder (see module docstring)."""
    path = Path(path)
    if not path.is_dir():
        raise DataError(f"{name} folder {path} does not exist")
    g2o = path / EDGES_FILE
    if not g2o.is_file():
        raise DataError(f"{name} folder {path} has no {EDGES_FILE}")
    src = load_edges_file(g2o, name)
    src.path = path
    if (path / EDGES_CSV).is_file():
        for row in read_edges_csv(path / EDGES_CSV):
            for k, t in (("i", "t_i"), ("j", "t_j")):
                if k in row and t in row and np.isfinite(row[t]):
                    src.times[int(row[k])] = float(row[t])
    if (path / TRAJECTORY_FILE).is_file():
        src.trajectory = read_tum(path / TRAJECTORY_FILE)
    if (path / GROUNDTRUTH_FILE).is_file():
        src.groundtruth = read_tum(path / GROUNDTRUTH_FILE)
    src.skill = read_skill(path)
    if (path / OBSERVATIONS_CSV).is_file():
        src.observations = read_observations(path / OBSERVATIONS_CSV)
    log.info("%s: %d edges%s from %s", name, len(src.edges), "" if src.observations is None else
             f" and {len(src.observations)} landmark sightings", path)
    return src


def read_skill(path: Path) -> dict | None:
    """The validation skill a learner folder points to (see :attr:`Source.skill`), or
    ``None`` when the folder has no ``report.json`` naming a calibration with one. A named
    calibration that cannot be read is an error (the edges were calibrated with it)."""
    report = Path(path) / REPORT_FILE
    if not report.is_file():
        return None
    try:
        cal = json.loads(report.read_text()).get("calibration")
    except (OSError, ValueError, AttributeError) as exc:
        raise FormatError(f"cannot read {report}: {exc}") from None
    if not cal:
        return None
    cal = Path(cal)
    if not cal.is_absolute() and not cal.is_file():
        cal = Path(path) / cal
    try:
        d = json.loads(cal.read_text())
        skill = (d.get("validation") or {}).get("skill")
    except (OSError, ValueError, AttributeError) as exc:
        raise FormatError(f"{report} names the calibration {cal}, which cannot be read: {exc}") from None
    if skill is None:
        return None
    try:
        ratio = float(skill["ratio"])
    except (KeyError, TypeError, ValueError):
        raise FormatError(f"{cal}: validation.skill needs a numeric ratio") from None
    if not np.isfinite(ratio) or ratio < 0:
        raise FormatError(f"{cal}: validation.skill.ratio must be finite and non-negative, got {ratio}")
    return {**skill, "ratio": ratio, "from": str(cal)}


def load_edges_file(path: Path, name: str | None = None) -> Source:
    """Load a bare g2o edges file (a :class:`Source` without timestamps)."""
    path = Path(path)
    name = name or path.stem
    edges, vertices = read_g2o(path)
    if not edges:
        raise FormatError(f"{path}: no EDGE_SE3:QUAT lines")
    for e in edges:
        e.extra["source"] = name
    return Source(name=name, path=path, edges=edges, vertices=vertices)


def resolve_frames(sources: Sequence[Source]) -> Frames:
    """The frame table: ids listed by vertices, ``edges.csv`` or a trajectory whose rows
    pair with them; with no listing at all, the ids the edges use. Without timestamps,
    ``id / FALLBACK_FPS``."""
    listed: dict[int, float | None] = {}
    by = []
    for s in sources:
        if s.vertices:
            for k in s.vertices:
                listed.setdefault(int(k), None)
            by.append(f"{s.name} vertices")
        if s.times:
            for k, t in s.times.items():
                listed[int(k)] = t
            by.append(f"{s.path / EDGES_CSV}")
    if not listed:
        ids = sorted({int(k) for s in sources for e in s.edges for k in (e.i, e.j)})
        for s in sources:
            for traj in (s.trajectory, s.groundtruth):
                if traj is not None and len(traj) == len(ids):
                    return Frames(np.array(ids, dtype=np.int64), traj.timestamps.copy(), "edge ids")
        return Frames(np.array(ids, dtype=np.int64), np.array(ids, dtype=np.float64) / FALLBACK_FPS, "edge ids",
                      synthetic_times=True)
    ids = np.array(sorted(listed), dtype=np.int64)
    times = np.array([np.nan if listed[int(k)] is None else listed[int(k)] for k in ids])
    if np.isnan(times).any():
        # vertices without csv timestamps: take them from a trajectory of the same length
        for s in sources:
            for traj in (s.trajectory, s.groundtruth):
                if traj is not None and len(traj) == len(ids):
                    return Frames(ids, traj.timestamps.copy(), ", ".join(by))
        return Frames(ids, ids.astype(np.float64) / FALLBACK_FPS, ", ".join(by), synthetic_times=True)
    return Frames(ids, times, ", ".join(by))


def poses_for_frames(traj: Trajectory | None, frames: Frames, partial: bool = False) -> NDArray[np.float64] | None:
    """(N, 4, 4) poses of ``traj`` at the frames, or ``None`` if they cannot be paired
    (by timestamp, or by order when the lengths are equal and the times are unknown);
    with ``partial`` a frame without a pose (by timestamp) is a NaN row instead."""
    if traj is None:
        return None
    if frames.synthetic_times:
        return traj.poses.copy() if len(traj) == len(frames.ids) else None
    idx = np.searchsorted(traj.timestamps, frames.times)
    out = np.empty((len(frames.ids), 4, 4))
    for n, (t, k) in enumerate(zip(frames.times, idx)):
        cands = [c for c in (k - 1, k) if 0 <= c < len(traj)]
        c = min(cands, key=lambda c: abs(traj.timestamps[c] - t)) if cands else None
        if c is None or abs(traj.timestamps[c] - t) > TIME_TOL:
            if not partial:
                return None
            out[n] = np.nan
            continue
        out[n] = traj.poses[c]
    return out


def find_sequence_dirs(root: Path) -> list[str]:
    """Names of sub-folders of ``root`` that hold ``edges.g2o`` (several sequences)."""
    root = Path(root)
    if (root / EDGES_FILE).is_file() or not root.is_dir():
        return []
    return sorted(p.name for p in root.iterdir() if (p / EDGES_FILE).is_file())
