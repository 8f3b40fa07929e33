"""Figures after the paper, rendered in memory (Agg) and returned as PNG bytes so the
stage can write them atomically after everything else succeeded.

* ``trajectories.png``: 3-D trajectories and their XZ projection versus ground truth
  (estimates aligned to it with evo's SE(3) Umeyama, no scale);
* ``relative_se3.png``: the six se(3) coordinates (v, w) of gap-1 relative poses over
  time, each estimate versus ground truth;
* ``outliers.png``: one se(3) coordinate of the edges versus ground truth, with
  high-variance edges and rejected edges marked;
* ``error_over_time.png``: translation error over time after alignment (without ground
  truth: whitened edge residuals over time).
"""

from __future__ import annotations

import copy
import io
from typing import Optional, Sequence

import numpy as np
from numpy.typing import NDArray

from data import geometry as geo
from data.formats import Edge, Trajectory

SE3_NAMES = ("v_x", "v_y", "v_z", "w_x", "w_y", "w_z")
COLORS = {"gt": "k", "teacher": "tab:orange", "learner": "tab:blue", "fused": "tab:green"}


def _figure(w: float, h: float):
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
    """``est`` (N, 4, 4) aligned to ``gt`` by evo's SE(3) Umeyama (no scale)."""
    e = copy.deepcopy(Trajectory(times, est).to_evo())
    e.align(Trajectory(times, gt).to_evo(), correct_scale=False)
    return Trajectory.from_evo(e).poses


def _rel_log(poses: NDArray[np.float64]) -> NDArray[np.float64]:
    return np.array([geo.se3_log(geo.relative_pose(poses[k], poses[k + 1])) for k in range(len(poses) - 1)])


def make_plots(times: NDArray[np.float64], rows: dict[str, NDArray[np.float64]],
               gt: Optional[NDArray[np.float64]], frame_ids: NDArray[np.int64],
               edges: Sequence[Edge], residuals: NDArray[np.float64], rejected: NDArray[np.bool_]) -> dict[str, bytes]:
    """All figures as ``{file name: PNG bytes}``.

    Args:
        times: (N,) timestamps; rows: name -> (N, 4, 4) ``T_world_cam`` estimates;
        gt: (N, 4, 4) ground truth or None; edges, residuals (E,), rejected (E,) bool.
    """
    t = times - times[0]
    aligned = {n: (align_to(gt, p, times) if gt is not None else p) for n, p in rows.items()}
    out = {}

    fig = _figure(12, 5.5)
    ax3 = fig.add_subplot(1, 2, 1, projection="3d")
    ax2 = fig.add_subplot(1, 2, 2)
    series = ([("gt", gt)] if gt is not None else []) + list(aligned.items())
    for n, p in series:
        xyz = p[:, :3, 3]
        ls = "--" if n == "gt" else "-"
        ax3.plot(xyz[:, 0], xyz[:, 1], xyz[:, 2], ls, color=COLORS.get(n), label=n, lw=1)
        ax2.plot(xyz[:, 0], xyz[:, 2], ls, color=COLORS.get(n), label=n, lw=1)
    ax3.set_xlabel("x [m]"); ax3.set_ylabel("y [m]"); ax3.set_zlabel("z [m]")
    ax3.set_title("3-D trajectories" + (" (aligned to GT)" if gt is not None else ""))
    ax2.set_xlabel("x [m]"); ax2.set_ylabel("z [m]"); ax2.set_title("XZ projection"); ax2.axis("equal")
    ax2.legend(loc="best", fontsize=8)
    out["trajectories.png"] = _png(fig)

    fig = _figure(12, 8)
    rels = {n: _rel_log(p) for n, p in rows.items()}
    gt_rel = _rel_log(gt) if gt is not None else None
    for c in range(6):
        ax = fig.add_subplot(3, 2, c + 1)
        if gt_rel is not None:
            ax.plot(t[1:], gt_rel[:, c], "k--", lw=1, label="gt")
        for n, r in rels.items():
            ax.plot(t[1:], r[:, c], color=COLORS.get(n), lw=0.8, label=n)
        ax.set_ylabel(SE3_NAMES[c] + (" [m]" if c < 3 else " [rad]"))
        if c >= 4:
            ax.set_xlabel("time [s]")
        if c == 0:
            ax.legend(fontsize=7)
    fig.suptitle("gap-1 relative poses in se(3) (v, w)")
    out["relative_se3.png"] = _png(fig)

    # outlier plot: forward translation (v_z) of the gap-1 edges of each source
    fig = _figure(12, 4.5)
    ax = fig.add_subplot(1, 1, 1)
    pos = {int(k): p for p, k in enumerate(frame_ids)}
    if gt_rel is not None:
        ax.plot(t[1:], gt_rel[:, 2], "k--", lw=1, label="gt")
    sig = np.array([np.sqrt(max(np.linalg.eigvalsh(e.cov[:3, :3]).max(), 0.0)) for e in edges]) if edges else np.array([])
    hi = sig > np.quantile(sig, 0.9) if len(sig) else sig.astype(bool)
    for src in sorted({str(e.extra.get("source", "edges")) for e in edges}):
        idx = [n for n, e in enumerate(edges) if e.extra.get("source", "edges") == src and pos[e.j] - pos[e.i] == 1]
        if not idx:
            continue
        tt = np.array([t[pos[edges[n].j]] for n in idx])
        vz = np.array([geo.se3_log(edges[n].T_i_j)[2] for n in idx])
        ax.plot(tt, vz, ".", ms=3, color=COLORS.get(src), label=f"{src} edges")
        m = hi[idx]
        ax.plot(tt[m], vz[m], "o", mfc="none", ms=7, color="tab:red", label=f"{src}: top-10 % sigma")
        r = rejected[idx]
        ax.plot(tt[r], vz[r], "x", ms=8, color="m", label=f"{src}: rejected")
    ax.set_xlabel("time [s]"); ax.set_ylabel("v_z [m]"); ax.legend(fontsize=7)
    ax.set_title("gap-1 edges, forward se(3) coordinate v_z; high-variance and rejected edges marked")
    out["outliers.png"] = _png(fig)

    fig = _figure(12, 4)
    ax = fig.add_subplot(1, 1, 1)
    if gt is not None:
        for n, p in aligned.items():
            ax.plot(t, np.linalg.norm(p[:, :3, 3] - gt[:, :3, 3], axis=1), color=COLORS.get(n), lw=1, label=n)
        ax.set_ylabel("translation error [m]"); ax.set_title("absolute error over time (aligned)")
    else:
        te = np.array([t[max(pos[e.i], pos[e.j])] for e in edges])
        ax.semilogy(te, np.maximum(residuals, 1e-6), ".", ms=3, label="edge residual")
        ax.semilogy(te[rejected], np.maximum(residuals[rejected], 1e-6), "x", color="m", label="rejected")
        ax.set_ylabel("whitened residual"); ax.set_title("edge residuals over time (no ground truth)")
    ax.set_xlabel("time [s]"); ax.legend(fontsize=8)
    out["error_over_time.png"] = _png(fig)
    return out
