"""The pose graph frame by frame: GTSAM's ISAM2 over the frames as they arrive, reviewed
(covariance scales per edge source, outlier edges) by the rules of ``posegraph optimize``
(:mod:`posegraph.graph`), and finished by its batch solve. Used by the
online pipeline (pipeline/online.py, ``ctcvo online``); imports neither the learner nor the teacher.
"""

from __future__ import annotations

import dataclasses
import logging
import time
from collections.abc import Sequence

import gtsam
import numpy as np
from numpy.typing import NDArray

from ctcvo.data import geometry as geo
from ctcvo.posegraph.config import ONLINE, PoseGraphConfig
from ctcvo.posegraph.edges import GraphError, edge_residuals
from ctcvo.posegraph.factors import between_factors, gtsam_error, prior_factor
from ctcvo.posegraph.graph import solve
from ctcvo.posegraph.robust import (
    CALIBRATION_SCALE_RANGE,
    CALIBRATION_TOLERANCE,
    DOWNWEIGHT_FACTOR,
    outlier_masks,
    source_scale_factors,
)
from ctcvo.posegraph.solvers import ISAM2_FINAL_UPDATES, isam2

log = logging.getLogger(__name__)


class OnlineGraph:
    """ISAM2 over frame ids: a prior fixes the first pose at the identity; each new pose
    starts at its prediction through its shortest good edge (else constant velocity, as
    the teacher's chained trajectory) and enters with its edges.

    The graph is reviewed as ``posegraph optimize`` reviews it - covariance scale per
    edge source (:func:`posegraph.robust.source_scale_factors`: median squared whitened residual
    against chi-square(6), corrected for the graph's redundancy) and outlier edges
    (:func:`posegraph.robust.outlier_masks`) - online: when it reaches ``review_from`` frames,
    at every doubling after that, and at the end until nothing changes. Factors whose scale
    or status changed are swapped in one ISAM2 update (log2(N) reviews over a run, so the
    cost stays amortised), so the robust kernel sees the residuals at the scale the batch
    solve sees them."""

    def __init__(self, cfg: PoseGraphConfig | None = None, review_from: int = 16) -> None:
        self.cfg = cfg or ONLINE
        self.isam = isam2()
        self.ids: list[int] = []
        self.pos: dict[int, int] = {}
        self.latest: dict[int, NDArray[np.float64]] = {}
        self.v_prev = np.eye(4)
        self.edges: list = []  # data.formats.Edge in the graph
        self.slots: list[int] = []  # ISAM2 factor index of each edge
        self.sources: list[str] = []
        self.status = np.zeros(0, np.int64)  # per edge: 0 in the graph, 1 down-weighted, 2 removed
        self.scale: dict[str, float] = {}
        self.next_review = review_from
        self.reviews = 0
        self.live: dict[int, object] = {}  # ISAM2 factor index -> factor, of the factors in the graph
        self.polish: dict | None = None

    def _edge_factors(self, edges: list, weak: NDArray[np.bool_] | None = None) -> list:
        """Robust factors of ``edges`` under the current source scales (``weak``: times
        ``DOWNWEIGHT_FACTOR``), built by :func:`posegraph.factors.between_factors`."""
        if not edges:
            return []
        ids = np.array([[e.i, e.j] for e in edges], dtype=np.int64)
        meas = [geo.to_gtsam_pose3(geo.orthonormalize(e.T_i_j)) for e in edges]
        mult = np.array([self.scale.get(e.extra.get("source", ""), 1.0) for e in edges])
        if weak is not None:
            mult = mult * np.where(weak, DOWNWEIGHT_FACTOR, 1.0)
        covs = np.stack([e.cov for e in edges]) * mult[:, None, None]
        return between_factors(ids, meas, covs, self.cfg.kernel)

    def add(self, frame_id: int, edges: list) -> NDArray[np.float64]:
        """Add frame ``frame_id`` with its ``data.formats.Edge`` list (edges (i, frame_id),
        i already in the graph; ``edge.extra["source"]`` names the source); return its
        current estimate ``T_world_cam``."""
        graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
        if not self.ids:
            T0 = np.eye(4)
            graph.add(prior_factor(frame_id, T0))
        else:
            prev = self.ids[-1]
            best = max(edges, key=lambda e: self.pos[e.i], default=None)  # the shortest gap
            if best is not None:
                T0 = self.latest[best.i] @ best.T_i_j
                if best.i == prev:
                    self.v_prev = best.T_i_j
            else:
                T0 = self.latest[prev] @ self.v_prev
                log.debug("frame %d: no edge, placed by constant velocity", frame_id)
                # an unconnected pose needs a factor: the constant-velocity guess, weakly
                graph.add(gtsam.BetweenFactorPose3(prev, frame_id, geo.to_gtsam_pose3(self.v_prev),
                                                   gtsam.noiseModel.Diagonal.Sigmas(np.full(6, 0.1))))
        values.insert(int(frame_id), geo.to_gtsam_pose3(T0))
        self._insert(graph, values, edges)
        self.pos[int(frame_id)] = len(self.ids)
        self.ids.append(int(frame_id))
        if len(self.ids) >= self.next_review:
            self.next_review *= 2
            self._review()
        self._refresh_latest()
        return self.latest[int(frame_id)]

    def add_edges(self, edges: list) -> None:
        """Add edges between poses already in the graph (``data.formats.Edge``; e.g.
        ``vo-online``'s longer teacher edges of the newest frame, estimated after its pose
        was written) in one ISAM2 update."""
        if not edges:
            return
        self._insert(gtsam.NonlinearFactorGraph(), gtsam.Values(), edges)
        self._refresh_latest()

    def _insert(self, graph, values, edges: list) -> None:
        """One ISAM2 update with ``graph`` and ``values`` plus the factors of ``edges``
        (added after the factors ``graph`` holds); records the edges and their factor slots."""
        first_edge = graph.size()
        for f in self._edge_factors(edges):
            graph.add(f)
        all_slots = list(self._update(graph, values).getNewFactorsIndices())
        self.live.update({int(k): graph.at(n) for n, k in enumerate(all_slots)})
        self.edges += edges
        self.slots += all_slots[first_edge:]
        self.status = np.concatenate([self.status, np.zeros(len(edges), np.int64)])

    def _refresh_latest(self) -> None:
        """Refresh the newest estimates (the anchors of the next predictions)."""
        for k in self.ids[-8:]:
            self.latest[k] = geo.from_gtsam_pose3(self.isam.calculateEstimatePose3(k))

    def _update(self, graph, values, remove: Sequence[int] = ()):
        try:
            return self.isam.update(graph, values, list(remove))
        except RuntimeError as exc:
            raise gtsam_error(exc) from None

    def poses(self) -> NDArray[np.float64]:
        """(N, 4, 4) current estimate of every pose."""
        est = self.isam.calculateEstimate()
        return np.stack([geo.from_gtsam_pose3(est.atPose3(k)) for k in self.ids])

    def _review(self, poses: NDArray[np.float64] | None = None) -> bool:
        """Re-estimate the per-source covariance scales and the outlier edges as ``posegraph
        optimize`` does (whitened residual above ``cfg.residual_threshold`` under the new
        scales: removed, or down-weighted where removal would disconnect the graph); swap
        the factors whose scale or status changed. Returns whether anything changed."""
        if not self.edges:
            return False
        names = list(dict.fromkeys(e.extra.get("source", "") for e in self.edges))
        src = np.array([names.index(e.extra.get("source", "")) for e in self.edges])
        pos = np.array([[self.pos[e.i], self.pos[e.j]] for e in self.edges], dtype=np.int64)
        T = np.stack([e.T_i_j for e in self.edges])
        scale = np.array([self.scale.get(n, 1.0) for n in names])
        info = np.linalg.inv(np.stack([e.cov for e in self.edges]) * scale[src, None, None])
        res = edge_residuals(self.poses() if poses is None else poses, pos, T, info)
        new = scale
        if self.cfg.calibrate:
            redundancy = 1.0 - (len(self.ids) - 1) / max(len(self.edges), 1)
            # over every edge, flagged ones included (robust median), as the batch solve does
            factor, _ = source_scale_factors(res, src, len(names), redundancy)
            new = np.clip(scale * factor, *CALIBRATION_SCALE_RANGE)
            moved = np.abs(np.log(new / scale)) > np.log1p(CALIBRATION_TOLERANCE)
            new = np.where(moved, new, scale)
        res = res * np.sqrt(scale / new)[src]  # under the new scales
        flagged = res > self.cfg.residual_threshold
        drop, weak = outlier_masks(len(self.ids), pos, flagged, np.argsort(res))
        status = np.where(drop, 2, np.where(weak, 1, 0))
        changed = np.flatnonzero((status != self.status) | (new != scale)[src])
        if len(changed) == 0:
            return False
        self.scale.update({n: float(v) for n, v in zip(names, new)})
        remove = [self.slots[n] for n in changed if self.slots[n] >= 0]
        add = [n for n in changed if status[n] != 2]
        graph = gtsam.NonlinearFactorGraph()
        for f in self._edge_factors([self.edges[n] for n in add], status[add] == 1):
            graph.add(f)
        res_u = self._update(graph, gtsam.Values(), remove)
        for n in changed:
            self.live.pop(int(self.slots[n]), None)
            self.slots[n] = -1
        for m, (n, slot) in enumerate(zip(add, res_u.getNewFactorsIndices())):
            self.slots[n] = int(slot)
            self.live[int(slot)] = graph.at(m)
        self.status = status
        self.reviews += 1
        log.debug("frame %d: covariance scales %s, %d outlier edges", self.ids[-1], self.scale, int(flagged.sum()))
        return True

    def final(self, polish: bool = True, observations: NDArray[np.float64] | None = None) -> NDArray[np.float64]:
        """(N, 4, 4) smoothed poses. A last review and ``ISAM2_FINAL_UPDATES`` ISAM2
        updates give the ISAM2 estimate (kept in ``isam2_poses``); with ``polish`` the
        batch solve of ``posegraph optimize`` (:func:`posegraph.graph.solve`, LM, its
        covariance calibration and outlier pass from scratch, the bundle adjustment of the
        landmark ``observations`` when given) then runs on the same edges,
        warm-started from it.

        Why the polish: with the robust kernel ISAM2's Gauss-Newton steps stop at a higher
        cost than LM reaches on the same factors (synthetic/tiny, Huber, no calibration:
        945 vs 886, ATE 15.8 vs 14.1 mm; the project's batch ``--solver isam2`` stops there
        too), and more updates or a zero relinearisation threshold do not move it; and the
        reviews made online on partial graphs can settle on other outliers than the batch
        pass. One solve at the end costs what ``posegraph optimize`` costs (bench/README.md,
        "Online mode")."""
        try:
            self._review()
            for _ in range(ISAM2_FINAL_UPDATES):
                self._update(gtsam.NonlinearFactorGraph(), gtsam.Values())
        except GraphError as exc:  # seen once on synthetic/tiny with a learner, not reproducibly
            log.warning("ISAM2's last updates stopped (%s); the batch solve starts from ISAM2's last estimate", exc)
        self.isam2_poses = self.poses()
        if not polish or len(self.ids) < 2 or not self.edges:
            return self.isam2_poses
        t0 = time.perf_counter()
        try:
            res = solve(np.array(self.ids, dtype=np.int64), self.edges, self.isam2_poses,
                        dataclasses.replace(self.cfg, solver="lm"), label="final batch solve", observations=observations)
        except GraphError as exc:  # e.g. a frame no edge reaches: keep the ISAM2 estimate
            log.warning("final batch solve skipped (%s); the ISAM2 estimate is the final trajectory", exc)
            return self.isam2_poses
        order = np.argsort(np.argsort(np.array(self.ids)))  # solve sorts by id
        self.polish = {"seconds": time.perf_counter() - t0, "iterations": res.iterations,
                       "outliers": len(res.outliers), "source_scales": res.source_scales, "bundle": res.bundle}
        return res.poses[order]
