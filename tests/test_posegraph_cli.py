"""posegraph optimize: report on a tiny teacher/learner fixture, CLI smoke, bad inputs."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from ctcvo.data.formats import Trajectory
from ctcvo.data.metrics import BASELINE_KEYS, baseline_reports
from ctcvo.posegraph import report
from ctcvo.posegraph import synthetic as syn
from ctcvo.posegraph.cli import main
from ctcvo.posegraph.report import METRIC_KEYS

N = 24


@pytest.fixture()
def dirs(tmp_path: Path) -> tuple[Path, Path]:
    """Teacher (gaps 1-2, with GT) and learner (gaps 1-4, no GT file) folders."""
    rng = np.random.default_rng(5)
    gt = syn.helix(N)
    times = 100.0 + np.arange(N) / 10.0  # 10 Hz: one second is 10 frames
    t = syn.write_source_dir(tmp_path / "teacher", gt, syn.make_edges(gt, [1, 2], syn.diag_cov(0.01, 0.01), rng), times)
    l = syn.write_source_dir(tmp_path / "learner", gt, syn.make_edges(gt, [1, 2, 3, 4], syn.diag_cov(0.02, 0.005), rng),
                             times, with_gt=False)
    return t, l


def _run(args: list[str], capsys) -> tuple[int, str]:
    rc = main(args)
    return rc, capsys.readouterr().err


def test_report_has_every_row_and_key(dirs, tmp_path, capsys):
    t, l = dirs
    out = tmp_path / "out"
    rc, err = _run(["optimize", "--teacher", str(t), "--learner", str(l), "--out", str(out), "--marginals"], capsys)
    assert rc == 0, err
    rep = json.loads((out / "report.json").read_text())
    assert list(rep["rows"]) == ["teacher", "teacher_graph", "learner", "fused", "zero_motion", "constant_velocity"]
    gt_keys = [*METRIC_KEYS, *(f"rpe_g{g}_{q}" for g in (1, 2, 3) for q in ("trans_m", "rot_deg")),
               "rpe_1s_trans_m", "rpe_1s_rot_deg"]
    comp_keys = ["composition_trans_rmse_m", "composition_rot_rmse_deg"]
    for name, block in rep["rows"].items():
        for k in gt_keys:
            assert isinstance(block[k], float), (name, k)
        for k in comp_keys:  # the baselines have no edges to be consistent with
            assert (block[k] is None) == (name in BASELINE_KEYS.values()), (name, k)
    # the baseline rows are data.metrics' baselines of the ground truth at the graph's frames
    times = 100.0 + np.arange(N) / 10.0
    want = baseline_reports(Trajectory(times, syn.helix(N)))
    for name, key in BASELINE_KEYS.items():
        block = rep["rows"][key]
        assert block["label"] == name and block["n_poses"] == N and "calibration" not in block
        assert block["composition_n"] == 0 and block["rpe_1s_frames"] == 10
        for k, v in want[name].items():
            assert block[k] == pytest.approx(v, rel=1e-6, abs=1e-9), (key, k)  # GT via TUM text
    # the learned rows beat both baselines on this easy fixture
    best_baseline = min(rep["rows"][b]["rpe_g1_trans_m"] for b in BASELINE_KEYS.values())
    for key in ("teacher", "learner", "fused"):
        assert rep["rows"][key]["rpe_g1_trans_m"] < best_baseline
    assert rep["rows"]["fused"]["rpe_1s_frames"] == 10
    cal = rep["rows"]["learner"]["calibration"]
    assert cal["calibration_n"] == 4 * N - 10
    assert 0.5 < cal["nees_over_dof"] < 1.6  # sampled from the stated covariance
    assert 0.0 <= cal["coverage_1sigma"] <= cal["coverage_2sigma"] <= 1.0
    # fusing 2 sources with longer gaps beats dead reckoning of either
    assert rep["rows"]["fused"]["ate_rmse_m"] < min(rep["rows"]["teacher"]["ate_rmse_m"],
                                                    rep["rows"]["learner"]["ate_rmse_m"])
    assert rep["has_groundtruth"] and rep["outliers"] == []
    for f in ("trajectory.tum", "report.md", "config.json", "marginals.npz", "trajectories.png",
              "relative_se3.png", "outliers.png", "error_over_time.png"):
        assert (out / f).stat().st_size > 0, f
    md = (out / "report.md").read_text()
    assert all(f"| {lbl} |" in md for lbl in ("teacher (chained)", "learner (chained)", "fused (graph)",
                                              "zero motion", "constant velocity"))
    m = np.load(out / "marginals.npz")
    assert m["cov"].shape == (N, 6, 6)


def test_without_groundtruth_reports_consistency_and_outliers(dirs, tmp_path, capsys):
    _, l = dirs
    out = tmp_path / "out"
    rc, err = _run(["optimize", "--learner", str(l), "--out", str(out), "--no-plots", "--solver", "isam2"], capsys)
    assert rc == 0, err
    rep = json.loads((out / "report.json").read_text())
    assert list(rep["rows"]) == ["learner", "fused"] and not rep["has_groundtruth"]  # no baseline rows
    md = (out / "report.md").read_text()
    assert "zero motion" not in md and "constant velocity" not in md
    assert rep["rows"]["fused"]["ate_rmse_m"] is None
    assert rep["rows"]["fused"]["composition_trans_rmse_m"] < rep["rows"]["learner"]["composition_trans_rmse_m"]
    assert rep["rows"]["learner"]["calibration"]["calibration_n"] == 0


def test_scene_defaults_to_runs_folders(dirs, tmp_path, monkeypatch, capsys):
    t, l = dirs
    base = tmp_path / "runs" / "synthetic-tiny"
    base.mkdir(parents=True)
    t.rename(base / "teacher")
    l.rename(base / "predict")
    monkeypatch.chdir(tmp_path)
    rc, err = _run(["optimize", "--scene", "synthetic/tiny", "--no-plots"], capsys)
    assert rc == 0, err
    assert (base / "posegraph" / "report.json").is_file()


def test_console_script_smoke(dirs, tmp_path):
    t, _ = dirs
    out = tmp_path / "cli"
    exe = Path(sys.executable).parent / "ctcvo"
    cmd = [str(exe)] if exe.exists() else [sys.executable, "-m", "ctcvo"]
    p = subprocess.run(cmd + ["posegraph", "optimize", "--edges", str(t / "edges.g2o"), "--out", str(out), "--no-plots"],
                       capture_output=True, text=True, timeout=120)
    assert p.returncode == 0, p.stderr
    rep = json.loads((out / "report.json").read_text())
    assert rep["synthetic_timestamps"] and list(rep["rows"]) == ["edges", "fused"]  # no GT: no baselines


def test_baseline_rows_known_answers_on_a_straight_line():
    """Constant speed along x, 10 Hz: zero motion misses every step (gap-g RPE = g steps,
    se(3) L2 = one step), constant velocity misses only the first step."""
    n, step = 24, 0.1
    gt = np.repeat(np.eye(4)[None], n, axis=0)
    gt[:, 0, 3] = step * np.arange(n)
    times = 5.0 + np.arange(n) / 10.0
    assert report.baseline_blocks(np.arange(n), times, None) == {}
    rows = report.baseline_blocks(np.arange(n), times, gt)
    assert list(rows) == ["zero_motion", "constant_velocity"]
    zm, cv = rows["zero_motion"], rows["constant_velocity"]
    for g in (1, 2, 3):
        assert zm[f"rpe_g{g}_trans_m"] == pytest.approx(g * step, rel=1e-9)
        # every pair g apart (n - g of them, metrics.rpe_rmse); only the first is off, by one step
        assert cv[f"rpe_g{g}_trans_m"] == pytest.approx(step / np.sqrt(n - g), rel=1e-9)
        assert zm[f"rpe_g{g}_rot_deg"] == pytest.approx(0, abs=1e-6)
        assert cv[f"rpe_g{g}_rot_deg"] == pytest.approx(0, abs=1e-6)
    assert zm["rpe_trans_rmse_m"] == pytest.approx(step, rel=1e-9)
    assert zm["rpe_1s_frames"] == cv["rpe_1s_frames"] == 10
    assert zm["rpe_1s_trans_m"] == pytest.approx(10 * step, rel=1e-9)
    assert cv["rpe_1s_trans_m"] == pytest.approx(step / np.sqrt(n - 10), rel=1e-9)
    assert zm["se3_l2_mean"] == pytest.approx(step, rel=1e-9)
    assert cv["se3_l2_mean"] == pytest.approx(step / (n - 1), rel=1e-9)
    # a still camera aligned onto the line: the RMS distance of the positions to their mean
    assert zm["ate_rmse_m"] == pytest.approx(step * np.sqrt((n**2 - 1) / 12), rel=1e-6)
    assert 0 < cv["ate_rmse_m"] < step
    for b in rows.values():
        assert b["composition_trans_rmse_m"] is None and b["composition_rot_rmse_deg"] is None
        assert "calibration" not in b
    md = report.report_markdown({"rows": rows, "frames": n, "edges_total": 0, "edges_per_source": {},
                                 "solver": {"name": "-", "initial_error": 0.0, "final_error": 0.0, "iterations": 0,
                                            "time_s": 0.0},
                                 "config": {"kernel": "-"}, "has_groundtruth": True, "outliers": [], "git": "-"})
    assert "| zero motion | 0.6922 | 0.1000 | 0.000 | 0.2000 |" in md


# ----------------------------------------------------------------------------------
# bad input: one clear error each, exit 1, nothing written
# ----------------------------------------------------------------------------------
def _edit_g2o(path: Path, fn) -> None:
    lines = path.read_text().splitlines()
    path.write_text("\n".join(fn(lines)) + "\n")


def _info_line(line: str, info: np.ndarray) -> str:
    toks = line.split()[:10]
    return " ".join(toks + [f"{x:.9g}" for x in info[np.triu_indices(6)]])


BAD_CASES = {
    "unknown_tag": (lambda ls: ls + ["EDGE_SE2 0 1 0 0 0 1 0 1 0 0 1 0 1"], "unknown g2o tag 'EDGE_SE2'"),
    "field_count": (lambda ls: [ls[0] + " 1.0"] + ls[1:], "needs 31 fields, got 32"),
    "non_finite": (lambda ls: [ls[0].replace(ls[0].split()[3], "nan", 1)] + ls[1:], "non-finite value"),
    "not_pd": (lambda ls: [_info_line(ls[0], np.diag([1, 1, 1, 1, 1, -1.0]))] + ls[1:], "not positive definite"),
    "missing_frame": (lambda ls: ls + [" ".join(["EDGE_SE3:QUAT", "3", "99"] + ls[0].split()[3:])],
                      "references frame 99, which does not exist"),
    "indeterminant": (lambda ls: [(_info_line(x, np.eye(6) * 1e-5) if x.split()[1:3] == ["9", "10"] else x)
                                  for x in ls if x.split()[1:3] not in (["8", "10"], ["9", "11"])],
                      "indeterminant near frame"),
}


def test_disconnected_teacher_graph_is_bridged(dirs, tmp_path, capsys):
    """No edge spans 9 -> 10: one bridge edge with the step of the teacher's trajectory
    joins the two halves (it used to be an error)."""
    t, _ = dirs
    _edit_g2o(t / "edges.g2o", lambda ls: [x for x in ls if x.split()[1:3] not in (["9", "10"], ["8", "10"], ["9", "11"])])
    out = tmp_path / "out"
    rc, err = _run(["optimize", "--teacher", str(t), "--out", str(out), "--no-plots"], capsys)
    assert rc == 0, err
    rep = json.loads((out / "report.json").read_text())
    assert rep["bridges"] == {"fused": 1, "teacher_graph": None}  # the teacher alone: fused is its graph
    assert "Bridge edges" in (out / "report.md").read_text()


@pytest.mark.parametrize("case", sorted(BAD_CASES))
def test_bad_input_is_one_clear_error(case, dirs, tmp_path, capsys):
    t, _ = dirs
    edit, msg = BAD_CASES[case]
    _edit_g2o(t / "edges.g2o", edit)
    out = tmp_path / "out"
    rc, err = _run(["optimize", "--teacher", str(t), "--out", str(out), "--no-plots"], capsys)
    assert rc == 1
    lines = err.strip().splitlines()
    assert lines[-1].startswith("error: ") and msg in lines[-1], err
    assert "Traceback" not in err
    assert not out.exists()


def test_overconfident_learner_scale_in_report(dirs, tmp_path, capsys):
    """Learner covariances 1000x too small: report.json/report.md give its estimated
    scale and the teacher's edges survive the outlier pass; ``--no-calibrate`` keeps
    the covariances as given (and loses the learner's edges). With ``--learner-edges all``:
    by default learner edges only bridge where the teacher's edges leave frames apart."""
    from ctcvo.data.formats import read_g2o, write_g2o

    t, l = dirs
    edges, _ = read_g2o(l / "edges.g2o")
    for e in edges:
        e.cov = e.cov / 1000.0
    write_g2o(l / "edges.g2o", edges)
    out = tmp_path / "out"
    rc, err = _run(["optimize", "--teacher", str(t), "--learner", str(l), "--out", str(out), "--no-plots",
                    "--learner-edges", "all"], capsys)
    assert rc == 0, err
    rep = json.loads((out / "report.json").read_text())
    assert 300 < rep["covariance_scales"]["learner"] < 3000, rep["covariance_scales"]
    assert 0.3 < rep["covariance_scales"]["teacher"] < 3
    assert rep["covariance_calibration"]["sources"]["learner"]["edges"] == 4 * N - 10
    assert sum(o["source"] == "teacher" for o in rep["outliers"]) <= 1
    assert rep["rows"]["learner"]["calibration"]["nees_over_dof"] > 300  # the raw covariances, vs GT
    assert "Covariance scale per source" in (out / "report.md").read_text()
    rc, err = _run(["optimize", "--teacher", str(t), "--learner", str(l), "--out", str(tmp_path / "raw"),
                    "--no-plots", "--no-calibrate", "--learner-edges", "all"], capsys)
    raw = json.loads((tmp_path / "raw" / "report.json").read_text())
    assert rc == 0 and raw["covariance_calibration"] is None and raw["covariance_scales"]["learner"] == 1.0
    # as given, nearly every learner edge is an outlier; calibrated, nearly none is
    assert sum(o["source"] == "learner" for o in raw["outliers"]) >= 0.9 * (4 * N - 10)
    assert sum(o["source"] == "learner" for o in rep["outliers"]) <= 4


def test_optimize_prints_the_table_and_the_edges_used(dirs, tmp_path, capsys):
    """`posegraph optimize` prints the report's table (not only its path) and the header says
    how many edges of each source the fused graph used, and why any were not."""
    t, l = dirs
    out = tmp_path / "out"
    rc = main(["optimize", "--teacher", str(t), "--learner", str(l), "--out", str(out), "--no-plots"])
    printed = capsys.readouterr().out
    assert rc == 0
    rep = json.loads((out / "report.json").read_text())
    assert "| fused (graph) |" in printed and "| teacher (chained) |" in printed
    assert f"full report: {out / 'report.md'}" in printed
    n_t, n_l = rep["edges_per_source"]["teacher"], rep["edges_per_source"]["learner"]
    line = next(s for s in printed.splitlines() if s.startswith("Edges used in the fused graph:"))
    assert line in (out / "report.md").read_text()
    if rep["config"]["learner_edges"] == "bridge":
        used = rep["edges_total"] - n_t
        assert f"teacher {n_t} of {n_t}, learner {used} of {n_l} (only edges that join frames" in line
    else:
        assert line == f"Edges used in the fused graph: teacher {n_t} of {n_t}, learner {n_l} of {n_l}."


def test_edge_use_says_why_edges_were_left_out():
    base = {"edges_per_source": {"teacher": 735, "learner": 735}, "graph_sources": ["teacher", "learner"],
            "edges_total": 735, "config": {"learner_edges": "bridge"},
            "skill_gate": {"learner": {"gated_gaps": [1, 2], "no_better_than_cv": [3], "scale": 1e4}}}
    line = report.edge_use(base)
    assert line.startswith("Edges used in the fused graph: teacher 735 of 735, learner 0 of 735 (only edges that "
                           "join frames the teacher's edges leave apart enter (--learner-edges bridge); none at gap(s) "
                           "1, 2: no better than zero motion on its validation pairs; none at gap(s) 3: no better "
                           "than constant velocity")
    every = {**base, "config": {"learner_edges": "all"}, "edges_total": 735 + 12}
    line = report.edge_use(every)
    assert "learner 12 of 735 (gap(s) 1, 2 no better than zero motion on its validation pairs: left out" in line
    assert report.edge_use({**every, "skill_gate": {}, "edges_total": 1470}) == \
        "Edges used in the fused graph: teacher 735 of 735, learner 735 of 735."


def test_each_solver_line_names_its_graph(dirs, tmp_path, caplog):
    """optimize solves two graphs (fused, and the teacher's edges alone as the control): each
    solver line says which one it is about, and each graph's summary line comes once."""
    import logging

    t, l = dirs
    caplog.set_level(logging.INFO, logger="ctcvo.posegraph.graph")
    assert main(["optimize", "--teacher", str(t), "--learner", str(l), "--out", str(tmp_path / "out"),
                 "--no-plots", "--learner-edges", "all"]) == 0
    lines = [r.getMessage() for r in caplog.records if r.name == "ctcvo.posegraph.graph"]
    labels = (f"{report.ROW_LABELS['fused']}: ", f"{report.ROW_LABELS['teacher_graph']}: ")
    assert lines and all(s.startswith(labels) for s in lines), lines
    summaries = [s for s in lines if " poses, " in s]
    assert [s.split(": ")[0] for s in summaries] == [x[:-2] for x in labels]
