"""Smooth hand-held 6-DoF camera trajectories through a :class:`~data.synthetic.layout.Scene`.

The camera wanders through the free part of the room along a cubic spline through random
waypoints, looking at points of interest (furniture fronts and tops, objects, walls) 0.9-2.6 m
away, with a slow random roll. The spline is re-timed so that the speed follows a smooth
random profile around ``mean_speed_mps`` while never exceeding ``max_speed_mps`` nor
``max_angular_dps`` (the camera slows down while it turns, as a person does). Small hand
tremor (1-4 Hz, ~1.5 mm, ~0.1 deg) is added on top. Poses are ``T_world_cam`` with the
OpenCV camera axes (x right, y down, z forward).
"""

from __future__ import annotations

import logging

import numpy as np
from numpy.typing import NDArray
from scipy.interpolate import CubicSpline
from scipy.spatial.transform import Rotation

from ctcvo.data.synthetic.config import SceneConfig
from ctcvo.data.synthetic.layout import Scene

log = logging.getLogger(__name__)

CLEARANCE_M = 0.3  # minimum distance of the camera from any solid box
_DENSE = 60  # samples per spline segment for re-timing


def look_at(p: NDArray, q: NDArray, roll: NDArray) -> NDArray[np.float64]:
    """Rotations (N, 3, 3) of cameras at ``p`` (N, 3) looking at ``q`` (N, 3), rolled by ``roll`` (N,) rad."""
    f = q - p
    f /= np.linalg.norm(f, axis=1, keepdims=True)
    x = np.cross(f, np.array([0.0, 0.0, 1.0]))
    x /= np.linalg.norm(x, axis=1, keepdims=True)
    y = np.cross(f, x)
    R = np.stack([x, y, f], axis=2)
    c, s = np.cos(roll), np.sin(roll)
    Rz = np.zeros((len(roll), 3, 3))
    Rz[:, 0, 0], Rz[:, 0, 1], Rz[:, 1, 0], Rz[:, 1, 1], Rz[:, 2, 2] = c, -s, s, c, 1.0
    return R @ Rz


def _clearance(scene: Scene, pts: NDArray) -> NDArray[np.float64]:
    d = np.full(len(pts), np.inf)
    for ob in scene.obstacles:
        d = np.minimum(d, ob.distance(pts))
    return d


def _smooth_noise(rng: np.random.Generator, t: NDArray, freqs: tuple[float, float], n: int = 3) -> NDArray:
    """Sum of ``n`` random sinusoids with unit total RMS, evaluated at ``t``."""
    out = np.zeros_like(t, dtype=np.float64)
    for _ in range(n):
        f = rng.uniform(*freqs)
        out += np.sin(2 * np.pi * f * t + rng.uniform(0, 2 * np.pi))
    return out * np.sqrt(2.0 / n)


def _waypoints(cfg: SceneConfig, scene: Scene, rng: np.random.Generator, n: int) -> tuple[NDArray, NDArray, NDArray]:
    lo, hi = scene.free_box
    pts: list[NDArray] = []
    for _ in range(200):
        p = rng.uniform(lo, hi)
        if _clearance(scene, p[None])[0] > 0.5:
            pts.append(p)
            break
    else:
        pts.append((lo + hi) / 2)
    while len(pts) < n:
        for _ in range(100):
            step = rng.uniform(0.4, 1.1)
            a = rng.uniform(0, 2 * np.pi)
            cand = pts[-1] + [step * np.cos(a), step * np.sin(a), rng.normal(0, 0.2)]
            cand = np.clip(cand, lo, hi)
            seg = pts[-1] + np.linspace(0, 1, 12)[:, None] * (cand - pts[-1])
            if np.linalg.norm(cand - pts[-1]) > 0.25 and _clearance(scene, seg).min() > CLEARANCE_M + 0.15:
                break
        pts.append(cand)
    P = np.array(pts)
    targets, prev_dir = [], None
    dmin, dmax = cfg.view_distance_m
    for p in P:
        d = np.linalg.norm(scene.interest - p, axis=1)
        cand = scene.interest[(d > dmin) & (d < dmax)]
        if len(cand) == 0:
            cand = scene.interest[np.argsort(np.abs(d - (dmin + dmax) / 2))[:5]]
        dirs = (cand - p) / np.linalg.norm(cand - p, axis=1, keepdims=True)
        if prev_dir is not None:
            close = dirs @ prev_dir > np.cos(np.radians(70))
            if close.any():
                cand, dirs = cand[close], dirs[close]
        k = int(rng.integers(0, len(cand)))
        targets.append(cand[k] + rng.normal(0, 0.1, 3))
        prev_dir = dirs[k]
    roll = rng.normal(0, np.radians(4), n)
    return P, np.array(targets), roll


