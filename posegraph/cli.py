"""``posegraph`` command line: argparse, logging, VOError -> ``error: ...`` and exit 1."""

from __future__ import annotations

import argparse
import dataclasses
import sys
from pathlib import Path
from typing import Optional, Sequence

from data.errors import VOError
from data.io import setup_logging
from data.scenes import add_topic_options, scene_with_topics
from posegraph.config import KERNELS, OUTLIER_ACTIONS, PRESETS, SOLVERS


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="posegraph", description="Fuse relative-pose edges with a GTSAM pose graph.")
    p.add_argument("-v", "--verbose", action="store_true", help="debug logging")
    sub = p.add_subparsers(dest="command", required=True)
    o = sub.add_parser("optimize", help="optimise teacher/learner edges, write trajectory.tum and a report")
    o.add_argument("--scene", help="scene spec (synthetic/NAME or a folder); sets default folders and ground truth")
    o.add_argument("--split", default="all", help="scene split for ground truth (train/test/all)")
    o.add_argument("--teacher", type=Path, help="teacher output folder (default runs/<scene-slug>/teacher)")
    o.add_argument("--learner", type=Path, help="learner output folder (default runs/<scene-slug>/learner)")
    o.add_argument("--edges", type=Path, nargs="+", default=[], help="bare g2o edge files instead of folders")
    o.add_argument("--out", type=Path, help="output folder (default runs/<scene-slug>/posegraph)")
    o.add_argument("--preset", choices=sorted(PRESETS), default="default")
    o.add_argument("--use", dest="sources", choices=["auto", "teacher", "learner", "fused"], help="edge sources in the graph")
    o.add_argument("--learner-edges", dest="learner_edges", choices=["bridge", "all"],
                   help="bridge (default): learner edges only where the teacher's edges leave frames apart; "
                        "all: every edge, weighed by its covariance")
    o.add_argument("--init", choices=["auto", "teacher", "learner", "chain"], help="initial values")
    o.add_argument("--solver", choices=SOLVERS)
    o.add_argument("--kernel", choices=KERNELS)
    o.add_argument("--kernel-k", type=float)
    o.add_argument("--max-gap", type=int)
    o.add_argument("--residual-threshold", type=float, help="whitened residual above which an edge is an outlier")
    o.add_argument("--max-trans-sigma", dest="max_trans_sigma_m", type=float, help="metres")
    o.add_argument("--max-rot-sigma", dest="max_rot_sigma_deg", type=float, help="degrees")
    o.add_argument("--outlier-action", choices=OUTLIER_ACTIONS)
    o.add_argument("--no-calibrate", dest="calibrate", action="store_false", default=None,
                   help="use every source's covariances as given (no per-source scale from residuals)")
    o.add_argument("--marginals", action="store_true", default=None, help="write marginals.npz")
    o.add_argument("--no-plots", dest="plots", action="store_false", default=None)
    add_topic_options(o)
    o.add_argument("--teacher-calibration", type=Path,
                   help="per-gap teacher covariance scales from `posegraph calibrate` (fitted on validation data)")
    c = sub.add_parser("calibrate", help="fit per-gap covariance scales of teacher edges from their own "
                                         "multi-gap consistency (no ground truth), on validation ranges")
    c.add_argument("--teacher", type=Path, nargs="+", required=True,
                   help="teacher output folder(s) of validation ranges or scenes (never the test data)")
    c.add_argument("--out", type=Path, required=True, help="calibration JSON to write")
    c.add_argument("--max-gap", type=int, help="use edges up to this gap (frame positions)")
    c.add_argument("--method", choices=["consistency", "groundtruth"], default="consistency",
                   help="consistency: from the multi-gap edges alone (no ground truth); groundtruth: NEES against "
                        "each folder's groundtruth.tum (synthetic validation scenes with exact ground truth)")
    return p


def main(argv: Optional[Sequence[str]] = None) -> int:
    args = _parser().parse_args(argv)
    setup_logging(args.verbose)
    try:
        if args.command == "calibrate":
            from posegraph.calibration import calibrate_teacher

            res = calibrate_teacher(args.teacher, args.out, max_gap=args.max_gap, method=args.method)
            print(", ".join(f"gap {g}: x{v:.3g}" for g, v in sorted(res.scales.items())), "->", args.out)
            return 0
        from posegraph.optimize import optimize

        args.scene = scene_with_topics(args.scene, args)
        fields = {f.name for f in dataclasses.fields(PRESETS[args.preset])}
        changes = {k: v for k, v in vars(args).items() if k in fields and v is not None}
        cfg = dataclasses.replace(PRESETS[args.preset], **changes)
        outs = optimize(scene=args.scene, teacher=args.teacher, learner=args.learner, edges=args.edges,
                        out=args.out, cfg=cfg, split=args.split, teacher_calibration=args.teacher_calibration)
    except VOError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 1
    for o in outs:
        print(o / "report.md")
    return 0


if __name__ == "__main__":
    sys.exit(main())
