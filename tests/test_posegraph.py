"""Pose graph: known-answer solves, robust outlier handling, covariance frame vs GTSAM."""

from __future__ import annotations

import dataclasses

import gtsam
import numpy as np
import pytest

from ctcvo.data import geometry as geo
from ctcvo.data.formats import Edge
from ctcvo.posegraph import factors, solvers
from ctcvo.posegraph import synthetic as syn
from ctcvo.posegraph.config import DEFAULT, PLAIN
from ctcvo.posegraph.edges import GraphError, chain_poses, whitened_residuals
from ctcvo.posegraph.graph import solve


def _loop(n: int = 16) -> np.ndarray:
    """Poses on a closed circle (the last frame is one step before the first)."""
    out = []
    for k in range(n):
        a = 2 * np.pi * k / n
        out.append(geo.make_T(geo.se3_exp([0, 0, 0, 0.1 * np.sin(a), a, 0])[:3, :3],
                              [np.cos(a), 0.2 * np.sin(2 * a), np.sin(a)]))
    return np.array(out)


def _max_err(a: np.ndarray, b: np.ndarray) -> float:
    """Largest |log(inv(a_k) b_k)| over poses (both anchored at the same first pose)."""
    return max(float(np.abs(geo.se3_log(geo.inv_T(x) @ y)).max()) for x, y in zip(a, b))


@pytest.mark.parametrize("solver", ["lm", "isam2"])
def test_loop_recovered_from_perturbed_initial_values(solver):
    gt = _loop()
    n = len(gt)
    cov = syn.diag_cov(0.01, 0.005)
    edges = syn.make_edges(gt, [1, 2], cov)
    edges.append(Edge(n - 1, 0, geo.relative_pose(gt[-1], gt[0]), cov))  # loop closure
    rng = np.random.default_rng(3)
    init = np.array([T @ geo.se3_exp(rng.normal(0, 0.1, 6)) for T in gt])
    init[0] = gt[0]  # the prior fixes the first pose where the initial values put it
    res = solve(np.arange(n), edges, init, dataclasses.replace(PLAIN, solver=solver))
    assert _max_err(gt, res.poses) < 1e-4
    assert _max_err(gt, init) > 0.1  # the perturbation was real
    assert res.final_error < 1e-8


def test_gross_outlier_is_rejected_and_solution_stays_close():
    gt = syn.helix(40)
    rng = np.random.default_rng(7)
    cov = syn.diag_cov(0.005, 0.002)
    edges = syn.make_edges(gt, [1, 2, 3], cov, rng)
    bad = 10  # edge 10 -> 11: 0.5 m and 30 degrees off
    edges[bad] = Edge(10, 11, edges[bad].T_i_j @ geo.se3_exp([0.5, 0, 0, 0, np.radians(30), 0]), cov)
    robust = solve(np.arange(40), edges, None, DEFAULT)
    plain = solve(np.arange(40), edges, None, PLAIN)
    gt0 = np.array([geo.relative_pose(gt[0], T) for T in gt])  # anchored like the solve
    err_r = max(np.linalg.norm(a[:3, 3] - b[:3, 3]) for a, b in zip(gt0, robust.poses))
    err_p = max(np.linalg.norm(a[:3, 3] - b[:3, 3]) for a, b in zip(gt0, plain.poses))
    assert [(o.i, o.j, o.reason, o.action) for o in robust.outliers] == [(10, 11, "residual", "removed")]
    assert err_r < 0.03, err_r  # the noise alone gives about 1 cm over 40 poses
    assert err_p > 3 * err_r  # least squares is pulled away by the outlier
    assert not robust.used[bad] and robust.used.sum() == len(edges) - 1


def test_outlier_downweighted_when_removal_would_disconnect():
    """Two contradicting edges 5 -> 6 are the only link between frames 0-5 and 6-11: both
    exceed the residual threshold (least squares puts frame 6 between them, whitened
    residuals about 31 and 46); the better one stays, down-weighted, the other is removed."""
    gt = syn.helix(12)
    cov = syn.diag_cov(0.01, 0.01)
    edges = syn.make_edges(gt, [1], cov)
    T = edges[5].T_i_j
    edges[5] = Edge(5, 6, T @ geo.se3_exp([0.5, 0, 0, 0, 0, 0]), cov)
    edges.append(Edge(5, 6, T @ geo.se3_exp([-0.5, 0, 0, 0, 0, 0]), syn.diag_cov(0.015, 0.01)))
    res = solve(np.arange(12), edges, None, dataclasses.replace(PLAIN, residual_threshold=20.0))
    assert [(o.i, o.j, o.reason, o.action) for o in res.outliers] == [
        (5, 6, "residual", "downweighted"), (5, 6, "residual", "removed")]
    assert res.outliers[0].value == pytest.approx(30.8, abs=1.0) and res.outliers[1].value == pytest.approx(46.2, abs=1.0)
    assert res.used.tolist() == [True] * len(edges[:-1]) + [False]


