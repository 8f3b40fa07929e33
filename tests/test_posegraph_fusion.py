"""Fusion that never hurts: the teacher-graph control row, per-gap teacher covariance
calibration from multi-gap consistency, the learner skill gate, bridges over a failed
teacher stretch, and the shared NEES helper."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest

from ctcvo.data import geometry as geo
from ctcvo.data.errors import FormatError
from ctcvo.data.formats import Edge, Trajectory
from ctcvo.data.uncertainty import CHI2_6_1SIGMA, CHI2_6_2SIGMA, CHI2_6_MEDIAN, mahalanobis2, nees_stats
from ctcvo.posegraph import synthetic as syn
from ctcvo.posegraph.calibration import GapScales, fit_gap_scales, read_gap_scales
from ctcvo.posegraph.cli import main
from ctcvo.posegraph.config import DEFAULT
from ctcvo.posegraph.edges import bridge_edges, components
from ctcvo.posegraph.optimize import optimize
from ctcvo.posegraph.report import nees

TRUE = {1: (0.004, 0.002), 2: (0.006, 0.003), 3: (0.008, 0.004)}  # sigma (m, rad) per gap
CLAIMED = {1: 1 / 100.0, 2: 1 / 40.0, 3: 1 / 10.0}  # claimed covariance = true * this


def _overconfident(gt: np.ndarray, rng: np.random.Generator, source: str = "teacher") -> list[Edge]:
    """Edges at gaps 1-3 drawn with TRUE noise but claiming covariances CLAIMED times it."""
    out = []
    for g, (st, sr) in TRUE.items():
        for e in syn.make_edges(gt, [g], syn.diag_cov(st, sr), rng, source=source):
            e.cov = e.cov * CLAIMED[g]
            out.append(e)
    return out


def test_shared_nees_helper_on_consistent_gaussian_errors():
    assert CHI2_6_1SIGMA == pytest.approx(7.0384, abs=1e-3) and CHI2_6_2SIGMA == pytest.approx(12.8488, abs=1e-3)
    assert CHI2_6_MEDIAN == pytest.approx(5.3481, abs=1e-3)
    rng = np.random.default_rng(0)
    L = rng.normal(size=(6, 6))
    C = L @ L.T + 0.1 * np.eye(6)
    r = rng.multivariate_normal(np.zeros(6), C, size=20000)
    s = nees_stats(mahalanobis2(r, np.broadcast_to(C, (len(r), 6, 6))))
    assert s["nees_over_dof"] == pytest.approx(1.0, abs=0.03)
    assert s["coverage_1sigma"] == pytest.approx(0.6827, abs=0.01)
    assert s["coverage_2sigma"] == pytest.approx(0.9545, abs=0.005)
    s4 = nees_stats(mahalanobis2(r, np.broadcast_to(C / 4, (len(r), 6, 6))))  # 4x overconfident
    assert s4["nees_over_dof"] == pytest.approx(4.0, rel=0.03) and s4["coverage_2sigma"] < 0.5
    assert nees_stats(np.zeros(0))["nees_mean"] is None


def test_gap_scales_recover_the_overconfidence_without_ground_truth():
    """Variance components from the multi-gap consistency alone find each gap's factor
    (100, 40, 10) to about 15 %; applied to an independent draw (another trajectory) they
    bring NEES/6 from ~50 to ~1."""
    gt = syn.helix(300, turns=1.5)
    fit = fit_gap_scales(np.arange(300), _overconfident(gt, np.random.default_rng(1)))
    for g, c in CLAIMED.items():
        assert fit.scales[g] * c == pytest.approx(1.0, rel=0.15), fit.scales
    assert fit.info["converged"]
    test_gt = syn.helix(200, radius=2.0, turns=0.7)
    edges = _overconfident(test_gt, np.random.default_rng(2))
    ids = np.arange(200)
    raw = nees_stats(nees(edges, ids, test_gt))["nees_over_dof"]
    cal = nees_stats(nees(fit.apply(ids, edges), ids, test_gt))["nees_over_dof"]
    assert raw > 30 and 0.8 < cal < 1.25, (raw, cal)


def test_gap_scales_file_round_trip_and_bad_files(tmp_path):
    s = GapScales({1: 50.0, 3: 7.0}, {"note": "x"})
    p = tmp_path / "cal.json"
    p.write_text(json.dumps(s.to_dict()))
    back = read_gap_scales(p)
    assert back.scales == {1: 50.0, 3: 7.0} and back.info["note"] == "x"
    assert back.scale(2) == 7.0 and back.scale(5) == 7.0 and back.scale(1) == 50.0  # nearest, ties to the longer
    for bad in ('{"format": 1, "scales": {"1": -2}}', '{"format": 2, "scales": {"1": 2}}', "nope",
                '{"format": 1, "scales": {"x": 2}}', '{"format": 1, "scales": {}}'):
        p.write_text(bad)
        with pytest.raises(FormatError):
            read_gap_scales(p)


def test_bridge_edges_join_components_along_time():
    gt = syn.helix(30)
    edges = [e for e in syn.make_edges(gt, [1, 2], syn.diag_cov(0.01, 0.01)) if not (10 <= e.i < 15 or 10 < e.j <= 15)]
    ids = np.arange(30)
    assert len(components(ids, edges)) > 1
    br = bridge_edges(ids, edges, gt, np.eye(6) * 1e-2)
    assert len(components(ids, edges + br)) == 1
    assert all(b.j == b.i + 1 and b.extra["source"] == "bridge" for b in br)
    assert np.allclose(br[0].T_i_j, geo.relative_pose(gt[br[0].i], gt[br[0].j]))
    assert bridge_edges(ids, edges + br, gt, np.eye(6) * 1e-2) == []
    assert np.allclose(bridge_edges(ids, edges, None, np.eye(6) * 1e-2)[0].T_i_j, np.eye(4))  # zero motion


def _folders(tmp_path: Path, n: int = 120, ratio: float | None = None, drop: tuple[int, int] | None = None,
             learner_sigma: float = 0.006, seed: int = 3, ratio_cv: float | None = None) -> tuple[Path, Path, np.ndarray]:
    """A teacher folder (gaps 1-3, correct covariances, optionally without any edge that
    touches frames ``drop``; its trajectory bridges that stretch at constant velocity) and a
    learner folder (gaps 1-2, noisier, correct covariances) whose report points to a
    calibration with validation skill ``ratio``."""
    rng = np.random.default_rng(seed)
    gt = syn.helix(n, turns=n / 150.0)
    times = np.arange(n) / 30.0
    teacher = syn.make_edges(gt, [1, 2, 3], syn.diag_cov(0.003, 0.0015), rng, source="teacher")
    learner = syn.make_edges(gt, [1, 2], syn.diag_cov(learner_sigma, learner_sigma / 2), rng, source="learner")
    if drop is not None:
        a, b = drop
        teacher = [e for e in teacher if e.j <= a or e.i >= b]
    t_dir = tmp_path / "teacher"
    syn.write_source_dir(t_dir, gt, teacher, times) if drop is None else None
    if drop is not None:  # the teacher's trajectory: its gap-1 chain, constant velocity over the hole
        from ctcvo.data.formats import write_edges_csv, write_g2o, write_tum

        step = {e.i: e.T_i_j for e in teacher if e.j == e.i + 1}
        traj, last = [np.eye(4)], np.eye(4)
        for k in range(n - 1):
            last = step.get(k, last)
            traj.append(traj[-1] @ last)
        write_g2o(t_dir / "edges.g2o", teacher)
        write_edges_csv(t_dir / "edges.csv", [{"i": k, "j": k + 1, "t_i": times[k], "t_j": times[k + 1],
                                               "status": "ok"} for k in range(n - 1)])
        write_tum(t_dir / "trajectory.tum", Trajectory(times, np.array(traj)))
        write_tum(t_dir / "groundtruth.tum", Trajectory(times, gt))
    l_dir = syn.write_source_dir(tmp_path / "learner", gt, learner, times, with_gt=False)
    if ratio is not None:
        cal = tmp_path / "calibration.json"
        cal.write_text(json.dumps({"format": 1, "validation": {"skill": {
            "reference": "teacher", "pairs": 100, "ratio": ratio,
            "by_gap": {"1": {"ratio": ratio}, "2": {"ratio": ratio * 0.9}}}}}))
        if ratio_cv is not None:
            d = json.loads(cal.read_text())
            for g in d["validation"]["skill"]["by_gap"].values():
                g["ratio_cv"] = ratio_cv
            cal.write_text(json.dumps(d))
        (l_dir / "report.json").write_text(json.dumps({"calibration": str(cal)}))
    return t_dir, l_dir, gt


def _report(out: Path) -> dict:
    return json.loads((out / "report.json").read_text())


def test_teacher_graph_row_and_skilled_learner(tmp_path):
    t, l, _ = _folders(tmp_path, ratio=0.5)
    out = optimize(teacher=t, learner=l, out=tmp_path / "pg", cfg=dataclasses.replace(DEFAULT, plots=False))[0]
    rep = _report(out)
    assert list(rep["rows"]) == ["teacher", "teacher_graph", "learner", "fused", "zero_motion", "constant_velocity"]
    assert rep["rows"]["teacher_graph"]["label"] == "teacher graph (teacher edges only)"
    assert rep["skill_gate"]["learner"]["gated_gaps"] == [] and rep["bridges"] == {"fused": 0, "teacher_graph": 0}
    md = (out / "report.md").read_text()
    assert "teacher graph (teacher edges only)" in md and "**comp. m / deg**" in md and "composition" in md
    # the graph of the teacher's own gap 1-3 edges beats the chained teacher
    assert rep["rows"]["teacher_graph"]["ate_rmse_m"] < rep["rows"]["teacher"]["ate_rmse_m"]


def test_learner_no_better_than_zero_motion_weighs_nothing(tmp_path):
    """Skill ratio 1.1 on validation: the fused poses are the teacher graph's (to 1e-5 m),
    although the learner's edges (biased here) would otherwise pull the graph."""
    t, l, gt = _folders(tmp_path, ratio=1.1)
    for f in (l / "edges.g2o",):  # a learner with a bias: every edge 1 cm too long in x
        from ctcvo.data.formats import read_g2o, write_g2o

        edges, _ = read_g2o(f)
        write_g2o(f, [dataclasses.replace(e, T_i_j=e.T_i_j @ geo.se3_exp([0.01, 0, 0, 0, 0, 0])) for e in edges])
    cfg = dataclasses.replace(DEFAULT, plots=False, learner_edges="all")
    rep = _report(optimize(teacher=t, learner=l, out=tmp_path / "gated", cfg=cfg)[0])
    assert rep["skill_gate"]["learner"]["gated_gaps"] == [1]  # gap 2's ratio is 0.99
    gated_both = tmp_path / "learner" / "report.json"
    cal = json.loads(Path(json.loads(gated_both.read_text())["calibration"]).read_text())
    cal["validation"]["skill"]["by_gap"]["2"]["ratio"] = 1.0
    Path(json.loads(gated_both.read_text())["calibration"]).write_text(json.dumps(cal))
    rep = _report(optimize(teacher=t, learner=l, out=tmp_path / "gated2", cfg=cfg)[0])
    rows = rep["rows"]
    assert rep["skill_gate"]["learner"]["gated_gaps"] == [1, 2]
    assert rows["fused"]["ate_rmse_m"] == pytest.approx(rows["teacher_graph"]["ate_rmse_m"], abs=1e-5)
    assert rows["fused"]["rpe_1s_trans_m"] == pytest.approx(rows["teacher_graph"]["rpe_1s_trans_m"], abs=1e-5)
    gated = np.loadtxt(tmp_path / "gated2" / "trajectory.tum")
    (l / "report.json").unlink()  # no skill known: the learner's edges are used as given and pull the graph
    optimize(teacher=t, learner=l, out=tmp_path / "free", cfg=cfg)
    free = np.loadtxt(tmp_path / "free" / "trajectory.tum")
    assert np.abs(free[:, 1:4] - gated[:, 1:4]).max() > 2e-3


