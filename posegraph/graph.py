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
from collections import deque
from dataclasses import dataclass, field
from typing import Optional, Sequence

import numpy as np
from numpy.typing import NDArray
from tqdm import tqdm

from data import geometry as geo
from data.errors import VOError
from data.formats import Edge
from posegraph.config import DEFAULT, PoseGraphConfig

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
    marginals: Optional[NDArray[np.float64]] = None
    """(N, 6, 6) marginal covariances in project order (v, w), right perturbation."""
    first_residuals: Optional[NDArray[np.float64]] = field(default=None, repr=False)
    """(E,) whitened residual norms after the first solve (before outlier handling)."""


# ----------------------------------------------------------------------------------
# validation and graph structure
# ----------------------------------------------------------------------------------
def validate_edges(frame_ids: NDArray[np.int64], edges: Sequence[Edge]) -> None:
    """Raise :class:`GraphError` for edges on unknown frames, bad covariances or poses
    (vectorised: large graphs validate in milliseconds)."""
    if len(frame_ids) < 2:
        raise GraphError(f"a pose graph needs at least two frames, got {len(frame_ids)}")
    if np.any(frame_ids < 0):
        raise GraphError("frame ids must be non-negative")
    if not edges:
        return
    lo, hi = int(frame_ids.min()), int(frame_ids.max())
    ij = np.array([(e.i, e.j) for e in edges], dtype=np.int64)
    covs = np.stack([np.asarray(e.cov, dtype=np.float64).reshape(6, 6) for e in edges])
    Ts = np.stack([np.asarray(e.T_i_j, dtype=np.float64).reshape(4, 4) for e in edges])

    def fail(n: int, why: str) -> None:
        e = edges[int(n)]
        raise GraphError(f"edge {e.i}->{e.j} ({e.extra.get('source', 'edges')}): {why}")

    known = np.isin(ij, frame_ids)
    if not known.all():
        n, c = np.argwhere(~known)[0]
        fail(n, f"references frame {ij[n, c]}, which does not exist ({len(frame_ids)} frames, ids {lo}..{hi})")
    same = np.flatnonzero(ij[:, 0] == ij[:, 1])
    if len(same):
        fail(same[0], "connects a frame to itself")
    bad = ~np.isfinite(covs).all(axis=(1, 2))
    if bad.any():
        fail(np.flatnonzero(bad)[0], "covariance must be a finite 6x6 matrix")
    sym = np.isclose(covs, covs.transpose(0, 2, 1), rtol=1e-6, atol=1e-12).all(axis=(1, 2))
    pd = np.linalg.eigvalsh(0.5 * (covs + covs.transpose(0, 2, 1))).min(axis=1) > 0
    if not (sym & pd).all():
        fail(np.flatnonzero(~(sym & pd))[0], "covariance is not symmetric positive definite")
    R = Ts[:, :3, :3]
    with np.errstate(invalid="ignore"):
        rigid = (np.isfinite(Ts).all(axis=(1, 2))
                 & np.isclose(R.transpose(0, 2, 1) @ R, np.eye(3), atol=1e-4).all(axis=(1, 2))
                 & (np.abs(np.linalg.det(np.nan_to_num(R)) - 1.0) < 1e-4)
                 & np.isclose(Ts[:, 3], [0, 0, 0, 1], atol=1e-4).all(axis=1))
    if not rigid.all():
        fail(np.flatnonzero(~rigid)[0], "relative pose is not a finite rigid transform")


def _orthonormalize_batch(Ts: NDArray[np.float64]) -> NDArray[np.float64]:
    """(N, 4, 4) transforms with rotation blocks projected onto SO(3) (batched SVD,
    same projection as :func:`data.geometry.orthonormalize`)."""
    Ts = np.array(Ts, dtype=np.float64).reshape(-1, 4, 4)
    U, _, Vt = np.linalg.svd(Ts[:, :3, :3])
    d = np.sign(np.linalg.det(U @ Vt))
    U[:, :, -1] *= d[:, None]
    Ts[:, :3, :3] = U @ Vt
    Ts[:, 3] = [0, 0, 0, 1]
    return Ts


