"""The one module that converts between geometry conventions.

Every quaternion re-ordering, se(3) ordering and covariance permutation in the project
lives here; docs/conventions.md states the conventions in words. Summary:

* Poses are 4x4 float64 homogeneous matrices named by their frames: ``T_world_cam``
  maps camera coordinates into the world. ``T_a_c = T_a_b @ T_b_c``.
* The relative pose between frames i and j is ``T_i_j = inv(T_world_i) @ T_world_j``.
* The project's se(3) vector is the paper's ``xi = (v, w)``: translation part first
  (``v``, the *tangent* translation, i.e. ``V^-1 t``), rotation vector second (``w``).
  ``T = se3_exp(xi)``; the perturbation convention is right (body frame):
  ``T_true = T_est @ se3_exp(delta)``.
* Quaternions in files (TUM, g2o) are ``(qx, qy, qz, qw)``; scipy uses the same order.
  GTSAM's ``Rot3.Quaternion`` takes ``(w, x, y, z)``; evo stores ``(w, x, y, z)``.
* GTSAM's Pose3 tangent is ``(w, v)`` (rotation first), also right perturbation, so a
  6x6 covariance converts between the two by a fixed permutation (:func:`cov_to_gtsam`).
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial.transform import Rotation

Mat4 = NDArray[np.float64]

#: Permutation taking a project-order vector (v, w) to GTSAM order (w, v).
_PERM_TO_GTSAM = np.array([3, 4, 5, 0, 1, 2])
#: Below this angle (rad) series expansions replace the closed forms.
_SMALL_ANGLE = 1e-4
_COS_LOG_FAST = float(np.cos(np.radians(150.0)))  # se3_log: closed form below 150 degrees
_SKEW_A, _SKEW_B = np.array([2, 0, 1]), np.array([1, 2, 0])  # vee(R - R^T) = R[A, B] - R[B, A]


# ----------------------------------------------------------------------------------
# basic SE(3) helpers
# ----------------------------------------------------------------------------------
def make_T(R: ArrayLike, t: ArrayLike) -> Mat4:
    """Build a 4x4 transform from a 3x3 rotation and a translation (3,)."""
    T = np.eye(4)
    T[:3, :3] = np.asarray(R, dtype=np.float64)
    T[:3, 3] = np.asarray(t, dtype=np.float64).reshape(3)
    return T


def inv_T(T: ArrayLike) -> Mat4:
    """Inverse of a rigid transform (exact, no general matrix inverse)."""
    T = np.asarray(T, dtype=np.float64)
    R = T[:3, :3]
    out = np.eye(4)
    out[:3, :3] = R.T
    out[:3, 3] = -R.T @ T[:3, 3]
    return out


def relative_pose(T_world_i: ArrayLike, T_world_j: ArrayLike) -> Mat4:
    """``T_i_j = inv(T_world_i) @ T_world_j`` (pose of frame j seen from frame i)."""
    return inv_T(T_world_i) @ np.asarray(T_world_j, dtype=np.float64)


def is_rigid(T: ArrayLike, atol: float = 1e-5) -> bool:
    """True if ``T`` is a finite 4x4 rigid transform (orthonormal, det +1)."""
    T = np.asarray(T, dtype=np.float64)
    return T.shape == (4, 4) and bool(rigid_mask(T[None], atol)[0])


def rigid_mask(Ts: ArrayLike, atol: float = 1e-5) -> NDArray[np.bool_]:
    """:func:`is_rigid` of each of a batch of transforms (N, 4, 4): a bool array (N,)."""
    Ts = np.asarray(Ts, dtype=np.float64).reshape(-1, 4, 4)
    ok = np.isfinite(Ts).all(axis=(1, 2))
    R = np.where(ok[:, None, None], Ts[:, :3, :3], np.eye(3))  # no warnings from non-finite rows
    ok &= np.isclose(R.transpose(0, 2, 1) @ R, np.eye(3), rtol=1e-5, atol=atol).all(axis=(1, 2))
    ok &= np.abs(np.linalg.det(R) - 1.0) < atol
    ok &= np.isclose(Ts[:, 3], [0, 0, 0, 1], rtol=1e-5, atol=atol).all(axis=1)
    return ok


def orthonormalize(T: ArrayLike) -> NDArray[np.float64]:
    """Project the rotation block of a transform (4, 4), or of each of a batch (..., 4, 4),
    onto SO(3): the closest rotation (orthogonal polar factor ``U V^T`` of the SVD, the
    last singular vector flipped when the determinant would be -1); the translation is
    kept and the last row set to ``0 0 0 1``.

    Exactly orthonormal blocks are returned unchanged; nearly orthonormal ones
    (``|R^T R - I| < 1e-3``, det > 0) take three Newton-Schulz steps
    ``R <- R (3 I - R^T R) / 2``, which converge quadratically to the same polar factor
    (vectorised, no SVD); the others a batched SVD."""
    T = np.array(T, dtype=np.float64)
    Ts = T.reshape(-1, 4, 4)
    R = Ts[:, :3, :3]
    err = np.abs(R.transpose(0, 2, 1) @ R - np.eye(3)).max(axis=(1, 2), initial=0.0)
    close = (err < 1e-3) & (np.linalg.det(R) > 0)
    near = np.flatnonzero(close & (err > 1e-12))  # exactly orthonormal ones stay as they are
    if len(near):
        Rn = R[near]
        for _ in range(3):
            Rn = 0.5 * Rn @ (3.0 * np.eye(3) - Rn.transpose(0, 2, 1) @ Rn)
        R[near] = Rn
    far = np.flatnonzero(~close)
    if len(far):
        U, _, Vt = np.linalg.svd(R[far])
        U[:, :, -1] *= np.sign(np.linalg.det(U @ Vt))[:, None]
        R[far] = U @ Vt
    Ts[:, 3] = [0, 0, 0, 1]
    return Ts.reshape(T.shape)


# ----------------------------------------------------------------------------------
# quaternions (file order x, y, z, w)
# ----------------------------------------------------------------------------------
def quat_xyzw_to_R(q_xyzw: ArrayLike) -> NDArray[np.float64]:
    """Rotation matrix from a quaternion in file order ``(qx, qy, qz, qw)``.

    The quaternion is normalised; ``q`` and ``-q`` give the same rotation.
    """
    q = np.asarray(q_xyzw, dtype=np.float64)
    n = np.linalg.norm(q)
    if not np.isfinite(n) or n < 1e-12:
        raise ValueError(f"invalid quaternion {q.tolist()}")
    return Rotation.from_quat(q / n).as_matrix()


def R_to_quat_xyzw(R: ArrayLike) -> NDArray[np.float64]:
    """Quaternion ``(qx, qy, qz, qw)`` of a rotation matrix (3, 3), with ``qw >= 0``; of a
    batch (..., 3, 3): (..., 4)."""
    R = np.asarray(R, dtype=np.float64)
    q = Rotation.from_matrix(R.reshape(-1, 3, 3)).as_quat()
    q[q[:, 3] < 0] *= -1.0
    return q.reshape(R.shape[:-2] + (4,))


def tum_to_T(row: ArrayLike) -> Mat4:
    """``T_world_cam`` from the 7 pose entries of a TUM row ``tx ty tz qx qy qz qw``."""
    row = np.asarray(row, dtype=np.float64)
    return make_T(quat_xyzw_to_R(row[3:7]), row[:3])


def T_to_tum(T: ArrayLike) -> NDArray[np.float64]:
    """The 7 pose entries ``tx ty tz qx qy qz qw`` of a TUM row; of a batch (..., 4, 4):
    (..., 7)."""
    T = np.asarray(T, dtype=np.float64)
    return np.concatenate([T[..., :3, 3], R_to_quat_xyzw(T[..., :3, :3])], axis=-1)


def quat_xyzw_to_wxyz(q_xyzw: ArrayLike) -> NDArray[np.float64]:
    """Re-order a quaternion from file order to ``(w, x, y, z)`` (GTSAM, evo)."""
    x, y, z, w = np.asarray(q_xyzw, dtype=np.float64)
    return np.array([w, x, y, z])


def quat_wxyz_to_xyzw(q_wxyz: ArrayLike) -> NDArray[np.float64]:
    """Re-order a quaternion from ``(w, x, y, z)`` to file order ``(x, y, z, w)``."""
    w, x, y, z = np.asarray(q_wxyz, dtype=np.float64)
    return np.array([x, y, z, w])


# ----------------------------------------------------------------------------------
# so(3) / se(3) exp and log, project order xi = (v, w)
# ----------------------------------------------------------------------------------
def hat(w: ArrayLike) -> NDArray[np.float64]:
    """Skew-symmetric matrix of a 3-vector (3,) -> (3, 3), or of each row (..., 3) -> (..., 3, 3)."""
    w = np.asarray(w, dtype=np.float64)
    x, y, z = w[..., 0], w[..., 1], w[..., 2]
    S = np.zeros(w.shape[:-1] + (3, 3))
    S[..., 0, 1], S[..., 0, 2], S[..., 1, 2] = -z, y, -x
    S[..., 1, 0], S[..., 2, 0], S[..., 2, 1] = z, -y, x
    return S


def _V_coeffs(theta: float) -> tuple[float, float]:
    """Coefficients (b, c) of ``V = I + b W + c W^2`` with series near theta = 0."""
    if theta < _SMALL_ANGLE:
        t2 = theta * theta
        return 0.5 - t2 / 24.0, 1.0 / 6.0 - t2 / 120.0
    return (1.0 - math.cos(theta)) / theta**2, (theta - math.sin(theta)) / theta**3


def _cross(a: NDArray[np.float64], b: NDArray[np.float64]) -> NDArray[np.float64]:
    """Row-wise cross product of (n, 3) arrays (np.cross costs 30x more on one row)."""
    return a[:, _SKEW_B] * b[:, _SKEW_A] - a[:, _SKEW_A] * b[:, _SKEW_B]


def se3_exp(xi: ArrayLike) -> Mat4:
    """Exponential map of ``xi = (v, w)`` (project order) to a 4x4 transform.

    Written out in scalars: the teacher takes ~60 of these per edge, and NumPy's per-call
    overhead on 3x3 blocks was most of their cost (16 -> 5 us a call)."""
    v0, v1, v2, x, y, z = np.asarray(xi, dtype=np.float64).reshape(6).tolist()
    theta = math.sqrt(x * x + y * y + z * z)
    if math.isinf(theta):  # NaN throughout, as NumPy's sin gives (math.sin refuses infinity)
        theta = math.nan
    # Rodrigues: R = I + a W + b W^2 with a = sin(t)/t, b = (1 - cos t)/t^2 (series near 0);
    # V = I + b W + c W^2; W = hat(w), W^2 = w w^T - theta^2 I
    a = 1.0 - theta * theta / 6.0 if theta < _SMALL_ANGLE else math.sin(theta) / theta
    b, c = _V_coeffs(theta)
    xx, yy, zz, xy, xz, yz = -(y * y + z * z), -(x * x + z * z), -(x * x + y * y), x * y, x * z, y * z
    r = (1.0 + b * xx, -a * z + b * xy, a * y + b * xz,
         a * z + b * xy, 1.0 + b * yy, -a * x + b * yz,
         -a * y + b * xz, a * x + b * yz, 1.0 + b * zz)
    m = (1.0 + c * xx, -b * z + c * xy, b * y + c * xz,
         b * z + c * xy, 1.0 + c * yy, -b * x + c * yz,
         -b * y + c * xz, b * x + c * yz, 1.0 + c * zz)
    return np.array([[r[0], r[1], r[2], m[0] * v0 + m[1] * v1 + m[2] * v2],
                     [r[3], r[4], r[5], m[3] * v0 + m[4] * v1 + m[5] * v2],
                     [r[6], r[7], r[8], m[6] * v0 + m[7] * v1 + m[8] * v2],
                     [0.0, 0.0, 0.0, 1.0]])


def se3_log(T: ArrayLike) -> NDArray[np.float64]:
    """Logarithm ``xi = (v, w)`` (6,) of a rigid transform (4, 4), or (..., 6) of a batch
    (..., 4, 4); ``v = V^-1 t``, not the raw ``t``.

    The rotation vector is ``theta / (2 sin theta) * vee(R - R^T)``, ``theta =
    atan2(sin, cos)`` from the skew part and the trace (accurate near 0); from 150 degrees
    on, where the skew part vanishes, it comes from scipy, which is accurate near pi.
    """
    T = np.asarray(T, dtype=np.float64)
    if T.shape == (4, 4):
        out = _se3_log_one(T)
        if out is not None:
            return out
    Ts = T.reshape(-1, 4, 4)
    R, t = Ts[:, :3, :3], Ts[:, :3, 3]
    s = 0.5 * (R[:, _SKEW_A, _SKEW_B] - R[:, _SKEW_B, _SKEW_A])  # sin(theta) * axis
    c = 0.5 * (R[:, 0, 0] + R[:, 1, 1] + R[:, 2, 2] - 1.0)  # cos(theta)
    sin_t = np.sqrt((s * s).sum(axis=1))
    safe = np.where(sin_t > 1e-12, sin_t, 1.0)
    w = s * np.where(sin_t > 1e-12, np.arctan2(sin_t, c) / safe, 1.0)[:, None]
    slow = c <= _COS_LOG_FAST
    if slow.any():
        w[slow] = Rotation.from_matrix(R[slow]).as_rotvec().reshape(-1, 3)
    # v = V^-1 t = t - w x t / 2 + d w x (w x t), d = (1 - (theta/2) cot(theta/2)) / theta^2
    theta = np.sqrt((w * w).sum(axis=1))
    small = theta < _SMALL_ANGLE
    half = 0.5 * np.where(small, 1.0, theta)
    d = np.where(small, 1.0 / 12.0 + theta * theta / 720.0, (1.0 - half / np.tan(half)) / (4.0 * half * half))
    wt = _cross(w, t)
    v = t - 0.5 * wt + d[:, None] * _cross(w, wt)
    return np.concatenate([v, w], axis=1).reshape(T.shape[:-2] + (6,))


def _se3_log_one(T: NDArray[np.float64]) -> NDArray[np.float64] | None:
    """:func:`se3_log` of one transform, the same formulas in scalars (the batch code's NumPy
    overhead was most of a single call's cost: 43 -> 2 us); None from 150 degrees on (scipy's
    branch)."""
    (r00, r01, r02, t0), (r10, r11, r12, t1), (r20, r21, r22, t2) = T[:3].tolist()
    sx, sy, sz = 0.5 * (r21 - r12), 0.5 * (r02 - r20), 0.5 * (r10 - r01)
    c = 0.5 * (r00 + r11 + r22 - 1.0)
    if c <= _COS_LOG_FAST:
        return None
    sin_t = math.sqrt(sx * sx + sy * sy + sz * sz)
    k = math.atan2(sin_t, c) / sin_t if sin_t > 1e-12 else 1.0
    wx, wy, wz = sx * k, sy * k, sz * k
    theta = math.sqrt(wx * wx + wy * wy + wz * wz)
    if theta < _SMALL_ANGLE:
        d = 1.0 / 12.0 + theta * theta / 720.0
    else:
        half = 0.5 * theta
        d = (1.0 - half / math.tan(half)) / (4.0 * half * half)
    ax, ay, az = wy * t2 - wz * t1, wz * t0 - wx * t2, wx * t1 - wy * t0  # w x t
    bx, by, bz = wy * az - wz * ay, wz * ax - wx * az, wx * ay - wy * ax  # w x (w x t)
    return np.array([t0 - 0.5 * ax + d * bx, t1 - 0.5 * ay + d * by, t2 - 0.5 * az + d * bz, wx, wy, wz])


def adjoint(T: ArrayLike) -> NDArray[np.float64]:
    """6x6 adjoint of ``T`` in project order (v, w): ``T exp(d) inv(T) = exp(adjoint(T) d)``,
    ``[[R, hat(t) R], [0, R]]``. Moves a right perturbation across a transform: for
    ``A = B @ C``, ``A exp(d) = B exp(adjoint(C) d) C`` (a covariance ``S`` becomes
    ``adjoint(C) S adjoint(C)^T``)."""
    T = np.asarray(T, dtype=np.float64)
    R, t = T[:3, :3], T[:3, 3]
    Ad = np.zeros((6, 6))
    Ad[:3, :3] = Ad[3:, 3:] = R
    Ad[:3, 3:] = hat(t) @ R
    return Ad


def rotation_angle_deg(T: ArrayLike) -> float:
    """Rotation angle of a transform's rotation block, degrees."""
    R = np.asarray(T, dtype=np.float64)[:3, :3]
    c = np.clip((np.trace(R) - 1.0) / 2.0, -1.0, 1.0)
    return float(np.degrees(np.arccos(c)))


