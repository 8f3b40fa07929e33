"""Loop closure over keyframes: place recognition, then geometric verification.

Place recognition is a cheap global descriptor: the keyframe's grey image shrunk to
:data:`_THUMB` pixels, blurred, zero-mean and unit-norm (as PTAM's small blurry image); two
keyframes look alike when the descriptors' correlation is at least :data:`LOOP_SCORE`. The
best :data:`LOOP_CANDIDATES` (:func:`loop_candidates`) are verified (:func:`verify`, by
:func:`teacher.keyframes.estimate_work`): the edge estimator
(:func:`teacher.odometry.estimate_edge`, exhaustive matching, PnP, refinement, dense step)
must pass with at least :data:`LOOP_MIN_INLIERS` PnP inliers, and the result must agree with
the chained poses within :data:`LOOP_GATE_M` / :data:`LOOP_GATE_DEG` (the drift a few
seconds' chaining can build up): a loop that passes matching between two different places
but would bend the trajectory by more is rejected (status ``loop_rejected``).
"""

from __future__ import annotations

import dataclasses

import cv2
import numpy as np
from numpy.typing import NDArray

from ctcvo.data import geometry as geo
from ctcvo.teacher.record import EdgeEstimate

_THUMB = (40, 30)  # width, height of the descriptor image
LOOP_SCORE = 0.8  # least correlation of two keyframes' descriptors; provisional
LOOP_CANDIDATES = 2  # candidates verified per keyframe
LOOP_MIN_INLIERS = 40  # least PnP inliers of a verified loop
LOOP_GATE_M = 0.3  # a loop edge may disagree with the chained poses this much (m) ...
LOOP_GATE_DEG = 15.0  # ... and this much (deg)


def thumbnail(rgb: NDArray[np.uint8]) -> NDArray[np.float64]:
    """The global descriptor of an image (see the module's docstring)."""
    g = cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY) if rgb.ndim == 3 else rgb
    t = cv2.GaussianBlur(cv2.resize(g, _THUMB, interpolation=cv2.INTER_AREA), (5, 5), 1.5).astype(np.float64)
    t -= t.mean()
    n = np.linalg.norm(t)
    return (t / n).ravel() if n > 0 else t.ravel()


def verify(e: EdgeEstimate, T_chain: NDArray[np.float64]) -> EdgeEstimate:
    """``e`` as a loop edge: kept when it passed with enough inliers and agrees with the
    chained motion ``T_chain`` within the gate; else marked ``loop_rejected``."""
    if not e.ok:
        return e
    if e.inliers >= LOOP_MIN_INLIERS and geo.agrees(T_chain, e.T_i_j, LOOP_GATE_M, LOOP_GATE_DEG):
        return e
    return dataclasses.replace(e, status="loop_rejected")


def loop_candidates(b: int, old: list[int], thumbs: dict[int, NDArray]) -> list[int]:
    """Place recognition: of the keyframes ``old`` (positions), the best
    :data:`LOOP_CANDIDATES` whose descriptor (``thumbs``) correlates with keyframe ``b``'s by
    at least :data:`LOOP_SCORE`, best first."""
    if not old:
        return []
    scores = np.array([float(thumbs[a] @ thumbs[b]) for a in old])
    out = []
    for o in np.argsort(-scores)[:LOOP_CANDIDATES]:
        if scores[o] < LOOP_SCORE:
            break
        out.append(old[o])
    return out