def _pose3s(Ts: NDArray[np.float64]) -> list:
    """``gtsam.Pose3`` objects of (N, 4, 4) transforms."""
    import gtsam

    return [gtsam.Pose3(T) for T in _orthonormalize_batch(Ts)]


def _covs_gtsam(covs: Sequence[NDArray[np.float64]]) -> NDArray[np.float64]:
    """(E, 6, 6) covariances re-ordered to GTSAM's (w, v) with the conversion module's
    vector permutation applied to rows and columns (batched cov_to_gtsam)."""
    c = np.stack([np.asarray(x, dtype=np.float64) for x in covs])
    c = geo.vec_to_gtsam(geo.vec_to_gtsam(c).transpose(0, 2, 1))
    return 0.5 * (c + c.transpose(0, 2, 1))


class _UnionFind:
    def __init__(self, n: int) -> None:
        self.parent = list(range(n))

    def find(self, a: int) -> int:
        while self.parent[a] != a:
            self.parent[a] = self.parent[self.parent[a]]
            a = self.parent[a]
        return a

    def union(self, a: int, b: int) -> bool:
        ra, rb = self.find(a), self.find(b)
        if ra == rb:
            return False
        self.parent[rb] = ra
        return True


def components(frame_ids: NDArray[np.int64], edges: Sequence[Edge]) -> list[list[int]]:
    """Connected components (lists of frame ids, sorted by first id)."""
    pos = {int(k): p for p, k in enumerate(frame_ids)}
    uf = _UnionFind(len(frame_ids))
    for e in edges:
        uf.union(pos[e.i], pos[e.j])
    groups: dict[int, list[int]] = {}
    for p, k in enumerate(frame_ids):
        groups.setdefault(uf.find(p), []).append(int(k))
    return sorted(groups.values(), key=lambda g: g[0])


def check_connected(frame_ids: NDArray[np.int64], edges: Sequence[Edge]) -> None:
    """Raise :class:`GraphError` naming the split when the graph is not connected."""
    comps = components(frame_ids, edges)
    if len(comps) > 1:
        sizes = ", ".join(f"{c[0]}..{c[-1]} ({len(c)} frames)" for c in comps[:4])
        more = f" and {len(comps) - 4} more" if len(comps) > 4 else ""
        raise GraphError(f"the pose graph is disconnected: {len(comps)} components: {sizes}{more}; "
                         "every frame needs a chain of edges to the first frame")


def chain_poses(frame_ids: NDArray[np.int64], edges: Sequence[Edge],
                T_world_first: Optional[NDArray[np.float64]] = None) -> NDArray[np.float64]:
    """Chain edges into ``T_world_cam`` poses (N, 4, 4) along a spanning tree.

    Breadth-first from the first frame, trying each frame's edges in order of
    increasing frame gap, so a complete gap-1 chain is used as is (dead reckoning).
    Raises :class:`GraphError` if some frame cannot be reached.
    """
    pos = {int(k): p for p, k in enumerate(frame_ids)}
    adj: list[list[tuple[int, int, int, bool]]] = [[] for _ in frame_ids]
    for n, e in enumerate(edges):
        a, b = pos[e.i], pos[e.j]
        adj[a].append((abs(b - a), b, n, False))
        adj[b].append((abs(b - a), a, n, True))  # traversed backwards: inverse, computed lazily
    for lst in adj:
        lst.sort(key=lambda x: (x[0], x[1]))
    poses = np.full((len(frame_ids), 4, 4), np.nan)
    poses[0] = np.eye(4) if T_world_first is None else T_world_first
    seen = np.zeros(len(frame_ids), bool)
    seen[0] = True
    queue = deque([0])
    # Process frames in increasing order where possible: a gap-1 chain then wins.
    while queue:
        a = queue.popleft()
        for _, b, n, backwards in adj[a]:
            if not seen[b]:
                seen[b] = True
                T_a_b = geo.inv_T(edges[n].T_i_j) if backwards else edges[n].T_i_j
                poses[b] = poses[a] @ T_a_b
                queue.append(b)
    if not seen.all():
        check_connected(frame_ids, edges)
    return poses


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


