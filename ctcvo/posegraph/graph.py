"""Factor graph from relative-pose edges, solved with GTSAM (batch LM or ISAM2).

Conventions (see docs/conventions.md): an :class:`~data.formats.Edge` carries
``T_i_j`` and a 6x6 covariance in the project tangent order (v, w), right perturbation
at the measurement. GTSAM's ``BetweenFactorPose3`` uses the same right perturbation with
rotation first, so the covariance is only re-ordered, with
:func:`data.geometry.cov_to_gtsam`. Variable keys are the frame ids themselves.

The pure entry point is :func:`solve`: frame ids, edges and initial poses in, a
:class:`SolveResult` out. Loading files and writing reports live in
:mod:`posegraph.sources` and :mod:`posegraph.optimize`.
"""

from __future__ import annotations

import logging
import math
import sys
import time
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray
from tqdm import tqdm

from ctcvo.data import geometry as geo
from ctcvo.data import uncertainty
from ctcvo.data.chain import UnionFind, chain_edges
from ctcvo.data.errors import VOError
from ctcvo.data.formats import Edge
from ctcvo.posegraph.config import DEFAULT, PoseGraphConfig

log = logging.getLogger(__name__)


class GraphError(VOError):
    """The pose graph cannot be built or solved (disconnected, indeterminant, bad edge)."""


@dataclass
class OutlierRecord:
    """An edge the outlier stage removed or down-weighted."""

    i: int
    j: int
    source: str
    reason: str
    """``covariance`` (a sigma above the threshold) or ``residual`` (whitened residual)."""
    value: float
    """The offending figure: sigma (m or deg) or whitened residual norm."""
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
    """Per-source covariance calibration from residuals (see :func:`calibrate_sources`)."""


# ----------------------------------------------------------------------------------
# validation and graph structure
# ----------------------------------------------------------------------------------
@dataclass
class EdgeArrays:
    """The edges as arrays (one Python pass over the Edge objects, then vectorised work)."""

    ids: NDArray[np.int64]
    """(E, 2) frame ids ``(i, j)``."""
    pos: NDArray[np.int64]
    """(E, 2) positions of ``i`` and ``j`` in the sorted frame ids (-1 for unknown ids)."""
    T: NDArray[np.float64]
    """(E, 4, 4) measured ``T_i_j``."""
    cov: NDArray[np.float64]
    """(E, 6, 6) covariances, project order (v, w)."""
    source: list[str]
    """(E,) ``edge.extra["source"]`` (``"edges"`` when absent)."""

    @property
    def gap(self) -> NDArray[np.int64]:
        """(E,) frame gap ``|pos_j - pos_i|`` in positions."""
        return np.abs(self.pos[:, 1] - self.pos[:, 0])


def edge_arrays(frame_ids: NDArray[np.int64], edges: Sequence[Edge]) -> EdgeArrays:
    """Stack ``edges`` into :class:`EdgeArrays` (``frame_ids`` sorted)."""
    frame_ids = np.asarray(frame_ids, dtype=np.int64)
    if not edges:
        return EdgeArrays(np.zeros((0, 2), np.int64), np.zeros((0, 2), np.int64), np.zeros((0, 4, 4)),
                          np.zeros((0, 6, 6)), [])
    ids = np.array([(e.i, e.j) for e in edges], dtype=np.int64)
    try:
        T = np.array([e.T_i_j for e in edges], dtype=np.float64).reshape(len(edges), 4, 4)
        cov = np.array([e.cov for e in edges], dtype=np.float64).reshape(len(edges), 6, 6)
    except ValueError:
        bad = next(n for n, e in enumerate(edges) if np.size(e.T_i_j) != 16 or np.size(e.cov) != 36)
        raise GraphError(f"edge {edges[bad].i}->{edges[bad].j}: needs a 4x4 pose and a 6x6 covariance") from None
    pos = np.searchsorted(frame_ids, ids)
    pos_c = np.minimum(pos, len(frame_ids) - 1)
    pos = np.where(frame_ids[pos_c] == ids, pos_c, -1)
    return EdgeArrays(ids, pos, T, cov, [str(e.extra.get("source", "edges")) for e in edges])


