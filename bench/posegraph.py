"""Pose-graph benchmark: batch LM versus ISAM2 on long chains.

Chains of N poses (helix) with edges at gaps 1..G (about G edges per pose), noisy
measurements, Huber kernel. Each size runs in its own subprocess so that the peak
resident memory (``ru_maxrss``, GTSAM's C++ heap included; tracemalloc would miss it)
is per size. Reported per size and solver:

* ``build_s``: creating the GTSAM factor graph and values from Edge objects;
* ``solve_s``: the optimiser alone (LM ``optimize()``, or ISAM2 frame-by-frame updates);
* ``full_s``: :func:`posegraph.graph.solve` end to end (validation, connectivity check,
  robust solve, residual-based outlier pass, re-solve if needed);
* ``rss_mb``: growth of peak RSS over the process after edge generation.

Target: 10k poses / 50k edges, LM in under 5 s.

    .venv/bin/python bench/posegraph.py                 # 1k, 10k, 50k; ISAM2 up to 10k
    .venv/bin/python bench/posegraph.py --sizes 1000 --isam2-max 1000
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

# This script is named like the package: keep bench/ off the import path.
sys.path[:] = [p for p in sys.path if Path(p or ".").resolve() != Path(__file__).resolve().parent]


def _rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def run_one(n: int, gaps: int, solver: str, seed: int = 0) -> dict:
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
            edges.append(Edge(k, k + g, T, cov))
    ids = np.arange(n)
    cfg = dataclasses.replace(DEFAULT, solver=solver)
    rss0 = _rss_mb()

    initial = pg.chain_poses(ids, edges)
    t0 = time.perf_counter()
    covs = [e.cov for e in edges]
    graph, values = pg.build_graph(ids, edges, covs, initial, cfg)
    build_s = time.perf_counter() - t0
    t0 = time.perf_counter()
    if solver == "lm":
        result, iters = pg._run_lm(graph, values, cfg)
    else:
        result, iters = pg._run_isam2(ids, edges, covs, initial, cfg)
    solve_s = time.perf_counter() - t0
    err0, err1 = graph.error(values), graph.error(result)
    del graph, values, result
    t0 = time.perf_counter()
    res = pg.solve(ids, edges, initial, cfg)
    full_s = time.perf_counter() - t0
    gt0 = np.array([geo.relative_pose(gt[0], T) for T in gt])
    drift = float(np.linalg.norm(res.poses[-1][:3, 3] - gt0[-1][:3, 3]))
    return {"poses": n, "edges": len(edges), "solver": solver, "build_s": round(build_s, 3),
            "solve_s": round(solve_s, 3), "iterations": iters, "full_s": round(full_s, 3),
            "rss_mb": round(_rss_mb() - rss0, 1), "error": [round(err0, 1), round(err1, 1)],
            "outliers": len(res.outliers), "end_error_m": round(drift, 4)}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--sizes", type=int, nargs="+", default=[1000, 10000, 50000])
    p.add_argument("--gaps", type=int, default=5, help="edges at gaps 1..GAPS")
    p.add_argument("--isam2-max", type=int, default=10000, help="largest size also run with ISAM2")
    p.add_argument("--one", nargs=2, metavar=("N", "SOLVER"), help=argparse.SUPPRESS)
    args = p.parse_args()
    if args.one:
        print(json.dumps(run_one(int(args.one[0]), args.gaps, args.one[1])))
        return
    rows = []
    for n in args.sizes:
        for solver in ("lm", "isam2"):
            if solver == "isam2" and n > args.isam2_max:
                continue
            out = subprocess.run([sys.executable, __file__, "--gaps", str(args.gaps), "--one", str(n), solver],
                                 capture_output=True, text=True)
            if out.returncode != 0:
                print(out.stderr, file=sys.stderr)
                raise SystemExit(out.returncode)
            rows.append(json.loads(out.stdout.strip().splitlines()[-1]))
            r = rows[-1]
            print(f"{r['poses']:>6} poses {r['edges']:>7} edges {r['solver']:>5}: build {r['build_s']:.2f} s, "
                  f"solve {r['solve_s']:.2f} s ({r['iterations']} it), full {r['full_s']:.2f} s, "
                  f"+{r['rss_mb']:.0f} MB peak RSS, end error {r['end_error_m']:.3f} m", flush=True)
    print(json.dumps(rows, indent=1))


if __name__ == "__main__":
    main()