def _prior(frame_id: int, T: NDArray[np.float64], cfg: PoseGraphConfig):
    import gtsam

    sig = np.array([cfg.prior_sigma_rot_rad] * 3 + [cfg.prior_sigma_trans_m] * 3)  # GTSAM order (w, v)
    return gtsam.PriorFactorPose3(int(frame_id), geo.to_gtsam_pose3(T), gtsam.noiseModel.Diagonal.Sigmas(sig))


def _factors(edges: Sequence[Edge], covs: Sequence[NDArray[np.float64]], cfg: PoseGraphConfig,
             measured: Optional[list] = None) -> list:
    """One robust ``BetweenFactorPose3`` per edge; noise models are shared between edges
    with identical covariances."""
    import gtsam

    if not edges:
        return []
    measured = measured if measured is not None else _pose3s(np.stack([e.T_i_j for e in edges]))
    cache: dict[bytes, object] = {}
    out = []
    for e, P, c in zip(edges, measured, _covs_gtsam(covs)):
        key = c.tobytes()
        model = cache.get(key)
        if model is None:
            model = cache[key] = _robust(gtsam.noiseModel.Gaussian.Covariance(c), cfg)
        out.append(gtsam.BetweenFactorPose3(int(e.i), int(e.j), P, model))
    return out


def build_graph(frame_ids: NDArray[np.int64], edges: Sequence[Edge], covs: Sequence[NDArray[np.float64]],
                initial: NDArray[np.float64], cfg: PoseGraphConfig = DEFAULT, measured: Optional[list] = None):
    """(``gtsam.NonlinearFactorGraph``, ``gtsam.Values``): a prior on the first frame at
    its initial pose, one ``BetweenFactorPose3`` per edge with covariance ``covs[k]``
    (project order, 6x6), robust kernel per ``cfg``; values from ``initial`` (N, 4, 4).
    ``measured`` optionally gives the edges' ``gtsam.Pose3`` (already converted)."""
    import gtsam

    graph = gtsam.NonlinearFactorGraph()
    graph.add(_prior(frame_ids[0], initial[0], cfg))
    for f in _factors(edges, covs, cfg, measured):
        graph.add(f)
    return graph, _values(frame_ids, initial)


def _values(frame_ids: NDArray[np.int64], poses: NDArray[np.float64]):
    import gtsam

    values = gtsam.Values()
    for k, P in zip(frame_ids, _pose3s(poses)):
        values.insert(int(k), P)
    return values


def _poses_from_values(frame_ids: NDArray[np.int64], values) -> NDArray[np.float64]:
    return np.stack([geo.from_gtsam_pose3(values.atPose3(int(k))) for k in frame_ids])


def _indeterminant(exc: RuntimeError) -> GraphError:
    msg = str(exc)
    if "Indeterminant" in msg or "Indeterminate" in msg or "indeterminant" in msg:
        first = " ".join(msg.split())
        var = first.split("near variable", 1)[1].split("(")[0].strip() if "near variable" in first else "?"
        return GraphError(f"the pose-graph linear system is indeterminant near frame {var}: "
                          "some poses are unconstrained or an edge covariance is degenerate")
    return GraphError(f"GTSAM failed: {' '.join(msg.split())[:300]}")


def _run_lm(graph, values, cfg: PoseGraphConfig):
    import gtsam

    params = gtsam.LevenbergMarquardtParams()
    params.setMaxIterations(cfg.max_iterations)
    params.setRelativeErrorTol(cfg.relative_error_tol)
    params.setAbsoluteErrorTol(0.0)
    try:
        opt = gtsam.LevenbergMarquardtOptimizer(graph, values, params)
        result = opt.optimize()
        # LM hides an indeterminant system behind its damping; one undamped
        # elimination at the solution exposes it (costs about one LM iteration).
        graph.linearize(result).eliminateMultifrontal()
    except RuntimeError as exc:
        raise _indeterminant(exc) from None
    return result, int(opt.iterations())


