"""``learner`` command line: ``learner fit``, ``learner calibrate``, ``learner predict`` (thin wrappers).

Parses arguments, configures logging, calls learner.train.fit / learner.calibrate.calibrate
/ learner.predict.predict, and turns a known failure into one line on stderr.
"""

from __future__ import annotations

import argparse
import logging
import sys
from collections.abc import Sequence
from pathlib import Path

from ctcvo.data.cli import add_command, make_parser, run
from ctcvo.data.errors import ConfigError
from ctcvo.data.scenes import add_topic_options, scene_with_topics, scenes_with_topics
from ctcvo.learner.config import INPUTS, PRESETS, VARIANTS, PredictConfig

PRESET_HELP = ("presets: 'paper' - the paper's network (320x240 VGG-11-BN widths, RGB pair; for a GPU); "
               "'cpu' - a network that trains on a 2-core CPU (128x96, VGG widths / 8, RGB + flow + inverse depth, "
               "1500 steps); 'demo' - the cpu network on flow and inverse depth without colour, with depth-scale and "
               "mirroring augmentation (the demo's); 'tiny' - a toy network for the tests only (it learns nothing useful)")
VARIANT_HELP = ("variants: cnn-* train the direct head on pairs, lstm-* and ctc also the LSTM on windows; *-gt on "
                "ground-truth labels, *-unsup on the teacher's, *-aug on teacher labels redrawn from their "
                "covariances; ctc adds the composite transformation constraints")
log = logging.getLogger(__name__)

DEVICE_HELP = "auto: CUDA when available, else the CPU"


def _parser() -> argparse.ArgumentParser:
    ap, sub = make_parser("ctcvo learner", "Train the CTCNet-style learner on teacher labels, calibrate its covariances "
                                     "and predict edges.\n\n" + PRESET_HELP + ".\n" + VARIANT_HELP + ".")

    _fit_options(sub)
    _calibrate_options(sub)
    _predict_options(sub)
    return ap


def _fit_options(sub: argparse._SubParsersAction) -> None:
    f = add_command(sub, "fit", "train on teacher (or ground-truth) labels",
                    "Train on teacher (or ground-truth) labels into a run folder. A rerun with the same inputs keeps "
                    "a finished run and continues an unfinished one; other inputs need --overwrite. Ctrl-C keeps the "
                    "last epoch's checkpoint: `learner fit --resume --out DIR` continues it.\n\n"
                    + PRESET_HELP + ".\n" + VARIANT_HELP + ".")
    f.add_argument("--scene", action="append", help="training scene: a 7-Scenes or TUM folder or synthetic/NAME "
                   "(repeatable; required unless --resume)")
    f.add_argument("--val-scene", action="append", help="validation scene (repeatable): per-epoch validation and the "
                   "covariance calibration; never a test scene (default: none, then no calibration)")
    f.add_argument("--frames", help="frame range START:STOP[:STEP] of every training sequence (default: all frames)")
    f.add_argument("--val-frames", help="frame range of the validation sequences (default: --frames); "
                   "a training sequence may validate on a disjoint range")
    f.add_argument("--split", help="7-Scenes split of a scene folder: train, test or all (default: all)")
    f.add_argument("--variant", choices=list(VARIANTS), help="training variant, see above (default: ctc)")
    f.add_argument("--preset", choices=list(PRESETS), help="network and schedule, see above (default: cpu)")
    f.add_argument("--out", type=Path, help="run folder (default: runs/<first scene>/learner)")
    f.add_argument("--overwrite", action="store_true",
                   help="replace a run of other inputs in --out instead of stopping with an error")
    f.add_argument("--resume", action="store_true",
                   help="continue the run in --out with its saved options (other options may be left out; "
                        "only schedule changes such as more --steps are accepted)")
    f.add_argument("--steps", type=int, help="total optimiser steps (default: the preset's; phase-1 and warm-up "
                   "steps keep the preset's proportions unless given)")
    f.add_argument("--pretrain-steps", type=int, help="phase-1 (single pairs) optimiser steps (default: the preset's)")
    f.add_argument("--warmup-steps", type=int, help="learning-rate warm-up steps (default: the preset's)")
    f.add_argument("--eval-every", type=int,
                   help="steps per epoch: evaluation, log line and checkpoint (default: the preset's)")
    f.add_argument("--lr", type=float, help="peak learning rate (default: the preset's)")
    f.add_argument("--batch-pairs", type=int, help="phase-1 pairs per step (default: the preset's)")
    f.add_argument("--seed", type=int, help="random seed (default: the preset's)")
    f.add_argument("--flip-prob", type=float,
                   help="left-right mirroring augmentation probability (default: the preset's)")
    f.add_argument("--reverse-prob", type=float,
                   help="time-reversal augmentation probability (default: the preset's)")
    f.add_argument("--scale-aug", type=float,
                   help="depth-scale augmentation: scale each sample's world by 2**u, u uniform in [-A, A] "
                        "(inputs with depth only; default: the preset's)")
    f.add_argument("--input", choices=list(INPUTS),
                   help="encoder input: rgb (the paper's RGB pair), rgbd (plus inverse depth) or flow (plus optical "
                        "flow and inverse depth), flowd (flow and both inverse depths, no colour) (default: the preset's)")
    f.add_argument("--device", default="auto", choices=["auto", "cpu", "cuda"], help=DEVICE_HELP)
    f.add_argument("--bf16", action="store_true", default=None, help="bfloat16 autocast of the forward pass (GPU)")
    f.add_argument("--pretrained", type=Path, help="local torchvision vgg11_bn state-dict file to start the "
                   "encoder from (default: random initialisation)")
    f.add_argument("--init", type=Path, help="fine-tune: start from the weights of this learner checkpoint "
                   "(same preset shape and --input), with a fresh optimiser and schedule (default: none)")
    f.add_argument("--teacher", type=Path,
                   help="teacher output folder to read labels from (`ctcvo teacher generate --out`; "
                        "default: runs/<scene>/teacher)")
    f.add_argument("--no-calibration", dest="calibrate", action="store_false", default=None,
                   help="do not fit calibration.json on the --val-scene sequences after training")
    add_topic_options(f)


