"""When each image was taken: depth and colour moments, and the rolling shutter's rows."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from ctcvo.data import geometry as geo
from ctcvo.data.open3d_import import o3d
from ctcvo.data.sensor import Sensor
from ctcvo.data.sequence import Intrinsics
from ctcvo.teacher.config import TeacherConfig
from ctcvo.teacher.features import FrameFeatures, backproject, project
from ctcvo.teacher.maps import DENSE_SCALE, DENSE_TARGET_SCALE, DenseMaps
from ctcvo.teacher.record import EdgeEstimate


def rolling_shutter_for(sensor: Sensor, cfg: TeacherConfig) -> float:
    """``cfg.rolling_shutter_s``, auto (None) resolved: the sensor's own readout
    (``Sequence.sensor``: a synthetic scene's sensor model's, 0 when noise-free; Kinect v1's,
    :data:`data.sensor.KINECT_V1_READOUT_S`, for real recordings)."""
    return sensor.readout_s if cfg.rolling_shutter_s is None else float(cfg.rolling_shutter_s)


def depth_moved(fi: FrameFeatures, fj: FrameFeatures, dt: float) -> bool:
    """Whether the edge's depth maps were taken at other moments than its colour images."""
    return (fi.depth_offset != 0.0 or fj.depth_offset != 0.0) and dt > 0


def to_depth_moments(T: NDArray, fi: FrameFeatures, fj: FrameFeatures, dt: float) -> NDArray:
    """``T_i_j`` between the frames' colour moments, ``dt`` seconds apart -> between their
    depth moments (``depth_offset`` later each): ``C_i^-1 T C_j``, ``C = exp(o xi)`` for
    the constant velocity ``xi = log(T) / dt`` of the motion itself (unchanged without
    offsets)."""
    if not depth_moved(fi, fj, dt):
        return T
    xi = geo.se3_log(T) / dt
    return geo.se3_exp(-fi.depth_offset * xi) @ T @ geo.se3_exp(fj.depth_offset * xi)


def _depth_span(fi: FrameFeatures, fj: FrameFeatures, dt: float) -> float:
    """Seconds between the edge's depth moments (its colour moments are ``dt`` apart);
    ``dt`` where that is under a quarter of it."""
    span = dt + fj.depth_offset - fi.depth_offset
    return span if span > dt / 4 else dt


def to_colour_moments(res: EdgeEstimate, fi: FrameFeatures, fj: FrameFeatures, dt: float) -> EdgeEstimate:
    """An estimate between the frames' depth moments (a dense alignment) -> between their
    colour moments, ``dt`` seconds apart, in place: ``T = C_i T_d C_j^-1``, ``C = exp(o xi)``
    at the constant velocity of the result itself, ``xi = log(T_d) / (dt + o_j - o_i)`` (the
    depth moments' time apart; ``dt`` where that is under a quarter of it). The velocity is
    the edge's own: neither an earlier motion's lag nor its noise enters. The covariance is
    moved with ``C_j`` and scaled by the ratio of the two time spans (first order)."""
    if not depth_moved(fi, fj, dt) or res.T_i_j is None:
        return res
    span = _depth_span(fi, fj, dt)
    xi = geo.se3_log(res.T_i_j) / span
    C_j = geo.se3_exp(fj.depth_offset * xi)
    res.T_i_j = geo.orthonormalize(geo.se3_exp(fi.depth_offset * xi) @ res.T_i_j @ geo.inv_T(C_j))
    if res.cov is not None:
        Ad = geo.adjoint(C_j)
        res.cov = (dt / span) ** 2 * (Ad @ res.cov @ Ad.T)
    return res


def cov_to_depth_moments(cov: NDArray | None, T: NDArray, fi: FrameFeatures, fj: FrameFeatures,
                          dt: float) -> NDArray | None:
    """The covariance of ``T`` (between colour moments) as one of :func:`to_depth_moments`'s
    result (the inverse of :func:`to_colour_moments`'s, first order)."""
    if cov is None or not depth_moved(fi, fj, dt):
        return cov
    span = _depth_span(fi, fj, dt)
    Ad = geo.adjoint(geo.se3_exp(-fj.depth_offset * geo.se3_log(T) / dt))
    return (span / dt) ** 2 * (Ad @ cov @ Ad.T)


