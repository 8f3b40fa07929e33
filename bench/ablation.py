"""Ablation of the seven learner variants (cnn/lstm x gt/unsup/aug, ctc): the paper's table.

Each variant is trained with the same preset, schedule and seed on ``--frames`` of the
``--scene`` scenes (repeatable) and evaluated by ``learner predict`` on ``--test-frames`` of
``--test-scene`` (default: the first ``--scene``). Teacher labels come from ``--teacher`` (one
training scene only) or from each scene's default teacher folder ``runs/<scene-slug>/teacher``
(made by ``ctcvo teacher generate`` first). ``--teacher-eval`` adds the teacher itself as a row: a
teacher output folder whose ``trajectory.tum`` covers the test frames (its poses are matched
to the test frames by timestamp, so a folder of a longer range works too).

Columns (all against the ground truth, metrics from :mod:`data.metrics` / evo):
``ate_rmse_m`` over the whole test range; ``ate_sub_mean_m`` +- ``ate_sub_std_m``, the
paper's ATE: mean and standard deviation of the ATE RMSE of sub-trajectories of
``--sub-length`` frames every ``--sub-stride`` frames, each aligned on its own (SE(3)
Umeyama, no scale); gap-1 RPE; the paper's se(3) L2 error of the gap-1 relative poses; the
MC-dropout covariance calibration keys of ``learner predict``. The runs go to ``--out``
(default ``runs/bench/<name>``); the record ``bench/results/<name>.json`` (bench/record.py,
rewritten after each variant, with the load average then) holds the rows, and stdout gets
them as Markdown tables. Beside every learned row stand the trivial baselines of
:func:`data.metrics.baseline_trajectories` on the test frames (computed once from the test
ground truth): results ``zero_motion`` (the camera never moves) and ``constant_velocity``
(each step repeats the previous true step), with the trajectory columns only.

    S=../shared/data/7scenes/redkitchen/seq-sample
    .venv/bin/python -m ctcvo teacher generate --scene $S --out runs/rk/teacher
    .venv/bin/python -m bench.ablation --scene $S --frames 0:350 --test-frames 450:600 \\
        --teacher runs/rk/teacher --teacher-eval runs/rk/teacher --val-scene $S --val-frames 350:450 \\
        --name ablation-redkitchen
    .venv/bin/python -m bench.ablation --scene synthetic/office --scene synthetic/lab \\
        --test-scene synthetic/kitchen --steps 300 --name ablation-synthetic

``--init CKPT`` fine-tunes every variant from a checkpoint (e.g. one pretrained on the
synthetic corpus) instead of training it from scratch.
"""

from __future__ import annotations

import argparse
import logging
import os
import time
from pathlib import Path

import numpy as np
import torch

from bench import record
from ctcvo.data.formats import Trajectory, read_tum
from ctcvo.data.metrics import BASELINE_KEYS, associate, ate_rmse, baseline_trajectories, trajectory_report
from ctcvo.data.scenes import open_scene
from ctcvo.learner.config import INPUTS, VARIANTS, PredictConfig
from ctcvo.learner.predict import predict
from ctcvo.learner.train import fit

TRAJ_KEYS = ["ate_rmse_m", "ate_sub_mean_m", "ate_sub_std_m", "rpe_trans_rmse_m", "rpe_rot_rmse_deg", "se3_l2_mean"]
CAL_KEYS = ["spearman_sigma_error", "coverage_1sigma", "coverage_2sigma", "outlier_auroc"]


def sub_trajectory_ate(gt: Trajectory, est: Trajectory, length: int, stride: int) -> np.ndarray:
    """ATE RMSE (m) of every sub-trajectory of ``length`` poses starting every ``stride``
    poses, each aligned on its own by evo (SE(3) Umeyama). Inputs: same timestamps, (N, 4, 4)."""
    if length < 2 or len(gt) < length:
        return np.array([ate_rmse(gt, est)])
    starts = range(0, len(gt) - length + 1, stride)
    return np.array([ate_rmse(Trajectory(gt.timestamps[a:a + length], gt.poses[a:a + length]),
                              Trajectory(est.timestamps[a:a + length], est.poses[a:a + length])) for a in starts])


