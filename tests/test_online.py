"""``ctcvo online`` (pipeline/online*.py): frame by frame it gives the batch stages' edges, an
ISAM2 trajectory as accurate as the batch pose graph on the same edges, follows a folder
still being written, and keeps the trajectory so far when interrupted."""

from __future__ import annotations

import json
import os
import shutil
import threading
import time
from collections import Counter
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from ctcvo.data.formats import read_edges_csv, read_g2o, read_tum
from ctcvo.data.live import FollowSevenScenes, FollowTum, FrameSource
from ctcvo.data.scenes import open_scene
from ctcvo.pipeline import online, online_cli, online_keyframes, online_loop, online_outputs
from ctcvo.teacher.config import TINY

pytestmark = pytest.mark.usefixtures("one_torch_thread")

TCFG = TINY  # gaps 2, 800 features: the tiny scene in seconds; keyframe and loop edges on (the default)
TCFG_WINDOW = replace(TCFG, keyframes=False)  # the window's edges only


@pytest.fixture(scope="module")
def batch(tmp_path_factory) -> Path:
    """``teacher generate`` and ``posegraph optimize`` (batch) on synthetic/tiny."""
    from ctcvo.posegraph.optimize import optimize
    from ctcvo.teacher.generate import generate

    root = tmp_path_factory.mktemp("batch")
    generate("synthetic/tiny", root / "teacher", config=replace(TCFG_WINDOW, workers=1), progress=False)
    optimize(teacher=root / "teacher", out=root / "posegraph")
    return root


@pytest.fixture(scope="module")
def batch_kf(tmp_path_factory) -> Path:
    """The same with the keyframe pass (``teacher generate``'s default)."""
    from ctcvo.posegraph.optimize import optimize
    from ctcvo.teacher.generate import generate

    root = tmp_path_factory.mktemp("batch_kf")
    generate("synthetic/tiny", root / "teacher", config=replace(TCFG, workers=1), progress=False)
    optimize(teacher=root / "teacher", out=root / "posegraph")
    return root


@pytest.fixture(scope="module")
def online_run(tmp_path_factory) -> online.OnlineResult:
    out = tmp_path_factory.mktemp("online")
    return online.run(online.open_source("synthetic/tiny"), out, TCFG_WINDOW, progress=False,
                      cfg=online_loop.OnlineConfig(pose_after_gap1=False))


@pytest.fixture(scope="module")
def online_kf(tmp_path_factory) -> online.OnlineResult:
    out = tmp_path_factory.mktemp("online_kf")
    return online.run(online.open_source("synthetic/tiny"), out, TCFG, progress=False)


def _teacher_file(root: Path, name: str) -> str:
    return next((root / "teacher").rglob(name)).read_text()


def test_online_keyframe_edges_equal_batch(batch, batch_kf, online_kf):
    """With keyframes on, online estimates teacher generate's keyframe edges (in a helper
    thread, on the chained window poses): its edges.g2o and edges.csv are the batch
    teacher's, byte for byte; its window edges are those of a run without keyframes;
    report.json counts the edges by kind; no keyframe's work was dropped."""
    assert online_kf.frames == 20 and not online_kf.interrupted
    assert _teacher_file(online_kf.out, "edges.g2o") == _teacher_file(batch_kf, "edges.g2o")
    assert _teacher_file(online_kf.out, "edges.csv") == _teacher_file(batch_kf, "edges.csv")
    rows = read_edges_csv(online_kf.out / "teacher" / "edges.csv")
    kinds = Counter(r["kind"] for r in rows if r["status"] == "ok")
    assert kinds["keyframe"] > 0 and all(r["j"] - r["i"] > TCFG.gaps for r in rows if r["kind"] != "window")
    window = [line for line in _teacher_file(online_kf.out, "edges.csv").splitlines() if ",window," in line]
    assert window == _teacher_file(batch, "edges.csv").splitlines()[1:]  # the text: NaN cells are equal
    rep = online_kf.report
    assert rep["teacher_edges_by_kind"] == dict(sorted(kinds.items()))  # the kinds present, as batch counts them
    batch_rep = json.loads(_teacher_file(batch_kf, "report.json"))
    assert rep["teacher_edges_by_kind"] == batch_rep["edges_by_kind"]
    assert rep["teacher_failed_edges_by_kind"] == batch_rep["failed_edges_by_kind"]
    assert rep["teacher_edges"] == sum(kinds.values()) and rep["teacher"]["keyframes"] is True
    assert rep["keyframes"]["dropped"] == 0 and rep["keyframes"]["keyframes"] >= 2


