"""data/geometry.py on the manifold, with known answers and against GTSAM, scipy and evo.

Every convention claim in docs/conventions.md that concerns a library is checked here by
running that library, not from memory.
"""

from __future__ import annotations

import gtsam
import numpy as np
import pytest
import scipy.linalg
from scipy.spatial.transform import Rotation

from ctcvo.data import geometry as geo

RNG_SEED = 7


def _twist_matrix(xi: np.ndarray) -> np.ndarray:
    """4x4 element of se(3) for project order xi = (v, w): [[hat(w), v], [0, 0]]."""
    X = np.zeros((4, 4))
    X[:3, :3] = geo.hat(xi[3:])
    X[:3, 3] = xi[:3]
    return X


def _random_xi(rng: np.random.Generator, angle: float) -> np.ndarray:
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    return np.concatenate([rng.normal(scale=0.5, size=3), angle * axis])


def _random_T(rng: np.random.Generator) -> np.ndarray:
    return geo.make_T(Rotation.random(random_state=rng.integers(1 << 30)).as_matrix(), rng.normal(size=3))


ANGLES = [0.0, 1e-9, 1e-6, 1e-4 * 0.999, 1e-4 * 1.001, 1e-3, 0.1, 1.0, 2.0, 3.0,
          np.pi - 1e-3, np.pi - 1e-6]


# ----------------------------------------------------------------------------------
# exp / log
# ----------------------------------------------------------------------------------
@pytest.mark.parametrize("angle", ANGLES)
def test_exp_matches_matrix_exponential(angle: float) -> None:
    rng = np.random.default_rng(RNG_SEED)
    for _ in range(5):
        xi = _random_xi(rng, angle)
        T = geo.se3_exp(xi)
        np.testing.assert_allclose(T, scipy.linalg.expm(_twist_matrix(xi)), atol=1e-12)
        assert geo.is_rigid(T, atol=1e-12)


@pytest.mark.parametrize("angle", ANGLES)
def test_log_exp_round_trip(angle: float) -> None:
    rng = np.random.default_rng(RNG_SEED)
    for _ in range(5):
        xi = _random_xi(rng, angle)
        back = geo.se3_log(geo.se3_exp(xi))
        assert np.all(np.isfinite(back))
        np.testing.assert_allclose(back, xi, atol=1e-12)
        np.testing.assert_allclose(geo.se3_exp(back), geo.se3_exp(xi), atol=1e-12)


@pytest.mark.parametrize("angle", [np.pi - 1e-9, np.pi])
def test_log_at_pi(angle: float) -> None:
    """At pi, w and -w are the same rotation: log must return one of them, exp must agree."""
    rng = np.random.default_rng(RNG_SEED)
    for _ in range(5):
        xi = _random_xi(rng, angle)
        T = geo.se3_exp(xi)
        back = geo.se3_log(T)
        assert np.linalg.norm(back[3:]) == pytest.approx(angle, abs=1e-8)
        np.testing.assert_allclose(geo.se3_exp(back), T, atol=1e-9)


def test_log_of_raw_translation_is_not_t() -> None:
    """v = V^-1 t, not the raw translation (the defect of the paper's released code)."""
    T = geo.make_T(Rotation.from_rotvec([0, 0, 1.0]).as_matrix(), [1.0, 0.0, 0.0])
    xi = geo.se3_log(T)
    assert np.linalg.norm(xi[:3] - T[:3, 3]) > 0.1
    # known answer for a rotation about z: V^-1 t in the xy plane, from expm of the twist
    np.testing.assert_allclose(scipy.linalg.expm(_twist_matrix(xi)), T, atol=1e-12)


def test_log_of_equal_poses_is_zero() -> None:
    rng = np.random.default_rng(RNG_SEED)
    for _ in range(20):
        a = _random_T(rng)
        d = geo.se3_log(geo.inv_T(a) @ a)
        assert np.all(np.isfinite(d))
        assert np.abs(d).max() < 1e-14
        assert np.abs(geo.se3_log(geo.relative_pose(a, a.copy()))).max() < 1e-14
    np.testing.assert_array_equal(geo.se3_log(np.eye(4)), np.zeros(6))
    np.testing.assert_array_equal(geo.se3_exp(np.zeros(6)), np.eye(4))