def test_chain_poses_prefers_gap_one_and_detects_disconnection():
    gt = syn.helix(6)
    edges = syn.make_edges(gt, [1, 2], syn.diag_cov(0.01, 0.01))
    poses = chain_poses(np.arange(6), edges, gt[0])
    assert _max_err(gt, poses) < 1e-9
    with pytest.raises(GraphError, match="disconnected: 2 components"):
        chain_poses(np.arange(6), [e for e in edges if not (e.i <= 2 < e.j)])


def test_covariance_frame_matches_gtsam_between_factor_whitening():
    """Sample delta ~ N(0, C) in project order, perturb T_true = T_meas @ exp(delta): GTSAM's
    BetweenFactorPose3 with cov_to_gtsam(C) must see delta (re-ordered) and whiten it to
    unit covariance. A left perturbation exp(delta) @ T_meas must fail the same check."""
    rng = np.random.default_rng(0)
    T_meas = geo.make_T(geo.se3_exp([0, 0, 0, 0.4, -0.9, 0.3])[:3, :3], [1.5, -0.4, 2.0])
    A = rng.normal(size=(6, 6))
    C = A @ A.T * 1e-4 + np.diag([4e-4, 1e-6, 1e-5, 1e-6, 2.5e-3, 1e-5])  # anisotropic, correlated
    noise = gtsam.noiseModel.Gaussian.Covariance(geo.cov_to_gtsam(C))
    factor = gtsam.BetweenFactorPose3(0, 1, gtsam.Pose3(T_meas), noise)
    deltas = rng.multivariate_normal(np.zeros(6), C, size=4000)

    def whitened(Ts):
        out, raw = [], []
        for T in Ts:
            v = gtsam.Values()
            v.insert(0, gtsam.Pose3())
            v.insert(1, gtsam.Pose3(T))
            raw.append(factor.unwhitenedError(v))
            out.append(noise.whiten(raw[-1]))
        return np.array(raw), np.array(out)

    raw, w = whitened([T_meas @ geo.se3_exp(d) for d in deltas])
    np.testing.assert_allclose(geo.vec_from_gtsam(raw), deltas, atol=1e-5)
    np.testing.assert_allclose(np.cov(w.T), np.eye(6), atol=0.1)
    _, w_left = whitened([geo.se3_exp(d) @ T_meas for d in deltas])
    assert np.abs(np.cov(w_left.T) - np.eye(6)).max() > 1.0


def test_marginal_covariance_is_edge_covariance_in_project_order(monkeypatch):
    """Pose 0 fixed, one edge with covariance C: the marginal of pose 1 (right
    perturbation, converted back to project order) is C."""
    monkeypatch.setattr(factors, "PRIOR_SIGMA_ROT_RAD", 1e-9)
    monkeypatch.setattr(factors, "PRIOR_SIGMA_TRANS_M", 1e-9)
    T01 = geo.make_T(geo.se3_exp([0, 0, 0, 0.3, 0.2, -0.5])[:3, :3], [0.3, 0.1, -0.2])
    A = np.random.default_rng(1).normal(size=(6, 6))
    C = A @ A.T * 1e-3 + np.eye(6) * 1e-4
    res = solve(np.arange(2), [Edge(0, 1, T01, C)], None, dataclasses.replace(PLAIN, marginals=True))
    np.testing.assert_allclose(res.marginals[1], C, rtol=1e-5, atol=1e-10)
    assert np.abs(res.marginals[0]).max() < 1e-15


def test_isam2_matches_lm_on_noisy_graph():
    gt = syn.helix(50)
    edges = syn.make_edges(gt, [1, 2, 3], syn.diag_cov(0.01, 0.005), np.random.default_rng(2))
    lm = solve(np.arange(50), edges, None, PLAIN)
    isam = solve(np.arange(50), edges, None, dataclasses.replace(PLAIN, solver="isam2"))
    assert _max_err(lm.poses, isam.poses) < 1e-3


