"""Per-gap covariance scales of one edge source from the consistency of its own multi-gap
edges: no ground truth.

A source with edges at gaps 1..K measures every stretch of the trajectory several times
(gap-1 chains against gap-2 edges against ...). In a least-squares fit of all of them, the
residuals tell how far the edges disagree; with correct covariances the squared whitened
residuals of a group add up to that group's share of the graph's redundancy. Variance-
component estimation (Förstner 1979; Koch, *Parameter Estimation and Hypothesis Testing
in Linear Models*, ch. 3.6) turns that into one scale per group (here: per gap ``g``):

    s_g <- s_g * sum_{e in g} r_e^2 / sum_{e in g} rho_e

with ``r_e^2 = d_e^T (s_g C_e)^-1 d_e`` the squared whitened residual of edge ``e`` and
``rho_e = 6 - tr((s_g C_e)^-1 J_e Sigma J_e^T)`` its redundancy number (the part of its
error the fit leaves in its residual; ``Sigma`` the covariance of the poses, ``J_e`` the
Jacobian of the edge's prediction), iterated to a fixed point. The solve uses the Huber
kernel of :class:`~posegraph.config.PoseGraphConfig`, and edges beyond ``trim`` whitened
residuals (relative to their redundancy) are left out of the sums, so that a few gross
failures do not inflate every covariance; the scales then describe the edges' core error.

Error the edges share (a bias every gap repeats, ground-truth jitter) is invisible to any
consistency check, so the scales are a lower bound on the real error; on the synthetic
rooms they bring the teacher's NEES/6 from ~100 to the 0.5-3 band (bench/README.md, "Pose
graph": "Teacher covariance calibration").

Fitted on a validation range (``posegraph calibrate``) and written as JSON
(docs/formats.md, "Pose graph"); ``posegraph optimize --teacher-calibration FILE`` applies
it to the teacher's edges of another range or scene.
"""

from __future__ import annotations

import dataclasses
import logging
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ctcvo.data import geometry as geo
from ctcvo.data.errors import DataError, FormatError
from ctcvo.data.formats import Edge
from ctcvo.data.io import git_revision, read_json_file, write_json
from ctcvo.data.runs import Fingerprint, claim, output_folder, upstream_digest
from ctcvo.data.uncertainty import CHI2_6_MEDIAN
from ctcvo.posegraph import edges as pe
from ctcvo.posegraph.config import DEFAULT, PoseGraphConfig
from ctcvo.posegraph.graph import solve
from ctcvo.posegraph.report import nees
from ctcvo.posegraph.sources import find_sequence_dirs, load_dir, poses_for_frames, resolve_frames

log = logging.getLogger(__name__)

CALIBRATION_FORMAT = 1
#: Frames per block of the redundancy computation (a dense (6N)^2 array per block).
BLOCK_FRAMES = 400


@dataclass
class GapScales:
    """Covariance scale per frame gap; gaps without their own fit use the nearest fitted gap."""

    scales: dict[int, float]
    info: dict[str, Any] = field(default_factory=dict)

    def scale(self, gap: int) -> float:
        if not self.scales:
            return 1.0
        if gap in self.scales:
            return self.scales[gap]
        return self.scales[min(self.scales, key=lambda g: (abs(g - gap), -g))]

    def apply(self, frame_ids: NDArray[np.int64], edges: Sequence[Edge]) -> list[Edge]:
        """Copies of ``edges`` with covariances times their gap's scale (gap in positions of
        the sorted ``frame_ids``); ``extra["cov_scale"]`` records the factor."""
        pos = {int(k): p for p, k in enumerate(np.sort(np.asarray(frame_ids)))}
        out = []
        for e in edges:
            s = self.scale(abs(pos[e.j] - pos[e.i]))
            out.append(dataclasses.replace(e, cov=np.asarray(e.cov) * s, extra={**e.extra, "cov_scale": s}))
        return out

    def to_dict(self) -> dict[str, Any]:
        return {"format": CALIBRATION_FORMAT, **self.info,
                "scales": {str(g): float(s) for g, s in sorted(self.scales.items())}}


