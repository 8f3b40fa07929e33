"""GTSAM factors from edges: measurements, robust noise models, the prior, values.

GTSAM's ``BetweenFactorPose3`` uses the project's right perturbation with rotation first,
so an edge's covariance (project order (v, w)) is only re-ordered
(:func:`data.geometry.cov_to_gtsam`). Variable keys are the frame ids themselves.
"""

from __future__ import annotations

from collections.abc import Sequence

import gtsam
import numpy as np
from numpy.typing import NDArray

from ctcvo.data import geometry as geo
from ctcvo.posegraph.edges import GraphError

# Huber width on an edge's whitened residual norm, from chi(6): a correct edge stays below 3.55
# in 95 % of cases (never varied in bench/README.md)
HUBER_K = 3.0
# standard deviations (rad, m) of the prior that fixes the first pose: a gauge fix, never varied
PRIOR_SIGMA_ROT_RAD = 1e-6
PRIOR_SIGMA_TRANS_M = 1e-6


def pose3s(Ts: NDArray[np.float64]) -> list:
    """``gtsam.Pose3`` objects of (N, 4, 4) transforms (orthonormalised first)."""
    return [gtsam.Pose3(T) for T in geo.orthonormalize(Ts)]


def _covs_gtsam(covs: NDArray[np.float64]) -> NDArray[np.float64]:
    """(E, 6, 6) covariances re-ordered to GTSAM's (w, v) with the conversion module's
    vector permutation applied to rows and columns (batched cov_to_gtsam)."""
    c = np.asarray(covs, dtype=np.float64).reshape(-1, 6, 6)
    c = geo.vec_to_gtsam(geo.vec_to_gtsam(c).transpose(0, 2, 1))
    return 0.5 * (c + c.transpose(0, 2, 1))


def _robust(base, kernel: str):
    if kernel == "none":
        return base
    return gtsam.noiseModel.Robust.Create(gtsam.noiseModel.mEstimator.Huber.Create(HUBER_K), base)


def prior_factor(frame_id: int, T: NDArray[np.float64]):
    """The prior that fixes frame ``frame_id`` at ``T`` (sigmas ``PRIOR_SIGMA_*``)."""
    sig = np.array([PRIOR_SIGMA_ROT_RAD] * 3 + [PRIOR_SIGMA_TRANS_M] * 3)  # GTSAM order (w, v)
    return gtsam.PriorFactorPose3(int(frame_id), geo.to_gtsam_pose3(T), gtsam.noiseModel.Diagonal.Sigmas(sig))


def between_factors(ids: NDArray[np.int64], measured: Sequence, covs: NDArray[np.float64], kernel: str) -> list:
    """One ``BetweenFactorPose3`` per edge (``ids`` (E, 2) frame ids, ``measured`` their
    ``gtsam.Pose3``, ``covs`` (E, 6, 6) project order) under the robust ``kernel``; noise
    models are shared between edges with identical covariances."""
    if len(ids) == 0:
        return []
    cache: dict[bytes, object] = {}
    out = []
    for (i, j), P, c in zip(ids.tolist(), measured, _covs_gtsam(covs)):
        key = c.tobytes()
        model = cache.get(key)
        if model is None:
            model = cache[key] = _robust(gtsam.noiseModel.Gaussian.Covariance(c), kernel)
        out.append(gtsam.BetweenFactorPose3(i, j, P, model))
    return out


def values_of(frame_ids: NDArray[np.int64], poses: NDArray[np.float64]) -> gtsam.Values:
    """``gtsam.Values`` holding ``poses`` (N, 4, 4) under the keys ``frame_ids``."""
    values = gtsam.Values()
    for k, P in zip(np.asarray(frame_ids).tolist(), pose3s(poses)):
        values.insert(k, P)
    return values


def poses_from_values(frame_ids: NDArray[np.int64], values) -> NDArray[np.float64]:
    """(N, 4, 4) poses of the (sorted) frame ids; the values hold exactly these Pose3 keys."""
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