def test_by_default_learner_edges_only_bridge(tmp_path):
    """learner_edges = "bridge" (default): a skilled but biased learner leaves the teacher
    graph as it is where the teacher's edges connect every frame; with "all" it pulls it."""
    t, l, _ = _folders(tmp_path, ratio=0.5)
    from ctcvo.data.formats import read_g2o, write_g2o

    edges, _ = read_g2o(l / "edges.g2o")
    write_g2o(l / "edges.g2o", [dataclasses.replace(e, T_i_j=e.T_i_j @ geo.se3_exp([0.01, 0, 0, 0, 0, 0]))
                                for e in edges])
    cfg = dataclasses.replace(DEFAULT, plots=False)
    rows = _report(optimize(teacher=t, learner=l, out=tmp_path / "b", cfg=cfg)[0])["rows"]
    assert rows["fused"]["ate_rmse_m"] == pytest.approx(rows["teacher_graph"]["ate_rmse_m"], abs=1e-9)
    rows = _report(optimize(teacher=t, learner=l, out=tmp_path / "a",
                            cfg=dataclasses.replace(cfg, learner_edges="all"))[0])["rows"]
    assert rows["fused"]["ate_rmse_m"] > rows["teacher_graph"]["ate_rmse_m"] + 1e-4


@pytest.mark.parametrize("mode", ["bridge", "all"])
def test_learner_bridges_a_stretch_where_the_teacher_failed(tmp_path, mode):
    """Every teacher edge touching frames 60-90 is gone: the teacher graph crosses that
    second at constant velocity (a bridge edge), the fused graph on the learner's edges;
    fused ATE is well below the teacher graph's and equals it nowhere near."""
    t, l, gt = _folders(tmp_path, n=180, ratio=0.5, drop=(60, 90))
    cfg = dataclasses.replace(DEFAULT, plots=False, learner_edges=mode)
    rep = _report(optimize(teacher=t, learner=l, out=tmp_path / "pg", cfg=cfg)[0])
    rows = rep["rows"]
    assert rep["bridges"] == {"fused": 0, "teacher_graph": 30}  # frames 61-89 have no edge at all
    assert rows["fused"]["ate_rmse_m"] < 0.3 * rows["teacher_graph"]["ate_rmse_m"], (
        rows["fused"]["ate_rmse_m"], rows["teacher_graph"]["ate_rmse_m"])
    assert rows["fused"]["rpe_1s_trans_m"] < 0.5 * rows["teacher_graph"]["rpe_1s_trans_m"]


