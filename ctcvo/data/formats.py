"""Readers and writers of the files stages exchange (see docs/formats.md).

* TUM trajectories ``timestamp tx ty tz qx qy qz qw`` (``T_world_cam``), read by evo.
* Relative-pose edges in g2o ``EDGE_SE3:QUAT`` with a 6x6 information matrix (upper
  triangle, row-major) in the project tangent order (v, w), which is also g2o's
  (translation, rotation) order; ``gtsam.readG2o`` reads these files. Vertices
  ``VERTEX_SE3:QUAT`` carry an initial trajectory.
* ``edges.csv``: per-edge quality figures and status, including failed edges.
* ``observations.csv``: sightings of landmarks (normalised pixel and depth), for
  the pose graph's bundle adjustment.

Every writer is atomic; every reader validates strictly and raises
:class:`~data.errors.FormatError` with the file, line and reason.
"""

from __future__ import annotations

import csv
import io
import math
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from ctcvo.data import geometry as geo
from ctcvo.data.errors import FormatError
from ctcvo.data.io import atomic_write


# ----------------------------------------------------------------------------------
# TUM trajectories
# ----------------------------------------------------------------------------------
@dataclass
class Trajectory:
    """Timestamps (N,) and ``T_world_cam`` poses (N, 4, 4)."""

    timestamps: NDArray[np.float64]
    poses: NDArray[np.float64]

    def __post_init__(self) -> None:
        self.timestamps = np.asarray(self.timestamps, dtype=np.float64).reshape(-1)
        self.poses = np.asarray(self.poses, dtype=np.float64).reshape(-1, 4, 4)
        if len(self.timestamps) != len(self.poses):
            raise ValueError(f"{len(self.timestamps)} timestamps but {len(self.poses)} poses")

    def __len__(self) -> int:
        return len(self.timestamps)

    def to_evo(self):  # -> evo.core.trajectory.PoseTrajectory3D
        from evo.core.trajectory import PoseTrajectory3D

        xyz, q_wxyz = geo.evo_pose_arrays(self.poses)
        return PoseTrajectory3D(positions_xyz=xyz, orientations_quat_wxyz=q_wxyz, timestamps=self.timestamps)

    @classmethod
    def from_evo(cls, traj) -> Trajectory:
        return cls(np.asarray(traj.timestamps), geo.poses_from_evo_arrays(traj.positions_xyz, traj.orientations_quat_wxyz))


def write_tum(path: Path, traj: Trajectory) -> None:
    """Write a TUM trajectory file atomically."""
    if not (np.all(np.isfinite(traj.timestamps)) and np.all(np.isfinite(traj.poses))):
        raise FormatError(f"refusing to write non-finite poses to {path}")
    with atomic_write(path) as fh:
        fh.write("# timestamp tx ty tz qx qy qz qw  (T_world_cam, metres)\n")
        for t, row in zip(traj.timestamps, geo.T_to_tum(np.asarray(traj.poses).reshape(-1, 4, 4))):
            fh.write(f"{t:.6f} " + " ".join(f"{x:.9f}" for x in row) + "\n")


def read_tum(path: Path) -> Trajectory:
    """Read a TUM trajectory: strict line-by-line validation, then evo's reader.

    Rows are ``timestamp tx ty tz qx qy qz qw`` (``#`` comments allowed), finite, with a
    non-zero quaternion and strictly increasing timestamps; otherwise
    :class:`~data.errors.FormatError` names the file and line.
    """
    from evo.tools.file_interface import FileInterfaceException, read_tum_trajectory_file

    path = Path(path)
    if not path.is_file():
        raise FormatError(f"missing TUM trajectory file {path}")
    _check_tum_rows(path)
    try:
        traj = read_tum_trajectory_file(str(path))
    except (FileInterfaceException, ValueError, IndexError) as exc:
        raise FormatError(f"{path}: {exc}") from None
    return Trajectory.from_evo(traj)


