"""Trajectory chaining: ``T_world_cam`` poses from relative-pose edges.

The project's one implementation, used by the teacher (its ``trajectory.tum``), the
learner's predictions, the pose graph's initial values and chained rows, the synthetic
test fixtures and the benchmarks.

The edges ``(i, j, T_i_j)`` (``T_world_j = T_world_i @ T_i_j``, docs/conventions.md) are
chained along a spanning tree: the minimum spanning tree by frame gap (Kruskal: smallest
gaps first, ties in edge order), walked breadth-first from the first frame. A complete
gap-1 chain is therefore used as is (dead reckoning), and longer edges only bridge missing
steps. Frames that no edge connects to the first one are either left unreached (NaN
poses) or, with ``fill_gaps``, placed by constant velocity: the first unreached frame
repeats the motion of the step before it, and its own component is chained from there.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ctcvo.data import geometry as geo


class UnionFind:
    """Disjoint sets of ``0..n-1`` (path halving)."""

    def __init__(self, n: int) -> None:
        self.parent = list(range(n))

    def find(self, a: int) -> int:
        while self.parent[a] != a:
            self.parent[a] = self.parent[self.parent[a]]
            a = self.parent[a]
        return a

    def union(self, a: int, b: int) -> bool:
        """Join the sets of ``a`` and ``b``; False if they were one already."""
        ra, rb = self.find(a), self.find(b)
        if ra == rb:
            return False
        self.parent[rb] = ra
        return True


@dataclass
class Chain:
    """Chained poses and how every missing gap-1 step was crossed."""

    poses: NDArray[np.float64]
    """(N, 4, 4) ``T_world_cam``; NaN for frames not reached (only without ``fill_gaps``)."""
    reached: NDArray[np.bool_]
    """(N,) frames connected to the first one by edges."""
    bridges: list[dict] = field(default_factory=list)
    """One ``{"i", "j", "method"}`` (frame ids) per consecutive pair without a gap-1 edge:
    ``"edge A->B"`` (the shortest tree edge spanning it) or ``"constant velocity"``."""


def chain_edges(frame_ids: ArrayLike, pos: ArrayLike, T: ArrayLike,
                T_world_first: ArrayLike | None = None, fill_gaps: bool = False) -> Chain:
    """Chain edges into ``T_world_cam`` poses along the minimum spanning tree by gap.

    Args:
        frame_ids: (N,) sorted frame ids (only used to name bridges).
        pos: (E, 2) positions ``(i, j)`` of each edge's frames in ``frame_ids``; the edge
            maps frame ``j`` into frame ``i`` (``T_world_j = T_world_i @ T[e]``); walked
            from ``j`` to ``i`` it is inverted.
        T: (E, 4, 4) relative poses ``T_i_j``.
        T_world_first: pose of the first frame (default: the identity).
        fill_gaps: place frames that no edge reaches by constant velocity instead of
            leaving them NaN.
    """
    frame_ids = np.asarray(frame_ids, dtype=np.int64).reshape(-1)
    pos = np.asarray(pos, dtype=np.int64).reshape(-1, 2)
    T = np.asarray(T, dtype=np.float64).reshape(-1, 4, 4)
    n = len(frame_ids)
    poses = np.full((n, 4, 4), np.nan)
    reached = np.zeros(n, bool)
    if n == 0:
        return Chain(poses, reached)
    uf = UnionFind(n)
    adj: list[list[tuple[int, int, bool]]] = [[] for _ in range(n)]
    tree: list[int] = []
    gap = np.abs(pos[:, 1] - pos[:, 0])
    for e in np.argsort(gap, kind="stable").tolist():
        p, q = int(pos[e, 0]), int(pos[e, 1])
        if uf.union(p, q):
            tree.append(e)
            adj[p].append((q, e, False))
            adj[q].append((p, e, True))  # traversed backwards: inverse

    def walk(start: int) -> None:
        reached[start] = True
        queue = deque([start])
        while queue:
            p = queue.popleft()
            for q, e, backwards in adj[p]:
                if not reached[q]:
                    reached[q] = True
                    poses[q] = poses[p] @ (geo.inv_T(T[e]) if backwards else T[e])
                    queue.append(q)

    poses[0] = np.eye(4) if T_world_first is None else np.asarray(T_world_first, dtype=np.float64)
    walk(0)
    connected = reached.copy()
    filled: list[int] = []
    while fill_gaps and not reached.all():
        q = int(np.argmin(reached))  # every frame before it is placed
        step = geo.relative_pose(poses[q - 2], poses[q - 1]) if q >= 2 else np.eye(4)
        poses[q] = poses[q - 1] @ step
        filled.append(q)
        walk(q)
    return Chain(poses, connected, _bridges(frame_ids, pos, gap, tree, filled))


def _bridges(frame_ids: NDArray[np.int64], pos: NDArray[np.int64], gap: NDArray[np.int64], tree: list[int],
             filled: list[int]) -> list[dict]:
    """How each consecutive pair (k, k+1) without a gap-1 edge is crossed: by a
    constant-velocity step, or else by the shortest tree edge spanning it (every tree path
    from k to k+1 crosses the cut between them)."""
    has_step = np.zeros(max(len(frame_ids) - 1, 0), bool)
    has_step[pos[gap == 1].min(axis=1)] = True
    missing = np.flatnonzero(~has_step)
    method: list[str | None] = [None] * len(missing)
    for q in filled:
        method[int(np.searchsorted(missing, q - 1))] = "constant velocity"
    nxt = list(range(len(missing) + 1))  # next missing step not yet named (path halving)

    def first_open(m: int) -> int:
        while nxt[m] != m:
            nxt[m] = nxt[nxt[m]]
            m = nxt[m]
        return m

    for m, name in enumerate(method):
        if name is not None:
            nxt[m] = m + 1
    for e in sorted((e for e in tree if gap[e] > 1), key=lambda e: int(gap[e])):
        a, b = sorted(int(p) for p in pos[e])
        m, stop = first_open(int(np.searchsorted(missing, a))), int(np.searchsorted(missing, b))
        while m < stop:
            method[m] = f"edge {int(frame_ids[pos[e, 0]])}->{int(frame_ids[pos[e, 1]])}"
            nxt[m] = m + 1
            m = first_open(m + 1)
    return [{"i": int(frame_ids[k]), "j": int(frame_ids[k + 1]), "method": name}
            for k, name in zip(missing.tolist(), method) if name is not None]


def chain_steps(steps: ArrayLike, T_world_first: ArrayLike | None = None) -> NDArray[np.float64]:
    """Dead reckoning: (N + 1, 4, 4) poses from N consecutive relative poses ``T_k_{k+1}``."""
    steps = np.asarray(steps, dtype=np.float64).reshape(-1, 4, 4)
    n = len(steps) + 1
    pos = np.stack([np.arange(n - 1), np.arange(1, n)], axis=1)
    return chain_edges(np.arange(n), pos, steps, T_world_first).poses
