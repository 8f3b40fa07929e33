"""Pose-graph benchmark: batch LM versus ISAM2 on long chains.

Chains of N poses (helix) with edges at gaps 1..G (about G edges per pose), noisy
measurements, Huber kernel. Each size runs in its own subprocess so that the peak
resident memory (``ru_maxrss``, GTSAM's C++ heap included; tracemalloc would miss it)
is per size. Reported per size and solver:

* ``build_s``: Edge objects to arrays, ``gtsam.Pose3`` measurements and robust
  ``BetweenFactorPose3`` factors (the one per-edge Python pass);
* ``solve_s``: the optimiser alone from the chained (dead-reckoning) poses (LM
  ``optimize()``, or ISAM2 frame-by-frame updates);
* ``check_s``: the undamped elimination that detects an indeterminant system;
* ``full_s``: :func:`posegraph.graph.solve` end to end (validation, connectivity check,
  conversion, robust solve, residual-based outlier pass, warm re-solve when edges were
  rejected, determinacy check; marginals with ``--marginals``);
* every time as wall-clock and as process CPU time (``*_cpu_s``: robust to other jobs
  on the machine);
* ``rss_mb``: growth of peak RSS over the process after edge generation.

Target: 10k poses / 50k edges, LM in under 5 s.

    .venv/bin/python -m bench.posegraph                 # 1k, 10k, 50k; ISAM2 up to 10k
    .venv/bin/python -m bench.posegraph --sizes 1000 --isam2-max 1000 --name posegraph-1k

Fusion (``--case``, issue 12): ``posegraph optimize`` on teacher + learner folders of a test
range, one table per case with every row of the report (teacher chained, teacher graph,
learner chained, fused, zero motion, constant velocity) and the check "fused <= teacher
graph" on ATE and 1 s RPE. A case is ``NAME:TEACHER:LEARNER[:TEACHER_CALIBRATION[:A-B]]``;
``A-B`` drops every teacher edge that touches a frame strictly between positions A and B
(a stretch where the teacher failed; its trajectory bridges it at constant velocity).
Outputs go to ``--out`` (default ``runs/bench/<name>``); the record is
``bench/results/<name>.json`` (bench/record.py):

    .venv/bin/python -m bench.posegraph --name posegraph-fusion-kitchen \
        --case kitchen:runs/synthetic-kitchen/teacher:runs/synthetic-kitchen/learner:cal.json \
        --case kitchen-hole:runs/synthetic-kitchen/teacher:runs/synthetic-kitchen/learner:cal.json:120-160
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import logging
import resource
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from bench import record

REPO = Path(__file__).resolve().parents[1]


def _rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


class _Clock:
    """Wall-clock and process CPU time of a block (``with _Clock() as c: ...; c.wall, c.cpu``)."""

    def __enter__(self) -> _Clock:
        self.w0, self.c0 = time.perf_counter(), time.process_time()
        return self

    def __exit__(self, *exc) -> None:
        self.wall, self.cpu = time.perf_counter() - self.w0, time.process_time() - self.c0


def run_one(n: int, gaps: int, solver: str, seed: int = 0, marginals: bool = False) -> dict:
    """Benchmark one size and solver in this process."""
    import gtsam  # noqa: F401  (import time is not build time)

    from ctcvo.data import geometry as geo
    from ctcvo.data.formats import Edge
    from ctcvo.posegraph import edges as pe
    from ctcvo.posegraph import graph as pg
    from ctcvo.posegraph import synthetic as syn
    from ctcvo.posegraph.config import DEFAULT
    from ctcvo.posegraph.solvers import check_determinate

    rng = np.random.default_rng(seed)
    gt = syn.helix(n, turns=n / 200.0)
    sig = np.array([0.01] * 3 + [0.005] * 3)
    cov = np.diag(sig**2)
    edges = []
    for g in range(1, gaps + 1):
        noise = rng.normal(size=(n - g, 6)) * sig
        for k in range(n - g):
            T = geo.relative_pose(gt[k], gt[k + g]) @ geo.se3_exp(noise[k])
            edges.append(Edge(k, k + g, T, cov, {"source": "edges"}))
    ids = np.arange(n)
    cfg = dataclasses.replace(DEFAULT, solver=solver)
    rss0 = _rss_mb()

    initial = pe.chain_poses(ids, edges)  # dead reckoning along the gap-1 edges
    with _Clock() as build:
        a = pe.edge_arrays(ids, edges)
        prob = pg._Problem(ids, a, initial, cfg)
        prob.factors(np.ones(len(edges)))
    with _Clock() as opt:  # the optimiser alone: one robust solve from the chained poses
        graph, values, result, iters = prob.solve(np.ones(len(edges), bool), np.ones(len(edges)), initial)
    err0, err1 = graph.error(values), graph.error(result)
    with _Clock() as check:
        check_determinate(graph, result)
    del graph, values, result, prob
    with _Clock() as full:
        res = pg.solve(ids, edges, initial, dataclasses.replace(cfg, marginals=marginals))
    gt0 = np.array([geo.relative_pose(gt[0], T) for T in gt])
    drift = float(np.linalg.norm(res.poses[-1][:3, 3] - gt0[-1][:3, 3]))
    return {"poses": n, "edges": len(edges), "solver": solver, "marginals": marginals,
            "build_s": round(build.wall, 3), "build_cpu_s": round(build.cpu, 3),
            "solve_s": round(opt.wall, 3), "solve_cpu_s": round(opt.cpu, 3), "iterations": iters,
            "check_s": round(check.wall, 3), "check_cpu_s": round(check.cpu, 3),
            "full_s": round(full.wall, 3), "full_cpu_s": round(full.cpu, 3), "full_iterations": res.iterations,
            "rss_mb": round(_rss_mb() - rss0, 1), "error": [round(err0, 1), round(err1, 1)],
            "outliers": len(res.outliers), "end_error_m": round(drift, 4)}


def drop_stretch(teacher: Path, out: Path, a: int, b: int) -> Path:
    """Copy of the teacher folder without the edges that touch frame positions a < p < b;
    its trajectory.tum is re-chained from the remaining gap-1 edges, repeating the last
    step over the hole (constant velocity, as the teacher bridges failed edges)."""
    import shutil

    from ctcvo.data.formats import Trajectory, read_g2o, read_tum, write_g2o, write_tum
    from ctcvo.posegraph.sources import load_dir, resolve_frames

    src = load_dir(teacher, "teacher")
    frames = resolve_frames([src])
    pos = {int(k): p for p, k in enumerate(frames.ids)}
    edges, _ = read_g2o(teacher / "edges.g2o")
    kept = [e for e in edges if not any(a < pos[k] < b for k in (e.i, e.j))]
    out.mkdir(parents=True, exist_ok=True)
    write_g2o(out / "edges.g2o", kept)
    for f in ("edges.csv", "groundtruth.tum"):
        if (teacher / f).is_file():
            shutil.copy(teacher / f, out / f)
    step = {pos[e.i]: e.T_i_j for e in kept if pos[e.j] == pos[e.i] + 1}
    traj = read_tum(teacher / "trajectory.tum")
    poses, last = [traj.poses[0]], np.eye(4)
    for p in range(len(frames.ids) - 1):
        last = step.get(p, last)
        poses.append(poses[-1] @ last)
    write_tum(out / "trajectory.tum", Trajectory(frames.times, np.array(poses)))
    return out


def run_case(spec: str, out: Path, learner_edges: str = "bridge") -> dict:
    """One fusion case (see module doc): the report's rows and the fused-vs-teacher-graph check."""
    from ctcvo.posegraph.optimize import optimize

    parts = spec.split(":")
    if len(parts) < 3:
        raise SystemExit(f"--case needs NAME:TEACHER:LEARNER[:CALIBRATION[:A-B]], got {spec!r}")
    name, teacher, learner = parts[0], Path(parts[1]), Path(parts[2])
    cal = Path(parts[3]) if len(parts) > 3 and parts[3] else None
    if len(parts) > 4 and parts[4]:
        a, b = (int(x) for x in parts[4].split("-"))
        teacher = drop_stretch(teacher, out / name / "teacher_hole", a, b)
    from ctcvo.posegraph.config import DEFAULT

    t0 = time.perf_counter()
    cfg = dataclasses.replace(DEFAULT, learner_edges=learner_edges, plots=False)
    o = optimize(teacher=teacher, learner=learner, out=out / name / f"posegraph-{learner_edges}", cfg=cfg,
                 teacher_calibration=cal)[0]
    rep = json.loads((o / "report.json").read_text())
    rows = rep["rows"]
    tg, fu = rows.get("teacher_graph"), rows["fused"]
    check = None
    if tg and tg["ate_rmse_m"] is not None:
        check = {k: fu[k] <= tg[k] * (1 + 1e-9) for k in ("ate_rmse_m", "rpe_1s_trans_m", "rpe_1s_rot_deg")}
    return {"case": name, "spec": spec, "learner_edges": learner_edges, "report": str(o / "report.json"),
            "time_s": round(time.perf_counter() - t0, 1),
            "rows": rows, "skill_gate": rep.get("skill_gate"), "bridges": rep.get("bridges"),
            "covariance_scales": rep.get("covariance_scales"), "fused_le_teacher_graph": check}


