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
(default ``runs/bench/<name>``, a folder ``seedS/VARIANT`` per run); the record
``bench/results/<name>.json`` (bench/record.py, rewritten after each variant, with the load
average then) holds the rows, and stdout gets them as Markdown tables. Beside every learned row stand the trivial baselines of
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

With ``--teacher-eval`` every row also carries the teacher as a second reference:
``vs_teacher`` (gap-1 RPE and se(3) L2 against the teacher's own relative poses on the test
frames) and ``se3_l2_x_teacher`` (the row's se(3) L2 against the ground truth over the
teacher's: the paper's learner / teacher ratio, 0.81 in the paper). ``--seed S [S ...]`` trains
every variant once per seed (runs ``OUT/seedS/VARIANT``; rows ``VARIANT seed S`` when several),
and the record's ``seeds`` holds each variant's mean and standard deviation over them. The
paper's kind of teacher (ORB-SLAM3, issue 27)::

    .venv/bin/python -m ctcvo teacher generate --backend orbslam3 --vocabulary ORBvoc.txt --scene $S \\
        --frames 0:600 --out runs/orb-rk/teacher
    .venv/bin/python -m bench.ablation --scene $S --frames 0:350 --test-frames 450:600 \\
        --teacher runs/orb-rk/teacher --teacher-eval runs/orb-rk/teacher --val-scene $S --val-frames 350:450 \\
        --variants ctc cnn-unsup lstm-unsup lstm-gt --seed 0 1 2 --name ablation-orbslam3-redkitchen

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
#: per epoch: se(3) L2 of each head on the training and the validation frames (vs ground truth)
CURVE_KEYS = ["steps", "train_direct_se3_l2", "train_lstm_se3_l2", "val_direct_se3_l2", "val_lstm_se3_l2"]
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


def test_groundtruth(scene: str, frames: str | None) -> Trajectory:
    """Ground truth of the (single) test sequence."""
    seqs = open_scene(scene, frames=frames)
    if len(seqs) != 1 or seqs[0].groundtruth() is None:
        raise SystemExit(f"the table needs one test sequence with ground truth, {scene} has {len(seqs)}")
    return Trajectory(seqs[0].times(), seqs[0].groundtruth())


def teacher_trajectory(folder: Path, gt: Trajectory) -> Trajectory:
    """The teacher's trajectory (``trajectory.tum``) on the test frames, matched by timestamp."""
    ref, est = associate(gt, read_tum(folder / "trajectory.tum"))
    if len(ref) != len(gt):
        raise SystemExit(f"{folder}/trajectory.tum covers {len(ref)} of the {len(gt)} test frames")
    return Trajectory(gt.timestamps, est.poses)


def versus_teacher(row: dict, est: Trajectory, teacher: Trajectory | None, teacher_row: dict | None) -> dict:
    """``row`` with the teacher as a second reference: ``vs_teacher`` (gap-1 RPE and se(3) L2 of
    ``est`` against the teacher's own relative poses) and ``se3_l2_x_teacher`` (its se(3) L2
    against the ground truth over the teacher's: the paper's learner / teacher ratio)."""
    if teacher is None or teacher_row is None:
        return row
    vs = trajectory_report(teacher, est)
    return {**row, "vs_teacher": {k: vs[k] for k in ("rpe_trans_rmse_m", "rpe_rot_rmse_deg", "se3_l2_mean")},
            "se3_l2_x_teacher": row["se3_l2_mean"] / teacher_row["se3_l2_mean"]}


def fmt(x: object) -> str:
    return "-" if x is None else (f"{x:.4g}" if isinstance(x, float) else str(x))


def parse_args() -> argparse.Namespace:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scene", action="append", required=True, help="training scene (repeatable)")
    ap.add_argument("--frames", help="training frame range")
    ap.add_argument("--test-scene", help="evaluation scene (default --scene)")
    ap.add_argument("--test-frames", help="evaluation frame range")
    ap.add_argument("--teacher", type=Path, help="teacher output folder of --scene (one training scene only)")
    ap.add_argument("--teacher-eval", type=Path, help="teacher output folder covering the test frames (teacher row, "
                    "and the second reference of every row)")
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
    ap.add_argument("--seed", type=int, nargs="+", default=[0], help="training seed(s): every variant once per seed")
    ap.add_argument("--flip-prob", type=float, help="left-right mirroring augmentation (default: the preset's)")
    ap.add_argument("--reverse-prob", type=float, help="time-reversal augmentation (default: the preset's)")
    ap.add_argument("--sub-length", type=int, default=30, help="frames per sub-trajectory of the ATE mean +- std")
    ap.add_argument("--sub-stride", type=int, default=15, help="frames between sub-trajectory starts")
    ap.add_argument("--out", type=Path, help="the variants' runs, OUT/seedS/VARIANT (default runs/bench/NAME)")
    record.add_arguments(ap, "ablation")
    args = ap.parse_args()
    args.out = args.out or record.RUNS / args.name
    if args.teacher is not None and len(args.scene) > 1:
        ap.error("--teacher needs a single --scene (several scenes read runs/<scene-slug>/teacher)")
    return args


