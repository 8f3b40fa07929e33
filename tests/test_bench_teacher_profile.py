"""bench/teacher_profile.py: its config overrides and its paired comparison of two runs'
labels against the ground truth (the profiling itself is a benchmark, not tested here)."""

from __future__ import annotations

import numpy as np
import pytest

from bench import teacher_profile as tp
from ctcvo.data import geometry as geo


def test_overrides_take_the_fields_type():
    assert tp.parse_set(["p2p_cov_stride=8", "dense_blend=0.5", "subpixel=true"]) == \
        {"p2p_cov_stride": 8, "dense_blend": 0.5, "subpixel": True}
    with pytest.raises(SystemExit, match="no field 'nope'"):
        tp.parse_set(["nope=1"])


def test_sensor_overrides_take_the_fields_type():
    assert tp.parse_sensor(["rolling_shutter_s=0", "noise_free=true", "depth_time_offset_s=-0.01,0"]) == \
        {"rolling_shutter_s": 0.0, "noise_free": True, "depth_time_offset_s": (-0.01, 0.0)}
    with pytest.raises(SystemExit, match="no field 'nope'"):
        tp.parse_sensor(["nope=1"])
    with pytest.raises(SystemExit, match="takes a synthetic scene"):
        tp.open_profiled("../somewhere/redkitchen", "0:10", {"rolling_shutter_s": 0.0})


def _save(path, moves_mm):
    """Three frames on a line 10 cm apart; edges (0,1), (1,2), (0,2), each label off the
    truth by ``moves_mm`` along x."""
    gt = np.stack([geo.make_T(np.eye(3), [0.1 * k, 0, 0]) for k in range(3)])
    ij = np.array([(10, 11), (11, 12), (10, 12)])
    T = np.stack([geo.relative_pose(gt[i - 10], gt[j - 10]) @ geo.make_T(np.eye(3), [m / 1000, 0, 0])
                  for (i, j), m in zip(ij, moves_mm)])
    np.savez(path, ij=ij, T=T, cov=np.tile(np.eye(6), (3, 1, 1)), ids=np.array([10, 11, 12]), gt=gt)


def test_compare_reports_paired_squared_error_differences(tmp_path, capsys):
    _save(tmp_path / "a.npz", [1.0, 1.0, 2.0])
    _save(tmp_path / "b.npz", [2.0, 1.0, 2.0])
    tp.compare(str(tmp_path / "a.npz"), str(tmp_path / "b.npz"))
    out = capsys.readouterr().out
    assert "gap 1: 2 edges, trans RMSE 1.000 -> 1.581 mm, paired difference of squared errors +1.5000" in out
    assert "all edges: 3 edges" in out and "+1.0000" in out
    assert "max 1.0000 mm; 1 of 3 edges" in out
    # A's labels are 1 % long at both gaps; three frames are too few for the drift
    assert "A: drift of the chained gap-1 edges over 30 frames - (a gap-1 edge is missing, or too few frames); " \
           "translation scale against the truth per gap 1: 1.0100, 2: 1.0100; " \
           "rotation scale per gap 1: -, 2: -; " \
           "translation error per gap, median / max: 1: 1.00 / 1.0, 2: 2.00 / 2.0 mm" in out
    assert "gap 1: 2 edges, rot RMSE 0.0000 -> 0.0000 deg, paired difference of squared errors +0.000000" in out
    assert "B: " in out and "median / max: 1: 1.50 / 2.0, 2: 2.00 / 2.0 mm" in out


def test_compare_reports_the_drift_of_the_chained_gap1_edges(tmp_path, capsys):
    """41 frames 10 cm apart along x, every gap-1 label 1 mm too long: over 30 frames the
    chain is 30 mm off, at every one of the 11 pairs; no rotation."""
    n = 41
    gt = np.stack([geo.make_T(np.eye(3), [0.1 * k, 0, 0]) for k in range(n)])
    ij = np.array([(k, k + 1) for k in range(n - 1)])
    T = np.stack([geo.make_T(np.eye(3), [0.101, 0, 0])] * (n - 1))
    for name in ("a", "b"):
        np.savez(tmp_path / f"{name}.npz", ij=ij, T=T, cov=np.tile(np.eye(6), (n - 1, 1, 1)), ids=np.arange(n), gt=gt)
    tp.compare(str(tmp_path / "a.npz"), str(tmp_path / "b.npz"))
    out = capsys.readouterr().out
    assert "B: drift of the chained gap-1 edges over 30 frames 30.0 mm / 0.00 deg; " \
           "translation scale against the truth per gap 1: 1.0100" in out


