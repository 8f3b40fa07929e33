"""What the synthetic sensor's depth bias pattern costs the teacher graph, room by room.

The synthetic sensor (Kinect v1 model, :mod:`ctcvo.data.synthetic.sensor`) adds to every depth
image a fixed, smooth inverse-depth bias pattern, seeded per room (``depth_bias_coeff``,
``depth_bias_px``). Long edges see a surface at other pixels than short ones, so the pattern
biases them differently, and alike across a room: a consistency check (and so the pose
graph's weights) cannot see it. Per room, the default teacher (``teacher generate``'s
settings, keyframes included) runs twice on the same frames, undistorted with the camera
``--camera`` as the demo undistorts them: as rendered, and with the room's true pattern
subtracted from every raw depth image (an oracle: the field the renderer added, which no
real recording gives). Each run's chain and teacher pose graph (as ``posegraph optimize``
solves it: :func:`bench.keyframes.figures`) are measured against the ground truth.

A diagnostic, not a choice: nothing is tuned on it. Its rooms are lab (validation), office
(training) and kitchen (the demo's test room, run last). Record ``bench/results/depth-bias.json``.

    python -m bench.depth_bias --camera CAM.json [--rooms lab office kitchen] [--frames 0:300]
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from bench import record
from bench.keyframes import figures as graph_figures
from ctcvo.data.scenes import open_scene
from ctcvo.data.sevenscenes import SevenScenesSequence
from ctcvo.data.synthetic.config import resolve_preset
from ctcvo.data.synthetic.sensor import depth_bias_field
from ctcvo.data.undistort import with_camera
from ctcvo.teacher.config import DEFAULT
from ctcvo.teacher.generate import run_sequence

ROOMS = ["lab", "office", "kitchen"]


class DebiasedSequence(SevenScenesSequence):
    """A rendered room whose raw depth images have ``bias`` (H, W, inverse metres) taken off
    (a module-level class, so the teacher's worker processes can unpickle it)."""

    bias: NDArray[np.float32]

    def _read_depth(self, pos: int) -> NDArray[np.float32]:
        z = super()._read_depth(pos)
        out = np.zeros_like(z)
        valid = z > 0
        inv = 1.0 / z[valid] - self.bias[valid]
        out[valid] = np.where(inv > 0, 1.0 / np.maximum(inv, 1e-6), 0.0)
        return out


def debiased(seq: SevenScenesSequence, room: str) -> SevenScenesSequence:
    """``seq`` (rendered room ``room``, not undistorted yet) with its true bias pattern removed, in place."""
    cfg = resolve_preset(room)
    bias = depth_bias_field(cfg.sensor, (cfg.height, cfg.width), cfg.seed)
    if bias is None:
        raise SystemExit(f"synthetic/{room} renders no depth bias pattern")
    seq.__class__ = DebiasedSequence
    seq.bias = bias
    return seq


def measure(seq) -> dict:
    """The default teacher's chain and graph figures on ``seq``."""
    run = run_sequence(seq, DEFAULT, progress=False)
    f = graph_figures(seq, run.edges, run.poses, run.kinds, run.observations)
    return {k: f[k] for k in ("ate_m", "rpe_gap1_m", "rpe_1s_m", "chain_ate_m")}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--camera", type=Path, required=True, help="camera file the rooms are undistorted with")
    ap.add_argument("--rooms", nargs="+", default=ROOMS, help="synthetic rooms (default: lab office kitchen)")
    ap.add_argument("--frames", default="0:300", help="frame range of every room (default 0:300)")
    record.add_arguments(ap, "depth-bias")
    args = ap.parse_args()
    rec = record.from_args(args, teacher=DEFAULT)
    rows = {}
    for room in args.rooms:
        rows[room] = {}
        for label in ("as rendered", "bias removed"):
            seq = open_scene(f"synthetic/{room}", frames=args.frames)[0]
            if label == "bias removed":
                seq = debiased(seq, room)
            rows[room][label] = measure(with_camera(seq, args.camera))
        print(room, rows[room], flush=True)
        rec.finish({"rooms": rows})


if __name__ == "__main__":
    main()
