"""Pose-graph configuration: one frozen dataclass, named presets as instances.

Change a preset with :func:`dataclasses.replace`, never by mutation::

    cfg = dataclasses.replace(DEFAULT, kernel="none", solver="isam2")

Tuned values no user needs to change are module constants next to the code that uses
them (:mod:`posegraph.factors`, :mod:`posegraph.solvers`, :mod:`posegraph.robust`,
:mod:`posegraph.fusion`).
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

from ctcvo.data.errors import ConfigError

SOURCES = ("auto", "teacher", "learner", "fused")
LEARNER_EDGES = ("bridge", "all")
SOLVERS = ("lm", "isam2")
KERNELS = ("huber", "none")


@dataclass(frozen=True)
class PoseGraphConfig:
    """Which edges enter the graph, how it is solved and which edges are rejected."""

    sources: str = "auto"
    """Edge sets in the graph: ``teacher``, ``learner``, ``fused`` (both) or ``auto``
    (every source given)."""

    learner_edges: str = "bridge"
    """``bridge``: other sources' edges join the teacher's only between frames its edges
    leave apart; ``all``: every edge, weighed by its calibrated covariance."""

    solver: str = "lm"
    """``lm`` (batch Levenberg-Marquardt) or ``isam2`` (incremental, frame by frame)."""

    kernel: str = "huber"
    """Robust kernel on every edge: ``huber`` or ``none`` (plain least squares)."""

    residual_threshold: float = 20.0
    """Edges whose whitened residual norm after the first solve exceeds this are outliers
    (gross errors only); ``inf`` disables the outlier pass."""

    calibrate: bool = True
    """Estimate one covariance scale per edge source from the whitened residuals before
    the outlier pass, so that an overconfident source cannot pull the graph onto itself."""

    marginals: bool = False
    """Compute the marginal covariance of every pose (``marginals.npz``)."""

    plots: bool = True
    """Write the PNG figures."""

    def __post_init__(self) -> None:
        for name, allowed in (("sources", SOURCES), ("learner_edges", LEARNER_EDGES), ("solver", SOLVERS),
                              ("kernel", KERNELS)):
            if getattr(self, name) not in allowed:
                raise ConfigError(f"{name} must be one of {', '.join(allowed)}, got {getattr(self, name)!r}")
        if not self.residual_threshold > 0:
            raise ConfigError(f"residual_threshold must be positive (inf: no outlier pass), got {self.residual_threshold}")

    def to_dict(self) -> dict:
        """Plain JSON-able dict (infinities as strings)."""
        return {k: str(v) if isinstance(v, float) and math.isinf(v) else v for k, v in dataclasses.asdict(self).items()}


#: Robust Huber LM with per-source covariance calibration and residual-based outlier removal.
DEFAULT = PoseGraphConfig()
#: Plain least squares with the covariances as given: no kernel, no calibration, no
#: outlier rejection (for known-answer tests).
PLAIN = PoseGraphConfig(kernel="none", residual_threshold=float("inf"), calibrate=False)
#: Incremental (online) mode.
ONLINE = PoseGraphConfig(solver="isam2")

PRESETS: dict[str, PoseGraphConfig] = {"default": DEFAULT, "plain": PLAIN, "online": ONLINE}
