"""Which edges of which source enter the fused graph: the sources in use, the skill gate
(a learner no better than zero motion on validation weighs nothing), the learner edges
that only bridge where the teacher's edges leave frames apart, and the initial values."""

from __future__ import annotations

import dataclasses
import logging
from collections.abc import Sequence

import numpy as np
from numpy.typing import NDArray

from ctcvo.data.errors import ConfigError, DataError
from ctcvo.data.formats import Edge
from ctcvo.posegraph.config import PoseGraphConfig
from ctcvo.posegraph.edges import chain_poses, component_labels, joining_edges
from ctcvo.posegraph.sources import Frames, Source, poses_for_frames

log = logging.getLogger(__name__)

# covariance scale of a source's edges at gaps where its validation skill is no better than zero
# motion: they then weigh so little that the fused result is the teacher graph's
# (tests/test_posegraph_fusion.py; bench/README.md "Fusion that never hurts")
UNSKILLED_SCALE = 1e4


def graph_sources(srcs: dict[str, Source], cfg: PoseGraphConfig) -> list[str]:
    """The names of the sources whose edges enter the graph (``cfg.sources``)."""
    if cfg.sources == "auto":
        return list(srcs)
    need = ["teacher", "learner"] if cfg.sources == "fused" else [cfg.sources]
    missing = [n for n in need if n not in srcs]
    if missing:
        raise ConfigError(f"--use {cfg.sources} needs the {' and '.join(missing)} folder")
    return need


def skill_gate(src: Source, frames: Frames) -> dict | None:
    """Which gaps of ``src`` weigh as nothing: those whose validation skill ratio (per gap
    when the skill has ``by_gap``, else overall) is 1 or more. ``None`` without a skill."""
    if src.skill is None:
        if src.name != "teacher":
            log.warning("%s: no validation skill (no calibration.json with validation.skill); its edges are used "
                        "as given", src.name)
        return None
    pos = {int(k): p for p, k in enumerate(frames.ids)}
    by_gap = src.skill.get("by_gap") or {}
    gaps = sorted({abs(pos[e.j] - pos[e.i]) for e in src.edges})
    ratio = {g: float((by_gap.get(str(g)) or src.skill)["ratio"]) for g in gaps}
    gated = [g for g in gaps if ratio[g] >= 1.0]
    ratio_cv = {g: (by_gap.get(str(g)) or src.skill).get("ratio_cv") for g in gaps}
    no_cv = [g for g in gaps if ratio_cv[g] is not None and ratio_cv[g] >= 1.0 and g not in gated]
    if gated:
        log.warning("%s: no better than zero motion on its validation pairs at gap(s) %s (se(3) L2 ratio %s); "
                    "those edges weigh %.0e times less", src.name, gated,
                    ", ".join(f"{ratio[g]:.2f}" for g in gated), UNSKILLED_SCALE)
    return {"ratio": src.skill["ratio"], "ratio_by_gap": {str(g): ratio[g] for g in gaps}, "gated_gaps": gated,
            "ratio_cv_by_gap": {str(g): ratio_cv[g] for g in gaps}, "no_better_than_cv": no_cv,
            "scale": UNSKILLED_SCALE, "reference": src.skill.get("reference"), "from": src.skill.get("from")}


def _gated_edges(src: Source, frames: Frames, gate: dict | None, others: Sequence = ()) -> list:
    """``src``'s edges for the graph. Edges at gated gaps (no better than zero motion on
    validation) weigh as nothing: they are left out, except those that join components the
    graph's other edges (``others`` and the source's ungated edges) leave apart - a stretch
    where the teacher failed - which stay, smallest gap first, with covariance times
    ``UNSKILLED_SCALE`` and the source name ``<name>:unskilled``. So where the teacher
    graph is connected, the fused graph is exactly the teacher graph."""
    if not gate or not gate["gated_gaps"]:
        return src.edges
    pos = {int(k): p for p, k in enumerate(frames.ids)}
    gated = set(gate["gated_gaps"])
    kept = [e for e in src.edges if abs(pos[e.j] - pos[e.i]) not in gated]
    weak = sorted((e for e in src.edges if abs(pos[e.j] - pos[e.i]) in gated), key=lambda e: abs(pos[e.j] - pos[e.i]))
    joined = joining_edges(frames.ids, list(others) + kept, weak)
    gate["bridging_edges"] = len(joined)
    return kept + [dataclasses.replace(e, cov=np.asarray(e.cov) * UNSKILLED_SCALE,
                                       extra={**e.extra, "source": f"{src.name}:unskilled"}) for e in joined]


def _crossing_edges(src: Source, frames: Frames, gate: dict | None, teacher_edges: Sequence) -> list:
    """``learner_edges = "bridge"``: the edges of ``src`` between frames that the teacher's
    edges leave in different components (the only relative poses the teacher lacks); none
    at gaps the skill gate found no better than zero motion (there the teacher's constant-
    velocity bridge is used instead), nor at gaps whose validation ``ratio_cv`` (against the
    constant-velocity guess from the teacher's previous step) is 1 or more: the teacher's
    bridge is the better guess there."""
    pos = {int(k): p for p, k in enumerate(frames.ids)}
    labels = component_labels(frames.ids, teacher_edges)
    gated = set(gate["gated_gaps"] + gate["no_better_than_cv"]) if gate else set()
    out = [e for e in src.edges
           if labels[pos[e.i]] != labels[pos[e.j]] and abs(pos[e.j] - pos[e.i]) not in gated]
    if gate is not None:
        gate["bridging_edges"] = len(out)
    log.info("%s: %d of %d edges join frames the teacher's edges leave apart (learner_edges = bridge)", src.name,
             len(out), len(src.edges))
    return out


def guide_poses(srcs: dict[str, Source], used: list[str], frames: Frames) -> NDArray[np.float64] | None:
    """Poses whose steps bridge a disconnected graph: the teacher's chained trajectory
    (constant velocity over its failed stretches) if it covers every frame, else the first
    used source's that does, else ``None`` (zero-motion bridges)."""
    for n in ["teacher"] + used:
        if n in srcs:
            traj = poses_for_frames(srcs[n].trajectory, frames)
            if traj is not None:
                return traj
    return None


def graph_edges(srcs: dict[str, Source], used: list[str], frames: Frames, gates: dict[str, dict | None],
                cfg: PoseGraphConfig) -> list[Edge]:
    """The edges of the fused graph, source by source (``cfg.learner_edges``); the
    sources' edges are left as they are."""
    if cfg.learner_edges == "bridge" and "teacher" in used and len(used) > 1:
        by = {n: srcs[n].edges if n == "teacher" else _crossing_edges(srcs[n], frames, gates[n], srcs["teacher"].edges)
              for n in used}
    else:
        by = {n: _gated_edges(srcs[n], frames, gates[n], [e for m in used if m != n and not gates[m] for e in srcs[m].edges])
              for n in used}
    edges = [e for n in used for e in by[n]]
    if not edges:
        raise DataError("no edges left for the pose graph")
    return edges


def initial_poses(srcs: dict[str, Source], used: list[str], frames: Frames,
                  edges: Sequence[Edge]) -> tuple[NDArray[np.float64], str]:
    """(initial poses, where from): the first used source's trajectory that covers every
    frame, else the chained ``edges``."""
    for n in used:
        traj = poses_for_frames(srcs[n].trajectory, frames)
        if traj is not None:
            return traj, f"{srcs[n].path}/trajectory.tum"
    return chain_poses(frames.ids, edges), "chained edges"
