"""Self-calibration of a camera's radial lens distortion from its own RGB-D frames
(``ctcvo teacher calibrate``), for cameras whose distortion nobody published.

A pinhole teacher on a camera with unmodelled radial distortion bends every bearing away
from the image centre a little; over a window of gap 1..5 the error mostly cancels, but
edges reaching back seconds (keyframes, loops) see the same points at other radii and carry
a bias the pose graph cannot average out. One coefficient ``k1`` of OpenCV's model
(``x_d = x (1 + k1 r^2)``) is estimated:

1. frame pairs ``(k, k + g)`` for the gaps :data:`GAPS` every :data:`STRIDE` frames: ORB
   matches (cross-checked), colour keypoints moved into depth-camera pixels, the first
   frame's depth, PnP-RANSAC at ``k1 = 0`` choosing the inliers;
2. for each ``k1`` of :data:`GRID`, the first frame's keypoints are undistorted and
   back-projected, the pair's pose refitted (iterative PnP from the RANSAC pose, through
   the distortion), and the reprojection errors in raw pixels, truncated at
   :data:`TRUNCATE_PX`, summed over all pairs;
3. the best grid value, refined by a parabola through its neighbours.

Short gaps leave ``k1`` weakly constrained (any small systematic error projects onto it),
so the gaps are 0.3-1 s of motion. On the validation rooms lab and office (sensor model
``residual_distortion_k1`` 0.015) it measures 0.009-0.011 over 200-300 frames, on lab
rendered without distortion -0.002; a 70-frame walk reads about 0.02 high. Undistorting
with 0.009 takes the teacher graph's ATE on lab 0:200 from 10.1 to 5.9 mm and on office
0:200 from 11.8 to 3.5 mm. Not applied to real recordings: on fr3/teddy (published
undistorted) an estimate of 0.017 raised the graph's ATE from 8.0 to 8.8-9.3 mm.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Iterable
from pathlib import Path

import cv2
import numpy as np
from numpy.typing import NDArray

from ctcvo.data.errors import ConfigError, DataError
from ctcvo.data.runs import Fingerprint, claim, output_folder, scene_id, stage_dir
from ctcvo.data.scenes import open_scene
from ctcvo.data.sequence import Sequence
from ctcvo.data.undistort import write_camera

log = logging.getLogger(__name__)

#: frame gaps of the pairs (30 Hz: 0.33 to 1 s of motion)
GAPS = (10, 20, 30)
#: a pair starts every STRIDE frames
STRIDE = 2
#: the k1 values tried
GRID = np.linspace(-0.06, 0.06, 13)
#: reprojection errors are truncated here (pixels): matches PnP-RANSAC kept as inliers at 3 px
#: may be outliers at another k1
TRUNCATE_PX = 3.0
#: ORB features per frame, the least PnP inliers of a pair used, and the least depth (m)
ORB_FEATURES, MIN_INLIERS, MIN_DEPTH_M = 2000, 30, 0.3


class _Pair:
    """Inlier matches of a frame pair: first frame's depth-camera pixels and depths, the
    second's pixels, and the RANSAC pose (Rodrigues vector, translation)."""

    def __init__(self, uv_a: NDArray, z_a: NDArray, uv_b: NDArray, rvec: NDArray, tvec: NDArray) -> None:
        self.uv_a, self.z_a, self.uv_b, self.rvec, self.tvec = uv_a, z_a, uv_b, rvec, tvec


def _features(seq: Sequence, k: int, orb) -> tuple[NDArray, NDArray, NDArray] | None:
    """Depth-camera pixels (N, 2), their depths (N,) and ORB descriptors of frame ``k``."""
    rgb, depth = seq.rgb(k), seq.depth(k)
    kps, des = orb.detectAndCompute(cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY), None)
    if des is None or len(kps) < MIN_INLIERS:
        return None
    uv = np.array([p.pt for p in kps], np.float32)
    if seq.sensor.colour is not None:
        uv = seq.sensor.colour.to_depth_pixels(uv, depth, seq.intrinsics.K)
    h, w = depth.shape
    z = depth[np.clip(np.rint(uv[:, 1]).astype(np.int64), 0, h - 1), np.clip(np.rint(uv[:, 0]).astype(np.int64), 0, w - 1)]
    return uv.astype(np.float64), z.astype(np.float64), des


def _pair(fa, fb, K: NDArray, matcher) -> _Pair | None:
    matches = matcher.match(fa[2], fb[2])
    ia = np.array([m.queryIdx for m in matches], np.int64)
    ib = np.array([m.trainIdx for m in matches], np.int64)
    if len(ia) == 0:
        return None
    keep = fa[1][ia] > MIN_DEPTH_M
    ia, ib = ia[keep], ib[keep]
    if len(ia) < MIN_INLIERS:
        return None
    uv_a, z_a, uv_b = fa[0][ia], fa[1][ia], fb[0][ib]
    X = _back_project((uv_a - K[:2, 2]) / K[[0, 1], [0, 1]], z_a)
    ok, rvec, tvec, inl = cv2.solvePnPRansac(X, uv_b, K, None, reprojectionError=TRUNCATE_PX, iterationsCount=200)
    if not ok or inl is None or len(inl) < MIN_INLIERS:
        return None
    inl = inl.ravel()
    return _Pair(uv_a[inl], z_a[inl], uv_b[inl], rvec, tvec)


def _back_project(xy: NDArray, z: NDArray) -> NDArray:
    return np.c_[xy, np.ones(len(xy))] * z[:, None]


