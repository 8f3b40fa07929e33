"""Bundle adjustment: landmark sightings solved jointly with the pose graph's edges.

The teacher's ``observations.csv`` (docs/formats.md) holds, for a sensor whose colour is
registered to its depth (TUM RGB-D), every sighting of a landmark (a feature track through
the keyframe and loop edges' inlier matches, or through the window's gap-1 edges'): the
normalised image point ``(x, y)`` and the depth ``z`` there. An edge is one pairwise estimate;
a landmark seen from five frames ties all five together, as ORB-SLAM3's local bundle
adjustment ties its keyframes and its tracking ties each frame to the local map.

Each sighting is ORB-SLAM3's RGB-D factor: a stereo measurement ``(x, x - b / z, y)`` of a
virtual stereo camera of baseline ``b`` (:data:`VIRTUAL_BASELINE_M`), ``sigma`` on each
coordinate, so that the depth's weight falls with ``z^2`` like a Kinect's disparity noise;
under a Huber kernel at ORB-SLAM3's stereo threshold (:data:`HUBER_K`). The joint solve
starts from the pose graph's solution, with the edges it kept at the scales it calibrated,
each landmark at its first sighting's back-projection.

Record ``keyframes`` (validation; ATE / 1 s / gap-1 RPE, mm): on fr3/teddy the teacher graph
goes from 4.9 / 7.3 / 2.64 to 4.5 / 6.8 / 2.60 with the keyframes' tracks (the window's
add more: :mod:`teacher.observations`). With a separate colour camera it does not
help everywhere (variant "bundle, any colour camera": redkitchen 0:450's 1 s RPE 21.7 ->
23.7, synthetic/lab's ATE 6.6 -> 7.2, redkitchen 350:450 and office level or better), so the
teacher writes no sightings there (:mod:`teacher.observations`). The virtual baseline and the
kernel are ORB-SLAM3's, never varied; the sightings' sigma is ORB-SLAM3's finest level's.
"""

from __future__ import annotations

import math
import time

import gtsam
import numpy as np
from numpy.typing import NDArray

from ctcvo.posegraph.solvers import run_lm

#: virtual stereo baseline (m) of the RGB-D factor: ORB-SLAM3's ``Camera.bf`` (40 px m in
#: TUM1.yaml, the value our ORB-SLAM3 peer runs with) over fr1's fx (517.3 px); never varied
VIRTUAL_BASELINE_M = 40.0 / 517.3
#: Huber width on a sighting's whitened residual: ORB-SLAM3's stereo outlier threshold,
#: sqrt of chi-square(3)'s 95 % quantile (7.815)
HUBER_K = math.sqrt(7.815)
#: a landmark enters with at least this many sightings among the graph's frames: one seen by
#: two keyframes repeats the matches of the edge between them, already in the graph; on
#: fr3/teddy 2 gave the same figures (within 0.05 mm) at twice the landmarks and time
MIN_SIGHTINGS = 3
#: the joint solve stops once an iteration lowers the error by less than this fraction, or
#: after MAX_ITERATIONS: it starts at the pose graph's solution (fr3/teddy: converged after 3
#: iterations, figures within 0.02 mm of 1e-6's 9 iterations, 0.16 against 0.42 s), as
#: ORB-SLAM3's local bundle adjustment runs a fixed few
RELATIVE_ERROR_TOL = 1e-3
MAX_ITERATIONS = 3


def usable(table: NDArray[np.float64], frame_ids: NDArray[np.int64]) -> NDArray[np.float64]:
    """The rows of an observation table (:func:`data.formats.read_observations`) whose frame
    is one of ``frame_ids`` and whose landmark keeps :data:`MIN_SIGHTINGS` such rows."""
    t = np.asarray(table, dtype=np.float64).reshape(-1, 6)
    t = t[np.isin(t[:, 1].astype(np.int64), np.asarray(frame_ids))]
    lm, counts = np.unique(t[:, 0], return_counts=True)
    return t[np.isin(t[:, 0], lm[counts >= MIN_SIGHTINGS])]


def sighting_factors(table: NDArray[np.float64], poses: dict[int, NDArray[np.float64]]) -> tuple[list, gtsam.Values]:
    """One ``GenericStereoFactor3D`` per row of a :func:`usable` table, and the landmarks'
    start values (their first sighting's point in the world, ``poses``: ``T_world_cam`` by
    frame id). Landmark ``l``'s key is ``gtsam.symbol('l', l)``; frames keep their ids."""
    cal = gtsam.Cal3_S2Stereo(1.0, 1.0, 0.0, 0.0, 0.0, VIRTUAL_BASELINE_M)
    models: dict[float, object] = {}
    keys = [gtsam.symbol("l", int(lm)) for lm in table[:, 0]]
    factors = []
    for key, (fr, x, y, z, s) in zip(keys, table[:, 1:].tolist()):
        model = models.get(s)
        if model is None:
            model = models[s] = gtsam.noiseModel.Robust.Create(
                gtsam.noiseModel.mEstimator.Huber.Create(HUBER_K), gtsam.noiseModel.Isotropic.Sigma(3, s))
        factors.append(gtsam.GenericStereoFactor3D(gtsam.StereoPoint2(x, x - VIRTUAL_BASELINE_M / z, y), model,
                                                   int(fr), key, cal))
    _, first = np.unique(table[:, 0], return_index=True)
    T = np.stack([poses[int(f)] for f in table[first, 1]])
    x, y, z = table[first, 2], table[first, 3], table[first, 4]
    world = np.einsum("nij,nj->ni", T[:, :3, :3], np.stack([x * z, y * z, z], axis=1)) + T[:, :3, 3]
    values = gtsam.Values()
    for n, X in zip(first.tolist(), world):
        values.insert(keys[n], X)
    return factors, values


def bundle_solve(graph, result, table: NDArray[np.float64], frame_ids: NDArray[np.int64],
                 poses: NDArray[np.float64]) -> tuple[object, object, dict]:
    """The pose graph ``graph`` solved at ``result`` (``poses`` (N, 4, 4) its poses of the
    sorted ``frame_ids``) again, with the sightings of ``table`` that :func:`usable` keeps:
    (joint graph, joint result, a report of landmarks, sightings, iterations and seconds).
    Without any usable sighting the graph and result come back as they are."""
    t0 = time.perf_counter()
    rows = usable(table, frame_ids)
    report = {"landmarks": int(len(np.unique(rows[:, 0]))), "sightings": int(len(rows)), "iterations": 0}
    if not len(rows):
        return graph, result, {**report, "seconds": 0.0}
    factors, landmarks = sighting_factors(rows, {int(k): T for k, T in zip(np.asarray(frame_ids).tolist(), poses)})
    joint = gtsam.NonlinearFactorGraph(graph)
    for f in factors:
        joint.add(f)
    start = gtsam.Values(result)
    start.insert(landmarks)
    out, iters = run_lm(joint, start, RELATIVE_ERROR_TOL, MAX_ITERATIONS)
    return joint, out, {**report, "iterations": iters, "seconds": time.perf_counter() - t0}


__all__ = ["HUBER_K", "MAX_ITERATIONS", "MIN_SIGHTINGS", "RELATIVE_ERROR_TOL", "VIRTUAL_BASELINE_M", "bundle_solve",
           "sighting_factors", "usable"]