def test_one_transforms_log_is_the_batchs_and_non_finite_input_gives_nan() -> None:
    """se3_log of one transform (written in scalars) agrees with the batch code on each of a
    batch, 150 degrees and beyond included; a non-finite twist or transform gives NaN, not an
    error."""
    rng = np.random.default_rng(RNG_SEED)
    Ts = np.stack([geo.se3_exp(_random_xi(rng, a)) for a in (0.0, 1e-6, 1e-3, 0.5, 2.0, 2.7, 3.1) for _ in range(3)])
    batch = geo.se3_log(Ts)
    for T, want in zip(Ts, batch):
        np.testing.assert_allclose(geo.se3_log(T), want, rtol=0, atol=1e-13)
    for bad in (np.inf, np.nan):
        assert np.isnan(geo.se3_exp([0, 0, 0, bad, 0, 0])[:3]).all()
        T = np.eye(4)
        T[0, 3] = T[1, 1] = bad
        assert np.isnan(geo.se3_log(T)).any()


def test_small_angle_series_continuity() -> None:
    """The series branch (< 1e-4 rad) and the closed form agree across the switch."""
    rng = np.random.default_rng(RNG_SEED)
    xi = _random_xi(rng, 1.0)
    u = xi[3:] / np.linalg.norm(xi[3:])
    lo = np.concatenate([xi[:3], u * (1e-4 * (1 - 1e-9))])
    hi = np.concatenate([xi[:3], u * (1e-4 * (1 + 1e-9))])
    np.testing.assert_allclose(geo.se3_exp(lo), geo.se3_exp(hi), atol=1e-12)
    np.testing.assert_allclose(geo.se3_log(geo.se3_exp(lo)), geo.se3_log(geo.se3_exp(hi)), atol=1e-12)


def test_log_of_a_batch_equals_each_log() -> None:
    """se3_log of (..., 4, 4) is the log of each transform (both rotation branches and the
    series mixed in one batch), and inverts exp: log(exp(xi)) = xi."""
    rng = np.random.default_rng(RNG_SEED)
    xis = np.array([_random_xi(rng, a) for a in ANGLES] + [np.zeros(6)])
    Ts = np.array([geo.se3_exp(x) for x in xis])
    batch = geo.se3_log(Ts)
    for x, T, got in zip(xis, Ts, batch):
        np.testing.assert_allclose(got, geo.se3_log(T), rtol=0, atol=1e-15)
        np.testing.assert_allclose(got, x, atol=1e-9)
    assert geo.se3_log(Ts[:12].reshape(3, 4, 4, 4)).shape == (3, 4, 6)
    assert geo.se3_log(np.zeros((0, 4, 4))).shape == (0, 6)


# ----------------------------------------------------------------------------------
# GTSAM agreement (tangent order (w, v), right perturbation)
# ----------------------------------------------------------------------------------
@pytest.mark.parametrize("angle", [0.0, 1e-9, 1e-6, 1e-3, 0.5, 2.0, np.pi - 1e-3])
def test_exp_log_match_gtsam(angle: float) -> None:
    rng = np.random.default_rng(RNG_SEED)
    for _ in range(5):
        xi = _random_xi(rng, angle)
        P = gtsam.Pose3.Expmap(geo.vec_to_gtsam(xi))
        np.testing.assert_allclose(geo.se3_exp(xi), P.matrix(), atol=1e-12)
        ours = geo.se3_log(P.matrix())
        theirs = geo.vec_from_gtsam(gtsam.Pose3.Logmap(P))
        # GTSAM's Logmap switches to a less accurate branch within ~1e-3 of pi (measured:
        # 1.8e-8 off at pi - 1e-3); ours stays exact there (checked against expm above)
        np.testing.assert_allclose(ours, theirs, atol=1e-7 if angle > 3.0 else 1e-12)
        np.testing.assert_allclose(ours, xi, atol=1e-12)


