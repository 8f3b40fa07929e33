"""Ablation of the seven learner variants (cnn/lstm x gt/unsup/aug, ctc).

Each variant is trained with the same preset, schedule and seed on ``--frames`` of the
``--scene`` scenes (repeatable) and evaluated by ``learner predict`` on ``--test-frames`` of
``--test-scene`` (default: the first ``--scene``); the table lists the report keys. Teacher
labels come from ``--teacher`` (one training scene only) or from each scene's default
teacher folder ``runs/<scene-slug>/teacher`` (made by the teacher when missing). Results go to ``--out``/ablation.json and are printed
as a Markdown table.

    .venv/bin/python bench/ablation.py --scene ../shared/data/7scenes/redkitchen/seq-sample \\
        --frames 0:400 --test-frames 400:600 --epochs 4 --steps-per-epoch 20 --out runs/ablation
    .venv/bin/python bench/ablation.py --scene synthetic/office --scene synthetic/lab \
        --test-scene synthetic/kitchen --epochs 4 --steps-per-epoch 20 --out runs/ablation-synth
"""

from __future__ import annotations

import argparse
import logging
import sys
import time
from pathlib import Path

sys.path = [q for q in sys.path if Path(q or ".").resolve() != Path(__file__).resolve().parent]

from data.io import write_json  # noqa: E402
from learner.config import VARIANTS, PredictConfig  # noqa: E402
from learner.predict import predict  # noqa: E402
from learner.train import fit  # noqa: E402

KEYS = ["ate_rmse_m", "rpe_trans_rmse_m", "rpe_rot_rmse_deg", "se3_l2_mean", "spearman_sigma_error",
        "coverage_1sigma", "coverage_2sigma", "outlier_auroc"]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scene", action="append", required=True, help="training scene (repeatable)")
    ap.add_argument("--frames", help="training frame range")
    ap.add_argument("--test-scene", help="evaluation scene (default --scene)")
    ap.add_argument("--test-frames", help="evaluation frame range")
    ap.add_argument("--teacher", type=Path, help="teacher output folder of --scene (one training scene only)")
    ap.add_argument("--variants", nargs="+", default=list(VARIANTS), choices=list(VARIANTS))
    ap.add_argument("--preset", default="cpu")
    ap.add_argument("--epochs", type=int, default=4)
    ap.add_argument("--steps-per-epoch", type=int, default=20)
    ap.add_argument("--samples", type=int, default=10)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", type=Path, default=Path("runs/ablation"))
    args = ap.parse_args()
    if args.teacher is not None and len(args.scene) > 1:
        ap.error("--teacher needs a single --scene (several scenes read runs/<scene-slug>/teacher)")
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    rows = {}
    for v in args.variants:
        run = args.out / v
        t0 = time.perf_counter()
        res = fit(args.scene, variant=v, preset=args.preset, frames=args.frames, out=run,
                  resume=(run / "checkpoint.pt").is_file(), teacher_root=args.teacher, epochs=args.epochs,
                  steps_per_epoch=args.steps_per_epoch, seed=args.seed)
        t_fit = time.perf_counter() - t0
        rep = predict(res.checkpoint, args.test_scene or args.scene[0], frames=args.test_frames, out=run / "predict",
                      config=PredictConfig(samples=args.samples)).reports[0]
        rows[v] = {"fit_s": round(t_fit, 1), "final_loss": res.history[-1]["loss"], **{k: rep.get(k) for k in KEYS}}
        write_json(args.out / "ablation.json", {"args": {k: str(x) for k, x in vars(args).items()}, "results": rows})
    print("| variant | " + " | ".join(KEYS) + " | fit s |")
    print("|---" * (len(KEYS) + 2) + "|")
    for v, r in rows.items():
        cells = [("-" if r[k] is None else f"{r[k]:.4g}") for k in KEYS]
        print(f"| {v} | " + " | ".join(cells) + f" | {r['fit_s']} |")


if __name__ == "__main__":
    main()
