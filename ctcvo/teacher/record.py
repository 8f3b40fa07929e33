"""The result of one edge estimate, and the diagnostics of how it was made."""

from __future__ import annotations

from collections import Counter
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray


@dataclass
class DenseOutcome:
    """One dense alignment of an edge: whether its result was taken, how many pixels paired
    (``fitness``, a fraction), and how far it moved the estimate it started from."""

    accepted: bool
    fitness: float = 0.0
    iterations: int | None = None
    rmse_m: float | None = None
    shift_m: float = 0.0
    shift_deg: float = 0.0
    weight: float | None = None
    """Information fusion: the fraction of the dense step taken (None: not fused)."""
    stale_stream: bool = False
    """One of the edge's frames has its colour and depth from different moments."""
    hybrid: DenseOutcome | None = None
    """The hybrid (photometric + depth) stage after this one, when it ran."""


@dataclass
class EdgeDiagnostics:
    """How an edge was made: ``path`` (``tracks``, ``guided``, ``exhaustive``, ``wide``,
    ``crosscheck``, ``depth``, ``rgbd``, ``dense`` or ``none``), the keypoint attempt that gave
    the sparse estimate (``source``) and why each later step did or did not take over."""

    path: str = "none"
    source: str | None = None
    sparse_status: str | None = None
    """A fallback's edge: the status of the sparse estimate it replaced."""
    start: str | None = None
    """``span`` when the rgbd fallback's second start (the depth moments' velocity) won."""
    depth_step: str | None = None
    rgbd_fallback: str | None = None
    dense_fallback: str | None = None
    """Status of the depth-alone step, the rgbd and the dense fallback when they failed."""
    trans_m: float = float("nan")
    rot_deg: float = float("nan")
    rmse_m: float | None = None
    conditioning: float | None = None
    error: str | None = None
    dense: DenseOutcome | None = None
    mixed_moments: bool = False
    """A longer window edge into or out of a frame whose colour and depth show different
    moments (one stream's image repeats an earlier frame's): its keypoints belong to one
    moment, its depth and the ground truth to the other (the covariance model's
    ``MIXED_MOMENTS_SCALES``)."""


@dataclass
class EdgeEstimate:
    """Result of one pair. ``status`` is ``ok`` or the reason of failure."""

    i: int
    j: int
    status: str
    T_i_j: NDArray[np.float64] | None = None
    cov: NDArray[np.float64] | None = None
    matches: int = 0
    inliers: int = 0
    inlier_ratio: float = 0.0
    rmse_px: float = float("nan")
    diag: EdgeDiagnostics = field(default_factory=EdgeDiagnostics)
    inlier_pairs: NDArray[np.int64] | None = None
    """(M, 2) keypoint indices (in i, in j) of the inlier correspondences."""
    inlier_points: NDArray[np.float64] | None = None
    """(M, 6) ``(u_i, v_i, z_i, u_j, v_j, z_j)`` of the inlier pairs as the estimate used them
    (keyframe and loop edges; :func:`teacher.observations.attach_points`)."""

    @property
    def ok(self) -> bool:
        return self.status == "ok"


def count_by_kind(edges: list[EdgeEstimate], kinds: dict[tuple[int, int], str], ok: bool) -> dict[str, int]:
    """The number of good (``ok``) or failed edges of each edges.csv ``kind`` present, by kind
    (a pair ``kinds`` lacks is a ``window`` edge): report.json's counts, batch's and online's."""
    return dict(sorted(Counter(kinds.get((e.i, e.j), "window") for e in edges if e.ok == ok).items()))
