"""Synthetic pose graphs with known answers (tests, benchmark, examples).

Edges are sampled exactly as the covariance convention says: ``T_meas = T_true @
exp(-delta)`` with ``delta ~ N(0, C)`` in project order (v, w), so that
``T_true = T_meas @ exp(delta)`` (right perturbation).
"""

from __future__ import annotations

from collections.abc import Iterable
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from ctcvo.data import geometry as geo
from ctcvo.data.chain import chain_steps
from ctcvo.data.formats import Edge, Trajectory, write_edges_csv, write_g2o, write_tum


def helix(n: int, radius: float = 1.0, turns: float = 1.0, rise: float = 0.5) -> NDArray[np.float64]:
    """(n, 4, 4) ``T_world_cam`` on a helix, camera yawing with the path."""
    out = np.empty((n, 4, 4))
    for k in range(n):
        a = 2 * np.pi * turns * k / max(n, 1)
        R = geo.se3_exp([0, 0, 0, 0, a, 0.1 * np.sin(3 * a)])[:3, :3]
        out[k] = geo.make_T(R, [radius * np.cos(a), rise * k / max(n, 1), radius * np.sin(a)])
    return out


def diag_cov(sigma_t: float, sigma_r: float) -> NDArray[np.float64]:
    """6x6 diagonal covariance, project order (v, w)."""
    return np.diag([sigma_t**2] * 3 + [sigma_r**2] * 3)


def sample_edge(T_true: NDArray[np.float64], cov: NDArray[np.float64], rng: np.random.Generator) -> NDArray[np.float64]:
    """A measurement of ``T_true`` with right-perturbation noise of covariance ``cov``."""
    delta = rng.multivariate_normal(np.zeros(6), cov)
    return T_true @ geo.se3_exp(-delta)


def make_edges(gt: NDArray[np.float64], gaps: Iterable[int], cov: NDArray[np.float64],
               rng: np.random.Generator | None = None, source: str = "edges",
               ids: NDArray[np.int64] | None = None) -> list[Edge]:
    """Edges ``k -> k + g`` for every gap ``g`` from ground truth (N, 4, 4); noisy when
    ``rng`` is given (noise from ``cov``), exact otherwise."""
    ids = np.arange(len(gt)) if ids is None else ids
    out = []
    for g in gaps:
        for k in range(len(gt) - g):
            T = geo.relative_pose(gt[k], gt[k + g])
            if rng is not None:
                T = sample_edge(T, cov, rng)
            out.append(Edge(int(ids[k]), int(ids[k + g]), T, cov.copy(), {"source": source}))
    return out


def chain_trajectory(edges: list[Edge], n: int) -> NDArray[np.float64]:
    """Dead-reckoned (n, 4, 4) poses from the gap-1 edges ``k -> k+1`` (positions 0..n-1)."""
    step = {e.i: e.T_i_j for e in edges if e.j == e.i + 1}
    return chain_steps([step[k] for k in range(n - 1)])


def write_source_dir(path: Path, gt: NDArray[np.float64], edges: list[Edge], times: NDArray[np.float64],
                     with_gt: bool = True) -> Path:
    """A teacher-like folder: edges.g2o, edges.csv, trajectory.tum (chained gap-1) and
    groundtruth.tum (optional). Frame ids are 0..N-1."""
    path = Path(path)
    write_g2o(path / "edges.g2o", edges)
    rows = [{"i": e.i, "j": e.j, "t_i": float(times[e.i]), "t_j": float(times[e.j]), "status": "ok"} for e in edges]
    write_edges_csv(path / "edges.csv", rows)
    write_tum(path / "trajectory.tum", Trajectory(times, chain_trajectory(edges, len(gt))))
    if with_gt:
        write_tum(path / "groundtruth.tum", Trajectory(times, gt))
    return path