# ----------------------------------------------------------------------------------
# vectorised internals used by large graphs
# ----------------------------------------------------------------------------------
def test_vectorised_residuals_match_gtsam():
    """The vectorised whitened residuals equal GTSAM's BetweenFactorPose3 whitened error,
    also for gross errors (30 degrees) where a small-angle shortcut would be wrong."""
    rng = np.random.default_rng(4)
    gt = syn.helix(12)
    A = rng.normal(size=(6, 6))
    C = A @ A.T * 1e-4 + np.eye(6) * 1e-5  # correlated, anisotropic
    edges = syn.make_edges(gt, [1, 2, 3], C, rng)
    edges[4] = Edge(4, 5, edges[4].T_i_j @ geo.se3_exp([0.3, 0, 0.1, 0, np.radians(30), 0.1]), C)
    poses = np.array([T @ geo.se3_exp(rng.normal(0, 0.01, 6)) for T in gt])
    ours = whitened_residuals(poses, np.arange(12), edges)
    noise = gtsam.noiseModel.Gaussian.Covariance(geo.cov_to_gtsam(C))
    values = gtsam.Values()
    for k, T in enumerate(geo.orthonormalize(poses)):
        values.insert(k, gtsam.Pose3(T))
    ref = [np.linalg.norm(noise.whiten(gtsam.BetweenFactorPose3(e.i, e.j, gtsam.Pose3(e.T_i_j), noise)
                                       .unwhitenedError(values))) for e in edges]
    np.testing.assert_allclose(ours, ref, rtol=1e-7)
    assert ours[4] > 30 and np.median(ours) < 10


def test_chain_poses_is_dead_reckoning_with_noisy_long_edges():
    """With a complete gap-1 chain, the spanning tree is that chain (frame k+1 is never
    reached through a noisy longer edge, which would make neighbours drift apart)."""
    gt = syn.helix(30)
    edges = syn.make_edges(gt, [3, 1, 2], syn.diag_cov(0.01, 0.01), np.random.default_rng(1))
    np.testing.assert_allclose(chain_poses(np.arange(30), edges), syn.chain_trajectory(edges, 30), atol=1e-12)


def test_default_tolerance_is_converged_well_inside_the_noise(monkeypatch):
    """The default LM stopping rule (relative cost decrease 1e-6) lands within 0.1 mm (1 %
    of one edge's 1 cm sigma) of a solve run to 1e-14, with fewer iterations."""
    gt = syn.helix(300, turns=1.5)
    edges = syn.make_edges(gt, [1, 2, 3, 4, 5], syn.diag_cov(0.01, 0.005), np.random.default_rng(6))
    init = syn.chain_trajectory(edges, 300)
    fast = solve(np.arange(300), edges, init, DEFAULT)
    monkeypatch.setattr(solvers, "LM_RELATIVE_ERROR_TOL", 1e-14)
    tight = solve(np.arange(300), edges, init, DEFAULT)
    diff = max(np.linalg.norm(a[:3, 3] - b[:3, 3]) for a, b in zip(fast.poses, tight.poses))
    assert diff < 1e-4, diff
    assert fast.iterations < tight.iterations
    assert [(o.i, o.j) for o in fast.outliers] == [(o.i, o.j) for o in tight.outliers]


def test_overconfident_source_is_rescaled_before_outlier_rejection():
    """Teacher edges with correct covariances (gaps 1-2) fused with learner edges that are
    3x noisier but claim covariances 1000x too small (gaps 1-4). Without calibration the
    outlier pass throws away a large part of the good edges; with it the learner's
    scale comes out near 1000, few teacher edges are rejected and the fused poses are
    at least as good as the teacher alone."""
    n = 120
    gt = syn.helix(n, turns=1.2)
    rng = np.random.default_rng(11)
    teacher = syn.make_edges(gt, [1, 2], syn.diag_cov(0.01, 0.005), rng, source="teacher")
    learner = syn.make_edges(gt, [1, 2, 3, 4], syn.diag_cov(0.03, 0.015), rng, source="learner")
    for e in learner:
        e.cov = e.cov / 1000.0
    gt0 = np.array([geo.relative_pose(gt[0], T) for T in gt])

    def max_err(res):
        return max(np.linalg.norm(a[:3, 3] - b[:3, 3]) for a, b in zip(gt0, res.poses))

    def rejected(res, source):
        return sum(o.source == source for o in res.outliers)

    ids = np.arange(n)
    cfg = dataclasses.replace(DEFAULT, residual_threshold=5.0)  # a strict cut shows the failure best
    alone = solve(ids, teacher, None, cfg)
    naive = solve(ids, teacher + learner, None, dataclasses.replace(cfg, calibrate=False))
    fused = solve(ids, teacher + learner, None, cfg)
    assert rejected(naive, "teacher") > 0.1 * len(teacher)  # the failure being fixed
    assert naive.source_scales == {"teacher": 1.0, "learner": 1.0} and naive.calibration is None
    assert rejected(fused, "teacher") <= 0.02 * len(teacher)
    assert rejected(fused, "learner") <= 0.05 * len(learner)
    assert 500 < fused.source_scales["learner"] < 2000, fused.source_scales
    assert 0.5 < fused.source_scales["teacher"] < 1.5, fused.source_scales
    cal = fused.calibration
    assert cal["converged"] and cal["iterations"] >= 2
    assert all(abs(np.log(c["residual_factor"])) <= np.log(1.25) for c in cal["sources"].values())
    assert max_err(fused) <= 1.05 * max_err(alone) < max_err(naive)