def validate_edges(frame_ids: NDArray[np.int64], edges: Sequence[Edge],
                   arrays: EdgeArrays | None = None) -> None:
    """Raise :class:`GraphError` for edges on unknown frames, bad covariances or poses
    (vectorised: 50k edges validate in about 0.1 s). ``frame_ids`` need not be sorted."""
    frame_ids = np.sort(np.asarray(frame_ids, dtype=np.int64))
    if len(frame_ids) < 2:
        raise GraphError(f"a pose graph needs at least two frames, got {len(frame_ids)}")
    if np.any(frame_ids < 0):
        raise GraphError("frame ids must be non-negative")
    if not edges:
        return
    a = arrays if arrays is not None else edge_arrays(frame_ids, edges)
    lo, hi = int(frame_ids.min()), int(frame_ids.max())

    def fail(n: int, why: str) -> None:
        e = edges[int(n)]
        raise GraphError(f"edge {e.i}->{e.j} ({e.extra.get('source', 'edges')}): {why}")

    known = a.pos >= 0
    if not known.all():
        n, c = np.argwhere(~known)[0]
        fail(n, f"references frame {a.ids[n, c]}, which does not exist ({len(frame_ids)} frames, ids {lo}..{hi})")
    same = np.flatnonzero(a.ids[:, 0] == a.ids[:, 1])
    if len(same):
        fail(same[0], "connects a frame to itself")
    covs, Ts = a.cov, a.T
    bad = ~np.isfinite(covs).all(axis=(1, 2))
    if bad.any():
        fail(np.flatnonzero(bad)[0], "covariance must be a finite 6x6 matrix")
    covT = covs.transpose(0, 2, 1)
    sym = (np.abs(covs - covT) <= 1e-12 + 1e-6 * np.abs(covT)).all(axis=(1, 2))
    pd = np.linalg.eigvalsh(0.5 * (covs + covT))[:, 0] > 0
    if not (sym & pd).all():
        fail(np.flatnonzero(~(sym & pd))[0], "covariance is not symmetric positive definite")
    with np.errstate(invalid="ignore"):
        finite = np.isfinite(Ts).all(axis=(1, 2))
        R = np.where(finite[:, None, None], Ts[:, :3, :3], 0.0)
        rigid = (finite
                 & (np.abs(R.transpose(0, 2, 1) @ R - np.eye(3)) <= 1e-4).all(axis=(1, 2))
                 & (np.abs(np.linalg.det(R) - 1.0) < 1e-4)
                 & (np.abs(Ts[:, 3] - [0, 0, 0, 1]) <= 1e-4).all(axis=1))
    if not rigid.all():
        fail(np.flatnonzero(~rigid)[0], "relative pose is not a finite rigid transform")


def _pose3s(Ts: NDArray[np.float64]) -> list:
    """``gtsam.Pose3`` objects of (N, 4, 4) transforms (orthonormalised first)."""
    import gtsam

    return [gtsam.Pose3(T) for T in geo.orthonormalize(Ts)]


def _covs_gtsam(covs: NDArray[np.float64]) -> NDArray[np.float64]:
    """(E, 6, 6) covariances re-ordered to GTSAM's (w, v) with the conversion module's
    vector permutation applied to rows and columns (batched cov_to_gtsam)."""
    c = np.asarray(covs, dtype=np.float64).reshape(-1, 6, 6)
    c = geo.vec_to_gtsam(geo.vec_to_gtsam(c).transpose(0, 2, 1))
    return 0.5 * (c + c.transpose(0, 2, 1))


def edge_residuals(poses: NDArray[np.float64], pos: NDArray[np.int64], T_meas: NDArray[np.float64],
                   info: NDArray[np.float64]) -> NDArray[np.float64]:
    """(E,) whitened residual norms ``sqrt(d^T C^-1 d)`` with ``d = log(inv(T_meas) @
    inv(T_i) @ T_j)`` (right perturbation at the measurement, project order).

    Args:
        poses: (N, 4, 4) ``T_world_cam``.
        pos: (E, 2) positions of the edges' frames in ``poses``.
        T_meas: (E, 4, 4) measured relative poses.
        info: (E, 6, 6) inverse covariances, project order.
    """
    if len(pos) == 0:
        return np.zeros(0)
    Pi, Pj = poses[pos[:, 0]], poses[pos[:, 1]]
    Ri_t = Pi[:, :3, :3].transpose(0, 2, 1)
    Mi_t = T_meas[:, :3, :3].transpose(0, 2, 1)
    R_rel = Ri_t @ Pj[:, :3, :3]
    t_rel = np.einsum("nij,nj->ni", Ri_t, Pj[:, :3, 3] - Pi[:, :3, 3])
    D = np.zeros((len(pos), 4, 4))
    D[:, :3, :3] = Mi_t @ R_rel
    D[:, :3, 3] = np.einsum("nij,nj->ni", Mi_t, t_rel - T_meas[:, :3, 3])
    D[:, 3, 3] = 1.0
    d = geo.se3_log(D)
    return np.sqrt(np.maximum(np.einsum("ni,nij,nj->n", d, info, d), 0.0))


