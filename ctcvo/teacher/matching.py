"""ORB matching between two frames: guided by a motion prediction, exhaustive, and the wide fallback."""

from __future__ import annotations

import cv2
import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from ctcvo.data import geometry as geo
from ctcvo.teacher.features import FrameFeatures, backproject, project

# 'the validation ranges': redkitchen 350:450 and synthetic/lab 0:150 (bench/README.md, seventh session)
RATIO = 0.85  # Lowe ratio test; set by hand (fa44eca); kept against 0.75 and 0.95 on the validation ranges
SEARCH_RADIUS_PX = 12.0  # guided matching radius; set by hand (fa44eca); kept against 8 and 20 on the validation ranges
MAX_HAMMING = 64  # of 256 bits; set by hand (fa44eca); kept against 48 and 80 on the validation ranges
FALLBACK_RADIUS_SCALE = 3.0  # wide matching radius / SEARCH_RADIUS_PX; a priori (b8a2c06): a ~3 deg sudden turn
#: guided matching drops candidate pairs this far apart (bits) before it sorts them, which
#: changes no match: such a pair is never a match (> MAX_HAMMING); as an i's second best it
#: passes the ratio test for any best <= MAX_HAMMING, as no second best does (MAX_HAMMING <
#: RATIO * this); and the best i of a j this far from it matches no i either
_IRRELEVANT_HAMMING = int(MAX_HAMMING / RATIO) + 1

def match(fi: FrameFeatures, fj: FrameFeatures,
          T_i_j_pred: NDArray | None = None, K: NDArray | None = None) -> NDArray[np.int64]:
    """Mutual-nearest ORB matches passing the ratio test: (M, 2) index pairs (into i, into j).

    Only keypoints of frame i with a valid depth take part. With a motion prediction
    ``T_i_j_pred`` (and ``K``), each is compared only with the keypoints of frame j within
    ``SEARCH_RADIUS_PX`` of its predicted position (guided matching, as ORB-SLAM's
    search by projection); without one, with all of them.
    """
    src = np.flatnonzero(fi.z > 0)
    if len(src) < 2 or len(fj.desc) < 2:
        return np.zeros((0, 2), np.int64)
    if T_i_j_pred is None:
        return _match_exhaustive(fi, fj, src)
    P = backproject(np.take(fi.uv, src, axis=0), fi.z[src], K)
    Tji = geo.inv_T(T_i_j_pred)
    Y = P @ Tji[:3, :3].T + Tji[:3, 3]
    front = Y[:, 2] > 1e-3
    src = src[front]
    pred = project(np.compress(front, Y, axis=0), K)
    near = cKDTree(pred).sparse_distance_matrix(fj.tree(), SEARCH_RADIUS_PX, output_type="ndarray")
    if len(near) == 0:
        return np.zeros((0, 2), np.int64)
    qi, cj = src[near["i"]], near["j"].astype(np.int64)
    x = np.take(fi.desc64, qi, axis=0)  # np.take: 4 times faster than fancy indexing here
    x ^= np.take(fj.desc64, cj, axis=0)
    d = np.add.reduce(np.bitwise_count(x), axis=1, dtype=np.int64)
    # pairs at _IRRELEVANT_HAMMING or more change no result (see there): most candidates are
    # unrelated keypoints (~128 bits apart), so the sorts below see a fraction of them
    near_enough = d < _IRRELEVANT_HAMMING
    qi, cj, d = qi[near_enough], cj[near_enough], d[near_enough]
    if len(d) == 0:
        return np.zeros((0, 2), np.int64)
    # best and second best in j for each i (one sort on the key (i, distance); d < 512)
    o = _stable_argsort((qi << 9) | d)
    qi_s, cj_s, d_s = qi[o], cj[o], d[o]
    first = np.flatnonzero(np.r_[True, qi_s[1:] != qi_s[:-1]])
    has2 = np.r_[first[1:], len(qi_s)] - first >= 2
    second = np.where(has2, d_s[np.minimum(first + 1, len(d_s) - 1)], 256)
    best_i, best_j, best_d = qi_s[first], cj_s[first], d_s[first]
    ok = (best_d <= MAX_HAMMING) & (best_d < RATIO * second)
    # mutual check: the best i for each j among the compared pairs
    o2 = _stable_argsort((cj << 9) | d)
    cj2, qi2 = cj[o2], qi[o2]
    first2 = np.flatnonzero(np.r_[True, cj2[1:] != cj2[:-1]])
    back = np.full(len(fj.desc), -1, np.int64)
    back[cj2[first2]] = qi2[first2]
    ok &= back[best_j] == best_i
    return np.stack([best_i[ok], best_j[ok]], axis=1)


