"""Teacher benchmark: this teacher vs Open3D's hybrid RGB-D odometry vs OpenCV's
``cv2.Odometry`` (RGB_DEPTH) vs ORB-SLAM3 RGB-D, side by side on the same frames in one run.

For each scene: frames per second end to end (decode included; the teacher also
estimates its gap 2..K edges, the odometry peers only gap 1; the teacher timed over
``--teacher-runs`` runs like ORB-SLAM3, the median, the first run being the cold one), ATE (SE(3)-aligned), RPE at
1 frame and at 1 s (translation, rotation) and the paper's se(3) L2, all through evo, of the
teacher's chained gap-1 trajectory, of the pose graph of all its edges (``teacher pose
graph``: what ``posegraph optimize`` makes of the teacher's edges.g2o) and of each peer; for
the teacher also its constant-velocity bridges, failed gap-1 edges and the paths that made
its gap-1 edges (teacher/odometry.py's fallback chain), and every row's ratios to Open3D.
With ``--orbslam3-vocabulary`` ORB-SLAM3 runs ``--orbslam3-runs`` times per scene: median and
min-max of each figure, and the frames it lost (bench/orbslam3_peer.py). Its runs alternate
with the teacher's (teacher, ORB-SLAM3, teacher, ...), so that both meet the machine in the
same state.

    .venv/bin/python -m bench.teacher          # every synthetic preset, stress scenes included,
                                               # redkitchen and TUM fr1/xyz images; teacher + Open3D
    .venv/bin/python -m bench.teacher --scenes ../shared/data/7scenes/redkitchen/seq-sample --frames 450:600 \
        --peers open3d cv2 --orbslam3-vocabulary VOC.txt --name teacher-redkitchen-test
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
from collections.abc import Callable
from pathlib import Path

if __name__ == "__main__":  # as `teacher generate` does: its worker imports while this process does
    from ctcvo.teacher import processes

    processes.start()

import cv2  # noqa: E402
import numpy as np  # noqa: E402
from threadpoolctl import threadpool_limits  # noqa: E402

from bench import orbslam3_peer, record, tables  # noqa: E402
from bench.orbslam3_peer import metrics, one_second  # noqa: E402
from ctcvo.data import geometry as geo  # noqa: E402
from ctcvo.data.chain import chain_steps  # noqa: E402
from ctcvo.data.formats import Edge, Trajectory  # noqa: E402
from ctcvo.data.scenes import open_scene  # noqa: E402
from ctcvo.data.undistort import read_camera, with_camera  # noqa: E402
from ctcvo.posegraph.graph import solve  # noqa: E402
from ctcvo.teacher.config import TeacherConfig  # noqa: E402
from ctcvo.teacher.generate import cov_scales, run_sequence  # noqa: E402

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


def _teacher_run(seq) -> tuple:
    """One teacher run as `teacher generate` runs it, and the pose graph of its good edges:
    (run, graph poses, solve seconds)."""
    # one OpenCV thread per process, data.sequence's default: the teacher uses the cores
    # through its own processes and threads
    cfg = TeacherConfig()
    cv2.setNumThreads(1)
    run = run_sequence(seq, cfg, progress=False)
    cv2.setNumThreads(os.cpu_count() or 1)
    t0 = time.perf_counter()
    scale = cov_scales(seq, run.edges, run.kinds, cfg.covariance)
    edges = [Edge(e.i, e.j, e.T_i_j, e.cov * scale[e.i, e.j]) for e in run.edges if e.ok]  # as edges.g2o holds them
    graph = solve(seq.ids(), edges, run.poses, observations=run.observations).poses
    return run, graph, time.perf_counter() - t0


def _timing(seconds: list[float], same: bool) -> dict:
    """The median of ``seconds`` (one per run) with every run's, and whether the runs' poses agreed."""
    return {"seconds": float(np.median(seconds)), "seconds_per_run": seconds, "runs": len(seconds),
            "same_poses_every_run": same}


def teacher_rows(seq, runs: int = 3, between: Callable[[], object] | None = None) -> list[dict]:
    """The teacher's chained gap-1 trajectory, and the pose graph of all its good edges
    (:func:`ctcvo.posegraph.graph.solve`, the default config, as ``posegraph optimize`` solves
    its edges.g2o, calibrated covariances included), its time added to the teacher's.
    Timed over ``runs`` runs like the ORB-SLAM3 peer: the median time (the first run is the
    cold one); the figures are the first run's, and ``same_poses_every_run`` says whether
    the later runs gave the same poses. ``between`` runs after each teacher run (a peer's
    run, so that both are timed in the same spells of a shared machine)."""
    done = []
    for _ in range(runs):
        done.append(_teacher_run(seq))
        if between is not None:
            between()
    run, graph, solve_s = done[0]
    same = all(np.array_equal(r.poses, run.poses) and np.array_equal(g, graph) for r, g, _ in done[1:])
    pos = {int(f): p for p, f in enumerate(seq.ids())}
    gap1 = [e for e in run.edges if pos[e.j] - pos[e.i] == 1]
    paths = Counter(e.diag.path for e in gap1)
    fails = sum(1 for e in gap1 if not e.ok)
    return [{"method": "this teacher (gaps 1-5)", "poses": run.poses, "fails": fails,
             **_timing([r.seconds for r, _, _ in done], same),
             "cv_bridges": sum(1 for b in run.bridges if b["method"] == "constant velocity"),
             "gap1_paths": dict(sorted(paths.items()))},
            {"method": "teacher pose graph (gaps 1-5)", "poses": graph, "fails": fails, "solve_s": solve_s,
             **_timing([r.seconds + s for r, _, s in done], same)}]


def _open_sequence(spec: str, frames: str | None, synthetic_frames: int | None, camera: Path | None = None):
    if camera is not None:  # every row gets the same undistorted frames
        return with_camera(_open_sequence(spec, frames, synthetic_frames), camera)
    if synthetic_frames and spec.startswith("synthetic/"):  # a shorter walk of the preset (rendered anew)
        from dataclasses import replace

        from ctcvo.data.synthetic import synthetic_sequence
        from ctcvo.data.synthetic.config import resolve_preset

        name = spec.split("/", 1)[1]
        seq = synthetic_sequence(name, config=replace(resolve_preset(name), frames=synthetic_frames))
        return seq.select(*[int(v) if v else None for v in frames.split(":")]) if frames else seq
    return open_scene(spec, frames=frames)[0]


def bench_scene(spec: str, frames: str | None, peers: list[str], synthetic_frames: int | None = None,
                orbslam3_vocabulary: Path | None = None, orbslam3_runs: int = 3, camera: Path | None = None,
                teacher_runs: int = 3) -> list[dict]:
    seq = _open_sequence(spec, frames, synthetic_frames, camera)
    gt = Trajectory(seq.times(), seq.groundtruth())
    # ORB-SLAM3's runs alternate with the teacher's: a shared machine's speed drifts by 10-20 %
    # over minutes (fr1/xyz, ORB-SLAM3 alone: 34-39 fps), and the fps ratio is the target
    orb_runs: list[dict] = []
    orb_tries = 0

    def orb_run() -> None:
        nonlocal orb_tries
        if orbslam3_vocabulary is not None and orb_tries < orbslam3_runs:
            orb_tries += 1
            orb_runs.extend(orbslam3_peer.each_run(seq, orbslam3_vocabulary, 1, orbslam3_peer.run_figures))

    rows = teacher_rows(seq, teacher_runs, between=orb_run)
    # The single-process peers run with OpenCV and OpenMP on every core, whatever
    # OMP_NUM_THREADS says (it limits only the teacher here).
    with threadpool_limits(os.cpu_count() or 1, user_api="openmp"):
        if "open3d" in peers:
            poses, sec, fails = run_open3d(seq)
            rows.append({"method": "Open3D hybrid (gap 1)", "poses": poses, "seconds": sec, "fails": fails})
        if "cv2" in peers:
            poses, sec, fails = run_opencv(seq)
            rows.append({"method": "cv2.Odometry RGB_DEPTH (gap 1)", "poses": poses, "seconds": sec, "fails": fails})
    second = one_second(seq.times())
    out = []
    for r in rows:
        rep = metrics(gt, Trajectory(seq.times(), r["poses"]), second)
        extra = {k: r[k] for k in ("cv_bridges", "gap1_paths", "solve_s", "runs", "seconds_per_run",
                                   "same_poses_every_run") if k in r}
        out.append({"scene": spec, "frames": len(seq), "method": r["method"], "fps": len(seq) / r["seconds"],
                    "gap1_failures": r["fails"], **extra, **rep})
        print(f"{spec}: {out[-1]}", file=sys.stderr, flush=True)
    if orbslam3_vocabulary is not None:
        while orb_tries < orbslam3_runs:  # more ORB-SLAM3 runs than the teacher's
            orb_run()
        out.append({"scene": spec, "frames": len(seq), "method": orbslam3_peer.METHOD, **orbslam3_peer.aggregate(orb_runs)})
    base = next((r for r in out if r["method"].startswith("Open3D")), None)
    if base is not None:
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
    orbslam3_peer.add_arguments(ap, "row")
    ap.add_argument("--teacher-runs", type=int, default=3,
                    help="teacher runs per scene, timed like ORB-SLAM3's: the median time (default 3)")
    ap.add_argument("--camera", type=Path, default=None,
                    help="camera file (ctcvo teacher calibrate, from training or validation frames): every row runs "
                         "on the frames undistorted with it")
    record.add_arguments(ap, "teacher")
    args = ap.parse_args()
    orbslam3_peer.check_arguments(ap, args)
    if args.teacher_runs < 1:
        ap.error(f"--teacher-runs must be >= 1, got {args.teacher_runs}")
    camera = None if args.camera is None else {"file": str(args.camera), "distortion": read_camera(args.camera)[1]}
    rec = record.from_args(args, teacher=TeacherConfig(), camera=camera)
    results = []
    for spec in args.scenes:
        if not spec.startswith("synthetic/") and not Path(spec).exists():
            print(f"skipping {spec}: not found", file=sys.stderr)
            continue
        results += bench_scene(spec, args.frames, args.peers, args.synthetic_frames, args.orbslam3_vocabulary,
                               args.orbslam3_runs, args.camera, args.teacher_runs)
        rec.finish({"rows": results})  # after every scene, so a long run that is cut short keeps what it measured
    print("\n".join(tables.markdown(tables.TEACHER_HEAD, [tables.teacher_cells(r, "") for r in results])))


if __name__ == "__main__":
    main()