def test_online_keyframes_trajectory_matches_batch_pose_graph(batch_kf, online_kf):
    """The final trajectory with the keyframe edges has the ATE of the batch pose graph on
    the batch teacher's edges (keyframe ones included) to 10 %, and the teacher's chain of
    the window's edges is the batch one."""
    pg = json.loads((batch_kf / "posegraph" / "report.json").read_text())
    batch_ate = pg["rows"]["fused"]["ate_rmse_m"]
    rep = online_kf.report
    assert abs(rep["final"]["ate_rmse_m"] - batch_ate) <= 0.1 * batch_ate, (rep["final"]["ate_rmse_m"], batch_ate)
    assert rep["final"]["ate_rmse_m"] < rep["teacher_chain"]["ate_rmse_m"]
    assert _teacher_file(online_kf.out, "trajectory.tum") == _teacher_file(batch_kf, "trajectory.tum")


def test_keyframe_work_waits_at_the_end_and_a_ctrl_c_drops_the_rest(monkeypatch):
    """KeyframeWorker.close waits for every keyframe in hand; a Ctrl-C during the wait (the
    event set) drops those not started, and says how many."""
    seq = open_scene("synthetic/tiny", frames="0:12:3")[0]

    def slow(work, *a):
        time.sleep(0.2)
        return []

    monkeypatch.setattr(online_keyframes, "estimate_work", slow)
    frames = [seq.frame(k) for k in range(len(seq))]
    for interrupt in (False, True):
        kf = online_keyframes.KeyframeWorker(seq.intrinsics, TCFG)
        for k, frame in enumerate(frames):  # 0.1 m apart: each one a keyframe
            assert kf.offer(k, frame, _moved(0.1 * k))
        asked = threading.Event()
        if interrupt:  # during the wait: the keyframe in hand is finished, the 2 or 3 after it dropped
            threading.Timer(0.05, asked.set).start()
        dropped = kf.close(asked)
        assert (2 <= dropped <= 3) if interrupt else dropped == 0
        assert kf.picked == 4 and kf.finished == 4 - dropped and not kf.thread.is_alive()
        assert len(kf.take(4)) == 0 and len(kf.lag_frames) == 4 - dropped


