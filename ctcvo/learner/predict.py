"""``learner predict``: Monte-Carlo-dropout edges with covariances, a trajectory, a report.

For every sequence of ``--scene`` the encoder runs once per frame pair; only the dropout
and the layers after it are resampled K times (:meth:`CTCNet.direct_mc`,
:meth:`CTCNet.sequential_mc`). Per edge the K twists give a mean ``xi`` (the edge is
``exp(mean)``) and a 6x6 sample covariance in the project tangent order (v, w), which is
regularised (:data:`learner.mcdropout.COV_FLOOR` on the diagonal) and written as information ``inv(cov)``.
When the checkpoint's folder holds a ``calibration.json`` (:mod:`learner.calibrate`, fitted
on a validation scene against teacher labels) the covariances are calibrated with it
before anything is written or flagged, unless ``use_calibration=False``.

Gap-1 edges come from the LSTM head (run over chunks of ``window_max`` consecutive pairs,
as in training) for the LSTM variants and from the direct head for ``cnn-*``; gaps
2..max_gap come from the direct head. Outputs per sequence (docs/formats.md, "Learner"):
``edges.g2o``, ``edges_mc.csv``, ``trajectory.tum``, ``report.json``.
"""

from __future__ import annotations

import csv
import dataclasses
import json
import logging
import sys
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from numpy.typing import NDArray
from scipy.stats import rankdata, spearmanr

from ctcvo.data import geometry as geo
from ctcvo.data.chain import chain_steps
from ctcvo.data.errors import ConfigError, DataError
from ctcvo.data.formats import Edge, Trajectory, write_g2o, write_tum
from ctcvo.data.io import atomic_write, git_revision, json_safe, write_json
from ctcvo.data.metrics import BASELINES, baseline_reports, se3_l2_errors, trajectory_report
from ctcvo.data.runs import (
    Fingerprint,
    claim,
    file_digest,
    frames_id,
    output_folder,
    scene_id,
    stage_dir,
    write_fingerprint,
)
from ctcvo.data.scenes import open_scene
from ctcvo.data.sequence import Sequence, frame_ranges_overlap
from ctcvo.data.uncertainty import mahalanobis2, nees_stats
from ctcvo.learner.calibrate import CALIBRATION_FILE, Calibration, calibration_for
from ctcvo.learner.checkpoint import CHECKPOINT, load_model
from ctcvo.learner.config import PredictConfig, check_variant, to_dict
from ctcvo.learner.dataset import load_frames
from ctcvo.learner.mcdropout import EdgeSet, mc_edges
from ctcvo.learner.model import CTCNet

log = logging.getLogger(__name__)

MC_CSV_COLUMNS = ["i", "j", "gap", "head", "sigma", "outlier", "error_se3_l2", "mahalanobis2"]
#: what ``learner predict`` writes per sequence (``--overwrite`` removes them first)
OUTPUT_FILES = ("edges.g2o", "edges_mc.csv", "trajectory.tum", "groundtruth.tum", "config.json", "report.json")
#: an edge is flagged an outlier when its sigma exceeds this many times the median sigma of
#: its gap (set with the first MC-dropout predict, 07e3e22, not tuned since)
OUTLIER_FACTOR = 3.0


@dataclass
class PredictResult:
    """Output folder and report of every predicted sequence."""

    out_dirs: list[Path] = field(default_factory=list)
    reports: list[dict] = field(default_factory=list)


def outlier_flags(edges: EdgeSet, factor: float) -> NDArray[np.bool_]:
    """Flag edges whose sigma exceeds ``factor`` x the median sigma of edges of the same gap."""
    sig = edges.sigma
    gaps = edges.j - edges.i
    flags = np.zeros(len(sig), dtype=bool)
    for g in np.unique(gaps):
        m = gaps == g
        flags[m] = sig[m] > factor * np.median(sig[m])
    return flags


def chain(edges: EdgeSet, T0: NDArray[np.float64]) -> NDArray[np.float64]:
    """``T_world_cam`` (N, 4, 4) from chaining the gap-1 edges from ``T0``."""
    one = np.nonzero(edges.j - edges.i == 1)[0]
    one = one[np.argsort(edges.i[one])]
    return chain_steps([geo.se3_exp(edges.mean[e]) for e in one], T0)


def auroc(score: NDArray[np.float64], positive: NDArray[np.bool_]) -> float:
    """Area under the ROC curve of ``score`` for the ``positive`` class (Mann-Whitney)."""
    npos, nneg = int(positive.sum()), int((~positive).sum())
    if npos == 0 or nneg == 0:
        return float("nan")
    r = rankdata(score)
    return float((r[positive].sum() - npos * (npos + 1) / 2) / (npos * nneg))


