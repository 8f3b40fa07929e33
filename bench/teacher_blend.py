"""How far to move from the sparse (colour keypoint) estimate towards the dense (depth)
alignment: the teacher with several ``dense_blend`` values on one sequence, gap-1 RPE and
ATE of its chained trajectory and the RMSE of its gap-5 labels (all against ground truth).

    .venv/bin/python -m bench.teacher_blend                         # redkitchen, 0 0.25 0.5 0.75 1
    .venv/bin/python -m bench.teacher_blend --scene synthetic/office --blends 0 0.25

``dense_blend = 0`` is the sparse estimate alone (the dense step still runs, for the same
cost); 1 takes the dense alignment whole. Accuracy only: the speed is bench/teacher.py's.
"""

from __future__ import annotations

import argparse
import dataclasses
from pathlib import Path

from data.scenes import open_scene
from teacher.config import TeacherConfig
from teacher.generate import build_report, run_sequence

REPO = Path(__file__).resolve().parents[1]

REDKITCHEN = REPO.parent / "shared" / "data" / "7scenes" / "redkitchen" / "seq-sample"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scene", default=str(REDKITCHEN))
    ap.add_argument("--blends", type=float, nargs="+", default=[0.0, 0.25, 0.5, 0.75, 1.0])
    args = ap.parse_args()
    seq = open_scene(args.scene)[0]
    print("| dense_blend | gap-1 RPE mm | gap-1 RPE deg | gap-5 labels mm / deg | ATE mm |")
    print("|---|---|---|---|---|")
    for b in args.blends:
        cfg = dataclasses.replace(TeacherConfig(), dense_blend=b)
        rep = build_report(seq, run_sequence(seq, cfg, progress=False), cfg)  # the teacher's report.json
        g5 = rep["label_error_by_gap"].get("5", {})
        print(f"| {b:g} | {1000 * rep['rpe_trans_rmse_m']:.2f} | {rep['rpe_rot_rmse_deg']:.3f} | "
              f"{1000 * g5.get('trans_rmse_m', float('nan')):.2f} / {g5.get('rot_rmse_deg', float('nan')):.3f} | "
              f"{1000 * rep['ate_rmse_m']:.1f} |", flush=True)


if __name__ == "__main__":
    main()
