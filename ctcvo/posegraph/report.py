"""The comparison table: teacher (chained), teacher graph (the teacher's own edges of every
gap, optimised without the learner: the control for the fused row), learner (chained),
fused (graph), and, with ground truth, the trivial baselines zero motion and constant
velocity. ``report.md`` explains every column (:data:`COLUMN_NOTES`).

Per row (``report.json`` ``rows.<name>``): the standard keys of
:func:`data.metrics.trajectory_report` (``ate_rmse_m``, ``rpe_trans_rmse_m``,
``rpe_rot_rmse_deg``, ``se3_l2_mean``) plus

* ``rpe_g{1,2,3}_trans_m`` / ``rpe_g{1,2,3}_rot_deg`` and ``rpe_1s_*``: evo RPE RMSE at
  gaps of 1, 2, 3 frames and of the frame count closest to one second;
* ``composition_trans_rmse_m`` / ``composition_rot_rmse_deg`` (+ ``composition_n``):
  disagreement between the row's trajectory and the direct gap > 1 edges of its source
  (for a chained row: composed gap-1 edges versus direct longer-gap edges; for the fused
  row: the graph versus every source's longer-gap edges). Needs no ground truth;
* for a source's edges with ground truth (``calibration``): mean NEES
  ``d^T C^-1 d`` with ``d = log(inv(T_meas) @ T_gt)`` (expected 6), its ratio to 6, and
  the fraction of edges inside the 1-sigma (68.27 %) and 2-sigma (95.45 %) chi-square
  regions of 6 dof (:mod:`data.uncertainty`).

With ground truth, two more rows follow (:func:`baseline_blocks`): ``zero_motion`` and
``constant_velocity``, the trajectories of :func:`data.metrics.baseline_trajectories` (a
camera that never moves; a constant-velocity model repeating the true previous step),
with the same ground-truth metric keys and ``null`` composition keys
(``composition_n`` 0) and no ``calibration``: no learned figure is shown without them.
Without ground truth these rows are absent.

Metrics that need ground truth are ``null`` without it. The top-level
``covariance_scales`` / ``covariance_calibration`` (see
:func:`posegraph.graph.solve`) give the scale each source's covariances were
multiplied by in the graph, estimated from residuals without ground truth.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from numpy.typing import NDArray

from ctcvo.data import geometry as geo
from ctcvo.data import metrics
from ctcvo.data.formats import Edge, Trajectory
from ctcvo.data.io import json_safe as _f  # JSON-safe number (NaN -> None)
from ctcvo.data.uncertainty import mahalanobis2, nees_stats
from ctcvo.posegraph.edges import BRIDGE_SIGMA_FACTOR

ROW_LABELS = {"teacher": "teacher (chained)", "teacher_graph": "teacher graph (teacher edges only)",
              "learner": "learner (chained)", "fused": "fused (graph)",
              "zero_motion": "zero motion", "constant_velocity": "constant velocity"}
BASELINE_KEYS = metrics.BASELINE_KEYS  # ``rows`` key of each trivial baseline
BASELINE_HOW = {"zero motion": "baseline: every pose is the first ground-truth pose",
                "constant velocity": "baseline: each step repeats the previous ground-truth step (first step zero)"}
RPE_GAPS = (1, 2, 3)
METRIC_KEYS = ("ate_rmse_m", "rpe_trans_rmse_m", "rpe_rot_rmse_deg", "se3_l2_mean")


def frames_per_second_gap(times: NDArray[np.float64]) -> int:
    """Frame gap closest to one second (median frame interval); 0 if unknown."""
    dt = np.diff(times)
    dt = dt[dt > 0]
    if len(dt) == 0:
        return 0
    return max(1, int(round(1.0 / float(np.median(dt)))))


def finite_rows(poses: NDArray[np.float64]) -> NDArray[np.bool_]:
    """(N,) the poses that are finite: the ground truth of a graph whose ``groundtruth.tum``
    leaves frames out (:func:`posegraph.optimize._groundtruth`) has NaN rows there, and
    the figures against it are computed over the others."""
    return np.isfinite(poses).all(axis=(1, 2))


def gt_metrics(gt: Trajectory, est: Trajectory) -> dict[str, float | None]:
    """Standard keys plus RPE at gaps 1, 2, 3 and one second (evo)."""
    out = {k: _f(v) for k, v in metrics.trajectory_report(gt, est).items()}
    for g in RPE_GAPS:
        t, r = metrics.rpe_rmse(gt, est, g)
        out[f"rpe_g{g}_trans_m"], out[f"rpe_g{g}_rot_deg"] = _f(t), _f(r)
    g1s = frames_per_second_gap(gt.timestamps)
    t, r = metrics.rpe_rmse(gt, est, g1s) if g1s >= 1 else (float("nan"), float("nan"))
    out["rpe_1s_frames"] = g1s
    out["rpe_1s_trans_m"], out["rpe_1s_rot_deg"] = _f(t), _f(r)
    return out


def empty_gt_metrics() -> dict[str, float | None]:
    out: dict[str, float | None] = {k: None for k in METRIC_KEYS}
    for g in RPE_GAPS:
        out[f"rpe_g{g}_trans_m"] = out[f"rpe_g{g}_rot_deg"] = None
    out["rpe_1s_frames"] = None
    out["rpe_1s_trans_m"] = out["rpe_1s_rot_deg"] = None
    return out


def edge_errors(poses: NDArray[np.float64], frame_ids: NDArray[np.int64],
                edges: Sequence[Edge]) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Per edge: translation (m) and rotation (deg) of ``inv(T_i_j) @ T_i_j(poses)``."""
    pos = {int(k): p for p, k in enumerate(frame_ids)}
    tr, rot = np.empty(len(edges)), np.empty(len(edges))
    for n, e in enumerate(edges):
        D = geo.inv_T(e.T_i_j) @ geo.relative_pose(poses[pos[e.i]], poses[pos[e.j]])
        tr[n], rot[n] = np.linalg.norm(D[:3, 3]), geo.rotation_angle_deg(D)
    return tr, rot