def _calibrate_options(sub: argparse._SubParsersAction) -> None:
    c = add_command(sub, "calibrate", "fit calibration.json (MC-dropout covariances vs teacher labels) "
                                      "of a checkpoint on a validation scene",
                    "Fit calibration.json (MC-dropout covariances vs teacher labels) of a checkpoint on a validation "
                    "scene, beside the checkpoint. A rerun with the same checkpoint, scenes, frames, teacher labels "
                    "and settings keeps it; other inputs need --overwrite.")
    c.add_argument("--checkpoint", type=Path, required=True, help="learner checkpoint.pt")
    c.add_argument("--scene", action="append", required=True,
                   help="validation scene (repeatable); never a training or test scene")
    c.add_argument("--frames", help="frame range START:STOP[:STEP] of every sequence (default: all frames)")
    c.add_argument("--split", default="all", help="7-Scenes split of a scene folder: train, test or all")
    c.add_argument("--teacher", type=Path,
                   help="teacher output folder to read labels from (`ctcvo teacher generate --out`; "
                        "default: runs/<scene>/teacher)")
    c.add_argument("--overwrite", action="store_true",
                   help="replace a calibration.json of other inputs instead of stopping with an error")
    _mc_options(c)
    c.add_argument("--device", default="auto", choices=["auto", "cpu", "cuda"], help=DEVICE_HELP)
    add_topic_options(c)


def _predict_options(sub: argparse._SubParsersAction) -> None:
    p = add_command(sub, "predict", "MC-dropout edges, trajectory and report of a scene",
                    "MC-dropout edges with covariances, a trajectory and a report of a scene. A rerun with the same "
                    "checkpoint, calibration, scene, frames and settings is skipped; other inputs need --overwrite.")
    p.add_argument("--checkpoint", type=Path, required=True, help="learner checkpoint.pt")
    p.add_argument("--scene", required=True, help="a 7-Scenes or TUM folder or synthetic/NAME")
    p.add_argument("--frames", help="frame range START:STOP[:STEP] (default: all frames)")
    p.add_argument("--split", default="all", help="7-Scenes split of a scene folder: train, test or all")
    p.add_argument("--out", type=Path, help="output folder (default: runs/<scene>/predict; never a training run's)")
    p.add_argument("--overwrite", action="store_true",
                   help="replace outputs of other inputs in --out instead of stopping with an error")
    _mc_options(p)
    p.add_argument("--preset", choices=list(PRESETS), help="fail unless the checkpoint has this preset (default: any)")
    p.add_argument("--device", default="auto", choices=["auto", "cpu", "cuda"], help=DEVICE_HELP)
    p.add_argument("--no-calibration", dest="calibration", action="store_false",
                   help="ignore the calibration.json beside the checkpoint")
    add_topic_options(p)


