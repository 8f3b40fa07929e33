"""The pose-graph solve: frame ids, edges and initial poses in, a :class:`SolveResult` out.

:func:`solve` validates the edges, solves the robust graph (batch LM or ISAM2,
:mod:`posegraph.solvers`), calibrates one covariance scale per edge source and rejects
outlier edges (:mod:`posegraph.robust`), re-solving warm-started after each. Edge arrays,
connectivity and bridges are in :mod:`posegraph.edges`, GTSAM factors in
:mod:`posegraph.factors`; loading files and writing reports in :mod:`posegraph.sources`
and :mod:`posegraph.optimize`.
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Sequence
from dataclasses import dataclass, field

import gtsam
import numpy as np
from numpy.typing import NDArray

from ctcvo.data import geometry as geo
from ctcvo.data.formats import Edge
from ctcvo.posegraph.bundle import bundle_solve
from ctcvo.posegraph.config import DEFAULT, PoseGraphConfig
from ctcvo.posegraph.edges import (
    EdgeArrays,
    GraphError,
    chain_poses,
    check_connected,
    edge_arrays,
    edge_residuals,
    validate_edges,
)
from ctcvo.posegraph.factors import between_factors, pose3s, poses_from_values, prior_factor, values_of
from ctcvo.posegraph.robust import (
    CALIBRATION_ITERATIONS,
    CALIBRATION_SCALE_RANGE,
    CALIBRATION_TOLERANCE,
    DOWNWEIGHT_FACTOR,
    outlier_masks,
    source_scale_factors,
)
from ctcvo.posegraph.solvers import check_determinate, marginal_covariances, run_isam2, run_lm

log = logging.getLogger(__name__)


@dataclass
class OutlierRecord:
    """An edge the outlier stage removed or down-weighted."""

    i: int
    j: int
    source: str
    reason: str
    """``residual``: its whitened residual after the first solve exceeded the threshold."""
    value: float
    """That whitened residual norm."""
    action: str
    """``removed`` or ``downweighted``."""

    def to_dict(self) -> dict:
        return {"i": self.i, "j": self.j, "source": self.source, "reason": self.reason,
                "value": float(self.value), "action": self.action}


@dataclass
class SolveResult:
    """Optimised poses and diagnostics."""

    frame_ids: NDArray[np.int64]
    """(N,) sorted frame ids (the graph keys)."""
    poses: NDArray[np.float64]
    """(N, 4, 4) optimised ``T_world_cam``."""
    outliers: list[OutlierRecord]
    residuals: NDArray[np.float64]
    """(E,) whitened residual norm of every input edge at the final solution (no kernel)."""
    used: NDArray[np.bool_]
    """(E,) whether the edge is in the final graph (removed outliers are not)."""
    initial_error: float
    final_error: float
    solver: str
    iterations: int
    time_s: float
    marginals: NDArray[np.float64] | None = None
    """(N, 6, 6) marginal covariances in project order (v, w), right perturbation."""
    first_residuals: NDArray[np.float64] | None = field(default=None, repr=False)
    """(E,) whitened residual norms after the first solve (before outlier handling)."""
    cpu_s: float = 0.0
    """Process CPU time of the solve (s); ``time_s`` is wall-clock."""
    source_scales: dict[str, float] = field(default_factory=dict)
    """Covariance scale applied to each edge source (1.0 without calibration)."""
    calibration: dict | None = None
    """Per-source covariance calibration from residuals (see :func:`_calibrate`)."""
    bundle: dict | None = None
    """The bundle adjustment's landmarks, sightings, iterations and seconds
    (:func:`posegraph.bundle.bundle_solve`); None without observations."""



class _Problem:
    """One graph's edges, converted once, solved repeatedly with different masks and
    covariance scales (first solve, calibration, outlier pass)."""

    def __init__(self, frame_ids: NDArray[np.int64], a: EdgeArrays, initial: NDArray[np.float64],
                 cfg: PoseGraphConfig, label: str = "") -> None:
        self.frame_ids, self.a, self.cfg = frame_ids, a, cfg
        self.tag = f"{label}: " if label else ""
        """Prefix of this graph's log lines (which of a run's graphs they are about)."""
        self.T = geo.orthonormalize(a.T)
        self.measured = pose3s(self.T)  # the one per-edge conversion
        self.prior = prior_factor(frame_ids[0], initial[0])
        self.info = np.linalg.inv(a.cov) if len(a.cov) else np.zeros((0, 6, 6))
        """(E, 6, 6) inverse covariances, project order."""
        self._base: list = [None] * len(a.ids)  # factors with the given covariances, built on demand

    def factors(self, scale: NDArray[np.float64]) -> list:
        """(E,) factors with covariances ``cov * scale[:, None, None]``, (E,) ``scale``; edges
        at scale 1 share their factor objects between calls (built once)."""
        one = scale == 1.0
        miss = np.flatnonzero(one & np.array([f is None for f in self._base], dtype=bool))
        for n, f in zip(miss.tolist(), self._make(miss, self.a.cov[miss])):
            self._base[n] = f
        out = list(self._base)
        other = np.flatnonzero(~one)
        for n, f in zip(other.tolist(), self._make(other, self.a.cov[other] * scale[other, None, None])):
            out[n] = f
        return out

    def _make(self, idx: NDArray[np.int64], covs: NDArray[np.float64]) -> list:
        return between_factors(self.a.ids[idx], [self.measured[n] for n in idx.tolist()], covs, self.cfg.kernel)

    def solve(self, use: NDArray[np.bool_], scale: NDArray[np.float64], start):
        """(graph, start values, result values, iterations); ``start`` is a ``gtsam.Values``
        or (N, 4, 4) poses."""
        facs = self.factors(scale)
        sel = np.flatnonzero(use)
        graph = gtsam.NonlinearFactorGraph()
        graph.add(self.prior)
        for n in sel.tolist():
            graph.add(facs[n])
        values = start if isinstance(start, gtsam.Values) else values_of(self.frame_ids, start)
        if self.cfg.solver == "lm":
            result, iters = run_lm(graph, values)
        else:
            poses = poses_from_values(self.frame_ids, values)
            result, iters = run_isam2(self.frame_ids, self.a.pos[sel], self.T[sel], [facs[n] for n in sel.tolist()],
                                      poses)
        return graph, values, result, iters

    def residuals(self, poses: NDArray[np.float64], scale: NDArray[np.float64]) -> NDArray[np.float64]:
        """(E,) whitened residual norms of every edge at ``poses`` under ``cov * scale``."""
        return edge_residuals(poses, self.a.pos, self.T, self.info / scale[:, None, None])


@dataclass
class _State:
    """The current solution of a :func:`solve` and the masks and scales it was solved with."""

    graph: object
    result: object
    poses: NDArray[np.float64]
    iterations: int
    src: NDArray[np.int64]
    """(E,) source index of every edge."""
    src_scale: NDArray[np.float64]
    """Covariance scale of every source."""
    drop: NDArray[np.bool_]
    weak: NDArray[np.bool_]

    def edge_scale(self) -> NDArray[np.float64]:
        """(E,) covariance scale of every edge: its source's, down-weighted edges inflated."""
        return self.src_scale[self.src] * np.where(self.weak, DOWNWEIGHT_FACTOR, 1.0)

    def resolve(self, prob: _Problem) -> None:
        """Solve again under the current masks and scales, warm-started from the current result."""
        self.graph, _, self.result, n = prob.solve(~self.drop, self.edge_scale(), self.result)
        self.iterations += n
        self.poses = poses_from_values(prob.frame_ids, self.result)