def agrees(T_a: ArrayLike, T_b: ArrayLike, max_m: float, max_deg: float) -> bool:
    """Two transforms differ by at most ``max_m`` of translation and ``max_deg`` of rotation
    (``inv(T_a) @ T_b``)."""
    d = relative_pose(T_a, T_b)
    return bool(np.linalg.norm(d[:3, 3]) <= max_m and rotation_angle_deg(d) <= max_deg)


# ----------------------------------------------------------------------------------
# covariances and GTSAM
# ----------------------------------------------------------------------------------
def vec_to_gtsam(xi: ArrayLike) -> NDArray[np.float64]:
    """Re-order a tangent vector from project order (v, w) to GTSAM order (w, v)."""
    return np.asarray(xi, dtype=np.float64)[..., _PERM_TO_GTSAM]


def vec_from_gtsam(xi_g: ArrayLike) -> NDArray[np.float64]:
    """Re-order a tangent vector from GTSAM order (w, v) to project order (v, w)."""
    inv = np.argsort(_PERM_TO_GTSAM)
    return np.asarray(xi_g, dtype=np.float64)[..., inv]


def cov_to_gtsam(cov: ArrayLike) -> NDArray[np.float64]:
    """6x6 covariance (or information) from project order (v, w) to GTSAM (w, v).

    Both are right-perturbation tangents at the same pose, so only the order changes.
    """
    c = np.asarray(cov, dtype=np.float64)
    p = _PERM_TO_GTSAM
    return c[np.ix_(p, p)]


