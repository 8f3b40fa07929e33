"""Benchmark: is the synthetic default a faithful stand-in for real data?

Runs the teacher (``ctcvo teacher generate``, default config) on the real redkitchen sample and on
each synthetic preset, and records, per scene, the teacher's label error against ground
truth: gap-1 RMSE and median (translation mm, rotation deg), gap-5 RMSE, the RPE of the
chained gap-1 trajectory over 1 s (30 frames), and the ratio of each synthetic number to the
real one. The issue's target: gap-1 RMSE of every preset within 0.5-2x of the real one.

    .venv/bin/python -m bench.synthetic_realism                  # real + office kitchen lab
    .venv/bin/python -m bench.synthetic_realism --presets office --reuse   # read old outputs

Outputs go to ``--out`` (default ``runs/bench/<name>/<scene>/``); ``--reuse`` only reads
folders already there. The record is ``bench/results/<name>.json`` (bench/record.py).
The real ground truth (KinectFusion) carries ~1.5-2 mm of frame-to-frame jitter per axis,
which inflates the real gap-1 error; the medians and the longer gaps are less affected (see ../shared/data/README.md).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from bench import record
from ctcvo.data import geometry as geo
from ctcvo.data.formats import read_edges_csv, read_g2o, read_tum
from ctcvo.data.metrics import relative_pose_error, rpe_rmse


def edge_errors(folder: Path) -> dict[int, np.ndarray]:
    """Per gap: (E, 2) errors of the good edges (translation m, rotation deg) against GT."""
    edges, _ = read_g2o(folder / "edges.g2o")
    gt = read_tum(folder / "groundtruth.tum")
    # vertex ids are frame ids; edges.csv gives their timestamps, which index groundtruth.tum
    stamp = {}
    for row in read_edges_csv(folder / "edges.csv"):
        stamp[row["i"]], stamp[row["j"]] = row["t_i"], row["t_j"]
    row_of = {f: int(np.argmin(np.abs(gt.timestamps - t))) for f, t in stamp.items()}
    out: dict[int, list] = {}
    for e in edges:
        a, b = row_of[e.i], row_of[e.j]
        out.setdefault(b - a, []).append(relative_pose_error(geo.relative_pose(gt.poses[a], gt.poses[b]), e.T_i_j))
    return {g: np.array(v) for g, v in sorted(out.items())}


def summary(folder: Path) -> dict[str, float]:
    """Label-error figures of one teacher output folder (see module docstring)."""
    errs = edge_errors(folder)
    gt, est = read_tum(folder / "groundtruth.tum"), read_tum(folder / "trajectory.tum")
    t30, r30 = rpe_rmse(gt, est, 30)
    e1, e5 = errs[1], errs.get(5, np.full((1, 2), np.nan))
    rms = lambda a: float(np.sqrt(np.mean(a ** 2)))  # noqa: E731
    return {
        "gap1_trans_rmse_mm": 1000 * rms(e1[:, 0]), "gap1_rot_rmse_deg": rms(e1[:, 1]),
        "gap1_trans_median_mm": 1000 * float(np.median(e1[:, 0])), "gap1_rot_median_deg": float(np.median(e1[:, 1])),
        "gap5_trans_rmse_mm": 1000 * rms(e5[:, 0]), "gap5_rot_rmse_deg": rms(e5[:, 1]),
        "rpe30_trans_rmse_mm": 1000 * t30, "rpe30_rot_rmse_deg": r30,
        "failed_gap1": json.loads((folder / "report.json").read_text())["failed_gap1_edges"],
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--presets", nargs="*", default=["office", "kitchen", "lab"])
    ap.add_argument("--real", type=Path, default=record.REDKITCHEN, help="real 7-Scenes sequence folder")
    ap.add_argument("--out", type=Path, help="teacher outputs (default runs/bench/NAME)")
    ap.add_argument("--reuse", action="store_true", help="read existing teacher outputs, run nothing")
    record.add_arguments(ap, "synthetic-realism")
    args = ap.parse_args()
    args.out = args.out or record.RUNS / args.name
    rec = record.from_args(args)

    scenes = {"redkitchen": str(args.real)} | {p: f"synthetic/{p}" for p in args.presets}
    results = {}
    for name, spec in scenes.items():
        folder = args.out / name
        if not args.reuse:
            from ctcvo.teacher.generate import generate

            folder = generate(spec, out=folder, overwrite=True)[0]
        results[name] = summary(folder)
    real = results["redkitchen"]
    keys = [("gap1_trans_rmse_mm", "{:.2f}"), ("gap1_rot_rmse_deg", "{:.3f}"), ("gap1_trans_median_mm", "{:.2f}"),
            ("gap1_rot_median_deg", "{:.3f}"), ("gap5_trans_rmse_mm", "{:.2f}"), ("gap5_rot_rmse_deg", "{:.3f}"),
            ("rpe30_trans_rmse_mm", "{:.1f}"), ("rpe30_rot_rmse_deg", "{:.2f}")]
    print("| scene | " + " | ".join(k for k, _ in keys) + " | failed gap-1 | ratio gap-1 trans / rot |")
    print("|---" * (len(keys) + 3) + "|")
    for name, r in results.items():
        ratio = (f"{r['gap1_trans_rmse_mm'] / real['gap1_trans_rmse_mm']:.2f} / "
                 f"{r['gap1_rot_rmse_deg'] / real['gap1_rot_rmse_deg']:.2f}")
        print(f"| {name} | " + " | ".join(f.format(r[k]) for k, f in keys) + f" | {r['failed_gap1']} | {ratio} |")
    rec.finish({"scenes": results})


if __name__ == "__main__":
    main()