def calibration(edges: EdgeSet, gt: NDArray[np.float64]) -> tuple[dict[str, float], NDArray, NDArray]:
    """Uncertainty quality against ground truth (N, 4, 4).

    * ``spearman_sigma_error``: rank correlation of sigma with the se(3) L2 error;
    * ``coverage_1sigma`` / ``coverage_2sigma``: fraction of edges whose error
      ``log(inv(T_est) T_gt)`` has squared Mahalanobis distance within the 6-dof chi-square
      quantile of 68.27% / 95.45% (a calibrated covariance gives those fractions);
      ``nees_mean``: the mean squared Mahalanobis distance (6 when calibrated);
    * ``outlier_auroc``: AUROC of sigma for separating the worst 10% edges by error.
    """
    T_est = np.array([geo.se3_exp(m) for m in edges.mean])
    T_gt = np.array([geo.relative_pose(gt[i], gt[j]) for i, j in zip(edges.i, edges.j)])
    err = se3_l2_errors(T_gt, T_est)
    d2 = mahalanobis2(np.array([geo.se3_log(geo.inv_T(a) @ b) for a, b in zip(T_est, T_gt)]), edges.cov)
    worst = err >= np.quantile(err, 0.9)
    # a rank correlation needs two rankings that vary (sigma is constant e.g. with 1 sample)
    varies = len(err) > 2 and np.ptp(edges.sigma) > 0 and np.ptp(err) > 0
    rho = spearmanr(edges.sigma, err).statistic if varies else float("nan")
    stats = nees_stats(d2)
    out = {
        "spearman_sigma_error": float(rho),
        "coverage_1sigma": stats["coverage_1sigma"],
        "coverage_2sigma": stats["coverage_2sigma"],
        "nees_mean": stats["nees_mean"],
        "outlier_auroc": auroc(edges.sigma, worst),
    }
    return out, err, d2


def predict(checkpoint: Path, scene: str, *, frames: str | None = None, split: str = "all",
            out: Path | None = None, config: PredictConfig = PredictConfig(), preset: str | None = None,
            progress: bool | None = None, use_calibration: bool = True, device: str = "auto",
            overwrite: bool = False) -> PredictResult:
    """Predict edges, trajectory and report for every sequence of ``scene`` (on ``device``:
    auto, cpu or cuda). With ground truth the report carries the trivial baselines'
    figures (``baselines``) beside the learner's.

    Outputs go to ``out`` (default ``runs/<scene-slug>/predict``; never a training run's
    folder) and follow the rerun rule of :mod:`data.runs`: the same checkpoint,
    calibration, scene, frames and settings are not predicted again; other inputs replace
    the old outputs only with ``overwrite``.

    ``use_calibration``: apply the ``calibration.json`` beside the checkpoint when there is
    one (an error when it was fitted for other weights or another drop ratio)."""
    checkpoint = Path(checkpoint)
    base = Path(out) if out is not None else stage_dir(scene, "predict")
    if (base / CHECKPOINT).exists() or base.resolve() == checkpoint.parent.resolve():
        raise ConfigError(f"--out {base} is a training run's folder: predict writes elsewhere (default "
                          f"{stage_dir(scene, 'predict')})")
    with output_folder(base):
        return _predict(checkpoint, scene, base, frames=frames, split=split, config=config, preset=preset,
                        progress=progress, use_calibration=use_calibration, device=device, overwrite=overwrite)


def _predict(checkpoint: Path, scene: str, base: Path, *, frames: str | None, split: str, config: PredictConfig,
             preset: str | None, progress: bool | None, use_calibration: bool, device: str,
             overwrite: bool) -> PredictResult:
    model, state = load_model(checkpoint, preset, device)
    found = calibration_for(checkpoint, config) if use_calibration else None
    if found is not None:
        log.info("applying covariance calibration %s (fitted on %s)", found[0],
                 ", ".join(map(str, found[1].info.get("scenes", []))))
    elif use_calibration:
        log.info("no %s beside %s: MC-dropout covariances are used as they are (under-estimated; "
                 "see `learner calibrate`)", CALIBRATION_FILE, checkpoint)
    seqs = open_scene(scene, split=split, frames=frames)
    if progress is None:
        progress = sys.stderr.isatty()
    result = PredictResult()
    ckpt_digest = file_digest(checkpoint)
    for seq in seqs:
        if len(seq) < 2:
            raise DataError(f"sequence {seq.name} needs at least 2 frames to predict edges")
        out_dir = base / seq.name if len(seqs) > 1 else base
        fp = Fingerprint("predict", {
            "scene": scene_id(scene), "sequence": seq.name, "frames": frames_id(seq.ids()), "checkpoint": ckpt_digest,
            "calibration": file_digest(found[0]) if found is not None else None, "predict": to_dict(config)})
        finished = (out_dir / "report.json").is_file()
        if claim(out_dir, fp, done=finished, has_outputs=finished, overwrite=overwrite, outputs=OUTPUT_FILES):
            log.info("%s: predicted edges of the same inputs in %s: kept", seq.name, out_dir)
            report = json.loads((out_dir / "report.json").read_text())
        else:
            edges = _sequence_edges(model, state, seq, base, found, frames, config, progress)
            report = _write_sequence(seq, out_dir, edges, checkpoint, state, found, config)
            write_json(out_dir / "config.json", {"scene": scene, "frames": frames, "split": split,
                                                 "checkpoint": str(checkpoint), "predict": to_dict(config),
                                                 "calibration": report["calibration"], "git_revision": git_revision()})
            write_fingerprint(out_dir, fp)
            write_json(out_dir / "report.json", report)
            log.info("%s: %d edges, %d outliers, %s covariances -> %s", seq.name, report["edges"], report["outliers"],
                     "calibrated" if found is not None else "uncalibrated", out_dir)
        result.out_dirs.append(out_dir)
        result.reports.append(report)
    return result