def test_vec_order_against_gtsam_semantics() -> None:
    """A pure-translation tangent (v only) moves GTSAM's Pose3 translation; w only rotates."""
    P = gtsam.Pose3.Expmap(geo.vec_to_gtsam([0.1, 0.2, 0.3, 0, 0, 0]))
    np.testing.assert_allclose(P.translation(), [0.1, 0.2, 0.3], atol=1e-15)
    np.testing.assert_allclose(P.rotation().matrix(), np.eye(3), atol=1e-15)
    P = gtsam.Pose3.Expmap(geo.vec_to_gtsam([0, 0, 0, 0.1, 0.2, 0.3]))
    np.testing.assert_allclose(P.translation(), 0, atol=1e-15)
    np.testing.assert_allclose(gtsam.Rot3.Logmap(P.rotation()), [0.1, 0.2, 0.3], atol=1e-15)
    np.testing.assert_allclose(geo.vec_from_gtsam(geo.vec_to_gtsam(np.arange(6.0))), np.arange(6.0))
    np.testing.assert_array_equal(geo.vec_to_gtsam(np.arange(6.0)), [3, 4, 5, 0, 1, 2])


def test_right_perturbation_matches_gtsam_between_factor() -> None:
    """BetweenFactorPose3's error is Logmap(measured^-1 * T_i_j): right perturbation at the
    measurement, the convention of Edge.cov. Checked on the factor itself."""
    rng = np.random.default_rng(RNG_SEED)
    T_wi, T_wj = _random_T(rng), _random_T(rng)
    T_ij = geo.relative_pose(T_wi, T_wj)
    delta = np.array([0.01, -0.02, 0.03, 0.02, -0.01, 0.015])
    measured = T_ij @ geo.se3_exp(-delta)  # so that T_ij = measured @ exp(delta)
    f = gtsam.BetweenFactorPose3(0, 1, gtsam.Pose3(measured), gtsam.noiseModel.Unit.Create(6))
    values = gtsam.Values()
    values.insert(0, gtsam.Pose3(T_wi))
    values.insert(1, gtsam.Pose3(T_wj))
    err = f.unwhitenedError(values)
    np.testing.assert_allclose(geo.vec_from_gtsam(err), delta, atol=1e-9)
    # and Pose3.expmap composes on the right
    xi = _random_xi(rng, 0.4)
    np.testing.assert_allclose(gtsam.Pose3(T_wi).expmap(geo.vec_to_gtsam(xi)).matrix(),
                               T_wi @ geo.se3_exp(xi), atol=1e-12)


def test_to_from_gtsam_pose3() -> None:
    rng = np.random.default_rng(RNG_SEED)
    T = _random_T(rng)
    np.testing.assert_allclose(geo.from_gtsam_pose3(geo.to_gtsam_pose3(T)), T, atol=1e-14)
    noisy = T.copy()
    noisy[:3, :3] += 1e-7  # a slightly non-orthonormal rotation is projected, not rejected
    assert geo.is_rigid(geo.from_gtsam_pose3(geo.to_gtsam_pose3(noisy)), atol=1e-12)


# ----------------------------------------------------------------------------------
# quaternions
# ----------------------------------------------------------------------------------
def test_quaternion_file_order_known_answer() -> None:
    # 90 degrees about z: (qx, qy, qz, qw) = (0, 0, sin 45, cos 45)
    s = np.sqrt(0.5)
    R = geo.quat_xyzw_to_R([0, 0, s, s])
    np.testing.assert_allclose(R, [[0, -1, 0], [1, 0, 0], [0, 0, 1]], atol=1e-15)
    np.testing.assert_allclose(geo.R_to_quat_xyzw(R), [0, 0, s, s], atol=1e-15)
    # scipy's default order is the file order
    np.testing.assert_allclose(Rotation.from_quat([0, 0, s, s]).as_matrix(), R, atol=1e-15)


