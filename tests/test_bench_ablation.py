"""bench/ablation.py: the teacher as a second reference, and the summary over seeds."""

from __future__ import annotations

import numpy as np
import pytest

from bench import ablation
from ctcvo.data import geometry as geo
from ctcvo.data.formats import Trajectory, write_tum
from ctcvo.data.metrics import trajectory_report


def _walk(n: int, rng: np.random.Generator, noise: float = 0.0, base: np.ndarray | None = None) -> np.ndarray:
    """(n, 4, 4) poses chained from steps of ~1 cm and ~0.5 deg (``base``: perturb those steps)."""
    poses = [np.eye(4)]
    for k in range(n - 1):
        step = (geo.relative_pose(base[k], base[k + 1]) if base is not None
                else geo.se3_exp(np.r_[0.01, 0.002, 0.0, 0.0, 0.009, 0.0]))
        poses.append(poses[-1] @ step @ geo.se3_exp(noise * rng.standard_normal(6)))
    return np.array(poses)


@pytest.fixture
def trajs():
    rng = np.random.default_rng(0)
    t = np.arange(40) * 0.1
    gt = _walk(40, rng)
    teacher = _walk(40, rng, 0.004, gt)
    learner = _walk(40, rng, 0.002, gt)
    return Trajectory(t, gt), Trajectory(t, teacher), Trajectory(t, learner)


def test_versus_teacher_ratio_and_second_reference(trajs):
    gt, teacher, learner = trajs
    t_row = trajectory_report(gt, teacher)
    row = ablation.versus_teacher(trajectory_report(gt, learner), learner, teacher, t_row)
    assert row["se3_l2_x_teacher"] == pytest.approx(row["se3_l2_mean"] / t_row["se3_l2_mean"])
    assert row["se3_l2_x_teacher"] < 1  # half the teacher's step noise
    # against the teacher, the learner's error holds both noises: above its error against the truth
    assert row["vs_teacher"]["se3_l2_mean"] > row["se3_l2_mean"]
    same = ablation.versus_teacher(t_row, teacher, teacher, t_row)
    assert same["se3_l2_x_teacher"] == pytest.approx(1.0)
    assert same["vs_teacher"]["se3_l2_mean"] == pytest.approx(0.0, abs=1e-9)
    assert ablation.versus_teacher({"se3_l2_mean": 1.0}, learner, None, None) == {"se3_l2_mean": 1.0}


def test_teacher_trajectory_matches_the_test_frames_by_time(tmp_path, trajs):
    gt, teacher, _ = trajs
    longer = Trajectory(np.r_[gt.timestamps, 4.0 + np.arange(5) * 0.1],
                        np.concatenate([teacher.poses, np.repeat(teacher.poses[-1:], 5, axis=0)]))
    write_tum(tmp_path / "trajectory.tum", longer)
    got = ablation.teacher_trajectory(tmp_path, Trajectory(gt.timestamps[10:], gt.poses[10:]))
    np.testing.assert_allclose(got.poses, teacher.poses[10:], atol=1e-6)
    write_tum(tmp_path / "trajectory.tum", Trajectory(gt.timestamps[:20], teacher.poses[:20]))
    with pytest.raises(SystemExit, match="covers 20 of the 40"):
        ablation.teacher_trajectory(tmp_path, gt)


def test_seed_summary_mean_and_std_per_variant():
    rows = {"teacher": {"se3_l2_mean": 9.0},
            "ctc seed 0": {"variant": "ctc", "seed": 0, "se3_l2_mean": 1.0, "se3_l2_x_teacher": 0.5},
            "ctc seed 1": {"variant": "ctc", "seed": 1, "se3_l2_mean": 3.0, "se3_l2_x_teacher": 1.5},
            "cnn-unsup seed 0": {"variant": "cnn-unsup", "seed": 0, "se3_l2_mean": 2.0}}
    s = ablation.seed_summary(rows)
    assert list(s) == ["ctc", "cnn-unsup"]
    assert s["ctc"]["seeds"] == [0, 1]
    assert s["ctc"]["se3_l2_mean"] == {"mean": 2.0, "std": 1.0, "n": 2}
    assert s["ctc"]["se3_l2_x_teacher"]["mean"] == pytest.approx(1.0)
    assert "se3_l2_x_teacher" not in s["cnn-unsup"] and s["cnn-unsup"]["se3_l2_mean"]["n"] == 1
