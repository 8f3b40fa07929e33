"""Known answers for three core pieces of the teacher: the depth look-up at keypoints, the
coarse-to-fine dense alignment, and the move of a pose and its covariance between the
colour and the depth moments of a frame pair."""

from __future__ import annotations

import numpy as np
import pytest

from ctcvo.data import geometry as geo
from ctcvo.teacher.fallbacks import pyramid_align
from ctcvo.teacher.features import DEPTH_EDGE_ABS, FrameFeatures, depth_at
from ctcvo.teacher.maps import DEPTH_MAX, DEPTH_MIN, dense_maps
from ctcvo.teacher.record import EdgeEstimate
from ctcvo.teacher.timing import cov_to_depth_moments, to_colour_moments, to_depth_moments

H, W = 240, 320  # at 160 x 120 the dense maps (every 2nd / 4th pixel) alias the texture: ~3 mm
K = np.array([[300.0, 0.0, 160.0], [0.0, 300.0, 120.0], [0.0, 0.0, 1.0]])


def test_depth_at_is_bilinear_on_a_ramp_and_exact_on_a_plane() -> None:
    """A ramp z = 1 + 0.002 u is linear, so bilinear interpolation is exact at sub-pixels."""
    u = np.arange(W, dtype=np.float32)
    ramp = np.tile(1.0 + 0.002 * u, (H, 1)).astype(np.float32)
    uv = np.array([[10.25, 20.5], [80.0, 60.0], [150.75, 100.1]], np.float32)
    np.testing.assert_allclose(depth_at(ramp, uv), 1.0 + 0.002 * uv[:, 0].astype(np.float64), rtol=1e-6)
    plane = np.full((H, W), 2.0, np.float32)
    np.testing.assert_array_equal(depth_at(plane, uv), [2.0, 2.0, 2.0])
    assert depth_at(plane, np.zeros((0, 2), np.float32)).shape == (0,)


def test_depth_at_refuses_borders_holes_edges_and_out_of_range_depth() -> None:
    depth = np.full((H, W), 2.0, np.float32)
    depth[:, 100:] = 2.0 + 10 * DEPTH_EDGE_ABS  # a depth discontinuity at u = 100
    depth[50, 40] = 0.0  # a hole
    depth[90:, :30] = DEPTH_MAX + 1.0  # beyond the usable range
    uv = np.array([
        [1.0, 60.0],      # 1 px from the border: its 5x5 window leaves the image
        [41.0, 51.0],     # a hole 1 px away, inside the 5x5 window
        [99.0, 60.0],     # the discontinuity inside the window
        [10.0, 100.0],    # too far
        [60.0, 30.0],     # fine
        [110.0, 30.0],    # fine, on the far side of the step
    ], np.float32)
    np.testing.assert_array_equal(depth_at(depth, uv), np.array([0, 0, 0, 0, 2.0, 2.0 + 10 * DEPTH_EDGE_ABS],
                                                                np.float32))
    near = np.full((H, W), DEPTH_MIN / 2, np.float32)
    assert depth_at(near, np.array([[60.0, 60.0]], np.float32))[0] == 0.0


