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
    .venv/bin/python -m bench.posegraph --sizes 1000 --isam2-max 1000
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import resource
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]


def _rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


class _Clock:
    """Wall-clock and process CPU time of a block (``with _Clock() as c: ...; c.wall, c.cpu``)."""

    def __enter__(self) -> "_Clock":
        self.w0, self.c0 = time.perf_counter(), time.process_time()
        return self

    def __exit__(self, *exc) -> None:
        self.wall, self.cpu = time.perf_counter() - self.w0, time.process_time() - self.c0


def run_one(n: int, gaps: int, solver: str, seed: int = 0, marginals: bool = False) -> dict:
    """Benchmark one size and solver in this process."""
    from data import geometry as geo
    from data.formats import Edge
    from posegraph import graph as pg
    from posegraph import synthetic as syn
    from posegraph.config import DEFAULT

    import gtsam  # noqa: F401  (import time is not build time)

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

    initial = pg.chain_poses(ids, edges)  # dead reckoning along the gap-1 edges
    with _Clock() as build:
        a = pg.edge_arrays(ids, edges)
        prob = pg._Problem(ids, a, initial, cfg)
        prob.factors(np.ones(len(edges)))
    with _Clock() as opt:  # the optimiser alone: one robust solve from the chained poses
        graph, values, result, iters = prob.solve(np.ones(len(edges), bool), np.ones(len(edges)), initial)
    err0, err1 = graph.error(values), graph.error(result)
    with _Clock() as check:
        pg.check_determinate(graph, result)
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


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--sizes", type=int, nargs="+", default=[1000, 10000, 50000])
    p.add_argument("--gaps", type=int, default=5, help="edges at gaps 1..GAPS")
    p.add_argument("--isam2-max", type=int, default=10000, help="largest size also run with ISAM2")
    p.add_argument("--marginals", action="store_true", help="full solve() also computes every marginal")
    p.add_argument("--one", nargs=2, metavar=("N", "SOLVER"), help=argparse.SUPPRESS)
    args = p.parse_args()
    if args.one:
        print(json.dumps(run_one(int(args.one[0]), args.gaps, args.one[1], marginals=args.marginals)))
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
    print(json.dumps(rows, indent=1))


if __name__ == "__main__":
    main()
