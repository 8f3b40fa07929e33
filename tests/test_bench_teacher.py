"""bench/teacher.py: ORB-SLAM3's runs alternate with the teacher's (neither is run here)."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

import bench.teacher as BT
from bench import orbslam3_peer
from ctcvo.data import geometry as geo


class _Seq:
    """Ten frames on a gentle curve, as much of a sequence as bench_scene reads."""

    name = "fake"

    def __init__(self) -> None:
        self.poses = np.stack([geo.se3_exp([0.05 * k, 0.01 * k * k, 0, 0, 0.02 * k, 0]) for k in range(10)])

    def __len__(self) -> int:
        return 10

    def times(self) -> np.ndarray:
        return np.arange(10) / 10.0

    def ids(self) -> np.ndarray:
        return np.arange(10)

    def groundtruth(self) -> np.ndarray:
        return self.poses


@pytest.mark.parametrize("teacher_runs, orb_runs", [(3, 3), (2, 3), (3, 1)])
def test_orbslam3_runs_alternate_with_the_teachers(monkeypatch, teacher_runs: int, orb_runs: int) -> None:
    seq, order = _Seq(), []

    def teacher_run(s):
        order.append("teacher")
        run = SimpleNamespace(poses=s.poses, edges=[], seconds=2.0, bridges=[], kinds={})
        return run, s.poses, 0.5

    def each_run(s, vocabulary, runs, figures):
        assert runs == 1
        order.append("orb")
        return [{"fps": 10.0 + len(order), "tracking_fps": 20.0, "lost_frames": 0}]

    monkeypatch.setattr(BT, "_open_sequence", lambda *a: seq)
    monkeypatch.setattr(BT, "_teacher_run", teacher_run)
    monkeypatch.setattr(orbslam3_peer, "each_run", each_run)
    rows = BT.bench_scene("fake", None, [], orbslam3_vocabulary="VOC.txt", orbslam3_runs=orb_runs,
                          teacher_runs=teacher_runs)
    pairs = min(teacher_runs, orb_runs)
    assert order[:2 * pairs] == ["teacher", "orb"] * pairs
    assert order.count("teacher") == teacher_runs and order.count("orb") == orb_runs
    orb = rows[-1]
    assert orb["method"] == orbslam3_peer.METHOD and orb["runs"] == orb_runs
    assert rows[1]["fps"] == pytest.approx(10 / 2.5)  # the graph's: teacher and solve