def read_gap_scales(path: Path) -> GapScales:
    """Read and validate a per-gap calibration file (:class:`FormatError` says what is wrong)."""
    path = Path(path)
    d = read_json_file(path, "per-gap covariance calibration", CALIBRATION_FORMAT, "scales", dict)
    try:
        scales = {int(g): float(s) for g, s in d["scales"].items()}
    except (TypeError, ValueError) as exc:
        raise FormatError(f"{path}: scales must map gaps to numbers ({exc})") from None
    if not scales or any(g < 1 or not (np.isfinite(s) and s > 0) for g, s in scales.items()):
        raise FormatError(f"{path}: needs at least one gap >= 1 with a finite positive scale")
    return GapScales(scales, {k: v for k, v in d.items() if k not in ("format", "scales")})


def _adjoint_inv(T: NDArray[np.float64]) -> NDArray[np.float64]:
    """(E, 6, 6) adjoints of ``inv(T)`` for (E, 4, 4) ``T``, project order (v, w):
    ``Ad(T) = [[R, [t]x R], [0, R]]``."""
    R, t = T[:, :3, :3].transpose(0, 2, 1), -np.einsum("nji,nj->ni", T[:, :3, :3], T[:, :3, 3])
    tx = np.zeros((len(T), 3, 3))
    tx[:, 0, 1], tx[:, 0, 2], tx[:, 1, 2] = -t[:, 2], t[:, 1], -t[:, 0]
    tx -= tx.transpose(0, 2, 1)
    out = np.zeros((len(T), 6, 6))
    out[:, :3, :3] = out[:, 3:, 3:] = R
    out[:, :3, 3:] = tx @ R
    return out


def _banded_inverse(H: NDArray[np.float64], bw: int) -> NDArray[np.float64]:
    """The entries of ``inv(H)`` within ``bw`` of the diagonal (others 0) of a symmetric
    positive-definite matrix with that bandwidth: banded Cholesky ``H = L L^T`` (LAPACK)
    and the Takahashi recurrence ``Z_ij = delta_ij / L_jj^2 - sum_k Z_ik L_kj / L_jj``
    (Takahashi, Fagan and Chin 1973), O(n bw^2) instead of a dense inverse."""
    from scipy.linalg import cholesky_banded

    n = len(H)
    ab = np.zeros((bw + 1, n))
    for d in range(bw + 1):
        ab[d, :n - d] = np.diagonal(H, -d)
    Lb = cholesky_banded(ab, lower=True)  # Lb[d, j] = L[j + d, j]
    Z = np.zeros((n + bw, n + bw))  # padded: no bounds checks at the end
    for j in range(n - 1, -1, -1):
        ljj, l = Lb[0, j], Lb[1:, j]  # l[k] = L[j + 1 + k, j]
        z = -(Z[j + 1:j + 1 + bw, j + 1:j + 1 + bw] @ l) / ljj
        Z[j + 1:j + 1 + bw, j] = Z[j, j + 1:j + 1 + bw] = z
        Z[j, j] = 1.0 / ljj**2 - float(z @ l) / ljj
    return Z[:n, :n]


