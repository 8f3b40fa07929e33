"""Figures after the paper, rendered in memory (Agg) and returned as PNG bytes so the
stage can write them atomically after everything else succeeded.

* ``trajectories.png``: 3-D trajectories (equal scale on the three axes) and their XZ
  projection versus ground truth (estimates aligned to it with evo's SE(3) Umeyama, no
  scale);
* ``relative_se3.png``: the six se(3) coordinates (v, w) of gap-1 relative poses over
  time, each estimate versus ground truth, a legend in every panel;
* ``outliers.png``: one se(3) coordinate of the gap-1 edges versus ground truth, with
  high-variance edges and rejected edges marked (one marker per kind, one colour per
  source; the legend names only what the figure shows);
* ``error_over_time.png``: translation error over time after alignment (without ground
  truth: whitened edge residuals over time).

Every time axis is the sequence's own time (the trajectories' timestamps: 7-Scenes and
synthetic frame ``k`` at ``k / 30`` s, TUM the recording's clock), so that a figure of
frames 450:600 reads 15-20 s and lines up with other runs over the same frames.
"""

from __future__ import annotations

import copy
import io
from collections.abc import Sequence

import numpy as np
from numpy.typing import NDArray

from ctcvo.data import geometry as geo
from ctcvo.data import metrics
from ctcvo.data.formats import Edge, Trajectory

SE3_NAMES = ("v_x", "v_y", "v_z", "w_x", "w_y", "w_z")
COLORS = {"gt": "k", "teacher": "tab:orange", "learner": "tab:blue", "fused": "tab:green"}
#: line styles that tell the series apart where they overlap: ground truth a wide grey
#: band underneath, each estimate its own colour, dash pattern and marker
STYLES = {"gt": dict(color="0.55", ls="-", lw=2.6, zorder=1),
          "teacher": dict(color=COLORS["teacher"], ls="-", lw=1.0, marker="o", zorder=3),
          "learner": dict(color=COLORS["learner"], ls="--", lw=1.0, marker="^", zorder=2),
          "fused": dict(color=COLORS["fused"], ls=":", lw=1.4, marker="s", zorder=4)}
_MARKERS = 24  # markers per line