def read_tum_rows(path: Path, fields: str, what: str, numbers: int = 1,
                  check: Callable[[str, NDArray[np.float64]], None] | None = None, growing: bool = False
                  ) -> list[tuple[str, list[str], NDArray[np.float64]]]:
    """The rows of a TUM-style text file (trajectories, TUM RGB-D ``rgb.txt`` /
    ``depth.txt``): blank and ``#`` lines skipped, each row ``len(fields.split())``
    whitespace-separated entries, the first ``numbers`` of them finite numbers, the first
    a timestamp, strictly increasing; ``check(where, numbers)`` may reject a row further.

    Returns ``("path:line", entries, the leading numbers)`` per row; raises
    :class:`~data.errors.FormatError` naming the file and line (``fields`` spells the
    expected row, ``what`` the rows, for the message of an empty file). ``growing``: the
    file is still being appended to: a last line without its newline is not read yet, and
    no rows is no error."""
    path = Path(path)
    try:
        text = path.read_text()
    except (OSError, UnicodeDecodeError) as exc:
        raise FormatError(f"{path}: cannot read as text ({exc})") from None
    if growing:
        text = text[: text.rfind("\n") + 1]
    lines = text.splitlines()
    rows, prev = [], -math.inf
    n = len(fields.split())
    for lineno, line in enumerate(lines, 1):
        s = line.strip()
        if not s or s.startswith("#"):
            continue
        where = f"{path}:{lineno}"
        toks = s.split()
        if len(toks) != n:
            raise FormatError(f"{where}: a row needs {n} entries '{fields}', got {len(toks)}")
        vals = _parse_floats(toks[:numbers], where)
        if check is not None:
            check(where, vals)
        t = vals[0]
        if t <= prev:
            raise FormatError(f"{where}: timestamps must be strictly increasing ({t:.6f} after {prev:.6f})")
        prev = t
        rows.append((where, toks, vals))
    if not rows and not growing:
        raise FormatError(f"{path}: no {what}")
    return rows


def _check_tum_rows(path: Path) -> None:
    def nonzero_quaternion(where: str, vals: NDArray[np.float64]) -> None:
        if np.linalg.norm(vals[4:]) < 1e-6:
            raise FormatError(f"{where}: zero quaternion")

    read_tum_rows(path, "timestamp tx ty tz qx qy qz qw", "poses", numbers=8, check=nonzero_quaternion)


# ----------------------------------------------------------------------------------
# g2o edges
# ----------------------------------------------------------------------------------
@dataclass
class Edge:
    """A relative-pose measurement ``T_i_j`` between frame ids i and j.

    ``cov`` is the 6x6 covariance in the project tangent order (v, w), right
    perturbation at ``T_i_j`` (``T_true = T_i_j @ exp(delta)``).
    """

    i: int
    j: int
    T_i_j: NDArray[np.float64]
    cov: NDArray[np.float64]
    extra: dict = field(default_factory=dict)

    @property
    def information(self) -> NDArray[np.float64]:
        return np.linalg.inv(self.cov)


def _check_covs(covs: list, whats: list[str], poses: list | None = None) -> None:
    """Raise :class:`FormatError` for the first covariance that is not a finite symmetric
    positive-definite 6x6 matrix, or (with ``poses``) the first relative pose that is not a
    finite rigid transform; checked in batches, reported in order."""
    shaped = np.array([np.shape(c) == (6, 6) for c in covs], dtype=bool)
    C = np.zeros((len(covs), 6, 6))
    if shaped.any():
        C[shaped] = np.asarray([c for c, s in zip(covs, shaped) if s], dtype=np.float64)
    finite = shaped & np.isfinite(C).all(axis=(1, 2))
    C[~finite] = np.eye(6)
    symmetric = np.isclose(C, C.transpose(0, 2, 1), rtol=1e-6, atol=1e-12).all(axis=(1, 2))
    posdef = np.linalg.eigvalsh(0.5 * (C + C.transpose(0, 2, 1))).min(axis=1) > 0 if len(C) else symmetric
    rigid = np.ones(len(covs), dtype=bool)
    if poses is not None:
        P = [np.asarray(T, dtype=np.float64) for T in poses]
        four = np.array([T.shape == (4, 4) for T in P], dtype=bool)
        rigid = four.copy()
        if four.any():
            rigid[four] = geo.rigid_mask(np.stack([T for T, f in zip(P, four) if f]), atol=1e-4)
    bad = np.flatnonzero(~(finite & symmetric & posdef & rigid))
    if not len(bad):
        return
    k = int(bad[0])
    if not finite[k]:
        raise FormatError(f"{whats[k]}: covariance must be a finite 6x6 matrix")
    if not symmetric[k]:
        raise FormatError(f"{whats[k]}: covariance is not symmetric")
    if not posdef[k]:
        raise FormatError(f"{whats[k]}: covariance is not positive definite")
    raise FormatError(f"{whats[k]}: relative pose is not a finite rigid transform")