def redundancy_numbers(poses: NDArray[np.float64], pos: NDArray[np.int64], covs: NDArray[np.float64],
                       prior_sigma: float = 1e-6) -> NDArray[np.float64]:
    """(E,) redundancy numbers ``rho_e = 6 - tr(C_e^-1 J_e Sigma J_e^T)`` of the linear
    least-squares graph with edges at positions ``pos`` (E, 2) of ``poses`` (N, 4, 4) and
    covariances ``covs`` (E, 6, 6), project order, the first pose fixed by a tight prior.

    ``J_e = [-Ad(inv(T_i_j)), I]`` (blocks of poses i and j) is the Jacobian of the right-
    perturbation residual at a zero residual, ``Sigma`` the inverse of ``H = sum_e J_e^T
    C_e^-1 J_e``; only its entries within the graph's bandwidth are computed
    (:func:`_banded_inverse`). The numbers add up to ``6 E - 6 (N - 1)``."""
    n = len(poses)
    i, j = pos[:, 0], pos[:, 1]
    T = np.einsum("nji,njk->nik", poses[i][:, :3, :3], poses[j][:, :3, :3])
    Tij = np.zeros((len(pos), 4, 4))
    Tij[:, :3, :3] = T
    Tij[:, :3, 3] = np.einsum("nji,nj->ni", poses[i][:, :3, :3], poses[j][:, :3, 3] - poses[i][:, :3, 3])
    Tij[:, 3, 3] = 1.0
    W = np.linalg.inv(covs)
    Ji = -_adjoint_inv(Tij)
    H = np.zeros((6 * n, 6 * n))
    Hr = H.reshape(n, 6, n, 6)
    blocks = {(0, 0): (Ji, Ji), (0, 1): (Ji, None), (1, 1): (None, None)}
    for (a, b), (Ja, Jb) in blocks.items():
        left = Ja.transpose(0, 2, 1) @ W if Ja is not None else W
        M = left @ Jb if Jb is not None else left
        ra, rb = (i if a == 0 else j), (i if b == 0 else j)
        np.add.at(Hr, (ra, slice(None), rb, slice(None)), M)
        if a != b:
            np.add.at(Hr, (rb, slice(None), ra, slice(None)), M.transpose(0, 2, 1))
    Hr[0, :, 0, :] += np.eye(6) / prior_sigma**2
    bw = 6 * (int(np.max(np.abs(j - i))) + 1) - 1
    Z = _banded_inverse(H, bw).reshape(n, 6, n, 6)
    Zii, Zjj, Zij = Z[i, :, i, :], Z[j, :, j, :], Z[i, :, j, :]
    # covariance of the predicted relative pose: Ji Zii Ji^T + Zjj + Ji Zij + Zji Ji^T
    P = Ji @ Zii @ Ji.transpose(0, 2, 1) + Zjj + Ji @ Zij + (Ji @ Zij).transpose(0, 2, 1)
    return 6.0 - np.einsum("nij,nji->n", W, P)


def fit_gap_scales(frame_ids: NDArray[np.int64], edges: Sequence[Edge], initial: NDArray[np.float64] | None = None,
                   cfg: PoseGraphConfig = DEFAULT, iterations: int = 20, tol: float = 0.01,
                   trim: float = 4.0, min_edges: int = 20) -> GapScales:
    """Per-gap covariance scales of one source's ``edges`` by variance-component
    estimation (module doc). ``frame_ids`` sorted; ``initial`` (N, 4, 4) start poses
    (default: the chained edges). Gaps with fewer than ``min_edges`` edges share the scale
    of the nearest fitted gap. Returns :class:`GapScales` with ``info`` holding the
    per-gap edge counts, trimmed counts, redundancy sums and the iterations."""
    frame_ids = np.sort(np.asarray(frame_ids, dtype=np.int64))
    edges = list(edges)
    a = pe.edge_arrays(frame_ids, edges)
    pe.validate_edges(frame_ids, edges, a)
    pe.check_connected(frame_ids, edges, a)
    own = np.array([src != "bridge" for src in a.source], dtype=bool)  # bridge edges join, never calibrate
    gap = np.where(own, a.gap, 0)
    gaps = sorted({int(g) for g in gap[own] if (gap == g).sum() >= min_edges})
    if not gaps:
        raise pe.GraphError(f"no gap has {min_edges} edges to calibrate on")
    if initial is None:
        initial = pe.chain_poses(frame_ids, edges)
    solve_cfg = dataclasses.replace(cfg, calibrate=False, residual_threshold=float("inf"), marginals=False,
                                    solver="lm")
    scale = {g: 1.0 for g in gaps}
    poses = np.asarray(initial, dtype=np.float64)
    # one robust start: the median whitened residual puts every gap near its scale
    info: dict[str, Any] = {"iterations": 0, "converged": False}
    for it in range(iterations + 1):
        s_e = np.array([scale.get(int(g), scale[min(gaps, key=lambda x: abs(x - g))]) if g else 1.0 for g in gap])
        covs = a.cov * s_e[:, None, None]
        scaled = [dataclasses.replace(e, cov=c) for e, c in zip(edges, covs)]
        poses = solve(frame_ids, scaled, poses, solve_cfg, label=f"per-gap scales, round {it + 1}").poses
        r2 = pe.edge_residuals(poses, a.pos, geo.orthonormalize(a.T), np.linalg.inv(covs)) ** 2
        rho = np.zeros(len(edges))
        for lo in range(0, len(frame_ids) - 1, BLOCK_FRAMES):
            hi = min(lo + BLOCK_FRAMES, len(frame_ids) - 1)
            inside = (a.pos.min(axis=1) >= lo) & (a.pos.max(axis=1) <= hi)
            rho[inside] = redundancy_numbers(poses[lo:hi + 1], a.pos[inside] - lo, covs[inside])
        keep = own & (rho > 1e-3) & (r2 <= trim**2 * np.maximum(rho, 1e-3))
        factor = {}
        for g in gaps:
            m = keep & (gap == g)
            factor[g] = float(r2[m].sum() / rho[m].sum()) if rho[m].sum() > 0 else 1.0
        info.update({"edges": {str(g): int((gap == g).sum()) for g in gaps},
                     "trimmed": {str(g): int(((gap == g) & ~keep).sum()) for g in gaps},
                     "redundancy": {str(g): float(rho[gap == g].sum()) for g in gaps},
                     "last_factor": {str(g): factor[g] for g in gaps}})
        if all(abs(np.log(f)) <= np.log1p(tol) for f in factor.values()):
            info["converged"] = True
            break
        if it == iterations:
            break
        if it == 0:  # first one common factor: exact in one step (a common scale leaves the fit as it is)
            common = float(r2[keep].sum() / rho[keep].sum())
            scale = {g: scale[g] * common for g in gaps}
        else:
            scale = {g: scale[g] * factor[g] for g in gaps}
        info["iterations"] = it + 1
        log.info("per-gap covariance scales %s", ", ".join(f"gap {g}: {s:.3g}" for g, s in scale.items()))
    info["trim"] = trim
    return GapScales(scale, info)


