"""Solving a factor graph: batch Levenberg-Marquardt, incremental ISAM2, the determinacy
check and marginal covariances."""

from __future__ import annotations

import sys

import gtsam
import numpy as np
from numpy.typing import NDArray
from tqdm import tqdm

from ctcvo.data import geometry as geo
from ctcvo.posegraph.edges import GraphError
from ctcvo.posegraph.factors import gtsam_error, prior_factor

# LM stops when the cost's relative decrease is below this: the robust kernel makes the last
# iterations converge linearly, and 1e-6 ends far inside one standard deviation of the optimum
# with 6 iterations instead of 9-10 at 1e-10 (bench/README.md, "Pose graph"); no absolute stop.
# GTSAM's default multifrontal Cholesky with COLAMD ordering measured fastest there.
LM_MAX_ITERATIONS = 100
LM_RELATIVE_ERROR_TOL = 1e-6
LM_ABSOLUTE_ERROR_TOL = 0.0
# ISAM2 relinearisation threshold (tangent-vector norm) and extra updates after the last frame:
# more updates or a zero threshold did not lower the cost (synthetic/tiny, bench/README.md "Online mode")
ISAM2_RELINEARIZE_THRESHOLD = 0.01
ISAM2_FINAL_UPDATES = 5


def isam2() -> gtsam.ISAM2:
    """An empty ISAM2 that relinearises at every update above ``ISAM2_RELINEARIZE_THRESHOLD``."""
    params = gtsam.ISAM2Params()
    params.setRelinearizeThreshold(ISAM2_RELINEARIZE_THRESHOLD)
    params.relinearizeSkip = 1
    return gtsam.ISAM2(params)


def run_lm(graph, values, relative_tol: float | None = None, max_iterations: int = LM_MAX_ITERATIONS):
    """(result values, iterations) of batch Levenberg-Marquardt from ``values``, stopping once
    an iteration lowers the error by less than ``relative_tol`` of it (None:
    ``LM_RELATIVE_ERROR_TOL``) or after ``max_iterations``."""
    params = gtsam.LevenbergMarquardtParams()
    params.setMaxIterations(max_iterations)
    params.setRelativeErrorTol(LM_RELATIVE_ERROR_TOL if relative_tol is None else relative_tol)
    params.setAbsoluteErrorTol(LM_ABSOLUTE_ERROR_TOL)
    try:
        opt = gtsam.LevenbergMarquardtOptimizer(graph, values, params)
        result = opt.optimize()
    except RuntimeError as exc:
        raise gtsam_error(exc) from None
    return result, int(opt.iterations())


def check_determinate(graph, values) -> None:
    """Raise :class:`GraphError` when the undamped linear system at ``values`` is singular."""
    try:
        graph.linearize(values).eliminateMultifrontal()
    except RuntimeError as exc:
        raise gtsam_error(exc) from None




class _Incremental:
    """The frame-by-frame state of :func:`run_isam2`."""

    def __init__(self, frame_ids: NDArray[np.int64], pos: NDArray[np.int64], T_meas: NDArray[np.float64],
                 factors: list) -> None:
        self.frame_ids, self.pos, self.T_meas, self.factors = frame_ids, pos, T_meas, factors
        gap = np.abs(pos[:, 1] - pos[:, 0])
        self.adj: list[list[int]] = [[] for _ in frame_ids]  # per frame: its edges, shortest gap first
        for n, (p, q) in enumerate(pos.tolist()):
            self.adj[p].append(n)
            self.adj[q].append(n)
        for lst in self.adj:
            lst.sort(key=lambda n: gap[n])
        self.inserted = np.zeros(len(frame_ids), bool)
        self.added = np.zeros(len(pos), bool)
        self.pending: list[int] = []
        self.est: dict[int, NDArray[np.float64]] = {}

    def _anchor(self, q: int) -> NDArray[np.float64] | None:
        """The predicted pose of frame position ``q`` through its shortest edge to an inserted frame."""
        pos, T_meas = self.pos, self.T_meas
        for n in self.adj[q]:
            other = pos[n, 1] if pos[n, 0] == q else pos[n, 0]
            if self.inserted[other]:
                T_anchor_q = T_meas[n] if pos[n, 0] == other else geo.inv_T(T_meas[n])
                return self.est[int(other)] @ T_anchor_q
        return None

    def insert_pending(self, graph, values) -> None:
        """Insert pending frames that now have an edge to the graph, with their edges."""
        grew = True
        while grew:
            grew = False
            for q in list(self.pending):
                T0 = self._anchor(q)
                if T0 is None:
                    continue
                values.insert(int(self.frame_ids[q]), geo.to_gtsam_pose3(T0))
                self.inserted[q], self.est[q] = True, T0
                self.pending.remove(q)
                grew = True
                for n in self.adj[q]:
                    if not self.added[n] and self.inserted[self.pos[n, 0]] and self.inserted[self.pos[n, 1]]:
                        graph.add(self.factors[n])
                        self.added[n] = True


def run_isam2(frame_ids: NDArray[np.int64], pos: NDArray[np.int64], T_meas: NDArray[np.float64], factors: list,
              initial: NDArray[np.float64]):
    """(result values, updates) of an incremental solve: frames enter in id order; a frame's
    edges to frames already in the graph are added with it (a frame with none waits until it
    is connected). ``pos`` (E, 2) positions, ``T_meas`` (E, 4, 4) and ``factors`` describe the
    edges; ``initial`` (N, 4, 4) gives the first pose."""
    isam = isam2()
    inc = _Incremental(frame_ids, pos, T_meas, factors)
    steps = 0
    bar = tqdm(total=len(frame_ids), desc="isam2", unit="pose", disable=not sys.stderr.isatty(), leave=False)
    try:
        for p in range(len(frame_ids)):
            graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
            if p == 0:
                graph.add(prior_factor(frame_ids[0], initial[0]))
                values.insert(int(frame_ids[0]), geo.to_gtsam_pose3(initial[0]))
                inc.inserted[0] = True
                inc.est[0] = initial[0]
            else:
                inc.pending.append(p)
            inc.insert_pending(graph, values)
            if values.size() or graph.size():
                isam.update(graph, values)
                steps += 1
                # refresh the estimates of the newest frames (cheap, used as anchors)
                for q in np.flatnonzero(inc.inserted)[-8:]:
                    inc.est[int(q)] = geo.from_gtsam_pose3(isam.calculateEstimatePose3(int(frame_ids[q])))
            bar.update(1)
        for _ in range(ISAM2_FINAL_UPDATES):  # extra relinearisation passes at the end
            isam.update()
        result = isam.calculateEstimate()
    except RuntimeError as exc:
        raise gtsam_error(exc) from None
    finally:
        bar.close()
    if not inc.inserted.all() or not inc.added.all():
        raise GraphError("ISAM2: some frames never connected to the graph")
    return result, steps


def marginal_covariances(graph, result, frame_ids: NDArray[np.int64]) -> NDArray[np.float64]:
    """(N, 6, 6) marginal covariance of every pose, project order (v, w), right perturbation."""
    try:
        m = gtsam.Marginals(graph, result)
        return np.stack([geo.cov_from_gtsam(m.marginalCovariance(int(k))) for k in frame_ids])
    except RuntimeError as exc:
        raise gtsam_error(exc) from None
