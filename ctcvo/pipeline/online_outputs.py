"""What ``ctcvo online`` writes (docs/formats.md, "Online mode"): the causal and the final
trajectory, the edges in the layout of ``teacher generate`` / ``learner predict`` and
``report.json``."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ctcvo.data.formats import Edge, Trajectory, read_tum, write_edges_csv, write_g2o, write_observations, write_tum
from ctcvo.data.io import ensure_dir, git_revision, json_safe, write_json
from ctcvo.data.metrics import trajectory_report
from ctcvo.data.runs import frames_id
from ctcvo.pipeline.online_loop import Estimator
from ctcvo.teacher.generate import _edge_rows as edge_rows  # edges.csv's rows, as teacher generate writes them
from ctcvo.teacher.generate import chain_trajectory
from ctcvo.teacher.observations import run_sightings
from ctcvo.teacher.record import count_by_kind

TRAJECTORY = "trajectory.tum"
FINAL_TRAJECTORY = "trajectory_final.tum"
REPORT = "report.json"
#: every file a run writes (report.json first: removed first, written last, it marks a finished run)
OUTPUT_FILES = (REPORT, TRAJECTORY, FINAL_TRAJECTORY, "teacher/edges.g2o", "teacher/edges.csv",
                "teacher/trajectory.tum", "teacher/groundtruth.tum", "learner/edges.g2o")
#: the first line of trajectory.tum
TRAJECTORY_HEADER = "# timestamp tx ty tz qx qy qz qw  (T_world_cam, metres; each frame's estimate when it arrived)\n"


def percentiles_ms(seconds: list[float]) -> dict[str, float]:
    """p50, p95, p99 and max of durations in seconds, in milliseconds (report.json's form)."""
    return {f"p{q}": 1000 * float(np.percentile(seconds, q)) for q in (50, 95, 99)} | {"max": 1000 * max(seconds)}


def write_outputs(out: Path, name: str, est: Estimator, teacher_cfg, seconds: float, timing: dict,
                  interrupted: bool, checkpoint: Path | None) -> dict:
    """Write the final trajectory, the edge folders and report.json (all atomically) of the
    run of sequence ``name`` that ``est`` holds; returns the report."""
    teacher, graph, gts = est.teacher, est.graph, est.gts
    ids = np.array(teacher.ids, dtype=np.int64)
    times = np.array(teacher.times)
    n = len(ids)
    t_edges = sorted(est.t_edges, key=lambda e: (e.i, e.j))  # the order of teacher generate's files
    seen = None  # the landmark sightings, as teacher generate writes them
    if teacher.colour is None:
        kept = set(ids.tolist())
        inside = [e for e in t_edges if e.i in kept and e.j in kept]
        seen = run_sightings([e for e in inside if (e.i, e.j) in est.kinds],
                             [e for e in inside if (e.i, e.j) not in est.kinds and e.inlier_points is not None],
                             teacher.intr)
    final = graph.final(observations=seen)[:n]  # the graph may hold a frame an interrupt cut short
    write_tum(out / FINAL_TRAJECTORY, Trajectory(times, final))
    scale = {(e.i, e.j): teacher.cov_scale(e, est.kinds.get((e.i, e.j), "window")) for e in t_edges}
    good = [Edge(e.i, e.j, e.T_i_j, e.cov * scale[e.i, e.j]) for e in t_edges if e.ok]
    # the window's edges chained, as teacher generate chains them before its keyframe pass
    chained, _ = chain_trajectory(ids, [e for e in t_edges if (e.i, e.j) not in est.kinds])
    tdir = ensure_dir(out / "teacher")
    write_g2o(tdir / "edges.g2o", good, {int(f): T for f, T in zip(ids, chained)})
    write_edges_csv(tdir / "edges.csv", edge_rows(t_edges, dict(zip(ids.tolist(), times.tolist())), est.kinds, scale))
    write_tum(tdir / "trajectory.tum", Trajectory(times, chained))
    if seen is not None:
        write_observations(tdir / "observations.csv", seen)
    has_gt = n >= 2 and all(g is not None for g in gts)
    if has_gt:
        gt = Trajectory(times, np.stack(gts))
        write_tum(tdir / "groundtruth.tum", gt)
    l_edges = est.l_edges
    if l_edges:
        ldir = ensure_dir(out / "learner")
        write_g2o(ldir / "edges.g2o", [Edge(e.i, e.j, e.T_i_j, e.cov) for e in sorted(l_edges, key=lambda e: (e.i, e.j))],
                  {int(f): T for f, T in zip(ids, final)})
    report: dict = {
        "sequence": name, "frames": n, "seconds": seconds, "fps": n / seconds if seconds > 0 else None,
        **timing, "interrupted": interrupted,
        "teacher_edges": len(good), "teacher_failed_edges": len(t_edges) - len(good),
        "teacher_edges_by_kind": count_by_kind(t_edges, est.kinds, True),
        "teacher_failed_edges_by_kind": count_by_kind(t_edges, est.kinds, False),
        "keyframes": est.keyframes.report(est.dropped_keyframes) if est.keyframes is not None else None,
        "learner_edges": len(l_edges), "checkpoint": str(checkpoint) if checkpoint else None,
        "covariance_scales": graph.scale, "graph_reviews": graph.reviews, "final_polish": graph.polish,
        "outlier_edges": {"removed": int((graph.status == 2).sum()), "downweighted": int((graph.status == 1).sum())},
        "frame_ids": frames_id(ids), "teacher": teacher_cfg.to_dict(), "git_revision": git_revision(),
    }
    if has_gt:
        report["final"] = trajectory_report(gt, Trajectory(times, final))
        if graph.polish is not None:
            report["final_isam2"] = trajectory_report(gt, Trajectory(times, graph.isam2_poses[:n]))
        report["online"] = trajectory_report(gt, Trajectory(times, read_tum(out / TRAJECTORY).poses[:n]))
        report["teacher_chain"] = trajectory_report(gt, Trajectory(times, chained))
    report = json_safe(report)  # what a later run reads back from the file (tuples as lists)
    write_json(out / REPORT, report)
    return report
