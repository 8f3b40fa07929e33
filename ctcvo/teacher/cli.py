"""``teacher`` console script: a thin wrapper around teacher.generate.generate."""

from __future__ import annotations

import argparse
import dataclasses
import sys
from collections.abc import Sequence
from pathlib import Path

from ctcvo.data.cli import add_command, make_parser, run
from ctcvo.data.scenes import add_topic_options, scene_with_topics
from ctcvo.teacher import processes
from ctcvo.teacher.config import PRESETS

PRESET_HELP = ("presets: 'default' - the teacher as benchmarked (K = 5 gaps, 1000 ORB features, two-way "
               "refinement and dense depth alignment); 'paper' - the paper's kind of teacher (ORB + PnP-RANSAC "
               "with a least-squares refinement, no dense step; noisier labels); "
               "'tiny' - 2 gaps and 800 features, for the tests only")


def build_parser() -> argparse.ArgumentParser:
    p, sub = make_parser("ctcvo teacher", "Classical RGB-D odometry that writes noisy relative-pose labels with "
                                    "covariances.\n\n" + PRESET_HELP + ".")
    g = add_command(sub, "generate", "estimate relative-pose labels for a scene",
                    "Estimate relative-pose labels (i, i+g), g = 1..K, of every sequence of a scene. A rerun with the "
                    "same inputs is skipped; other inputs in the same folder need --overwrite.\n\n"
                    + PRESET_HELP + ".")
    g.add_argument("--scene", required=True, help="a 7-Scenes or TUM folder, a ROS bag, or synthetic/NAME")
    g.add_argument("--out", type=Path, default=None, help="output folder (default: runs/<scene>/teacher)")
    g.add_argument("--gaps", type=int, default=None, help="largest frame gap K of the edges (default: the preset's)")
    g.add_argument("--frames", default=None, help="frame range START:STOP[:STEP] of each sequence (default: all)")
    g.add_argument("--split", default="all", choices=["train", "test", "all"], help="split of a 7-Scenes scene folder")
    g.add_argument("--preset", default="default", choices=sorted(PRESETS), help="teacher preset, see above")
    g.add_argument("--workers", type=int, default=None,
                   help="worker processes (default: the preset's, 2)")
    g.add_argument("--overwrite", action="store_true",
                   help="replace outputs of other inputs instead of stopping with an error")
    add_topic_options(g)
    return p


def _generate(args: argparse.Namespace) -> int:
    cfg = PRESETS[args.preset]
    if args.gaps is not None:
        cfg = dataclasses.replace(cfg, gaps=args.gaps)
    if args.workers is not None:
        cfg = dataclasses.replace(cfg, workers=args.workers)
    if cfg.workers > 1:
        processes.start()  # the workers import Open3D and the teacher while this process does
    from ctcvo.teacher.generate import generate

    args.scene = scene_with_topics(args.scene, args)
    generate(args.scene, args.out, args.split, args.frames, cfg, args.overwrite)
    return 0


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    return run(args, _generate, "interrupted (finished sequences are kept; rerun to resume)", fmt="%(message)s")


if __name__ == "__main__":
    sys.exit(main())