def collect_pairs(seqs: Iterable[Sequence]) -> tuple[list[_Pair], NDArray]:
    """The inlier matches of every pair of every sequence, and their common camera matrix."""
    orb = cv2.ORB_create(ORB_FEATURES)
    matcher = cv2.BFMatcher(cv2.NORM_HAMMING, crossCheck=True)
    pairs, K = [], None
    for seq in seqs:
        if K is not None and not np.array_equal(K, seq.intrinsics.K):
            raise ConfigError(f"{seq.name}: another camera matrix than the first sequence's; calibrate one camera "
                              "at a time")
        K = seq.intrinsics.K
        feats: dict[int, tuple | None] = {}
        for g in GAPS:
            for a in range(0, len(seq) - g, STRIDE):
                for k in (a, a + g):
                    if k not in feats:
                        try:
                            feats[k] = _features(seq, k, orb)
                        except DataError as e:
                            log.warning("%s", e)
                            feats[k] = None
                if feats[a] is not None and feats[a + g] is not None:
                    p = _pair(feats[a], feats[a + g], K, matcher)
                    if p is not None:
                        pairs.append(p)
    return pairs, K


def reprojection_cost(pairs: list[_Pair], K: NDArray, k1: float) -> float:
    """Mean truncated squared reprojection error (px^2) of all pairs with distortion ``k1``,
    measured in raw pixels: the first frame's keypoints are undistorted and back-projected,
    the pose refitted, and the points projected through the distortion into the second
    frame (errors measured between undistorted points would shrink with ``k1`` itself)."""
    D = np.array([k1, 0.0, 0.0, 0.0, 0.0])
    total, count = 0.0, 0
    for p in pairs:
        X = _back_project(cv2.undistortPoints(p.uv_a.reshape(-1, 1, 2), K, D).reshape(-1, 2), p.z_a)
        _, rvec, tvec = cv2.solvePnP(X, p.uv_b, K, D, p.rvec.copy(), p.tvec.copy(), useExtrinsicGuess=True)
        proj, _ = cv2.projectPoints(X, rvec, tvec, K, D)
        err = np.minimum(np.linalg.norm(proj.reshape(-1, 2) - p.uv_b, axis=1), TRUNCATE_PX)
        total += float(np.sum(err ** 2))
        count += len(err)
    return total / max(count, 1)


def estimate_k1(seqs: Iterable[Sequence]) -> dict:
    """The radial coefficient ``k1`` of the sequences' common camera, with what it rests on:
    ``pairs``, ``cost_px2`` per grid value, and ``gain`` (the cost's fall from ``k1 = 0``)."""
    t0 = time.perf_counter()
    pairs, K = collect_pairs(seqs)
    if len(pairs) < 10:
        raise DataError(f"only {len(pairs)} frame pairs {GAPS} frames apart matched; calibration needs at least 10 "
                        "(longer sequences, or frames with more texture and depth)")
    costs = np.array([reprojection_cost(pairs, K, k) for k in GRID])
    i = int(np.argmin(costs))
    if i in (0, len(GRID) - 1):
        raise DataError(f"the distortion's best value lies at the end of the range tried ({GRID[i]:+.3f}): "
                        "this is not a camera with mild radial distortion")
    a, b, c = costs[i - 1: i + 2]
    k1 = float(GRID[i] + 0.5 * (a - c) / (a - 2 * b + c) * (GRID[1] - GRID[0]))
    zero = costs[len(GRID) // 2]
    return {"k1": k1, "pairs": len(pairs), "gain": float((zero - costs.min()) / zero),
            "grid": [float(g) for g in GRID], "cost_px2": [float(x) for x in costs],
            "seconds": time.perf_counter() - t0}


def calibrate(scenes: list[str], frames: list[str | None], out: Path | None = None, overwrite: bool = False) -> Path:
    """``ctcvo teacher calibrate``: estimate ``k1`` on the frames of ``scenes`` (``frames``:
    one range for all, or one per scene) and write the camera file ``out`` (default:
    ``runs/<first scene>/camera/camera.json``). A camera file of the same inputs is kept."""
    if len(frames) not in (1, len(scenes)):
        raise ConfigError(f"--frames given {len(frames)} times for {len(scenes)} scenes: give it once or per --scene")
    frames = frames * len(scenes) if len(frames) == 1 else frames
    out = Path(out) if out is not None else stage_dir(scenes[0], "camera") / "camera.json"
    fp = Fingerprint("camera", {"scenes": [scene_id(s) for s in scenes], "frames": list(frames),
                                "estimator": {"gaps": list(GAPS), "stride": STRIDE, "truncate_px": TRUNCATE_PX}})
    with output_folder(out.parent):
        if claim(out.parent, fp, done=out.is_file(), has_outputs=out.is_file(), overwrite=overwrite,
                 outputs=(out.name,), inside=out.name):
            log.info("camera file of the same inputs in %s: kept", out)
            return out
        seqs = [s for spec, fr in zip(scenes, frames) for s in open_scene(spec, frames=fr)]
        if any(s.undistortion is not None for s in seqs):
            raise ConfigError("a scene's reader already undistorts its frames (a published or camera.txt distortion)")
        fit = estimate_k1(seqs)
        write_camera(out, seqs[0].intrinsics, (fit["k1"], 0.0, 0.0, 0.0, 0.0),
                     {"calibration": {**fit, "scenes": scenes, "frames": frames}, "fingerprint": fp.to_dict()})
    log.info("k1 %+.4f from %d frame pairs (reprojection cost %.2f %% below k1 = 0): %s", fit["k1"], fit["pairs"],
             100 * fit["gain"], out)
    return out