def trajectory_row(gt: Trajectory, est: Trajectory, length: int, stride: int) -> dict[str, float]:
    """The trajectory columns of the table for one estimate."""
    sub = sub_trajectory_ate(gt, est, length, stride)
    rep = trajectory_report(gt, est)
    rep.update(ate_sub_mean_m=float(sub.mean()), ate_sub_std_m=float(sub.std()), ate_sub_count=len(sub))
    return rep


def baseline_rows(gt: Trajectory, length: int, stride: int) -> dict[str, dict]:
    """The trajectory columns of the trivial baselines (keys ``zero_motion``,
    ``constant_velocity``) on the test ground truth, each with its ``label``."""
    return {BASELINE_KEYS[name]: {"label": name, **trajectory_row(gt, est, length, stride)}
            for name, est in baseline_trajectories(gt).items()}


def test_groundtruth(scene: str, frames: str | None) -> Trajectory:
    """Ground truth of the (single) test sequence."""
    seqs = open_scene(scene, frames=frames)
    if len(seqs) != 1 or seqs[0].groundtruth() is None:
        raise SystemExit(f"the table needs one test sequence with ground truth, {scene} has {len(seqs)}")
    return Trajectory(seqs[0].times(), seqs[0].groundtruth())


def teacher_row(folder: Path, gt: Trajectory, length: int, stride: int) -> dict[str, float]:
    """The teacher's chained gap-1 trajectory on the test frames, matched by timestamp."""
    est = read_tum(folder / "trajectory.tum")
    ref, est = associate(gt, est)
    if len(ref) != len(gt):
        raise SystemExit(f"{folder}/trajectory.tum covers {len(ref)} of the {len(gt)} test frames")
    return trajectory_row(ref, est, length, stride)


