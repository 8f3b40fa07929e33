"""`ctcvo demo` end to end on tiny scenes, run twice (the second run only
reads what the first wrote), and a pose graph over a teacher run longer than the learner's."""

from __future__ import annotations

import contextlib
import io
import json
import re
import time

import pytest

pytestmark = pytest.mark.slow  # trains and renders

@pytest.fixture(scope="module")
def demo_runs(tmp_path_factory):
    """The demo's runs/ folder, its two outputs and the two runs' times."""
    import torch

    from ctcvo.pipeline import demo

    tmp = tmp_path_factory.mktemp("demo")
    mp = pytest.MonkeyPatch()
    mp.chdir(tmp)
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    args = ["--train", "synthetic/tiny", "--val", "synthetic/tiny-clean", "--test", "synthetic/tiny",
            "--frames", "0:12", "--steps", "2", "--preset", "tiny", "--no-calibrate"]  # 12 frames: too few to calibrate
    try:
        outs, secs, starts, prints = [], [], [], []
        for _ in range(2):
            starts.append(time.time())
            t0 = time.perf_counter()
            with contextlib.redirect_stdout(io.StringIO()) as printed:
                outs.append(demo.main(args))
            secs.append(time.perf_counter() - t0)
            prints.append(printed.getvalue())
        yield tmp, outs, secs, starts, prints
    finally:
        torch.set_num_threads(before)
        mp.undo()


def test_demo_end_to_end_on_tiny_scenes(demo_runs, capsys):
    """Every stage runs, the learner is calibrated on the validation scene, the table has
    the three rows and the two baselines, and predict did not write into the training run."""
    tmp, rcs, secs, _, prints = demo_runs
    assert rcs == [0, 0]
    stages = dict(re.findall(r"^(teacher generate \S+|learner fit .*?|learner predict \S+|posegraph optimize \S+|total)"
                             r"\s+([0-9.]+) s$", prints[0].split("time per stage:")[1], re.M))
    assert len(stages) == 6 and float(stages["total"]) <= secs[0] + 0.05, prints[0][-800:]
    runs = tmp / "runs" / "synthetic-tiny"
    assert (runs / "learner" / "calibration.json").is_file()
    assert not (runs / "learner" / "edges.g2o").exists() and (runs / "predict" / "edges.g2o").is_file()
    rep = json.loads((runs / "posegraph" / "report.json").read_text())
    assert rep["frames"] == 12
    for row in ("teacher", "learner", "fused", "zero_motion", "constant_velocity"):
        assert row in rep["rows"], list(rep["rows"])
    for stage in ("teacher", "learner", "predict", "posegraph"):
        fp = json.loads((runs / stage / "fingerprint.json").read_text())
        assert fp["stage"] == stage and fp["digest"].startswith("sha256:")
        assert (runs / stage / "config.json").is_file()


def test_demo_rerun_reads_only(demo_runs):
    """The second run rewrote nothing (every stage's fingerprint matched) and took a
    fraction of the first run's time."""
    tmp, rcs, secs, starts, _ = demo_runs
    runs = tmp / "runs"
    newest = max(p.stat().st_mtime for p in runs.rglob("*") if p.is_file())
    assert newest < starts[1]  # the second run wrote no file
    assert secs[1] < 0.5 * secs[0], secs


def test_posegraph_cuts_a_longer_teacher_run_to_the_learner_frames(demo_runs, tmp_path, monkeypatch):
    """Teacher over 0:12, learner over 4:12: the graph uses the 8 frames both cover (no
    disconnected learner row); --frames 6:12 cuts both further."""
    from ctcvo.learner.predict import predict
    from ctcvo.posegraph.optimize import optimize

    tmp, _, _, _, _ = demo_runs
    monkeypatch.chdir(tmp)
    runs = tmp / "runs" / "synthetic-tiny"
    pred = predict(runs / "learner" / "checkpoint.pt", "synthetic/tiny", frames="4:12", out=tmp_path / "pred")
    assert json.loads((pred.out_dirs[0] / "report.json").read_text())["frames"] == 8
    out = optimize(scene="synthetic/tiny", teacher=runs / "teacher", learner=pred.out_dirs[0], out=tmp_path / "pg")[0]
    rep = json.loads((out / "report.json").read_text())
    assert rep["frames"] == 8 and rep["frames_cut"] == "ids 4..11 (8 frames)"
    assert {"teacher", "learner", "fused"} <= set(rep["rows"])
    out = optimize(scene="synthetic/tiny", teacher=runs / "teacher", learner=pred.out_dirs[0], out=tmp_path / "pg6",
                   frames="6:12")[0]
    rep = json.loads((out / "report.json").read_text())
    assert rep["frames"] == 6 and rep["rows"]["learner"]["ate_rmse_m"] is not None