def test_q_and_minus_q_same_rotation() -> None:
    rng = np.random.default_rng(RNG_SEED)
    for _ in range(20):
        q = rng.normal(size=4)
        np.testing.assert_allclose(geo.quat_xyzw_to_R(q), geo.quat_xyzw_to_R(-q), atol=1e-15)
        row = np.concatenate([rng.normal(size=3), q])
        row_neg = np.concatenate([row[:3], -q])
        np.testing.assert_allclose(geo.tum_to_T(row), geo.tum_to_T(row_neg), atol=1e-15)
        assert geo.T_to_tum(geo.tum_to_T(row_neg))[6] >= 0  # written with qw >= 0
        np.testing.assert_allclose(geo.tum_to_T(geo.T_to_tum(geo.tum_to_T(row))), geo.tum_to_T(row), atol=1e-14)


def test_quaternion_rejects_zero_and_nan() -> None:
    for q in ([0, 0, 0, 0], [np.nan, 0, 0, 1], [np.inf, 0, 0, 1]):
        with pytest.raises(ValueError, match="invalid quaternion"):
            geo.quat_xyzw_to_R(q)


def test_quaternion_order_against_gtsam() -> None:
    rng = np.random.default_rng(RNG_SEED)
    for _ in range(20):
        q_xyzw = Rotation.random(random_state=rng.integers(1 << 30)).as_quat()
        w, x, y, z = geo.quat_xyzw_to_wxyz(q_xyzw)
        R_gtsam = gtsam.Rot3.Quaternion(w, x, y, z).matrix()
        np.testing.assert_allclose(R_gtsam, geo.quat_xyzw_to_R(q_xyzw), atol=1e-14)
        # the wrong order is a silently different rotation (the check can fail)
        assert np.abs(gtsam.Rot3.Quaternion(*q_xyzw).matrix() - R_gtsam).max() > 1e-3
        q_back = gtsam.Rot3(R_gtsam).toQuaternion()
        wxyz = np.array([q_back.w(), q_back.x(), q_back.y(), q_back.z()])
        sign = np.sign(wxyz @ geo.quat_xyzw_to_wxyz(q_xyzw))
        np.testing.assert_allclose(sign * wxyz, geo.quat_xyzw_to_wxyz(q_xyzw), atol=1e-14)
        np.testing.assert_allclose(geo.quat_wxyz_to_xyzw(geo.quat_xyzw_to_wxyz(q_xyzw)), q_xyzw)


# ----------------------------------------------------------------------------------
# covariances
# ----------------------------------------------------------------------------------
def _random_cov(rng: np.random.Generator) -> np.ndarray:
    A = rng.normal(size=(6, 6))
    return A @ A.T + 0.1 * np.eye(6)


def test_cov_permutation_round_trip_and_consistency() -> None:
    rng = np.random.default_rng(RNG_SEED)
    C = _random_cov(rng)
    np.testing.assert_array_equal(geo.cov_from_gtsam(geo.cov_to_gtsam(C)), C)
    np.testing.assert_array_equal(geo.cov_to_gtsam(geo.cov_from_gtsam(C)), C)
    # P x = vec_to_gtsam(x)  =>  cov_to_gtsam(C) = P C P^T
    P = np.stack([geo.vec_to_gtsam(e) for e in np.eye(6)], axis=1)
    x = rng.normal(size=6)
    np.testing.assert_array_equal(P @ x, geo.vec_to_gtsam(x))
    np.testing.assert_allclose(geo.cov_to_gtsam(C), P @ C @ P.T, atol=0)
    # the information matrix permutes the same way
    np.testing.assert_allclose(geo.cov_to_gtsam(np.linalg.inv(C)), np.linalg.inv(geo.cov_to_gtsam(C)), rtol=1e-10,
                               atol=1e-12)
    # translation block (project rows 0..2) lands in GTSAM rows 3..5
    np.testing.assert_array_equal(geo.cov_to_gtsam(C)[3:, 3:], C[:3, :3])
    np.testing.assert_array_equal(geo.cov_to_gtsam(C)[:3, 3:], C[3:, :3])