def _mm(x) -> str:
    return "-" if x is None else f"{1000 * x:.1f}"


def print_case(r: dict) -> None:
    print(f"\n### {r['case']}, learner_edges = {r['learner_edges']} ({r['spec']})\n")
    print("| row | ATE mm | RPE1 mm / deg | RPE 1s mm / deg | se(3) L2 | NEES/6 (edges vs GT) |")
    print("|---|---|---|---|---|---|")
    for b in r["rows"].values():
        nees = (b.get("calibration") or {}).get("nees_over_dof")
        rot1 = "-" if b["rpe_g1_rot_deg"] is None else f"{b['rpe_g1_rot_deg']:.3f}"
        rots = "-" if b["rpe_1s_rot_deg"] is None else f"{b['rpe_1s_rot_deg']:.2f}"
        se3 = "-" if b["se3_l2_mean"] is None else f"{b['se3_l2_mean']:.4f}"
        print(f"| {b['label']} | {_mm(b['ate_rmse_m'])} | {_mm(b['rpe_g1_trans_m'])} / {rot1} | "
              f"{_mm(b['rpe_1s_trans_m'])} / {rots} | {se3} | {'-' if nees is None else f'{nees:.2f}'} |")
    gate = {n: (g["ratio"], g["gated_gaps"]) for n, g in (r["skill_gate"] or {}).items()}
    print(f"\nskill gate {gate}, bridges {r['bridges']}, graph scales {r['covariance_scales']}, "
          f"fused <= teacher graph: {r['fused_le_teacher_graph']}", flush=True)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--sizes", type=int, nargs="+", default=[1000, 10000, 50000])
    p.add_argument("--gaps", type=int, default=5, help="edges at gaps 1..GAPS")
    p.add_argument("--isam2-max", type=int, default=10000, help="largest size also run with ISAM2")
    p.add_argument("--marginals", action="store_true", help="full solve() also computes every marginal")
    p.add_argument("--one", nargs=2, metavar=("N", "SOLVER"), help=argparse.SUPPRESS)
    p.add_argument("--case", action="append", default=[],
                   help="fusion case NAME:TEACHER:LEARNER[:TEACHER_CALIBRATION[:A-B]] (repeatable; no timing run)")
    p.add_argument("--out", type=Path, help="fusion outputs (default runs/bench/NAME)")
    p.add_argument("--learner-edges", nargs="+", default=["bridge"], choices=["bridge", "all"],
                   help="posegraph learner_edges setting(s) each case runs with")
    record.add_arguments(p, "posegraph")
    args = p.parse_args()
    if args.one:
        print(json.dumps(run_one(int(args.one[0]), args.gaps, args.one[1], marginals=args.marginals)))
        return
    rec = record.from_args(args)
    if args.case:
        args.out = args.out or record.RUNS / args.name
        logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
        results = []
        for spec in args.case:
            for mode in args.learner_edges:
                results.append(run_case(spec, args.out, mode))
                print_case(results[-1])
        rec.finish({"cases": results})
        return
    rows = []
    for n in args.sizes:
        for solver in ("lm", "isam2"):
            if solver == "isam2" and n > args.isam2_max:
                continue
            cmd = [sys.executable, "-m", "bench.posegraph", "--gaps", str(args.gaps), "--one", str(n), solver]
            out = subprocess.run(cmd + (["--marginals"] if args.marginals else []), capture_output=True, text=True,
                                 cwd=REPO)
            if out.returncode != 0:
                print(out.stderr, file=sys.stderr)
                raise SystemExit(out.returncode)
            rows.append(json.loads(out.stdout.strip().splitlines()[-1]))
            r = rows[-1]
            print(f"{r['poses']:>6} poses {r['edges']:>7} edges {r['solver']:>5}: "
                  f"build {r['build_s']:.2f} s (cpu {r['build_cpu_s']:.2f}), "
                  f"solve {r['solve_s']:.2f} s (cpu {r['solve_cpu_s']:.2f}, {r['iterations']} it), "
                  f"full {r['full_s']:.2f} s (cpu {r['full_cpu_s']:.2f}, {r['full_iterations']} it, "
                  f"{r['outliers']} outliers), +{r['rss_mb']:.0f} MB peak RSS, end error {r['end_error_m']:.3f} m",
                  flush=True)
    rec.finish({"sizes": rows})


if __name__ == "__main__":
    main()
