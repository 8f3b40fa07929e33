"""``teacher`` console script: a thin wrapper around :func:`teacher.generate.generate`."""

from __future__ import annotations

import argparse
import dataclasses
import sys
from pathlib import Path
from typing import Optional, Sequence

from data.errors import VOError
from data.io import setup_logging
from data.scenes import add_topic_options, scene_with_topics
from teacher import processes
from teacher.config import PRESETS


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="teacher", description=__doc__)
    sub = p.add_subparsers(dest="command", required=True)
    g = sub.add_parser("generate", help="estimate relative-pose labels for a scene")
    g.add_argument("--scene", required=True, help="sequence/scene folder (7-Scenes, TUM), ROS bag, or synthetic/NAME")
    g.add_argument("--out", type=Path, default=None, help="output folder (default runs/<scene>/teacher)")
    g.add_argument("--gaps", type=int, default=None, help="largest frame gap K of the edges (default 5)")
    g.add_argument("--frames", default=None, help="frame range START:STOP[:STEP] of each sequence")
    g.add_argument("--split", default="all", choices=["train", "test", "all"], help="split of a 7-Scenes scene folder")
    g.add_argument("--preset", default="default", choices=sorted(PRESETS), help="teacher preset")
    g.add_argument("--workers", type=int, default=None, help="worker processes (default 2)")
    g.add_argument("--overwrite", action="store_true", help="redo sequences whose outputs exist")
    g.add_argument("-v", "--verbose", action="store_true")
    add_topic_options(g)
    return p


def main(argv: Optional[Sequence[str]] = None) -> int:
    args = build_parser().parse_args(argv)
    setup_logging(args.verbose, "%(message)s")
    cfg = PRESETS[args.preset]
    if args.gaps is not None:
        cfg = dataclasses.replace(cfg, gaps=args.gaps)
    if args.workers is not None:
        cfg = dataclasses.replace(cfg, workers=args.workers)
    if cfg.workers > 1:
        processes.start()  # the workers import Open3D and the teacher while this process does
    from teacher.generate import generate

    try:
        args.scene = scene_with_topics(args.scene, args)
        generate(args.scene, args.out, args.split, args.frames, cfg, args.overwrite)
    except VOError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print("error: interrupted (finished sequences are kept; rerun to resume)", file=sys.stderr)
        return 130
    return 0


if __name__ == "__main__":
    sys.exit(main())
