"""Covariance calibration of the learner (learner/calibrate.py): the fit recovers a known
variance model, the calibrated covariances reach the nominal coverage, calibration.json round
trips, ``learner predict`` applies it, ``learner fit`` writes it from a validation scene, and the
CLI fails clearly. The on-disk fixture is the tiny 7-Scenes-layout sequence of
test_learner_train.py (a training and a separately named validation copy)."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
from test_learner_train import gt_poses, write_sequence, write_teacher

from ctcvo.data.errors import ConfigError, DataError, FormatError
from ctcvo.data.formats import read_g2o
from ctcvo.learner import cli
from ctcvo.learner.calibrate import (
    CALIBRATION_FILE,
    Calibration,
    GroupFit,
    calibrate,
    file_sha1,
    fit_groups,
    fit_variance_model,
    mahalanobis2,
    nees_stats,
    read_calibration,
)
from ctcvo.learner.config import CalibrationConfig, PredictConfig
from ctcvo.learner.predict import predict
from ctcvo.learner.train import fit

pytestmark = pytest.mark.usefixtures("one_torch_thread")


# ----------------------------------------------------------------------------------
# the fit, on residuals drawn from a known model
# ----------------------------------------------------------------------------------
def _draw(rng: np.random.Generator, n: int, a: float, b: float, t: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """MC variances c (log-uniform 1e-7..1e-4), teacher variances t, residuals ~ N(0, a c + b + t)."""
    c = 10.0 ** rng.uniform(-7, -4, n)
    tt = np.full(n, t)
    r = rng.normal(size=n) * np.sqrt(a * c + b + tt)
    return c, r, tt


@pytest.mark.parametrize("a, b", [(4.0, 1e-5), (40.0, 2e-5), (1.0, 3e-6)])
def test_fit_recovers_known_scale_and_floor(a: float, b: float) -> None:
    rng = np.random.default_rng(int(a))
    c, r, t = _draw(rng, 4000, a, b, 2e-6)
    ah, bh, kept = fit_variance_model(c, r**2, t)
    assert ah == pytest.approx(a, rel=0.1)
    assert bh == pytest.approx(b, rel=0.2)
    assert kept.mean() > 0.999  # a Gaussian sample loses (almost) nothing to the 4-sigma trim


def test_fit_is_robust_to_gross_outliers() -> None:
    rng = np.random.default_rng(5)
    c, r, t = _draw(rng, 4000, 4.0, 1e-5, 2e-6)
    bad = rng.choice(len(r), 40, replace=False)  # 1 % gross failures (0.3 m / rad)
    r[bad] = 0.3
    ah, bh, kept = fit_variance_model(c, r**2, t)
    assert ah == pytest.approx(4.0, rel=0.1) and bh == pytest.approx(1e-5, rel=0.2)
    assert not kept[bad].any()
    # without trimming the failures inflate the floor (and with it every covariance)
    _, b_raw, _ = fit_variance_model(c, r**2, t, CalibrationConfig(trim_z=1e6))
    assert b_raw > 30 * 1e-5


def test_teacher_variance_is_not_taken_as_learner_error() -> None:
    rng = np.random.default_rng(6)
    c, r, t = _draw(rng, 4000, 4.0, 1e-5, 1e-5)
    _, b_with, _ = fit_variance_model(c, r**2, t)
    _, b_without, _ = fit_variance_model(c, r**2, None)
    assert b_with == pytest.approx(1e-5, rel=0.2)
    assert b_without == pytest.approx(2e-5, rel=0.2)  # floor absorbs the teacher's variance


def test_scale_only_fit() -> None:
    rng = np.random.default_rng(4)
    c, r, t = _draw(rng, 4000, 9.0, 0.0, 0.0)
    a, b, _ = fit_variance_model(c, r**2, None, CalibrationConfig(fit_floor=False))
    assert a == pytest.approx(9.0, rel=0.1) and b == pytest.approx(CalibrationConfig().min_variance)
    c, r, t = _draw(rng, 4000, 9.0, 1e-5, 0.0)  # with a floor in the data the scale alone must grow
    a_only, _, _ = fit_variance_model(c, r**2, None, CalibrationConfig(fit_floor=False))
    a_both, b_both, _ = fit_variance_model(c, r**2, None)
    assert a_only > 1.5 * 9.0 and a_both == pytest.approx(9.0, rel=0.1) and b_both == pytest.approx(1e-5, rel=0.2)


def test_fit_bounds_and_bad_input() -> None:
    rng = np.random.default_rng(7)
    c = 10.0 ** rng.uniform(-7, -4, 500)
    r = rng.normal(size=500) * 1e-3  # error unrelated to c: all floor, no scale
    a, b, _ = fit_variance_model(c, r**2)
    assert a >= 0 and a < 0.1 and b == pytest.approx(1e-6, rel=0.2)
    with pytest.raises(ValueError):
        fit_variance_model(c[:2], r[:2] ** 2)
    with pytest.raises(ValueError):
        fit_variance_model(-c, r**2)


def _random_covs(rng: np.random.Generator, n: int) -> np.ndarray:
    """Correlated SPD covariances (n, 6, 6), scales spread over two decades."""
    A = rng.normal(size=(n, 6, 6)) * (10.0 ** rng.uniform(-3.5, -2.5, (n, 1, 1)))
    return A @ A.transpose(0, 2, 1) / 6 + 1e-10 * np.eye(6)


def test_calibrated_covariances_reach_nominal_coverage() -> None:
    """Residuals drawn from D C D + diag(b) with per-dimension a, b, and two heads with
    different models: before calibration coverage is ~0, after it is nominal."""
    rng = np.random.default_rng(8)
    n = 3000
    heads = np.array(["lstm"] * 1000 + ["direct"] * 2000)
    gaps = np.array([1] * 1000 + [2] * 1000 + [3] * 1000)
    C = _random_covs(rng, n)
    truth = {"lstm": GroupFit("lstm", 1, 0, (9, 9, 16, 4, 4, 4), (1e-6,) * 3 + (1e-7,) * 3),
             "direct": GroupFit("direct", None, 0, (25,) * 6, (4e-6,) * 6)}
    true_cov = np.array([truth[h].apply(C[e:e + 1])[0] for e, h in enumerate(heads)])
    r = np.einsum("eij,ej->ei", np.linalg.cholesky(true_cov), rng.normal(size=(n, 6)))
    before = nees_stats(mahalanobis2(r, C))
    groups = fit_groups(C, r, heads, gaps)
    assert [(g.head, g.gap) for g in groups] == [("direct", 2), ("direct", 3), ("direct", None), ("lstm", 1),
                                                 ("lstm", None), (None, None)]
    cal = Calibration(groups)
    after = nees_stats(mahalanobis2(r, cal.apply(C, heads, gaps)))
    assert before["coverage_2sigma"] < 0.2
    assert after["coverage_1sigma"] == pytest.approx(0.6827, abs=0.03)
    assert after["coverage_2sigma"] == pytest.approx(0.9545, abs=0.015)
    assert after["nees_mean"] == pytest.approx(6.0, rel=0.07)
    np.testing.assert_allclose(cal.lookup("lstm", 1).a, truth["lstm"].a, rtol=0.15)


def test_apply_keeps_positive_definite_and_falls_back() -> None:
    fit_all = GroupFit(None, None, 50, (2.0,) * 6, (1e-6,) * 6)
    fit_direct = GroupFit("direct", None, 40, (0.0,) * 6, (4e-6,) * 6)  # a = 0: only the floor is left
    cal = Calibration([fit_direct, fit_all])
    C = np.tile(np.ones((6, 6)) * 1e-4, (3, 1, 1))  # rank 1 (PSD, singular)
    out = cal.apply(C, ["direct", "lstm", "direct"], np.array([7, 1, 2]))
    np.testing.assert_allclose(out[0], 4e-6 * np.eye(6))  # unseen gap 7: the head's fit
    np.testing.assert_allclose(out[1], 2.0 * C[1] + 1e-6 * np.eye(6))  # unseen head: every pair's fit
    assert np.linalg.eigvalsh(out).min() > 0
    assert cal.lookup("lstm", 3) is fit_all


def test_fit_groups_needs_enough_pairs() -> None:
    rng = np.random.default_rng(9)
    C = _random_covs(rng, 10)
    with pytest.raises(DataError, match="only 10 validation pairs"):
        fit_groups(C, rng.normal(size=(10, 6)) * 1e-3, ["lstm"] * 10, np.ones(10, dtype=int))


# ----------------------------------------------------------------------------------
# on disk: calibrate, calibration.json, predict, fit
# ----------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def data_dirs(tmp_path_factory) -> dict[str, Path]:
    """Training and validation sequences (same path, other textures, other names) and a
    teacher folder with labels for both (frame ids 0..19, poses of gt_poses())."""
    root = tmp_path_factory.mktemp("calib-data")
    train = write_sequence(root / "a")
    val_dir = write_sequence(root / "b", seed=3)  # b/scene/seq-01
    val_dir.parent.rename(root / "b" / "val")  # 7-Scenes names it <scene>-<seq>: val-seq-01
    val_dir = root / "b" / "val" / "seq-01"
    teacher = write_teacher(root / "teacher", gt_poses())
    return {"train": train, "val": val_dir, "teacher": teacher}


@pytest.fixture(scope="module")
def run(data_dirs, tmp_path_factory) -> Path:
    """A tiny ctc checkpoint trained on the training sequence only (no calibration yet)."""
    out = tmp_path_factory.mktemp("calib-run")
    return fit([str(data_dirs["train"])], variant="ctc", preset="tiny", out=out,
               teacher_root=data_dirs["teacher"]).checkpoint


def _copy_run(ckpt: Path, dst: Path) -> Path:
    dst.mkdir(parents=True)
    for f in ckpt.parent.iterdir():
        if f.is_file():
            shutil.copy(f, dst / f.name)
    return dst / ckpt.name


@pytest.mark.slow
def test_calibrate_writes_a_readable_calibration(run, data_dirs, tmp_path, monkeypatch) -> None:
    ckpt = _copy_run(run, tmp_path / "run")
    from ctcvo.data.sequence import Sequence

    def no_gt(self):
        raise AssertionError("calibration must not read ground truth")

    monkeypatch.setattr(Sequence, "groundtruth", no_gt)
    res = calibrate(ckpt, str(data_dirs["val"]), teacher_root=data_dirs["teacher"],
                    config=PredictConfig(samples=6))
    assert res.path == tmp_path / "run" / CALIBRATION_FILE
    d = json.loads(res.path.read_text())
    assert d["format"] == 1 and d["samples"] == 6 and d["drop"] == 0.1 and d["variant"] == "ctc"
    assert d["pairs"] == (19 + 18 + 17 - 1)  # teacher gaps 1..3, one failed edge left out
    assert d["sequences"][0]["sequence"] == "val-seq-01" and d["sequences"][0]["pairs"] == d["pairs"]
    assert d["groups"][-1]["head"] is None and d["groups"][-1]["gap"] is None
    for k in ("before", "after"):
        assert set(d["validation"][k]) == {"nees_mean", "nees_over_dof", "coverage_1sigma", "coverage_2sigma"}
    # the round trip gives the same calibration
    back = read_calibration(res.path)
    assert back.groups == res.calibration.groups
    assert back.to_dict() == d
    # calibration brings the in-sample validation NEES toward 6
    before, after = d["validation"]["before"]["nees_mean"], d["validation"]["after"]["nees_mean"]
    assert abs(np.log(after / 6)) < abs(np.log(before / 6))


@pytest.mark.slow
def test_calibrate_reruns_by_the_rule(run, data_dirs, tmp_path, monkeypatch, caplog, capsys) -> None:
    """The same inputs keep calibration.json without predicting again; other inputs are a
    one-line error naming what differs until --overwrite; a run killed while predicting
    leaves the previous file as it was."""
    import ctcvo.learner.calibrate as C
    from ctcvo.data.runs import StaleOutputError

    ckpt = _copy_run(run, tmp_path / "run")
    fit_fp = (ckpt.parent / "fingerprint.json").read_text()
    kw = dict(teacher_root=data_dirs["teacher"], config=PredictConfig(samples=4))
    first = calibrate(ckpt, str(data_dirs["val"]), **kw)
    text = first.path.read_text()
    fp = json.loads(text)["fingerprint"]
    assert fp["stage"] == "calibrate" and list(fp["inputs"]["sequences"].values()) == ["0..19 (20 frames)"]

    def no_prediction(*a, **k):
        raise AssertionError("a calibration of the same inputs was predicted again")

    monkeypatch.setattr(C, "mc_edges", no_prediction)
    caplog.set_level("INFO")
    again = calibrate(ckpt, str(data_dirs["val"]), **kw)
    assert "calibration of the same inputs: kept" in caplog.text
    assert first.path.read_text() == text and again.calibration.groups == first.calibration.groups
    assert again.report == first.report
    with pytest.raises(StaleOutputError, match=r"calibration.json holds outputs of other inputs \(sequences\..*"
                                               r"0\.\.19 \(20 frames\) -> 0\.\.17 \(18 frames\)\); pass --overwrite"):
        calibrate(ckpt, str(data_dirs["val"]), frames="0:18", **kw)
    # killed while predicting, with --overwrite: the old calibration is still whole
    monkeypatch.setattr(C, "mc_edges", lambda *a, **k: (_ for _ in ()).throw(KeyboardInterrupt()))
    with pytest.raises(KeyboardInterrupt):
        calibrate(ckpt, str(data_dirs["val"]), frames="0:18", overwrite=True, **kw)
    assert first.path.read_text() == text
    monkeypatch.undo()
    other = calibrate(ckpt, str(data_dirs["val"]), frames="0:18", overwrite=True, **kw)
    d = json.loads(other.path.read_text())
    assert d["frames"] == "0:18" and list(d["fingerprint"]["inputs"]["sequences"].values()) == ["0..17 (18 frames)"]
    assert (ckpt.parent / "fingerprint.json").read_text() == fit_fp  # the training run's own fingerprint is left alone
    # the command line: another sample count is one line and exit 1; --overwrite replaces
    base = ["calibrate", "--checkpoint", str(ckpt), "--scene", str(data_dirs["val"]), "--teacher",
            str(data_dirs["teacher"]), "--frames", "0:18"]
    assert cli.main([*base, "--samples", "4"]) == 0
    assert cli.main([*base, "--samples", "3"]) == 1
    err = capsys.readouterr().err.strip()
    assert err.startswith("error: ") and "\n" not in err and "predict.samples: 4 -> 3" in err
    assert cli.main([*base, "--samples", "3", "--overwrite"]) == 0
    assert json.loads(other.path.read_text())["samples"] == 3


def test_read_calibration_rejects_bad_files(tmp_path) -> None:
    p = tmp_path / CALIBRATION_FILE
    p.write_text("{not json")
    with pytest.raises(FormatError, match="cannot read learner calibration"):
        read_calibration(p)
    good = {"format": 1, "groups": [{"head": None, "gap": None, "pairs": 40, "a": [1] * 6, "b": [1e-6] * 6}]}
    p.write_text(json.dumps(good))
    assert read_calibration(p).lookup("lstm", 1).pairs == 40
    for bad, msg in [({**good, "format": 2}, "not a learner calibration"),
                     ({"format": 1, "groups": [{**good["groups"][0], "b": [0] * 6}]}, "b > 0"),
                     ({"format": 1, "groups": [{**good["groups"][0], "a": [1] * 5}]}, "6 finite"),
                     ({"format": 1, "groups": [{**good["groups"][0], "head": "lstm"}]}, "no group for every pair")]:
        p.write_text(json.dumps(bad))
        with pytest.raises(FormatError, match=msg):
            read_calibration(p)


@pytest.mark.slow
def test_predict_applies_the_calibration(run, data_dirs, tmp_path) -> None:
    ckpt = _copy_run(run, tmp_path / "run")
    cfg = PredictConfig(samples=6, max_gap=3)
    seq = str(data_dirs["train"])  # stands in for a test scene; only the covariances are compared
    raw = predict(ckpt, seq, out=tmp_path / "raw", config=cfg).reports[0]
    assert raw["calibration_applied"] is False and raw["calibration"] is None and "raw_coverage_1sigma" not in raw
    # a hand-made calibration with known numbers: per-head scale and floor
    cal = {"format": 1, "checkpoint_sha1": file_sha1(ckpt),
           "drop": cfg.drop, "samples": cfg.samples,
           "groups": [{"head": "lstm", "gap": 1, "pairs": 30, "a": [100.0] * 3 + [50.0] * 3, "b": [1e-6] * 6},
                      {"head": None, "gap": None, "pairs": 60, "a": [400.0] * 6, "b": [4e-6] * 6}]}
    (ckpt.parent / CALIBRATION_FILE).write_text(json.dumps(cal))
    rep = predict(ckpt, seq, out=tmp_path / "cal", config=cfg).reports[0]
    assert rep["calibration_applied"] is True and rep["calibration"] == str(ckpt.parent / CALIBRATION_FILE)
    assert rep["raw_coverage_1sigma"] == raw["coverage_1sigma"] and rep["raw_nees_mean"] == raw["nees_mean"]
    assert rep["nees_mean"] < raw["nees_mean"]
    e_raw, _ = read_g2o(tmp_path / "raw" / "edges.g2o")
    e_cal, _ = read_g2o(tmp_path / "cal" / "edges.g2o")
    for x, y in zip(e_raw, e_cal):
        assert (x.i, x.j) == (y.i, y.j)
        np.testing.assert_allclose(x.T_i_j, y.T_i_j)  # the means are untouched
        a, b = ([100.0] * 3 + [50.0] * 3, 1e-6) if y.j - y.i == 1 else ([400.0] * 6, 4e-6)
        s = np.sqrt(a)
        np.testing.assert_allclose(y.cov, s[:, None] * x.cov * s[None, :] + b * np.eye(6), rtol=1e-6, atol=1e-15)
    # --no-calibration gives the raw edges back
    off = predict(ckpt, seq, out=tmp_path / "off", config=cfg, use_calibration=False).reports[0]
    assert off["calibration_applied"] is False and off["nees_mean"] == raw["nees_mean"]
    # a calibration of another drop ratio, or of other weights, is refused
    with pytest.raises(ConfigError, match="MC-dropout ratio 0.1, not 0.2"):
        predict(ckpt, seq, out=tmp_path / "x", config=PredictConfig(samples=6, max_gap=3, drop=0.2))
    with open(ckpt, "ab") as fh:
        fh.write(b"\0")
    with pytest.raises(ConfigError, match="other weights"):
        predict(ckpt, seq, out=tmp_path / "y", config=cfg)


@pytest.mark.slow
def test_fit_with_validation_scene_calibrates(data_dirs, tmp_path, caplog) -> None:
    kw = dict(variant="cnn-unsup", preset="tiny", teacher_root=data_dirs["teacher"], steps=2)
    res = fit([str(data_dirs["train"])], val_scenes=[str(data_dirs["val"])], out=tmp_path / "run", **kw)
    assert res.calibration == tmp_path / "run" / CALIBRATION_FILE and res.calibration.is_file()
    d = json.loads(res.calibration.read_text())
    assert d["scenes"] == [str(data_dirs["val"])] and d["checkpoint_epoch"] == 1
    assert [s["sequence"] for s in d["sequences"]] == ["val-seq-01"]
    rep = predict(res.checkpoint, str(data_dirs["train"]), out=tmp_path / "pred",
                  config=PredictConfig(samples=4, max_gap=3)).reports[0]
    assert rep["calibration_applied"] is True
    assert "also a calibration sequence" not in caplog.text
    predict(res.checkpoint, str(data_dirs["val"]), out=tmp_path / "pred-val", config=PredictConfig(samples=4, max_gap=3))
    assert "val-seq-01 is also a calibration sequence" in caplog.text
    # training on (the saved options, with more steps) refits the calibration for the new weights
    res2 = fit([str(data_dirs["train"])], out=tmp_path / "run", resume=True, **{**kw, "steps": 4})
    assert res2.calibration == res.calibration
    assert json.loads(res2.calibration.read_text())["checkpoint_epoch"] == 2
    # no validation scene, no calibration
    res3 = fit([str(data_dirs["train"])], out=tmp_path / "run3", **kw)
    assert res3.calibration is None and not (tmp_path / "run3" / CALIBRATION_FILE).exists()


def test_fit_checks_validation_teacher_labels_before_training(data_dirs, tmp_path) -> None:
    with pytest.raises(DataError, match="no teacher labels for"):
        fit([str(data_dirs["train"])], val_scenes=[str(data_dirs["val"])], variant="cnn-gt", preset="tiny",
            out=tmp_path / "run", teacher_root=tmp_path / "nothing", steps=2)
    assert not (tmp_path / "run" / "checkpoint.pt").exists()


# ----------------------------------------------------------------------------------
# command line
# ----------------------------------------------------------------------------------
@pytest.mark.slow
def test_cli_calibrate_then_predict(run, data_dirs, tmp_path, capsys) -> None:
    ckpt = _copy_run(run, tmp_path / "run")
    assert cli.main(["calibrate", "--checkpoint", str(ckpt), "--scene", str(data_dirs["val"]),
                     "--teacher", str(data_dirs["teacher"]), "--samples", "4"]) == 0
    assert capsys.readouterr().out.strip() == str(ckpt.parent / CALIBRATION_FILE)
    assert cli.main(["predict", "--checkpoint", str(ckpt), "--scene", str(data_dirs["train"]), "--samples", "4",
                     "--out", str(tmp_path / "p")]) == 0
    assert json.loads((tmp_path / "p" / "report.json").read_text())["calibration_applied"] is True
    assert cli.main(["predict", "--checkpoint", str(ckpt), "--scene", str(data_dirs["train"]), "--samples", "4",
                     "--out", str(tmp_path / "q"), "--no-calibration"]) == 0
    assert json.loads((tmp_path / "q" / "report.json").read_text())["calibration_applied"] is False


@pytest.mark.slow
@pytest.mark.parametrize("args, message", [
    (["calibrate", "--checkpoint", "{tmp}/missing.pt", "--scene", "{val}", "--teacher", "{teacher}"],
     "does not exist"),
    (["calibrate", "--checkpoint", "{ckpt}", "--scene", "{val}", "--teacher", "{tmp}/none"], "no teacher labels for"),
    (["calibrate", "--checkpoint", "{ckpt}", "--scene", "{val}", "--teacher", "{teacher}", "--frames", "0:6"],
     "calibration needs at least 30"),
    (["calibrate", "--checkpoint", "{ckpt}", "--scene", "{tmp}/nowhere"], "not found"),
    (["calibrate", "--checkpoint", "{ckpt}", "--scene", "{val}", "--drop", "0"], "needs --drop > 0"),
])
def test_cli_calibrate_bad_inputs_exit_1(args, message, run, data_dirs, tmp_path, capsys) -> None:
    argv = [a.format(tmp=tmp_path, val=data_dirs["val"], teacher=data_dirs["teacher"], ckpt=run) for a in args]
    assert cli.main(argv) == 1
    err = capsys.readouterr().err.strip()
    assert err.startswith("error: ") and message in err and "\n" not in err and "Traceback" not in err
    assert not (run.parent / CALIBRATION_FILE).exists()


@pytest.mark.slow
def test_teacher_labels_of_another_sequence_are_refused(run, data_dirs, tmp_path) -> None:
    """``--teacher DIR`` of a single-sequence scene is the folder itself; a teacher folder
    records its sequence in report.json, so another sequence's labels are caught."""
    other = tmp_path / "teacher"
    shutil.copytree(data_dirs["teacher"], other)
    (other / "report.json").write_text(json.dumps({"sequence": "scene-seq-01"}))
    with pytest.raises(DataError, match="of sequence 'scene-seq-01', not 'val-seq-01'"):
        calibrate(run, str(data_dirs["val"]), teacher_root=other, config=PredictConfig(samples=2))
    (other / "report.json").write_text(json.dumps({"sequence": "val-seq-01"}))
    ckpt = _copy_run(run, tmp_path / "run")
    assert calibrate(ckpt, str(data_dirs["val"]), teacher_root=other, config=PredictConfig(samples=2)).path.is_file()


def test_skill_figures_against_zero_motion_and_constant_velocity():
    """Labels of a camera moving at constant velocity (0.01 per step in v_x): a learner that
    halves every motion is 0.5x zero motion's distance, and worse than the constant-velocity
    guess from the previous label, which is exact (NaN for the pairs with no previous step)."""
    from ctcvo.learner.calibrate import constant_velocity_l2, skill_figures

    i = np.array([0, 1, 2, 3, 0, 1, 2])
    j = np.array([1, 2, 3, 4, 2, 3, 4])
    log_t = np.zeros((7, 6))
    log_t[:, 0] = 0.01 * (j - i)
    cv = constant_velocity_l2(i, j, log_t)
    assert np.isnan(cv[0]) and np.isnan(cv[4]) and np.allclose(cv[[1, 2, 3, 5, 6]], 0.0)
    l2 = np.linalg.norm(log_t - 0.5 * log_t, axis=1)
    s = skill_figures(l2, np.linalg.norm(log_t, axis=1), j - i, cv)
    assert s["ratio"] == pytest.approx(0.5) and s["by_gap"]["2"]["ratio"] == pytest.approx(0.5)
    assert s["by_gap"]["1"]["pairs"] == 4 and s["ratio_cv"] == float("inf")