def write_g2o(path: Path, edges: Iterable[Edge], vertices: dict[int, NDArray[np.float64]] | None = None) -> None:
    """Write ``VERTEX_SE3:QUAT`` lines (id -> ``T_world_cam``) and ``EDGE_SE3:QUAT`` lines.

    Every edge is checked first (covariance, rigid pose), so a bad edge leaves no file."""
    edges = list(edges)
    _check_covs([e.cov for e in edges], [f"edge {e.i}->{e.j}" for e in edges], [e.T_i_j for e in edges])
    iu = np.triu_indices(6)
    buf = io.StringIO()
    vids = sorted(vertices or {})
    if vids:
        rows = geo.T_to_tum(np.stack([np.asarray(vertices[v], dtype=np.float64) for v in vids]))
        for vid, row in zip(vids, rows):
            buf.write(f"VERTEX_SE3:QUAT {vid} " + " ".join(f"{x:.9f}" for x in row) + "\n")
    if edges:
        covs = np.stack([np.asarray(e.cov, dtype=np.float64) for e in edges])
        infos = np.linalg.inv(covs)
        infos = 0.5 * (infos + infos.transpose(0, 2, 1))
        poses = geo.T_to_tum(np.stack([np.asarray(e.T_i_j, dtype=np.float64) for e in edges]))
        for e, row, info in zip(edges, poses, infos):
            pose = " ".join(f"{x:.9f}" for x in row)
            inf = " ".join(f"{x:.17g}" for x in info[iu])  # exact float round trip
            buf.write(f"EDGE_SE3:QUAT {e.i} {e.j} {pose} {inf}\n")
    with atomic_write(path) as fh:
        fh.write(buf.getvalue())


def read_g2o(path: Path) -> tuple[list[Edge], dict[int, NDArray[np.float64]]]:
    """Strictly parse a g2o SE(3) file: (edges, vertices id -> ``T_world_cam``)."""
    path = Path(path)
    if not path.is_file():
        raise FormatError(f"missing g2o file {path}")
    edges: list[Edge] = []
    vertices: dict[int, NDArray[np.float64]] = {}
    iu = np.triu_indices(6)
    with open(path) as fh:
        for lineno, line in enumerate(fh, 1):
            toks = line.split()
            if not toks or toks[0].startswith("#"):
                continue
            where = f"{path}:{lineno}"
            tag = toks[0]
            if tag == "VERTEX_SE3:QUAT":
                if len(toks) != 9:
                    raise FormatError(f"{where}: VERTEX_SE3:QUAT needs 9 fields, got {len(toks)}")
                vid, vals = _parse_ints(toks[1:2], where)[0], _parse_floats(toks[2:], where)
                vertices[vid] = _pose_from_vals(vals, where)
            elif tag == "EDGE_SE3:QUAT":
                if len(toks) != 31:
                    raise FormatError(f"{where}: EDGE_SE3:QUAT needs 31 fields, got {len(toks)}")
                i, j = _parse_ints(toks[1:3], where)
                vals = _parse_floats(toks[3:], where)
                T = _pose_from_vals(vals[:7], where)
                info = np.zeros((6, 6))
                info[iu] = vals[7:]
                info = info + np.triu(info, 1).T
                try:
                    cov = np.linalg.inv(info)
                except np.linalg.LinAlgError:
                    raise FormatError(f"{where}: information matrix is singular") from None
                cov = 0.5 * (cov + cov.T)
                if np.linalg.eigvalsh(info).min() <= 0:
                    raise FormatError(f"{where}: information matrix is not positive definite")
                edges.append(Edge(i, j, T, cov))
            elif tag == "FIX":
                continue
            else:
                raise FormatError(f"{where}: unknown g2o tag {tag!r} (expected VERTEX_SE3:QUAT or EDGE_SE3:QUAT)")
    return edges, vertices


def _parse_ints(toks: list[str], where: str) -> list[int]:
    try:
        return [int(t) for t in toks]
    except ValueError:
        raise FormatError(f"{where}: expected integer ids, got {' '.join(toks)}") from None


def _parse_floats(toks: list[str], where: str) -> NDArray[np.float64]:
    try:
        vals = np.array([float(t) for t in toks])
    except ValueError:
        raise FormatError(f"{where}: expected numbers") from None
    if not np.all(np.isfinite(vals)):
        raise FormatError(f"{where}: non-finite value")
    return vals


def _pose_from_vals(vals: NDArray[np.float64], where: str) -> NDArray[np.float64]:
    try:
        return geo.tum_to_T(vals)
    except ValueError as exc:
        raise FormatError(f"{where}: {exc}") from None


# ----------------------------------------------------------------------------------
# edges.csv sidecar
# ----------------------------------------------------------------------------------
EDGE_CSV_COLUMNS = [
    "i", "j", "t_i", "t_j", "status", "matches", "inliers", "inlier_ratio", "rmse_px",
    "trans_m", "rot_deg", "dense_fitness", "dense_shift_m", "path", "kind", "cov_scale", "mixed_moments",
]
#: edges.csv columns read as strings, and as integers (every other one is a float)
EDGE_CSV_STRINGS = ("status", "path", "kind")
EDGE_CSV_INTS = ("i", "j", "matches", "inliers", "mixed_moments")


