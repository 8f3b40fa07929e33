"""End to end on synthetic scenes: teacher -> learner fit (calibrated on a validation
scene) -> learner predict -> pose graph.

    python -m posegraph.pipeline [--train synthetic/office] [--val synthetic/lab]
                                 [--test synthetic/kitchen] [--frames 0:120] [--steps 200]

Each stage is called through its library function and writes its usual files under
``runs/<scene-slug>/`` (teacher/, learner/, posegraph/); work already on disk is reused by
the stages that support it. At the end the pose-graph table of the test scene is printed.
"""

from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path
from typing import Optional, Sequence

from data.errors import VOError
from data.io import setup_logging

log = logging.getLogger("posegraph.pipeline")  # also when run as __main__


def run(train: str, test: str, frames: Optional[str], steps: Optional[int],
        preset: str = "cpu", variant: str = "ctc", val: Optional[str] = "synthetic/lab") -> Path:
    """Run every stage; return the pose-graph output folder of ``test``. With ``val``, the
    learner's MC-dropout covariances are calibrated on that scene's teacher labels (never
    on the test scene, never on ground truth)."""
    from learner.predict import predict
    from learner.train import CHECKPOINT, default_run_dir, fit
    from posegraph.optimize import optimize
    from teacher.generate import generate

    for scene in dict.fromkeys([s for s in (train, val, test) if s]):
        log.info("teacher generate %s", scene)
        generate(scene, None, "all", frames)
    log.info("learner fit %s (%s, %s)%s", train, preset, variant, f", calibrated on {val}" if val else "")
    # a rerun continues (or, when finished, keeps) the run's checkpoint instead of refusing it
    resume = (default_run_dir(train) / CHECKPOINT).is_file()
    res = fit([train], variant=variant, preset=preset, val_scenes=[val] if val else (), frames=frames,
              steps=steps, resume=resume)
    log.info("learner predict %s", test)
    predict(res.checkpoint, test, frames=frames)
    log.info("posegraph optimize %s", test)
    outs = optimize(scene=test)
    return outs[0]


def main(argv: Optional[Sequence[str]] = None) -> int:
    p = argparse.ArgumentParser(prog="python -m posegraph.pipeline", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--train", default="synthetic/office", help="training scene")
    p.add_argument("--val", default="synthetic/lab",
                   help="validation scene for the covariance calibration ('' for none)")
    p.add_argument("--test", default="synthetic/kitchen", help="test scene")
    p.add_argument("--frames", default=None, help="frame range START:STOP[:STEP] of every scene")
    p.add_argument("--steps", type=int, default=None, help="learner optimiser steps (default: the preset's)")
    p.add_argument("--preset", default="cpu")
    p.add_argument("--variant", default="ctc")
    args = p.parse_args(argv)
    setup_logging()
    try:
        out = run(args.train, args.test, args.frames, args.steps, args.preset, args.variant,
                  args.val or None)
    except VOError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 1
    print((out / "report.md").read_text())
    return 0


if __name__ == "__main__":
    sys.exit(main())