def make_trajectory(cfg: SceneConfig, scene: Scene, rng: np.random.Generator) -> NDArray[np.float64]:
    """``cfg.frames`` poses ``T_world_cam`` (N, 4, 4) at ``cfg.fps`` (see module docstring)."""
    n_frames = cfg.frames
    duration = (n_frames - 1) / cfg.fps
    n_wp = int(np.ceil(duration * cfg.mean_speed_mps / 0.6)) + 4
    w_max = np.radians(cfg.max_angular_dps)
    for attempt in range(30):
        P, Q, roll = _waypoints(cfg, scene, rng, n_wp)
        u_knots = np.arange(n_wp, dtype=np.float64)
        sp, sq, sr = CubicSpline(u_knots, P), CubicSpline(u_knots, Q), CubicSpline(u_knots, roll)
        u = np.linspace(0, n_wp - 1, (n_wp - 1) * _DENSE + 1)
        p, q = sp(u), sq(u)
        R = look_at(p, q, sr(u))
        ds = np.linalg.norm(np.diff(p, axis=0), axis=1)
        rel = np.einsum("nji,njk->nik", R[:-1], R[1:])
        dth = np.arccos(np.clip((np.trace(rel, axis1=1, axis2=2) - 1) / 2, -1, 1))
        um = (u[:-1] + u[1:]) / 2
        v_des = cfg.mean_speed_mps * np.exp(cfg.speed_variability * _smooth_noise(rng, um, (0.1, 0.4)))
        v_des = np.clip(v_des, cfg.min_speed_mps, cfg.max_speed_mps)
        dt = np.maximum.reduce([ds / v_des, dth / w_max, np.full_like(ds, 1e-6)])
        t = np.concatenate([[0.0], np.cumsum(dt)])
        clear = _clearance(scene, p).min()
        if t[-1] < duration:
            n_wp = int(n_wp * 1.5) + 2
            continue
        if clear < CLEARANCE_M:
            log.debug("trajectory attempt %d too close to furniture (%.2f m)", attempt, clear)
            continue
        break
    else:
        log.warning("could not find a trajectory keeping %.2f m from furniture; using the last one", CLEARANCE_M)
    tk = np.arange(n_frames) / cfg.fps
    uk = np.interp(tk, t, u)
    pk, qk = sp(uk), sq(uk)
    Rk = look_at(pk, qk, sr(uk))
    # hand tremor
    jt = np.stack([_smooth_noise(rng, tk, (1.0, 4.0)) for _ in range(3)], 1) * cfg.jitter_trans_m / np.sqrt(3)
    jr = np.stack([_smooth_noise(rng, tk, (1.0, 4.0)) for _ in range(3)], 1) * np.radians(cfg.jitter_rot_deg) / np.sqrt(3)
    Rk = Rk @ Rotation.from_rotvec(jr).as_matrix()
    T = np.tile(np.eye(4), (n_frames, 1, 1))
    T[:, :3, :3] = Rk
    T[:, :3, 3] = pk + jt
    return T


def motion_stats(T: NDArray[np.float64], fps: float) -> dict[str, float]:
    """Speed statistics of poses (N, 4, 4): mean/max m/s and deg/s, mean/max mm per frame."""
    dp = np.linalg.norm(np.diff(T[:, :3, 3], axis=0), axis=1)
    rel = np.einsum("nji,njk->nik", T[:-1, :3, :3], T[1:, :3, :3])
    dth = np.degrees(np.arccos(np.clip((np.trace(rel, axis1=1, axis2=2) - 1) / 2, -1, 1)))
    return {
        "mean_speed_mps": float(dp.mean() * fps), "max_speed_mps": float(dp.max() * fps),
        "mean_angular_dps": float(dth.mean() * fps), "max_angular_dps": float(dth.max() * fps),
        "mean_step_mm": float(dp.mean() * 1000), "max_step_mm": float(dp.max() * 1000),
    }
