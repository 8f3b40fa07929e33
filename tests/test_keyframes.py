"""Keyframe and loop edges of the teacher (ctcvo.teacher.keyframes, ctcvo.teacher.loops)."""

from __future__ import annotations

import copy
import dataclasses

import numpy as np
import pytest

from ctcvo.data import geometry as geo
from ctcvo.data.formats import Edge, read_edges_csv, read_g2o
from ctcvo.data.scenes import open_scene
from ctcvo.posegraph.graph import solve
from ctcvo.teacher import cli
from ctcvo.teacher.config import TINY
from ctcvo.teacher.generate import run_sequence
from ctcvo.teacher.keyframes import FALLBACK_GATE_M, gate_fallback
from ctcvo.teacher.loops import verify
from ctcvo.teacher.record import EdgeDiagnostics, EdgeEstimate

CFG = dataclasses.replace(TINY, workers=1, keyframes=True)


def _there_and_back(seq, period: float = 0.5):
    """``seq`` played forward then backward (its last frame's images are its first's), one frame
    every ``period`` seconds, so the return is old enough to be a loop candidate."""
    n = len(seq)
    order = np.concatenate([np.arange(n), np.arange(n - 2, -1, -1)])
    base = seq._positions[order]
    view = copy.copy(seq)
    rgb, depth = seq._read_rgb, seq._read_depth
    view._read_rgb = lambda p: rgb(int(base[p]))
    view._read_depth = lambda p: depth(int(base[p]))
    view.timestamps = np.arange(len(order)) * period
    view.depth_timestamps = None
    view.frame_ids = np.arange(len(order), dtype=np.int64)
    gt = seq.groundtruth()
    view._gt = None if gt is None else gt[order]
    view._positions = np.arange(len(order))
    return view


def test_keyframe_edges_are_marked_in_edges_csv(tmp_path):
    out = tmp_path / "t"
    assert cli.main(["generate", "--scene", "synthetic/tiny", "--out", str(out), "--preset", "tiny",
                     "--workers", "1", "--keyframes"]) == 0
    rows = read_edges_csv(next(out.rglob("edges.csv")))
    kinds = {r["kind"] for r in rows}
    assert {"window", "keyframe"} <= kinds
    gap = max(r["j"] - r["i"] for r in rows if r["kind"] == "window")
    kf = [r for r in rows if r["kind"] == "keyframe"]
    assert gap == TINY.gaps and all(r["j"] - r["i"] > gap for r in kf)
    g2o_edges, _ = read_g2o(next(out.rglob("edges.g2o")))
    pairs = {(e.i, e.j) for e in g2o_edges}
    assert {(r["i"], r["j"]) for r in kf if r["status"] == "ok"} <= pairs


@pytest.fixture(scope="module")
def loop_run():
    seq = _there_and_back(open_scene("synthetic/tiny")[0])
    return seq, run_sequence(seq, CFG, progress=False)


def test_a_synthetic_loop_closes(loop_run):
    seq, run = loop_run
    n = len(seq)
    loops = [e for e in run.edges if run.kinds.get((e.i, e.j)) == "loop" and e.ok]
    assert any(e.i == 0 for e in loops), "the return to the start was not recognised"

    def end_to_start(kinds: set[str]) -> float:
        edges = [Edge(e.i, e.j, e.T_i_j, e.cov) for e in run.edges
                 if e.ok and run.kinds.get((e.i, e.j), "window") in kinds]
        poses = solve(seq.ids(), edges, run.poses).poses
        return float(np.linalg.norm(geo.relative_pose(poses[0], poses[n - 1])[:3, 3]))

    closed = end_to_start({"window", "keyframe", "loop"})
    assert closed < 0.01  # the last frame's images are the first's: it is at the start
    assert closed < 0.5 * end_to_start({"window", "keyframe"})  # and the loop edges are why


