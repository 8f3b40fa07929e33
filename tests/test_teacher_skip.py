"""One bad frame does not end a teacher run: an unreadable image is skipped and bridged by the
longer edges, a non-finite ground-truth pose only leaves the evaluation; ``--strict`` aborts."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from ctcvo.data.errors import DataError
from ctcvo.data.formats import read_edges_csv, read_g2o, read_tum
from ctcvo.data.scenes import open_scene
from ctcvo.posegraph import cli as pg_cli
from ctcvo.teacher import cli, skips
from ctcvo.teacher.config import TeacherConfig
from ctcvo.teacher.generate import run_sequence
from tests.conftest import REDKITCHEN, require_real_data

N_FRAMES = 10


def _copy(src: Path, dst: Path, n: int = N_FRAMES) -> Path:
    """The first ``n`` frames of the 7-Scenes-layout sequence ``src`` in ``dst`` (a sequence folder)."""
    dst.mkdir(parents=True)
    for k in range(n):
        for f in src.glob(f"frame-{k:06d}.*"):
            shutil.copy(f, dst / f.name)
    for cand in (src / "camera-intrinsics.txt", src.parent / "camera-intrinsics.txt"):
        if cand.is_file():
            shutil.copy(cand, dst.parent / "camera-intrinsics.txt")
            break
    return dst


def _truncate(path: Path) -> None:
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])  # a JPEG cut off half-way, as a failed copy leaves it


@pytest.fixture()
def tiny10(tmp_path) -> Path:
    return _copy(open_scene("synthetic/tiny")[0].root, tmp_path / "scene" / "seq-01")


def _err(capsys) -> str:
    err = capsys.readouterr().err.strip().splitlines()
    assert err and err[-1].startswith("error: ") and not any("Traceback" in x for x in err)
    return err[-1]


def _generate(scene: Path, out: Path, *extra: str) -> int:
    return cli.main(["generate", "--scene", str(scene), "--out", str(out), "--preset", "tiny", *extra])


def _check_skipped(out: Path, bad: int, gaps: int) -> dict:
    """report.json lists ``bad`` as skipped and bridged; no output holds a pose or edge of it."""
    rep = json.loads((out / "report.json").read_text())
    assert rep["frames"] == N_FRAMES and [s["frame"] for s in rep["frames_skipped"]] == [bad]
    assert f"frame-{bad:06d}.color.jpg" in rep["frames_skipped"][0]["why"]
    assert rep["frames_skipped"][0]["bridge"] == f"edge {bad - 1}->{bad + 1}"
    rows = read_edges_csv(out / "edges.csv")
    assert not any(bad in (r["i"], r["j"]) for r in rows)
    pairs = {(int(r["i"]), int(r["j"])): r["status"] for r in rows if r["kind"] == "window"}
    assert pairs[(bad - 1, bad + 1)] == "ok"  # the bridge
    # every other pair within the largest gap was attempted, gaps counted in frames of the sequence
    want = {(i, j) for i in range(N_FRAMES) for j in range(i + 1, min(i + gaps, N_FRAMES - 1) + 1) if bad not in (i, j)}
    assert set(pairs) == want
    edges, vertices = read_g2o(out / "edges.g2o")
    assert sorted(vertices) == [k for k in range(N_FRAMES) if k != bad]
    assert len(read_tum(out / "trajectory.tum")) == N_FRAMES - 1
    assert np.isfinite(rep["ate_rmse_m"]) and rep["ate_rmse_m"] < 0.05
    return rep


@pytest.mark.slow
def test_truncated_jpeg_is_skipped_and_bridged(tiny10, tmp_path, capsys, caplog):
    _truncate(tiny10 / "frame-000004.color.jpg")
    out = tmp_path / "o"
    assert _generate(tiny10, out) == 0
    assert [r.getMessage().split(" (")[0] for r in caplog.records if r.levelname == "WARNING"] == [
        "scene-seq-01: frame 4 skipped"]  # one line
    _check_skipped(out, 4, gaps=2)  # the tiny preset: K = 2
    # the pose graph takes a frame without edges in its stride: it is not in the graph
    assert pg_cli.main(["optimize", "--teacher", str(out), "--out", str(tmp_path / "pg"), "--no-plots"]) == 0
    pg = json.loads((tmp_path / "pg" / "report.json").read_text())
    assert pg["frames"] == N_FRAMES - 1 and pg["rows"]["fused"]["ate_rmse_m"] < 0.05
    assert len(read_tum(tmp_path / "pg" / "trajectory.tum")) == N_FRAMES - 1
    # the learner reads every frame itself: it names the skipped one instead of asking for a rerun
    from ctcvo.learner.dataset import find_teacher_edges

    with pytest.raises(DataError, match=r"the teacher skipped frame\(s\) 4 of scene-seq-01"):
        find_teacher_edges(str(tiny10), open_scene(str(tiny10)), "all", None, out)
    # --strict: today's behaviour, one line and exit 1, nothing written
    assert _generate(tiny10, tmp_path / "strict", "--strict") == 1
    assert "frame-000004.color.jpg" in _err(capsys)
    assert not (tmp_path / "strict" / "report.json").exists()


@pytest.mark.slow
def test_truncated_jpeg_in_real_redkitchen(tmp_path, capsys):
    src = require_real_data(REDKITCHEN)
    seq = _copy(src, tmp_path / "redkitchen" / "seq-01")
    _truncate(seq / "frame-000005.color.jpg")
    out = tmp_path / "o"
    assert _generate(seq, out) == 0
    _check_skipped(out, 5, gaps=2)
    assert _generate(seq, tmp_path / "strict", "--strict") == 1
    assert "frame-000005.color.jpg" in _err(capsys)


@pytest.mark.slow
def test_unbridgeable_run_of_bad_frames_stops(tiny10, tmp_path, capsys):
    for k in (5, 6):  # two in a row: no edge of the tiny preset (K = 2) jumps over them
        _truncate(tiny10 / f"frame-{k:06d}.color.jpg")
    assert _generate(tiny10, tmp_path / "o") == 1
    err = _err(capsys)
    assert "frames 5..6" in err and "frame-000005.color.jpg" in err
    assert not (tmp_path / "o" / "report.json").exists()


@pytest.mark.slow
def test_unreadable_depth_png_is_skipped(tiny10, tmp_path):
    (tiny10 / "frame-000003.depth.png").write_bytes(b"\x89PNG\r\n")
    out = tmp_path / "o"
    assert _generate(tiny10, out, "--gaps", "3") == 0
    rep = json.loads((out / "report.json").read_text())
    assert rep["frames_skipped"][0]["frame"] == 3 and "depth" in rep["frames_skipped"][0]["why"]
    assert rep["frames_skipped"][0]["bridge"] == "edge 2->4"


@pytest.mark.slow
def test_nonfinite_groundtruth_only_leaves_the_evaluation(tiny10, tmp_path, capsys, caplog):
    (tiny10 / "frame-000003.pose.txt").write_text("nan " * 16)
    out = tmp_path / "o"
    assert _generate(tiny10, out) == 0
    assert any("frame 3 left out of the evaluation" in r.getMessage() for r in caplog.records)
    rep = json.loads((out / "report.json").read_text())
    assert rep["frames_skipped"] == [] and [d["frame"] for d in rep["groundtruth_dropped"]] == [3]
    assert "non-finite" in rep["groundtruth_dropped"][0]["why"]
    assert np.isfinite(rep["ate_rmse_m"]) and rep["ate_rmse_m"] < 0.05
    assert sum(v["edges"] for v in rep["label_error_by_gap"].values()) == 17 - 4  # (1, 3) (2, 3) (3, 4) (3, 5) touch frame 3
    assert len(read_tum(out / "trajectory.tum")) == N_FRAMES  # the teacher needs no ground truth
    gt = read_tum(out / "groundtruth.tum")
    assert len(gt) == N_FRAMES - 1 and 3 / 30 not in set(np.round(gt.timestamps, 6))
    # the pose graph evaluates over the frames groundtruth.tum covers
    assert pg_cli.main(["optimize", "--teacher", str(out), "--out", str(tmp_path / "pg")]) == 0
    pg = json.loads((tmp_path / "pg" / "report.json").read_text())
    assert pg["frames"] == N_FRAMES and pg["frames_without_groundtruth"] == [3]
    assert pg["rows"]["teacher"]["ate_rmse_m"] == pytest.approx(rep["ate_rmse_m"], rel=1e-6)
    assert (tmp_path / "pg" / "trajectories.png").is_file()
    assert _generate(tiny10, tmp_path / "strict", "--strict") == 1
    assert "non-finite" in _err(capsys)


def test_groundtruth_of_a_sequence_with_a_nonfinite_pose(tiny10):
    (tiny10 / "frame-000003.pose.txt").write_text("nan " * 16)
    seq = open_scene(str(tiny10))[0]
    assert [d["frame"] for d in seq.groundtruth_dropped()] == [3]
    with pytest.raises(DataError, match="frame-000003.pose.txt contains non-finite"):
        seq.groundtruth()  # readers that need every pose still stop, naming it
    gt = seq.groundtruth(partial=True)
    assert np.isnan(gt[3]).all() and np.isfinite(np.delete(gt, 3, axis=0)).all()
    assert seq.select(4, 8).groundtruth_dropped() == [] and np.isfinite(seq.select(4, 8).groundtruth()).all()


def test_runs_of_bad_frames():
    ids = np.arange(100, 110)
    assert skips.runs_of([7, 2, 3, 9]) == [[2, 3], [7], [9]]
    skips.check(ids, {2: "x", 3: "y", 7: "z"}, gaps=3)  # runs of 2 < K = 3 are bridged
    with pytest.raises(DataError, match=r"frames 102\.\.104 \(3 in a row\).*gap 3.*first: x"):
        skips.check(ids, {2: "x", 3: "y", 4: "z"}, gaps=3)
    with pytest.raises(DataError, match="frame 109 .*gap 1"):
        skips.check(ids, {9: "x"}, gaps=1)
    with pytest.raises(DataError, match="fewer than 2"):
        skips.check(ids[:3], {0: "a", 2: "b"}, gaps=2)


@pytest.mark.slow
def test_worker_chunks_skip_a_frame_at_their_border(tmp_path):
    """A frame read by two chunks (the first reads K frames past its end) is listed once,
    and the chunked run gives the same edges as one chunk."""
    seq_dir = _copy(open_scene("synthetic/tiny")[0].root, tmp_path / "s" / "seq-01", n=20)
    _truncate(seq_dir / "frame-000010.color.jpg")
    seq = open_scene(str(seq_dir))[0]
    one = run_sequence(seq, TeacherConfig(gaps=3, workers=1), progress=False)
    two = run_sequence(seq, TeacherConfig(gaps=3, workers=2, chunk_frames=10), progress=False)
    assert [s["frame"] for s in one.skipped] == [s["frame"] for s in two.skipped] == [10]
    assert [(e.i, e.j) for e in one.edges] == [(e.i, e.j) for e in two.edges]
    assert (9, 11) in {(e.i, e.j) for e in two.edges if e.ok} and len(two.frames) == 19


@pytest.mark.slow
def test_orbslam3_backend_skips_a_truncated_jpeg(tiny10, tmp_path, capsys):
    pytest.importorskip("pyorbslam3")
    from ctcvo.teacher import vocabulary as V

    seq = open_scene(str(tiny10))[0]
    vocab = tmp_path / "voc.txt"
    V.write_vocabulary(V.build_vocabulary(V.descriptors_of(seq, range(0, N_FRAMES, 3)), k=6, levels=3), vocab)
    _truncate(tiny10 / "frame-000004.color.jpg")
    out = tmp_path / "o"
    args = ["--backend", "orbslam3", "--vocabulary", str(vocab), "--gaps", "2"]
    assert _generate(tiny10, out, *args) == 0
    rep = json.loads((out / "report.json").read_text())
    assert [s["frame"] for s in rep["frames_skipped"]] == [4]
    pairs = {(int(r["i"]), int(r["j"])): r["status"] for r in read_edges_csv(out / "edges.csv")}
    assert pairs[(3, 4)] == pairs[(4, 5)] == "unreadable" and pairs[(3, 5)] == "ok"
    assert 4 not in read_g2o(out / "edges.g2o")[1]
    assert _generate(tiny10, tmp_path / "strict", *args, "--strict") == 1
    assert "frame-000004.color.jpg" in _err(capsys)


def test_vocabulary_leaves_an_unreadable_frame_out(tiny10, tmp_path, capsys, caplog):
    _truncate(tiny10 / "frame-000002.color.jpg")
    args = ["vocabulary", "--scene", str(tiny10), "--k", "4", "--levels", "2", "--features", "200"]
    assert cli.main([*args, "--out", str(tmp_path / "voc.txt")]) == 0
    assert any("frame 2 left out of the vocabulary" in r.getMessage() for r in caplog.records)
    assert (tmp_path / "voc.txt").is_file()
    assert cli.main([*args, "--out", str(tmp_path / "strict.txt"), "--strict"]) == 1
    assert "frame-000002.color.jpg" in _err(capsys)
    assert not (tmp_path / "strict.txt").exists()


@pytest.mark.slow
def test_bad_first_and_last_frames_shorten_the_trajectory(tiny10, tmp_path):
    for k in (0, N_FRAMES - 1):
        _truncate(tiny10 / f"frame-{k:06d}.color.jpg")
    out = tmp_path / "o"
    assert _generate(tiny10, out) == 0
    rep = json.loads((out / "report.json").read_text())
    assert [(s["frame"], s["bridge"]) for s in rep["frames_skipped"]] == [(0, None), (N_FRAMES - 1, None)]
    traj = read_tum(out / "trajectory.tum")
    assert len(traj) == N_FRAMES - 2 and traj.timestamps[0] == pytest.approx(1 / 30, abs=1e-6)
    np.testing.assert_allclose(traj.poses[0], np.eye(4), atol=1e-9)  # the first readable frame is the origin
    assert rep["bridges"] == [] and rep["ate_rmse_m"] < 0.05