METHODS = ("consistency", "groundtruth")


def groundtruth_gap_scales(frame_ids: NDArray[np.int64], edges: Sequence[Edge], gt_poses: NDArray[np.float64],
                           min_edges: int = 20) -> tuple[dict[int, NDArray[np.float64]], dict[int, float]]:
    """Per gap: the NEES (squared Mahalanobis distance to the ground truth) of every edge
    and the scale ``median(NEES) / median(chi2_6)`` that makes the gap's median consistent.
    The median, not the mean: the teacher's errors are heavy-tailed, and a mean-based scale
    (office -> lab, validation) over-covered (1-sigma coverage 0.89, NEES/6 0.59) where the
    median-based one came out at 0.70 / 1.39 (bench/README.md)."""
    frame_ids = np.sort(np.asarray(frame_ids, dtype=np.int64))
    pos = {int(k): p for p, k in enumerate(frame_ids)}
    gap = np.array([abs(pos[e.j] - pos[e.i]) for e in edges])
    v = nees(edges, frame_ids, gt_poses)
    by = {int(g): v[gap == g] for g in np.unique(gap) if (gap == g).sum() >= min_edges}
    return by, {g: float(np.median(x)) / CHI2_6_MEDIAN for g, x in by.items()}


def calibrate_teacher(teachers: Sequence[Path], out: Path, max_gap: int | None = None,
                      cfg: PoseGraphConfig = DEFAULT, method: str = "consistency",
                      overwrite: bool = False) -> GapScales:
    """``posegraph calibrate``: fit per-gap scales on the teacher folders ``teachers``
    (validation ranges or scenes, never test data) and write them atomically to ``out``.

    ``consistency`` (no ground truth): :func:`fit_gap_scales` per folder, pooled per gap
    weighted by each folder's redundancy there. ``groundtruth``: the folders' own
    ``groundtruth.tum`` (for synthetic scenes, whose ground truth is exact), pooled NEES
    per gap (:func:`groundtruth_gap_scales`).

    Rerun rule (:mod:`data.runs`): ``out`` records the fingerprint of its inputs (the
    teacher folders' digests, method, max_gap, config) under ``fingerprint``; an ``out``
    of the same inputs is kept and returned, one of other inputs is replaced only with
    ``overwrite``, otherwise :class:`data.runs.StaleOutputError` says what differs."""
    if method not in METHODS:
        raise DataError(f"calibration method must be one of {', '.join(METHODS)}, got {method!r}")
    folders = []
    for t in teachers:
        t = Path(t)
        names = find_sequence_dirs(t)
        folders += [t / n for n in names] if names else [t]
    out = Path(out)
    for f in folders:
        if not (f / "edges.g2o").is_file():
            raise DataError(f"teacher folder {f} " + ("has no edges.g2o" if f.is_dir() else "does not exist"))
    fp = Fingerprint("posegraph-calibrate", {
        "teachers": {str(f.resolve()): upstream_digest(f, "edges.g2o") for f in folders},
        "method": method, "max_gap": max_gap, "config": cfg.to_dict()})
    with output_folder(out.parent):
        if claim(out.parent, fp, done=out.is_file(), has_outputs=out.is_file(), overwrite=overwrite,
                 inside=out.name, hint="pass --overwrite to replace it, or choose another --out"):
            log.info("%s: calibration of the same teacher edges and settings: kept", out)
            return read_gap_scales(out)
        res = _fit_teacher_scales(folders, max_gap, cfg, method)
        res.info["fingerprint"] = fp.to_dict()  # in the file itself: written in the same atomic step
        res.info["git"] = git_revision()
        write_json(out, res.to_dict())
    return res


