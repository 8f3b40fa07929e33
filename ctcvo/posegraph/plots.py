"""Figures of ``posegraph optimize``, rendered in memory (Agg) and returned as PNG bytes so
the stage can write them atomically after everything else succeeded.

Every series has its own colour (Okabe-Ito, colour-blind safe) and line style and the
report's human label (:data:`LABELS`); each figure has one shared legend. Estimates are
aligned to ground truth as the report's ATE is: evo's SE(3) Umeyama (no scale) over all
frames of the graph.

* ``trajectories.png``: a top view and a side view (2-D, equal aspect) of every row
  aligned to ground truth; the two horizontal world axes are the two along which the
  trajectory spans most, the vertical the one it spans least (each panel names its axes).
  Ground truth is drawn last, thin and black; the fused row a wide pale band underneath,
  so that it shows where it equals the teacher graph. Units mm below 1 m of extent, else m;
  the legend gives each row's ATE.
* ``error_over_time.png``: each row's position error after that alignment over time, on
  a log axis (a 0.5 m error and a 2 mm one both readable); without ground truth the
  edges' whitened residuals over time.
* ``relative_se3.png``: per-dimension errors of the gap-1 relative poses against ground
  truth, ``|log(T_est_rel) - log(T_gt_rel)|`` per se(3) component (v in mm, w in deg; the
  components of the report's se(3) L2), one box per row (median, quartiles, 5-95 %
  whiskers) on a log axis; without ground truth against the fused graph.
* ``outliers.png``: every edge of every gap at its whitened residual after the first
  (calibrated) solve, the threshold, and the report's outlier edges (``report.json``
  ``outliers``: the same count, split by action and gap).

Every time axis is the sequence's own time (the trajectories' timestamps: 7-Scenes and
synthetic frame ``k`` at ``k / 30`` s, TUM the recording's clock), so that a figure of
frames 450:600 reads 15-20 s and lines up with other runs over the same frames.
"""

from __future__ import annotations

import copy
import io
from collections import Counter
from collections.abc import Sequence

import numpy as np
from numpy.typing import NDArray

from ctcvo.data import geometry as geo
from ctcvo.data import metrics
from ctcvo.data.formats import Edge, Trajectory
from ctcvo.posegraph.graph import OutlierRecord
from ctcvo.posegraph.report import ROW_LABELS

#: the report's row labels, and ground truth's
LABELS = {"gt": "ground truth", **ROW_LABELS}
#: colour, line style and width of each series (Okabe-Ito colours); ground truth thin on
#: top, the fused row a wide pale band underneath
STYLES = {"gt": dict(color="black", ls="-", lw=0.8, zorder=10),
          "teacher": dict(color="#E69F00", ls="--", lw=1.4, zorder=4),
          "teacher_graph": dict(color="#CC79A7", ls="-.", lw=1.4, zorder=5),
          "learner": dict(color="#0072B2", ls=":", lw=1.8, zorder=3),
          "fused": dict(color="#009E73", ls="-", lw=4.0, alpha=0.45, zorder=2, solid_capstyle="round")}
_OTHER = [dict(color="#D55E00", ls=(0, (5, 1, 1, 1)), lw=1.4, zorder=3),
          dict(color="#56B4E9", ls=(0, (3, 1)), lw=1.4, zorder=3)]
SE3_NAMES = ("v_x", "v_y", "v_z", "w_x", "w_y", "w_z")
ALIGNMENT = "SE(3) Umeyama alignment (no scale) on all {n} frames"
MM_BELOW_M = 1.0  # trajectories spanning less than this (m) are drawn in mm
_LOG_FLOOR = 1e-6  # smallest value drawn on a log axis (m, rad or whitened)


def label(name: str) -> str:
    """The human label of a row or series (a bare edge source keeps its name, chained)."""
    return LABELS.get(name, f"{name} (chained)")


def style(name: str) -> dict:
    """Line keywords of a series."""
    if name in STYLES:
        return dict(STYLES[name])
    return dict(_OTHER[sum(map(ord, name)) % len(_OTHER)])