def _room_depth(T_world_cam: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Depth and grey of a camera at ``T_world_cam`` in a box room [-1, 1] x [-0.8, 0.8] x
    [-1, 3] (ray casting), its walls textured in world coordinates."""
    v, u = np.mgrid[0:H, 0:W].astype(np.float64)
    rays_c = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], -1)
    R, o = T_world_cam[:3, :3], T_world_cam[:3, 3]
    d = rays_c @ R.T
    lo, hi = np.array([-1.0, -0.8, -1.0]), np.array([1.0, 0.8, 3.0])
    with np.errstate(divide="ignore", invalid="ignore"):
        t = np.where(d > 0, (hi - o) / d, (lo - o) / d)
    s = np.min(np.where(np.isfinite(t) & (t > 0), t, np.inf), axis=-1)
    X = o + s[..., None] * d
    grey = 127 + 60 * np.sin(7 * X[..., 0]) * np.cos(5 * X[..., 1]) + 40 * np.sin(6 * X[..., 2])
    return (s * 1.0).astype(np.float32), np.clip(grey, 0, 255).astype(np.uint8)  # z = s for rays with z = 1


def test_pyramid_align_recovers_a_known_motion_from_identity() -> None:
    """Two ray-cast views (noise-free) of a textured box room, 2.7 cm and 2 degrees apart: from
    the identity, the coarse-to-fine hybrid alignment lands on the true T_i_j (measured: 0.6 mm,
    0.012 deg; 0.3 mm at 640 x 480)."""
    T_w_i = np.eye(4)
    T_i_j = geo.se3_exp(np.array([0.02, -0.01, 0.015, 0.01, 0.03, -0.015]))
    (zi, gi), (zj, gj) = _room_depth(T_w_i), _room_depth(T_w_i @ T_i_j)
    di, dj = dense_maps(zi, K, gi), dense_maps(zj, K, gj)
    T, fitness = pyramid_align(np.eye(4), di, dj)
    err = geo.se3_log(geo.inv_T(T_i_j) @ T)
    assert fitness > 0.5
    assert np.linalg.norm(err[:3]) < 1.5e-3 and np.degrees(np.linalg.norm(err[3:])) < 0.03, err


def _frames(o_i: float, o_j: float) -> tuple[FrameFeatures, FrameFeatures]:
    def one(offset: float) -> FrameFeatures:
        return FrameFeatures(np.zeros((0, 2), np.float32), np.zeros((0, 32), np.uint8), np.zeros(0, np.float32),
                             np.zeros((H, W), np.uint8), np.zeros((H, W), np.float32), depth_offset=offset)
    return one(o_i), one(o_j)


def test_pure_translation_moves_between_moments_at_constant_velocity() -> None:
    """Colour moments dt apart, depth offsets o_i, o_j: a pure translation t_d between the
    depth moments spans dt + o_j - o_i seconds, so between the colour moments it is
    t_d dt / (dt + o_j - o_i), and a translation-only covariance scales by that ratio squared."""
    dt, o_i, o_j = 1 / 30, 0.004, 0.012
    fi, fj = _frames(o_i, o_j)
    t_d = np.array([0.03, -0.01, 0.02])
    T_d = np.eye(4)
    T_d[:3, 3] = t_d
    cov = np.diag([4e-6, 1e-6, 9e-6, 0.0, 0.0, 0.0])
    res = to_colour_moments(EdgeEstimate(0, 1, "ok", T_d.copy(), cov.copy()), fi, fj, dt)
    ratio = dt / (dt + o_j - o_i)
    np.testing.assert_allclose(res.T_i_j[:3, 3], t_d * ratio, atol=1e-12)
    np.testing.assert_allclose(res.T_i_j[:3, :3], np.eye(3), atol=1e-12)
    np.testing.assert_allclose(res.cov, cov * ratio**2, atol=1e-18)
    # and back: the pose and its covariance at the depth moments again
    np.testing.assert_allclose(to_depth_moments(res.T_i_j, fi, fj, dt), T_d, atol=1e-12)
    np.testing.assert_allclose(cov_to_depth_moments(res.cov, res.T_i_j, fi, fj, dt), cov, atol=1e-18)


def test_general_motion_round_trips_and_no_offset_is_the_identity() -> None:
    dt = 1 / 30
    T_d = geo.se3_exp(np.array([0.02, 0.01, -0.03, 0.05, -0.02, 0.03]))
    A = np.random.default_rng(3).normal(size=(6, 6)) * 1e-3
    cov = A @ A.T
    fi, fj = _frames(0.0, 0.0)
    same = to_colour_moments(EdgeEstimate(0, 1, "ok", T_d.copy(), cov.copy()), fi, fj, dt)
    np.testing.assert_array_equal(same.T_i_j, T_d)
    np.testing.assert_array_equal(same.cov, cov)
    fi, fj = _frames(0.003, 0.010)
    moved = to_colour_moments(EdgeEstimate(0, 1, "ok", T_d.copy(), cov.copy()), fi, fj, dt)
    assert not np.allclose(moved.T_i_j, T_d)
    np.testing.assert_allclose(to_depth_moments(moved.T_i_j, fi, fj, dt), T_d, atol=1e-9)
    back = cov_to_depth_moments(moved.cov, moved.T_i_j, fi, fj, dt)
    np.testing.assert_allclose(back, cov, rtol=1e-6, atol=1e-14)


@pytest.mark.parametrize("dt", [0.0, -1 / 30])
def test_no_time_apart_leaves_the_estimate_alone(dt: float) -> None:
    fi, fj = _frames(0.003, 0.010)
    T = geo.se3_exp(np.array([0.01, 0, 0, 0, 0, 0.01]))
    res = to_colour_moments(EdgeEstimate(0, 1, "ok", T.copy(), np.eye(6)), fi, fj, dt)
    np.testing.assert_array_equal(res.T_i_j, T)


def test_guided_matching_drops_only_pairs_that_change_nothing(monkeypatch):
    """Dropping candidate pairs 76+ bits apart before the sorts (matching._IRRELEVANT_HAMMING)
    gives the matches of the full candidate set: random descriptors, each keypoint of i with a
    copy in j 0-89 bits off and, for half of them, a decoy 55-89 bits off beside it (seconds
    best where the ratio test decides), so a lower bound would change matches."""
    from ctcvo.teacher import matching
    from ctcvo.teacher.features import FrameFeatures

    rng = np.random.default_rng(3)
    n = 400
    K = np.array([[500.0, 0, 320], [0, 500.0, 240], [0, 0, 1]])

    def off(d, bits):
        b = np.unpackbits(d)
        b[rng.choice(256, bits, replace=False)] ^= 1
        return np.packbits(b)

    uv = rng.uniform([0, 0], [640, 480], (n, 2)).astype(np.float32)
    desc_i = rng.integers(0, 256, (n, 32), dtype=np.uint8)
    copies = np.stack([off(d, int(b)) for d, b in zip(desc_i, rng.integers(0, 90, n))])
    decoys = np.stack([off(d, int(b)) for d, b in zip(desc_i[: n // 2], rng.integers(55, 90, n // 2))])
    uv_j = np.concatenate([uv + rng.normal(0, 2, (n, 2)), uv[: n // 2] + rng.normal(0, 2, (n // 2, 2))]).astype(np.float32)
    desc_j = np.concatenate([copies, decoys])
    blank = np.zeros((480, 640), np.uint8), np.zeros((480, 640), np.float32)
    fi = FrameFeatures(uv, desc_i, np.full(n, 2.0, np.float32), *blank)
    fj = FrameFeatures(uv_j, desc_j, np.full(len(uv_j), 2.0, np.float32), *blank)

    def run(limit):
        monkeypatch.setattr(matching, "_IRRELEVANT_HAMMING", limit)
        fi._tree = fj._tree = None
        return matching.match(fi, fj, np.eye(4), K)

    bound = matching._IRRELEVANT_HAMMING
    full = run(10**9)
    assert 50 < len(full) < n
    assert np.array_equal(run(bound), full)
    assert not np.array_equal(run(66), full)  # the bound is not arbitrary: a lower one changes matches
