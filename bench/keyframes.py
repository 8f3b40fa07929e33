"""Keyframe and loop edges on validation data: the teacher graph without them, with them, and
with each of their constants moved one at a time.

For each validation range (redkitchen 0:450 and 350:450, TUM fr3/teddy, synthetic/lab; and the
training room office) the default teacher's window edges are estimated once (``keyframes`` off); then the keyframe pass
(:func:`ctcvo.teacher.keyframes.add_keyframe_edges`) runs once per variant: ``window`` (no
keyframe pass), ``default`` (the module's constants; the bundle adjustment of the landmark
sightings where the colour is registered, as the teacher writes them), ``no bundle`` and
``bundle, any colour camera`` (default without it, and with it whatever the colour camera:
the keyframes' tracks, as the window keeps its own only where the colour is registered),
``keyframes' tracks only`` (default without the window's tracks),
each entry of :data:`SWEEP`, one constant changed, and each of :data:`GROUPED`. The pose graph
(:func:`ctcvo.posegraph.graph.solve`, the default ``PoseGraphConfig``, the calibrated
covariances ``edges.g2o`` carries, as ``posegraph optimize`` solves it) optimises each
variant's good edges; ATE, gap-1 and 1 s RPE are measured against the ground truth, and the
keyframe edges' median NEES. Record ``bench/results/keyframes.json``.

    python -m bench.keyframes [--scenes SPEC:START:STOP ...] [--camera CAM.json]

The record's rooms are undistorted with the camera ``teacher calibrate`` fits on office and lab
(``--camera``), as the demo undistorts its rooms.
"""

from __future__ import annotations

import argparse
import dataclasses
import time
from collections import Counter
from contextlib import contextmanager
from pathlib import Path

import numpy as np

from bench import record
from ctcvo.data.formats import Edge, Trajectory
from ctcvo.data.metrics import ate_rmse, groundtruth_residuals, rpe_rmse
from ctcvo.data.scenes import open_scene
from ctcvo.data.uncertainty import CHI2_6_MEDIAN, mahalanobis2
from ctcvo.data.undistort import with_camera
from ctcvo.posegraph.graph import solve
from ctcvo.teacher import covariance_model, keyframes, loops
from ctcvo.teacher.config import DEFAULT, colour_camera_for
from ctcvo.teacher.generate import cov_scales, features_of, run_sequence
from ctcvo.teacher.observations import merged, sightings

VALIDATION = [f"{record.REDKITCHEN}:0:450", f"{record.REDKITCHEN}:350:450", f"{record.TUM_TEDDY}:0:200",
              "synthetic/lab:0:300", "synthetic/office:0:300"]
#: the constants moved one at a time, each to the values listed (module keyframes or loops;
#: KEYFRAME_SCALE v: covariance_model.KEYFRAME_SCALES' factor of every noise model set to v)
SWEEP: dict[str, tuple[float, ...]] = {
    "KF_TRANS_M": (0.03, 0.1, 0.2), "KF_ROT_DEG": (5.0, 20.0), "KF_MIN_OVERLAP": (0.5, 0.85),
    "COVISIBLE_OVERLAP": (0.2, 0.6), "REACH_S": (3.0, 12.0), "MAX_COVISIBLE": (6, 10), "LOOP_SCORE": (0.6,),
    "FALLBACK_GATE_M": (0.1,), "KEYFRAME_SCALE": (0.15, 0.25, 0.5, 1.0, 2.0, 4.0),
    "REGISTERED_FEATURE_FACTOR": (1, 2, 4), "SEPARATE_FEATURE_FACTOR": (2, 3),
}
#: variants that move several constants together
GROUPED: dict[str, dict[str, float]] = {
    "no fallback gate": {"FALLBACK_GATE_M": float("inf"), "FALLBACK_GATE_DEG": float("inf")},
}


def _module(name: str):
    """The module of constant ``name``: keyframes or loops."""
    return keyframes if hasattr(keyframes, name) else loops


def _default(name: str):
    """The shipped value of a :data:`SWEEP` name."""
    return dict(covariance_model.KEYFRAME_SCALES) if name == "KEYFRAME_SCALE" else getattr(_module(name), name)


@contextmanager
def constants(**values):
    """The keyframe and loop modules' constants (and ``KEYFRAME_SCALE``, see :data:`SWEEP`)
    set to ``values`` for the ``with`` block."""
    scales = dict(covariance_model.KEYFRAME_SCALES)
    mods = {name: _module(name) for name in values if name != "KEYFRAME_SCALE"}
    old = {name: getattr(mods[name], name) for name in mods}
    try:
        for name, v in values.items():
            if name == "KEYFRAME_SCALE":
                covariance_model.KEYFRAME_SCALES = {k: float(v) for k in scales}
            else:
                setattr(mods[name], name, type(old[name])(v))
        yield
    finally:
        covariance_model.KEYFRAME_SCALES = scales
        for name, v in old.items():
            setattr(mods[name], name, v)


