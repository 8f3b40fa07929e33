"""Colour-depth timing (issue 13, sixth session): does the teacher's ``depth_time_compensation``
recover, on a scene whose depth images are taken at other moments than its colour images,
the accuracy it has where both are taken together?

On a synthetic validation scene (default ``lab``) rendered twice with its repeated frames off
(their poses follow the depth, which the time offsets do not model): with colour and depth
at the same moment, and with each frame's depth taken ``--offset LO HI`` seconds after its
colour (uniform per frame; TUM fr1/xyz's association is about ``-0.0167 0``). The teacher
runs on both, with and without the compensation (gap-1 edges, ``gaps`` 1: the gap-1 edges of
a ``gaps`` 5 run are the same), and optionally Open3D's hybrid odometry (``--open3d``).

With ``--tum FOLDER`` (diagnosis only: TUM is not used for choices) the gap-1 edges of the
teacher and of Open3D on a TUM sequence are compared with the ground truth interpolated at
the colour (RGB) timestamps, at the depth timestamps, and at the RGB timestamps shifted by
a constant (the ground truth's own clock offset).

    .venv/bin/python -m bench.depth_timing --scene lab [--dense-method point-to-plane]
    .venv/bin/python -m bench.depth_timing --tum ../shared/data/tum/images/rgbd_dataset_freiburg1_xyz
    .venv/bin/python -m bench.depth_timing --tum ../shared/data/tum/images/rgbd_dataset_freiburg1_xyz --labels --frames 0:150
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
from pathlib import Path

if __name__ == "__main__":
    from ctcvo.teacher import processes

    processes.start()

import numpy as np  # noqa: E402

from ctcvo.data import geometry as geo  # noqa: E402
from ctcvo.data.formats import Trajectory  # noqa: E402
from ctcvo.data.metrics import trajectory_report  # noqa: E402
from ctcvo.teacher.config import TeacherConfig  # noqa: E402
from ctcvo.teacher.generate import run_sequence  # noqa: E402


def _sensor_variant(name: str, offset: tuple[float, float]):
    from ctcvo.data.synthetic import synthetic_sequence
    from ctcvo.data.synthetic.config import resolve_preset

    cfg = resolve_preset(name)
    sensor = dataclasses.replace(cfg.sensor, frame_repeat_prob=0.0, rgb_repeat_prob=0.0, depth_repeat_prob=0.0,
                                 depth_time_offset_s=tuple(offset))
    return synthetic_sequence(name, config=dataclasses.replace(cfg, sensor=sensor))


def _report(seq, poses) -> dict:
    rep = trajectory_report(Trajectory(seq.times(), seq.groundtruth()), Trajectory(seq.times(), poses))
    return {"gap1_mm": 1000 * rep["rpe_trans_rmse_m"], "gap1_deg": rep["rpe_rot_rmse_deg"], "ate_mm": 1000 * rep["ate_rmse_m"]}


def synthetic(args) -> list[dict]:
    rows = []
    for label, offset in (("same moment", (0.0, 0.0)), (f"depth {args.offset[0]:+.4f}..{args.offset[1]:+.4f} s", args.offset)):
        seq = _sensor_variant(args.scene, offset)
        if args.frames:
            a, b = (int(v) for v in args.frames.split(":"))
            seq = seq.select(a, b)
        offs = seq.depth_offsets()
        runs = [("teacher", True)] if not offs.any() else [("teacher, no compensation", False), ("teacher", True)]
        for method, comp in runs:
            cfg = dataclasses.replace(TeacherConfig(), gaps=1, depth_time_compensation=comp, dense_method=args.dense_method)
            run = run_sequence(seq, cfg, progress=False)
            if args.dense_method != "auto":
                method += f", {args.dense_method}"
            rows.append({"scene": args.scene, "timing": label, "method": method, **_report(seq, run.poses)})
            print(rows[-1], file=sys.stderr, flush=True)
        if args.open3d:
            from bench.teacher import run_open3d

            rows.append({"scene": args.scene, "timing": label, "method": "Open3D hybrid",
                         **_report(seq, run_open3d(seq)[0])})
            print(rows[-1], file=sys.stderr, flush=True)
    print("| scene | colour-depth timing | method | gap-1 mm | gap-1 deg | ATE mm |")
    print("|---|---|---|---|---|---|")
    for r in rows:
        print(f"| {r['scene']} {args.frames or ''} | {r['timing']} | {r['method']} | {r['gap1_mm']:.2f} | "
              f"{r['gap1_deg']:.3f} | {r['ate_mm']:.1f} |")
    return rows


def tum(args) -> list[dict]:
    from bench.teacher import run_open3d
    from ctcvo.data.tum import TumSequence, interpolate_poses, read_groundtruth

    seq = TumSequence(args.tum)
    if args.frames:
        a, b = (int(v) for v in args.frames.split(":"))
        seq = seq.select(a, b)
    tr, td = seq.times(), seq.depth_times()
    t_gt, T_gt = read_groundtruth(Path(args.tum) / "groundtruth.txt")
    dt = td - tr
    print(f"depth minus RGB time: median {1e3 * np.median(dt):.1f} ms, 5-95 % {1e3 * np.percentile(dt, 5):.1f} "
          f"to {1e3 * np.percentile(dt, 95):.1f} ms; its change between consecutive frames: std "
          f"{1e3 * np.diff(dt).std():.1f} ms", file=sys.stderr)
    methods = {}
    for name, kw in (("teacher, no compensation", {"depth_time_compensation": False}), ("teacher", {}),
                     ("teacher sparse only (dense_iters 0), no compensation", {"dense_iters": 0,
                                                                                "depth_time_compensation": False})):
        run = run_sequence(seq, dataclasses.replace(TeacherConfig(), gaps=1, **kw), progress=False)
        methods[name] = run.poses
    methods["Open3D hybrid"] = run_open3d(seq)[0]
    refs = {"GT at RGB times": tr, "GT at depth times": td, "GT at RGB times - 10 ms": tr - 0.010,
            "GT at RGB times - 20 ms": tr - 0.020}
    rows = []
    for ref, t in refs.items():
        G = interpolate_poses(t_gt, T_gt, t)
        for name, poses in methods.items():
            e = []
            for k in range(len(t) - 1):
                D = geo.inv_T(geo.relative_pose(G[k], G[k + 1])) @ geo.relative_pose(poses[k], poses[k + 1])
                e.append((np.linalg.norm(D[:3, 3]), geo.rotation_angle_deg(D)))
            e = np.array(e)
            rows.append({"reference": ref, "method": name, "gap1_mm": 1000 * float(np.sqrt(np.mean(e[:, 0] ** 2))),
                         "gap1_deg": float(np.sqrt(np.mean(e[:, 1] ** 2)))})
    # the uncompensated teacher's and Open3D's gap-1 motions moved from the depth to the colour
    # moments afterwards, T_r = C_i T C_{i+1}^-1, with C from the ground truth itself (an oracle),
    # from its velocity over the frame interval, or from the previous estimated motion (causal)
    G_r, G_d = interpolate_poses(t_gt, T_gt, tr), interpolate_poses(t_gt, T_gt, td)
    n = len(tr)
    for name in ("teacher, no compensation", "Open3D hybrid"):
        E = [geo.relative_pose(methods[name][k], methods[name][k + 1]) for k in range(n - 1)]
        vel = [geo.se3_log(E[k]) / (tr[k + 1] - tr[k]) for k in range(n - 1)]
        vel_gt = [geo.se3_log(geo.relative_pose(G_r[k], G_r[k + 1])) / (tr[k + 1] - tr[k]) for k in range(n - 1)]
        sources = {"oracle C (ground truth at both moments)": [geo.relative_pose(G_r[k], G_d[k]) for k in range(n)],
                   "C from the ground truth's velocity": [geo.se3_exp(vel_gt[min(k, n - 2)] * dt[k]) for k in range(n)],
                   "C from the previous estimated motion": [geo.se3_exp(vel[max(k - 1, 0)] * dt[k]) for k in range(n)]}
        for label, C in sources.items():
            moved = np.array([np.eye(4)] + [C[k] @ E[k] @ geo.inv_T(C[k + 1]) for k in range(n - 1)])
            rows_e = []
            for k in range(n - 1):
                D = geo.inv_T(geo.relative_pose(G_r[k], G_r[k + 1])) @ moved[k + 1]
                rows_e.append((np.linalg.norm(D[:3, 3]), geo.rotation_angle_deg(D)))
            e = np.array(rows_e)
            rows.append({"reference": "GT at RGB times", "method": f"{name}, moved afterwards: {label}",
                         "gap1_mm": 1000 * float(np.sqrt(np.mean(e[:, 0] ** 2))),
                         "gap1_deg": float(np.sqrt(np.mean(e[:, 1] ** 2)))})
    print("| reference | method | gap-1 mm | gap-1 deg |")
    print("|---|---|---|---|")
    for r in rows:
        print(f"| {r['reference']} | {r['method']} | {r['gap1_mm']:.2f} | {r['gap1_deg']:.3f} |")
    return rows


def tum_labels(args) -> list[dict]:
    """The teacher as ``bench.teacher`` runs it (default config, gaps 1-5), with and without the
    compensation, on a TUM folder: gap-1 RPE and ATE of the chained trajectory against the
    ground truth at the RGB times (the "before" beside ``bench.teacher``'s figures)."""
    from ctcvo.data.tum import TumSequence

    seq = TumSequence(args.tum)
    if args.frames:
        a, b = (int(v) for v in args.frames.split(":"))
        seq = seq.select(a, b)
    rows = []
    for comp in (False, True):
        run = run_sequence(seq, dataclasses.replace(TeacherConfig(), depth_time_compensation=comp), progress=False)
        rows.append({"frames": len(seq), "depth_time_compensation": comp, **_report(seq, run.poses)})
    print("| frames | depth_time_compensation | gap-1 mm | gap-1 deg | ATE mm |")
    print("|---|---|---|---|---|")
    for r in rows:
        print(f"| {args.frames or 'all'} ({r['frames']}) | {r['depth_time_compensation']} | {r['gap1_mm']:.2f} | "
              f"{r['gap1_deg']:.3f} | {r['ate_mm']:.1f} |")
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scene", default="lab", help="synthetic scene (a validation scene: lab)")
    ap.add_argument("--frames", default=None, help="frame range START:STOP")
    ap.add_argument("--offset", nargs=2, type=float, default=[-1 / 60, 0.0], metavar=("LO", "HI"),
                    help="depth minus colour time range, seconds (default: TUM-like -0.0167 0)")
    ap.add_argument("--open3d", action="store_true", help="also Open3D's hybrid odometry (slow)")
    ap.add_argument("--dense-method", default="auto", choices=["auto", "hybrid", "point-to-plane"],
                    help="the teacher's dense_method (auto: hybrid on synthetic scenes; real recordings: point-to-plane)")
    ap.add_argument("--tum", type=Path, default=None, help="diagnosis on a TUM RGB-D folder instead")
    ap.add_argument("--labels", action="store_true",
                    help="with --tum: the teacher's labels (gaps 1-5) with and without the compensation, RPE and ATE")
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args()
    rows = (tum_labels(args) if args.labels else tum(args)) if args.tum else synthetic(args)
    if args.json:
        args.json.write_text(json.dumps(rows, indent=2))


if __name__ == "__main__":
    main()