def _style(name: str, n: int) -> dict:
    """Plot keywords of a series of ``n`` points (markers spaced ~``_MARKERS`` per line)."""
    st = dict(STYLES.get(name, dict(ls="-", lw=1.0, marker="d", zorder=2)))
    if "marker" in st:
        st.update(ms=3.5, mfc="none", markevery=max(1, n // _MARKERS))
    return st


def _figure(w: float, h: float):
    """A matplotlib figure on the Agg canvas (no display needed)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(w, h), dpi=100)
    FigureCanvasAgg(fig)
    return fig


def _png(fig) -> bytes:
    buf = io.BytesIO()
    fig.tight_layout()
    fig.savefig(buf, format="png")
    return buf.getvalue()


def align_to(gt: NDArray[np.float64], est: NDArray[np.float64], times: NDArray[np.float64]) -> NDArray[np.float64]:
    """``est`` (N, 4, 4) aligned to ``gt`` by evo's SE(3) Umeyama (no scale), fitted on the
    frames whose ground truth is finite (NaN rows: frames the teacher left out of its
    evaluation, :func:`posegraph.optimize._groundtruth`)."""
    has = np.isfinite(gt).all(axis=(1, 2))
    if not has.all():
        e = Trajectory(times[has], est[has]).to_evo()
        r, t, _ = e.align(Trajectory(times[has], gt[has]).to_evo(), correct_scale=False)
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = r, t
        return T @ est
    e = copy.deepcopy(Trajectory(times, est).to_evo())
    e.align(Trajectory(times, gt).to_evo(), correct_scale=False)
    return Trajectory.from_evo(e).poses


def _rel_log(poses: NDArray[np.float64]) -> NDArray[np.float64]:
    return geo.se3_log(metrics.relative_poses(poses))


def make_plots(times: NDArray[np.float64], rows: dict[str, NDArray[np.float64]],
               gt: NDArray[np.float64] | None, frame_ids: NDArray[np.int64],
               edges: Sequence[Edge], residuals: NDArray[np.float64], rejected: NDArray[np.bool_]) -> dict[str, bytes]:
    """All figures as ``{file name: PNG bytes}``.

    Args:
        times: (N,) timestamps; rows: name -> (N, 4, 4) ``T_world_cam`` estimates;
        gt: (N, 4, 4) ground truth or None; edges, residuals (E,), rejected (E,) bool.
    """
    t = np.asarray(times, dtype=np.float64)  # the sequence's own time
    aligned = {n: (align_to(gt, p, times) if gt is not None else p) for n, p in rows.items()}
    gt_rel = _rel_log(gt) if gt is not None else None
    pos = {int(k): p for p, k in enumerate(frame_ids)}
    return {"trajectories.png": _trajectories(gt, aligned),
            "relative_se3.png": _relative_se3(t, rows, gt_rel),
            "outliers.png": _outliers(t, pos, gt_rel, edges, rejected),
            "error_over_time.png": _error_over_time(t, pos, gt, aligned, edges, residuals, rejected)}


def _trajectories(gt: NDArray[np.float64] | None, aligned: dict[str, NDArray[np.float64]]) -> bytes:
    """3-D trajectories and their XZ projection."""
    from matplotlib.ticker import MaxNLocator

    fig = _figure(12, 5.5)
    ax3 = fig.add_subplot(1, 2, 1, projection="3d")
    ax2 = fig.add_subplot(1, 2, 2)
    series = ([("gt", gt)] if gt is not None else []) + list(aligned.items())
    for n, p in series:
        xyz = p[:, :3, 3]
        ax3.plot(xyz[:, 0], xyz[:, 1], xyz[:, 2], label=n, **_style(n, len(xyz)))
        ax2.plot(xyz[:, 0], xyz[:, 2], label=n, **_style(n, len(xyz)))
    ax3.set_aspect("equal")  # metres alike on x, y and z
    for axis in (ax3.xaxis, ax3.yaxis, ax3.zaxis):
        axis.set_major_locator(MaxNLocator(4))  # a short axis keeps legible ticks
    ax3.set_xlabel("x [m]")
    ax3.set_ylabel("y [m]")
    ax3.set_zlabel("z [m]")
    ax3.set_title("3-D trajectories" + (" (aligned to GT)" if gt is not None else ""))
    ax3.legend(loc="upper left", fontsize=8)
    ax2.set_xlabel("x [m]")
    ax2.set_ylabel("z [m]")
    ax2.set_title("XZ projection")
    ax2.axis("equal")
    ax2.legend(loc="best", fontsize=8)
    return _png(fig)


def _relative_se3(t: NDArray[np.float64], rows: dict[str, NDArray[np.float64]],
                  gt_rel: NDArray[np.float64] | None) -> bytes:
    """The six se(3) coordinates of every row's gap-1 relative poses over time."""
    fig = _figure(12, 9)
    rels = {n: _rel_log(p) for n, p in rows.items()}
    for c in range(6):
        ax = fig.add_subplot(3, 2, c + 1)
        if gt_rel is not None:
            ax.plot(t[1:], gt_rel[:, c], label="gt", **_style("gt", len(gt_rel)))
        for n, r in rels.items():
            ax.plot(t[1:], r[:, c], label=n, **_style(n, len(r)))
        ax.set_ylabel(SE3_NAMES[c] + (" [m]" if c < 3 else " [rad]"))
        if c >= 4:
            ax.set_xlabel("time [s]")
        ax.legend(fontsize=7, loc="lower right", bbox_to_anchor=(1.0, 1.0), ncol=len(rels) + (gt_rel is not None),
                  frameon=False, borderaxespad=0.2)  # above the panel, off the data
    fig.suptitle("gap-1 relative poses in se(3) (v, w)")
    return _png(fig)


def _outliers(t: NDArray[np.float64], pos: dict[int, int], gt_rel: NDArray[np.float64] | None,
              edges: Sequence[Edge], rejected: NDArray[np.bool_]) -> bytes:
    """Forward translation (v_z) of the gap-1 edges of each source, high-variance and rejected edges marked."""
    fig = _figure(12, 4.5)
    ax = fig.add_subplot(1, 1, 1)
    if gt_rel is not None:
        ax.plot(t[1:], gt_rel[:, 2], label="gt", **_style("gt", len(gt_rel)))
    sig = np.array([np.sqrt(max(np.linalg.eigvalsh(e.cov[:3, :3]).max(), 0.0)) for e in edges]) if edges else np.array([])
    hi = sig > np.quantile(sig, 0.9) if len(sig) else sig.astype(bool)
    for src in sorted({str(e.extra.get("source", "edges")) for e in edges}):
        idx = [n for n, e in enumerate(edges) if e.extra.get("source", "edges") == src and pos[e.j] - pos[e.i] == 1]
        if not idx:
            continue
        tt = np.array([t[pos[edges[n].j]] for n in idx])
        vz = np.array([geo.se3_log(edges[n].T_i_j)[2] for n in idx])
        color = COLORS.get(src, "tab:purple")
        ax.plot(tt, vz, ".", ms=4, color=color, label=f"{src} edge ({len(idx)})", zorder=3)
        for mask, kind in ((hi[idx], dict(marker="o", mfc="none", ms=8, mew=1.2, label="top-10 % sigma of all edges")),
                           (rejected[idx], dict(marker="x", ms=8, mew=1.5, label="rejected by the graph"))):
            if mask.any():  # only what appears gets a legend entry
                label = f"{src}: {kind.pop('label')} ({int(mask.sum())})"
                ax.plot(tt[mask], vz[mask], ls="none", color=color, label=label, zorder=4, **kind)
    ax.set_xlabel("time [s]")
    ax.set_ylabel("v_z [m]")
    ax.legend(fontsize=7, loc="upper right")
    ax.set_title("gap-1 edges, forward se(3) coordinate v_z; high-variance and rejected edges marked")
    return _png(fig)


def _error_over_time(t: NDArray[np.float64], pos: dict[int, int], gt: NDArray[np.float64] | None,
                     aligned: dict[str, NDArray[np.float64]], edges: Sequence[Edge], residuals: NDArray[np.float64],
                     rejected: NDArray[np.bool_]) -> bytes:
    """Each row's aligned translation error over time, or without ground truth the edges' residuals."""
    fig = _figure(12, 4)
    ax = fig.add_subplot(1, 1, 1)
    if gt is not None:
        for n, p in aligned.items():
            ax.plot(t, np.linalg.norm(p[:, :3, 3] - gt[:, :3, 3], axis=1), label=n, **_style(n, len(p)))
        ax.set_ylabel("translation error [m]")
        ax.set_title("absolute error over time (aligned)")
    else:
        te = np.array([t[max(pos[e.i], pos[e.j])] for e in edges])
        ax.semilogy(te, np.maximum(residuals, 1e-6), ".", ms=3, label="edge residual")
        if rejected.any():
            ax.semilogy(te[rejected], np.maximum(residuals[rejected], 1e-6), "x", color="m", label="rejected")
        ax.set_ylabel("whitened residual")
        ax.set_title("edge residuals over time (no ground truth)")
    ax.set_xlabel("time [s]")
    ax.legend(fontsize=8)
    return _png(fig)