def _run_isam2(frame_ids: NDArray[np.int64], edges: Sequence[Edge], covs: Sequence[NDArray[np.float64]],
               initial: NDArray[np.float64], cfg: PoseGraphConfig, measured: Optional[list] = None):
    """Incremental solve: frames enter in id order; a frame's edges to frames already
    in the graph are added with it (a frame with none waits until it is connected)."""
    import gtsam

    params = gtsam.ISAM2Params()
    params.setRelinearizeThreshold(cfg.isam2_relinearize_threshold)
    params.relinearizeSkip = 1
    isam = gtsam.ISAM2(params)
    factors = _factors(edges, covs, cfg, measured)
    pos = {int(k): p for p, k in enumerate(frame_ids)}
    adj: list[list[int]] = [[] for _ in frame_ids]
    for n, e in enumerate(edges):
        adj[pos[e.i]].append(n)
        adj[pos[e.j]].append(n)
    inserted = np.zeros(len(frame_ids), bool)
    added = np.zeros(len(edges), bool)
    pending: list[int] = []
    est: dict[int, NDArray[np.float64]] = {}
    steps = 0
    bar = tqdm(total=len(frame_ids), desc="isam2", unit="pose", disable=not sys.stderr.isatty(), leave=False)
    try:
        for p in range(len(frame_ids)):
            graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
            if p == 0:
                graph.add(_prior(frame_ids[0], initial[0], cfg))
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
                    for n in sorted(adj[q], key=lambda n: abs(pos[edges[n].j] - pos[edges[n].i])):
                        e = edges[n]
                        other = pos[e.j] if pos[e.i] == q else pos[e.i]
                        if inserted[other]:  # predict the new pose through its shortest edge
                            anchor = other
                            T_anchor_q = e.T_i_j if pos[e.i] == other else geo.inv_T(e.T_i_j)
                            break
                    if anchor is None:
                        continue
                    T0 = est[anchor] @ T_anchor_q
                    values.insert(int(frame_ids[q]), geo.to_gtsam_pose3(T0))
                    inserted[q], est[q] = True, T0
                    pending.remove(q)
                    grew = True
                    for n in adj[q]:
                        e = edges[n]
                        if not added[n] and inserted[pos[e.i]] and inserted[pos[e.j]]:
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
        raise _indeterminant(exc) from None
    finally:
        bar.close()
    if not inserted.all() or not added.all():
        raise GraphError("ISAM2: some frames never connected to the graph")
    return result, steps


def _sigma_figures(cov: NDArray[np.float64]) -> tuple[float, float]:
    """(largest translation sigma in m, largest rotation sigma in deg) of a (v, w) covariance."""
    st = math.sqrt(max(float(np.linalg.eigvalsh(cov[:3, :3]).max()), 0.0))
    sr = math.degrees(math.sqrt(max(float(np.linalg.eigvalsh(cov[3:, 3:]).max()), 0.0)))
    return st, sr


def _residuals(values, edges: Sequence[Edge], covs: Sequence[NDArray[np.float64]],
               measured: Optional[list] = None) -> NDArray[np.float64]:
    """(E,) whitened residual norms without kernel: GTSAM's between-factor error
    (right perturbation at the measurement, GTSAM order) whitened by the covariance."""
    import gtsam

    if not edges:
        return np.zeros(0)
    measured = measured if measured is not None else _pose3s(np.stack([e.T_i_j for e in edges]))
    unit = gtsam.noiseModel.Unit.Create(6)
    err = np.array([gtsam.BetweenFactorPose3(int(e.i), int(e.j), P, unit).unwhitenedError(values)
                    for e, P in zip(edges, measured)])
    info = np.linalg.inv(_covs_gtsam(covs))
    return np.sqrt(np.maximum(np.einsum("ni,nij,nj->n", err, info, err), 0.0))


