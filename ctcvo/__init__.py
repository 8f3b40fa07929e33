"""ctcvo: self-supervised RGB-D visual odometry after CTCNet.

Stages (each a subpackage with a library entry point and a ``ctcvo <stage>`` command):
``ctcvo.teacher`` (classical odometry labels), ``ctcvo.learner`` (CNN + LSTM trained on
them), ``ctcvo.posegraph`` (GTSAM fusion and the error report); ``ctcvo.data`` holds the
readers, formats and conventions, and ``ctcvo.pipeline`` composes the stages (demo, online).
"""

__version__ = "0.2.0"
