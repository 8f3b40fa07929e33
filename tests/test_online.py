"""``vo-online`` (pipeline/online.py): frame by frame it gives the batch stages' edges, an
ISAM2 trajectory as accurate as the batch pose graph on the same edges, follows a folder
still being written, and keeps the trajectory so far when interrupted."""

from __future__ import annotations

import json
import shutil
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from data.formats import read_g2o, read_tum
from data.scenes import open_scene
from pipeline import online
from teacher.config import TINY

pytestmark = pytest.mark.usefixtures("one_torch_thread")

TCFG = TINY  # gaps 2, 800 features: the tiny scene in seconds


@pytest.fixture(scope="module")
def batch(tmp_path_factory) -> Path:
    """``teacher generate`` and ``posegraph optimize`` (batch) on synthetic/tiny."""
    from posegraph.optimize import optimize
    from teacher.generate import generate

    root = tmp_path_factory.mktemp("batch")
    generate("synthetic/tiny", root / "teacher", config=TCFG.__class__(**{**TCFG.to_dict(), "workers": 1}),
             progress=False)
    optimize(teacher=root / "teacher", out=root / "posegraph")
    return root


@pytest.fixture(scope="module")
def online_run(tmp_path_factory) -> online.OnlineResult:
    out = tmp_path_factory.mktemp("online")
    return online.run(online.open_source("synthetic/tiny"), out, TCFG, progress=False)


@pytest.mark.slow
def test_online_teacher_edges_equal_batch(batch, online_run):
    """The same edges, bit for bit: online/teacher/edges.g2o is the batch teacher's file."""
    assert online_run.frames == 20 and not online_run.interrupted
    a = (batch / "teacher" / "edges.g2o").read_text()
    b = (online_run.out / "teacher" / "edges.g2o").read_text()
    assert a == b
    rep = online_run.report
    assert rep["teacher_edges"] == len(read_g2o(batch / "teacher" / "edges.g2o")[0])


@pytest.mark.slow
def test_online_trajectory_matches_batch_pose_graph(batch, online_run):
    """The final trajectory (ISAM2, then the batch solve warm-started from it) has the ATE
    of the batch pose graph on the same edges to 10 %; the ISAM2 estimate alone and the
    causal per-frame estimates beat chaining the gap-1 edges; the trajectory file has one
    flushed row per frame."""
    pg = json.loads((batch / "posegraph" / "report.json").read_text())
    batch_ate = pg["rows"]["fused"]["ate_rmse_m"]
    rep = online_run.report
    assert abs(rep["final"]["ate_rmse_m"] - batch_ate) <= 0.1 * batch_ate, (rep["final"]["ate_rmse_m"], batch_ate)
    chain = rep["teacher_chain"]["ate_rmse_m"]
    assert rep["final_isam2"]["ate_rmse_m"] < chain and rep["online"]["ate_rmse_m"] < chain
    rows = read_tum(online_run.out / online.TRAJECTORY)
    assert len(rows) == 20
    gt = open_scene("synthetic/tiny")[0]
    np.testing.assert_allclose(rows.timestamps, gt.times(), atol=1e-6)
    assert len(read_tum(online_run.out / online.FINAL_TRAJECTORY)) == 20
    assert online_run.latency_ms["p95"] > 0 and online_run.fps > 0


def _copy_frames_slowly(src: Path, dst: Path, period_s: float, done: threading.Event) -> None:
    """A writer: each frame's files appear by an atomic rename, one frame per period."""
    try:
        shutil.copy(src.parent / "camera-intrinsics.txt", dst / "camera-intrinsics.txt") \
            if (src.parent / "camera-intrinsics.txt").is_file() else None
        ids = sorted(int(p.name[6:12]) for p in src.glob("frame-*.depth.png"))
        for k in ids:
            for f in sorted(src.glob(f"frame-{k:06d}.*")):
                tmp = dst / f".tmp-{f.name}"
                shutil.copy(f, tmp)
                tmp.rename(dst / f.name)
            time.sleep(period_s)
    finally:
        done.set()