def composition_consistency(poses: NDArray[np.float64], frame_ids: NDArray[np.int64],
                            edges: Sequence[Edge]) -> dict[str, float | None]:
    """RMSE disagreement of ``poses`` (N, 4, 4) with the gap > 1 edges (see module doc)."""
    pos = {int(k): p for p, k in enumerate(frame_ids)}
    long = [e for e in edges if abs(pos[e.j] - pos[e.i]) > 1]
    if not long:
        return {"composition_trans_rmse_m": None, "composition_rot_rmse_deg": None, "composition_n": 0}
    tr, rot = edge_errors(poses, frame_ids, long)
    return {"composition_trans_rmse_m": _f(np.sqrt(np.mean(tr**2))),
            "composition_rot_rmse_deg": _f(np.sqrt(np.mean(rot**2))), "composition_n": len(long)}


def nees(edges: Sequence[Edge], frame_ids: NDArray[np.int64], gt_poses: NDArray[np.float64]) -> NDArray[np.float64]:
    """(E,) normalised estimation error squared of each edge against ground truth:
    ``d^T C^-1 d`` with ``d = log(inv(T_meas) @ T_gt)`` (project order, right perturbation)."""
    d = metrics.groundtruth_residuals(edges, gt_poses, frame_ids)
    return mahalanobis2(d, np.array([e.cov for e in edges]).reshape(-1, 6, 6))


def calibration(edges: Sequence[Edge], frame_ids: NDArray[np.int64],
                gt_poses: NDArray[np.float64] | None) -> dict[str, float | None]:
    """Covariance calibration of a source's edges (NEES, 1-sigma / 2-sigma coverage, from
    :func:`data.uncertainty.nees_stats`)."""
    if gt_poses is not None:  # only the edges between frames with a finite ground truth
        has = {int(k) for k in np.asarray(frame_ids)[finite_rows(gt_poses)]}
        edges = [e for e in edges if e.i in has and e.j in has]
    if gt_poses is None or not edges:
        return {**nees_stats(np.zeros(0)), "calibration_n": 0}
    v = nees(edges, frame_ids, gt_poses)
    return {k: _f(x) for k, x in nees_stats(v).items()} | {"calibration_n": len(v)}


