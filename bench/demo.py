"""The end-to-end demo as a benchmark: ``ctcvo demo`` (what ``make demo`` runs) in a folder of
its own, timed, with the test room's pose-graph rows recorded.

    .venv/bin/python -m bench.demo              # runs/bench/demo/runs/synthetic-*/..., from scratch
    .venv/bin/python -m bench.demo --cache runs/bench/demo/cache   # as on a fresh machine: renders too
    .venv/bin/python -m bench.demo --keep       # keep that folder's finished stages (a rerun: seconds)
    .venv/bin/python -m bench.demo --orbslam3-vocabulary VOC.txt   # ORB-SLAM3 and Open3D beside it

The demo renders the synthetic rooms into the render cache (``--cache``, default
``$VO_CACHE_DIR`` or ``~/.cache/ctcvo``) when they are missing there; the record says which
were there. The record is ``bench/results/<name>.json``
(bench/record.py): wall and CPU time of the whole command and every row of the test room's
``posegraph/report.json``; with ``--orbslam3-vocabulary`` (a vocabulary of training frames,
``ctcvo teacher vocabulary``) also ORB-SLAM3's (median of ``--orbslam3-runs`` SLAM runs) and
Open3D's gap-1 odometry on the same frames, run after the demo.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import resource
import shutil
import subprocess
import sys
import time
from pathlib import Path

from bench import record
from bench.orbslam3_peer import metrics, one_second, orbslam3_row
from bench.teacher import run_open3d
from ctcvo.data.formats import Trajectory
from ctcvo.data.scenes import open_scene
from ctcvo.data.undistort import with_camera

ROOMS = ("office", "lab", "kitchen")
ROW_KEYS = ("ate_rmse_m", "rpe_g1_trans_m", "rpe_g1_rot_deg", "rpe_1s_trans_m", "rpe_1s_rot_deg", "se3_l2_mean")


def cached_rooms(cache: Path) -> list[str]:
    """The demo's rooms already rendered in the render cache ``cache`` (``<room>-<8 hex digits>``)."""
    names = [p.name for p in (cache / "synthetic").glob("*")] if (cache / "synthetic").is_dir() else []
    return [r for r in ROOMS if any(re.fullmatch(rf"{r}-[0-9a-f]{{8}}", n) for n in names)]


def peer_rows(scene: str, vocabulary: Path, runs: int, camera: Path | None) -> dict[str, dict]:
    """ORB-SLAM3's (median of ``runs``) and Open3D's rows on the demo's test room ``scene``,
    on the frames the demo's teacher saw (undistorted with the demo's ``camera`` file)."""
    seq = open_scene(scene)[0]
    seq = seq if camera is None else with_camera(seq, camera)
    gt, second = Trajectory(seq.times(), seq.groundtruth()), one_second(seq.times())
    o3d = metrics(gt, Trajectory(seq.times(), run_open3d(seq)[0]), second)
    orb = orbslam3_row(seq, vocabulary, runs)
    keys = dict(zip(ROW_KEYS, ("ate_rmse_m", "rpe_trans_rmse_m", "rpe_rot_rmse_deg", "rpe_1s_trans_m", "rpe_1s_rot_deg",
                               "se3_l2_mean")))
    return {"orbslam3": {"label": f"ORB-SLAM3 (median of {runs} runs)", **{k: orb[v] for k, v in keys.items()}},
            "open3d": {"label": "Open3D hybrid (gap 1)", **{k: o3d[v] for k, v in keys.items()}}}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, help="working folder of the demo (default runs/bench/NAME)")
    ap.add_argument("--keep", action="store_true", help="keep the stages already finished there")
    ap.add_argument("--cache", type=Path, default=Path(os.environ.get("VO_CACHE_DIR", Path.home() / ".cache" / "ctcvo")),
                    help="render cache of the run (default $VO_CACHE_DIR or ~/.cache/ctcvo)")
    ap.add_argument("--orbslam3-vocabulary", type=Path, help="adds ORB-SLAM3's and Open3D's rows on the test room")
    ap.add_argument("--orbslam3-runs", type=int, default=3, help="ORB-SLAM3 SLAM runs (median reported)")
    record.add_arguments(ap, "demo")
    args = ap.parse_args()
    work = args.out or record.RUNS / args.name
    if not args.keep:
        shutil.rmtree(work, ignore_errors=True)
    work.mkdir(parents=True, exist_ok=True)
    rec = record.from_args(args, out=work, rooms_in_render_cache=cached_rooms(args.cache))
    env = {**os.environ, "PYTHONPATH": str(record.REPO), "VO_CACHE_DIR": str(args.cache.resolve())}
    t0, c0 = time.perf_counter(), resource.getrusage(resource.RUSAGE_CHILDREN)
    with open(work / "demo.log", "w") as log:
        done = subprocess.run([sys.executable, "-m", "ctcvo", "demo"], cwd=work, env=env, stdout=log, stderr=log)
    wall, c1 = time.perf_counter() - t0, resource.getrusage(resource.RUSAGE_CHILDREN)
    if done.returncode != 0:
        print(f"ctcvo demo exited {done.returncode}; see {work / 'demo.log'}", file=sys.stderr)
        return done.returncode
    rep = json.loads((work / "runs" / "synthetic-kitchen" / "posegraph" / "report.json").read_text())
    rows = {k: {"label": r["label"], **{c: r.get(c) for c in ROW_KEYS}} for k, r in rep["rows"].items()}
    if args.orbslam3_vocabulary is not None:
        os.environ["VO_CACHE_DIR"] = env["VO_CACHE_DIR"]  # the rooms the demo rendered
        cameras = sorted((work / "runs").glob("*/camera/camera.json"))
        rows.update(peer_rows(rep["scene"], args.orbslam3_vocabulary, args.orbslam3_runs, (cameras or [None])[0]))
    print("| row | ATE mm | gap-1 RPE mm / deg | se(3) L2 |\n|---|---|---|---|")
    for r in rows.values():
        print(f"| {r['label']} | {1000 * r['ate_rmse_m']:.1f} | {1000 * r['rpe_g1_trans_m']:.2f} / "
              f"{r['rpe_g1_rot_deg']:.3f} | {r['se3_l2_mean']:.4f} |")
    rec.finish({"wall_s": round(wall, 1), "cpu_s": round(c1.ru_utime + c1.ru_stime - c0.ru_utime - c0.ru_stime, 1),
                "test_scene": rep["scene"], "frames": rep["frames"], "outliers": len(rep["outliers"]), "rows": rows})
    return 0


if __name__ == "__main__":
    sys.exit(main())