def whitened_residuals(poses: NDArray[np.float64], frame_ids: NDArray[np.int64], edges: Sequence[Edge],
                       covs: Optional[Sequence[NDArray[np.float64]]] = None) -> NDArray[np.float64]:
    """(E,) ``sqrt(d^T C^-1 d)``, ``d`` the right-perturbation residual of each edge at
    ``poses`` (N, 4, 4) (``T_i_j(poses) = T_i_j @ exp(d)``), no robust kernel."""
    return _residuals(_values(frame_ids, poses), edges, [e.cov for e in edges] if covs is None else covs)


def _keep_connected(frame_ids: NDArray[np.int64], edges: Sequence[Edge], drop: NDArray[np.bool_],
                    order: NDArray[np.int64]) -> NDArray[np.bool_]:
    """Of the edges marked in ``drop``, return those that must stay (down-weighted) to
    keep the graph connected; tried in ``order`` (best first)."""
    pos = {int(k): p for p, k in enumerate(frame_ids)}
    uf = _UnionFind(len(frame_ids))
    for n, e in enumerate(edges):
        if not drop[n]:
            uf.union(pos[e.i], pos[e.j])
    keep = np.zeros(len(edges), bool)
    for n in order:
        if drop[n] and uf.union(pos[edges[n].i], pos[edges[n].j]):
            keep[n] = True
    return keep


def _solve_once(frame_ids, edges, covs, initial, cfg, measured):
    graph, values = build_graph(frame_ids, edges, covs, initial, cfg, measured)
    if cfg.solver == "lm":
        result, iters = _run_lm(graph, values, cfg)
    else:
        result, iters = _run_isam2(frame_ids, edges, covs, initial, cfg, measured)
    return graph, values, result, iters