def cov_from_gtsam(cov_g: ArrayLike) -> NDArray[np.float64]:
    """6x6 covariance (or information) from GTSAM order (w, v) to project order (v, w)."""
    c = np.asarray(cov_g, dtype=np.float64)
    inv = np.argsort(_PERM_TO_GTSAM)
    return c[np.ix_(inv, inv)]


def to_gtsam_pose3(T: ArrayLike):  # -> gtsam.Pose3
    """A ``gtsam.Pose3`` from a 4x4 transform (imports gtsam lazily)."""
    import gtsam

    return gtsam.Pose3(orthonormalize(T))


def from_gtsam_pose3(pose) -> Mat4:
    """4x4 transform from a ``gtsam.Pose3``."""
    return np.asarray(pose.matrix(), dtype=np.float64)


def evo_pose_arrays(T_list: ArrayLike) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """(positions (N, 3), quaternions (N, 4) in evo's ``w x y z`` order) of poses."""
    Ts = np.asarray(T_list, dtype=np.float64)
    xyz = Ts[:, :3, 3].copy()
    q = Rotation.from_matrix(Ts[:, :3, :3]).as_quat()  # x y z w
    return xyz, q[:, [3, 0, 1, 2]]


def poses_from_evo_arrays(xyz: ArrayLike, q_wxyz: ArrayLike) -> NDArray[np.float64]:
    """(N, 4, 4) poses from evo's positions and ``w x y z`` quaternions."""
    xyz = np.asarray(xyz, dtype=np.float64)
    q = np.asarray(q_wxyz, dtype=np.float64)
    out = np.tile(np.eye(4), (len(xyz), 1, 1))
    out[:, :3, :3] = Rotation.from_quat(q[:, [1, 2, 3, 0]]).as_matrix()
    out[:, :3, 3] = xyz
    return out
