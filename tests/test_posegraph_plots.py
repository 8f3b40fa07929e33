"""posegraph optimize's figures: what they show agrees with report.json (outlier count over
every gap, ATE per row, the alignment named), human labels, the views and axes asked for."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest

from ctcvo.data import geometry as geo
from ctcvo.data import metrics
from ctcvo.posegraph import optimize as opt
from ctcvo.posegraph import plots
from ctcvo.posegraph import synthetic as syn
from ctcvo.posegraph.config import DEFAULT

N = 40
GROSS = {(5, 6), (12, 14), (20, 23), (30, 32)}  # learner edges made gross outliers, gaps 1-3


def _folders(tmp_path: Path) -> tuple[Path, Path]:
    """Teacher (gaps 1-2, with ground truth) and learner (gaps 1-3, four gross outliers)."""
    rng = np.random.default_rng(7)
    gt = syn.helix(N, radius=2.0)
    times = np.arange(N) / 30.0
    t = syn.write_source_dir(tmp_path / "teacher", gt, syn.make_edges(gt, [1, 2], syn.diag_cov(0.01, 0.005), rng,
                                                                      source="teacher"), times)
    le = syn.make_edges(gt, [1, 2, 3], syn.diag_cov(0.01, 0.005), rng, source="learner")
    for e in le:
        if (e.i, e.j) in GROSS:
            e.T_i_j = e.T_i_j @ geo.se3_exp([0.5, -0.3, 0.4, 0.3, 0.2, -0.2])
    return t, syn.write_source_dir(tmp_path / "learner", gt, le, times, with_gt=False)


@pytest.fixture(scope="module")
def run(tmp_path_factory) -> tuple[dict, dict, Path]:
    """(figures, report.json, output folder) of one optimize run with every learner edge in the graph."""
    tmp = tmp_path_factory.mktemp("plots")
    t, l = _folders(tmp)
    figs: dict = {}

    def capture(*args, **kwargs):
        figs.update(plots.make_figures(*args, **kwargs))
        return plots.make_plots(*args, **kwargs)

    mp = pytest.MonkeyPatch()
    mp.setattr(opt, "make_plots", capture)
    try:
        out = opt.optimize(teacher=t, learner=l, out=tmp / "pg", cfg=dataclasses.replace(DEFAULT, learner_edges="all"))[0]
    finally:
        mp.undo()
    return figs, json.loads((out / "report.json").read_text()), out


def _legend(fig) -> list[str]:
    (leg,) = fig.legends
    return [t.get_text() for t in leg.get_texts()]


def test_files_written_and_outlier_count_is_the_reports(run):
    figs, rep, out = run
    for name in ("trajectories.png", "relative_se3.png", "outliers.png", "error_over_time.png"):
        assert (out / name).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n", name
    outl = rep["outliers"]
    gaps = {o["j"] - o["i"] for o in outl}
    assert {(o["i"], o["j"]) for o in outl} >= GROSS and len(gaps) > 1  # a gap-1 count would differ
    title = figs["outliers.png"]._suptitle.get_text()
    assert title.startswith(f"Outlier edges: {len(outl)} of {rep['edges_total']} (all gaps 1-3")
    removed = sum(o["action"] == "removed" for o in outl)
    assert f"{removed} removed" in title
    assert "by gap: " + ", ".join(f"{g}: {sum(o['j'] - o['i'] == g for o in outl)}" for g in sorted(gaps)) in title
    # as many crosses in the figure as removed edges
    ax = figs["outliers.png"].axes[0]
    crosses = sum(len(ln.get_xdata()) for ln in ax.get_lines() if ln.get_marker() == "x")
    assert crosses == removed
    assert any(t == f"learner: removed ({removed})" for t in _legend(figs["outliers.png"]))


def test_trajectories_top_and_side_view_with_human_labels(run):
    figs, rep, _ = run
    fig = figs["trajectories.png"]
    assert [ax.get_title().split(" (")[0] for ax in fig.axes] == ["top view", "side view"]
    assert all(ax.get_aspect() == 1.0 for ax in fig.axes)  # equal aspect
    labels = _legend(fig)
    assert labels[-1] == "ground truth"
    for key in ("teacher", "teacher_graph", "learner", "fused"):  # the report's label and ATE, no variable names
        b = rep["rows"][key]
        assert f"{b['label']}, ATE {1e3 * b['ate_rmse_m']:.1f} mm" in labels, (key, labels)
    assert not any("_" in t for t in labels)
    lines = [ln for ln in fig.axes[0].get_lines() if ln.get_linestyle() != "None"]
    styles = {(ln.get_color(), ln.get_linestyle()) for ln in lines}
    assert len(styles) == len(lines) == 5  # distinct colour and style per series
    gt_line = max(lines, key=lambda ln: ln.get_zorder())  # ground truth on top, thinnest
    assert gt_line.get_color() == "black" and gt_line.get_linewidth() == min(ln.get_linewidth() for ln in lines)
    assert "SE(3) Umeyama" in fig._suptitle.get_text() and f"all {N} frames" in fig._suptitle.get_text()


def test_error_over_time_log_axis_names_alignment(run):
    figs, _, _ = run
    fig = figs["error_over_time.png"]
    assert fig.axes[0].get_yscale() == "log"
    assert "SE(3) Umeyama alignment (no scale) on all" in fig._suptitle.get_text()
    assert "mm" in fig.axes[0].get_ylabel()


def test_relative_se3_errors_are_the_reports_se3_l2(run):
    figs, rep, _ = run
    fig = figs["relative_se3.png"]
    assert [ax.get_yscale() for ax in fig.axes] == ["log", "log"] and len(fig.legends) == 1
    assert "against ground truth" in fig._suptitle.get_text()
    assert [t.get_text() for t in fig.axes[0].get_xticklabels()] == ["v_x", "v_y", "v_z"]
    # back in metres and radians, the per-component errors are the report's se(3) L2 per pair
    gt = syn.helix(N, radius=2.0)
    est = gt.copy()
    est[1:, :3, 3] += 0.01 * np.arange(1, N)[:, None]
    err = plots.relative_errors({"x": est}, gt)["x"] / np.array([1e3] * 3 + [np.degrees(1.0)] * 3)
    want = metrics.se3_l2_errors(metrics.relative_poses(gt), metrics.relative_poses(est))
    np.testing.assert_allclose(np.linalg.norm(err, axis=1), want, rtol=1e-9)


def test_view_axes_put_the_least_spanned_axis_vertical():
    xyz = np.c_[np.linspace(0, 3, 10), np.linspace(0, 0.1, 10), np.linspace(0, 1, 10)]
    assert plots.view_axes(xyz) == (0, 2, 1)
