"""Covariances of the dense alignments (point-to-plane, hybrid) and their conditioning."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from ctcvo.teacher.maps import PHOTO_WEIGHT, DenseMaps
from ctcvo.teacher.sparse import huber_weights

DENSE_TRUNC_M = 0.07  # Open3D's depth_outlier_trunc default (b8ac45d), not tuned
DENSE_HUBER_M = 0.05  # Open3D's depth_huber_delta default (b8ac45d), not tuned
PHOTO_HUBER = 0.1  # grey units; Open3D's default, not tuned
PHOTO_HUBER_SCALED = PHOTO_HUBER * float(np.sqrt(PHOTO_WEIGHT))
DENSE_MIN_SIGMA_M = 0.0003  # point-to-plane residual floor: 1/sqrt(12) mm depth steps (b8a2c06), not tuned

def point_to_plane_covariance(T_i_j: NDArray, di: DenseMaps, dj: DenseMaps,
                              stride: int = 1) -> tuple[NDArray | None, int, float]:
    """Covariance (6, 6), (v, w) order, right perturbation at ``T_i_j``, of the dense
    point-to-plane alignment of frame j's points to frame i's surface; also the number of
    pixel pairs and their RMS distance (m).

    The pairs are formed as Open3D's projective kernel forms them (j's point moved into i,
    projected with ``di.K``, paired with i's vertex at the rounded pixel, kept within
    ``DENSE_TRUNC_M``). Residual ``r = n^T (T q - p)``; with ``m = R^T n`` its Jacobian
    is ``[m^T, (q x m)^T]``. ``sigma^2`` is the Huber-weighted residual variance, floored at
    ``DENSE_MIN_SIGMA_M`` squared (two images of one repeated depth map agree exactly). The
    pixels' errors are correlated (smooth depth bias, correlated noise), so this is a lower
    bound of the real uncertainty. None when fewer than 6 pairs or a singular system.
    ``stride``: use every ``stride``-th point of j in both axes (the covariance is then
    scaled back to all of them)."""
    q = dj.moved_points(stride)
    R, t = T_i_j[:3, :3], T_i_j[:3, 3]
    X = q @ R.T + t
    vert, nrm, h, w, K = di.surface()
    # rows are selected with np.take / np.compress: the same rows as fancy or boolean
    # indexing, which NumPy does 4-10 times slower on (N, 3) arrays
    front = X[:, 2] > 1e-6
    if not front.all():
        q, X = np.compress(front, q, axis=0), np.compress(front, X, axis=0)
    u = np.rint(K[0, 0] * X[:, 0] / X[:, 2] + K[0, 2]).astype(np.int64)
    v = np.rint(K[1, 1] * X[:, 1] / X[:, 2] + K[1, 2]).astype(np.int64)
    idx = np.flatnonzero((u >= 0) & (u < w) & (v >= 0) & (v < h))
    pix = v[idx] * w + u[idx]
    p, n = np.take(vert, pix, axis=0), np.take(nrm, pix, axis=0)
    use = np.isfinite(p).all(axis=1) & np.isfinite(n).all(axis=1)
    idx = idx[use]
    p, n = np.compress(use, p, axis=0).astype(np.float64), np.compress(use, n, axis=0).astype(np.float64)
    Xs = np.take(X, idx, axis=0)
    d = Xs - p
    ok = np.sqrt(np.add.reduce(d * d, axis=1)) < DENSE_TRUNC_M  # np.linalg.norm's formula
    q, X = np.take(q, idx[ok], axis=0), np.compress(ok, Xs, axis=0)
    p, n = np.compress(ok, p, axis=0), np.compress(ok, n, axis=0)
    if len(q) < 6:
        return None, len(q), float("nan")
    r = np.einsum("ij,ij->i", n, X - p)
    m = n @ R
    J = np.empty((len(q), 6))
    J[:, :3] = m
    J[:, 3] = q[:, 1] * m[:, 2] - q[:, 2] * m[:, 1]  # q x m, written out (np.cross's formula)
    J[:, 4] = q[:, 2] * m[:, 0] - q[:, 0] * m[:, 2]
    J[:, 5] = q[:, 0] * m[:, 1] - q[:, 1] * m[:, 0]
    _, wts, _ = huber_weights(r, DENSE_HUBER_M)
    H = J.T @ (J * wts[:, None])
    sigma2 = max(float(np.sum(wts * r * r) / max(len(r) - 6, 1)), DENSE_MIN_SIGMA_M ** 2)
    try:
        cov = sigma2 * np.linalg.inv(H) / stride ** 2
    except np.linalg.LinAlgError:
        return None, len(q), float(np.sqrt(np.mean(r * r)))
    if not np.all(np.isfinite(cov)):
        return None, len(q), float(np.sqrt(np.mean(r * r)))
    return 0.5 * (cov + cov.T), len(q), float(np.sqrt(np.mean(r * r)))


def hybrid_covariance(T_i_j: NDArray, di: DenseMaps, dj: DenseMaps,
                      stride: int = 2) -> NDArray | None:
    """Covariance (6, 6), (v, w) order, right perturbation at ``T_i_j``, of the hybrid
    alignment of :func:`hybrid_align`: the inverse of the summed information of its two
    residuals at the result, each pixel pair formed as Open3D's kernel forms it (frame j's
    point ``q`` moved into i, the nearest pixel of i's full-resolution maps, kept within
    ``DENSE_TRUNC_M`` in depth). Photometric ``r_I = I_i(u) - I_j(q)`` and depth
    ``r_D = D_i(u) - z(T q)``, their Jacobians through the Sobel derivatives of frame i
    (``/ 8``: per pixel) and the projection; each term Huber-weighted (``PHOTO_HUBER``,
    ``DENSE_HUBER_M``) and divided by its own weighted residual variance (floored at
    ``DENSE_MIN_SIGMA_M`` squared for depth). Pixel errors are correlated, so, like
    :func:`point_to_plane_covariance`, a lower bound. ``stride``: every ``stride``-th point
    of j in both axes (scaled back to all). None without photometric maps, with fewer
    than 12 pairs or a singular system."""
    pi, pj = di.photo, dj.photo
    if pi is None or pj is None or not (pi.grey and pj.grey):
        return None
    q = dj.points.numpy()[::stride, ::stride].reshape(-1, 3)
    Ij = pj.src_intensity.numpy()[::stride, ::stride].reshape(-1)
    ok = np.all(np.isfinite(q), axis=1)
    q, Ij = q[ok].astype(np.float64), Ij[ok].astype(np.float64)
    R, t = T_i_j[:3, :3], T_i_j[:3, 3]
    X = q @ R.T + t
    K = pi.K.numpy()
    Di = pi.depth.numpy()[..., 0]
    h, w = Di.shape
    front = X[:, 2] > 1e-6
    X, q, Ij = X[front], q[front], Ij[front]
    uf = K[0, 0] * X[:, 0] / X[:, 2] + K[0, 2]
    vf = K[1, 1] * X[:, 1] / X[:, 2] + K[1, 2]
    u, v = np.rint(uf).astype(np.int64), np.rint(vf).astype(np.int64)
    inside = (u >= 1) & (u < w - 1) & (v >= 1) & (v < h - 1)
    X, q, Ij, u, v = X[inside], q[inside], Ij[inside], u[inside], v[inside]
    d = Di[v, u].astype(np.float64)
    g = [a.numpy()[..., 0][v, u].astype(np.float64) / 8.0 for a in (pi.depth_dx, pi.depth_dy, pi.intensity_dx, pi.intensity_dy)]
    rD = d - X[:, 2]
    ok = np.isfinite(d) & (np.abs(rD) <= DENSE_TRUNC_M) & np.all(np.isfinite(np.stack(g)), axis=0)
    if ok.sum() < 12:
        return None
    X, q, rD = X[ok], q[ok], rD[ok]
    gDx, gDy, gIx, gIy = (a[ok] for a in g)
    rI = pi.intensity.numpy()[..., 0][v[ok], u[ok]].astype(np.float64) - Ij[ok]
    iz = 1.0 / X[:, 2]
    # d(u, v)/dX of the pinhole projection, rows (3,) per pixel
    du = np.stack([K[0, 0] * iz, np.zeros_like(iz), -K[0, 0] * X[:, 0] * iz * iz], axis=1)
    dv = np.stack([np.zeros_like(iz), K[1, 1] * iz, -K[1, 1] * X[:, 1] * iz * iz], axis=1)
    bI = gIx[:, None] * du + gIy[:, None] * dv
    bD = gDx[:, None] * du + gDy[:, None] * dv
    bD[:, 2] -= 1.0
    info = np.zeros((6, 6))
    a = float(np.sqrt(PHOTO_WEIGHT))  # the grey maps' scale (photo_maps)
    for b, r, k, floor in ((bI, rI, PHOTO_HUBER_SCALED, a / 255), (bD, rD, DENSE_HUBER_M, DENSE_MIN_SIGMA_M)):
        m = b @ R  # R^T b per pixel
        J = np.concatenate([m, np.cross(q, m)], axis=1)
        _, wts, _ = huber_weights(r, k)
        sigma2 = max(float(np.sum(wts * r * r) / max(len(r) - 6, 1)), floor ** 2)
        info += J.T @ (J * wts[:, None]) / sigma2
    try:
        cov = np.linalg.inv(info) / stride ** 2
    except np.linalg.LinAlgError:
        return None
    if not np.all(np.isfinite(cov)):
        return None
    return 0.5 * (cov + cov.T)


def conditioning(cov: NDArray, dj: DenseMaps) -> float:
    """Smallest over largest eigenvalue of a dense covariance with rotations scaled by the
    median depth of frame j (a rotation of 1 rad moves the points by ~z metres); small when
    the depth leaves a direction nearly free (``FALLBACK_MIN_CONDITIONING``)."""
    z = float(np.nanmedian(dj.points.numpy()[..., 2]))
    S = np.diag([1.0, 1.0, 1.0, z, z, z])
    ev = np.linalg.eigvalsh(S @ cov @ S)
    return float(ev[0] / ev[-1]) if ev[-1] > 0 else 0.0

