"""bench/orbslam3_peer.py: the ORB-SLAM3 row's aggregation over runs (median, min-max, lost
frames) and its table cells, on made-up runs (ORB-SLAM3 itself is not run)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from bench import orbslam3_peer as P
from bench import tables


def _run(ate: float, rpe: float, fps: float, lost: int) -> dict:
    return {"ate_rmse_m": ate, "rpe_trans_rmse_m": rpe, "rpe_rot_rmse_deg": 10 * rpe, "rpe_1s_trans_m": 3 * rpe,
            "rpe_1s_rot_deg": 20 * rpe, "se3_l2_mean": rpe / 2, "fps": fps, "tracking_fps": 2 * fps,
            "lost_frames": lost}


def test_median_and_spread_over_runs():
    runs = [_run(0.030, 0.005, 10.0, 0), _run(0.034, 0.004, 12.0, 3), _run(0.031, 0.007, 9.0, 1)]
    agg = P.aggregate(runs)
    assert agg["runs"] == 3
    assert agg["ate_rmse_m"] == pytest.approx(0.031) and agg["spread"]["ate_rmse_m"] == pytest.approx([0.030, 0.034])
    assert agg["rpe_trans_rmse_m"] == pytest.approx(0.005)
    assert agg["spread"]["rpe_1s_rot_deg"] == pytest.approx([0.08, 0.14])
    assert agg["fps"] == pytest.approx(10.0) and agg["tracking_fps"] == pytest.approx(20.0)
    assert agg["lost_frames_per_run"] == [0, 3, 1] and agg["lost_frames"] == 3
    assert agg["per_run"] == runs


def test_a_run_without_metrics_is_left_out_of_them_but_its_lost_frames_count():
    broken = {"lost_frames": 150, "fps": 8.0, "tracking_fps": 16.0}  # tracked < 2 frames: no metrics
    agg = P.aggregate([_run(0.02, 0.004, 10.0, 0), _run(0.04, 0.006, 12.0, 2), broken])
    assert agg["ate_rmse_m"] == pytest.approx(0.03) and agg["spread"]["ate_rmse_m_runs"] == 2
    assert agg["fps"] == pytest.approx(10.0) and agg["spread"]["fps_runs"] == 3
    assert agg["lost_frames"] == 150
    only_broken = P.aggregate([broken])
    assert math.isnan(only_broken["ate_rmse_m"]) and only_broken["lost_frames"] == 150
    with pytest.raises(ValueError):
        P.aggregate([])


def test_one_second_in_frames():
    assert P.one_second(np.arange(100) / 30.0) == 30
    assert P.one_second(np.arange(10) * 0.1) == 10
    assert P.one_second(np.array([0.0])) == 1


def test_table_cells_show_median_spread_and_lost_frames():
    row = {"scene": "synthetic/kitchen", "frames": 300, "method": P.METHOD, "fps_vs_open3d": 4.0,
           **P.aggregate([_run(0.0047, 0.0039, 10.0, 0), _run(0.0082, 0.0040, 11.0, 2), _run(0.0060, 0.0041, 9.5, 0)])}
    cells = dict(zip(tables.TEACHER_HEAD, tables.teacher_cells(row, "")))
    assert cells["ATE mm"] == "6.0 (4.7-8.2)"
    assert cells["gap-1 RPE mm"] == "4.00 (3.90-4.10)"
    assert cells["gap-1 fails / lost frames"] == "lost 0/2/0"
    assert cells["method"].endswith("3 runs")
    single = {"scene": "synthetic/kitchen", "frames": 300, "method": "Open3D hybrid (gap 1)", "gap1_failures": 1,
              **_run(0.01, 0.002, 2.0, 0)}
    cells = dict(zip(tables.TEACHER_HEAD, tables.teacher_cells(single, "")))
    assert cells["ATE mm"] == "10.0" and cells["gap-1 fails / lost frames"] == "1"


class _Result:
    """A stand-in for run_orbslam3's result: ``ok`` frames tracked, identity poses elsewhere NaN."""

    def __init__(self, ok: np.ndarray) -> None:
        self.ok, self.fps, self.track_seconds = ok, 20.0, len(ok) / 40.0
        self.map_changed = np.zeros(len(ok), dtype=bool)

    def poses(self, use: str) -> np.ndarray:
        poses = np.tile(np.eye(4), (len(self.ok), 1, 1))
        poses[~self.ok] = np.nan
        return poses


class _Seq:
    name = "made-up"

    def __init__(self, n: int) -> None:
        self.n = n

    def __len__(self) -> int:
        return self.n

    def times(self) -> np.ndarray:
        return np.arange(self.n) / 30.0

    def groundtruth(self) -> np.ndarray:
        gt = np.tile(np.eye(4), (self.n, 1, 1))
        gt[:, 0, 3] = np.arange(self.n) * 0.01  # 1 cm per frame along x
        return gt


def test_each_run_measures_the_tracked_frames_and_drops_runs_without_figures(monkeypatch):
    tracked = [np.arange(60) < 45, np.arange(60) < 1]  # run 1 loses 15 frames, run 2 tracks one
    monkeypatch.setattr(P, "run_orbslam3", lambda seq, vocabulary, mode: _Result(tracked.pop(0)))
    seq = _Seq(60)
    row = P.orbslam3_row(seq, "VOC.txt", runs=2)
    assert row["runs"] == 2 and row["lost_frames_per_run"] == [15, 59]
    assert row["tracking_fps"] == pytest.approx(40.0)
    assert row["spread"]["ate_rmse_m_runs"] == 1 and row["rpe_trans_rmse_m"] == pytest.approx(0.01, rel=1e-6)

    def figures(seq, result):
        gt, est, lost = P.tracked(seq, result)
        return {"frames": len(est.poses), "lost": lost} if len(est.poses) >= 2 else None

    tracked[:] = [np.arange(60) < 45, np.arange(60) < 1]
    assert P.each_run(seq, "VOC.txt", 2, figures) == [{"frames": 45, "lost": 15}]
