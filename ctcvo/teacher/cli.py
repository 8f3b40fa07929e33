"""``ctcvo teacher``: thin wrappers around teacher.generate.generate (our odometry), the
ORB-SLAM3 backend and the ORB vocabulary builder (teacher.orbslam3_generate)."""

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
    g.add_argument("--keyframes", action=argparse.BooleanOptionalAction, default=None,
                   help="also estimate keyframe edges reaching back seconds and verified loop edges "
                        "(default: the preset's, on)")
    g.add_argument("--covariance", default="calibrated", choices=["calibrated", "raw"],
                   help="calibrated: covariances scaled per gap to the sensor's real errors (fitted on validation "
                        "data); raw: the estimator's own, far too small on real data")
    g.add_argument("--camera", type=Path, default=None,
                   help="camera file from `ctcvo teacher calibrate`: undistort the frames with its lens distortion "
                        "(default: the frames as the reader gives them)")
    g.add_argument("--overwrite", action="store_true",
                   help="replace outputs of other inputs instead of stopping with an error")
    g.add_argument("--strict", action="store_true",
                   help="stop at the first unreadable frame or non-finite ground-truth pose (default: skip the frame "
                        "with a warning, bridge it by the longer edges and list it in report.json)")
    orb = g.add_argument_group("ORB-SLAM3 backend (--backend orbslam3; needs `pip install ctcvo[orbslam3]`, GPL-3.0)")
    orb.add_argument("--backend", default="ours", choices=["ours", "orbslam3"],
                     help="ours: this project's odometry; orbslam3: ORB-SLAM3 RGB-D through pyorbslam3")
    orb.add_argument("--vocabulary", type=Path, help="DBoW2 text vocabulary (`ctcvo teacher vocabulary`, or ORBvoc.txt; "
                     "required with --backend orbslam3, default: none)")
    orb.add_argument("--mode", default="slam", choices=["slam", "localization"],
                     help="localization: mapping stops after the first tracked frame")
    orb.add_argument("--labels", default="final", choices=["final", "causal"],
                     help="relative poses from the keyframe-refined trajectory or the per-frame causal poses "
                          "(final: better on fr3/teddy, level on redkitchen 350:450)")
    orb.add_argument("--orb-settings", type=Path, help="your own ORB-SLAM3 YAML (default: from the sequence)")
    orb.add_argument("--orb-features", type=int, default=1000, help="ORB features per frame")
    add_topic_options(g)
    c = add_command(sub, "calibrate", "self-calibrate the camera's radial lens distortion from its frames",
                    "Estimate one radial distortion coefficient k1 (OpenCV model) of the camera that recorded the "
                    "given frames, from ORB matches between frames 0.3-1 s apart and their depth, and write a camera "
                    "file for `teacher generate --camera` and `online --camera`. Calibrate on training or validation "
                    "frames of the camera, never on test frames.")
    c.add_argument("--scene", action="append", required=True, help="a scene of the camera (repeat for several)")
    c.add_argument("--frames", action="append", default=None,
                   help="frame range START:STOP[:STEP], once for every scene or once per --scene (default: all)")
    c.add_argument("--out", type=Path, default=None,
                   help="camera file to write (JSON; default: runs/<first scene>/camera/camera.json)")
    c.add_argument("--overwrite", action="store_true", help="replace a camera file of other inputs")
    v = add_command(sub, "vocabulary", "build an ORB vocabulary (DBoW2 text format) from training frames",
                    "Build a DBoW2 text vocabulary (ORB-SLAM's ORBvoc.txt format) by hierarchical k-medians on the ORB "
                    "descriptors of the given frames. Never build it from test frames: it is a trained model.")
    v.add_argument("--scene", action="append", required=True, help="a scene (repeat for several)")
    v.add_argument("--frames", action="append", default=None,
                   help="frame range START:STOP[:STEP], once for every scene or once per --scene (default: all)")
    v.add_argument("--out", type=Path, required=True, help="vocabulary file to write")
    v.add_argument("--k", type=int, default=10, help="branching factor (DBoW2 allows <= 20)")
    v.add_argument("--levels", type=int, default=5, help="depth of the tree (DBoW2 allows <= 10)")
    v.add_argument("--features", type=int, default=1000, help="ORB features per frame")
    v.add_argument("--seed", type=int, default=0, help="seed of the k-means++ seeding")
    v.add_argument("--strict", action="store_true",
                   help="stop at the first unreadable frame (default: leave it out with a warning)")
    return p


def _generate(args: argparse.Namespace) -> int:
    if args.backend == "orbslam3":
        return _generate_orbslam3(args)
    if args.vocabulary is not None or args.orb_settings is not None:
        from ctcvo.data.errors import ConfigError

        raise ConfigError("--vocabulary and --orb-settings are options of --backend orbslam3")
    cfg = PRESETS[args.preset]
    if args.gaps is not None:
        cfg = dataclasses.replace(cfg, gaps=args.gaps)
    if args.workers is not None:
        cfg = dataclasses.replace(cfg, workers=args.workers)
    if args.keyframes is not None:
        cfg = dataclasses.replace(cfg, keyframes=args.keyframes)
    cfg = dataclasses.replace(cfg, covariance=args.covariance)
    if cfg.workers > 1:
        processes.start()  # the workers import Open3D and the teacher while this process does
    from ctcvo.teacher.generate import generate

    args.scene = scene_with_topics(args.scene, args)
    generate(args.scene, args.out, args.split, args.frames, cfg, args.overwrite, strict=args.strict, camera=args.camera)
    return 0


def _generate_orbslam3(args: argparse.Namespace) -> int:
    from ctcvo.data.errors import ConfigError
    from ctcvo.teacher.orbslam3_generate import generate_orbslam3

    if args.vocabulary is None:
        raise ConfigError("--backend orbslam3 needs --vocabulary FILE (build one with `ctcvo teacher vocabulary`)")
    args.scene = scene_with_topics(args.scene, args)
    generate_orbslam3(args.scene, args.vocabulary, args.out, args.split, args.frames,
                      args.gaps if args.gaps is not None else PRESETS[args.preset].gaps, args.mode, args.labels,
                      args.orb_settings, args.orb_features, args.overwrite, strict=args.strict)
    return 0


def _calibrate(args: argparse.Namespace) -> int:
    from ctcvo.teacher.calibrate import calibrate

    calibrate(args.scene, args.frames or [None], args.out, args.overwrite)
    return 0


def _vocabulary(args: argparse.Namespace) -> int:
    from ctcvo.teacher.orbslam3_generate import build_vocabulary_file

    build_vocabulary_file(args.scene, args.out, args.frames or [None], args.k, args.levels, args.features, args.seed,
                          strict=args.strict)
    return 0


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    body = {"generate": _generate, "calibrate": _calibrate, "vocabulary": _vocabulary}[args.command]
    return run(args, body, "interrupted (finished sequences are kept; rerun to resume)", fmt="%(message)s")


if __name__ == "__main__":
    sys.exit(main())