def _fit_teacher_scales(folders: list[Path], max_gap: int | None, cfg: PoseGraphConfig, method: str) -> GapScales:
    """The fit of :func:`calibrate_teacher` over the sequence folders ``folders``."""
    sums: dict[int, list[float]] = {}
    pooled: dict[int, list] = {}
    per = []
    for f in folders:
        src = load_dir(f, "teacher")
        frames = resolve_frames([src])
        pos = {int(k): p for p, k in enumerate(frames.ids)}
        edges = [e for e in src.edges if max_gap is None or abs(pos[e.j] - pos[e.i]) <= max_gap]
        if method == "groundtruth":
            gt = poses_for_frames(src.groundtruth, frames)
            if gt is None:
                raise DataError(f"{f}: --method groundtruth needs a groundtruth.tum covering every frame")
            by, sc = groundtruth_gap_scales(frames.ids, edges, gt)
            for g, x in by.items():
                pooled.setdefault(g, []).append(x)
            per.append({"folder": str(f), "frames": len(frames.ids), "scales": {str(g): v for g, v in sc.items()},
                        "edges": {str(g): len(x) for g, x in by.items()}})
            continue
        init = poses_for_frames(src.trajectory, frames)
        bridges = pe.bridge_edges(frames.ids, edges, init, pe.bridge_cov(frames.ids, edges))
        if bridges:
            log.warning("%s: %d bridge edge(s) join a disconnected teacher graph (not calibrated)", f, len(bridges))
        fit = fit_gap_scales(frames.ids, edges + bridges, init, cfg)
        per.append({"folder": str(f), "frames": len(frames.ids), "scales": {str(g): v for g, v in fit.scales.items()},
                    **{k: fit.info[k] for k in ("edges", "trimmed", "redundancy", "iterations", "converged")}})
        for g, s in fit.scales.items():
            # pool per gap: weight each folder's scale by its redundancy at that gap
            w = fit.info["redundancy"][str(g)]
            acc = sums.setdefault(g, [0.0, 0.0])
            acc[0] += w * s
            acc[1] += w
    if method == "groundtruth":
        scales = {g: float(np.median(np.concatenate(x))) / CHI2_6_MEDIAN for g, x in pooled.items()}
    else:
        scales = {g: a / w for g, (a, w) in sums.items() if w > 0}
    if not scales:
        raise DataError("no gap had enough edges to calibrate")
    return GapScales(scales, {"fitted_on": per, "method": method, "max_gap": max_gap})


__all__ = ["GapScales", "calibrate_teacher", "fit_gap_scales", "read_gap_scales", "redundancy_numbers"]
