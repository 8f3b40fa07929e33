"""data/chain.py: the one trajectory chaining, with known answers."""

from __future__ import annotations

import numpy as np

from ctcvo.data import geometry as geo
from ctcvo.data.chain import chain_edges, chain_steps


def _poses(n: int, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    out = [geo.se3_exp(rng.normal(size=6))]
    for _ in range(n - 1):
        out.append(out[-1] @ geo.se3_exp(rng.normal(0, 0.1, 6)))
    return np.array(out)


def test_chain_steps_is_dead_reckoning_from_the_first_pose():
    gt = _poses(8)
    steps = [geo.relative_pose(gt[k], gt[k + 1]) for k in range(7)]
    np.testing.assert_allclose(chain_steps(steps, gt[0]), gt, atol=1e-12)
    np.testing.assert_allclose(chain_steps(steps)[0], np.eye(4))
    assert chain_steps(np.zeros((0, 4, 4))).shape == (1, 4, 4)


def test_edges_walked_backwards_are_inverted_and_gap_one_is_preferred():
    """Frame 2 is reached only through the edge (2, 3) walked from 3 to 2; the noisy gap-2
    edge (0, 2) is not used where gap-1 edges connect."""
    gt = _poses(5, seed=1)
    ids = np.array([10, 11, 12, 13, 14])
    pairs = [(0, 1), (1, 3), (2, 3), (3, 4), (0, 2)]
    T = [geo.relative_pose(gt[a], gt[b]) for a, b in pairs]
    T[4] = T[4] @ geo.se3_exp([0.5, 0, 0, 0, 0.3, 0])  # wrong, and must stay unused
    ch = chain_edges(ids, pairs, T, gt[0])
    assert ch.reached.all()
    np.testing.assert_allclose(ch.poses, gt, atol=1e-12)
    assert ch.bridges == [{"i": 11, "j": 12, "method": "edge 11->13"}]


def test_unreached_frames_are_nan_or_filled_by_constant_velocity():
    """Frames 3..5 have no edge to 0..2: NaN without fill_gaps; with it, frame 3 repeats
    the step 1 -> 2 and frames 4, 5 follow their own edges."""
    gt = _poses(6, seed=2)
    pairs = [(0, 1), (1, 2), (3, 4), (4, 5)]
    T = [geo.relative_pose(gt[a], gt[b]) for a, b in pairs]
    ch = chain_edges(np.arange(6), pairs, T)
    assert ch.reached.tolist() == [True] * 3 + [False] * 3 and np.isnan(ch.poses[3:]).all()
    assert ch.bridges == []
    ch = chain_edges(np.arange(6), pairs, T, gt[0], fill_gaps=True)
    assert ch.reached.tolist() == [True] * 3 + [False] * 3  # connected by edges: still no
    np.testing.assert_allclose(ch.poses[:3], gt[:3], atol=1e-12)
    np.testing.assert_allclose(ch.poses[3], gt[2] @ geo.relative_pose(gt[1], gt[2]), atol=1e-12)
    for k in (4, 5):
        np.testing.assert_allclose(geo.relative_pose(ch.poses[3], ch.poses[k]), geo.relative_pose(gt[3], gt[k]),
                                   atol=1e-12)
    assert ch.bridges == [{"i": 2, "j": 3, "method": "constant velocity"}]