def _component_labels(n: int, pos: NDArray[np.int64]) -> NDArray[np.int64]:
    """(n,) connected-component label of every frame position (scipy, vectorised)."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    adj = coo_matrix((np.ones(len(pos)), (pos[:, 0], pos[:, 1])), shape=(n, n))
    return connected_components(adj, directed=False)[1]


def component_labels(frame_ids: NDArray[np.int64], edges: Sequence[Edge]) -> NDArray[np.int64]:
    """(N,) connected-component label of every frame of the sorted ``frame_ids``."""
    return _component_labels(len(frame_ids), edge_arrays(np.asarray(frame_ids, dtype=np.int64), edges).pos)


def components(frame_ids: NDArray[np.int64], edges: Sequence[Edge]) -> list[list[int]]:
    """Connected components (lists of frame ids, sorted by first id); ``frame_ids`` sorted."""
    frame_ids = np.asarray(frame_ids, dtype=np.int64)
    labels = _component_labels(len(frame_ids), edge_arrays(frame_ids, edges).pos)
    groups: dict[int, list[int]] = {}
    for lab, k in zip(labels.tolist(), frame_ids.tolist()):
        groups.setdefault(lab, []).append(k)
    return sorted(groups.values(), key=lambda g: g[0])


def check_connected(frame_ids: NDArray[np.int64], edges: Sequence[Edge],
                    arrays: EdgeArrays | None = None) -> None:
    """Raise :class:`GraphError` naming the split when the graph is not connected."""
    frame_ids = np.asarray(frame_ids, dtype=np.int64)
    pos = (arrays if arrays is not None else edge_arrays(frame_ids, edges)).pos
    if len(np.unique(_component_labels(len(frame_ids), pos))) == 1:
        return
    comps = components(frame_ids, edges)
    sizes = ", ".join(f"{c[0]}..{c[-1]} ({len(c)} frames)" for c in comps[:4])
    more = f" and {len(comps) - 4} more" if len(comps) > 4 else ""
    raise GraphError(f"the pose graph is disconnected: {len(comps)} components: {sizes}{more}; "
                     "every frame needs a chain of edges to the first frame")


def chain_poses(frame_ids: NDArray[np.int64], edges: Sequence[Edge],
                T_world_first: NDArray[np.float64] | None = None) -> NDArray[np.float64]:
    """Chain edges into ``T_world_cam`` poses (N, 4, 4) along a spanning tree.

    The tree is the minimum spanning tree by frame gap (Kruskal: smallest gaps first,
    ties in edge order), walked breadth-first from the first frame, so a complete gap-1
    chain is used as is (dead reckoning) and longer edges only bridge missing steps.
    ``frame_ids`` must be sorted. Raises :class:`GraphError` if some frame cannot be reached.
    """
    frame_ids = np.asarray(frame_ids, dtype=np.int64)
    a = edge_arrays(frame_ids, edges)
    if (a.pos < 0).any():
        validate_edges(frame_ids, edges, a)
    chained = chain_edges(frame_ids, a.pos, a.T, T_world_first)
    if not chained.reached.all():
        check_connected(frame_ids, edges, a)
    return chained.poses


def bridge_edges(frame_ids: NDArray[np.int64], edges: Sequence[Edge], poses: NDArray[np.float64] | None,
                 cov: NDArray[np.float64]) -> list[Edge]:
    """Edges that join the components of a disconnected graph, ``[]`` when it is connected.

    Each joins consecutive frames (positions ``p``, ``p + 1`` of the sorted ``frame_ids``)
    that lie in different components, earliest first, until one component is left. The
    measurement is the relative pose of ``poses`` (N, 4, 4) there (a source's chained
    trajectory, e.g. the teacher's constant-velocity bridge over failed edges), or the
    identity (zero motion) without poses; ``cov`` (6, 6) is large, since the bridge is a
    guess. The edges carry ``extra["source"] = "bridge"``."""
    frame_ids = np.asarray(frame_ids, dtype=np.int64)
    labels = _component_labels(len(frame_ids), edge_arrays(frame_ids, edges).pos)
    uf = UnionFind(len(frame_ids))
    first: dict[int, int] = {}
    for p, lab in enumerate(labels.tolist()):
        uf.union(first.setdefault(lab, p), p)
    out = []
    for p in range(len(frame_ids) - 1):
        if uf.union(p, p + 1):
            T = np.eye(4) if poses is None else geo.relative_pose(poses[p], poses[p + 1])
            out.append(Edge(int(frame_ids[p]), int(frame_ids[p + 1]), T, np.array(cov, dtype=np.float64),
                            {"source": "bridge"}))
    return out


def bridge_cov(frame_ids: NDArray[np.int64], edges: Sequence[Edge], factor: float) -> NDArray[np.float64]:
    """(6, 6) diagonal covariance ``factor^2`` times the median diagonal of the
    smallest-gap ``edges`` (a bridge edge's; identity-sized 1e-4 without edges)."""
    if not edges:
        return np.eye(6) * 1e-4 * factor**2
    a = edge_arrays(np.asarray(frame_ids, dtype=np.int64), edges)
    gap = a.gap if (a.pos >= 0).all() else np.ones(len(edges), np.int64)
    d = np.median(np.diagonal(a.cov[gap == gap.min()], axis1=1, axis2=2), axis=0)
    return np.diag(d * factor**2)


def joining_edges(frame_ids: NDArray[np.int64], edges: Sequence[Edge], candidates: Sequence[Edge]) -> list[Edge]:
    """Those of ``candidates`` (taken in order) that join components of the graph of
    ``edges``; ``[]`` when it is connected."""
    frame_ids = np.asarray(frame_ids, dtype=np.int64)
    labels = _component_labels(len(frame_ids), edge_arrays(frame_ids, edges).pos)
    if len(np.unique(labels)) == 1 or not candidates:
        return []
    uf = UnionFind(len(frame_ids))
    first: dict[int, int] = {}
    for p, lab in enumerate(labels.tolist()):
        uf.union(first.setdefault(lab, p), p)
    pos = edge_arrays(frame_ids, candidates).pos
    return [e for e, (p, q) in zip(candidates, pos.tolist()) if uf.union(p, q)]


# ----------------------------------------------------------------------------------
# GTSAM graph
# ----------------------------------------------------------------------------------
def _robust(base, cfg: PoseGraphConfig):
    import gtsam

    if cfg.kernel == "none":
        return base
    est = gtsam.noiseModel.mEstimator
    kernel = est.Huber.Create(cfg.kernel_k) if cfg.kernel == "huber" else est.Cauchy.Create(cfg.kernel_k)
    return gtsam.noiseModel.Robust.Create(kernel, base)


def prior_factor(frame_id: int, T: NDArray[np.float64], cfg: PoseGraphConfig):
    """The prior that fixes frame ``frame_id`` at ``T`` (sigmas ``cfg.prior_sigma_*``)."""
    import gtsam

    sig = np.array([cfg.prior_sigma_rot_rad] * 3 + [cfg.prior_sigma_trans_m] * 3)  # GTSAM order (w, v)
    return gtsam.PriorFactorPose3(int(frame_id), geo.to_gtsam_pose3(T), gtsam.noiseModel.Diagonal.Sigmas(sig))


def between_factors(ids: NDArray[np.int64], measured: Sequence, covs: NDArray[np.float64],
                    cfg: PoseGraphConfig) -> list:
    """One robust ``BetweenFactorPose3`` per edge (``ids`` (E, 2) frame ids, ``measured``
    their ``gtsam.Pose3``, ``covs`` (E, 6, 6) project order); noise models are shared
    between edges with identical covariances."""
    import gtsam

    if len(ids) == 0:
        return []
    cache: dict[bytes, object] = {}
    out = []
    for (i, j), P, c in zip(ids.tolist(), measured, _covs_gtsam(covs)):
        key = c.tobytes()
        model = cache.get(key)
        if model is None:
            model = cache[key] = _robust(gtsam.noiseModel.Gaussian.Covariance(c), cfg)
        out.append(gtsam.BetweenFactorPose3(i, j, P, model))
    return out


def build_graph(frame_ids: NDArray[np.int64], edges: Sequence[Edge], covs: Sequence[NDArray[np.float64]],
                initial: NDArray[np.float64], cfg: PoseGraphConfig = DEFAULT, measured: list | None = None):
    """(``gtsam.NonlinearFactorGraph``, ``gtsam.Values``): a prior on the first frame at
    its initial pose, one ``BetweenFactorPose3`` per edge with covariance ``covs[k]``
    (project order, 6x6), robust kernel per ``cfg``; values from ``initial`` (N, 4, 4).
    ``measured`` optionally gives the edges' ``gtsam.Pose3`` (already converted)."""
    import gtsam

    a = edge_arrays(np.asarray(frame_ids, dtype=np.int64), edges)
    measured = measured if measured is not None else _pose3s(a.T)
    graph = gtsam.NonlinearFactorGraph()
    graph.add(prior_factor(frame_ids[0], initial[0], cfg))
    for f in between_factors(a.ids, measured, np.asarray(covs, dtype=np.float64).reshape(-1, 6, 6), cfg):
        graph.add(f)
    return graph, _values(frame_ids, initial)


def _values(frame_ids: NDArray[np.int64], poses: NDArray[np.float64]):
    import gtsam

    values = gtsam.Values()
    for k, P in zip(np.asarray(frame_ids).tolist(), _pose3s(poses)):
        values.insert(k, P)
    return values


def _poses_from_values(frame_ids: NDArray[np.int64], values) -> NDArray[np.float64]:
    """(N, 4, 4) poses of the (sorted) frame ids; the values hold exactly these Pose3 keys."""
    import gtsam

    X = gtsam.utilities.extractPose3(values)  # key order, rows: R row-major (9), t (3)
    if X.shape[0] != len(frame_ids):
        return np.stack([geo.from_gtsam_pose3(values.atPose3(int(k))) for k in frame_ids])
    out = np.zeros((len(X), 4, 4))
    out[:, :3, :3] = X[:, :9].reshape(-1, 3, 3)
    out[:, :3, 3] = X[:, 9:]
    out[:, 3, 3] = 1.0
    return out


def gtsam_error(exc: RuntimeError) -> GraphError:
    """The one-line :class:`GraphError` of a GTSAM ``RuntimeError`` (an indeterminant system named as such)."""
    msg = str(exc)
    if "Indeterminant" in msg or "Indeterminate" in msg or "indeterminant" in msg:
        first = " ".join(msg.split())
        var = first.split("near variable", 1)[1].split("(")[0].strip() if "near variable" in first else "?"
        return GraphError(f"the pose-graph linear system is indeterminant near frame {var}: "
                          "some poses are unconstrained or an edge covariance is degenerate")
    return GraphError(f"GTSAM failed: {' '.join(msg.split())[:300]}")


def _lm_params(cfg: PoseGraphConfig):
    import gtsam

    params = gtsam.LevenbergMarquardtParams()
    params.setMaxIterations(cfg.max_iterations)
    params.setRelativeErrorTol(cfg.relative_error_tol)
    params.setAbsoluteErrorTol(cfg.absolute_error_tol)
    params.setLinearSolverType(cfg.linear_solver)
    params.setOrderingType(cfg.ordering)
    return params


def _run_lm(graph, values, cfg: PoseGraphConfig, check: bool = True):
    """Batch Levenberg-Marquardt; with ``check``, one undamped elimination at the solution
    (LM hides an indeterminant system behind its damping; this costs about one iteration)."""
    import gtsam

    try:
        opt = gtsam.LevenbergMarquardtOptimizer(graph, values, _lm_params(cfg))
        result = opt.optimize()
        if check:
            check_determinate(graph, result)
    except RuntimeError as exc:
        raise gtsam_error(exc) from None
    return result, int(opt.iterations())


def check_determinate(graph, values) -> None:
    """Raise :class:`GraphError` when the undamped linear system at ``values`` is singular."""
    try:
        graph.linearize(values).eliminateMultifrontal()
    except RuntimeError as exc:
        raise gtsam_error(exc) from None


def _run_isam2(frame_ids: NDArray[np.int64], pos: NDArray[np.int64], T_meas: NDArray[np.float64], factors: list,
               initial: NDArray[np.float64], cfg: PoseGraphConfig):
    """Incremental solve: frames enter in id order; a frame's edges to frames already
    in the graph are added with it (a frame with none waits until it is connected).
    ``pos`` (E, 2) positions, ``T_meas`` (E, 4, 4) and ``factors`` describe the edges."""
    import gtsam

    params = gtsam.ISAM2Params()
    params.setRelinearizeThreshold(cfg.isam2_relinearize_threshold)
    params.relinearizeSkip = 1
    isam = gtsam.ISAM2(params)
    gap = np.abs(pos[:, 1] - pos[:, 0])
    adj: list[list[int]] = [[] for _ in frame_ids]
    for n, (p, q) in enumerate(pos.tolist()):
        adj[p].append(n)
        adj[q].append(n)
    for lst in adj:
        lst.sort(key=lambda n: gap[n])
    inserted = np.zeros(len(frame_ids), bool)
    added = np.zeros(len(pos), bool)
    pending: list[int] = []
    est: dict[int, NDArray[np.float64]] = {}
    steps = 0
    bar = tqdm(total=len(frame_ids), desc="isam2", unit="pose", disable=not sys.stderr.isatty(), leave=False)
    try:
        for p in range(len(frame_ids)):
            graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
            if p == 0:
                graph.add(prior_factor(frame_ids[0], initial[0], cfg))
                values.insert(int(frame_ids[0]), geo.to_gtsam_pose3(initial[0]))
                inserted[0] = True
                est[0] = initial[0]
            else:
                pending.append(p)
            grew = True
            while grew:  # insert pending frames that now have an edge to the graph
                grew = False
                for q in list(pending):
                    anchor, T_anchor_q = None, None
                    for n in adj[q]:  # predict the new pose through its shortest edge
                        other = pos[n, 1] if pos[n, 0] == q else pos[n, 0]
                        if inserted[other]:
                            anchor = int(other)
                            T_anchor_q = T_meas[n] if pos[n, 0] == other else geo.inv_T(T_meas[n])
                            break
                    if anchor is None:
                        continue
                    T0 = est[anchor] @ T_anchor_q
                    values.insert(int(frame_ids[q]), geo.to_gtsam_pose3(T0))
                    inserted[q], est[q] = True, T0
                    pending.remove(q)
                    grew = True
                    for n in adj[q]:
                        if not added[n] and inserted[pos[n, 0]] and inserted[pos[n, 1]]:
                            graph.add(factors[n])
                            added[n] = True
            if values.size() or graph.size():
                isam.update(graph, values)
                steps += 1
                # refresh the estimates of the newest frames (cheap, used as anchors)
                for q in np.flatnonzero(inserted)[-8:]:
                    est[int(q)] = geo.from_gtsam_pose3(isam.calculateEstimatePose3(int(frame_ids[q])))
            bar.update(1)
        for _ in range(cfg.isam2_final_updates):  # extra relinearisation passes at the end
            isam.update()
        result = isam.calculateEstimate()
    except RuntimeError as exc:
        raise gtsam_error(exc) from None
    finally:
        bar.close()
    if not inserted.all() or not added.all():
        raise GraphError("ISAM2: some frames never connected to the graph")
    return result, steps


def _sigma_figures(covs: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """(E,) largest translation sigma (m) and (E,) largest rotation sigma (deg) of (E, 6, 6)
    covariances in (v, w) order."""
    st = np.sqrt(np.maximum(np.linalg.eigvalsh(covs[:, :3, :3])[:, -1], 0.0))
    sr = np.degrees(np.sqrt(np.maximum(np.linalg.eigvalsh(covs[:, 3:, 3:])[:, -1], 0.0)))
    return st, sr


def whitened_residuals(poses: NDArray[np.float64], frame_ids: NDArray[np.int64], edges: Sequence[Edge],
                       covs: Sequence[NDArray[np.float64]] | None = None) -> NDArray[np.float64]:
    """(E,) ``sqrt(d^T C^-1 d)``, ``d`` the right-perturbation residual of each edge at
    ``poses`` (N, 4, 4) of the sorted ``frame_ids`` (``T_i_j(poses) = T_i_j @ exp(d)``),
    no robust kernel."""
    a = edge_arrays(np.asarray(frame_ids, dtype=np.int64), edges)
    c = a.cov if covs is None else np.asarray(covs, dtype=np.float64).reshape(-1, 6, 6)
    return edge_residuals(np.asarray(poses, dtype=np.float64), a.pos, geo.orthonormalize(a.T), np.linalg.inv(c))


def _keep_connected(n_frames: int, pos: NDArray[np.int64], drop: NDArray[np.bool_],
                    order: NDArray[np.int64]) -> NDArray[np.bool_]:
    """Of the edges marked in ``drop``, return those that must stay (down-weighted) to
    keep the graph connected; tried in ``order`` (best first)."""
    keep = np.zeros(len(pos), bool)
    if not drop.any():
        return keep
    labels = _component_labels(n_frames, pos[~drop])
    if len(np.unique(labels)) == 1:
        return keep
    # union frames by component label, then add dropped edges best first while they join components
    uf = UnionFind(n_frames)
    first: dict[int, int] = {}
    for p, lab in enumerate(labels.tolist()):
        uf.union(first.setdefault(lab, p), p)
    for n in np.asarray(order).tolist():
        if drop[n] and uf.union(int(pos[n, 0]), int(pos[n, 1])):
            keep[n] = True
    return keep


def outlier_masks(n_frames: int, pos: NDArray[np.int64], flagged: NDArray[np.bool_], order: NDArray[np.int64],
                  cfg: PoseGraphConfig) -> tuple[NDArray[np.bool_], NDArray[np.bool_]]:
    """(drop, downweight) masks for the flagged edges under ``cfg.outlier_action``."""
    if cfg.outlier_action == "downweight":
        return np.zeros(len(pos), bool), flagged.copy()
    keep = _keep_connected(n_frames, pos, flagged, order)
    return flagged & ~keep, keep


class _Problem:
    """One graph's edges, converted once, solved repeatedly with different masks and
    covariance scales (first solve, outlier pass, re-solve)."""

    def __init__(self, frame_ids: NDArray[np.int64], a: EdgeArrays, initial: NDArray[np.float64],
                 cfg: PoseGraphConfig) -> None:
        self.frame_ids, self.a, self.cfg = frame_ids, a, cfg
        self.T = geo.orthonormalize(a.T)
        self.measured = _pose3s(self.T)  # the one per-edge conversion
        self.prior = prior_factor(frame_ids[0], initial[0], cfg)
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
        return between_factors(self.a.ids[idx], [self.measured[n] for n in idx.tolist()], covs, self.cfg)

    def solve(self, use: NDArray[np.bool_], scale: NDArray[np.float64], start):
        """(graph, start values, result values, iterations); ``start`` is a ``gtsam.Values``
        or (N, 4, 4) poses."""
        import gtsam

        facs = self.factors(scale)
        sel = np.flatnonzero(use)
        graph = gtsam.NonlinearFactorGraph()
        graph.add(self.prior)
        for n in sel.tolist():
            graph.add(facs[n])
        values = start if isinstance(start, gtsam.Values) else _values(self.frame_ids, start)
        if self.cfg.solver == "lm":
            result, iters = _run_lm(graph, values, self.cfg, check=False)
        else:
            poses = _poses_from_values(self.frame_ids, values)
            result, iters = _run_isam2(self.frame_ids, self.a.pos[sel], self.T[sel], [facs[n] for n in sel.tolist()],
                                       poses, self.cfg)
        return graph, values, result, iters

    def residuals(self, poses: NDArray[np.float64], scale: NDArray[np.float64]) -> NDArray[np.float64]:
        """(E,) whitened residual norms of every edge at ``poses`` under ``cov * scale``."""
        return edge_residuals(poses, self.a.pos, self.T, self.info / scale[:, None, None])


#: Median of the chi-square distribution with 6 degrees of freedom (5.348).
CHI2_6_MEDIAN = uncertainty.CHI2_6_MEDIAN


def source_scale_factors(res: NDArray[np.float64], src: NDArray[np.int64], est: NDArray[np.bool_], n_src: int,
                   redundancy: float, cfg: PoseGraphConfig) -> tuple[NDArray[np.float64], NDArray[np.int64]]:
    """Per source: (factor by which its covariances should grow, number of edges used).

    ``median(r^2) / (CHI2_6_MEDIAN * redundancy)`` over the source's edges in ``est``;
    1 for a source with fewer than ``cfg.calibration_min_edges`` edges or when the graph
    has (almost) no redundancy (residuals then say nothing about the noise)."""
    factor, counts = np.ones(n_src), np.zeros(n_src, np.int64)
    for k in range(n_src):
        r = res[(src == k) & est]
        counts[k] = len(r)
        if len(r) >= cfg.calibration_min_edges and redundancy > 0.05:
            factor[k] = max(float(np.median(r**2)), 1e-300) / (CHI2_6_MEDIAN * redundancy)
    return factor, counts


def solve(frame_ids: NDArray[np.int64], edges: Sequence[Edge], initial: NDArray[np.float64] | None = None,
          cfg: PoseGraphConfig = DEFAULT, fixed_sources: Sequence[str] = ()) -> SolveResult:
    """Optimise the pose graph.

    Args:
        frame_ids: (N,) frame ids (sorted here); the first is fixed by a prior.
        edges: relative-pose edges; ``edge.extra["source"]`` names their origin.
        initial: (N, 4, 4) initial ``T_world_cam`` (default: :func:`chain_poses`).
        cfg: solver, kernel and outlier settings.
        fixed_sources: sources whose covariances were already calibrated on validation
            data (or deliberately set): they keep scale 1 in the per-source calibration.

    Steps: validate; reject by covariance size; first (robust) solve; with
    ``cfg.calibrate``, estimate one covariance scale per source from the whitened
    residuals and re-solve (warm-started) until the scales settle; reject edges whose
    whitened residual under the calibrated covariances exceeds
    ``cfg.residual_threshold``; solve again (warm-started) if any were rejected; check
    the final linear system is determinate; optional marginals. Raises
    :class:`GraphError` on bad input.
    """
    t0, c0 = time.perf_counter(), time.process_time()
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
    n_frames, n_edges = len(frame_ids), len(edges)
    prob = _Problem(frame_ids, a, initial, cfg)

    reason: dict[int, tuple[str, float]] = {}
    # 1) covariance above threshold
    flagged = np.zeros(n_edges, bool)
    if n_edges and (math.isfinite(cfg.max_trans_sigma_m) or math.isfinite(cfg.max_rot_sigma_deg)):
        st, sr = _sigma_figures(a.cov)
        for n in np.flatnonzero(st > cfg.max_trans_sigma_m).tolist():
            reason[n] = ("covariance_trans_sigma_m", float(st[n]))
        for n in np.flatnonzero((sr > cfg.max_rot_sigma_deg) & (st <= cfg.max_trans_sigma_m)).tolist():
            reason[n] = ("covariance_rot_sigma_deg", float(sr[n]))
        flagged = np.array([n in reason for n in range(n_edges)], bool)
    drop, weak = outlier_masks(n_frames, a.pos, flagged, np.arange(n_edges), cfg)

    names = list(dict.fromkeys(a.source))
    index = {n: k for k, n in enumerate(names)}
    src = np.array([index[x] for x in a.source], dtype=np.int64)
    src_scale = np.ones(len(names))

    def scale_of(weak: NDArray[np.bool_]) -> NDArray[np.float64]:
        return src_scale[src] * np.where(weak, cfg.downweight_factor, 1.0)

    graph, values0, result, iters = prob.solve(~drop, scale_of(weak), initial)
    initial_error = float(graph.error(values0))
    poses = _poses_from_values(frame_ids, result)
    calib = None
    # 2) per-source covariance scale from the residuals (before any residual-based rejection)
    if cfg.calibrate:
        calib = {"sources": {}, "iterations": 0, "converged": False,
                 "redundancy": 1.0 - (n_frames - 1) / max(int((~drop).sum()), 1)}
        est = ~drop & ~weak
        for it in range(cfg.calibration_iterations + 1):
            factor, counts = source_scale_factors(prob.residuals(poses, src_scale[src]), src, est, len(names),
                                            calib["redundancy"], cfg)
            factor[[k for k, n in enumerate(names) if n in fixed_sources]] = 1.0
            new = np.clip(src_scale * factor, *cfg.calibration_scale_range)
            calib["sources"] = {n: {"edges": int(counts[k]), "scale": float(src_scale[k]),
                                    "residual_factor": float(factor[k])} for k, n in enumerate(names)}
            if np.all(np.abs(np.log(new / src_scale)) <= math.log1p(cfg.calibration_tolerance)):
                calib["converged"] = True
                break
            if it == cfg.calibration_iterations:
                break
            src_scale = new
            calib["iterations"] += 1
            log.info("covariance scales %s; re-solving", ", ".join(f"{n} {v:.3g}" for n, v in zip(names, new)))
            graph, _, result, it_n = prob.solve(~drop, scale_of(weak), result)
            iters += it_n
            poses = _poses_from_values(frame_ids, result)
        calib["sources"] = {n: {**v, "scale": float(src_scale[k])} for k, (n, v) in enumerate(calib["sources"].items())}
    first_res = prob.residuals(poses, src_scale[src])
    final_res = first_res
    # 3) whitened residual (under the calibrated covariances) after the first solve
    if math.isfinite(cfg.residual_threshold):
        bad = (first_res > cfg.residual_threshold) & ~flagged
        if bad.any():
            for n in np.flatnonzero(bad).tolist():
                reason[n] = ("residual", float(first_res[n]))
            flagged = flagged | bad
            drop, weak = outlier_masks(n_frames, a.pos, flagged, np.argsort(first_res), cfg)
            log.info("re-solving without %d outlier edge(s)", int(bad.sum()))
            # warm start from the first solution (the prior stays on the first frame)
            graph, _, result, iters2 = prob.solve(~drop, scale_of(weak), result)
            iters += iters2
            poses = _poses_from_values(frame_ids, result)
            final_res = prob.residuals(poses, src_scale[src])
    outliers = [OutlierRecord(int(a.ids[n, 0]), int(a.ids[n, 1]), a.source[n], reason[n][0], reason[n][1],
                              "removed" if drop[n] else "downweighted") for n in np.flatnonzero(flagged).tolist()]
    marg = None
    if cfg.marginals:  # factorises the undamped system: also the determinacy check
        marg = marginal_covariances(graph, result, frame_ids)
    else:
        check_determinate(graph, result)
    res = SolveResult(
        frame_ids=frame_ids, poses=poses, outliers=outliers, residuals=final_res, used=~drop,
        initial_error=initial_error, final_error=float(graph.error(result)),
        solver=cfg.solver, iterations=iters, time_s=time.perf_counter() - t0, marginals=marg,
        first_residuals=first_res, cpu_s=time.process_time() - c0,
        source_scales={n: float(v) for n, v in zip(names, src_scale)}, calibration=calib,
    )
    log.info("%s: %d poses, %d edges (%d outliers), error %.4g -> %.4g in %.2f s", cfg.solver, n_frames,
             n_edges, len(outliers), res.initial_error, res.final_error, res.time_s)
    return res


def marginal_covariances(graph, result, frame_ids: NDArray[np.int64]) -> NDArray[np.float64]:
    """(N, 6, 6) marginal covariance of every pose, project order (v, w), right perturbation."""
    import gtsam

    try:
        m = gtsam.Marginals(graph, result)
        return np.stack([geo.cov_from_gtsam(m.marginalCovariance(int(k))) for k in frame_ids])
    except RuntimeError as exc:
        raise gtsam_error(exc) from None


__all__ = ["EdgeArrays", "GraphError", "OutlierRecord", "SolveResult", "bridge_cov", "bridge_edges", "build_graph", "chain_poses", "joining_edges",
           "check_connected", "check_determinate", "component_labels", "components", "edge_arrays", "edge_residuals",
           "marginal_covariances", "solve", "validate_edges", "whitened_residuals"]
