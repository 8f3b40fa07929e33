"""``learner`` command line: ``learner fit``, ``learner calibrate``, ``learner predict`` (thin wrappers).

Parses arguments, configures logging, calls :func:`learner.train.fit` /
:func:`learner.calibrate.calibrate` / :func:`learner.predict.predict`, and turns a :class:`~data.errors.VOError` into
``error: <message>`` on stderr with exit code 1.
"""

from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path
from typing import Optional, Sequence

from data.errors import VOError
from data.io import setup_logging
from data.scenes import add_topic_options, scene_with_topics, scenes_with_topics
from learner.config import INPUTS, PRESETS, VARIANTS, PredictConfig


def _parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(prog="learner", description="Train the CTCNet-style learner and predict edges.")
    ap.add_argument("-v", "--verbose", action="store_true", help="debug logging")
    sub = ap.add_subparsers(dest="cmd", required=True)

    f = sub.add_parser("fit", help="train on teacher (or ground-truth) labels")
    f.add_argument("--scene", action="append", required=True, help="scene spec (repeatable)")
    f.add_argument("--val-scene", action="append", default=[], help="validation scene spec (repeatable)")
    f.add_argument("--frames", help="frame range START:STOP[:STEP] of every sequence")
    f.add_argument("--val-frames", help="frame range of the validation sequences (default: --frames); "
                   "a training sequence may validate on a disjoint range")
    f.add_argument("--split", default="all", help="7-Scenes split for scene folders (train/test/all)")
    f.add_argument("--variant", default="ctc", choices=list(VARIANTS))
    f.add_argument("--preset", default="cpu", choices=list(PRESETS))
    f.add_argument("--out", type=Path, help="run folder (default runs/<scene-slug>/learner)")
    f.add_argument("--steps", type=int, help="total optimiser steps (overrides the preset; phase-1 and warm-up "
                   "steps keep the preset's proportions unless given)")
    f.add_argument("--pretrain-steps", type=int, help="phase-1 (single pairs) optimiser steps")
    f.add_argument("--warmup-steps", type=int, help="learning-rate warm-up steps")
    f.add_argument("--eval-every", type=int, help="steps per epoch: evaluation, log line and checkpoint")
    f.add_argument("--lr", type=float, help="peak learning rate (overrides the preset)")
    f.add_argument("--batch-pairs", type=int, help="phase-1 pairs per step (overrides the preset)")
    f.add_argument("--seed", type=int, help="random seed (overrides the preset)")
    f.add_argument("--flip-prob", type=float, help="left-right mirroring augmentation probability (overrides the preset)")
    f.add_argument("--reverse-prob", type=float, help="time-reversal augmentation probability (overrides the preset)")
    f.add_argument("--input", choices=list(INPUTS),
                   help="encoder input: the paper's RGB pair, plus inverse depth, or plus optical flow and "
                        "inverse depth (default: the preset's)")
    f.add_argument("--device", default="auto", choices=["auto", "cpu", "cuda"],
                   help="auto: CUDA when available (default), else the CPU")
    f.add_argument("--bf16", action="store_true", help="bfloat16 autocast of the forward pass (GPU)")
    f.add_argument("--resume", action="store_true", help="continue the run in --out from its checkpoint")
    f.add_argument("--pretrained", type=Path, help="local torchvision vgg11_bn state-dict file")
    f.add_argument("--init", type=Path, help="fine-tune: start from the weights of this learner checkpoint "
                   "(same preset shape and --input), with a fresh optimiser and schedule")
    f.add_argument("--teacher", type=Path,
                   help="teacher output folder to read labels from (never generated); "
                        "default runs/<scene-slug>/teacher, generated when missing")
    f.add_argument("--no-calibration", dest="calibrate", action="store_false",
                   help="do not fit calibration.json on the --val-scene sequences after training")
    add_topic_options(f)

    c = sub.add_parser("calibrate", help="fit calibration.json (MC-dropout covariances vs teacher labels) "
                                         "of a checkpoint on a validation scene")
    c.add_argument("--checkpoint", type=Path, required=True)
    c.add_argument("--scene", action="append", required=True,
                   help="validation scene spec (repeatable); never a training or test scene")
    c.add_argument("--frames", help="frame range START:STOP[:STEP] of every sequence")
    c.add_argument("--split", default="all")
    c.add_argument("--teacher", type=Path,
                   help="teacher output folder to read labels from (never generated); "
                        "default runs/<scene-slug>/teacher, generated when missing")
    c.add_argument("--samples", type=int, default=PredictConfig.samples, help="MC-dropout passes K")
    c.add_argument("--drop", type=float, default=PredictConfig.drop, help="MC-dropout drop ratio")
    c.add_argument("--max-gap", type=int, default=PredictConfig.max_gap, help="longest direct edge gap")
    c.add_argument("--device", default="auto", choices=["auto", "cpu", "cuda"])
    add_topic_options(c)

    p = sub.add_parser("predict", help="MC-dropout edges, trajectory and report")
    p.add_argument("--checkpoint", type=Path, required=True)
    p.add_argument("--scene", required=True)
    p.add_argument("--frames", help="frame range START:STOP[:STEP]")
    p.add_argument("--split", default="all")
    p.add_argument("--out", type=Path, help="output folder (default runs/<scene-slug>/learner)")
    p.add_argument("--samples", type=int, default=PredictConfig.samples, help="MC-dropout passes K")
    p.add_argument("--drop", type=float, default=PredictConfig.drop, help="MC-dropout drop ratio")
    p.add_argument("--max-gap", type=int, default=PredictConfig.max_gap, help="longest direct edge gap")
    p.add_argument("--preset", choices=list(PRESETS), help="fail unless the checkpoint has this preset")
    p.add_argument("--device", default="auto", choices=["auto", "cpu", "cuda"])
    p.add_argument("--no-calibration", dest="calibration", action="store_false",
                   help="ignore the calibration.json beside the checkpoint")
    add_topic_options(p)
    return ap