def test_cov_mahalanobis_matches_gtsam_noise_model() -> None:
    """x^T C^-1 x (project order) equals GTSAM's whitened squared norm of the re-ordered x."""
    rng = np.random.default_rng(RNG_SEED)
    C = _random_cov(rng)
    model = gtsam.noiseModel.Gaussian.Covariance(geo.cov_to_gtsam(C))
    np.testing.assert_allclose(model.covariance(), geo.cov_to_gtsam(C), rtol=1e-10)
    for _ in range(10):
        x = rng.normal(size=6)
        want = x @ np.linalg.solve(C, x)
        got = float(np.sum(model.whiten(geo.vec_to_gtsam(x)) ** 2))
        assert got == pytest.approx(want, rel=1e-9)
        # a covariance left in project order would give a different answer
        wrong = gtsam.noiseModel.Gaussian.Covariance(C)
        assert float(np.sum(wrong.whiten(geo.vec_to_gtsam(x)) ** 2)) != pytest.approx(want, rel=1e-3)


# ----------------------------------------------------------------------------------
# relative poses, helpers, evo
# ----------------------------------------------------------------------------------
def test_relative_pose_and_composition() -> None:
    rng = np.random.default_rng(RNG_SEED)
    T_w_a, T_a_b, T_b_c = _random_T(rng), _random_T(rng), _random_T(rng)
    T_w_b = T_w_a @ T_a_b
    T_w_c = T_w_b @ T_b_c
    np.testing.assert_allclose(geo.relative_pose(T_w_a, T_w_a), np.eye(4), atol=1e-14)
    np.testing.assert_allclose(geo.relative_pose(T_w_a, T_w_b), T_a_b, atol=1e-12)
    np.testing.assert_allclose(geo.relative_pose(T_w_a, T_w_c), T_a_b @ T_b_c, atol=1e-12)
    np.testing.assert_allclose(geo.relative_pose(np.eye(4), T_w_a), T_w_a, atol=1e-14)
    np.testing.assert_allclose(geo.relative_pose(T_w_b, T_w_a), geo.inv_T(T_a_b), atol=1e-12)
    # T_i_j maps points from frame j into frame i
    p_b = rng.normal(size=3)
    p_w = (T_w_b @ np.append(p_b, 1))[:3]
    np.testing.assert_allclose((geo.inv_T(T_w_a) @ np.append(p_w, 1))[:3], (T_a_b @ np.append(p_b, 1))[:3], atol=1e-12)
    np.testing.assert_allclose(geo.inv_T(T_w_a), np.linalg.inv(T_w_a), atol=1e-12)


def test_rigid_checks_and_orthonormalize() -> None:
    rng = np.random.default_rng(RNG_SEED)
    T = _random_T(rng)
    assert geo.is_rigid(T)
    bad = T.copy()
    bad[:3, :3] *= -1  # det -1: a reflection
    assert not geo.is_rigid(bad)
    nan = T.copy()
    nan[0, 3] = np.nan
    assert not geo.is_rigid(nan)
    assert not geo.is_rigid(np.eye(3))
    noisy = T + 1e-4 * rng.normal(size=(4, 4)) * np.array([1, 1, 1, 0])[:, None]
    fixed = geo.orthonormalize(noisy)
    assert geo.is_rigid(fixed, atol=1e-12)
    np.testing.assert_allclose(fixed[:3, 3], noisy[:3, 3])
    assert geo.rotation_angle_deg(geo.se3_exp([0, 0, 0, 0, 0, np.radians(30)])) == pytest.approx(30, abs=1e-9)
    assert geo.rotation_angle_deg(geo.se3_exp([0, 0, 0, np.pi, 0, 0])) == pytest.approx(180, abs=1e-9)