def _moved(x: float) -> np.ndarray:
    T = np.eye(4)
    T[0, 3] = x
    return T


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
    of the batch pose graph on the same edges to 10 % and beats chaining the gap-1 edges by
    far (4.8 against 11.4 mm); the causal per-frame estimates beat the chain (10.4 mm); the
    ISAM2 estimate alone is level with it on these 20 frames (11.46 against 11.48 mm at
    teacher stage 5, 11.43 against 11.43 at 6), so it is held to the chain within 2 %; the
    trajectory file has one flushed row per frame."""
    pg = json.loads((batch / "posegraph" / "report.json").read_text())
    batch_ate = pg["rows"]["fused"]["ate_rmse_m"]
    rep = online_run.report
    assert abs(rep["final"]["ate_rmse_m"] - batch_ate) <= 0.1 * batch_ate, (rep["final"]["ate_rmse_m"], batch_ate)
    chain = rep["teacher_chain"]["ate_rmse_m"]
    assert rep["final"]["ate_rmse_m"] < 0.7 * chain and rep["online"]["ate_rmse_m"] < chain
    assert rep["final_isam2"]["ate_rmse_m"] < 1.02 * chain
    rows = read_tum(online_run.out / online_outputs.TRAJECTORY)
    assert len(rows) == 20
    gt = open_scene("synthetic/tiny")[0]
    np.testing.assert_allclose(rows.timestamps, gt.times(), atol=1e-6)
    assert len(read_tum(online_run.out / online_outputs.FINAL_TRAJECTORY)) == 20
    assert online_run.latency_ms["p95"] > 0 and online_run.fps > 0


@pytest.mark.slow
def test_pose_after_gap1_solves_the_same_edges(batch, online_run, tmp_path):
    """``pose_after_gap1``: each frame's pose is written after its gap-1 edge, the longer
    edges follow in a second update; the edges are still the batch teacher's bit for bit,
    the final trajectory solves the same graph (the batch pose graph's ATE to 10 %), and
    the causal estimates still beat chaining the gap-1 edges."""
    res = online.run(online.open_source("synthetic/tiny"), tmp_path / "o", TCFG_WINDOW,
                     cfg=online_loop.OnlineConfig(pose_after_gap1=True), progress=False)
    assert res.frames == 20
    assert (res.out / "teacher" / "edges.g2o").read_text() == (batch / "teacher" / "edges.g2o").read_text()
    batch_ate = json.loads((batch / "posegraph" / "report.json").read_text())["rows"]["fused"]["ate_rmse_m"]
    rep = res.report
    assert abs(rep["final"]["ate_rmse_m"] - batch_ate) <= 0.1 * batch_ate, (rep["final"]["ate_rmse_m"], batch_ate)
    assert rep["online"]["ate_rmse_m"] < rep["teacher_chain"]["ate_rmse_m"]
    causal = read_tum(res.out / online_outputs.TRAJECTORY).poses
    assert len(causal) == 20 and not np.allclose(causal, read_tum(online_run.out / online_outputs.TRAJECTORY).poses)
    # each frame's work until its pose is part of its whole work (so every percentile is too)
    assert all(rep["work_to_pose_ms"][q] <= rep["work_ms"][q] for q in ("p50", "p95", "max"))
    assert online_run.report["work_to_pose_ms"] == online_run.report["work_ms"]
    assert 0 < rep["work_to_pose_cpu_ms"]["p50"] <= rep["work_to_pose_cpu_ms"]["max"]


def test_window_halves_give_the_edges_of_add():
    """EdgeWindow.add_gap1 then add_longer gives add's edges; a second add_gap1 before
    add_longer is refused (the tracks of the first frame would be lost)."""
    from ctcvo.teacher.features import extract
    from ctcvo.teacher.window import EdgeWindow

    seq = open_scene("synthetic/tiny", frames="0:4")[0]
    feats = [[extract(seq.rgb(k), seq.depth(k), TCFG, K=seq.intrinsics.K) for k in range(4)] for _ in range(2)]
    whole, halves = EdgeWindow(seq.intrinsics, TCFG), EdgeWindow(seq.intrinsics, TCFG)
    for k in range(4):
        a = whole.add(int(seq.ids()[k]), float(seq.times()[k]), feats[0][k])
        first = halves.add_gap1(int(seq.ids()[k]), float(seq.times()[k]), feats[1][k])
        if k == 1:
            with pytest.raises(RuntimeError):
                halves.add_gap1(int(seq.ids()[k + 1]), float(seq.times()[k + 1]), feats[1][k + 1])
        b = first + halves.add_longer()
        assert [(e.i, e.j) for e in a] == [(e.i, e.j) for e in b] and len(first) == (k > 0)
        assert all(np.array_equal(x.T_i_j, y.T_i_j) for x, y in zip(a, b) if x.ok)


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
def test_follow_a_folder_being_written(tmp_path, online_kf):
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
                                            cfg=online_loop.OnlineConfig(poll_s=0.01, timeout_s=3.0)),
                         tmp_path / "out", TCFG, progress=False, cfg=online_loop.OnlineConfig(poll_s=0.01, timeout_s=3.0))
    finally:
        writer.join()
    assert done.is_set() and res.frames == 20  # keyframe edges too: they do not depend on the timing
    assert (res.out / "teacher" / "edges.g2o").read_text() == (online_kf.out / "teacher" / "edges.g2o").read_text()


@pytest.mark.slow
def test_drop_late_takes_the_newest_frame_when_behind(tmp_path, monkeypatch):
    """A writer far faster than the estimator (slowed to 0.1 s a frame): with --drop-late
    every written frame is either taken or counted as skipped, the taken ones in order and
    the last one among them, and the edges join the frames taken."""
    seq = open_scene("synthetic/tiny")[0]
    live = tmp_path / "live"
    live.mkdir()
    shutil.copy(seq.root.parent / "config.json", tmp_path / "config.json")
    add = online_loop.OnlineTeacher.add

    def slow_add(self, frame, fk):
        time.sleep(0.1)
        return add(self, frame, fk)

    monkeypatch.setattr(online_loop.OnlineTeacher, "add", slow_add)
    cfg = online_loop.OnlineConfig(poll_s=0.005, timeout_s=2.0, drop_late=True)
    done = threading.Event()
    writer = threading.Thread(target=_copy_frames_slowly, args=(seq.root, live, 0.01, done))
    writer.start()
    try:
        res = online.run(online.open_source(str(live), follow=True, cfg=cfg), tmp_path / "out", TCFG,
                         progress=False, cfg=cfg)
    finally:
        writer.join()
    rep = res.report
    assert done.is_set() and rep["frames_skipped"] > 0
    assert res.frames + rep["frames_skipped"] == 20
    ids = np.round(30 * read_tum(res.out / online_outputs.FINAL_TRAJECTORY).timestamps).astype(int)
    assert len(ids) == res.frames and np.all(np.diff(ids) > 0) and ids[-1] == 19
    edges, _ = read_g2o(res.out / "teacher" / "edges.g2o")
    taken = set(ids.tolist())
    assert edges and all(e.i in taken and e.j in taken for e in edges)
    gap1 = {(e.i, e.j) for e in edges} & set(zip(ids[:-1].tolist(), ids[1:].tolist()))
    assert len(gap1) >= len(ids) // 2  # consecutive frames taken are joined (a wide gap may fail)


def test_follow_latency_counts_from_when_the_frame_was_written(tmp_path):
    """A followed frame arrives when its last file was written (modification time), not
    when the run gets to it; a recording read from disk arrives when it is handed over."""
    seq = open_scene("synthetic/tiny")[0]
    live = tmp_path / "live"
    live.mkdir()
    written = time.time() - 2.0
    for f in seq.root.glob("frame-000000.*"):
        shutil.copy(f, live / f.name)
        os.utime(live / f.name, (written, written))
    src = online.open_source(str(live), follow=True, cfg=online_loop.OnlineConfig(poll_s=0.01, timeout_s=0.2))
    next(iter(src))
    assert 1.9 < time.perf_counter() - src.arrival() < 60
    assert online.open_source("synthetic/tiny").arrival() is None


def test_follow_times_out_without_frames(tmp_path):
    """A folder whose frames never become readable (a depth file without its colour image)."""
    (tmp_path / "stuck").mkdir()
    (tmp_path / "stuck" / "frame-000000.depth.png").write_bytes(b"")
    src = online.open_source(str(tmp_path / "stuck"), follow=True, cfg=online_loop.OnlineConfig(poll_s=0.01, timeout_s=0.2))
    from ctcvo.data.errors import DataError

    with pytest.raises(DataError, match="no frame arrived"):
        online.run(src, tmp_path / "o", TCFG, progress=False)
    assert not (tmp_path / "o" / online_outputs.TRAJECTORY).exists()


class _Interrupting(FrameSource):
    """A source whose user presses Ctrl-C after ``n`` frames."""

    def __init__(self, inner: FrameSource, n: int) -> None:
        self.inner, self.n, self.name, self.intrinsics, self.sensor = inner, n, inner.name, inner.intrinsics, inner.sensor

    def __iter__(self):
        for k, f in enumerate(self.inner):
            if k == self.n:
                raise KeyboardInterrupt
            yield f


@pytest.mark.slow
def test_ctrl_c_keeps_the_trajectory_so_far(tmp_path, monkeypatch, capsys):
    inner = online.open_source("synthetic/tiny")
    monkeypatch.setattr(online, "open_source", lambda *a, **k: _Interrupting(inner, 9))
    rc = online_cli.main(["--scene", "synthetic/tiny", "--out", str(tmp_path / "o"), "--preset", "tiny"])
    assert rc == 130
    err = capsys.readouterr().err.strip().splitlines()
    assert len([l for l in err if l.startswith("interrupted after")]) == 1
    assert "Traceback" not in "\n".join(err)
    # the frames handed over before the interrupt are all kept (prefetched ones included)
    n = len(read_tum(tmp_path / "o" / online_outputs.TRAJECTORY))
    assert 7 <= n <= 9
    rep = json.loads((tmp_path / "o" / "report.json").read_text())
    assert rep["interrupted"] and rep["frames"] == n
    assert rep["keyframes"]["dropped"] == 0  # the keyframe work in hand was finished
    assert len(read_tum(tmp_path / "o" / online_outputs.FINAL_TRAJECTORY)) == n


class _SigintAt(FrameSource):
    """A source after whose frame ``n`` the user presses Ctrl-C (a real SIGINT, which the
    main thread gets wherever it is in a frame's work)."""

    def __init__(self, inner: FrameSource, n: int) -> None:
        self.inner, self.n, self.name, self.intrinsics, self.sensor = inner, n, inner.name, inner.intrinsics, inner.sensor

    def __iter__(self):
        import signal

        for k, f in enumerate(self.inner):
            if k == self.n:
                os.kill(os.getpid(), signal.SIGINT)
            yield f


@pytest.mark.slow
def test_sigint_ends_the_run_after_the_frame_in_hand(tmp_path):
    """Ctrl-C in the middle of a frame's work ends the run once that frame is done: the
    trajectory files, report and edges hold the same frames."""
    import signal

    before = signal.getsignal(signal.SIGINT)
    res = online.run(_SigintAt(online.open_source("synthetic/tiny"), 6), tmp_path / "o", TCFG, progress=False,
                     cfg=online_loop.OnlineConfig(pose_after_gap1=True))
    assert signal.getsignal(signal.SIGINT) is before  # the run's handler is gone
    assert res.interrupted and 4 <= res.frames < 20
    causal, final = read_tum(res.out / online_outputs.TRAJECTORY), read_tum(res.out / online_outputs.FINAL_TRAJECTORY)
    assert len(causal) == len(final) == res.frames == res.report["frames"]
    ids = set(np.round(30 * final.timestamps).astype(int).tolist())
    edges, _ = read_g2o(res.out / "teacher" / "edges.g2o")
    assert edges and all(e.i in ids and e.j in ids for e in edges)


def test_cli_window_defaults_to_online_gaps():
    """``ctcvo online`` estimates edges to the last ONLINE_GAPS frames unless --gaps says
    otherwise; a preset with fewer keeps its own; teacher generate keeps 5."""
    def gaps(*argv):
        return online_cli._configs(online_cli.build_parser().parse_args(["--scene", "x", *argv]))[0].gaps
    assert online_loop.ONLINE_GAPS == 4 < online.TEACHER_DEFAULT.gaps == 5
    assert gaps() == 4 and gaps("--preset", "tiny") == TINY.gaps == 2 and gaps("--gaps", "5") == 5


def test_cli_errors_are_one_line(tmp_path, capsys):
    assert online_cli.main(["--scene", str(tmp_path / "nope"), "--out", str(tmp_path / "o")]) == 1
    err = capsys.readouterr().err.strip()
    assert err.startswith("error: ") and "\n" not in err
    assert online_cli.main(["--scene", "synthetic/tiny", "--follow", "--frames", "0:5", "--out", str(tmp_path / "o")]) == 1
    assert "--frames does not apply with --follow" in capsys.readouterr().err
    assert online_cli.main(["--scene", "synthetic/tiny", "--drop-late", "--out", str(tmp_path / "o")]) == 1
    assert "--drop-late needs --follow" in capsys.readouterr().err


@pytest.mark.slow
def test_online_learner_edges_equal_predict(batch, tmp_path):
    """With dropout off the MC mean is the network's output: the online learner's edges
    equal ``learner predict``'s (the LSTM over the same chunks), and they enter the graph."""
    from ctcvo.learner.config import PredictConfig
    from ctcvo.learner.predict import predict
    from ctcvo.learner.train import fit

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


def _untrained_checkpoint(path: Path) -> Path:
    """A tiny-preset learner checkpoint, untrained (seeded), its outputs scaled up so that
    dropout spreads them well above the covariance floor."""
    import torch

    from ctcvo.learner.checkpoint import save_checkpoint
    from ctcvo.learner.config import TINY as LTINY
    from ctcvo.learner.model import CTCNet

    torch.manual_seed(0)
    net = CTCNet(LTINY.model)
    net.output_scale.fill_(100.0)  # untrained heads predict about 1e-3 of it
    save_checkpoint(path, net, torch.optim.Adam(net.parameters()), 0, LTINY, "ctc", [])
    return path


def test_online_learner_runs_torch_on_its_own_thread_count(tmp_path):
    """:meth:`OnlineLearner.add` runs torch on ``ONLINE_THREADS`` threads whatever the
    caller's count (a pool of one per core stalled on busy cores), and gives the caller's
    count back; each edge still gets its K samples."""
    import torch

    from ctcvo.learner import online as lo
    from ctcvo.learner.config import PredictConfig

    learner = lo.OnlineLearner(_untrained_checkpoint(tmp_path / "c.pt"), PredictConfig(samples=4, drop=0.2, max_gap=2),
                               use_calibration=False)
    seen, encode = [], learner.model.encode
    learner.model.encode = lambda x: (seen.append(torch.get_num_threads()), encode(x))[1]
    rng = np.random.default_rng(0)
    before = torch.get_num_threads()
    torch.set_num_threads(lo.ONLINE_THREADS + 1)
    try:
        edges = [learner.add((rng.integers(0, 256, (3, 48, 64), dtype=np.uint8), None, None)) for _ in range(4)]
        assert torch.get_num_threads() == lo.ONLINE_THREADS + 1
    finally:
        torch.set_num_threads(before)
    assert seen == [lo.ONLINE_THREADS] * 3
    assert [[(g, h) for g, _, _, h in e] for e in edges] == [[], [(1, "lstm")], [(1, "lstm"), (2, "direct")],
                                                               [(1, "lstm"), (2, "direct")]]
    assert all(np.trace(c) > 1e-6 for e in edges for _, _, c, _ in e)  # 1e-8 floor: dropout spread them


@pytest.mark.slow
def test_learner_beside_the_teacher_gives_the_serial_edges(tmp_path, monkeypatch):
    """The learner's edges of each frame come from a helper thread while the teacher
    estimates its own; with dropout on (same seed) they are those of a serial run, byte
    for byte, and the run's CPU time counts the helper's share."""
    from ctcvo.learner.config import PredictConfig
    from ctcvo.learner.online import OnlineLearner

    ckpt, cfg = _untrained_checkpoint(tmp_path / "c.pt"), PredictConfig(samples=4, drop=0.2, max_gap=2)
    threads, add = [], OnlineLearner.add
    monkeypatch.setattr(OnlineLearner, "add", lambda self, x: (threads.append(threading.current_thread().name),
                                                              add(self, x))[1])
    learn = online_loop.Estimator._learner
    monkeypatch.setattr(online_loop.Estimator, "_learner", lambda self, x: (learn(self, x)[0], 1.0))  # its CPU s
    # the window's edges only: the file's vertices are the final trajectory, which keyframe edges entering
    # the graph when their thread finishes move at the solver's tolerance
    beside = online.run(online.open_source("synthetic/tiny", "0:8"), tmp_path / "beside", TCFG_WINDOW, checkpoint=ckpt,
                        predict_cfg=cfg, progress=False)
    assert len(threads) == 8 and all(t.startswith("vo-online-learner") for t in threads)
    init = online_loop.Estimator.__init__

    def serial(self, *args) -> None:
        init(self, *args)
        self.pool.shutdown()
        self.pool = None

    monkeypatch.setattr(online_loop.Estimator, "__init__", serial)
    threads.clear()
    alone = online.run(online.open_source("synthetic/tiny", "0:8"), tmp_path / "serial", TCFG_WINDOW, checkpoint=ckpt,
                       predict_cfg=cfg, progress=False)
    assert threads == ["MainThread"] * 8
    a, b = ((run.out / "learner" / "edges.g2o").read_bytes() for run in (beside, alone))
    assert a == b and beside.report["learner_edges"] == 7 + 6
    assert beside.report["work_to_pose_cpu_ms"]["p50"] > 1000  # the 1 s the learner said it took


# ----------------------------------------------------------------------------------
# the rerun rule (data/runs.py)
# ----------------------------------------------------------------------------------
@pytest.mark.slow
def test_rerun_keeps_refuses_and_overwrites(tmp_path, monkeypatch, capsys):
    """A second identical run keeps the finished outputs without computing; other inputs
    are one line naming what differs, the outputs untouched; --overwrite replaces them."""
    out = tmp_path / "o"
    first = online.online("synthetic/tiny", out, teacher_cfg=TCFG, progress=False)
    assert not first.kept and first.frames == 20
    fp = json.loads((out / "fingerprint.json").read_text())
    assert fp["stage"] == "online" and fp["inputs"]["frames"] == "0..19 (20 frames)"
    assert fp["inputs"]["follow"] is False and fp["inputs"]["checkpoint"] is None
    stamp = {f: (out / f).stat().st_mtime_ns for f in online_outputs.OUTPUT_FILES if (out / f).exists()}
    assert set(stamp) >= {"report.json", "trajectory.tum", "trajectory_final.tum", "teacher/edges.g2o"}

    def no_run(*a, **k):
        raise AssertionError("a finished run of the same inputs was computed again")

    monkeypatch.setattr(online, "run", no_run)
    again = online.online("synthetic/tiny", out, teacher_cfg=TCFG, progress=False)
    assert again.kept and again.frames == 20 and again.report == first.report
    argv = ["--scene", "synthetic/tiny", "--preset", "tiny", "--out", str(out)]
    assert online_cli.main(argv) == 0
    assert "(kept: a finished run of the same inputs)" in capsys.readouterr().out
    assert online_cli.main([*argv, "--frames", "0:10"]) == 1
    err = capsys.readouterr().err.strip()
    assert err == (f"error: {out} holds outputs of other inputs (frames: 0..19 (20 frames) -> 0..9 (10 frames)); "
                   "pass --overwrite to replace them, or choose another --out")
    assert online_cli.main([*argv, "--gaps", "1"]) == 1
    assert "teacher.gaps: 2 -> 1" in capsys.readouterr().err
    assert {f: (out / f).stat().st_mtime_ns for f in stamp} == stamp
    monkeypatch.undo()
    assert online_cli.main([*argv, "--frames", "0:10", "--overwrite"]) == 0
    assert len(read_tum(out / online_outputs.TRAJECTORY)) == 10
    assert json.loads((out / "report.json").read_text())["frame_ids"] == "0..9 (10 frames)"


@pytest.mark.slow
def test_a_killed_run_is_run_again_and_fails_leave_nothing(tmp_path):
    """SIGKILL mid-run leaves no report.json (the mark of a finished run) and only whole
    files; the same command again computes the run afresh; other inputs are refused.
    A run in which no frame arrived leaves no folder behind."""
    import os
    import signal
    import subprocess
    import sys

    out = tmp_path / "o"
    argv = [sys.executable, "-m", "ctcvo.pipeline.online_cli", "--scene", "synthetic/tiny", "--preset", "tiny", "--out", str(out)]
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    proc = subprocess.Popen(argv, cwd=Path(__file__).resolve().parents[1], env=env, stdout=subprocess.DEVNULL,
                            stderr=subprocess.DEVNULL)
    try:
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline and proc.poll() is None:
            traj = out / online_outputs.TRAJECTORY
            if traj.is_file() and len(traj.read_text().splitlines()) >= 4:  # header + 3 frames
                break
            time.sleep(0.02)
        assert proc.poll() is None, "the run ended before it could be killed"
        proc.send_signal(signal.SIGKILL)
    finally:
        proc.wait()
    assert (out / "fingerprint.json").is_file() and not (out / "report.json").exists()
    assert not (out / online_outputs.FINAL_TRAJECTORY).exists()
    rows = read_tum(out / online_outputs.TRAJECTORY)  # whole rows only
    assert 3 <= len(rows) < 20
    from ctcvo.data.runs import StaleOutputError

    with pytest.raises(StaleOutputError, match="holds outputs of other inputs"):
        online.online("synthetic/tiny", out, frames="0:10", teacher_cfg=TCFG, progress=False)
    res = online.online("synthetic/tiny", out, teacher_cfg=TCFG, progress=False)
    assert not res.kept and res.frames == 20 and len(read_tum(out / online_outputs.TRAJECTORY)) == 20

    (tmp_path / "empty").mkdir()
    from ctcvo.data.errors import DataError

    with pytest.raises(DataError, match="no frame arrived"):
        online.online(str(tmp_path / "empty"), tmp_path / "runs" / "x", follow=True, teacher_cfg=TCFG,
                      cfg=online_loop.OnlineConfig(poll_s=0.01, timeout_s=0.2), progress=False)
    assert not (tmp_path / "runs").exists()


@pytest.mark.slow
def test_follow_rerun_is_kept_until_the_folder_grows(tmp_path):
    """With --follow a finished run is kept while the folder holds no frame it did not
    take; once frames were added, the same command runs again over all of them."""
    src = open_scene("synthetic/tiny")[0].root
    live = tmp_path / "live"
    live.mkdir()

    def copy(ids):
        for k in ids:
            for f in src.glob(f"frame-{k:06d}.*"):
                shutil.copy(f, live / f.name)

    copy(range(10))
    cfg = online_loop.OnlineConfig(poll_s=0.01, timeout_s=0.3)
    kw = dict(follow=True, teacher_cfg=TCFG, cfg=cfg, progress=False)
    first = online.online(str(live), tmp_path / "o", **kw)
    assert first.frames == 10 and first.report["frame_ids"] == "0..9 (10 frames)"
    assert json.loads((tmp_path / "o" / "fingerprint.json").read_text())["inputs"]["frames"] == "as they arrive"
    assert online.online(str(live), tmp_path / "o", **kw).kept
    copy(range(10, 14))
    grown = online.online(str(live), tmp_path / "o", **kw)
    assert not grown.kept and grown.frames == 14 and len(read_tum(tmp_path / "o" / online_outputs.TRAJECTORY)) == 14


# ----------------------------------------------------------------------------------
# --follow on a TUM RGB-D folder being written
# ----------------------------------------------------------------------------------
def _tum_frames(n: int = 20):
    """synthetic/tiny's frames as TUM RGB-D files: (RGB time, rgb PNG, depth time, depth PNG)
    with depth 4 ms after RGB, the camera, and groundtruth.txt rows at the RGB times."""
    import cv2

    from ctcvo.data import geometry as geo

    seq = open_scene("synthetic/tiny")[0]
    gt = seq.groundtruth()
    frames = []
    for k in range(min(n, len(seq))):
        t = 1305031100.0 + k / 30.0
        ok1, rgb = cv2.imencode(".png", cv2.cvtColor(seq.rgb(k), cv2.COLOR_RGB2BGR))
        ok2, dep = cv2.imencode(".png", np.round(seq.depth(k) * 5000.0).clip(0, 65535).astype(np.uint16))
        assert ok1 and ok2
        frames.append((t, rgb.tobytes(), t + 0.004, dep.tobytes()))
    i = seq.intrinsics
    camera = f"{i.fx} {i.fy} {i.cx} {i.cy} {i.width} {i.height}\n"
    gt_rows = "".join(f"{f[0]:.6f} " + " ".join(f"{x:.9f}" for x in geo.T_to_tum(T)) + "\n"
                      for f, T in zip(frames, gt))
    return frames, camera, gt_rows


def _write_tum(folder: Path, frames, camera: str, gt_rows: str, period_s: float = 0.0) -> None:
    """A TUM writer: images by atomic rename, list lines appended (a line is sometimes
    flushed before its newline, or before its image exists), one frame per period."""
    (folder / "rgb").mkdir(parents=True, exist_ok=True)
    (folder / "depth").mkdir(exist_ok=True)
    (folder / "camera.txt").write_text(camera)
    (folder / "groundtruth.txt").write_text(gt_rows)

    def put(rel: str, data: bytes) -> None:
        tmp = folder / f"{rel}.tmp"
        tmp.write_bytes(data)
        tmp.rename(folder / rel)

    with open(folder / "rgb.txt", "a") as rgb_list, open(folder / "depth.txt", "a") as depth_list:
        for k, (t_rgb, rgb, t_dep, dep) in enumerate(frames):
            rel_rgb, rel_dep = f"rgb/{t_rgb:.6f}.png", f"depth/{t_dep:.6f}.png"
            line_first = k % 3 == 1  # the list names the image before it is written
            if not line_first:
                put(rel_rgb, rgb)
                put(rel_dep, dep)
            rgb_list.write(f"{t_rgb:.6f} {rel_rgb}")
            rgb_list.flush()
            time.sleep(period_s / 4)
            rgb_list.write("\n")
            rgb_list.flush()
            depth_list.write(f"{t_dep:.6f} {rel_dep}\n")
            depth_list.flush()
            if line_first:
                time.sleep(period_s / 4)
                put(rel_rgb, rgb)
                put(rel_dep, dep)
            time.sleep(period_s)


@pytest.mark.slow
def test_follow_a_tum_folder_being_written(tmp_path, monkeypatch):
    """rgb.txt and depth.txt grow while ctcvo online --follow runs: every frame is taken once,
    paired as the TUM reader pairs a finished folder, with the same teacher edges and ground
    truth as a run over that finished folder; a rerun is kept until the lists grow."""
    frames, camera, gt_rows = _tum_frames()
    live = tmp_path / "live"
    live.mkdir()
    cfg = online_loop.OnlineConfig(poll_s=0.01, timeout_s=2.0)
    writer = threading.Thread(target=_write_tum, args=(live, frames, camera, gt_rows, 0.04))
    writer.start()
    try:
        res = online.online(str(live), tmp_path / "follow", follow=True, teacher_cfg=TCFG, cfg=cfg, progress=False)
    finally:
        writer.join()
    assert res.frames == 20 and res.report["frame_ids"] == "0..19 (20 frames)"
    rows = read_tum(res.out / online_outputs.TRAJECTORY)
    np.testing.assert_allclose(rows.timestamps, [f[0] for f in frames], atol=1e-6)
    # the same folder, finished, read by the TUM reader
    batch = online.online(str(live), tmp_path / "batch", teacher_cfg=TCFG, progress=False)
    assert batch.frames == 20
    assert (res.out / "teacher" / "edges.g2o").read_text() == (batch.out / "teacher" / "edges.g2o").read_text()
    assert (res.out / "teacher" / "groundtruth.tum").read_text() == \
        (batch.out / "teacher" / "groundtruth.tum").read_text()
    assert res.report["final"]["ate_rmse_m"] == pytest.approx(batch.report["final"]["ate_rmse_m"], rel=1e-6)
    # rerun: kept while the lists have not grown; one more frame (and a line without its
    # newline yet, not read) and it runs again over all of them
    assert online.online(str(live), tmp_path / "follow", follow=True, teacher_cfg=TCFG, cfg=cfg, progress=False).kept
    t, rgb, t_dep, dep = frames[-1]
    _write_tum(live, [(t + 1 / 30, rgb, t_dep + 1 / 30, dep)], camera, gt_rows)
    with open(live / "rgb.txt", "a") as fh:
        fh.write("1305031200.000000 rgb/half-writ")
    src = online.open_source(str(live), follow=True, cfg=cfg)
    assert isinstance(src, FollowTum) and len(src.present_ids()) == 21

    class Ran(Exception):
        pass

    monkeypatch.setattr(online, "run", lambda *a, **k: (_ for _ in ()).throw(Ran()))
    with pytest.raises(Ran):
        online.online(str(live), tmp_path / "follow", follow=True, teacher_cfg=TCFG, cfg=cfg, progress=False)


def test_follow_picks_the_layout_and_waits_for_one(tmp_path):
    cfg = online_loop.OnlineConfig(poll_s=0.01, timeout_s=0.2)
    from ctcvo.data.errors import DataError

    (tmp_path / "tum_fr1").mkdir()
    (tmp_path / "tum_fr1" / "rgb.txt").write_text("# nothing yet\n")
    assert isinstance(online.open_source(str(tmp_path / "tum_fr1"), follow=True, cfg=cfg), FollowTum)
    (tmp_path / "seven").mkdir()
    (tmp_path / "seven" / "frame-000000.depth.png").write_bytes(b"")
    assert isinstance(online.open_source(str(tmp_path / "seven"), follow=True, cfg=cfg), FollowSevenScenes)
    (tmp_path / "empty").mkdir()
    with pytest.raises(DataError, match="no frame arrived within 0.2 s"):
        online.open_source(str(tmp_path / "empty"), follow=True, cfg=cfg)


@pytest.mark.slow
def test_ctrl_c_gives_one_line_and_exit_130(tmp_path, redkitchen):
    """Ctrl-C (SIGINT to the process group, as a terminal sends it) mid-run: exit 130, one
    line after the progress lines, and no Open3D memory listing at exit."""
    import signal
    import subprocess
    import sys

    out = tmp_path / "o"
    argv = [sys.executable, "-m", "ctcvo", "online", "--scene", str(redkitchen), "--frames", "0:600", "--out", str(out)]
    proc = subprocess.Popen(argv, cwd=Path(__file__).resolve().parents[1], env={**os.environ, "OMP_NUM_THREADS": "1"},
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True)
    try:
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline and proc.poll() is None:
            traj = out / online_outputs.TRAJECTORY
            if traj.is_file() and len(traj.read_text().splitlines()) >= 30:
                break
            time.sleep(0.05)
        assert proc.poll() is None, "the run ended before it could be interrupted"
        os.killpg(proc.pid, signal.SIGINT)
        _, err = proc.communicate(timeout=120)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 130, err[-2000:]
    assert "Open3D" not in err
    after = [line for line in err.splitlines() if " online: " not in line]
    assert len(after) <= 2 and after[-1].startswith("interrupted after "), after


def test_online_writes_and_adjusts_the_batch_teachers_landmark_sightings(tmp_path):
    """With registered colour the online teacher's observations.csv is teacher generate's, and
    the final solve adjusts them as posegraph optimize does."""
    from ctcvo.teacher.generate import generate

    cfg = replace(TCFG, colour_camera="registered")
    generate("synthetic/tiny", tmp_path / "batch", config=replace(cfg, workers=1), progress=False)
    run = online.run(online.open_source("synthetic/tiny"), tmp_path / "online", cfg, progress=False)
    ours = next((tmp_path / "online").rglob("teacher/observations.csv")).read_text()
    assert ours == next((tmp_path / "batch").rglob("observations.csv")).read_text()
    assert run.report["final_polish"]["bundle"]["sightings"] > 0