def _to_middle_row(X: NDArray, rows: NDArray, height: int, xi: NDArray, readout_s: float) -> NDArray:
    """Points ``X`` (..., 3) seen by the image rows ``rows`` (...,) of a rolling-shutter frame,
    moved to the frame's middle-row moment, to first order: ``X + s (w x X + v)``, ``s`` the
    row's time after the middle row's, ``xi = (v, w)`` the camera's body velocity (per s)."""
    s = ((np.asarray(rows, np.float64) / (height - 1) - 0.5) * readout_s).astype(X.dtype)[..., None]
    v, w = (float(a) for a in xi[:3]), (float(a) for a in xi[3:])
    (vx, vy, vz), (wx, wy, wz) = v, w
    x, y, z = X[..., 0], X[..., 1], X[..., 2]
    # w x X + v, written out (np.cross copies its operands into its own layout)
    m = np.stack([wy * z - wz * y + vx, wz * x - wx * z + vy, wx * y - wy * x + vz], axis=-1)
    return X + s * m


def map_to_middle_row(maps: o3d.core.Tensor, row_step: int, height: int, xi: NDArray,
                      readout_s: float) -> o3d.core.Tensor:
    """A vertex map (h, w, 3) of every ``row_step``-th row of a ``height``-row image, each
    point moved to the middle row's moment (:func:`_to_middle_row`)."""
    X = maps.numpy()
    rows = (np.arange(X.shape[0]) * row_step)[:, None]
    return o3d.core.Tensor(np.ascontiguousarray(_to_middle_row(X, rows, height, xi, readout_s)))


def rolling_shutter_views(fi: FrameFeatures, fj: FrameFeatures, intr: Intrinsics,
                          cfg: TeacherConfig) -> tuple | None:
    """For an edge (i, j) with ``cfg.rolling_shutter_s``: frame i's keypoints (pixels, depths)
    and dense maps moved to its middle row's moment at ``fi.velocity_out``, frame j's at
    ``fj.velocity_in`` (:func:`_to_middle_row`; each frame's are built once per role and
    kept). Returns ``((uv_i, z_i), (uv_j, z_j), dense_i, dense_j)``; None without the
    correction (off, or a velocity unknown). Keypoints without depth keep their pixel; the
    dense maps keep their normals and carry no photometric maps (the hybrid stage runs on
    gap-1 edges only, which are never corrected). The window sets the velocities of its frames,
    the keyframe pass those of its keyframes (:func:`teacher.keyframes.estimate_work`)."""
    if not cfg.rolling_shutter_s or fi.velocity_out is None or fj.velocity_in is None:
        return None  # off, auto not resolved (rolling_shutter_for), or a velocity unknown
    (kp_i, dense_i), (kp_j, dense_j) = _rolling_view(fi, "out", intr, cfg), _rolling_view(fj, "in", intr, cfg)
    return kp_i, kp_j, dense_i, dense_j


def middle_row_keypoints(f: FrameFeatures, role: str, intr: Intrinsics, cfg: TeacherConfig) -> tuple:
    """Frame ``f``'s keypoints ``(uv, z)`` moved to its middle row's moment at its own velocity
    out of it (``role`` ``out``) or into it (``in``), as :func:`rolling_shutter_views` moves
    them; as they are without the correction or that velocity."""
    if not cfg.rolling_shutter_s or (f.velocity_out if role == "out" else f.velocity_in) is None:
        return f.uv, f.z
    return _rolling_view(f, role, intr, cfg)[0]


def _rolling_view(f: FrameFeatures, role: str, intr: Intrinsics, cfg: TeacherConfig) -> tuple:
    """``((uv, z), dense)`` of :func:`rolling_shutter_views` for frame ``f`` as an edge's
    older (``out``) or newer (``in``) frame."""
    if role not in f._rolling:
        xi = f.velocity_out if role == "out" else f.velocity_in
        K, h = intr.K, intr.height
        uv, z = f.uv.astype(np.float64), f.z.astype(np.float64)
        ok = z > 0
        X = _to_middle_row(backproject(uv[ok], z[ok], K), uv[ok, 1], h, xi, cfg.rolling_shutter_s)
        uv, z = uv.copy(), z.copy()
        uv[ok], z[ok] = project(X, K), X[:, 2]
        dense, d = None, f.dense
        if d is not None and role == "out" and d.vertex is not None:  # the frame aligned to
            vertex = map_to_middle_row(d.vertex, DENSE_TARGET_SCALE, h, xi, cfg.rolling_shutter_s)
            dense = DenseMaps(d.points, vertex, d.normal, d.K)
        elif d is not None and role == "in":  # the frame moved
            dense = DenseMaps(map_to_middle_row(d.points, DENSE_SCALE, h, xi, cfg.rolling_shutter_s), d.vertex,
                              d.normal, d.K)
        f._rolling[role] = ((uv, z), dense)
    return f._rolling[role]

