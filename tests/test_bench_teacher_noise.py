"""bench/teacher_noise.py: the calibrated label-noise control and the crossover read-out."""

from __future__ import annotations

import json

import numpy as np
import pytest

import bench.teacher_noise as tn  # noqa: E402
from ctcvo.data import geometry as geo
from ctcvo.data.errors import VOError
from ctcvo.data.formats import read_edges_csv, read_g2o, read_tum
from ctcvo.teacher import cli


@pytest.fixture(scope="module")
def tiny_teacher(tmp_path_factory):
    out = tmp_path_factory.mktemp("teacher")
    assert cli.main(["generate", "--scene", "synthetic/tiny", "--out", str(out), "--gaps", "3",
                     "--frames", "0:16", "--workers", "1"]) == 0
    return out


@pytest.mark.slow
def test_noisy_teacher_hits_its_target_and_widens_the_covariances(tiny_teacher, tmp_path):
    ids, gt = tn.groundtruth("synthetic/tiny", "0:12")
    src, _ = tn.window_edges(tiny_teacher)  # keyframe edges are left out of the noisy copy
    assert 0 < len(src) < len(read_g2o(tiny_teacher / "edges.g2o")[0]) and all(e.j - e.i <= 3 for e in src)
    base = tn.label_errors(src, ids, gt.poses)["se3_l2_mean"]
    target = 2.5 * base
    info = tn.add_label_noise(tiny_teacher, "synthetic/tiny", "0:12", target, tmp_path / "noisy", seed=3)
    new, vertices = read_g2o(tmp_path / "noisy" / "edges.g2o")
    # calibrated on frames 0:12: the noisy gap-1 labels there score the target
    assert tn.label_errors(new, ids, gt.poses)["se3_l2_mean"] == pytest.approx(target, rel=1e-6)
    assert info["achieved_se3_l2_gap1"] == pytest.approx(target, rel=1e-6) and info["scale"] > 0
    assert [(e.i, e.j) for e in new] == [(e.i, e.j) for e in src]
    assert [(r["i"], r["j"]) for r in read_edges_csv(tmp_path / "noisy" / "edges.csv")
            if r["status"] == "ok"] == [(e.i, e.j) for e in src]
    for a, b in zip(src, new):
        sig = np.array(info["sigma_by_gap"][str(b.j - b.i)])
        np.testing.assert_allclose(b.cov, a.cov + np.diag(sig ** 2), rtol=1e-6, atol=1e-12)
        assert not np.allclose(a.T_i_j, b.T_i_j)
    # the trajectory chains the noisy gap-1 labels; the report carries the block
    traj = read_tum(tmp_path / "noisy" / "trajectory.tum")
    step = {e.i: e.T_i_j for e in new if e.j - e.i == 1}
    for k in range(len(traj) - 1):
        np.testing.assert_allclose(geo.relative_pose(traj.poses[k], traj.poses[k + 1]), step[k], atol=1e-6)
    rep = json.loads((tmp_path / "noisy" / "report.json").read_text())
    assert rep["label_noise"]["target_se3_l2_gap1"] == target and "label_error_by_gap" not in rep
    assert sorted(vertices) == list(range(16))
    with pytest.raises(VOError, match="not above"):
        tn.add_label_noise(tiny_teacher, "synthetic/tiny", "0:12", 0.5 * base, tmp_path / "bad")


def test_crossover():
    assert "0.00600" in tn.crossover([(0.004, 0.005), (0.008, 0.007)])  # y - x: +1e-3 -> -1e-3
    assert "every point above" in tn.crossover([(0.004, 0.008), (0.008, 0.009)])
    assert "every point below" in tn.crossover([(0.004, 0.003), (0.008, 0.006)])
