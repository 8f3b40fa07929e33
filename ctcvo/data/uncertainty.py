"""Covariance consistency figures: squared Mahalanobis distance (NEES), its mean against the
degrees of freedom, and the coverage of the 1-sigma and 2-sigma chi-square regions.

One implementation for every stage (the learner's calibration, ``learner predict``'s report
and the pose graph's table). Residuals are 6-vectors in the project tangent order (v, w)
with covariances in the same order (docs/conventions.md); nothing here depends on the order
as long as residual and covariance share it.

A consistent estimator has ``E[d^T C^-1 d] = dof`` (NEES / dof = 1) and puts 68.27 % /
95.45 % of its errors inside the chi-square(dof) quantiles of those masses (the masses of
+-1 and +-2 sigma of a Gaussian).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray
from scipy.stats import chi2, norm

#: Probability masses of +-1 and +-2 standard deviations of a Gaussian (68.27 %, 95.45 %).
MASS_1SIGMA = float(norm.cdf(1.0) - norm.cdf(-1.0))
MASS_2SIGMA = float(norm.cdf(2.0) - norm.cdf(-2.0))


def chi2_region(mass: float, dof: int = 6) -> float:
    """Squared-distance bound of the chi-square(``dof``) region holding ``mass``."""
    return float(chi2.ppf(mass, dof))


#: chi-square (6 dof) bounds of the 1-sigma and 2-sigma masses (7.04, 12.85).
CHI2_6_1SIGMA = chi2_region(MASS_1SIGMA)
CHI2_6_2SIGMA = chi2_region(MASS_2SIGMA)
#: Median of chi-square with 6 dof (5.348).
CHI2_6_MEDIAN = float(chi2.median(6))


def mahalanobis2(r: NDArray[np.float64], cov: NDArray[np.float64]) -> NDArray[np.float64]:
    """Squared Mahalanobis distances (E,) of residuals (E, D) under covariances (E, D, D)."""
    r = np.asarray(r, dtype=np.float64)
    if len(r) == 0:
        return np.zeros(0)
    cov = np.broadcast_to(np.asarray(cov, dtype=np.float64), r.shape + r.shape[-1:])
    return np.einsum("ei,ei->e", r, np.linalg.solve(cov, r[..., None])[..., 0])


def nees_stats(d2: NDArray[np.float64], dof: int = 6) -> dict[str, float | None]:
    """Mean NEES, its ratio to ``dof`` and the 1-sigma / 2-sigma coverage of squared
    Mahalanobis distances ``d2`` (E,); every value ``None`` for no distances."""
    d2 = np.asarray(d2, dtype=np.float64)
    if len(d2) == 0:
        return {"nees_mean": None, "nees_over_dof": None, "coverage_1sigma": None, "coverage_2sigma": None}
    lo, hi = chi2_region(MASS_1SIGMA, dof), chi2_region(MASS_2SIGMA, dof)
    return {"nees_mean": float(np.mean(d2)), "nees_over_dof": float(np.mean(d2) / dof),
            "coverage_1sigma": float(np.mean(d2 <= lo)), "coverage_2sigma": float(np.mean(d2 <= hi))}


__all__ = ["CHI2_6_1SIGMA", "CHI2_6_2SIGMA", "CHI2_6_MEDIAN", "MASS_1SIGMA", "MASS_2SIGMA", "chi2_region",
           "mahalanobis2", "nees_stats"]
