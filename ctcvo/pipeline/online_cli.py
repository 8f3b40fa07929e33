"""``ctcvo online``: the command line of :func:`pipeline.online.online`."""

from __future__ import annotations

import argparse
import dataclasses
import logging
import sys
from collections.abc import Sequence
from pathlib import Path

from ctcvo.data.cli import HelpFormatter
from ctcvo.data.errors import ConfigError, VOError, one_line
from ctcvo.data.io import setup_logging
from ctcvo.data.scenes import add_topic_options, scene_with_topics
from ctcvo.learner.config import PredictConfig
from ctcvo.pipeline.online import online
from ctcvo.pipeline.online_loop import ONLINE_GAPS, OnlineConfig
from ctcvo.pipeline.online_outputs import TRAJECTORY
from ctcvo.teacher.config import PRESETS as TEACHER_PRESETS

DESCRIPTION = """\
Odometry frame by frame, as the frames arrive: the teacher's edges of each new
frame (and, with --checkpoint, the learner's), an ISAM2 pose graph, and each
frame's pose appended to OUT/trajectory.tum as soon as it is known. Keyframe
and loop edges (as teacher generate adds them) are estimated in a helper thread
and enter the graph a few frames later.

Frames come from any --scene read in order, or with --follow from a
7-Scenes-layout or TUM RGB-D folder still being written. At the end (or on
Ctrl-C) OUT holds the smoothed trajectory_final.tum, the edges in teacher/ and
learner/ and report.json (fps, latency, ATE when there is ground truth). A rerun
of the same inputs keeps a finished run."""


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="ctcvo online", description=DESCRIPTION, formatter_class=HelpFormatter)
    p.add_argument("--scene", required=True, help="sequence folder, ROS bag or synthetic/NAME; with --follow "
                   "a 7-Scenes-layout or TUM RGB-D folder being written")
    p.add_argument("--checkpoint", type=Path,
                   help="learner checkpoint: add its MC-dropout edges (default: none, teacher edges only)")
    p.add_argument("--out", type=Path, help="output folder (default runs/<scene>/online)")
    p.add_argument("--overwrite", action="store_true",
                   help="replace the outputs of other inputs in --out instead of stopping with an error")
    p.add_argument("--frames", help="frame range START:STOP[:STEP] (default: every frame)")
    p.add_argument("--camera", type=Path, default=None,
                   help="camera file from `ctcvo teacher calibrate`: undistort the frames with its lens distortion "
                        "(default: the frames as the reader gives them)")
    p.add_argument("--follow", action="store_true", help="the folder is still being written: wait for new frames")
    p.add_argument("--timeout", type=float, default=OnlineConfig.timeout_s,
                   help="--follow: end after this many seconds without a new frame")
    p.add_argument("--poll", type=float, default=OnlineConfig.poll_s, help="--follow: seconds between polls")
    p.add_argument("--gaps", type=int, help=f"teacher edges to the last K frames (default {ONLINE_GAPS}, or the preset's "
                   "if fewer; teacher generate's are 5)")
    p.add_argument("--preset", default="default", choices=sorted(TEACHER_PRESETS), help="teacher preset")
    p.add_argument("--keyframes", action=argparse.BooleanOptionalAction, default=None,
                   help="also estimate keyframe and loop edges (as teacher generate), in a helper thread off the "
                   "frames' critical path (default: the preset's, on)")
    p.add_argument("--pose-after-gap1", action=argparse.BooleanOptionalAction, default=OnlineConfig.pose_after_gap1,
                   help="write each frame's pose once its gap-1 edge is in the graph; its longer edges follow "
                   "(default: on)")
    p.add_argument("--drop-late", action="store_true",
                   help="--follow: when frames come faster than they are processed, take the newest and skip "
                   "the ones in between (bounded latency, fewer frames)")
    p.add_argument("--samples", type=int, help="MC-dropout passes K (default 10)")
    p.add_argument("--max-gap", type=int, help="learner edges to the last frames (default 5)")
    p.add_argument("--device", default="auto", choices=["auto", "cpu", "cuda"],
                   help="learner device; auto: CUDA when available, else the CPU")
    p.add_argument("-v", "--verbose", action="store_true")
    add_topic_options(p)
    return p


def _configs(args: argparse.Namespace) -> tuple:
    """The teacher, predict and online configs of the options (ConfigError for bad online ones)."""
    tcfg = TEACHER_PRESETS[args.preset]
    tcfg = dataclasses.replace(tcfg, gaps=args.gaps if args.gaps is not None else min(tcfg.gaps, ONLINE_GAPS))
    if args.keyframes is not None:
        tcfg = dataclasses.replace(tcfg, keyframes=args.keyframes)
    pcfg = PredictConfig(**{k: v for k, v in (("samples", args.samples), ("max_gap", args.max_gap)) if v is not None})
    if args.timeout <= 0 or args.poll <= 0:
        raise ConfigError("--timeout and --poll must be positive")
    if args.drop_late and not args.follow:
        raise ConfigError("--drop-late needs --follow (a recording read from disk has every frame taken)")
    ocfg = OnlineConfig(poll_s=args.poll, timeout_s=args.timeout, pose_after_gap1=args.pose_after_gap1,
                        drop_late=args.drop_late)
    return tcfg, pcfg, ocfg


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    setup_logging(args.verbose, "%(message)s")
    if not args.verbose:  # the final smoothing's solver lines (scales, re-solves, LM): -v shows them
        logging.getLogger("ctcvo.posegraph.graph").setLevel(logging.WARNING)
    try:
        scene = scene_with_topics(args.scene, args)
        tcfg, pcfg, ocfg = _configs(args)
        res = online(scene, args.out, frames=args.frames, follow=args.follow, teacher_cfg=tcfg,
                     checkpoint=args.checkpoint, predict_cfg=pcfg if args.checkpoint else None, cfg=ocfg,
                     device=args.device, overwrite=args.overwrite, camera=args.camera)
    except VOError as exc:
        print(f"error: {one_line(exc)}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:  # outside the frame loop (opening, writing)
        print("error: interrupted", file=sys.stderr)
        return 130
    rep = res.report
    line = (f"{res.frames} frames, {res.fps:.1f} fps, latency p50 {res.latency_ms['p50']:.0f} ms / "
            f"p95 {res.latency_ms['p95']:.0f} ms")
    if "final" in rep:
        line += f", ATE {1000 * rep['final']['ate_rmse_m']:.1f} mm"
    if res.interrupted:
        print(f"interrupted after {line}; trajectory so far in {res.out / TRAJECTORY}", file=sys.stderr)
        return 130
    print(f"{line} -> {res.out}" + (" (kept: a finished run of the same inputs)" if res.kept else ""))
    return 0


if __name__ == "__main__":
    sys.exit(main())