def test_a_false_loop_is_rejected(loop_run):
    seq, run = loop_run
    e = next(e for e in run.edges if run.kinds.get((e.i, e.j)) == "loop" and e.ok)
    assert verify(e, e.T_i_j).ok
    far = e.T_i_j @ geo.se3_exp(np.array([0.5, 0.0, 0.0, 0.0, 0.0, 0.0]))  # another place, 0.5 m away
    assert verify(e, far).status == "loop_rejected"


def test_a_fallback_keyframe_edge_far_from_its_prediction_is_rejected():
    T = geo.se3_exp(np.array([0.2, 0.0, 0.1, 0.0, 0.05, 0.0]))
    near = T @ geo.se3_exp(np.array([0.5 * FALLBACK_GATE_M, 0.0, 0.0, 0.0, 0.0, 0.0]))
    far = T @ geo.se3_exp(np.array([2.0 * FALLBACK_GATE_M, 0.0, 0.0, 0.0, 0.0, 0.0]))
    turned = T @ geo.se3_exp(np.array([0.0, 0.0, 0.0, 0.0, 0.0, np.deg2rad(10.0)]))
    for path in ("depth", "rgbd", "dense"):
        e = EdgeEstimate(3, 40, "ok", T_i_j=T, cov=np.eye(6), diag=EdgeDiagnostics(path=path))
        assert gate_fallback(e, near).ok
        assert gate_fallback(e, far).status == "fallback_disagrees"
        assert gate_fallback(e, turned).status == "fallback_disagrees"
    sparse = EdgeEstimate(3, 40, "ok", T_i_j=T, cov=np.eye(6), diag=EdgeDiagnostics(path="guided"))
    assert gate_fallback(sparse, far).ok  # keypoint edges answer to the pose graph's rules alone
    failed = EdgeEstimate(3, 40, "few_inliers", diag=EdgeDiagnostics(path="rgbd"))
    assert gate_fallback(failed, far).status == "few_inliers"


def test_keyframe_pass_in_worker_processes_gives_the_same_edges(monkeypatch):
    """The keyframe pass cut between this process and a worker (two keyframe edges per worker
    suffice here) gives the keyframe edges of one process bit for bit."""
    from ctcvo.teacher import generate

    seq = open_scene("synthetic/tiny")[0]
    one = run_sequence(seq, CFG, progress=False)
    here: list[int] = []
    estimate = generate.estimate_works

    def counted(works, *args):  # this process's share (the worker's runs unpatched)
        here.append(len(works))
        return estimate(works, *args)

    monkeypatch.setattr(generate, "KF_EDGES_PER_WORKER", 2)
    monkeypatch.setattr(generate, "estimate_works", counted)
    two = run_sequence(seq, dataclasses.replace(CFG, workers=2), progress=False)
    n_works = len(generate.keyframe_works(seq, CFG, one.poses))
    assert len(here) == 1 and 0 < here[0] < n_works  # this process estimated only its share
    assert one.kinds == two.kinds and len(one.kinds) >= 4
    a = {(e.i, e.j): e for e in one.edges if (e.i, e.j) in one.kinds}
    b = {(e.i, e.j): e for e in two.edges if (e.i, e.j) in two.kinds}
    for k, e in a.items():
        assert e.status == b[k].status and np.array_equal(e.T_i_j, b[k].T_i_j) and np.array_equal(e.cov, b[k].cov)


def test_keyframes_picked_on_the_window_pass_looks_are_those_of_the_images():
    """The depth points and thumbnails the window pass keeps of each frame pick the keyframes,
    covisible keyframes and loop candidates that reading the images again picks."""
    from ctcvo.teacher import generate

    seq = _there_and_back(open_scene("synthetic/tiny")[0])
    edges, _, looks = generate._run_chunk(seq, CFG, 0, len(seq))
    assert sorted(looks) == [int(f) for f in seq.ids()]
    poses, _ = generate.chain_trajectory(seq.ids(), edges)
    shape = [(w.b.pos, [a.pos for a in w.covisible], [a.pos for a in w.loops])
             for w in generate.keyframe_works(seq, CFG, poses)]
    assert shape == [(w.b.pos, [a.pos for a in w.covisible], [a.pos for a in w.loops])
                     for w in generate.keyframe_works(seq, CFG, poses, looks)]
    assert any(w[2] for w in shape)  # a loop candidate, found on the thumbnails


