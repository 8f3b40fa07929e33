"""The learner: a CTCNet-style CNN+LSTM trained on teacher labels with composite
transformation constraints, and Monte-Carlo-dropout prediction of edges with covariances.

Modules: :mod:`learner.config` (presets), :mod:`learner.se3` (torch SE(3)),
:mod:`learner.model`, :mod:`learner.loss`, :mod:`learner.dataset` (frames + labels),
:mod:`learner.augment`, :mod:`learner.batches`, :mod:`learner.evaluate`,
:mod:`learner.checkpoint`, :mod:`learner.device`, :mod:`learner.train` (``fit``),
:mod:`learner.mcdropout` (MC-dropout edges), :mod:`learner.calibrate` (``calibrate``),
:mod:`learner.predict` (``predict``), :mod:`learner.online` (frame by frame),
:mod:`learner.cli`.
"""