def fmt(x: object) -> str:
    return "-" if x is None else (f"{x:.4g}" if isinstance(x, float) else str(x))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scene", action="append", required=True, help="training scene (repeatable)")
    ap.add_argument("--frames", help="training frame range")
    ap.add_argument("--test-scene", help="evaluation scene (default --scene)")
    ap.add_argument("--test-frames", help="evaluation frame range")
    ap.add_argument("--teacher", type=Path, help="teacher output folder of --scene (one training scene only)")
    ap.add_argument("--teacher-eval", type=Path, help="teacher output folder covering the test frames (teacher row)")
    ap.add_argument("--variants", nargs="+", default=list(VARIANTS), choices=list(VARIANTS))
    ap.add_argument("--preset", default="cpu")
    ap.add_argument("--steps", type=int, help="optimiser steps per variant (default: the preset's)")
    ap.add_argument("--lr", type=float, help="peak learning rate (default: the preset's)")
    ap.add_argument("--init", type=Path, help="fine-tune every variant from this learner checkpoint's weights "
                    "(learner fit --init; default: random initialisation)")
    ap.add_argument("--input", choices=list(INPUTS), help="encoder input (default: the preset's)")
    ap.add_argument("--val-scene", action="append", default=[], help="validation scene (repeatable; logged per epoch)")
    ap.add_argument("--val-frames", help="validation frame range (never the test range)")
    ap.add_argument("--samples", type=int, default=10)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--flip-prob", type=float, help="left-right mirroring augmentation (default: the preset's)")
    ap.add_argument("--reverse-prob", type=float, help="time-reversal augmentation (default: the preset's)")
    ap.add_argument("--sub-length", type=int, default=30, help="frames per sub-trajectory of the ATE mean +- std")
    ap.add_argument("--sub-stride", type=int, default=15, help="frames between sub-trajectory starts")
    ap.add_argument("--out", type=Path, help="the variants' runs (default runs/bench/NAME)")
    record.add_arguments(ap, "ablation")
    args = ap.parse_args()
    args.out = args.out or record.RUNS / args.name
    if args.teacher is not None and len(args.scene) > 1:
        ap.error("--teacher needs a single --scene (several scenes read runs/<scene-slug>/teacher)")
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    test_scene = args.test_scene or args.scene[0]
    gt = test_groundtruth(test_scene, args.test_frames)
    rows: dict[str, dict] = {}
    if args.teacher_eval is not None:
        rows["teacher"] = teacher_row(args.teacher_eval, gt, args.sub_length, args.sub_stride)
    rows.update(baseline_rows(gt, args.sub_length, args.sub_stride))
    rec = record.from_args(args, torch_threads=torch.get_num_threads())
    for v in args.variants:
        run = args.out / v
        t0, c0 = time.perf_counter(), time.process_time()
        res = fit(args.scene, variant=v, preset=args.preset, frames=args.frames, out=run,
                  val_scenes=args.val_scene, val_frames=args.val_frames, calibrate=False,
                  teacher_root=args.teacher, steps=args.steps, init=args.init,  # a rerun keeps or continues the run
                  lr=args.lr, input=args.input, seed=args.seed, flip_prob=args.flip_prob, reverse_prob=args.reverse_prob)
        t_fit, c_fit = time.perf_counter() - t0, time.process_time() - c0
        rep = predict(res.checkpoint, test_scene, frames=args.test_frames, out=run / "predict",
                      config=PredictConfig(samples=args.samples)).reports[0]
        est = read_tum(run / "predict" / "trajectory.tum")
        row = trajectory_row(gt, est, args.sub_length, args.sub_stride)
        for k in ("ate_rmse_m", "rpe_trans_rmse_m", "se3_l2_mean"):  # same metrics as learner predict's report
            if rep.get(k) is not None and not np.isclose(rep[k], row[k], rtol=1e-6, atol=1e-9):
                logging.warning("%s: %s %.6g here vs %.6g in report.json", v, k, row[k], rep[k])
        rows[v] = {**row, **{k: rep.get(k) for k in CAL_KEYS}, "fit_s": round(t_fit, 1), "fit_cpu_s": round(c_fit, 1),
                   "epochs": res.epochs_done, "steps": res.history[-1]["steps"] if res.history else 0,
                   "final_loss": res.history[-1].get("windows_loss", res.history[-1].get("pairs_loss")),
                   "loadavg_1_5_15": [round(x, 2) for x in os.getloadavg()],
                   "finished": time.strftime("%H:%M:%S", time.gmtime())}
        rec.finish({"rows": rows})
    rec.finish({"rows": rows})
    print("| variant | ATE m (whole) | ATE m (sub-traj. mean +- std) | RPE trans m | RPE rot deg | se(3) L2 |")
    print("|---|---|---|---|---|---|")
    for v, r in rows.items():
        print(f"| {r.get('label', v)} | {fmt(r['ate_rmse_m'])} | "
              f"{fmt(r['ate_sub_mean_m'])} +- {fmt(r['ate_sub_std_m'])} | "
              f"{fmt(r['rpe_trans_rmse_m'])} | {fmt(r['rpe_rot_rmse_deg'])} | {fmt(r['se3_l2_mean'])} |")
    print()
    print("| variant | " + " | ".join(CAL_KEYS) + " | fit s (wall / CPU) | steps |")
    print("|---" * (len(CAL_KEYS) + 3) + "|")
    for v, r in rows.items():
        if v == "teacher" or v in BASELINE_KEYS.values():
            continue
        print(f"| {v} | " + " | ".join(fmt(r[k]) for k in CAL_KEYS) + f" | {r['fit_s']} / {r['fit_cpu_s']} | {r['steps']} |")


if __name__ == "__main__":
    main()