def test_orthonormalize_is_the_closest_rotation() -> None:
    """orthonormalize of one transform or a batch is the polar factor of the rotation block
    (scipy.linalg.polar) on both of its paths (Newton-Schulz near SO(3), SVD further
    away); a reflection becomes a rotation; exact rotations are returned unchanged."""
    rng = np.random.default_rng(8)
    Ts = np.array([_random_T(rng) for _ in range(40)])
    noisy = Ts + rng.normal(size=Ts.shape) * np.repeat([1e-6, 1e-2], 20)[:, None, None]
    noisy[:, 3] = [0, 0, 0, 1]
    fixed = geo.orthonormalize(noisy)
    for n, T in zip(noisy, fixed):
        np.testing.assert_allclose(T[:3, :3], scipy.linalg.polar(n[:3, :3])[0], atol=1e-12)
        np.testing.assert_array_equal(T[:3, 3], n[:3, 3])
        np.testing.assert_allclose(geo.orthonormalize(n), T, rtol=0, atol=1e-15)
    assert np.array_equal(geo.orthonormalize(Ts), Ts)
    mirror = Ts[0].copy()
    mirror[:3, 0] *= -1  # det -1
    assert geo.is_rigid(geo.orthonormalize(mirror), atol=1e-12)
    assert geo.orthonormalize(np.zeros((0, 4, 4))).shape == (0, 4, 4)


def test_evo_array_round_trip() -> None:
    from evo.core.trajectory import PoseTrajectory3D

    rng = np.random.default_rng(RNG_SEED)
    Ts = np.stack([_random_T(rng) for _ in range(10)])
    xyz, q_wxyz = geo.evo_pose_arrays(Ts)
    np.testing.assert_allclose(geo.poses_from_evo_arrays(xyz, q_wxyz), Ts, atol=1e-14)
    # evo's own conversion from matrices stores w x y z
    traj = PoseTrajectory3D(poses_se3=list(Ts), timestamps=np.arange(10.0))
    sign = np.sign(np.sum(traj.orientations_quat_wxyz * q_wxyz, axis=1))[:, None]
    np.testing.assert_allclose(sign * traj.orientations_quat_wxyz, q_wxyz, atol=1e-12)
    np.testing.assert_allclose(traj.positions_xyz, xyz)
    np.testing.assert_allclose(np.stack(traj.poses_se3), Ts, atol=1e-12)


def test_evo_reads_tum_quaternion_as_xyzw(tmp_path) -> None:
    """A TUM row 'qx qy qz qw' ends up as evo's (w, x, y, z)."""
    from evo.tools.file_interface import read_tum_trajectory_file

    q = Rotation.from_rotvec([0.2, -0.4, 0.7]).as_quat()  # x y z w
    f = tmp_path / "t.tum"
    f.write_text("0.0 1 2 3 " + " ".join(f"{x:.12f}" for x in q) + "\n1.0 1 2 3 0 0 0 1\n")
    traj = read_tum_trajectory_file(str(f))
    np.testing.assert_allclose(traj.orientations_quat_wxyz[0], geo.quat_xyzw_to_wxyz(q), atol=1e-12)
    np.testing.assert_allclose(traj.poses_se3[0][:3, :3], geo.quat_xyzw_to_R(q), atol=1e-12)


