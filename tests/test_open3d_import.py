"""ctcvo.data.open3d_import: Open3D without its ML datasets and web viewer until they are used."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]

_SCRIPT = """
import sys
from ctcvo.data.open3d_import import o3d
import numpy as np
heavy = ("sklearn", "pandas", "dash", "plotly")
print("loaded-before", sorted(m for m in heavy if m in sys.modules))
# what the teacher uses works
pts = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.eye(3)))
print("points", len(pts.points), callable(o3d.t.pipelines.odometry.compute_odometry_result_point_to_plane))
# the deferred subpackages are still there, loaded on first use
print("viz", callable(o3d.visualization.draw_plotly), "dash" in sys.modules)
import open3d.ml.datasets
import open3d.visualization.gui
print("ml", o3d.ml.datasets is sys.modules["open3d.ml.datasets"], type(sys.modules["open3d.ml"]).__name__)
"""


def test_open3d_defers_ml_and_visualization_until_used() -> None:
    out = subprocess.run([sys.executable, "-c", _SCRIPT], cwd=REPO, capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    lines = dict(line.split(" ", 1) for line in out.stdout.splitlines())
    assert lines["loaded-before"] == "[]"
    assert lines["points"] == "3 True"
    assert lines["viz"] == "True True"
    assert lines["ml"] == "True module"