def solve(frame_ids: NDArray[np.int64], edges: Sequence[Edge], initial: Optional[NDArray[np.float64]] = None,
          cfg: PoseGraphConfig = DEFAULT) -> SolveResult:
    """Optimise the pose graph.

    Args:
        frame_ids: (N,) frame ids (sorted here); the first is fixed by a prior.
        edges: relative-pose edges; ``edge.extra["source"]`` names their origin.
        initial: (N, 4, 4) initial ``T_world_cam`` (default: :func:`chain_poses`).
        cfg: solver, kernel and outlier settings.

    Steps: validate; reject by covariance size; first solve; reject edges whose
    whitened residual exceeds ``cfg.residual_threshold``; solve again if any were
    rejected; optional marginals. Raises :class:`GraphError` on bad input.
    """
    t0 = time.perf_counter()
    frame_ids = np.asarray(frame_ids, dtype=np.int64)
    order = np.argsort(frame_ids, kind="stable")
    frame_ids = frame_ids[order]
    if len(np.unique(frame_ids)) != len(frame_ids):
        raise GraphError("duplicate frame ids")
    edges = list(edges)
    validate_edges(frame_ids, edges)
    check_connected(frame_ids, edges)
    if initial is None:
        initial = chain_poses(frame_ids, edges)
    else:
        initial = np.asarray(initial, dtype=np.float64)[order]
        if initial.shape != (len(frame_ids), 4, 4) or not np.all(np.isfinite(initial)):
            raise GraphError(f"initial poses must be finite with shape ({len(frame_ids)}, 4, 4)")

    covs = [np.asarray(e.cov, dtype=np.float64) for e in edges]
    measured = _pose3s(np.stack([e.T_i_j for e in edges]))
    outliers: list[OutlierRecord] = []
    drop = np.zeros(len(edges), bool)
    weak = np.zeros(len(edges), bool)
    reason: dict[int, tuple[str, float]] = {}
    # 1) covariance above threshold
    if math.isfinite(cfg.max_trans_sigma_m) or math.isfinite(cfg.max_rot_sigma_deg):
        for n, c in enumerate(covs):
            st, sr = _sigma_figures(c)
            if st > cfg.max_trans_sigma_m:
                reason[n] = ("covariance_trans_sigma_m", st)
            elif sr > cfg.max_rot_sigma_deg:
                reason[n] = ("covariance_rot_sigma_deg", sr)
    flagged = np.array([n in reason for n in range(len(edges))], bool)
    drop, weak = _apply_action(frame_ids, edges, flagged, np.arange(len(edges)), cfg)

    def run(drop: NDArray[np.bool_], weak: NDArray[np.bool_], start: NDArray[np.float64]):
        sel = [n for n in range(len(edges)) if not drop[n]]
        c = [covs[n] * (cfg.downweight_factor if weak[n] else 1.0) for n in sel]
        return _solve_once(frame_ids, [edges[n] for n in sel], c, start, cfg, [measured[n] for n in sel])

    graph, values, result, iters = run(drop, weak, initial)
    initial_error = float(graph.error(values))
    poses = _poses_from_values(frame_ids, result)
    first_res = _residuals(result, edges, covs, measured)
    # 2) whitened residual after the first solve
    if math.isfinite(cfg.residual_threshold):
        bad = (first_res > cfg.residual_threshold) & ~flagged
        if bad.any():
            for n in np.flatnonzero(bad):
                reason[int(n)] = ("residual", float(first_res[n]))
            flagged = flagged | bad
            drop, weak = _apply_action(frame_ids, edges, flagged, np.argsort(first_res), cfg)
            log.info("re-solving without %d outlier edge(s)", int(bad.sum()))
            # warm start from the first solution (the prior stays on the first frame)
            graph, values, result, iters2 = run(drop, weak, poses)
            iters += iters2
            poses = _poses_from_values(frame_ids, result)
    for n in np.flatnonzero(flagged):
        e = edges[n]
        outliers.append(OutlierRecord(int(e.i), int(e.j), str(e.extra.get("source", "edges")), reason[int(n)][0],
                                      reason[int(n)][1], "removed" if drop[n] else "downweighted"))
    marg = None
    if cfg.marginals:
        marg = marginal_covariances(graph, result, frame_ids)
    res = SolveResult(
        frame_ids=frame_ids, poses=poses, outliers=outliers,
        residuals=_residuals(result, edges, covs, measured) if flagged.any() else first_res, used=~drop,
        initial_error=initial_error, final_error=float(graph.error(result)),
        solver=cfg.solver, iterations=iters, time_s=time.perf_counter() - t0, marginals=marg,
        first_residuals=first_res,
    )
    log.info("%s: %d poses, %d edges (%d outliers), error %.4g -> %.4g in %.2f s", cfg.solver, len(frame_ids),
             len(edges), len(outliers), res.initial_error, res.final_error, res.time_s)
    return res


def _apply_action(frame_ids, edges, flagged, order, cfg) -> tuple[NDArray[np.bool_], NDArray[np.bool_]]:
    """(drop, downweight) masks for the flagged edges under ``cfg.outlier_action``."""
    if cfg.outlier_action == "downweight":
        return np.zeros(len(edges), bool), flagged.copy()
    keep = _keep_connected(frame_ids, edges, flagged, order)
    return flagged & ~keep, keep


def marginal_covariances(graph, result, frame_ids: NDArray[np.int64]) -> NDArray[np.float64]:
    """(N, 6, 6) marginal covariance of every pose, project order (v, w), right perturbation."""
    import gtsam

    try:
        m = gtsam.Marginals(graph, result)
        return np.stack([geo.cov_from_gtsam(m.marginalCovariance(int(k))) for k in frame_ids])
    except RuntimeError as exc:
        raise _indeterminant(exc) from None


__all__ = ["GraphError", "OutlierRecord", "SolveResult", "build_graph", "chain_poses", "check_connected",
           "components", "marginal_covariances", "solve", "validate_edges", "whitened_residuals"]