def test_calibrated_single_source_is_left_as_given():
    """A source whose covariances are right keeps scale 1 (no re-solve); the same edges
    with covariances 50x too small get scale ~50 and the same poses."""
    gt = syn.helix(100)
    edges = syn.make_edges(gt, [1, 2, 3], syn.diag_cov(0.01, 0.005), np.random.default_rng(12))
    right = solve(np.arange(100), edges, None, DEFAULT)
    small = solve(np.arange(100), [Edge(e.i, e.j, e.T_i_j, e.cov / 50.0) for e in edges], None, DEFAULT)
    assert right.source_scales == {"edges": 1.0} and right.calibration["iterations"] == 0
    assert 35 < small.source_scales["edges"] < 70
    assert _max_err(right.poses, small.poses) < 1e-3
    assert len(small.outliers) == len(right.outliers) <= 2


@pytest.mark.parametrize("outliers", [0.0, 0.05])
def test_graph_is_no_worse_than_its_own_chain(outliers):
    """Issue 28's rule on edges the model describes: unbiased noise growing with the gap (and
    5 % of edges 10x worse, which the robust kernel and the outlier pass must absorb), the
    default solve (kernel, source calibration, outlier pass). Over several draws the graph of
    gaps 1-5 is never worse than the chain of its gap-1 edges, in ATE or in gap-1 RPE: its
    weights and outlier rules do not make a chain worse. (Where the real teacher's graph loses
    to its chain, on synthetic/lab, the long edges are biased: bench/README.md, pose graph.)"""
    from ctcvo.data.formats import Trajectory
    from ctcvo.data.metrics import ate_rmse, rpe_rmse

    n = 200
    gt = syn.helix(n, radius=2.0, turns=0.5)
    times = np.arange(n) / 30.0
    truth = Trajectory(times, gt)
    for seed in range(5):
        rng = np.random.default_rng(seed)
        edges = []
        for g in range(1, 6):
            cov = syn.diag_cov(0.002 * np.sqrt(g), np.radians(0.1) * np.sqrt(g))
            for e in syn.make_edges(gt, [g], cov, rng):
                if rng.random() < outliers:  # a heavy tail: this edge's error is 10x its sigma
                    T = geo.relative_pose(gt[e.i], gt[e.j])
                    e = dataclasses.replace(e, T_i_j=syn.sample_edge(T, 100 * cov, rng))
                edges.append(e)
        chain = Trajectory(times, syn.chain_trajectory(edges, n))
        graph = Trajectory(times, solve(np.arange(n), edges, chain.poses).poses)
        # with these weights the graph's gap-1 RPE is about 0.6x the chain's (0.2-0.3x with the
        # tail, which the chain takes whole) and its ATE 0.1-0.4x; weights that invert the
        # gaps' order and claim 10x the certainty leave the gap-1 RPE at 0.94-1.01x
        assert ate_rmse(truth, graph) <= 0.5 * ate_rmse(truth, chain), seed
        assert rpe_rmse(truth, graph, 1)[0] <= 0.8 * rpe_rmse(truth, chain, 1)[0], seed


def test_online_graph_final_survives_a_failed_isam2_update(caplog):
    """An ISAM2 update that throws in :meth:`OnlineGraph.final` (GTSAM's indeterminate
    system, seen once on synthetic/tiny) leaves the final trajectory to the batch solve, warm
    started from ISAM2's last estimate: the batch solve's poses, and a warning, not a crash."""
    from ctcvo.posegraph.online import OnlineGraph

    gt = _loop(12)
    rng = np.random.default_rng(3)
    g = OnlineGraph()
    edges = []
    for k in range(len(gt)):
        new = [Edge(i, k, geo.relative_pose(gt[i], gt[k]) @ geo.se3_exp(rng.normal(0, 1e-3, 6)), np.eye(6) * 1e-6,
                    {"source": "teacher"}) for i in range(max(0, k - 2), k)]
        g.add(k, new)
        edges += new

    class Failing:
        def __init__(self, isam):
            self.isam = isam

        def update(self, *args):
            raise RuntimeError("Indeterminate linear system detected while working near variable 4 (Symbol: 4).")

        def __getattr__(self, name):
            return getattr(self.isam, name)

    g.isam = Failing(g.isam)
    with caplog.at_level("WARNING"):
        poses = g.final()
    assert "ISAM2's last updates stopped" in caplog.text and "near frame 4" in caplog.text
    want = solve(np.arange(len(gt)), edges, g.isam2_poses, dataclasses.replace(g.cfg, solver="lm")).poses
    assert _max_err(poses, want) < 1e-9
    assert _max_err(geo.inv_T(poses[0]) @ poses, geo.inv_T(gt[0]) @ gt) < 0.01  # the trajectory, anchored at frame 0