# ----------------------------------------------------------------------------------
# conventions of the vision libraries (docs/conventions.md states these; checked here)
# ----------------------------------------------------------------------------------
def test_opencv_solvepnp_returns_T_cam_obj() -> None:
    import cv2

    rng = np.random.default_rng(RNG_SEED)
    K = np.array([[500.0, 0, 320], [0, 500, 240], [0, 0, 1]])
    T_cam_obj = geo.make_T(Rotation.from_rotvec([0.1, -0.2, 0.05]).as_matrix(), [0.1, -0.05, 2.0])
    X_obj = rng.uniform(-1, 1, size=(30, 3))
    X_cam = X_obj @ T_cam_obj[:3, :3].T + T_cam_obj[:3, 3]
    uv = X_cam @ K.T
    uv = uv[:, :2] / uv[:, 2:]  # u = fx x / z + cx (column), v = fy y / z + cy (row)
    ok, rvec, tvec = cv2.solvePnP(X_obj, uv, K, None, flags=cv2.SOLVEPNP_SQPNP)
    assert ok
    R, _ = cv2.Rodrigues(rvec)
    np.testing.assert_allclose(geo.make_T(R, tvec.ravel()), T_cam_obj, atol=1e-9)
    np.testing.assert_allclose(R, Rotation.from_rotvec(rvec.ravel()).as_matrix(), atol=1e-15)  # rvec = rotvec


def _rendered_rgbd_pair(T_s_t: np.ndarray, W: int = 160, H: int = 120):
    """A textured bumpy surface seen from a source camera and from a target camera at
    ``T_s_t`` (target pose in the source frame); z-buffered point splatting. Returns
    (K, gray_s, depth_s, gray_t, depth_t) with depth in metres (0 = no data)."""
    K = np.array([[125.0, 0, W / 2], [0, 125.0, H / 2], [0, 0, 1]])
    yy, xx = np.mgrid[0:H, 0:W].astype(np.float64)
    # supersample the source surface so the target image has no holes
    ys, xs = np.mgrid[0:H:0.25, 0:W:0.25]
    z = 1.5 + 0.2 * np.sin(xs / 12.0) * np.cos(ys / 15.0)
    tex = 128 + 60 * np.sin(xs / 3.5) + 60 * np.cos(ys / 2.5) * np.sin(xs / 6.5)
    P_s = np.stack([(xs - K[0, 2]) / K[0, 0] * z, (ys - K[1, 2]) / K[1, 1] * z, z], -1).reshape(-1, 3)

    def render(P):
        u = np.round(K[0, 0] * P[:, 0] / P[:, 2] + K[0, 2]).astype(int)
        v = np.round(K[1, 1] * P[:, 1] / P[:, 2] + K[1, 2]).astype(int)
        ok = (u >= 0) & (u < W) & (v >= 0) & (v < H)
        order = np.argsort(-P[ok, 2])  # far first, near ones overwrite
        depth, gray = np.zeros((H, W)), np.zeros((H, W))
        depth[v[ok][order], u[ok][order]] = P[ok, 2][order]
        gray[v[ok][order], u[ok][order]] = tex.reshape(-1)[ok][order]
        return gray.clip(0, 255).astype(np.uint8), depth.astype(np.float32)

    T_t_s = geo.inv_T(T_s_t)
    gray_s, depth_s = render(P_s)
    gray_t, depth_t = render(P_s @ T_t_s[:3, :3].T + T_t_s[:3, 3])
    return K, gray_s, depth_s, gray_t, depth_t


_T_S_T = geo.make_T(Rotation.from_rotvec([0.0, 0.02, 0.01]).as_matrix(), [0.03, -0.01, 0.02])


def test_open3d_rgbd_odometry_returns_T_target_source() -> None:
    o3d = pytest.importorskip("open3d")
    K, gs, ds, gt, dt = _rendered_rgbd_pair(_T_S_T)
    H, W = gs.shape
    intr = o3d.camera.PinholeCameraIntrinsic(W, H, K[0, 0], K[1, 1], K[0, 2], K[1, 2])

    def rgbd(g, d):
        return o3d.geometry.RGBDImage.create_from_color_and_depth(
            o3d.geometry.Image(np.ascontiguousarray(np.repeat(g[..., None], 3, -1))), o3d.geometry.Image(d),
            depth_scale=1.0, depth_trunc=10.0, convert_rgb_to_intensity=True)

    ok, T, _ = o3d.pipelines.odometry.compute_rgbd_odometry(
        rgbd(gs, ds), rgbd(gt, dt), intr, np.eye(4), o3d.pipelines.odometry.RGBDOdometryJacobianFromHybridTerm(),
        o3d.pipelines.odometry.OdometryOption())
    assert ok
    T_t_s = geo.inv_T(_T_S_T)
    assert np.abs(T - T_t_s).max() < 0.005  # maps source points into the target frame
    assert np.abs(T - _T_S_T).max() > 0.03  # and is not the other direction