def test_learner_no_better_than_constant_velocity_does_not_bridge(tmp_path):
    """The same hole, but the learner's validation edges were no closer to the teacher's
    labels than the constant-velocity guess: the fused graph keeps the teacher's bridge."""
    t, l, gt = _folders(tmp_path, n=180, ratio=0.5, drop=(60, 90), ratio_cv=1.2)
    rep = _report(optimize(teacher=t, learner=l, out=tmp_path / "pg", cfg=dataclasses.replace(DEFAULT, plots=False))[0])
    assert rep["skill_gate"]["learner"]["no_better_than_cv"] == [1, 2]
    assert rep["bridges"] == {"fused": 30, "teacher_graph": 30}
    assert rep["rows"]["fused"]["ate_rmse_m"] == pytest.approx(rep["rows"]["teacher_graph"]["ate_rmse_m"], abs=1e-9)


@pytest.mark.slow
def test_cli_calibrate_then_optimize_with_teacher_calibration(tmp_path, capsys):
    """`posegraph calibrate` on one folder's overconfident teacher edges, applied by
    `posegraph optimize --teacher-calibration` to another folder: the teacher's NEES/6
    goes from ~50 to ~1 there, the raw figure stays in the report."""
    times = np.arange(300) / 30.0
    val_gt = syn.helix(300, turns=1.5)
    val = syn.write_source_dir(tmp_path / "val", val_gt, _overconfident(val_gt, np.random.default_rng(4)), times)
    test_gt = syn.helix(200, radius=2.0, turns=0.7)
    test = syn.write_source_dir(tmp_path / "test", test_gt, _overconfident(test_gt, np.random.default_rng(5)),
                                times[:200])
    cal = tmp_path / "teacher_cal.json"
    assert main(["calibrate", "--teacher", str(val), "--out", str(cal)]) == 0, capsys.readouterr().err
    d = json.loads(cal.read_text())
    assert set(d["scales"]) == {"1", "2", "3"} and d["fitted_on"][0]["folder"] == str(val)
    # the rerun rule: the same inputs keep the file, other inputs need --overwrite
    text = cal.read_text()
    assert d["fingerprint"]["stage"] == "posegraph-calibrate"
    assert main(["calibrate", "--teacher", str(val), "--out", str(cal)]) == 0 and cal.read_text() == text
    capsys.readouterr()
    assert main(["calibrate", "--teacher", str(val), "--out", str(cal), "--max-gap", "2"]) == 1
    err = capsys.readouterr().err.strip()
    assert err.startswith("error: ") and "\n" not in err and "max_gap: null -> 2" in err and "--overwrite" in err
    assert cal.read_text() == text
    assert main(["calibrate", "--teacher", str(val), "--out", str(tmp_path / "gap2.json"), "--max-gap", "2"]) == 0
    assert set(json.loads((tmp_path / "gap2.json").read_text())["scales"]) == {"1", "2"}
    assert main(["calibrate", "--teacher", str(val), "--out", str(cal), "--max-gap", "2", "--overwrite"]) == 0
    assert json.loads(cal.read_text())["scales"] == json.loads((tmp_path / "gap2.json").read_text())["scales"]
    assert main(["calibrate", "--teacher", str(val), "--out", str(cal), "--overwrite"]) == 0
    assert json.loads(cal.read_text())["scales"] == d["scales"]
    out = tmp_path / "pg"
    assert main(["optimize", "--teacher", str(test), "--out", str(out), "--no-plots",
                 "--teacher-calibration", str(cal)]) == 0, capsys.readouterr().err
    rep = _report(out)
    t = rep["rows"]["teacher"]
    assert t["calibration_raw"]["nees_over_dof"] > 30 and 0.75 < t["calibration"]["nees_over_dof"] < 1.35
    assert rep["covariance_scales"]["teacher"] == 1.0  # calibrated on validation data: kept as is
    assert "raw, before the per-gap scales" in (out / "report.md").read_text()
    assert main(["optimize", "--teacher", str(test), "--out", str(out), "--teacher-calibration",
                 str(tmp_path / "missing.json")]) == 1
    assert capsys.readouterr().err.startswith("error: ")
