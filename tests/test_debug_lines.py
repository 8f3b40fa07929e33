"""`-v` shows what a user debugging a bad edge or the learner's data needs."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

from ctcvo.teacher.odometry import describe
from ctcvo.teacher.record import DenseOutcome, EdgeDiagnostics, EdgeEstimate


def test_edge_debug_line_names_the_fallback_and_the_dense_fitness() -> None:
    diag = EdgeDiagnostics(path="rgbd", sparse_status="few_matches", dense=DenseOutcome(True, fitness=0.5,
                                                                                         shift_m=0.002))
    line = describe(EdgeEstimate(3, 4, "ok", matches=12, inliers=7, diag=diag))
    assert line == ("ok, 12 matches, 7 inliers, path rgbd, keypoints few_matches, dense step taken, fitness 0.500, "
                    "moved 2.0 mm / 0.00 deg")


def test_teacher_shows_each_edge_with_v(tmp_path) -> None:
    """`ctcvo teacher -v generate` logs one debug line per edge (none without -v)."""
    def run(*v: str) -> str:
        cmd = [sys.executable, "-m", "ctcvo", "teacher", *v, "generate", "--scene", "synthetic/tiny", "--preset",
               "tiny", "--frames", "0:4", "--out", str(tmp_path / f"t{len(v)}")]
        return subprocess.run(cmd, capture_output=True, text=True, check=True, timeout=300,
                              cwd=Path(__file__).resolve().parents[1]).stderr

    assert "edge 0->1: " in run("-v") and "edge 0->1: " not in run()
