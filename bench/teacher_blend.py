"""How to combine the sparse (colour keypoint) estimate with the dense (depth) alignment:
the teacher with several ``dense_blend`` values (``dense_fusion="blend"``) and several
``dense_cov_scale`` values (``dense_fusion="information"``) on one sequence: gap-1 RPE and ATE
of its chained trajectory and the RMSE of its gap-5 labels (all against ground truth).

    .venv/bin/python -m bench.teacher_blend                      # redkitchen 0:450 (train + val)
    .venv/bin/python -m bench.teacher_blend --scene synthetic/lab --frames 0:300 --blends 0 0.25 --scales 1 5

Validation data only: redkitchen 0:450 (its test range is 450:600) and synthetic/lab (the
test scene is synthetic/kitchen). ``dense_blend = 0`` is the sparse estimate alone (the
dense step still runs, for the same cost); 1 takes the dense alignment whole. Accuracy only:
the speed is bench/teacher.py's.
"""

from __future__ import annotations

import argparse
import dataclasses
from pathlib import Path

from ctcvo.data.scenes import open_scene
from ctcvo.teacher.config import TeacherConfig
from ctcvo.teacher.generate import build_report, run_sequence

REPO = Path(__file__).resolve().parents[1]

REDKITCHEN = REPO.parent / "shared" / "data" / "7scenes" / "redkitchen" / "seq-sample"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scene", default=str(REDKITCHEN))
    ap.add_argument("--frames", default="0:450", help="frame range (default 0:450: never a test range)")
    ap.add_argument("--blends", type=float, nargs="*", default=[0.0, 0.25, 0.5, 1.0])
    ap.add_argument("--scales", type=float, nargs="*", default=[1.0, 3.0, 5.0, 10.0])
    args = ap.parse_args()
    seq = open_scene(args.scene, frames=args.frames)[0]
    runs = [("blend", {"dense_fusion": "blend", "dense_blend": b}, f"dense_blend {b:g}") for b in args.blends]
    runs += [("information", {"dense_fusion": "information", "dense_cov_scale": s}, f"information, scale {s:g}")
             for s in args.scales]
    print("| combination | gap-1 RPE mm | gap-1 RPE deg | gap-5 labels mm / deg | ATE mm |")
    print("|---|---|---|---|---|")
    for _, kw, name in runs:
        cfg = dataclasses.replace(TeacherConfig(), **kw)
        rep = build_report(seq, run_sequence(seq, cfg, progress=False), cfg)  # the teacher's report.json
        g5 = rep["label_error_by_gap"].get("5", {})
        print(f"| {name} | {1000 * rep['rpe_trans_rmse_m']:.2f} | {rep['rpe_rot_rmse_deg']:.3f} | "
              f"{1000 * g5.get('trans_rmse_m', float('nan')):.2f} / {g5.get('rot_rmse_deg', float('nan')):.3f} | "
              f"{1000 * rep['ate_rmse_m']:.1f} |", flush=True)


if __name__ == "__main__":
    main()