def _prepare(frame_ids: NDArray[np.int64], edges: Sequence[Edge],
             initial: NDArray[np.float64] | None) -> tuple[NDArray[np.int64], list[Edge], EdgeArrays, NDArray[np.float64]]:
    """Sorted frame ids, the edges, their arrays and the initial poses, validated."""
    frame_ids = np.asarray(frame_ids, dtype=np.int64)
    order = np.argsort(frame_ids, kind="stable")
    frame_ids = frame_ids[order]
    if len(np.unique(frame_ids)) != len(frame_ids):
        raise GraphError("duplicate frame ids")
    edges = list(edges)
    a = edge_arrays(frame_ids, edges)
    validate_edges(frame_ids, edges, a)
    check_connected(frame_ids, edges, a)
    if initial is None:
        initial = chain_poses(frame_ids, edges)
    else:
        initial = np.asarray(initial, dtype=np.float64)[order]
        if initial.shape != (len(frame_ids), 4, 4) or not np.all(np.isfinite(initial)):
            raise GraphError(f"initial poses must be finite with shape ({len(frame_ids)}, 4, 4)")
    return frame_ids, edges, a, initial


def _calibrate(prob: _Problem, st: _State, names: list[str], fixed_sources: Sequence[str]) -> dict:
    """Per-source covariance scales from the whitened residuals, re-solving (warm-started)
    until they settle; updates ``st`` and returns the calibration record."""
    n_frames, n_edges = len(prob.frame_ids), len(st.src)
    calib = {"sources": {}, "iterations": 0, "converged": False,
             "redundancy": 1.0 - (n_frames - 1) / max(n_edges, 1)}
    for it in range(CALIBRATION_ITERATIONS + 1):
        factor, counts = source_scale_factors(prob.residuals(st.poses, st.src_scale[st.src]), st.src, len(names),
                                              calib["redundancy"])
        factor[[k for k, n in enumerate(names) if n in fixed_sources]] = 1.0
        new = np.clip(st.src_scale * factor, *CALIBRATION_SCALE_RANGE)
        calib["sources"] = {n: {"edges": int(counts[k]), "scale": float(st.src_scale[k]),
                                "residual_factor": float(factor[k])} for k, n in enumerate(names)}
        if np.all(np.abs(np.log(new / st.src_scale)) <= math.log1p(CALIBRATION_TOLERANCE)):
            calib["converged"] = True
            break
        if it == CALIBRATION_ITERATIONS:
            break
        st.src_scale = new
        calib["iterations"] += 1
        log.info("%scovariance scales %s; re-solving", prob.tag, ", ".join(f"{n} {v:.3g}" for n, v in zip(names, new)))
        st.resolve(prob)
    calib["sources"] = {n: {**v, "scale": float(st.src_scale[k])} for k, (n, v) in enumerate(calib["sources"].items())}
    return calib


