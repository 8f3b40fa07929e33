"""Landmark sightings (``observations.csv``) for the pose graph's bundle adjustment.

Edges match keypoints between frames; their inlier matches, chained across edges, are
feature tracks: landmarks seen from several frames. Two sets of tracks, one per feature set:

* the keyframe and loop edges' (:mod:`teacher.keyframes`): landmarks seen from keyframes
  seconds apart, on the keyframes' own features;
* the window's gap-1 edges' (:mod:`teacher.window`): landmarks followed frame by frame, on
  every frame's features, as ORB-SLAM3 tracks each frame against its local map; each frame's
  :data:`WINDOW_TRACKS_PER_FRAME` longest. A gap-1 edge keeps its points only between frames
  whose images are both new (no repeat of one stream).

Each sighting is written with the point and depth the edge's estimate used (moved to the
frame's middle-row moment by the rolling shutter correction), as a normalised image point,
for :mod:`posegraph.bundle` to solve jointly with the edges. On fr3/teddy 0:200 (validation)
the window's tracks took the teacher graph from 4.45 / 6.84 / 2.60 to 4.25 / 6.55 / 2.39 mm
(ATE / 1 s / gap-1 RPE) over the keyframes' alone (every track, uncapped: 4.18 / 6.48 / 2.35;
:data:`WINDOW_TRACKS_PER_FRAME`). Uncapped, the window's tracks alone gave 4.55 / 6.90 /
2.41, and adding the longer window edges' matches merged more tracks into conflicts and
dropped them (4.21 / 6.57 / 2.38).

Written only where the colour camera is the depth camera (TUM RGB-D: registered colour):
there a keypoint's pixel is a pinhole projection of the depth camera the poses belong to.
With a separate colour camera (7-Scenes, the synthetic rooms) it passes through an
approximate colour model (:class:`data.sensor.ColourCamera`), and the bundle adjustment lost
on some such validation ranges (:mod:`posegraph.bundle`); the window's tracks lost on every
one (scratch, ATE / 1 s / gap-1 mm: synthetic/lab 0:300 6.6 / 4.4 / 1.27 -> 7.1 / 4.9 / 2.71,
redkitchen 0:450 24.0 / 21.7 / 3.71 -> 23.9 / 23.9 / 4.16, 350:450 13.5 / 22.6 / 4.44 -> 13.6
/ 22.8 / 4.92).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from ctcvo.data.sequence import Intrinsics
from ctcvo.teacher.features import FrameFeatures
from ctcvo.teacher.record import EdgeEstimate
from ctcvo.teacher.timing import middle_row_keypoints

#: a sighting's standard deviation (px) in x and y: ORB-SLAM3's at the finest ORB level
#: (1 px times 1.2 per level; the level is not kept); never varied
SIGHTING_SIGMA_PX = 1.0
#: a frame's window tracks: its sightings of the landmarks followed longest (most sightings)
#: are kept, the landmark with all its sightings, up to this many per frame. fr3/teddy 0:200
#: (validation; ATE / 1 s / gap-1 RPE mm, bundle seconds): 40 4.27 / 6.60 / 2.41, 0.31 s; 60
#: 4.25 / 6.55 / 2.39, 0.42 s; 80 4.24 / 6.53 / 2.37; every track 4.18 / 6.48 / 2.35, 0.54 s
#: (the keyframes' alone 4.44 / 6.85 / 2.60, 0.17 s). A frame's every track made the bundle
#: adjustment the batch command's largest cost after the teacher (fr1/xyz: 2.0 s, not 0.7); the
#: same cap over the keyframes' landmarks as well lost more (100: 4.41 / 6.65 / 2.37)
WINDOW_TRACKS_PER_FRAME = 60
#: keypoint indices below this per frame (features are at most a few thousand)
_KEY_BASE = 1 << 20


def attach_points(e: EdgeEstimate, fi: FrameFeatures, fj: FrameFeatures, intr: Intrinsics, cfg) -> EdgeEstimate:
    """``e`` with ``inlier_points``: for each of its inlier pairs the pixel and depth of the
    keypoint in i and in j, each moved to its frame's middle-row moment at the frame's own
    velocity (:func:`teacher.timing.middle_row_keypoints`; a keyframe's velocity is the same
    into and out of it, so a keypoint gets the same point in every edge); ``e`` unchanged
    without pairs."""
    if not e.ok or e.inlier_pairs is None or not len(e.inlier_pairs):
        return e
    (uv_i, z_i), (uv_j, z_j) = middle_row_keypoints(fi, "out", intr, cfg), middle_row_keypoints(fj, "in", intr, cfg)
    p, q = e.inlier_pairs[:, 0], e.inlier_pairs[:, 1]
    e.inlier_points = np.column_stack([uv_i[p], z_i[p], uv_j[q], z_j[q]]).astype(np.float64)
    return e


def run_sightings(keyframe_edges: list[EdgeEstimate], window_edges: list[EdgeEstimate],
                  intr: Intrinsics) -> NDArray[np.float64]:
    """``observations.csv``'s table of a run (``teacher generate``'s and online's alike): the
    keyframe and loop edges' tracks, then the window's gap-1 edges' (:func:`window_sightings`),
    :func:`merged`."""
    return merged(sightings(keyframe_edges, intr), window_sightings(window_edges, intr))


def window_sightings(edges: list[EdgeEstimate], intr: Intrinsics) -> NDArray[np.float64]:
    """The :func:`sightings` of the window's gap-1 edges, each frame's
    :data:`WINDOW_TRACKS_PER_FRAME` longest tracks (:func:`longest_tracks`)."""
    return longest_tracks(sightings(edges, intr), WINDOW_TRACKS_PER_FRAME)


def longest_tracks(table: NDArray[np.float64], per_frame: int) -> NDArray[np.float64]:
    """The rows of the landmarks that are among the ``per_frame`` most sighted of one of their
    frames (ties: the lower landmark id), every sighting of such a landmark kept."""
    if not len(table):
        return table
    lm, inv, counts = np.unique(table[:, 0], return_inverse=True, return_counts=True)
    order = np.lexsort((lm[inv], -counts[inv], table[:, 1]))  # by frame, longest first
    frame = table[order, 1]
    start = np.flatnonzero(np.r_[True, frame[1:] != frame[:-1]])
    rank = np.arange(len(order)) - np.repeat(start, np.diff(np.r_[start, len(order)]))
    keep = np.zeros(len(lm), bool)
    keep[inv[order[rank < per_frame]]] = True
    return table[keep[inv]]


def merged(*tables: NDArray[np.float64]) -> NDArray[np.float64]:
    """Observation tables of different feature sets as one: each table's landmarks renumbered
    after the ones before it, rows sorted by landmark, then frame."""
    out, base = [], 0
    for t in tables:
        t = np.asarray(t, dtype=np.float64).reshape(-1, 6).copy()
        t[:, 0] += base
        base = int(t[:, 0].max()) + 1 if len(t) else base
        out.append(t)
    table = np.concatenate(out) if out else np.zeros((0, 6))
    return table[np.lexsort((table[:, 1], table[:, 0]))]


def sightings(edges: list[EdgeEstimate], intr: Intrinsics) -> NDArray[np.float64]:
    """The observation table (:data:`data.formats.OBSERVATION_COLUMNS`) of the good edges'
    ``inlier_points``, edges over one feature set (keypoint indices name the same keypoint in
    every edge): one landmark per connected set of matched keypoints, left out where it
    holds two keypoints of one frame (a wrong match) or fewer than two sightings with depth."""
    keys, pts = [], []
    for e in edges:
        if not e.ok or e.inlier_pairs is None or e.inlier_points is None:
            continue
        keys.append(np.column_stack([e.i * _KEY_BASE + e.inlier_pairs[:, 0], e.j * _KEY_BASE + e.inlier_pairs[:, 1]]))
        pts.append(e.inlier_points)
    if not keys:
        return np.zeros((0, 6))
    pair_keys, pair_pts = np.concatenate(keys), np.concatenate(pts)
    nodes, idx = np.unique(pair_keys.ravel(), return_inverse=True)
    idx = idx.reshape(-1, 2)
    where = np.zeros((len(nodes), 3))
    where[idx[:, 0]], where[idx[:, 1]] = pair_pts[:, :3], pair_pts[:, 3:]
    n = len(nodes)
    _, label = connected_components(coo_matrix((np.ones(len(idx)), (idx[:, 0], idx[:, 1])), shape=(n, n)), directed=False)
    frame = nodes // _KEY_BASE
    has_depth = where[:, 2] > 0
    # one keypoint per frame and landmark: a set holding two of one frame is a wrong match
    span = int(frame.max()) + 1
    pair = np.unique(label.astype(np.int64) * span + frame)  # the (label, frame) pairs, as one key
    per_label = np.bincount(label, minlength=label.max() + 1)
    clean = per_label == np.bincount(pair // span, minlength=label.max() + 1)
    seen = np.bincount(label[has_depth], minlength=label.max() + 1)
    keep = has_depth & clean[label] & (seen[label] >= 2)
    landmark = np.unique(label[keep], return_inverse=True)[1]
    f = float(np.sqrt(intr.fx * intr.fy))
    table = np.column_stack([landmark, frame[keep], (where[keep, 0] - intr.cx) / intr.fx,
                             (where[keep, 1] - intr.cy) / intr.fy, where[keep, 2],
                             np.full(int(keep.sum()), SIGHTING_SIGMA_PX / f)])
    return table[np.lexsort((table[:, 1], table[:, 0]))]
