"""bench/teacher_profile.py: its config overrides and its paired comparison of two runs'
labels against the ground truth (the profiling itself is a benchmark, not tested here)."""

from __future__ import annotations

import numpy as np
import pytest

from bench import teacher_profile as tp
from data import geometry as geo


def test_overrides_take_the_fields_type():
    assert tp.parse_set(["p2p_cov_stride=8", "dense_blend=0.5", "subpixel=true"]) == \
        {"p2p_cov_stride": 8, "dense_blend": 0.5, "subpixel": True}
    with pytest.raises(SystemExit, match="no field 'nope'"):
        tp.parse_set(["nope=1"])


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
