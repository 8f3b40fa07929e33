"""End to end on synthetic scenes: teacher -> learner fit (calibrated on a validation
scene) -> learner predict -> pose graph.

    python -m pipeline.demo [--train synthetic/office] [--val synthetic/lab]
                            [--test synthetic/kitchen] [--frames 0:120] [--steps 200]

Each stage is called through its library function and writes its usual files under
runs/<scene-slug>/ (teacher/, learner/, predict/, posegraph/). Every stage follows the
same rerun rule: work of the same inputs already on disk is kept (a second run only
reads it), and work of other inputs stops the demo unless --overwrite is given. At the
end the pose-graph table of the test scene is printed.
"""

from __future__ import annotations

import argparse
import logging
import sys
from collections.abc import Sequence
from pathlib import Path

from ctcvo.data.cli import HelpFormatter
from ctcvo.data.cli import run as run_cli

log = logging.getLogger("ctcvo.pipeline.demo")  # also when run as __main__


#: the demo learner's encoder input: the flow and both frames' inverse depth, no colour.
#: Chosen on the validation scene lab (ctc, cpu preset, trained on office): 0.81x zero
#: motion's se(3) L2, against 1.05-1.12x with the cpu preset's RGB + flow input, which fits
#: the one training room's appearance (bench/README.md, "Learner: does it learn?", 5).
DEMO_INPUT = "flowd"
#: the demo learner's augmentation beyond the cpu preset's time reversal: depth scaling
#: (``TrainConfig.scale_aug``, the world scaled by 2**u, |u| <= 1) and left-right
#: mirroring. Chosen on validation scenes only (lab, lab at double speed, the corpus rooms
#: room-0..3; trained on office, two seeds): with them every one of the six is below zero
#: motion and the mean ratio is 0.82-0.88x; without them two of the six are above it in
#: each seed, mean 0.99-1.12x (bench/README.md, "Learner: does it learn?", 6).
DEMO_AUGMENT = {"scale_aug": 1.0, "flip_prob": 0.5}


def run(train: str, test: str, frames: str | None, steps: int | None,
        preset: str = "cpu", variant: str = "ctc", val: str | None = "synthetic/lab",
        overwrite: bool = False, input: str | None = DEMO_INPUT, augment: dict | None = None) -> Path:
    """Run every stage; return the pose-graph output folder of ``test``. With ``val``, the
    learner's MC-dropout covariances are calibrated on that scene's teacher labels (never
    on the test scene, never on ground truth). ``input``: the learner's encoder input (None:
    the preset's); ``augment``: training overrides (None: :data:`DEMO_AUGMENT`; ``{}``: the
    preset's augmentation)."""
    from ctcvo.learner.predict import predict
    from ctcvo.learner.train import fit
    from ctcvo.posegraph.optimize import optimize
    from ctcvo.teacher.generate import generate

    for scene in dict.fromkeys([s for s in (train, val, test) if s]):
        log.info("teacher generate %s", scene)
        generate(scene, None, "all", frames, overwrite=overwrite)
    log.info("learner fit %s (%s, %s)%s", train, preset, variant, f", calibrated on {val}" if val else "")
    res = fit([train], variant=variant, preset=preset, val_scenes=[val] if val else (), frames=frames,
              steps=steps, overwrite=overwrite, input=input, **(augment if augment is not None else DEMO_AUGMENT))
    log.info("learner predict %s", test)
    predict(res.checkpoint, test, frames=frames, overwrite=overwrite)  # -> runs/<test>/predict
    log.info("posegraph optimize %s", test)
    outs = optimize(scene=test, overwrite=overwrite)  # runs/<test>/{teacher,predict} -> runs/<test>/posegraph
    return outs[0]


def main(argv: Sequence[str] | None = None) -> int:
    from ctcvo.learner.config import INPUTS, PRESETS, VARIANTS

    p = argparse.ArgumentParser(prog="ctcvo demo", description=__doc__, formatter_class=HelpFormatter)
    p.add_argument("-v", "--verbose", action="store_true", help="debug messages of this project's modules")
    p.add_argument("--train", default="synthetic/office", help="training scene")
    p.add_argument("--val", default="synthetic/lab",
                   help="validation scene for the covariance calibration ('' for none)")
    p.add_argument("--test", default="synthetic/kitchen", help="test scene")
    p.add_argument("--frames", default=None, help="frame range START:STOP[:STEP] of every scene (default: all)")
    p.add_argument("--steps", type=int, default=None, help="learner optimiser steps (default: the preset's)")
    p.add_argument("--preset", default="cpu", choices=list(PRESETS), help="learner preset (see `learner fit -h`)")
    p.add_argument("--variant", default="ctc", choices=list(VARIANTS), help="learner variant (see `learner fit -h`)")
    p.add_argument("--overwrite", action="store_true", help="let every stage replace outputs of other inputs")
    p.add_argument("--input", default=DEMO_INPUT, choices=list(INPUTS),
                   help="learner encoder input (flowd: optical flow and inverse depth, no colour; chosen on lab)")
    args = p.parse_args(argv)

    def body(a: argparse.Namespace) -> int:
        out = run(a.train, a.test, a.frames, a.steps, a.preset, a.variant, a.val or None, a.overwrite, a.input)
        print((out / "report.md").read_text())
        return 0

    return run_cli(args, body)


if __name__ == "__main__":
    sys.exit(main())
