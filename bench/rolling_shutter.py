"""Rolling shutter and the dense point-to-plane step: a diagnosis on a synthetic room.

The synthetic sensor reads its rows out over ``rolling_shutter_s`` (27 ms, Kinect v1-like):
row ``r`` of frame k is seen from ``T_k exp(s_r xi_k)``, ``s_r = (r / (H - 1) - 0.5) *
readout``, the ground truth is the middle row's pose. This script aligns pairs of frames
(gaps 1, 3, 5) with Open3D's point-to-plane kernel as the teacher's dense step does (the
teacher's maps, ``dense_scale`` / ``dense_target_scale``), from the ground truth perturbed by
2 mm / 0.17 deg, and reports the translation error (median / mean, mm) three ways:

* ``plain``: the maps as they are (what the teacher does);
* ``warp``: both frames' vertex maps moved to their middle row's moment to first order,
  ``X + s_r (w x X + v)`` (:func:`teacher.odometry.map_to_middle_row`, as the teacher moves
  them), with the true velocity of each frame (the renderer's own central difference of the
  ground truth): what a rolling-shutter-aware step could at best do;
* ``warp, wrong sign``: the same warp reversed (a check that the warp is not just noise).

Repeated frames are off (they repeat poses). ``--clean-depth`` turns the depth noise, bias,
quantisation and holes off, leaving the rolling shutter (and the colour sensor, unused here).

    OMP_NUM_THREADS=1 .venv/bin/python -m bench.rolling_shutter --clean-depth --iters 20
    OMP_NUM_THREADS=1 .venv/bin/python -m bench.rolling_shutter --clean-depth --iters 20 --readout 0
    OMP_NUM_THREADS=1 .venv/bin/python -m bench.rolling_shutter --iters 3

Diagnosis only: no teacher parameter comes from it (bench/README.md, "Rolling shutter").
"""

from __future__ import annotations

import argparse
import dataclasses

import numpy as np

from bench.teacher_profile import CLEAN_DEPTH, NO_REPEATS  # --clean-depth: the sensor fields set to 0
from ctcvo.data import geometry as geo
from ctcvo.data.open3d_import import o3d
from ctcvo.data.synthetic import synthetic_sequence
from ctcvo.data.synthetic.config import resolve_preset
from ctcvo.teacher import odometry as od
from ctcvo.teacher.config import TeacherConfig

#: the start's offset from the ground truth, se(3) (v, w): 3 mm, 0.17 deg
START = np.array([0.002, -0.002, 0.001, 0.002, 0.001, -0.001])


def point_to_plane(T: np.ndarray, di: od.DenseMaps, dj: od.DenseMaps, cfg: TeacherConfig, iters: int) -> np.ndarray:
    """``iters`` iterations of Open3D's point-to-plane kernel from ``T`` (T_i_j), as the
    teacher's dense stage runs them (no early stop)."""
    Tt = o3d.core.Tensor(T)
    for _ in range(iters):
        step = o3d.t.pipelines.odometry.compute_odometry_result_point_to_plane(
            dj.points, di.vertex, di.normal, di.K, Tt, cfg.dense_trunc_m, cfg.dense_huber_m)
        Tt = step.transformation.matmul(Tt)
    return Tt.numpy()


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scene", default="lab", help="a synthetic preset (validation: lab)")
    ap.add_argument("--frames", type=int, default=150, help="pairs are drawn from frames 10 .. FRAMES - 10")
    ap.add_argument("--readout", type=float, default=0.027, help="the render's rolling shutter readout, s (0: global)")
    ap.add_argument("--clean-depth", action="store_true")
    ap.add_argument("--iters", type=int, default=20)
    ap.add_argument("--every", type=int, default=9, help="a pair every EVERY frames")
    args = ap.parse_args(argv)
    base = resolve_preset(args.scene)
    sensor = dataclasses.replace(base.sensor, **NO_REPEATS, **(CLEAN_DEPTH if args.clean_depth else {}),
                                 rolling_shutter_s=args.readout)
    seq = synthetic_sequence(args.scene, config=dataclasses.replace(base, sensor=sensor))
    gt, K, h, cfg = seq.groundtruth(), seq.intrinsics.K, seq.intrinsics.height, TeacherConfig()
    dt = 1.0 / base.fps
    maps: dict[int, od.DenseMaps] = {}

    def dense(k: int) -> od.DenseMaps:
        if k not in maps:
            maps[k] = od.dense_maps(seq.depth(k), K, cfg)
        return maps[k]

    def velocity(k: int) -> np.ndarray:  # as the renderer: central difference, per second
        return geo.se3_log(geo.relative_pose(gt[k - 1], gt[k + 1])) / (2 * dt)

    readout = base.sensor.rolling_shutter_s  # what a teacher would be told of the camera
    for g in (1, 3, 5):
        errs: dict[str, list[float]] = {"plain": [], "warp": [], "warp, wrong sign": []}
        for i in range(10, min(args.frames, len(seq)) - 10 - g, args.every):
            j = i + g
            G = geo.relative_pose(gt[i], gt[j])
            T0 = G @ geo.se3_exp(START)
            di, dj = dense(i), dense(j)
            for name, sign in (("plain", 0.0), ("warp", 1.0), ("warp, wrong sign", -1.0)):
                if sign:
                    wi = od.DenseMaps(di.points, od.map_to_middle_row(di.vertex, cfg.dense_target_scale, h, velocity(i),
                                                                      sign * readout), di.normal, di.K)
                    wj = od.DenseMaps(od.map_to_middle_row(dj.points, cfg.dense_scale, h, velocity(j), sign * readout),
                                      None, None, dj.K)
                else:
                    wi, wj = di, dj
                T = point_to_plane(T0, wi, wj, cfg, args.iters)
                errs[name].append(1000 * float(np.linalg.norm((geo.inv_T(G) @ T)[:3, 3])))
        print(f"{args.scene} readout {args.readout * 1000:.0f} ms{' clean depth' if args.clean_depth else ''}, "
              f"{args.iters} iterations, gap {g} ({len(errs['plain'])} pairs): "
              + "; ".join(f"{k} {np.median(v):.2f} / {np.mean(v):.2f}" for k, v in errs.items()), flush=True)


if __name__ == "__main__":
    main()