def row_block(name: str, poses: NDArray[np.float64], frame_ids: NDArray[np.int64], times: NDArray[np.float64],
              gt_poses: NDArray[np.float64] | None, consistency_edges: Sequence[Edge],
              calib_edges: Sequence[Edge] | None = None, how: str = "") -> dict:
    """One ``rows.<name>`` block of ``report.json``."""
    block: dict = {"label": ROW_LABELS.get(name, name), "how": how, "n_poses": len(frame_ids)}
    if gt_poses is not None:
        has = finite_rows(gt_poses)
        block.update(gt_metrics(Trajectory(times[has], gt_poses[has]), Trajectory(times[has], poses[has])))
    else:
        block.update(empty_gt_metrics())
    block.update(composition_consistency(poses, frame_ids, consistency_edges))
    if calib_edges is not None:
        block["calibration"] = calibration(calib_edges, frame_ids, gt_poses)
    return block


def baseline_blocks(frame_ids: NDArray[np.int64], times: NDArray[np.float64],
                    gt_poses: NDArray[np.float64] | None) -> dict[str, dict]:
    """``rows.zero_motion`` and ``rows.constant_velocity`` (see module doc); ``{}`` without
    ground truth."""
    if gt_poses is None:
        return {}
    has = finite_rows(gt_poses)
    gt = Trajectory(times[has], gt_poses[has])
    out = {}
    for name, traj in metrics.baseline_trajectories(gt).items():
        key = BASELINE_KEYS[name]
        block: dict = {"label": ROW_LABELS[key], "how": BASELINE_HOW[name], "n_poses": len(frame_ids)}
        block.update(gt_metrics(gt, traj))
        block.update({"composition_trans_rmse_m": None, "composition_rot_rmse_deg": None, "composition_n": 0})
        out[key] = block
    return out


#: report.md's explanation of every column of the table.
COLUMN_NOTES = [
    "Columns: **ATE m** - absolute trajectory error, RMSE of the positions after an SE(3) Umeyama "
    "alignment (no scale) to the ground truth (evo APE). **RPEk m / deg** - relative pose error "
    "over k frames, RMSE of the translation (m) and rotation angle (deg) of `inv(T_gt_rel) @ T_est_rel` "
    "(evo RPE, every frame pair k apart). **RPE 1s** - the same over the frame gap closest to one "
    "second (the drift a second of motion accumulates). **se(3) L2** - the paper's local metric, "
    "mean of `||log(T_gt_rel) - log(T_est_rel)||` over gap-1 pairs (v, w order). **comp. m / deg** "
    "- composition consistency, needs no ground truth: RMSE disagreement between the row's "
    "trajectory and the direct gap > 1 edges of its source(s) (a chained row: its composed gap-1 "
    "edges against its own longer edges; the graph rows: the optimised poses against the longer "
    "edges they were fitted to). `-`: not defined for the row (no ground truth, no longer edges).",
]


def _cell(v, fmt: str) -> str:
    return "-" if v is None else format(v, fmt)


def report_markdown(report: dict) -> str:
    """``report.md``: the table, calibration, outliers and settings."""
    title = report.get("scene") or report.get("name") or " + ".join(report.get("inputs", {}).values()) or "edges"
    lines = [f"# Pose graph: {title}", "",
             f"{report['frames']} frames, {report['edges_total']} edges "
             f"({', '.join(f'{k}: {v}' for k, v in report['edges_per_source'].items())}), "
             f"solver {report['solver']['name']}, kernel {report['config']['kernel']}; "
             f"ground truth: {'yes' if report['has_groundtruth'] else 'no'}.", ""]
    use = edge_use(report)
    if use:
        lines += [use, ""]
    lines += _md_table(report) + _md_skill(report) + _md_calibration(report) + _md_outliers(report)
    lines += ["", "## Solver", "", f"- initial error {report['solver']['initial_error']:.6g}, final "
              f"{report['solver']['final_error']:.6g}, {report['solver']['iterations']} iterations/updates, "
              f"{report['solver']['time_s']:.2f} s", f"- git {report['git']}", ""]
    return "\n".join(lines)


def _used_counts(report: dict) -> dict[str, int | None]:
    """Edges of each source in the fused graph: every edge of a source the graph takes as
    given; the one source it selects from (the learner, by ``learner_edges`` and its skill
    gate) gets the rest of ``edges_total``; ``None`` where that cannot be told."""
    given = report.get("edges_per_source") or {}
    gates = report.get("skill_gate") or {}
    bridge = _bridge_mode(report)
    selected = [n for n in given if (bridge and n != "teacher") or (gates.get(n) or {}).get("gated_gaps")]
    used: dict[str, int | None] = {n: v for n, v in given.items() if n not in selected}
    rest = report.get("edges_total", 0) - sum(v for v in used.values() if v is not None)
    for n in selected:
        used[n] = rest if len(selected) == 1 else None
    return {n: used[n] for n in given}


