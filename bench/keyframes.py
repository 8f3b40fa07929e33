"""Keyframe and loop edges on validation data: the teacher graph with and without them.

For each validation range (redkitchen 0:450 and 350:450, TUM fr3/teddy, synthetic/lab) the default
teacher runs twice, without and with ``keyframes`` (:mod:`ctcvo.teacher.keyframes`); the
pose graph (:func:`ctcvo.posegraph.graph.solve`, the default ``PoseGraphConfig``, as
``posegraph optimize`` solves the teacher's edges.g2o) optimises each run's good edges, and
ATE, gap-1 and 1 s RPE are measured against the ground truth. Record
``bench/results/keyframes.json``.

    python -m bench.keyframes [--scenes SPEC:FRAMES ...]
"""

from __future__ import annotations

import argparse
import dataclasses
import time
from collections import Counter

import numpy as np

from bench import record
from ctcvo.data.formats import Edge, Trajectory
from ctcvo.data.metrics import ate_rmse, rpe_rmse
from ctcvo.data.scenes import open_scene
from ctcvo.posegraph.graph import solve
from ctcvo.teacher.config import DEFAULT
from ctcvo.teacher.generate import run_sequence

VALIDATION = [f"{record.REDKITCHEN}:0:450", f"{record.REDKITCHEN}:350:450", f"{record.TUM_TEDDY}:0:200", "synthetic/lab:0:200"]


def _figures(seq, run) -> dict:
    gt = Trajectory(seq.times(), seq.groundtruth())
    edges = [Edge(e.i, e.j, e.T_i_j, e.cov) for e in run.edges if e.ok]
    poses = solve(seq.ids(), edges, run.poses).poses
    est = Trajectory(seq.times(), poses)
    second = max(1, int(round(1.0 / np.median(np.diff(seq.times())))))
    kinds = Counter(run.kinds.get((e.i, e.j), "window") + ("" if e.ok else "_failed") for e in run.edges)
    return {"ate_m": ate_rmse(gt, est), "rpe_gap1_m": rpe_rmse(gt, est, 1)[0],
            "rpe_1s_m": rpe_rmse(gt, est, second)[0], "chain_ate_m": ate_rmse(gt, Trajectory(seq.times(), run.poses)),
            "teacher_seconds": run.seconds, "edges_by_kind": dict(kinds)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scenes", nargs="+", default=VALIDATION, help="SPEC:START:STOP of validation ranges")
    record.add_arguments(ap, "keyframes")
    args = ap.parse_args()
    cfg = dataclasses.replace(DEFAULT, workers=1)
    rec = record.from_args(args, teacher=cfg)
    out = {}
    for spec in args.scenes:
        scene, a, b = spec.rsplit(":", 2)
        seq = open_scene(scene, frames=f"{a}:{b}")[0]
        row = {}
        for on in (False, True):
            t0 = time.perf_counter()
            run = run_sequence(seq, dataclasses.replace(cfg, keyframes=on), progress=False)
            row["keyframes" if on else "window"] = {**_figures(seq, run), "wall_s": time.perf_counter() - t0}
            print(spec, on, row["keyframes" if on else "window"], flush=True)
        out[f"{scene.rsplit('/', 1)[-1]}:{a}:{b}"] = row
        rec.finish({"scenes": out})


if __name__ == "__main__":
    main()
