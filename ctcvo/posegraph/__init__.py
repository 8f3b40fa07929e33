"""Pose-graph fusion of teacher and learner relative-pose edges with GTSAM.

* :mod:`posegraph.config` - :class:`PoseGraphConfig` and presets;
* :mod:`posegraph.edges` - edge arrays, validation, residuals, connectivity, bridges;
* :mod:`posegraph.factors` - GTSAM factors, robust noise models, the prior;
* :mod:`posegraph.solvers` - batch LM, incremental ISAM2, determinacy, marginals;
* :mod:`posegraph.robust` - per-source covariance scales and outlier masks;
* :mod:`posegraph.graph` - :func:`~posegraph.graph.solve`, the whole robust solve;
* :mod:`posegraph.sources` - reading teacher / learner folders and edge files;
* :mod:`posegraph.fusion` - which edges of which source enter the fused graph;
* :mod:`posegraph.calibration` - per-gap teacher covariance scales (``posegraph calibrate``);
* :mod:`posegraph.report` - metrics table (ATE, RPE, se(3) L2, consistency, calibration);
* :mod:`posegraph.plots` - figures after the paper;
* :mod:`posegraph.online` - the graph frame by frame (``ctcvo online``);
* :mod:`posegraph.optimize` - the ``posegraph optimize`` stage;
* :mod:`posegraph.cli` - the thin command line.
"""

from ctcvo.posegraph.config import DEFAULT, PRESETS, PoseGraphConfig

__all__ = ["DEFAULT", "PRESETS", "PoseGraphConfig"]