def test_opencv_odometry_returns_T_dst_src() -> None:
    import cv2

    if not hasattr(cv2, "OdometrySettings"):
        pytest.skip("cv2.Odometry (OpenCV 5 ptcloud module) not available")
    K, gs, ds, gt, dt = _rendered_rgbd_pair(_T_S_T)
    settings = cv2.OdometrySettings()
    settings.setCameraMatrix(K.astype(np.float32))
    odo = cv2.Odometry(cv2.OdometryType_RGB_DEPTH, settings, cv2.OdometryAlgoType_COMMON)
    ok, Rt = odo.compute(ds, gs, dt, gt)
    assert ok
    assert np.abs(Rt - geo.inv_T(_T_S_T)).max() < 0.005
    assert np.abs(Rt - _T_S_T).max() > 0.03


# ----------------------------------------------------------------------------------
# data.metrics: trivial baselines
# ----------------------------------------------------------------------------------
def test_metrics_baselines_known_answers_on_a_screw_motion() -> None:
    """Constant screw motion ``gt_k = T0 S^k``: zero motion stays at ``T0`` (every gap-1
    pair misses one ``S``), constant velocity is ``gt`` one frame late (only the first pair
    misses ``S``)."""
    from ctcvo.data.formats import Trajectory
    from ctcvo.data.metrics import (
        BASELINE_KEYS,
        BASELINES,
        baseline_reports,
        baseline_trajectories,
        constant_velocity_poses,
        zero_motion_poses,
    )

    rng = np.random.default_rng(RNG_SEED)
    n, xi = 12, np.array([0.05, -0.02, 0.1, 0.01, 0.03, -0.02])
    S, T0 = geo.se3_exp(xi), _random_T(rng)
    gt = np.array([T0 @ np.linalg.matrix_power(S, k) for k in range(n)])
    np.testing.assert_allclose(zero_motion_poses(gt), np.repeat(T0[None], n, axis=0))
    cv = constant_velocity_poses(gt)
    np.testing.assert_allclose(cv[0], T0)
    np.testing.assert_allclose(cv[1:], gt[:-1], atol=1e-12)
    times = 3.0 + 0.1 * np.arange(n)
    trajs = baseline_trajectories(Trajectory(times, gt))
    assert tuple(trajs) == BASELINES and BASELINE_KEYS == {"zero motion": "zero_motion",
                                                           "constant velocity": "constant_velocity"}
    assert all(np.array_equal(t.timestamps, times) for t in trajs.values())
    rep = baseline_reports(Trajectory(times, gt))
    step_t, step_deg = float(np.linalg.norm(S[:3, 3])), float(np.degrees(np.linalg.norm(xi[3:])))
    zm, cvr = rep["zero motion"], rep["constant velocity"]
    assert zm["rpe_trans_rmse_m"] == pytest.approx(step_t, rel=1e-9)
    assert zm["rpe_rot_rmse_deg"] == pytest.approx(step_deg, rel=1e-6)
    assert zm["se3_l2_mean"] == pytest.approx(np.linalg.norm(xi), rel=1e-9)
    assert cvr["rpe_trans_rmse_m"] == pytest.approx(step_t / np.sqrt(n - 1), rel=1e-9)
    assert cvr["rpe_rot_rmse_deg"] == pytest.approx(step_deg / np.sqrt(n - 1), rel=1e-6)
    assert cvr["se3_l2_mean"] == pytest.approx(np.linalg.norm(xi) / (n - 1), rel=1e-9)
    assert 0 < cvr["ate_rmse_m"] < zm["ate_rmse_m"]
