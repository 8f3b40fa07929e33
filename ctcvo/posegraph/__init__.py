"""Pose-graph fusion of teacher and learner relative-pose edges with GTSAM.

* :mod:`posegraph.config` - :class:`PoseGraphConfig` and presets;
* :mod:`posegraph.graph` - factor graph, LM / ISAM2 solve, outlier handling, marginals;
* :mod:`posegraph.sources` - reading teacher / learner folders and edge files;
* :mod:`posegraph.report` - metrics table (ATE, RPE, se(3) L2, consistency, calibration);
* :mod:`posegraph.plots` - figures after the paper;
* :mod:`posegraph.optimize` - the ``posegraph optimize`` stage;
* :mod:`posegraph.cli` - the thin command line.
"""

from ctcvo.posegraph.config import DEFAULT, PRESETS, PoseGraphConfig

__all__ = ["DEFAULT", "PRESETS", "PoseGraphConfig"]