def test_compare_reports_rotation_errors_and_their_scale(tmp_path, capsys):
    """Frames turning 2 deg each about y; A's gap-1 labels turn 2 % too far (0.04 deg off),
    B's are exact: the rotation RMSE, its paired difference and A's rotation scale."""
    n = 4
    rot = lambda deg: geo.make_T(geo.se3_exp([0, 0, 0, 0, np.radians(deg), 0])[:3, :3], [0, 0, 0])
    gt = np.stack([rot(2.0 * k) for k in range(n)])
    ij = np.array([(k, k + 1) for k in range(n - 1)])
    for name, deg in (("a", 2.04), ("b", 2.0)):
        T = np.stack([rot(deg)] * (n - 1))
        np.savez(tmp_path / f"{name}.npz", ij=ij, T=T, cov=np.tile(np.eye(6), (n - 1, 1, 1)), ids=np.arange(n), gt=gt)
    tp.compare(str(tmp_path / "a.npz"), str(tmp_path / "b.npz"))
    out = capsys.readouterr().out
    assert "gap 1: 3 edges, rot RMSE 0.0400 -> 0.0000 deg, paired difference of squared errors -0.001600 +- 0.000000" in out
    assert "A: " in out and "rotation scale per gap 1: 1.0200;" in out
    assert "B: " in out and out.split("B: ")[1].count("rotation scale per gap 1: 1.0000;") == 1


def test_sensor_off_turns_every_part_off_and_takes_overrides_on_top():
    from ctcvo.data.synthetic.config import SensorConfig

    off = tp.parse_sensor(["depth_bias_coeff=0.001"], all_off=True)
    assert off["depth_bias_coeff"] == 0.001 and off["rolling_shutter_s"] == 0.0 and off["rgb_focal_scale"] == 1.0
    assert set(tp.SENSOR_OFF) <= {f for f in SensorConfig.__dataclass_fields__}
    assert tp.parse_sensor([], all_off=False) == {}


def test_why_counts_each_attempts_failure_and_compares_the_refused_estimate(capsys):
    """``--why``: per gap, the paths and the chain of attempt statuses of the edges the first
    attempt did not make; a refused estimate's error beside the label that replaced it."""
    from ctcvo.teacher.odometry import EdgeEstimate

    gt = np.stack([geo.make_T(np.eye(3), [0.1 * k, 0, 0]) for k in range(3)])
    off = lambda i, j, mm: geo.relative_pose(gt[i], gt[j]) @ geo.make_T(np.eye(3), [mm / 1000, 0, 0])

    def est(i, j, status, source, T=None, path=None):
        e = EdgeEstimate(i, j, status, T_i_j=T, inliers=100, inlier_ratio=0.9, rmse_px=1.7 if status != "ok" else 0.8)
        e.info["source"] = source
        if path:
            e.info["path"] = path
        return e

    r = tp.Reasons()
    first_ok = est(0, 1, "ok", "guided", off(0, 1, 1.0), "guided")
    r.edges.append((first_ok, [first_ok]))
    refused = est(0, 2, "high_rmse", "tracks", off(0, 2, 20.0))
    final = est(0, 2, "ok", "guided", off(0, 2, 4.0), "rgbd")
    r.edges.append((final, [refused, est(0, 2, "few_matches", "guided")]))
    r.report(np.arange(3), gt)
    out = capsys.readouterr().out
    assert "gap 1: 1 edges; paths guided 1\n" in out
    assert "gap 2: 1 edges; paths rgbd 1" in out and "1  tracks:high_rmse > guided:few_matches -> rgbd" in out
    assert "high_rmse               1    100 / 0.90 / 1.70  refused 20.00 / 20.00  label 4.00 / 4.00" in out