def test_the_incremental_api_frame_by_frame():
    """KeyframeSelector and KeyframeHistory fed one frame at a time (as ``ctcvo online`` feeds
    them, no sequence at hand): a keyframe every KF_TRANS_M; keyframe edges to the newest
    covisible keyframes beyond the window's gaps and within REACH_S, at most MAX_COVISIBLE;
    loop candidates only older than REACH_S, by their look."""
    from ctcvo.data.sequence import Intrinsics
    from ctcvo.teacher import keyframes as kf

    intr = Intrinsics(fx=500.0, fy=500.0, cx=320.0, cy=240.0, width=640, height=480)
    depth = np.full((480, 640), 3.0, np.float32)  # a wall 3 m ahead
    rng = np.random.default_rng(0)
    looks = rng.standard_normal((60, 1200))
    looks /= np.linalg.norm(looks, axis=1, keepdims=True)  # unrelated places: correlations near 0
    looks[58] = looks[0]  # the last keyframe looks like the first
    sel, hist, gaps = kf.KeyframeSelector(intr), kf.KeyframeHistory(intr, gaps=2), 2
    step = 0.6 * kf.KF_TRANS_M  # a keyframe every second frame
    works = []
    for k in range(60):
        T = np.eye(4)
        T[0, 3] = step * k
        pts = kf.depth_points(depth, intr)
        if sel.offer(T, pts):
            works.append(hist.add(kf.Keyframe(k, k, 0.25 * k, T, pts, looks[k])))
    assert [w.b.pos for w in works] == list(range(0, 60, 2))
    for w in works:
        assert len(w.covisible) <= kf.MAX_COVISIBLE
        assert all(w.b.pos - a.pos > gaps and w.b.time - a.time <= kf.REACH_S for a in w.covisible)
        assert [a.pos for a in w.covisible] == sorted((a.pos for a in w.covisible), reverse=True)
        assert all(w.b.time - a.time > kf.REACH_S for a in w.loops)
    assert [a.pos for a in works[2].covisible] == [0]  # 4 - 2 is within the gaps
    assert len(works[-1].covisible) == kf.MAX_COVISIBLE
    assert [(w.b.pos, [a.pos for a in w.loops]) for w in works if w.loops] == [(58, [0])]


def test_a_frame_with_one_stream_repeated_is_never_a_keyframe_and_keyframes_carry_their_velocity():
    """A frame whose colour (or depth) image repeats the previous frame's while the other is
    new is passed over (the next new frame is picked); a keyframe's velocity is its pose
    estimates' per second into it, unknown next to a repeated image."""
    from ctcvo.data.sequence import Intrinsics
    from ctcvo.teacher import keyframes as kf

    intr = Intrinsics(fx=500.0, fy=500.0, cx=320.0, cy=240.0, width=640, height=480)
    pts = kf.depth_points(np.full((480, 640), 3.0, np.float32), intr)
    step = geo.se3_exp(np.array([2.0 * kf.KF_TRANS_M, 0, 0, 0, 0.01, 0]))  # a keyframe every frame
    keys = [(bytes([k]), bytes([k])) for k in range(8)]
    keys[3] = (keys[2][0], b"new")  # frame 3's colour repeats frame 2's
    keys[6] = (keys[5][0] + b"+", keys[5][1])  # frame 6's depth repeats frame 5's
    sel, picked, velocity = kf.KeyframeSelector(intr), [], {}
    T = np.eye(4)
    for k in range(8):
        if sel.offer(T, pts, keys[k], 0.1 * k):
            picked.append(k)
            velocity[k] = sel.velocity
        T = T @ step
    assert picked == [0, 1, 2, 4, 5, 7]
    assert velocity[0] is None and velocity[4] is None  # frame 0: no motion yet; 4: after the repeat in 3
    np.testing.assert_allclose(velocity[2], geo.se3_log(step) / 0.1, atol=1e-9)
    assert velocity[7] is None  # after frame 6's repeated depth
    assert sel.offer(T, pts) is True and sel.velocity is None  # keys unknown: taken as new, no time, no velocity