def _bridge_mode(report: dict) -> bool:
    sources = report.get("graph_sources") or list(report.get("edges_per_source") or {})
    return (report.get("config") or {}).get("learner_edges") == "bridge" and "teacher" in sources and len(sources) > 1


def _why_unused(report: dict, name: str) -> str:
    """Why some of ``name``'s edges are not in the fused graph (see posegraph.fusion)."""
    gate = (report.get("skill_gate") or {}).get(name) or {}
    gated, no_cv = gate.get("gated_gaps") or [], gate.get("no_better_than_cv") or []
    why = []
    if _bridge_mode(report):
        why.append("only edges that join frames the teacher's edges leave apart enter (--learner-edges bridge)")
        if gated:
            why.append(f"none at gap(s) {', '.join(map(str, gated))}: no better than zero motion on its validation pairs")
        if no_cv:
            why.append(f"none at gap(s) {', '.join(map(str, no_cv))}: no better than constant velocity on its "
                       "validation pairs")
    elif gated:
        why.append(f"gap(s) {', '.join(map(str, gated))} no better than zero motion on its validation pairs: left out "
                   "except where they join frames the other edges leave apart (then weighed "
                   f"{gate.get('scale', 0):.0e} times less)")
    return "; ".join(why)


def edge_use(report: dict) -> str:
    """One line: how many edges of each source the fused graph used, and why any were not."""
    given = report.get("edges_per_source") or {}
    if not given:
        return ""
    used = _used_counts(report)
    parts = []
    for n, total in given.items():
        u = used[n]
        part = f"{n} {'?' if u is None else u} of {total}"
        if u is None or u < total:
            why = _why_unused(report, n)
            if u == 0 and _bridge_mode(report) and not (report.get("skill_gate") or {}).get(n, {}).get("gated_gaps"):
                why += "; the teacher's edges leave no frames apart here"
            part += f" ({why})" if why else ""
        parts.append(part)
    return "Edges used in the fused graph: " + ", ".join(parts) + "."


def summary_text(report: dict) -> str:
    """What ``posegraph optimize`` prints: the title, the edges used and the table."""
    table = _md_table(report)
    table = table[:table.index("")] if "" in table else table
    md = report_markdown(report)
    return md[:md.index("\n| ")] + "\n" + "\n".join(table) + "\n"


def _md_table(report: dict) -> list[str]:
    """The metrics table, its notes, and the notes on baselines, the control row and bridges."""
    rows = report["rows"]
    g1s = next((b.get("rpe_1s_frames") for b in rows.values() if b.get("rpe_1s_frames")), None)
    head = ["row", "ATE m", "RPE1 m", "RPE1 deg", "RPE2 m", "RPE2 deg", "RPE3 m", "RPE3 deg",
            f"RPE 1s m ({g1s or '?'} fr)", "RPE 1s deg", "se(3) L2", "comp. m", "comp. deg"]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for b in rows.values():
        cells = [b["label"], _cell(b["ate_rmse_m"], ".4f")]
        for g in RPE_GAPS:
            cells += [_cell(b[f"rpe_g{g}_trans_m"], ".4f"), _cell(b[f"rpe_g{g}_rot_deg"], ".3f")]
        cells += [_cell(b["rpe_1s_trans_m"], ".4f"), _cell(b["rpe_1s_rot_deg"], ".3f"), _cell(b["se3_l2_mean"], ".4f"),
                  _cell(b["composition_trans_rmse_m"], ".4f"), _cell(b["composition_rot_rmse_deg"], ".3f")]
        lines.append("| " + " | ".join(cells) + " |")
    lines += ["", *COLUMN_NOTES]
    if any(k in rows for k in BASELINE_KEYS.values()):
        lines += ["", "Baselines from the ground truth: zero motion (the camera never moves) and constant "
                  "velocity (each step repeats the previous true step, the first step is zero)."]
    if "teacher_graph" in rows and "fused" in rows and report.get("graph_sources") != ["teacher"]:
        lines += ["", "The teacher graph is the control for the fused row: the same solver over the teacher's "
                  "own edges (all its gaps), no learner. Fusion helps where the fused row is below it."]
    br = report.get("bridges") or {}
    if br.get("fused") or br.get("teacher_graph"):
        lines += ["", f"Bridge edges (where the graph's edges left it disconnected; the chained trajectory's step "
                  f"or zero motion, sigma {BRIDGE_SIGMA_FACTOR}x the graph's typical edge): "
                  f"fused {br.get('fused') or 0}, teacher graph {br.get('teacher_graph') or 0}."]
    return lines