def _mc_options(p: argparse.ArgumentParser) -> None:
    p.add_argument("--samples", type=int, default=PredictConfig.samples, help="MC-dropout passes K")
    p.add_argument("--drop", type=float, default=PredictConfig.drop, help="MC-dropout drop ratio")
    p.add_argument("--max-gap", type=int, default=PredictConfig.max_gap, help="longest direct edge gap")


def _fit(args: argparse.Namespace) -> int:
    log.info("learner fit: %s (loading PyTorch ...)", ", ".join(args.scene or ["resuming " + str(args.out)]))
    from ctcvo.learner.train import FitInterrupted, fit

    if not args.scene and not args.resume:
        raise ConfigError("give --scene (or --resume --out DIR)")
    try:
        res = fit(args.scene or (), variant=args.variant, preset=args.preset, val_scenes=args.val_scene,
                  frames=args.frames, val_frames=args.val_frames, split=args.split, out=args.out,
                  resume=args.resume, overwrite=args.overwrite, pretrained=args.pretrained, teacher_root=args.teacher,
                  steps=args.steps, pretrain_steps=args.pretrain_steps, warmup_steps=args.warmup_steps,
                  eval_every=args.eval_every, lr=args.lr, batch_pairs=args.batch_pairs, seed=args.seed,
                  device=args.device, bf16=args.bf16, input=args.input, init=args.init, flip_prob=args.flip_prob,
                  reverse_prob=args.reverse_prob, scale_aug=args.scale_aug, calibrate=args.calibrate)
    except FitInterrupted as exc:
        print(exc, file=sys.stderr)
        return 130
    log.info("checkpoint: %s", res.checkpoint)
    return 0


def _calibrate(args: argparse.Namespace) -> int:
    log.info("learner calibrate: %s on %s (loading PyTorch ...)", args.checkpoint, ", ".join(args.scene))
    from ctcvo.learner.calibrate import calibrate

    cfg = PredictConfig(samples=args.samples, drop=args.drop, max_gap=args.max_gap)
    cres = calibrate(args.checkpoint, args.scene, frames=args.frames, split=args.split,
                     teacher_root=args.teacher, config=cfg, device=args.device, overwrite=args.overwrite)
    print(cres.path)
    return 0


def _predict(args: argparse.Namespace) -> int:
    log.info("learner predict: %s on %s (loading PyTorch ...)", args.checkpoint, args.scene)
    from ctcvo.learner.predict import predict

    cfg = PredictConfig(samples=args.samples, drop=args.drop, max_gap=args.max_gap)
    res = predict(args.checkpoint, args.scene, frames=args.frames, split=args.split, out=args.out,
                  config=cfg, preset=args.preset, use_calibration=args.calibration, device=args.device,
                  overwrite=args.overwrite)
    for d in res.out_dirs:
        print(d)
    return 0


def main(argv: Sequence[str] | None = None) -> int:
    args = _parser().parse_args(argv)
    body = {"fit": _fit, "calibrate": _calibrate, "predict": _predict}[args.command]

    def with_topics(a: argparse.Namespace) -> int:
        # the bag topic options apply to the bag scenes among --scene / --val-scene
        if isinstance(a.scene, list):
            val = getattr(a, "val_scene", None) or []
            scenes = scenes_with_topics(a.scene + val, a)
            a.scene = scenes[:len(a.scene)]
            if hasattr(a, "val_scene"):
                a.val_scene = scenes[len(a.scene):] or a.val_scene
        elif a.scene is not None:
            a.scene = scene_with_topics(a.scene, a)
        return body(a)

    return run(args, with_topics)


if __name__ == "__main__":
    sys.exit(main())
