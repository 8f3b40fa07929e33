"""Landmark sightings: observations.csv, the tracks the teacher builds (keyframes' and the
window's), and the pose graph's bundle adjustment."""

from __future__ import annotations

import dataclasses
import json
import warnings

import numpy as np
import pytest

from ctcvo.data import geometry as geo
from ctcvo.data.errors import FormatError
from ctcvo.data.formats import Edge, read_observations, write_observations
from ctcvo.data.scenes import open_scene
from ctcvo.data.sequence import Intrinsics
from ctcvo.posegraph import bundle
from ctcvo.posegraph.cli import main as posegraph_main
from ctcvo.posegraph.config import ONLINE
from ctcvo.posegraph.graph import solve
from ctcvo.teacher.config import TINY
from ctcvo.teacher.generate import run_sequence, write_outputs
from ctcvo.teacher.observations import SIGHTING_SIGMA_PX, longest_tracks, sightings
from ctcvo.teacher.record import EdgeEstimate

INTR = Intrinsics(500.0, 500.0, 320.0, 240.0, 640, 480)


def test_observations_csv_round_trip_and_malformed_files(tmp_path):
    table = np.array([[0, 3, 0.1, -0.2, 1.5, 0.002], [0, 7, 0.12, -0.19, 1.4, 0.002], [1, 3, 0.0, 0.3, 2.0, 0.002]])
    write_observations(tmp_path / "o.csv", table)
    assert np.array_equal(read_observations(tmp_path / "o.csv"), table)
    write_observations(tmp_path / "none.csv", np.zeros((0, 6)))  # a registered run without sightings
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert read_observations(tmp_path / "none.csv").shape == (0, 6)
    header = "landmark,frame,x,y,z,sigma\n"
    for body, why in [("0,3,0.1,0.2,nan,0.002\n", "non-finite"), ("0,3,0.1,0.2,-1,0.002\n", "z"),
                      ("0.5,3,0.1,0.2,1,0.002\n", "integer"), ("0,3,0.1,0.2,1\n", "rows"), ("0,3,a,0.2,1,1\n", "malformed"),
                      ("0,3,0.1,0.2,1,0.002\n0,3,0.2,0.2,1,0.002\n", "twice")]:
        (tmp_path / "bad.csv").write_text(header + body)
        with pytest.raises(FormatError, match=why):
            read_observations(tmp_path / "bad.csv")
    (tmp_path / "bad.csv").write_text("frame,landmark,x,y,z,sigma\n")
    with pytest.raises(FormatError, match="header"):
        read_observations(tmp_path / "bad.csv")


def _edge(i: int, j: int, pairs: list[tuple[int, int]], z: float = 1.0) -> EdgeEstimate:
    p = np.array(pairs, dtype=np.int64)
    pts = np.column_stack([320 + 10 * p[:, 0], 240 + np.zeros(len(p)), np.full(len(p), z),
                           320 + 10 * p[:, 1], 240 + np.zeros(len(p)), np.full(len(p), z)]).astype(np.float64)
    return EdgeEstimate(i, j, "ok", np.eye(4), np.eye(6), inlier_pairs=p, inlier_points=pts)


def test_sightings_chain_matches_into_landmarks_and_drop_wrong_ones():
    edges = [_edge(0, 5, [(0, 0), (1, 1)]), _edge(5, 9, [(0, 3), (2, 4)]), _edge(0, 9, [(0, 3)]),
             _edge(9, 12, [(7, 8)], z=0.0),  # no depth: no landmark
             _edge(20, 21, [(0, 0)]), _edge(21, 22, [(0, 0)]), _edge(20, 22, [(1, 0)])]  # frame 20 twice: wrong
    edges.append(dataclasses.replace(_edge(30, 31, [(0, 0)]), status="too_few_inliers"))
    t = sightings(edges, INTR)
    landmarks = {int(lm): sorted(int(f) for f in t[t[:, 0] == lm, 1]) for lm in np.unique(t[:, 0])}
    assert sorted(landmarks.values()) == [[0, 5], [0, 5, 9], [5, 9]]
    row = t[(t[:, 1] == 9)][0]  # keypoint 3 or 4 of frame 9: normalised pixel
    assert row[2] in ((320 + 10 * 3 - INTR.cx) / INTR.fx, (320 + 10 * 4 - INTR.cx) / INTR.fx)
    assert np.allclose(t[:, 5], SIGHTING_SIGMA_PX / INTR.fx) and np.all(t[:, 4] > 0)