def _figure(w: float, h: float):
    """A matplotlib figure on the Agg canvas (no display needed)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(w, h), dpi=100, layout="constrained")
    FigureCanvasAgg(fig)
    return fig


def _png(fig) -> bytes:
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=150)
    return buf.getvalue()


def _umeyama(ref: NDArray[np.float64], est: NDArray[np.float64]) -> NDArray[np.float64]:
    """The rigid motion (4, 4) that best fits ``est``'s positions (N, 4, 4) to ``ref``'s
    (Umeyama, no scale): where evo refuses (all positions equal or collinear)."""
    a, b = ref[:, :3, 3], est[:, :3, 3]
    ma, mb = a.mean(axis=0), b.mean(axis=0)
    U, _, Vt = np.linalg.svd((a - ma).T @ (b - mb) / len(a))
    R = U @ np.diag([1.0, 1.0, np.sign(np.linalg.det(U) * np.linalg.det(Vt)) or 1.0]) @ Vt
    return geo.make_T(R, ma - R @ mb)


def align_to(gt: NDArray[np.float64], est: NDArray[np.float64], times: NDArray[np.float64]) -> NDArray[np.float64]:
    """``est`` (N, 4, 4) aligned to ``gt`` by evo's SE(3) Umeyama (no scale), as the ATE,
    fitted on the frames whose ground truth is finite (NaN rows: frames the teacher left out
    of its evaluation, :func:`posegraph.optimize._groundtruth`)."""
    from evo.core.geometry import GeometryException

    has = np.isfinite(gt).all(axis=(1, 2))
    ref, sub, t = gt[has], est[has], times[has]
    try:
        r, tr, _ = copy.deepcopy(Trajectory(t, sub).to_evo()).align(Trajectory(t, ref).to_evo(), correct_scale=False)
    except GeometryException:
        return _umeyama(ref, sub) @ est
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = r, tr
    return T @ est


def make_figures(times: NDArray[np.float64], rows: dict[str, NDArray[np.float64]],
                 gt: NDArray[np.float64] | None, frame_ids: NDArray[np.int64], edges: Sequence[Edge],
                 residuals: NDArray[np.float64], outliers: Sequence[OutlierRecord], threshold: float) -> dict:
    """All figures as ``{file name: matplotlib Figure}``.

    Args:
        times: (N,) timestamps; rows: name -> (N, 4, 4) ``T_world_cam`` estimates (report order);
        gt: (N, 4, 4) ground truth or None; edges: the fused graph's input edges;
        residuals: (E,) their whitened residuals after the first solve (what the outlier
        test compares with ``threshold``); outliers: the solve's outlier records (the report's).
    """
    t = np.asarray(times, dtype=np.float64)
    aligned = {n: (align_to(gt, p, t) if gt is not None else p) for n, p in rows.items()}
    pos = {int(k): p for p, k in enumerate(frame_ids)}
    return {"trajectories.png": _trajectories(gt, aligned),
            "relative_se3.png": _relative_se3(rows, gt),
            "outliers.png": _outliers(t, pos, edges, residuals, outliers, threshold),
            "error_over_time.png": _error_over_time(t, pos, gt, aligned, edges, residuals, threshold)}


def make_plots(times: NDArray[np.float64], rows: dict[str, NDArray[np.float64]],
               gt: NDArray[np.float64] | None, frame_ids: NDArray[np.int64], edges: Sequence[Edge],
               residuals: NDArray[np.float64], outliers: Sequence[OutlierRecord], threshold: float) -> dict[str, bytes]:
    """:func:`make_figures` as ``{file name: PNG bytes}``."""
    figs = make_figures(times, rows, gt, frame_ids, edges, residuals, outliers, threshold)
    return {name: _png(fig) for name, fig in figs.items()}


def _ate_m(gt: NDArray[np.float64] | None, p: NDArray[np.float64]) -> float | None:
    """RMSE of the aligned positions (the report's ATE)."""
    return None if gt is None else float(np.sqrt(np.mean(np.sum((p[:, :3, 3] - gt[:, :3, 3]) ** 2, axis=1))))


def _legend_label(name: str, ate: float | None) -> str:
    return label(name) if ate is None else f"{label(name)}, ATE {1e3 * ate:.1f} mm"


def _shared_legend(fig, handles: list, labels: list[str], ncol: int | None = None) -> None:
    """One legend for the whole figure, under the panels (none without series)."""
    if not labels:
        return
    fig.legend(handles, labels, loc="outside lower center", ncol=ncol or min(len(labels), 3), fontsize=9,
               frameon=False)


def view_axes(xyz: NDArray[np.float64]) -> tuple[int, int, int]:
    """(main horizontal, second horizontal, vertical) world axes of positions (N, 3): by
    decreasing extent, the vertical being the one the trajectory spans least."""
    order = np.argsort(-np.ptp(xyz, axis=0), kind="stable")
    return int(order[0]), int(order[1]), int(order[2])


def _trajectories(gt: NDArray[np.float64] | None, aligned: dict[str, NDArray[np.float64]]) -> object:
    """Top and side view of every row (aligned) and the ground truth, equal aspect."""
    from matplotlib.ticker import MaxNLocator

    series = list(aligned.items()) + ([("gt", gt)] if gt is not None else [])  # ground truth last
    ref = gt if gt is not None else aligned.get("fused", next(iter(aligned.values())))
    a, b, up = view_axes(ref[:, :3, 3])
    mm = float(np.ptp(ref[:, :3, 3], axis=0).max()) < MM_BELOW_M
    unit, k = ("mm", 1e3) if mm else ("m", 1.0)
    fig = _figure(12, 5.6)
    axes = fig.subplots(1, 2)
    handles = []
    for ax, (h, v), title in ((axes[0], (a, b), "top view"), (axes[1], (a, up), "side view")):
        for n, p in series:
            (line,) = ax.plot(k * p[:, h, 3], k * p[:, v, 3], **style(n))
            if ax is axes[0]:
                handles.append(line)
        ax.plot(k * ref[0, h, 3], k * ref[0, v, 3], "o", color="black", ms=5, mfc="white", zorder=11)
        ax.set_aspect("equal", adjustable="datalim")
        ax.set_xlabel(f"{'xyz'[h]} [{unit}]")
        ax.set_ylabel(f"{'xyz'[v]} [{unit}]")
        ax.set_title(f"{title} ({'xyz'[h]}-{'xyz'[v]} plane; o: start)", fontsize=10)
        ax.xaxis.set_major_locator(MaxNLocator(6))
        ax.yaxis.set_major_locator(MaxNLocator(6))
        ax.grid(True, lw=0.3, color="0.85")
    labels = [_legend_label(n, _ate_m(gt, p) if n != "gt" else None) for n, p in series]
    _shared_legend(fig, handles, labels)
    what = f"aligned to ground truth by {ALIGNMENT.format(n=len(ref))}" if gt is not None else "no ground truth"
    fig.suptitle(f"Trajectories ({what})", fontsize=11)
    return fig


def _error_over_time(t: NDArray[np.float64], pos: dict[int, int], gt: NDArray[np.float64] | None,
                     aligned: dict[str, NDArray[np.float64]], edges: Sequence[Edge], residuals: NDArray[np.float64],
                     threshold: float) -> object:
    """Each row's aligned position error over time (log axis), or without ground truth the edges' residuals."""
    fig = _figure(12, 4.4)
    ax = fig.subplots(1, 1)
    if gt is None:
        return _residuals_over_time(fig, ax, t, pos, edges, residuals, threshold)
    handles, labels = [], []
    for n, p in aligned.items():
        err = np.linalg.norm(p[:, :3, 3] - gt[:, :3, 3], axis=1)
        (line,) = ax.semilogy(t, 1e3 * np.maximum(err, _LOG_FLOOR), **style(n))
        handles.append(line)
        labels.append(_legend_label(n, _ate_m(gt, p)))
    ax.set_ylabel("position error [mm] (log)")
    ax.set_xlabel("time [s]")
    ax.grid(True, which="both", lw=0.3, color="0.85")
    _shared_legend(fig, handles, labels, ncol=min(len(labels), 4))
    fig.suptitle(f"Absolute position error over time after {ALIGNMENT.format(n=len(t))} (as the report's ATE)",
                 fontsize=11)
    return fig


def _sources(edges: Sequence[Edge]) -> list[str]:
    return list(dict.fromkeys(str(e.extra.get("source", "edges")) for e in edges))


def _residual_points(ax, t: NDArray[np.float64], pos: dict[int, int], edges: Sequence[Edge],
                     residuals: NDArray[np.float64], label, alpha: float | None = None) -> tuple:
    """Each source's edges as points: whitened residual (log axis) at the time of the edge's
    later frame, labelled ``label(source, mask)``. Returns (times, residuals floored, sources,
    handles, labels)."""
    te = np.array([t[max(pos[e.i], pos[e.j])] for e in edges])
    res = np.maximum(np.asarray(residuals, dtype=np.float64), _LOG_FLOOR)
    src = np.array([str(e.extra.get("source", "edges")) for e in edges])
    handles, labels = [], []
    for s in _sources(edges):
        m = src == s
        (h,) = ax.semilogy(te[m], res[m], ".", ms=3, color=style(s)["color"], alpha=alpha)
        handles.append(h)
        labels.append(label(s, m))
    return te, res, src, handles, labels


def _threshold_line(ax, threshold: float, name: str, handles: list, labels: list) -> None:
    """The outlier threshold as a dashed line, with its legend entry (none when infinite)."""
    if np.isfinite(threshold):
        handles.append(ax.axhline(threshold, color="0.3", ls="--", lw=1))
        labels.append(f"{name} {threshold:g}")


def _residuals_over_time(fig, ax, t: NDArray[np.float64], pos: dict[int, int], edges: Sequence[Edge],
                         residuals: NDArray[np.float64], threshold: float) -> object:
    """Without ground truth: every edge's whitened residual at the time of its later frame."""
    *_, handles, labels = _residual_points(ax, t, pos, edges, residuals, lambda s, m: f"{s} edges ({int(m.sum())})")
    _threshold_line(ax, threshold, "outlier threshold", handles, labels)
    ax.set_xlabel("time [s]")
    ax.set_ylabel("whitened residual (log)")
    ax.grid(True, which="both", lw=0.3, color="0.85")
    _shared_legend(fig, handles, labels, ncol=len(labels))
    fig.suptitle("Edge residuals over time after the first solve (no ground truth)", fontsize=11)
    return fig


def _rel_log(poses: NDArray[np.float64]) -> NDArray[np.float64]:
    return geo.se3_log(metrics.relative_poses(poses))


def relative_errors(rows: dict[str, NDArray[np.float64]], ref: NDArray[np.float64]) -> dict[str, NDArray[np.float64]]:
    """Per row, (N-1, 6) ``|log(T_est_rel) - log(T_ref_rel)|`` of the gap-1 relative poses,
    v in mm and w in deg."""
    r = _rel_log(ref)
    unit = np.array([1e3] * 3 + [np.degrees(1.0)] * 3)
    return {n: np.abs(_rel_log(p) - r) * unit for n, p in rows.items()}


def _relative_se3(rows: dict[str, NDArray[np.float64]], gt: NDArray[np.float64] | None) -> object:
    """Per-dimension gap-1 errors against ground truth (or the fused graph): one box per row."""
    from matplotlib.patches import Patch

    if gt is not None:
        errs, ref = relative_errors(rows, gt), "ground truth"
    else:
        errs, ref = relative_errors({n: p for n, p in rows.items() if n != "fused"}, rows["fused"]), "the fused graph"
    fig = _figure(12, 4.8)
    axes = fig.subplots(1, 2)
    names = list(errs)
    if not names:
        fig.text(0.5, 0.5, f"no row to compare with {ref}", ha="center", bbox=dict(fc="white", ec="0.5"))
    w = 0.8 / max(len(names), 1)
    for ax, comps, unit in ((axes[0], range(3), "mm"), (axes[1], range(3, 6), "deg")):
        for k, n in enumerate(names):
            data = [np.maximum(errs[n][:, c], _LOG_FLOOR) for c in comps]
            st = style(n)
            bp = ax.boxplot(data, positions=np.arange(3) + (k - (len(names) - 1) / 2) * w, widths=0.85 * w,
                            whis=(5, 95), showfliers=False, patch_artist=True)
            for box in bp["boxes"]:
                box.set(facecolor=st["color"], alpha=0.75, edgecolor="black", lw=0.6)
            for part in ("whiskers", "caps"):
                for line in bp[part]:
                    line.set(color=st["color"], lw=1.0)
            for line in bp["medians"]:
                line.set(color="black", lw=1.0)
        ax.set_yscale("log")
        ax.set_xticks(range(3), [SE3_NAMES[c] for c in comps])
        ax.set_ylabel(f"|error| [{unit}] (log)")
        ax.grid(True, axis="y", which="both", lw=0.3, color="0.85")
    axes[0].set_title("translation components v", fontsize=10)
    axes[1].set_title("rotation components w", fontsize=10)
    handles = [Patch(facecolor=style(n)["color"], alpha=0.75, edgecolor="black", lw=0.6) for n in names]
    _shared_legend(fig, handles, [label(n) for n in names], ncol=min(len(names), 4))
    fig.suptitle(f"Gap-1 relative-pose error per se(3) component against {ref}: |log(T_est_rel) - log(T_ref_rel)|\n"
                 "(box: quartiles, line: median, whiskers: 5-95 %)", fontsize=10)
    return fig


def match_outliers(edges: Sequence[Edge], outliers: Sequence[OutlierRecord]) -> dict[int, str]:
    """``{edge index: action}`` of every outlier record (matched by frames and source)."""
    free: dict[tuple, list[int]] = {}
    for n, e in enumerate(edges):
        free.setdefault((e.i, e.j, str(e.extra.get("source", "edges"))), []).append(n)
    out = {}
    for o in outliers:
        idx = free.get((o.i, o.j, o.source))
        if idx:
            out[idx.pop(0)] = o.action
    return out


def _outliers(t: NDArray[np.float64], pos: dict[int, int], edges: Sequence[Edge], residuals: NDArray[np.float64],
              outliers: Sequence[OutlierRecord], threshold: float) -> object:
    """Every edge's first-solve residual over time, the threshold, and the report's outliers."""
    fig = _figure(12, 4.8)
    ax = fig.subplots(1, 1)
    gaps = np.array([abs(pos[e.j] - pos[e.i]) for e in edges])
    flagged = match_outliers(edges, outliers)
    te, res, src, handles, labels = _residual_points(
        ax, t, pos, edges, residuals, lambda s, m: f"{s} edges ({int(m.sum())}, gaps {gaps[m].min()}-{gaps[m].max()})",
        alpha=0.6)
    for action, marker in (("removed", "x"), ("downweighted", "D")):
        for s in _sources(edges):
            idx = [n for n, a in flagged.items() if a == action and src[n] == s]
            if idx:
                (h,) = ax.semilogy(te[idx], res[idx], ls="none", marker=marker, ms=7, mew=1.4, mfc="none",
                                   color=style(s)["color"], zorder=5)
                handles.append(h)
                labels.append(f"{s}: {action} ({len(idx)})")
    _threshold_line(ax, threshold, "threshold", handles, labels)
    ax.set_xlabel("time of the edge's later frame [s]")
    ax.set_ylabel("whitened residual, first solve (log)")
    ax.grid(True, which="both", lw=0.3, color="0.85")
    _shared_legend(fig, handles, labels, ncol=min(len(labels), 4))
    fig.suptitle(outlier_title(outliers, edges, pos), fontsize=11)
    return fig


def outlier_title(outliers: Sequence[OutlierRecord], edges: Sequence[Edge], pos: dict[int, int]) -> str:
    """The outlier figure's title: the report's count over all gaps, by action and by gap."""
    acts = Counter(o.action for o in outliers)
    by_gap = Counter(abs(pos[o.j] - pos[o.i]) for o in outliers)
    gaps = sorted({abs(pos[e.j] - pos[e.i]) for e in edges})
    title = (f"Outlier edges: {len(outliers)} of {len(edges)} (all gaps {gaps[0]}-{gaps[-1]}; as report.json), "
             f"{acts.get('removed', 0)} removed, {acts.get('downweighted', 0)} down-weighted")
    if by_gap:
        title += "; by gap: " + ", ".join(f"{g}: {c}" for g, c in sorted(by_gap.items()))
    return title
