"""Frames the teacher could not read: skipped, bridged by the longer edges, or the run stops.

A frame whose colour or depth image is missing, truncated or malformed (a
:class:`~data.errors.DataError` from the reader) is skipped with a warning unless the run is
``strict``: it takes its place in the stream (:meth:`teacher.window.EdgeWindow.skip`), so the
edges (i, j), j - i <= K, that would have started or ended at it are simply not estimated,
and those that jump over it (the frame before to the frame after: gap 2) bridge it. The
frame has no pose in the outputs (no vertex, no trajectory row); ``report.json`` lists it.
The ORB-SLAM3 backend does the same (:func:`teacher.orbslam3.run_orbslam3`: the frame is not
given to ORB-SLAM3, its edges fail with status ``unreadable``).

A frame whose ground-truth pose is unusable (non-finite) keeps its place: only the
evaluation against ground truth leaves it out (``groundtruth_dropped``).

A run of K or more consecutive unreadable frames cannot be bridged by any edge (the
trajectory would fall apart, or, at an end of the sequence, silently lose frames): the run
stops with one line naming them, as it does with fewer than two readable frames.
"""

from __future__ import annotations

import logging
from collections.abc import Iterable

import numpy as np
from numpy.typing import NDArray

from ctcvo.data.errors import DataError
from ctcvo.data.sequence import Sequence
from ctcvo.teacher.record import EdgeEstimate

log = logging.getLogger(__name__)


def runs_of(positions: Iterable[int]) -> list[list[int]]:
    """Consecutive runs of the sorted positions ``positions``."""
    runs: list[list[int]] = []
    for p in sorted(set(positions)):
        if runs and p == runs[-1][-1] + 1:
            runs[-1].append(p)
        else:
            runs.append([p])
    return runs


def unbridgeable(ids: NDArray[np.int64], run: list[int], gaps: int, why: str) -> DataError:
    """The error that stops a run at ``run`` (positions) of consecutive unreadable frames."""
    a, b = int(ids[run[0]]), int(ids[run[-1]])
    frames = f"frame {a}" if a == b else f"frames {a}..{b}"
    return DataError(f"{frames} ({len(run)} in a row) cannot be read, more than the longest edge (gap {gaps}) can "
                     f"bridge; the first: {why} (rerun with --frames to leave them out)")


def check(ids: NDArray[np.int64], skipped: dict[int, str], gaps: int) -> None:
    """Raise the :class:`DataError` that stops a run with the unreadable frames ``skipped``
    ({position: why}): a run of ``gaps`` or more in a row, or fewer than two readable frames."""
    for run in runs_of(skipped):
        if len(run) >= gaps:
            raise unbridgeable(ids, run, gaps, skipped[run[0]])
    if len(ids) - len(skipped) < 2:
        first = min(skipped)
        raise DataError(f"{len(skipped)} of {len(ids)} frames cannot be read, fewer than 2 are left; "
                        f"the first: {skipped[first]}")


def warn(name: str, ids: NDArray[np.int64], skipped: dict[int, str]) -> None:
    """One warning line per skipped frame of the sequence ``name``."""
    for p in sorted(skipped):
        log.warning("%s: frame %d skipped (no pose, the edges over it bridge it; --strict stops instead): %s",
                    name, int(ids[p]), skipped[p])


def check_groundtruth(seq: Sequence, strict: bool) -> None:
    """A frame with an unusable ground-truth pose: a :class:`DataError` with ``strict``, else
    one warning line (the teacher needs no ground truth; its evaluation leaves the frame out)."""
    dropped = seq.groundtruth_dropped()
    if strict and dropped:
        seq.groundtruth()  # raises, naming the first
    for d in dropped:
        log.warning("%s: frame %d left out of the evaluation (--strict stops instead): %s", seq.name, d["frame"], d["why"])


def report(ids: NDArray[np.int64], skipped: dict[int, str], edges: list[EdgeEstimate]) -> list[dict]:
    """``report.json``'s ``frames_skipped``: ``{frame, why, bridge}`` per skipped frame, the
    bridge the shortest good edge that jumps over it (``"edge A->B"``; ``None`` at either end
    of the sequence, where nothing needs a bridge, or when every one failed: the chained
    trajectory then crosses it by constant velocity, see ``bridges``)."""
    pos = {int(f): p for p, f in enumerate(ids)}
    good = sorted(((pos[e.j] - pos[e.i], e.i, e.j) for e in edges if e.ok), key=lambda t: t[0])
    out = []
    for p in sorted(skipped):
        over = next((f"edge {i}->{j}" for _, i, j in good if pos[i] < p < pos[j]), None)
        out.append({"frame": int(ids[p]), "why": skipped[p], "bridge": over})
    return out