def test_keyframe_edges_are_corrected_for_the_rolling_shutter():
    """The keyframe pass resolves the sensor's readout (synthetic/tiny: 27 ms) as the window
    does: on the same pose estimates, its edges between keyframes of known velocity move
    against those of a teacher told the shutter is global; a noise-free scene (no readout)
    gives the same edges either way."""
    from ctcvo.teacher import generate, keyframes

    def kf_edges(scene):
        seq = open_scene(scene)[0]
        poses, _ = generate.chain_trajectory(seq.ids(), generate._run_chunk(seq, CFG, 0, len(seq))[0])
        works = keyframes.keyframe_works(seq, CFG, poses)
        moving = {w.b.frame_id for w in works if w.b.velocity is not None}
        assert len(moving) >= len(works) - 2
        out = []
        for rolling in (None, 0.0):
            cfg = dataclasses.replace(CFG, rolling_shutter_s=rolling)
            found = keyframes.keyframe_edges(seq, cfg, poses, generate.features_of(seq, cfg))
            out.append({(e.i, e.j): e.T_i_j for e, _ in found if e.ok})
        return out, moving

    (auto, off), moving = kf_edges("synthetic/tiny")
    assert auto.keys() == off.keys()
    both = [k for k in auto if k[0] in moving and k[1] in moving]
    assert len(both) >= 3
    assert all(np.linalg.norm(auto[k][:3, 3] - off[k][:3, 3]) > 1e-5 for k in both)  # corrected (metres)
    (clean_auto, clean_off), _ = kf_edges("synthetic/tiny-clean")
    assert clean_auto and all(np.array_equal(clean_auto[k], clean_off[k]) for k in clean_auto)


def test_keyframes_of_registered_colour_extract_more_features():
    """Keyframes extract ``REGISTERED_FEATURE_FACTOR`` times the window's ORB features where the
    colour is registered to the depth (a noise-free room: no colour model), strongest first, and
    the searches without a prediction take the strongest ``n_features`` (a prefix: the same
    indices); the window's count times ``SEPARATE_FEATURE_FACTOR`` with a separate colour
    camera; online's helper thread uses the same detector."""
    from ctcvo.teacher import generate, keyframes

    assert keyframes.REGISTERED_FEATURE_FACTOR > 1
    for scene, factor in (("synthetic/tiny-clean", keyframes.REGISTERED_FEATURE_FACTOR),
                          ("synthetic/tiny", keyframes.SEPARATE_FEATURE_FACTOR)):
        seq = open_scene(scene)[0]
        colour = generate.colour_camera_for(seq.sensor, CFG)
        assert (colour is None) == (scene == "synthetic/tiny-clean")
        assert keyframes.keyframe_orb(CFG, colour).orb.getMaxFeatures() == CFG.n_features * factor
        f = generate.features_of(seq, CFG)(0)
        n_win = len(generate.extract(seq.rgb(0), seq.depth(0), CFG, generate.make_orb(CFG), seq.intrinsics.K, colour).uv)
        if factor == 1:
            assert len(f.uv) == n_win and f.searched is None and f.strongest() is f
            continue
        assert len(f.uv) > n_win and f.searched == CFG.n_features
        s = f.strongest()
        assert len(s.uv) == CFG.n_features and np.array_equal(s.desc, f.desc[:CFG.n_features])
        assert np.array_equal(s.uv, f.uv[:CFG.n_features]) and s.tree().n == CFG.n_features
