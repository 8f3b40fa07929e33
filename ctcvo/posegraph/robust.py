"""Robustness to wrong covariances and wrong edges: one covariance scale per edge source
from the whitened residuals (variance components), and the masks of outlier edges."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from ctcvo.data import uncertainty
from ctcvo.posegraph.edges import position_labels, united_components

#: Median of the chi-square distribution with 6 degrees of freedom (5.348).
CHI2_6_MEDIAN = uncertainty.CHI2_6_MEDIAN
# per-source calibration: at most this many re-solves; scales move only while some source's
# factor is outside [1 / (1 + tol), 1 + tol] (a median of a few hundred residuals is good to
# about 5 %); a source with fewer edges keeps scale 1; scales stay within the range (an exactly
# consistent source would shrink towards 0). The calibration was measured on redkitchen 0:160
# (bench/README.md, "Pose graph"); these bounds were never varied
CALIBRATION_ITERATIONS = 6
CALIBRATION_TOLERANCE = 0.25
CALIBRATION_MIN_EDGES = 20
CALIBRATION_SCALE_RANGE = (1e-2, 1e6)
# covariance inflation of an outlier edge kept because its removal would disconnect the graph
# (down-weighting every outlier instead measured the same as removal, bench/README.md
# "`--outlier-action downweight`")
DOWNWEIGHT_FACTOR = 100.0


def source_scale_factors(res: NDArray[np.float64], src: NDArray[np.int64], n_src: int,
                         redundancy: float) -> tuple[NDArray[np.float64], NDArray[np.int64]]:
    """Per source: (factor by which its covariances should grow, number of its edges).

    ``median(r^2) / (CHI2_6_MEDIAN * redundancy)`` over the source's whitened residuals
    ``res`` (``src`` (E,) source index of each edge); 1 for a source with fewer than
    ``CALIBRATION_MIN_EDGES`` edges or when the graph has (almost) no redundancy (residuals
    then say nothing about the noise)."""
    factor, counts = np.ones(n_src), np.zeros(n_src, np.int64)
    for k in range(n_src):
        r = res[src == k]
        counts[k] = len(r)
        if len(r) >= CALIBRATION_MIN_EDGES and redundancy > 0.05:
            factor[k] = max(float(np.median(r**2)), 1e-300) / (CHI2_6_MEDIAN * redundancy)
    return factor, counts


def _keep_connected(n_frames: int, pos: NDArray[np.int64], drop: NDArray[np.bool_],
                    order: NDArray[np.int64]) -> NDArray[np.bool_]:
    """Of the edges marked in ``drop``, return those that must stay (down-weighted) to
    keep the graph connected; tried in ``order`` (best first)."""
    keep = np.zeros(len(pos), bool)
    if not drop.any():
        return keep
    labels = position_labels(n_frames, pos[~drop])
    if len(np.unique(labels)) == 1:
        return keep
    uf = united_components(labels)
    for n in np.asarray(order).tolist():
        if drop[n] and uf.union(int(pos[n, 0]), int(pos[n, 1])):
            keep[n] = True
    return keep


def outlier_masks(n_frames: int, pos: NDArray[np.int64], flagged: NDArray[np.bool_],
                  order: NDArray[np.int64]) -> tuple[NDArray[np.bool_], NDArray[np.bool_]]:
    """(drop, downweight) masks of the ``flagged`` edges: removed, except those whose removal
    would disconnect the graph (tried in ``order``, best first), which are down-weighted."""
    keep = _keep_connected(n_frames, pos, flagged, order)
    return flagged & ~keep, keep
