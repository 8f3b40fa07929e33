"""Teacher benchmark: this teacher vs Open3D's hybrid RGB-D odometry vs OpenCV's
``cv2.Odometry`` (RGB_DEPTH), side by side on the same frames in one run.

For each scene: frames per second end to end (decode included; the teacher also
estimates its gap 2..K edges, the peers only gap 1) and gap-1 RPE (trans, rot), ATE and
the paper's se(3) L2 of the chained gap-1 trajectory, all metrics through evo; for the
teacher also its constant-velocity bridges, failed gap-1 edges and the paths that made its
gap-1 edges (see teacher/odometry.py's fallback chain), and its ratios to Open3D (gap-1
error, fps).

    .venv/bin/python -m bench.teacher          # every synthetic preset, stress scenes included,
                                               # redkitchen and TUM fr1/xyz images; teacher + Open3D
    .venv/bin/python -m bench.teacher --scenes ../shared/data/7scenes/redkitchen/seq-sample --frames 450:600 \
        --peers open3d cv2 --name teacher-redkitchen-test
    .venv/bin/python -m bench.teacher --scenes synthetic/stress-far --synthetic-frames 60   # a 60-frame walk

The record is ``bench/results/<name>.json`` (bench/record.py), rewritten after every scene so
that a run cut short keeps what it measured; stdout gets a Markdown table.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from collections import Counter
from pathlib import Path

if __name__ == "__main__":  # as `teacher generate` does: its worker imports while this process does
    from ctcvo.teacher import processes

    processes.start()

import cv2  # noqa: E402
import numpy as np  # noqa: E402
from threadpoolctl import threadpool_limits  # noqa: E402

from bench import record  # noqa: E402
from ctcvo.data import geometry as geo  # noqa: E402
from ctcvo.data.chain import chain_steps  # noqa: E402
from ctcvo.data.formats import Trajectory  # noqa: E402
from ctcvo.data.metrics import trajectory_report  # noqa: E402
from ctcvo.data.scenes import open_scene  # noqa: E402
from ctcvo.teacher.config import TeacherConfig  # noqa: E402
from ctcvo.teacher.generate import run_sequence  # noqa: E402

SYNTHETIC = ["synthetic/office", "synthetic/lab", "synthetic/kitchen", "synthetic/stress-lowfreq",
             "synthetic/stress-repetitive", "synthetic/stress-far", "synthetic/stress-fast", "synthetic/stress-blur",
             "synthetic/stress-textureless"]


def run_open3d(seq) -> tuple[np.ndarray, float, int]:
    """Gap-1 chain of Open3D's compute_rgbd_odometry (hybrid term), T_k_{k+1} = inv(T_target_source)."""
    from ctcvo.data.open3d_import import o3d

    K = seq.intrinsics
    intr = o3d.camera.PinholeCameraIntrinsic(K.width, K.height, K.fx, K.fy, K.cx, K.cy)
    option = o3d.pipelines.odometry.OdometryOption()
    jac = o3d.pipelines.odometry.RGBDOdometryJacobianFromHybridTerm()

    def rgbd(k):
        return o3d.geometry.RGBDImage.create_from_color_and_depth(
            o3d.geometry.Image(np.ascontiguousarray(seq.rgb(k))), o3d.geometry.Image(seq.depth(k)),
            depth_scale=1.0, depth_trunc=4.5, convert_rgb_to_intensity=True)

    t0 = time.perf_counter()
    prev, rel, fails, init = rgbd(0), [], 0, np.eye(4)
    for k in range(1, len(seq)):
        cur = rgbd(k)
        ok, T_t_s, _ = o3d.pipelines.odometry.compute_rgbd_odometry(prev, cur, intr, init, jac, option)
        if not ok:
            fails += 1
            T_t_s = init
        rel.append(geo.inv_T(np.asarray(T_t_s)))
        init = np.asarray(T_t_s)
        prev = cur
    return chain_steps(rel), time.perf_counter() - t0, fails


def run_opencv(seq) -> tuple[np.ndarray, float, int]:
    """Gap-1 chain of OpenCV 5's cv2.Odometry (RGB_DEPTH), T_k_{k+1} = inv(T_dst_src)."""
    settings = cv2.OdometrySettings()
    settings.setCameraMatrix(seq.intrinsics.K.astype(np.float32))
    odo = cv2.Odometry(cv2.OdometryType_RGB_DEPTH, settings, cv2.OdometryAlgoType_COMMON)

    def frame(k):
        return seq.depth(k), cv2.cvtColor(seq.rgb(k), cv2.COLOR_RGB2GRAY)

    t0 = time.perf_counter()
    prev, rel, fails = frame(0), [], 0
    for k in range(1, len(seq)):
        cur = frame(k)
        ok, Rt = odo.compute(prev[0], prev[1], cur[0], cur[1])
        if not ok or not np.all(np.isfinite(Rt)):
            fails += 1
            Rt = np.eye(4)
        rel.append(geo.inv_T(np.asarray(Rt, dtype=np.float64)))
        prev = cur
    return chain_steps(rel), time.perf_counter() - t0, fails