def _sequence_edges(model: CTCNet, state: dict, seq: Sequence, base: Path, found: tuple[Path, Calibration] | None,
                    frames: str | None, config: PredictConfig, progress: bool) -> tuple[EdgeSet, EdgeSet]:
    """The raw MC-dropout edges of ``seq`` and the same with calibrated covariances (when
    there is a calibration; else the raw ones again)."""
    uses_lstm, _, _ = check_variant(state["variant"])
    mcfg = model.cfg
    frames_u8 = load_frames(seq, mcfg.width, mcfg.height, base / "cache", mcfg.input)
    raw = mc_edges(model, frames_u8, uses_lstm=uses_lstm, window=int(state["train_config"]["window_max"]),
                   cfg=config, progress=progress)
    if found is None:
        return raw, raw
    if (seq.name in {str(s.get("sequence")) for s in found[1].info.get("sequences", [])}
            and frame_ranges_overlap(found[1].info.get("frames"), frames)):
        log.warning("%s is also a calibration sequence of %s (calibrated on frames %s, predicting %s): "
                    "uncertainty figures on calibration frames are optimistic", seq.name, found[0],
                    found[1].info.get("frames") or "all", frames or "all")
    return raw, dataclasses.replace(raw, cov=found[1].apply(raw.cov, raw.head, raw.j - raw.i))


def _write_sequence(seq: Sequence, out_dir: Path, edges: tuple[EdgeSet, EdgeSet], checkpoint: Path, state: dict,
                    found: tuple[Path, Calibration] | None, config: PredictConfig) -> dict:
    """Write the edges, trajectories and MC csv of one sequence; its report (not written yet)."""
    raw, edges = edges
    flags = outlier_flags(edges, OUTLIER_FACTOR)  # on the calibrated covariances
    ids, gt = seq.ids(), seq.groundtruth()
    poses = chain(edges, gt[0] if gt is not None else np.eye(4))
    write_g2o(out_dir / "edges.g2o",
              [Edge(int(ids[i]), int(ids[j]), geo.se3_exp(m), c) for i, j, m, c in
               zip(edges.i, edges.j, edges.mean, edges.cov)],
              vertices={int(f): T for f, T in zip(ids, poses)})
    write_tum(out_dir / "trajectory.tum", Trajectory(seq.times(), poses))
    report: dict = {
        "sequence": seq.name, "frames": len(seq), "checkpoint": str(checkpoint), "preset": state["preset"],
        "variant": state["variant"], "samples": config.samples, "drop": config.drop,
        "max_gap": int((edges.j - edges.i).max()), "edges": len(edges.i), "outliers": int(flags.sum()),
        "median_sigma_gap1": float(np.median(edges.sigma[edges.j - edges.i == 1])),
        "calibration_applied": found is not None, "calibration": str(found[0]) if found is not None else None,
        "git_revision": git_revision(),
    }
    err = d2 = None
    if gt is not None:
        gt_traj = Trajectory(seq.times(), gt)
        write_tum(out_dir / "groundtruth.tum", gt_traj)
        report.update(trajectory_report(gt_traj, Trajectory(seq.times(), poses)))
        report["baselines"] = baseline_reports(gt_traj)
        log.info("%s: against ground truth, se(3) L2 %.5f, ATE %.4f m (zero motion %.5f / %.4f m, constant "
                 "velocity %.5f / %.4f m)",
                 seq.name, report["se3_l2_mean"], report["ate_rmse_m"],
                 *(report["baselines"][b][k] for b in BASELINES for k in ("se3_l2_mean", "ate_rmse_m")))
        cal, err, d2 = calibration(edges, gt)
        report.update(cal)
        if found is not None:  # the same figures under the uncalibrated MC-dropout covariances
            raw_cal, _, _ = calibration(raw, gt)
            report.update({f"raw_{k}": raw_cal[k] for k in
                           ("coverage_1sigma", "coverage_2sigma", "nees_mean", "spearman_sigma_error")})
    _write_mc_csv(out_dir / "edges_mc.csv", edges, ids, flags, err, d2)
    return json_safe(report)


def _write_mc_csv(path: Path, edges: EdgeSet, ids: NDArray[np.int64], flags: NDArray[np.bool_],
                  err: NDArray | None, d2: NDArray | None) -> None:
    sig = edges.sigma
    with atomic_write(path) as fh:
        w = csv.writer(fh, lineterminator="\n")
        w.writerow(MC_CSV_COLUMNS)
        for e in range(len(edges.i)):
            w.writerow([int(ids[edges.i[e]]), int(ids[edges.j[e]]), int(edges.j[e] - edges.i[e]), edges.head[e],
                        f"{sig[e]:.6g}", int(flags[e]),
                        "" if err is None else f"{err[e]:.6g}", "" if d2 is None else f"{d2[e]:.6g}"])