def _md_skill(report: dict) -> list[str]:
    """The validation skill of each gated source and the teacher's per-gap scales."""
    lines = []
    gates = report.get("skill_gate") or {}
    if gates:
        lines += ["", "## Validation skill (se(3) L2 over zero motion's, on validation pairs)", "",
                  "| source | ratio | per gap | per gap, over constant velocity's | gaps weighed as nothing | "
                  "gaps that never bridge (no better than constant velocity) | reference |",
                  "|---|---|---|---|---|---|---|"]
        for n, g in gates.items():
            per = ", ".join(f"{k}: {v:.2f}" for k, v in g["ratio_by_gap"].items())
            cv = ", ".join(f"{k}: {'-' if v is None else format(v, '.2f')}" for k, v in
                           (g.get("ratio_cv_by_gap") or {}).items())
            lines.append(f"| {n} | {g['ratio']:.3f} | {per} | {cv or '-'} | "
                         f"{', '.join(map(str, g['gated_gaps'])) or 'none'} | "
                         f"{', '.join(map(str, g.get('no_better_than_cv') or [])) or 'none'} | "
                         f"{g.get('reference') or '-'} |")
    tc = report.get("teacher_calibration")
    if tc:
        lines += ["", f"Teacher covariances scaled per gap (fitted on validation data, no ground truth: "
                  f"{tc.get('from') or '-'}): " + ", ".join(f"gap {g}: x{v:.3g}" for g, v in tc["scales"].items())
                  + "; the graph keeps them."]
    return lines


def _md_calibration(report: dict) -> list[str]:
    """Covariance calibration against the ground truth, and the graph's per-source scales."""
    rows = report["rows"]
    lines = []
    cal = [(n, b["calibration"]) for n, b in rows.items() if "calibration" in b]
    if cal:
        lines += ["", "## Covariance calibration (edges vs ground truth)", "",
                  "| source | edges | mean NEES (6 ideal) | NEES/6 | 1-sigma coverage (68.3 %) | 2-sigma coverage (95.4 %) |",
                  "|---|---|---|---|---|---|"]
        for n, c in cal + [(f"{n} (raw, before the per-gap scales)", b["calibration_raw"])
                           for n, b in rows.items() if "calibration_raw" in b]:
            lines.append(f"| {n} | {c['calibration_n']} | {_cell(c['nees_mean'], '.3f')} | "
                         f"{_cell(c['nees_over_dof'], '.3f')} | {_cell(c['coverage_1sigma'], '.3f')} | "
                         f"{_cell(c['coverage_2sigma'], '.3f')} |")
    cc = report.get("covariance_calibration")
    if cc:
        lines += ["", "## Covariance scale per source (from the graph's residuals)", "",
                  f"Each source's covariances were multiplied by `scale` before the outlier pass "
                  f"({cc['iterations']} re-solve(s), {'converged' if cc['converged'] else 'not converged'}, "
                  f"redundancy {cc['redundancy']:.3f}); `residual factor` is the last estimate "
                  "median(r^2) / (5.348 redundancy), about 1 when calibrated.", "",
                  "| source | edges | scale | residual factor |", "|---|---|---|---|"]
        lines += [f"| {n} | {c['edges']} | {c['scale']:.4g} | {c['residual_factor']:.3f} |"
                  for n, c in cc["sources"].items()]
    return lines


def _md_outliers(report: dict) -> list[str]:
    """The outlier edges (the first 200)."""
    out = report["outliers"]
    lines = ["", f"## Outliers ({len(out)})", ""]
    if out:
        lines += ["| i | j | source | reason | value | action |", "|---|---|---|---|---|---|"]
        lines += [f"| {o['i']} | {o['j']} | {o['source']} | {o['reason']} | {o['value']:.3g} | {o['action']} |"
                  for o in out[:200]]
        if len(out) > 200:
            lines.append(f"\n... and {len(out) - 200} more in report.json")
    else:
        lines.append("none")
    return lines
