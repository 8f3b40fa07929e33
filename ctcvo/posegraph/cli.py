"""``posegraph`` command line: argparse, logging, known failures -> ``error: ...`` and exit 1."""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
from collections.abc import Sequence
from pathlib import Path

from ctcvo.data.cli import add_command, make_parser, run
from ctcvo.data.scenes import add_topic_options, scene_with_topics
from ctcvo.posegraph.config import DEFAULT, KERNELS, LEARNER_EDGES, PRESETS, SOLVERS, SOURCES

PRESET_HELP = ("presets: 'default' - robust (Huber) Levenberg-Marquardt with per-source covariance calibration "
               "and outlier removal; 'plain' - no kernel, no calibration, no outlier test; "
               "'online' - the default with incremental iSAM2")


def _d(field: str) -> str:
    """The help suffix of an option that overrides a preset field."""
    v = getattr(DEFAULT, field)
    return f"(default: the preset's; 'default' has {'no limit' if v is None or v == float('inf') else v})"


def _parser() -> argparse.ArgumentParser:
    p, sub = make_parser("ctcvo posegraph", "Fuse relative-pose edges with a GTSAM pose graph.\n\n" + PRESET_HELP + ".")
    o = add_command(sub, "optimize", "optimise teacher/learner edges, write trajectory.tum and a report",
                    "Optimise teacher and learner edges in one pose graph; write the fused trajectory.tum, "
                    "report.json/.md and plots. A rerun with the same inputs is skipped; other inputs in the same "
                    "folder need --overwrite.\n\n" + PRESET_HELP + ".")
    o.add_argument("--scene", help="a 7-Scenes or TUM folder or synthetic/NAME: sets the default folders "
                   "and the ground truth")
    o.add_argument("--split", default="all", help="7-Scenes split of a scene folder: train, test or all")
    o.add_argument("--frames", help="frame range START:STOP[:STEP] of the sequence: every source is cut to it "
                   "(default: the frames every source covers)")
    o.add_argument("--teacher", type=Path, help="teacher output folder (default: runs/<scene>/teacher)")
    o.add_argument("--learner", type=Path, help="learner predict output folder (default: runs/<scene>/predict)")
    o.add_argument("--edges", type=Path, nargs="+", default=[],
                   help="bare g2o edge files instead of folders (default: none)")
    o.add_argument("--out", type=Path, help="output folder (default: runs/<scene>/posegraph)")
    o.add_argument("--overwrite", action="store_true",
                   help="replace outputs of other inputs in --out instead of stopping with an error")
    o.add_argument("--preset", choices=sorted(PRESETS), default="default", help="solver settings, see above")
    o.add_argument("--use", dest="sources", choices=SOURCES,
                   help="edge sources in the graph; auto: every source given " + _d("sources"))
    o.add_argument("--learner-edges", dest="learner_edges", choices=LEARNER_EDGES,
                   help="bridge: learner edges only where the teacher's edges leave frames apart; "
                        "all: every edge, weighed by its covariance " + _d("learner_edges"))
    o.add_argument("--solver", choices=SOLVERS, help="batch Levenberg-Marquardt or incremental iSAM2 " + _d("solver"))
    o.add_argument("--kernel", choices=KERNELS, help="robust kernel of every edge " + _d("kernel"))
    o.add_argument("--residual-threshold", type=float,
                   help="whitened residual above which an edge is an outlier " + _d("residual_threshold"))
    o.add_argument("--no-calibrate", dest="calibrate", action="store_false", default=None,
                   help="use every source's covariances as given (no per-source scale from residuals)")
    o.add_argument("--marginals", action="store_true", default=None, help="write marginals.npz")
    o.add_argument("--no-plots", dest="plots", action="store_false", default=None, help="write no PNG figures")
    add_topic_options(o)
    o.add_argument("--teacher-calibration", type=Path,
                   help="per-gap teacher covariance scales from `posegraph calibrate` (fitted on validation data; "
                        "default: none, the teacher's covariances as written)")
    c = add_command(sub, "calibrate", "fit per-gap covariance scales of teacher edges from their own "
                                      "multi-gap consistency or against ground truth, on validation ranges")
    c.add_argument("--teacher", type=Path, nargs="+", required=True,
                   help="teacher output folder(s) of validation ranges or scenes (never the test data)")
    c.add_argument("--out", type=Path, required=True, help="calibration JSON to write")
    c.add_argument("--overwrite", action="store_true",
                   help="replace an --out fitted on other inputs instead of stopping with an error")
    c.add_argument("--max-gap", type=int, help="use edges up to this gap (frame positions; default: all)")
    c.add_argument("--method", choices=["consistency", "groundtruth"], default="consistency",
                   help="consistency: from the multi-gap edges alone (no ground truth); groundtruth: NEES against "
                        "each folder's groundtruth.tum (synthetic validation scenes with exact ground truth)")
    return p


def _calibrate(args: argparse.Namespace) -> int:
    from ctcvo.posegraph.calibration import calibrate_teacher

    res = calibrate_teacher(args.teacher, args.out, max_gap=args.max_gap, method=args.method,
                            overwrite=args.overwrite)
    print(", ".join(f"gap {g}: x{v:.3g}" for g, v in sorted(res.scales.items())), "->", args.out)
    return 0


def _optimize(args: argparse.Namespace) -> int:
    from ctcvo.posegraph.optimize import optimize
    from ctcvo.posegraph.report import summary_text

    if args.command == "calibrate":
        return _calibrate(args)
    args.scene = scene_with_topics(args.scene, args)
    fields = {f.name for f in dataclasses.fields(PRESETS[args.preset])}
    changes = {k: v for k, v in vars(args).items() if k in fields and v is not None}
    cfg = dataclasses.replace(PRESETS[args.preset], **changes)
    outs = optimize(scene=args.scene, teacher=args.teacher, learner=args.learner, edges=args.edges,
                    out=args.out, cfg=cfg, split=args.split, frames=args.frames, overwrite=args.overwrite,
                    teacher_calibration=args.teacher_calibration)
    for o in outs:
        print(summary_text(json.loads((o / "report.json").read_text())))
        print(f"full report: {o / 'report.md'}")
    return 0


def main(argv: Sequence[str] | None = None) -> int:
    return run(_parser().parse_args(argv), _optimize)


if __name__ == "__main__":
    sys.exit(main())