def run_variant(args: argparse.Namespace, variant: str, seed: int, test_scene: str, gt: Trajectory) -> dict:
    """Train one variant with one seed (a rerun keeps or continues the run), predict the test
    frames and return its row."""
    run = args.out / f"seed{seed}" / variant
    t0, c0 = time.perf_counter(), time.process_time()
    res = fit(args.scene, variant=variant, preset=args.preset, frames=args.frames, out=run,
              val_scenes=args.val_scene, val_frames=args.val_frames, calibrate=False,
              teacher_root=args.teacher, steps=args.steps, init=args.init,
              lr=args.lr, input=args.input, seed=seed, flip_prob=args.flip_prob, reverse_prob=args.reverse_prob)
    t_fit, c_fit = time.perf_counter() - t0, time.process_time() - c0
    rep = predict(res.checkpoint, test_scene, frames=args.test_frames, out=run / "predict",
                  config=PredictConfig(samples=args.samples)).reports[0]
    est = read_tum(run / "predict" / "trajectory.tum")
    row = trajectory_row(gt, est, args.sub_length, args.sub_stride)
    for k in ("ate_rmse_m", "rpe_trans_rmse_m", "se3_l2_mean"):  # same metrics as learner predict's report
        if rep.get(k) is not None and not np.isclose(rep[k], row[k], rtol=1e-6, atol=1e-9):
            logging.warning("%s: %s %.6g here vs %.6g in report.json", variant, k, row[k], rep[k])
    val = res.history[-1] if res.history else {}
    return {"variant": variant, "seed": seed, "run": str(run), **row, **{k: rep.get(k) for k in CAL_KEYS},
            "fit_s": round(t_fit, 1), "fit_cpu_s": round(c_fit, 1), "epochs": res.epochs_done,
            "train_s": round(sum(h.get("train_seconds", 0.0) for h in res.history), 1),  # also of a kept run
            "steps": val.get("steps", 0), "final_loss": val.get("windows_loss", val.get("pairs_loss")),
            "last_epoch": {k: v for k, v in val.items() if isinstance(v, (int, float, str))},
            "curve": [{k: h.get(k) for k in CURVE_KEYS} for h in res.history],
            "loadavg_1_5_15": [round(x, 2) for x in os.getloadavg()],
            "finished": time.strftime("%H:%M:%S", time.gmtime()), "_est": est}


def seed_summary(rows: dict[str, dict]) -> dict[str, dict]:
    """Mean, standard deviation and count over seeds of each variant's figures."""
    out: dict[str, dict] = {}
    for v in dict.fromkeys(r["variant"] for r in rows.values() if "variant" in r):
        rs = [r for r in rows.values() if r.get("variant") == v]
        out[v] = {"seeds": [r["seed"] for r in rs]}
        for k in ("se3_l2_mean", "se3_l2_x_teacher", "rpe_trans_rmse_m", "rpe_rot_rmse_deg", "ate_rmse_m"):
            xs = np.array([r[k] for r in rs if r.get(k) is not None])
            if len(xs):
                out[v][k] = {"mean": float(xs.mean()), "std": float(xs.std()), "n": len(xs)}
    return out


def print_tables(rows: dict[str, dict]) -> None:
    print("| row | ATE m (whole) | ATE m (sub-traj. mean +- std) | RPE trans m | RPE rot deg | se(3) L2 | x teacher "
          "| se(3) L2 vs teacher |")
    print("|---" * 8 + "|")
    for v, r in rows.items():
        print(f"| {r.get('label', v)} | {fmt(r['ate_rmse_m'])} | "
              f"{fmt(r['ate_sub_mean_m'])} +- {fmt(r['ate_sub_std_m'])} | "
              f"{fmt(r['rpe_trans_rmse_m'])} | {fmt(r['rpe_rot_rmse_deg'])} | {fmt(r['se3_l2_mean'])} | "
              f"{fmt(r.get('se3_l2_x_teacher'))} | {fmt(r.get('vs_teacher', {}).get('se3_l2_mean'))} |")
    print()
    print("| row | " + " | ".join(CAL_KEYS) + " | fit s (wall / CPU) | steps |")
    print("|---" * (len(CAL_KEYS) + 3) + "|")
    for v, r in rows.items():
        if "variant" in r:
            print(f"| {v} | " + " | ".join(fmt(r[k]) for k in CAL_KEYS) + f" | {r['fit_s']} / {r['fit_cpu_s']} | "
                  f"{r['steps']} |")


def main() -> None:
    args = parse_args()
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    test_scene = args.test_scene or args.scene[0]
    gt = test_groundtruth(test_scene, args.test_frames)
    teacher = None if args.teacher_eval is None else teacher_trajectory(args.teacher_eval, gt)
    rows: dict[str, dict] = {}
    if teacher is not None:
        rows["teacher"] = versus_teacher(trajectory_row(gt, teacher, args.sub_length, args.sub_stride), teacher,
                                         teacher, trajectory_report(gt, teacher))
    for key, est in baseline_trajectories(gt).items():
        row = {"label": key, **trajectory_row(gt, est, args.sub_length, args.sub_stride)}
        rows[BASELINE_KEYS[key]] = versus_teacher(row, est, teacher, rows.get("teacher"))
    rec = record.from_args(args, torch_threads=torch.get_num_threads())
    for seed in args.seed:
        for v in args.variants:
            row = run_variant(args, v, seed, test_scene, gt)
            key = v if len(args.seed) == 1 else f"{v} seed {seed}"
            rows[key] = versus_teacher(row, row.pop("_est"), teacher, rows.get("teacher"))
            rec.finish({"rows": rows, "seeds": seed_summary(rows)})
    rec.finish({"rows": rows, "seeds": seed_summary(rows)})
    print_tables(rows)


if __name__ == "__main__":
    main()
