"""bench/drift.py: the rotation's scale and the RPE over time scales, on made-up trajectories
(no teacher or peer is run), and its table."""

from __future__ import annotations

import math

import numpy as np
import pytest

from bench import drift, tables
from ctcvo.data import geometry as geo
from ctcvo.data.formats import Trajectory


def _turning(n: int, deg_per_frame: float, m_per_frame: float = 0.01) -> np.ndarray:
    """A camera yawing ``deg_per_frame`` and moving ``m_per_frame`` forward (its own z) each frame."""
    c, s = math.cos(math.radians(deg_per_frame)), math.sin(math.radians(deg_per_frame))
    step = geo.make_T(np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]]), np.array([0.0, 0.0, m_per_frame]))
    out = [np.eye(4)]
    for _ in range(n - 1):
        out.append(out[-1] @ step)
    return np.array(out)


def test_rotation_scale_is_the_ratio_of_turned_angles():
    t = np.arange(90) / 30.0
    gt = Trajectory(t, _turning(90, 1.0))
    assert drift.rotation_scale(gt, gt, 30) == pytest.approx(1.0)
    assert drift.rotation_scale(gt, Trajectory(t, _turning(90, 0.9)), 30) == pytest.approx(0.9)
    # pairs turning less than the threshold are left out: no pair, no ratio
    assert math.isnan(drift.rotation_scale(Trajectory(t, _turning(90, 0.001)), gt, 30))


def test_drift_grows_with_the_time_scale_for_a_biased_rotation():
    t = np.arange(120) / 30.0
    gt, est = Trajectory(t, _turning(120, 1.0)), Trajectory(t, _turning(120, 0.9))
    f = drift.drift_figures(gt, est, 30)
    assert f["deltas"] == [1, 10, 30, 60, 90]
    assert np.all(np.diff(f["rpe_deg"]) > 0) and np.all(np.diff(f["rpe_m"]) > 0)
    assert f["rpe_deg"][2] == pytest.approx(3.0, rel=1e-3)  # 10 % of 30 deg
    assert f["rotation_scale_1s"] == pytest.approx(0.9)
    short = drift.drift_figures(Trajectory(t[:40], gt.poses[:40]), Trajectory(t[:40], est.poses[:40]), 30)
    assert math.isnan(short["rpe_m"][3]) and math.isnan(short["rpe_deg"][4])  # 2 s and 3 s do not fit


def test_table_rows_per_range_and_method():
    row = {"deltas": [1, 10, 30, 60, 90], "rpe_m": [0.003, 0.006, 0.011, 0.018, 0.027],
           "rpe_deg": [0.29, 0.7, 1.26, 1.82, 2.19], "rotation_scale_1s": 0.97}
    rec = {"revision": "abc", "date_utc": "2026-12-04T00:00:00", "config": {"scales_s": list(drift.SCALES_S)},
           "machine": {"cpu_count": 2, "load_average_start": [1.0], "load_average_end": [1.0]},
           "figures": {"rows": [{"range": "/d/tum/rgbd_dataset_freiburg3_teddy:0:200", "method": "teacher pose graph",
                                 **row},
                                {"range": "/d/tum/rgbd_dataset_freiburg3_teddy:0:200", "method": "ORB-SLAM3",
                                 "runs": 3, **row},
                                {"range": "/d/tum/rgbd_dataset_freiburg3_teddy:0:200", "method": "ORB-SLAM3",
                                 "runs": 0}]}}
    lines = tables.drift_table({"drift": rec})
    assert lines[0].startswith("| range | method | 1 frame | 0.33 s | 1 s | 2 s | 3 s |")
    assert "| fr3/teddy 0:200 | teacher pose graph | 3.0 / 0.29 | 6.0 / 0.70 | 11.0 / 1.26 |" in lines[2]
    assert "ORB-SLAM3, median of 3" in lines[3] and len(lines) == 6  # the run-less row is left out
