"""End to end on synthetic scenes: camera calibration -> teacher -> learner fit
(calibrated on a validation scene) -> learner predict -> pose graph.

    ctcvo demo [--train synthetic/office] [--val synthetic/lab] [--test synthetic/kitchen]
               [--frames 0:120] [--steps 200] [--preset demo] [--no-calibrate]

The camera's radial lens distortion is self-calibrated on the train and validation
scenes (``teacher calibrate``, no ground truth) and every scene's teacher runs on frames
undistorted with it: the synthetic sensor's lens is not the pinhole its intrinsics say
(on the validation rooms, teacher graph ATE lab 0:200 10.1 -> 5.9 mm, office 0:200 11.8 ->
3.5 mm). ``--no-calibrate`` for a camera already calibrated (TUM fr1/fr2, camera.txt).

Each stage is called through its library function and writes its usual files under
runs/<scene-slug>/ (teacher/, learner/, predict/, posegraph/). Every stage follows the
same rerun rule: work of the same inputs already on disk is kept (a second run only
reads it), and work of other inputs stops the demo unless --overwrite is given. At the
end the pose-graph table of the test scene is printed, then the time of each stage.
"""

from __future__ import annotations

import argparse
import logging
import sys
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from ctcvo.data.cli import HelpFormatter
from ctcvo.data.cli import run as run_cli
from ctcvo.learner.config import PRESETS, VARIANTS
from ctcvo.learner.predict import predict
from ctcvo.learner.train import fit
from ctcvo.posegraph.optimize import optimize
from ctcvo.teacher.calibrate import calibrate
from ctcvo.teacher.generate import generate

log = logging.getLogger("ctcvo.pipeline.demo")  # also when run as __main__


class StageTimes:
    """Wall-clock seconds of each stage, in the order they ran."""

    def __init__(self) -> None:
        self.seconds: dict[str, float] = {}

    def run(self, name: str, fn: Callable[..., Any], *args: Any, **kwargs: Any) -> Any:
        log.info("%s", name)
        t0 = time.perf_counter()
        try:
            return fn(*args, **kwargs)
        finally:
            self.seconds[name] = self.seconds.get(name, 0.0) + time.perf_counter() - t0

    def table(self) -> str:
        width = max(map(len, self.seconds), default=5)
        rows = [f"{name:<{width}}  {secs:8.1f} s" for name, secs in self.seconds.items()]
        return "\n".join(["time per stage:", *rows, f"{'total':<{width}}  {sum(self.seconds.values()):8.1f} s"])


def run(train: str, test: str, frames: str | None, steps: int | None, preset: str = "demo", variant: str = "ctc",
        val: str | None = "synthetic/lab", overwrite: bool = False, times: StageTimes | None = None,
        calibrate_camera: bool = True) -> Path:
    """Run every stage; return the pose-graph output folder of ``test``. With ``val``, the
    learner's MC-dropout covariances are calibrated on that scene's teacher labels (never
    on the test scene, never on ground truth); with ``calibrate_camera`` the lens
    distortion is calibrated on ``train`` and ``val`` (never on the test scene)."""
    times = times if times is not None else StageTimes()
    known = [s for s in dict.fromkeys((train, val)) if s]
    camera = (times.run(f"teacher calibrate {' '.join(known)}", calibrate, known, [frames], overwrite=overwrite)
              if calibrate_camera else None)
    for scene in dict.fromkeys([s for s in (train, val, test) if s]):
        times.run(f"teacher generate {scene}", generate, scene, None, "all", frames, overwrite=overwrite,
                  camera=camera)
    res = times.run(f"learner fit {train} ({preset}, {variant})", fit, [train], variant=variant, preset=preset,
                    val_scenes=[val] if val else (), frames=frames, steps=steps, overwrite=overwrite)
    times.run(f"learner predict {test}", predict, res.checkpoint, test, frames=frames, overwrite=overwrite)
    outs = times.run(f"posegraph optimize {test}", optimize, scene=test, overwrite=overwrite)
    return outs[0]


def main(argv: Sequence[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="ctcvo demo", description=__doc__, formatter_class=HelpFormatter)
    p.add_argument("-v", "--verbose", action="store_true", help="debug messages of this project's modules")
    p.add_argument("--train", default="synthetic/office", help="training scene")
    p.add_argument("--val", default="synthetic/lab",
                   help="validation scene for the covariance calibration ('' for none)")
    p.add_argument("--test", default="synthetic/kitchen", help="test scene")
    p.add_argument("--frames", default=None, help="frame range START:STOP[:STEP] of every scene (default: all)")
    p.add_argument("--steps", type=int, default=None, help="learner optimiser steps (default: the preset's)")
    p.add_argument("--preset", default="demo", choices=list(PRESETS),
                   help="learner preset (see `ctcvo learner fit -h`; demo: cpu with flow + inverse depth input "
                        "and depth-scale / mirror augmentation, chosen on validation rooms)")
    p.add_argument("--variant", default="ctc", choices=list(VARIANTS), help="learner variant")
    p.add_argument("--calibrate", action=argparse.BooleanOptionalAction, default=True,
                   help="self-calibrate the lens distortion on the train and val scenes first (default: on)")
    p.add_argument("--overwrite", action="store_true", help="let every stage replace outputs of other inputs")
    args = p.parse_args(argv)

    def body(a: argparse.Namespace) -> int:
        times = StageTimes()
        out = run(a.train, a.test, a.frames, a.steps, a.preset, a.variant, a.val or None, a.overwrite, times,
                  a.calibrate)
        print((out / "report.md").read_text())
        print(times.table())
        return 0

    return run_cli(args, body)


if __name__ == "__main__":
    sys.exit(main())
