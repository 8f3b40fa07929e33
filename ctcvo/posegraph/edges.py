"""Edges as arrays: validation, whitened residuals, connectivity, chaining and bridges.

Conventions (see docs/conventions.md): an :class:`~data.formats.Edge` carries ``T_i_j``
and a 6x6 covariance in the project tangent order (v, w), right perturbation at the
measurement. Everything here is numpy and scipy; GTSAM enters in :mod:`posegraph.factors`.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from ctcvo.data import geometry as geo
from ctcvo.data.chain import UnionFind, chain_edges
from ctcvo.data.errors import VOError
from ctcvo.data.formats import Edge

# a bridge edge's standard deviation as a multiple of the graph's typical (smallest-gap) edge: loose,
# yet moderate, since a fixed 0.05 m / 3 deg bridge among 1 mm redkitchen edges made GTSAM's
# elimination indeterminant (issue 12, "Fusion that never hurts"; not varied since)
BRIDGE_SIGMA_FACTOR = 10.0


class GraphError(VOError):
    """The pose graph cannot be built or solved (disconnected, indeterminant, bad edge)."""


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



def whitened_residuals(poses: NDArray[np.float64], frame_ids: NDArray[np.int64], edges: Sequence[Edge],
                       covs: Sequence[NDArray[np.float64]] | None = None) -> NDArray[np.float64]:
    """(E,) ``sqrt(d^T C^-1 d)``, ``d`` the right-perturbation residual of each edge at
    ``poses`` (N, 4, 4) of the sorted ``frame_ids`` (``T_i_j(poses) = T_i_j @ exp(d)``),
    no robust kernel."""
    a = edge_arrays(np.asarray(frame_ids, dtype=np.int64), edges)
    c = a.cov if covs is None else np.asarray(covs, dtype=np.float64).reshape(-1, 6, 6)
    return edge_residuals(np.asarray(poses, dtype=np.float64), a.pos, geo.orthonormalize(a.T), np.linalg.inv(c))


# ----------------------------------------------------------------------------------
# connectivity, chaining, bridges
# ----------------------------------------------------------------------------------
def position_labels(n: int, pos: NDArray[np.int64]) -> NDArray[np.int64]:
    """(n,) connected-component label of every frame position, (E, 2) edge positions ``pos``."""
    adj = coo_matrix((np.ones(len(pos)), (pos[:, 0], pos[:, 1])), shape=(n, n))
    return connected_components(adj, directed=False)[1]


def united_components(labels: NDArray[np.int64]) -> UnionFind:
    """A union-find over the positions with every component of ``labels`` already united."""
    uf = UnionFind(len(labels))
    first: dict[int, int] = {}
    for p, lab in enumerate(labels.tolist()):
        uf.union(first.setdefault(lab, p), p)
    return uf


def component_labels(frame_ids: NDArray[np.int64], edges: Sequence[Edge]) -> NDArray[np.int64]:
    """(N,) connected-component label of every frame of the sorted ``frame_ids``."""
    return position_labels(len(frame_ids), edge_arrays(np.asarray(frame_ids, dtype=np.int64), edges).pos)


def components(frame_ids: NDArray[np.int64], edges: Sequence[Edge]) -> list[list[int]]:
    """Connected components (lists of frame ids, sorted by first id); ``frame_ids`` sorted."""
    frame_ids = np.asarray(frame_ids, dtype=np.int64)
    labels = position_labels(len(frame_ids), edge_arrays(frame_ids, edges).pos)
    groups: dict[int, list[int]] = {}
    for lab, k in zip(labels.tolist(), frame_ids.tolist()):
        groups.setdefault(lab, []).append(k)
    return sorted(groups.values(), key=lambda g: g[0])


def check_connected(frame_ids: NDArray[np.int64], edges: Sequence[Edge],
                    arrays: EdgeArrays | None = None) -> None:
    """Raise :class:`GraphError` naming the split when the graph is not connected."""
    frame_ids = np.asarray(frame_ids, dtype=np.int64)
    pos = (arrays if arrays is not None else edge_arrays(frame_ids, edges)).pos
    if len(np.unique(position_labels(len(frame_ids), pos))) == 1:
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
    uf = united_components(position_labels(len(frame_ids), edge_arrays(frame_ids, edges).pos))
    out = []
    for p in range(len(frame_ids) - 1):
        if uf.union(p, p + 1):
            T = np.eye(4) if poses is None else geo.relative_pose(poses[p], poses[p + 1])
            out.append(Edge(int(frame_ids[p]), int(frame_ids[p + 1]), T, np.array(cov, dtype=np.float64),
                            {"source": "bridge"}))
    return out


def bridge_cov(frame_ids: NDArray[np.int64], edges: Sequence[Edge]) -> NDArray[np.float64]:
    """(6, 6) diagonal covariance of a bridge edge: ``BRIDGE_SIGMA_FACTOR^2`` times the median
    diagonal of the smallest-gap ``edges`` (identity-sized 1e-4 without edges)."""
    factor = BRIDGE_SIGMA_FACTOR
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
    labels = position_labels(len(frame_ids), edge_arrays(frame_ids, edges).pos)
    if len(np.unique(labels)) == 1 or not candidates:
        return []
    uf = united_components(labels)
    pos = edge_arrays(frame_ids, candidates).pos
    return [e for e, (p, q) in zip(candidates, pos.tolist()) if uf.union(p, q)]