def _stable_argsort(key: NDArray[np.int64]) -> NDArray[np.int64]:
    """``np.argsort(key, kind="stable")`` for non-negative int64 keys, as an unstable sort of
    keys made unique by their position in the low bits (the same order: ties keep their
    order). NumPy sorts int64 with timsort when stable and with a SIMD quicksort otherwise:
    on guided matching's ~9,000 candidates 0.3 instead of 0.5-2.7 ms."""
    n = len(key)
    bits = max(n.bit_length(), 1)
    if n == 0 or int(key.max()) >= 1 << (62 - bits):
        return np.argsort(key, kind="stable")
    return np.argsort((key << bits) | np.arange(n, dtype=np.int64))


def match_wide(fi: FrameFeatures, fj: FrameFeatures,
               T_i_j_pred: NDArray | None = None, K: NDArray | None = None) -> NDArray[np.int64]:
    """Fallback matching (``cfg.fallback_wide``): cross-checked nearest neighbours (each the
    other's best) within ``MAX_HAMMING``, without the ratio test. With a motion prediction,
    candidates lie within ``FALLBACK_RADIUS_SCALE * SEARCH_RADIUS_PX`` of the predicted
    position; without one, all keypoints of frame j (OpenCV's brute-force cross-check).
    Repeated or low-contrast texture gives close best and second-best distances, which the
    ratio test discards; RANSAC then sorts the right matches from the wrong ones."""
    src = np.flatnonzero(fi.z > 0)
    if len(src) < 2 or len(fj.desc) < 2:
        return np.zeros((0, 2), np.int64)
    if T_i_j_pred is None:
        ms = cv2.BFMatcher(cv2.NORM_HAMMING, crossCheck=True).match(fi.desc[src], fj.desc)
        p = np.array([(src[m.queryIdx], m.trainIdx) for m in ms if m.distance <= MAX_HAMMING],
                     np.int64).reshape(-1, 2)
        return p
    P = backproject(fi.uv[src], fi.z[src], K)
    Tji = geo.inv_T(T_i_j_pred)
    Y = P @ Tji[:3, :3].T + Tji[:3, 3]
    src = src[Y[:, 2] > 1e-3]
    pred = project(Y[Y[:, 2] > 1e-3], K)
    near = cKDTree(pred).sparse_distance_matrix(fj.tree(), FALLBACK_RADIUS_SCALE * SEARCH_RADIUS_PX,
                                                output_type="ndarray")
    if len(near) == 0:
        return np.zeros((0, 2), np.int64)
    qi, cj = src[near["i"]], near["j"].astype(np.int64)
    d = np.bitwise_count(fi.desc64[qi] ^ fj.desc64[cj]).sum(axis=1, dtype=np.int64)
    o = np.argsort((qi << 9) | d, kind="stable")  # best j of each i
    first = np.flatnonzero(np.r_[True, qi[o][1:] != qi[o][:-1]])
    best_i, best_j, best_d = qi[o][first], cj[o][first], d[o][first]
    o2 = np.argsort((cj << 9) | d, kind="stable")  # best i of each j
    first2 = np.flatnonzero(np.r_[True, cj[o2][1:] != cj[o2][:-1]])
    back = np.full(len(fj.desc), -1, np.int64)
    back[cj[o2][first2]] = qi[o2][first2]
    ok = (best_d <= MAX_HAMMING) & (back[best_j] == best_i)
    return np.stack([best_i[ok], best_j[ok]], axis=1)


def _match_exhaustive(fi: FrameFeatures, fj: FrameFeatures, src: NDArray[np.int64]) -> NDArray[np.int64]:
    """Brute-force mutual-nearest + ratio-test matching of keypoints ``src`` of frame i."""
    bf = cv2.BFMatcher(cv2.NORM_HAMMING)
    di = fi.desc[src]
    fwd = bf.knnMatch(di, fj.desc, k=2)
    back = np.full(len(fj.desc), -1, np.int64)
    for m in bf.match(fj.desc, di):
        back[m.queryIdx] = m.trainIdx
    pairs = [(a.queryIdx, a.trainIdx) for a, b in (ms for ms in fwd if len(ms) == 2)
             if a.distance <= MAX_HAMMING and a.distance < RATIO * b.distance
             and back[a.trainIdx] == a.queryIdx]
    p = np.array(pairs, dtype=np.int64).reshape(-1, 2)
    p[:, 0] = src[p[:, 0]]
    return p