def write_edges_csv(path: Path, rows: Iterable[dict]) -> None:
    """Write the per-edge sidecar (columns :data:`EDGE_CSV_COLUMNS`)."""
    with atomic_write(path) as fh:
        w = csv.DictWriter(fh, fieldnames=EDGE_CSV_COLUMNS, extrasaction="ignore", lineterminator="\n")
        w.writeheader()
        for r in rows:
            w.writerow({k: _fmt(r.get(k, "")) for k in EDGE_CSV_COLUMNS})


def _fmt(v) -> str:
    if isinstance(v, float):
        return "nan" if math.isnan(v) else repr(float(v))  # shortest exact form (timestamps ~1e9 s)
    return str(v)


def read_edges_csv(path: Path) -> list[dict]:
    """Read ``edges.csv``; numeric columns are converted, ``status`` and ``path`` stay strings."""
    path = Path(path)
    if not path.is_file():
        raise FormatError(f"missing edge table {path}")
    out = []
    with open(path, newline="") as fh:
        reader = csv.DictReader(fh)
        if reader.fieldnames is None or not {"i", "j", "status"} <= set(reader.fieldnames):
            raise FormatError(f"{path}: header must contain i, j and status")
        for lineno, r in enumerate(reader, 2):
            try:
                row = {k: (v if k in EDGE_CSV_STRINGS else (int(v) if k in EDGE_CSV_INTS else float(v)))
                       for k, v in r.items() if v != ""}
            except (TypeError, ValueError):
                raise FormatError(f"{path}:{lineno}: malformed row") from None
            if not {"i", "j", "status"} <= set(row):
                raise FormatError(f"{path}:{lineno}: a row needs i, j and status")
            out.append(row)
    return out


# ----------------------------------------------------------------------------------
# Keyframe observations (observations.csv)
# ----------------------------------------------------------------------------------
#: columns of ``observations.csv``: one row per sighting of a landmark in a frame
OBSERVATION_COLUMNS = ("landmark", "frame", "x", "y", "z", "sigma")


def write_observations(path: Path, table: NDArray[np.float64]) -> None:
    """Write ``observations.csv`` from an (K, 6) array in :data:`OBSERVATION_COLUMNS` order."""
    with atomic_write(path) as fh:
        fh.write(",".join(OBSERVATION_COLUMNS) + "\n")
        for lm, fr, x, y, z, s in np.asarray(table, dtype=np.float64).tolist():
            fh.write(f"{int(lm)},{int(fr)},{x!r},{y!r},{z!r},{s!r}\n")


def read_observations(path: Path) -> NDArray[np.float64]:
    """Read ``observations.csv`` into an (K, 6) array (:data:`OBSERVATION_COLUMNS`); every
    value finite, ``z`` and ``sigma`` positive, ``landmark`` and ``frame`` integers, no frame
    seeing a landmark twice."""
    path = Path(path)
    if not path.is_file():
        raise FormatError(f"missing observation table {path}")
    with open(path, newline="") as fh:
        header = fh.readline().strip()
        if tuple(header.split(",")) != OBSERVATION_COLUMNS:
            raise FormatError(f"{path}: header must be {','.join(OBSERVATION_COLUMNS)}")
        body = fh.read()
    if not body.strip():  # no sightings (loadtxt would warn on an empty body)
        return np.zeros((0, 6))
    try:
        table = np.loadtxt(io.StringIO(body), delimiter=",", ndmin=2, dtype=np.float64)
    except ValueError as exc:
        raise FormatError(f"{path}: malformed row ({' '.join(str(exc).split())[:120]})") from None
    if table.shape[1] != 6:
        raise FormatError(f"{path}: rows must have {len(OBSERVATION_COLUMNS)} values, got {table.shape[1]}")
    bad = ~np.isfinite(table).all(axis=1) | (table[:, 4] <= 0) | (table[:, 5] <= 0) \
        | (table[:, :2] != np.round(table[:, :2])).any(axis=1)
    if bad.any():
        raise FormatError(f"{path}:{int(np.flatnonzero(bad)[0]) + 2}: non-finite value, non-positive z or sigma, "
                          "or a non-integer landmark or frame")
    if len(np.unique(table[:, :2], axis=0)) != len(table):
        raise FormatError(f"{path}: a frame sees the same landmark twice")
    return table