def figures(seq, edges, poses, kinds: dict, observations=None) -> dict:
    """Graph ATE and RPE of a run's good edges (calibrated covariances; with ``observations``,
    the bundle adjustment), the edges by kind and the keyframe edges' median NEES over
    chi-square(6)'s median (1: consistent)."""
    ok = [e for e in edges if e.ok]
    kind = [kinds.get((e.i, e.j), "window") for e in ok]
    scale = cov_scales(seq, ok, kinds)
    good = [Edge(e.i, e.j, e.T_i_j, e.cov * scale[e.i, e.j]) for e in ok]
    kf = [g for g, k in zip(good, kind) if k == "keyframe"]
    nees = mahalanobis2(groundtruth_residuals(kf, seq.groundtruth(), seq.ids()), np.array([g.cov for g in kf]))
    gt = Trajectory(seq.times(), seq.groundtruth())
    est = Trajectory(seq.times(), solve(seq.ids(), good, poses, observations=observations).poses)
    second = max(1, int(round(1.0 / np.median(np.diff(seq.times())))))
    by_kind = Counter(kinds.get((e.i, e.j), "window") + ("" if e.ok else "_failed") for e in edges)
    return {"ate_m": ate_rmse(gt, est), "rpe_gap1_m": rpe_rmse(gt, est, 1)[0], "rpe_1s_m": rpe_rmse(gt, est, second)[0],
            "chain_ate_m": ate_rmse(gt, Trajectory(seq.times(), poses)), "edges_by_kind": dict(by_kind),
            "keyframe_median_nees_over_chi2": float(np.median(nees)) / CHI2_6_MEDIAN if len(kf) else None}


ONLY_KEYFRAMES = "keyframes' tracks only"
EXTRA = ["no bundle", "bundle, any colour camera", ONLY_KEYFRAMES]  # variants of default's edges


def variants() -> list[tuple[str, dict]]:
    """(label, constants) of every variant after ``window``."""
    return ([("default", {})] + [(f"{name} {v:g}", {name: v}) for name, vs in SWEEP.items() for v in vs]
            + list(GROUPED.items()))


def run_range(seq, cfg) -> dict:
    """Every variant's figures on one validation range."""
    t0 = time.perf_counter()
    run = run_sequence(seq, cfg, progress=False)
    row = {"window": {**figures(seq, run.edges, run.poses, {}), "seconds": time.perf_counter() - t0}}
    registered = colour_camera_for(seq.sensor, cfg) is None
    for label, values in variants():
        edges = list(run.edges)
        t0 = time.perf_counter()
        with constants(**values):
            kinds = keyframes.add_keyframe_edges(seq, cfg, edges, run.poses, features_of(seq, cfg))
            pass_s = time.perf_counter() - t0
            own = sightings([e for e in edges if (e.i, e.j) in kinds], seq.intrinsics)
            seen = merged(own, run.observations) if registered else None  # as teacher generate writes them
            row[label] = {**figures(seq, edges, run.poses, kinds, seen), "keyframe_pass_s": pass_s}
            if label == "default":  # the bundle adjustment never, whatever the colour camera, without the window's
                same = {k: v for k, v in row[label].items() if k != "keyframe_pass_s"}  # default's own case
                row["no bundle"] = figures(seq, edges, run.poses, kinds) if registered else same
                row["bundle, any colour camera"] = same if registered else figures(seq, edges, run.poses, kinds, own)
                row[ONLY_KEYFRAMES] = figures(seq, edges, run.poses, kinds, own) if registered else same
        for lab in [label] + (EXTRA if label == "default" else []):
            print(seq.name, lab, {k: v for k, v in row[lab].items() if k != "edges_by_kind"}, flush=True)
    return row


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scenes", nargs="+", default=VALIDATION, help="SPEC:START:STOP of validation ranges")
    ap.add_argument("--camera", type=Path, help="a camera file (teacher calibrate) that undistorts the synthetic ranges, "
                    "as the demo undistorts its rooms")
    record.add_arguments(ap, "keyframes")
    args = ap.parse_args()
    cfg = dataclasses.replace(DEFAULT, workers=1, keyframes=False)
    rec = record.from_args(args, teacher=cfg, sweep={k: list(v) for k, v in SWEEP.items()},
                           defaults={name: _default(name) for name in SWEEP})
    out = {}
    for spec in args.scenes:
        scene, a, b = spec.rsplit(":", 2)
        seq = open_scene(scene, frames=f"{a}:{b}")[0]
        if args.camera is not None and scene.startswith("synthetic/"):
            seq = with_camera(seq, args.camera)
        out[f"{scene.rsplit('/', 1)[-1]}:{a}:{b}"] = run_range(seq, cfg)
        rec.finish({"scenes": out})


if __name__ == "__main__":
    main()