def main(argv: Optional[Sequence[str]] = None) -> int:
    args = _parser().parse_args(argv)
    setup_logging(args.verbose)
    try:
        # the bag topic options apply to the bag scenes among --scene / --val-scene
        if isinstance(args.scene, list):
            scenes = scenes_with_topics(args.scene + getattr(args, "val_scene", []), args)
            args.scene, args.val_scene = scenes[:len(args.scene)], scenes[len(args.scene):]
        else:
            args.scene = scene_with_topics(args.scene, args)
        if args.cmd == "fit":
            from learner.train import fit

            res = fit(args.scene, variant=args.variant, preset=args.preset, val_scenes=args.val_scene,
                      frames=args.frames, val_frames=args.val_frames, split=args.split, out=args.out,
                      resume=args.resume,
                      pretrained=args.pretrained, teacher_root=args.teacher, steps=args.steps,
                      pretrain_steps=args.pretrain_steps, warmup_steps=args.warmup_steps, eval_every=args.eval_every,
                      lr=args.lr, batch_pairs=args.batch_pairs, seed=args.seed, device=args.device, bf16=args.bf16, input=args.input, init=args.init,
                      flip_prob=args.flip_prob, reverse_prob=args.reverse_prob,
                      calibrate=args.calibrate)
            logging.getLogger("learner").info("checkpoint: %s", res.checkpoint)
        elif args.cmd == "calibrate":
            from learner.calibrate import calibrate

            cfg = PredictConfig(samples=args.samples, drop=args.drop, max_gap=args.max_gap)
            cres = calibrate(args.checkpoint, args.scene, frames=args.frames, split=args.split,
                             teacher_root=args.teacher, config=cfg, device=args.device)
            print(cres.path)
        else:
            from learner.predict import predict

            cfg = PredictConfig(samples=args.samples, drop=args.drop, max_gap=args.max_gap)
            res = predict(args.checkpoint, args.scene, frames=args.frames, split=args.split, out=args.out,
                          config=cfg, preset=args.preset, use_calibration=args.calibration, device=args.device)
            for d in res.out_dirs:
                print(d)
    except VOError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