def _reject_outliers(prob: _Problem, st: _State, first_res: NDArray[np.float64]) -> NDArray[np.bool_]:
    """Flag edges whose whitened residual (under the calibrated covariances) after the first
    solve exceeds ``cfg.residual_threshold`` and re-solve without them; (E,) flags."""
    flagged = np.zeros(len(st.src), bool)
    if not math.isfinite(prob.cfg.residual_threshold):
        return flagged
    flagged = first_res > prob.cfg.residual_threshold
    if flagged.any():
        st.drop, st.weak = outlier_masks(len(prob.frame_ids), prob.a.pos, flagged, np.argsort(first_res))
        log.info("%sre-solving without %d outlier edge(s)", prob.tag, int(flagged.sum()))
        st.resolve(prob)  # warm start from the first solution (the prior stays on the first frame)
    return flagged


def solve(frame_ids: NDArray[np.int64], edges: Sequence[Edge], initial: NDArray[np.float64] | None = None,
          cfg: PoseGraphConfig = DEFAULT, fixed_sources: Sequence[str] = (), label: str = "",
          observations: NDArray[np.float64] | None = None) -> SolveResult:
    """Optimise the pose graph.

    Args:
        frame_ids: (N,) frame ids (sorted here); the first is fixed by a prior.
        edges: relative-pose edges; ``edge.extra["source"]`` names their origin.
        initial: (N, 4, 4) initial ``T_world_cam`` (default: :func:`chain_poses`).
        cfg: solver, kernel and outlier settings.
        fixed_sources: sources whose covariances were already calibrated on validation
            data (or deliberately set): they keep scale 1 in the per-source calibration.
        label: which graph this is, at the start of its log lines (a run that solves two
            graphs, such as ``posegraph optimize``'s fused and teacher-only ones).
        observations: (K, 6) landmark sightings (``observations.csv``), solved
            jointly with the final graph (:mod:`posegraph.bundle`; batch LM only).

    Steps: validate; first (robust) solve; with ``cfg.calibrate``, estimate one covariance
    scale per source from the whitened residuals and re-solve (warm-started) until the
    scales settle; reject edges whose whitened residual under the calibrated covariances
    exceeds ``cfg.residual_threshold`` and solve again (warm-started) if any were; with
    observations, the bundle adjustment; check the final linear system is determinate;
    optional marginals. Raises
    :class:`GraphError` on bad input.
    """
    t0, c0 = time.perf_counter(), time.process_time()
    frame_ids, edges, a, initial = _prepare(frame_ids, edges, initial)
    prob = _Problem(frame_ids, a, initial, cfg, label)
    names = list(dict.fromkeys(a.source))
    index = {n: k for k, n in enumerate(names)}
    none = np.zeros(len(edges), bool)
    st = _State(None, None, initial, 0, np.array([index[x] for x in a.source], dtype=np.int64), np.ones(len(names)),
                none, none)
    st.graph, values0, st.result, st.iterations = prob.solve(~st.drop, st.edge_scale(), initial)
    initial_error = float(st.graph.error(values0))
    st.poses = poses_from_values(frame_ids, st.result)
    calib = _calibrate(prob, st, names, fixed_sources) if cfg.calibrate else None
    first_res = prob.residuals(st.poses, st.src_scale[st.src])
    flagged = _reject_outliers(prob, st, first_res)
    final_res = prob.residuals(st.poses, st.src_scale[st.src]) if flagged.any() else first_res
    outliers = [OutlierRecord(int(a.ids[n, 0]), int(a.ids[n, 1]), a.source[n], "residual", float(first_res[n]),
                              "removed" if st.drop[n] else "downweighted") for n in np.flatnonzero(flagged).tolist()]
    if not cfg.marginals:  # the edges' graph: sightings (3 each, stereo) leave no pose less determinate
        check_determinate(st.graph, st.result)
    bundle = None
    if observations is not None and len(observations) and cfg.solver != "lm":
        log.info("%s%d landmark sightings left out: the bundle adjustment runs with the batch LM solver only",
                 prob.tag, len(observations))
    elif observations is not None and len(observations):
        st.graph, st.result, bundle = bundle_solve(st.graph, st.result, observations, frame_ids, st.poses)
        st.poses = poses_from_values(frame_ids, st.result)
        final_res = prob.residuals(st.poses, st.src_scale[st.src])
    marg = None
    if cfg.marginals:  # factorises the undamped system: also the determinacy check
        marg = marginal_covariances(st.graph, st.result, frame_ids)
    res = SolveResult(
        frame_ids=frame_ids, poses=st.poses, outliers=outliers, residuals=final_res, used=~st.drop,
        initial_error=initial_error, final_error=float(st.graph.error(st.result)),
        solver=cfg.solver, iterations=st.iterations, time_s=time.perf_counter() - t0, marginals=marg,
        first_residuals=first_res, cpu_s=time.process_time() - c0,
        source_scales={n: float(v) for n, v in zip(names, st.src_scale)}, calibration=calib, bundle=bundle,
    )
    log.info("%s%s: %d poses, %d edges (%d outliers), error %.4g -> %.4g in %.2f s", prob.tag, cfg.solver,
             len(frame_ids), len(edges), len(outliers), res.initial_error, res.final_error, res.time_s)
    return res


__all__ = ["OutlierRecord", "SolveResult", "solve"]