def bench_scene(spec: str, frames: str | None, peers: list[str], synthetic_frames: int | None = None) -> list[dict]:
    if synthetic_frames and spec.startswith("synthetic/"):  # a shorter walk of the preset (rendered anew)
        from dataclasses import replace

        from ctcvo.data.synthetic import synthetic_sequence
        from ctcvo.data.synthetic.config import resolve_preset

        name = spec.split("/", 1)[1]
        seq = synthetic_sequence(name, config=replace(resolve_preset(name), frames=synthetic_frames))
        seq = seq.select(*[int(v) if v else None for v in frames.split(":")]) if frames else seq
    else:
        seq = open_scene(spec, frames=frames)[0]
    gt = Trajectory(seq.times(), seq.groundtruth())
    rows = []
    # Each method runs as it is meant to be used: the teacher as `teacher generate` runs it
    # (one OpenCV thread per process, data.sequence's default: it uses the cores through
    # its own processes and threads), the single-process peers with OpenCV and OpenMP on
    # every core, whatever OMP_NUM_THREADS says (it limits only the teacher here).
    cores = os.cpu_count() or 1
    cv2.setNumThreads(1)
    run = run_sequence(seq, TeacherConfig(), progress=False)
    cv2.setNumThreads(cores)
    pos = {int(f): p for p, f in enumerate(seq.ids())}
    gap1 = [e for e in run.edges if pos[e.j] - pos[e.i] == 1]
    paths = Counter(e.info.get("path", "none") for e in gap1)
    rows.append({"method": "this teacher (gaps 1-5)", "poses": run.poses, "seconds": run.seconds,
                 "fails": sum(1 for e in gap1 if not e.ok),
                 "cv_bridges": sum(1 for b in run.bridges if b["method"] == "constant velocity"),
                 "gap1_paths": dict(sorted(paths.items()))})
    with threadpool_limits(cores, user_api="openmp"):
        if "open3d" in peers:
            poses, sec, fails = run_open3d(seq)
            rows.append({"method": "Open3D hybrid (gap 1)", "poses": poses, "seconds": sec, "fails": fails})
        if "cv2" in peers:
            poses, sec, fails = run_opencv(seq)
            rows.append({"method": "cv2.Odometry RGB_DEPTH (gap 1)", "poses": poses, "seconds": sec, "fails": fails})
    out = []
    for r in rows:
        rep = trajectory_report(gt, Trajectory(seq.times(), r["poses"]))
        extra = {k: r[k] for k in ("cv_bridges", "gap1_paths") if k in r}
        out.append({"scene": spec, "frames": len(seq), "method": r["method"], "fps": len(seq) / r["seconds"],
                    "gap1_failures": r["fails"], **extra, **rep})
        print(f"{spec}: {out[-1]}", file=sys.stderr, flush=True)
    if "open3d" in peers:
        base = out[1]
        for r in out:
            r["fps_vs_open3d"] = r["fps"] / base["fps"]
            r["rpe_vs_open3d"] = r["rpe_trans_rmse_m"] / base["rpe_trans_rmse_m"]
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scenes", nargs="+", default=SYNTHETIC + [str(record.REDKITCHEN), str(record.TUM_XYZ)],
                    help="synthetic/NAME or a sequence folder (default: every synthetic preset, redkitchen, TUM fr1/xyz)")
    ap.add_argument("--frames", default=None, help="frame range START:STOP of every scene")
    ap.add_argument("--peers", nargs="*", default=["open3d"], choices=["open3d", "cv2"],
                    help="methods run beside the teacher (default: Open3D's hybrid odometry)")
    ap.add_argument("--synthetic-frames", type=int, default=None,
                    help="render each synthetic preset with this many frames instead of its own (a shorter walk)")
    record.add_arguments(ap, "teacher")
    args = ap.parse_args()
    rec = record.from_args(args, teacher=TeacherConfig())
    results = []
    for spec in args.scenes:
        if not spec.startswith("synthetic/") and not Path(spec).exists():
            print(f"skipping {spec}: not found", file=sys.stderr)
            continue
        results += bench_scene(spec, args.frames, args.peers, args.synthetic_frames)
        rec.finish({"rows": results})  # after every scene, so a long run that is cut short keeps what it measured
    print("| scene | frames | method | fps | fps / Open3D | gap-1 fails | CV bridges | RPE trans (mm) | RPE / Open3D "
          "| RPE rot (deg) | ATE (mm) | se(3) L2 | teacher gap-1 paths |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    for r in results:
        name = Path(r["scene"]).name if not r["scene"].startswith("synthetic/") else r["scene"]
        paths = " ".join(f"{k} {v}" for k, v in r.get("gap1_paths", {}).items())
        print(f"| {name} | {r['frames']} | {r['method']} | {r['fps']:.1f} | {r.get('fps_vs_open3d', float('nan')):.1f}x | "
              f"{r['gap1_failures']} | {r.get('cv_bridges', '')} | {1000 * r['rpe_trans_rmse_m']:.2f} | "
              f"{r.get('rpe_vs_open3d', float('nan')):.2f} | {r['rpe_rot_rmse_deg']:.3f} | {1000 * r['ate_rmse_m']:.1f} | "
              f"{r['se3_l2_mean']:.5f} | {paths} |")


if __name__ == "__main__":
    main()
