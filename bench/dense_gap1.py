"""The point-to-plane step over one frame, on the real (Kinect v1) validation ranges.

Where the dense step would be the depth alone and the colour is registered to the depth
(TUM RGB-D), the teacher keeps a gap-1 edge's keypoint estimate (step 4 of
:mod:`ctcvo.teacher.odometry`). For each validation range (redkitchen 0:450 and 350:450, TUM
fr3/teddy) the default teacher runs as shipped, with the step on every gap-1 edge (as before,
with the covariance scales fitted then, :data:`WITH_GAP1_SCALES`), and without it on every
gap-1 edge (7-Scenes' too). Per variant: the teacher pose graph's ATE, gap-1 and 1 s RPE (every
edge kind, as ``posegraph optimize`` solves them), the chain's ATE, and per frame gap the
rotation's scale error, axis by axis: the least-squares slope of (estimate - ground truth) on
the ground truth's rotation vector (0: unbiased; -0.1: 10 % too little rotation; the ground
truth's own noise pulls it below 0, most at gap 1). Record ``bench/results/dense-gap1.json``.

    python -m bench.dense_gap1 [--scenes SPEC:START:STOP ...]
"""

from __future__ import annotations

import argparse
import dataclasses
from contextlib import contextmanager

import numpy as np

from bench import record
from bench.keyframes import figures as graph_figures
from ctcvo.data import geometry as geo
from ctcvo.data.scenes import open_scene
from ctcvo.teacher import covariance_model, keyframes, window
from ctcvo.teacher.config import DEFAULT
from ctcvo.teacher.generate import features_of, run_sequence

VALIDATION = [f"{record.REDKITCHEN}:0:450", f"{record.REDKITCHEN}:350:450", f"{record.TUM_TEDDY}:0:200"]
#: kinect-v1's per-gap scales fitted with the point-to-plane step on gap-1 edges (record
#: teacher-covariance at 87a5bfd, the same fit ranges)
WITH_GAP1_SCALES = (120, 94.7, 71.6, 77.4, 101)


@contextmanager
def gap1_rule(step: bool):
    """The window's gap-1 edges with the point-to-plane step on all of them (``step``; with the
    scales fitted then) or on none (every colour camera taken as registered)."""
    estimate, scales = window.estimate_edge, covariance_model.GAP_SCALES["kinect-v1"]

    def forced(i, j, fi, fj, *args, **kw):
        if not step:
            fi.registered = fj.registered = True
        return estimate(i, j, fi, fj, *args, **{**kw, "gap1": kw.get("gap1", False) and not step})

    window.estimate_edge = forced
    if step:
        covariance_model.GAP_SCALES["kinect-v1"] = WITH_GAP1_SCALES
    try:
        yield
    finally:
        window.estimate_edge, covariance_model.GAP_SCALES["kinect-v1"] = estimate, scales


def rotation_scale_errors(seq, edges, gaps=range(1, 6)) -> dict[int, list[float]]:
    """Per gap, the slope of (estimate - ground truth) on the ground truth's rotation vector,
    per camera axis (x, y, z), over the good window edges of that gap."""
    gt, pos = seq.groundtruth(), {int(k): p for p, k in enumerate(seq.ids())}
    out = {}
    for g in gaps:
        pairs = [(geo.se3_log(geo.relative_pose(gt[pos[e.i]], gt[pos[e.j]]))[3:], geo.se3_log(e.T_i_j)[3:])
                 for e in edges if e.ok and pos[e.j] - pos[e.i] == g]
        if not pairs:
            continue
        X = np.array([p[0] for p in pairs])
        Y = np.array([p[1] for p in pairs]) - X
        out[g] = [float(X[:, k] @ Y[:, k] / max(X[:, k] @ X[:, k], 1e-30)) for k in range(3)]
    return out


def figures(seq, cfg) -> dict:
    """The teacher's run on ``seq`` with keyframe edges, through the default pose graph
    (:func:`bench.keyframes.figures`), and its window edges' rotation scale errors."""
    run = run_sequence(seq, cfg, progress=False)
    edges = list(run.edges)
    kinds = keyframes.add_keyframe_edges(seq, cfg, edges, run.poses, features_of(seq, cfg))
    return {**graph_figures(seq, edges, run.poses, kinds), "rotation_scale_error": rotation_scale_errors(seq, run.edges)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scenes", nargs="+", default=VALIDATION, help="SPEC:START:STOP of validation ranges")
    record.add_arguments(ap, "dense-gap1")
    args = ap.parse_args()
    cfg = dataclasses.replace(DEFAULT, workers=1, keyframes=False)
    rec = record.from_args(args, teacher=cfg, with_gap1_scales=WITH_GAP1_SCALES)
    out = {}
    for spec in args.scenes:
        scene, a, b = spec.rsplit(":", 2)
        seq = open_scene(scene, frames=f"{a}:{b}")[0]
        row = {"shipped": figures(seq, cfg)}
        for label, step in (("step at every gap 1", True), ("at no gap 1", False)):
            with gap1_rule(step):
                row[label] = figures(seq, cfg)
        out[f"{scene.rsplit('/', 1)[-1]}:{a}:{b}"] = row
        print(spec, {v: {k: x for k, x in f.items() if k != "rotation_scale_error"} for v, f in row.items()}, flush=True)
        rec.finish({"scenes": out})


if __name__ == "__main__":
    main()