@pytest.mark.slow
def test_follow_a_folder_being_written(tmp_path, online_run):
    """Frames written by another thread one by one are taken as they arrive; the run ends
    after --timeout without a new frame, with the edges of the complete folder."""
    seq = open_scene("synthetic/tiny")[0]
    src = seq.root
    live = tmp_path / "live"
    live.mkdir()
    # the renderer's sensor description beside the live folder, as beside the scene: the
    # teacher's colour camera and dense method come from it (a real recording has none)
    shutil.copy(src.parent / "config.json", tmp_path / "config.json")
    done = threading.Event()
    writer = threading.Thread(target=_copy_frames_slowly, args=(src, live, 0.05, done))
    writer.start()
    try:
        res = online.run(online.open_source(str(live), follow=True,
                                            cfg=online.OnlineConfig(poll_s=0.01, timeout_s=3.0)),
                         tmp_path / "out", TCFG, progress=False, cfg=online.OnlineConfig(poll_s=0.01, timeout_s=3.0))
    finally:
        writer.join()
    assert done.is_set() and res.frames == 20
    assert (res.out / "teacher" / "edges.g2o").read_text() == (online_run.out / "teacher" / "edges.g2o").read_text()


def test_follow_times_out_without_frames(tmp_path):
    (tmp_path / "empty").mkdir()
    src = online.open_source(str(tmp_path / "empty"), follow=True, cfg=online.OnlineConfig(poll_s=0.01, timeout_s=0.2))
    from data.errors import DataError

    with pytest.raises(DataError, match="no frame arrived"):
        online.run(src, tmp_path / "o", TCFG, progress=False)


class _Interrupting(online.FrameSource):
    """A source whose user presses Ctrl-C after ``n`` frames."""

    def __init__(self, inner: online.FrameSource, n: int) -> None:
        self.inner, self.n, self.name, self.intrinsics = inner, n, inner.name, inner.intrinsics

    def __iter__(self):
        for k, f in enumerate(self.inner):
            if k == self.n:
                raise KeyboardInterrupt
            yield f


@pytest.mark.slow
def test_ctrl_c_keeps_the_trajectory_so_far(tmp_path, monkeypatch, capsys):
    inner = online.open_source("synthetic/tiny")
    monkeypatch.setattr(online, "open_source", lambda *a, **k: _Interrupting(inner, 9))
    rc = online.main(["--scene", "synthetic/tiny", "--out", str(tmp_path / "o"), "--preset", "tiny"])
    assert rc == 130
    err = capsys.readouterr().err.strip().splitlines()
    assert len([l for l in err if l.startswith("interrupted after")]) == 1
    assert "Traceback" not in "\n".join(err)
    # the frames handed over before the interrupt are all kept (prefetched ones included)
    n = len(read_tum(tmp_path / "o" / online.TRAJECTORY))
    assert 7 <= n <= 9
    rep = json.loads((tmp_path / "o" / "report.json").read_text())
    assert rep["interrupted"] and rep["frames"] == n
    assert len(read_tum(tmp_path / "o" / online.FINAL_TRAJECTORY)) == n


def test_cli_errors_are_one_line(tmp_path, capsys):
    assert online.main(["--scene", str(tmp_path / "nope"), "--out", str(tmp_path / "o")]) == 1
    err = capsys.readouterr().err.strip()
    assert err.startswith("error: ") and "\n" not in err
    assert online.main(["--scene", "synthetic/tiny", "--follow", "--frames", "0:5", "--out", str(tmp_path / "o")]) == 1
    assert "--frames does not apply with --follow" in capsys.readouterr().err


@pytest.mark.slow
def test_online_learner_edges_equal_predict(batch, tmp_path):
    """With dropout off the MC mean is the network's output: the online learner's edges
    equal ``learner predict``'s (the LSTM over the same chunks), and they enter the graph."""
    from learner.config import PredictConfig
    from learner.predict import predict
    from learner.train import fit

    res = fit(["synthetic/tiny"], variant="ctc", preset="tiny", out=tmp_path / "run",
              teacher_root=batch / "teacher", calibrate=False)
    cfg = PredictConfig(samples=3, drop=0.0, max_gap=3)
    predict(res.checkpoint, "synthetic/tiny", out=tmp_path / "pred", config=cfg, use_calibration=False, device="cpu")
    run = online.run(online.open_source("synthetic/tiny"), tmp_path / "online", TCFG, checkpoint=res.checkpoint,
                     predict_cfg=cfg, progress=False)
    want = {(e.i, e.j): e for e in read_g2o(tmp_path / "pred" / "edges.g2o")[0]}
    got = {(e.i, e.j): e for e in read_g2o(tmp_path / "online" / "learner" / "edges.g2o")[0]}
    assert set(got) == set(want) and run.report["learner_edges"] == len(want)
    for key, e in want.items():
        np.testing.assert_allclose(got[key].T_i_j, e.T_i_j, atol=2e-5)
    assert run.report["final"]["ate_rmse_m"] < 1.0