def test_bundle_pulls_a_biased_graph_onto_its_landmarks():
    rng = np.random.default_rng(0)
    n = 12
    poses = np.stack([geo.se3_exp(np.array([0.05 * k, 0.01 * k, 0.0, 0.0, 0.02 * k, 0.0])) for k in range(n)])
    world = rng.uniform([-1.0, -0.8, 1.5], [1.0, 0.8, 3.0], (300, 3))
    bias = geo.se3_exp(np.array([0.004, -0.003, 0.002, 0.002, -0.001, 0.001]))  # every edge errs the same way
    edges = [Edge(k, k + 1, geo.relative_pose(poses[k], poses[k + 1]) @ bias, np.eye(6) * 1e-4) for k in range(n - 1)]
    rows = []
    for lm, X in enumerate(world):
        for k in range(0, n, 3):  # keyframes 0, 3, 6, 9
            Xc = geo.inv_T(poses[k])[:3, :3] @ X + geo.inv_T(poses[k])[:3, 3]
            rows.append([lm, k, Xc[0] / Xc[2], Xc[1] / Xc[2], Xc[2], 1.0 / 500])
    table = np.array(rows)
    ids = np.arange(n)

    def err(P, at=slice(None)):
        return float(np.max(np.linalg.norm(P[at, :3, 3] - poses[at, :3, 3], axis=1)))

    graph = solve(ids, edges)
    joint = solve(ids, edges, observations=table)
    keyframes = slice(0, 10, 3)
    assert err(graph.poses, keyframes) > 0.02  # the bias adds up over the edges
    assert err(joint.poses, keyframes) < 0.001  # exact sightings put the keyframes back
    assert err(joint.poses) < 0.3 * err(graph.poses)  # and the frames between them with them
    assert joint.bundle["landmarks"] == len(world) and joint.bundle["sightings"] == len(table)
    assert solve(ids, edges, cfg=ONLINE, observations=table).bundle is None  # batch LM only (logged)
    # sightings of frames outside the graph, and landmarks left with too few, stay out
    assert bundle.usable(table, ids[:4]).shape[0] == 0  # keyframes 0 and 3 only: two sightings each
    assert len(bundle.usable(table, ids[:7])) == 3 * len(world)


@pytest.fixture(scope="module")
def registered_run():
    seq = open_scene("synthetic/tiny")[0]
    cfg = dataclasses.replace(TINY, workers=1, keyframes=True, colour_camera="registered")
    return seq, cfg, run_sequence(seq, cfg, progress=False)


def test_the_teacher_writes_sightings_for_registered_colour_only(registered_run, tmp_path):
    seq, cfg, run = registered_run
    t = run.observations
    assert t is not None and len(t) > 0
    kf = {f for e in run.edges if run.kinds.get((e.i, e.j)) in ("keyframe", "loop") for f in (e.i, e.j)}
    window = run_sequence(seq, dataclasses.replace(cfg, keyframes=False), progress=False).observations
    pos = {int(f): p for p, f in enumerate(seq.ids())}
    for lm in np.unique(window[:, 0]):  # the window's landmarks are followed frame by frame
        assert np.all(np.diff([pos[int(f)] for f in window[window[:, 0] == lm, 1]]) == 1)
    assert set(window[:, 1].astype(int)) - kf  # into the frames between keyframes
    rows = {tuple(r) for r in t[:, 1:].tolist()}
    assert all(tuple(r) in rows for r in window[:, 1:].tolist())  # the run's table holds them
    in_window = {tuple(w) for w in window[:, 1:].tolist()}
    from_keyframes = [r for r in t[:, 1:].tolist() if tuple(r) not in in_window]
    assert from_keyframes and {int(r[0]) for r in from_keyframes} <= kf  # and the keyframes' own
    assert all(e.inlier_points is None for e in run.edges)  # not kept in the results
    write_outputs(seq, run, cfg, tmp_path / "t", {})
    assert np.array_equal(read_observations(tmp_path / "t" / "observations.csv"), t)
    separate = run_sequence(seq, dataclasses.replace(cfg, colour_camera="auto"), progress=False)
    assert separate.observations is None  # synthetic/tiny's colour camera is not its depth camera
    write_outputs(seq, separate, cfg, tmp_path / "s", {})
    assert not (tmp_path / "s" / "observations.csv").exists()


def test_posegraph_optimize_adjusts_the_teachers_sightings(registered_run, tmp_path):
    seq, cfg, run = registered_run
    write_outputs(seq, run, cfg, tmp_path / "t", {})
    assert posegraph_main(["optimize", "--teacher", str(tmp_path / "t"), "--out", str(tmp_path / "g"), "--no-plots"]) == 0
    rep = json.loads((tmp_path / "g" / "report.json").read_text())
    assert rep["bundle"]["sightings"] > 0 and rep["bundle"]["landmarks"] > 0
    (tmp_path / "t" / "observations.csv").write_text("landmark,frame,x,y,z,sigma\n0,0,0.1,0.1,-1,0.01\n")
    assert posegraph_main(["optimize", "--teacher", str(tmp_path / "t"), "--out", str(tmp_path / "h"),
                           "--no-plots"]) != 0  # a corrupt table: one-line error, no traceback


def test_the_window_keeps_points_of_gap1_edges_between_new_images_only():
    """With ``sightings`` the window's good gap-1 edges keep their inlier pairs and points,
    except into and out of a frame that repeats one image of the frame before it; the longer
    edges keep neither; without it no edge keeps them."""
    from ctcvo.teacher.features import extract
    from ctcvo.teacher.window import EdgeWindow

    seq = open_scene("synthetic/tiny")[0]
    cfg = dataclasses.replace(TINY, gaps=3)

    def edges(sightings: bool) -> dict:
        w, out = EdgeWindow(seq.intrinsics, cfg, sightings=sightings), {}
        for k in range(7):
            rgb = seq.rgb(3) if k == 4 else seq.rgb(k)  # frame 4 repeats frame 3's colour
            fk = extract(rgb, seq.depth(k), cfg, K=seq.intrinsics.K)
            out.update({(e.i, e.j): e for e in w.add(int(seq.ids()[k]), k / 30, fk)})
        return out

    ids = seq.ids()
    got = edges(True)
    with_points = {(int(i), int(j)) for (i, j), e in got.items() if e.inlier_points is not None}
    assert with_points == {(int(ids[k]), int(ids[k + 1])) for k in (0, 1, 2, 5)}
    for ij in with_points:
        e = got[ij]
        assert e.ok and e.inlier_points.shape == (len(e.inlier_pairs), 6) and np.all(e.inlier_points[:, 2] > 0)
    assert all(e.inlier_pairs is None for ij, e in got.items() if ij not in with_points)
    assert all(e.inlier_points is None for e in edges(False).values())


def test_longest_tracks_keeps_each_frames_most_sighted_landmarks_whole():
    # landmark: frames; frame 2 sees 0 (3 sightings), 1 (4), 2 (2) and 3 (3)
    tracks = {0: [1, 2, 3], 1: [2, 3, 4, 5], 2: [2, 3], 3: [0, 1, 2], 4: [7, 8]}
    table = np.array([[lm, f, 0.0, 0.0, 1.0, 0.002] for lm, fs in tracks.items() for f in fs])
    kept = longest_tracks(table, 2)
    got = {int(lm): sorted(int(f) for f in kept[kept[:, 0] == lm, 1]) for lm in np.unique(kept[:, 0])}
    # frame 2 keeps 1 and 0 (the tie with 3 goes to the lower id), frame 0 keeps 3, frame 7 keeps 4;
    # landmark 2 is no frame's two longest
    assert got == {0: [1, 2, 3], 1: [2, 3, 4, 5], 3: [0, 1, 2], 4: [7, 8]}
    one = longest_tracks(table, 1)  # frame 1 keeps 0 (its tie with 3), frame 0 keeps 3, frame 2 keeps 1
    assert sorted(set(one[:, 0].astype(int))) == [0, 1, 3, 4]
    assert longest_tracks(table[:0], 5).shape == (0, 6)
