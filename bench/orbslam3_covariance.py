"""Calibrating the ORB-SLAM3 backend's per-gap covariance model on validation data.

ORB-SLAM3 gives no covariance, so the backend gives each edge (i, i+g) a diagonal one in the
project tangent order (v, w) from a per-gap model (ctcvo/teacher/orbslam3.py,
``edge_covariance``): ``sigma(g) = sigma_gap1 * g ** exponent``, translation and rotation each.
This script fits that model against the ground truth, the way ``posegraph calibrate --method
groundtruth`` fits its per-gap scales (a median, not a mean: the errors are heavy-tailed):

* every good edge of ``--runs`` SLAM runs of each validation range (redkitchen 350:450, TUM
  fr3/teddy 0:200), its error ``d = log(inv(T_label) @ T_gt)`` (the NEES convention of
  posegraph.report.nees);
* per gap, ``sigma_t(g)^2 = median |d_v|^2 / median chi2_3``, likewise ``sigma_r(g)``; the
  exponent is the least-squares slope of ``log sigma`` on ``log g`` over both (one common
  exponent); then ``sigma_gap1`` of each is the pooled median over every gap with the gaps
  divided out;
* the tracked-map-points factor ``clip(sqrt(POINTS_REF / points), *POINTS_SCALE)`` is tested
  by refitting the model with it and comparing the Gaussian negative log-likelihood per edge
  (lower is better), on the ranges fitted and on each range left out of the fit (fitted on
  the other), and the NEES/6 of the edges with the fewest and the most points.

Reported per gap before (the placeholder model) and after (the fit): NEES/6 (the mean, as
every report.json gives it), median NEES / median chi2_6 (1 when the median is consistent)
and the 1-sigma coverage. Record ``bench/results/orbslam3-covariance.json``.

    .venv/bin/python -m bench.orbslam3_covariance --vocabulary VOC.txt [--runs 2]
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
from scipy.stats import chi2

from bench import record
from ctcvo.data.metrics import groundtruth_residuals
from ctcvo.data.scenes import open_scene
from ctcvo.data.uncertainty import CHI2_6_MEDIAN, nees_stats
from ctcvo.teacher import orbslam3 as O

VALIDATION = [f"{record.REDKITCHEN}:350:450", f"{record.TUM_TEDDY}:0:200"]
#: the model before this calibration (issue 27's placeholder, seeded from its RPE table)
PLACEHOLDER = {"sigma_trans_gap1_m": 0.005, "sigma_rot_gap1_deg": 0.3, "gap_exponent": 0.5, "points_ref": 300,
               "points_scale": [0.5, 3.0]}
#: the points factor's reference and clip range, tested as the placeholder had them
POINTS_REF, POINTS_SCALE = 300, (0.5, 3.0)
GAPS = 5


def edge_errors(seq, result) -> dict[str, np.ndarray]:
    """Every good edge's gap, tracked points and error ``log(inv(T_label) @ T_gt)`` (E, 6), (v, w)."""
    good = [e for e in O.edges_from(result, GAPS, O.DEFAULT_LABELS) if e.good]
    return {"gap": np.array([e.gap for e in good]), "points": np.array([e.points for e in good]),
            "d": groundtruth_residuals(good, seq.groundtruth(), seq.ids())}


def points_factor(points: np.ndarray, use: bool) -> np.ndarray:
    return np.clip(np.sqrt(POINTS_REF / np.maximum(points, 1)), *POINTS_SCALE) if use else np.ones(len(points))


def fit(e: dict[str, np.ndarray], use_points: bool) -> dict:
    """The model fitted to the pooled edge errors ``e`` (module docstring)."""
    m3 = float(chi2.median(3))
    f2 = points_factor(e["points"], use_points) ** 2
    t2, r2 = (e["d"][:, :3] ** 2).sum(1) / f2, (e["d"][:, 3:] ** 2).sum(1) / f2
    gaps = np.unique(e["gap"])
    per = {int(g): (np.sqrt(np.median(t2[e["gap"] == g]) / m3), np.sqrt(np.median(r2[e["gap"] == g]) / m3))
           for g in gaps}
    lg = np.log(gaps.astype(float))
    ys = [np.log([per[int(g)][k] for g in gaps]) for k in (0, 1)]
    # one slope, two intercepts: least squares of both log-sigma series on log g
    lc = lg - lg.mean()
    a = float(sum((lc * (y - y.mean())).sum() for y in ys) / (2 * (lc ** 2).sum()))
    g2a = e["gap"].astype(float) ** (2 * a)
    return {"sigma_trans_gap1_m": float(np.sqrt(np.median(t2 / g2a) / m3)),
            "sigma_rot_gap1_deg": float(np.degrees(np.sqrt(np.median(r2 / g2a) / m3))), "gap_exponent": a,
            "points_factor": use_points,
            "per_gap_sigma": {str(g): {"trans_m": float(s[0]), "rot_deg": float(np.degrees(s[1]))} for g, s in per.items()}}


def nees_of(e: dict[str, np.ndarray], model: dict, use_points: bool) -> np.ndarray:
    """(E,) NEES of each edge under the diagonal ``model``."""
    scale = e["gap"].astype(float) ** model["gap_exponent"] * points_factor(e["points"], use_points)
    st, sr = model["sigma_trans_gap1_m"] * scale, np.radians(model["sigma_rot_gap1_deg"]) * scale
    return (e["d"][:, :3] ** 2).sum(1) / st ** 2 + (e["d"][:, 3:] ** 2).sum(1) / sr ** 2


def nll(e: dict[str, np.ndarray], model: dict, use_points: bool) -> float:
    """Mean Gaussian negative log-likelihood per edge (constants dropped) under ``model``."""
    scale = e["gap"].astype(float) ** model["gap_exponent"] * points_factor(e["points"], use_points)
    logdet = 6 * np.log(scale) + 3 * np.log(model["sigma_trans_gap1_m"] ** 2) \
        + 3 * np.log(np.radians(model["sigma_rot_gap1_deg"]) ** 2)
    return float(np.mean(0.5 * (nees_of(e, model, use_points) + logdet)))


def by_gap(e: dict[str, np.ndarray], v: np.ndarray) -> dict[str, dict]:
    """NEES statistics per gap and over all edges of the NEES values ``v``."""
    out = {}
    for g in [*np.unique(e["gap"]), None]:
        m = e["gap"] == g if g is not None else np.ones(len(v), bool)
        s = nees_stats(v[m])
        out[str(g) if g is not None else "all"] = {"edges": int(m.sum()), "nees_over_6": s["nees_over_dof"],
                                                   "median_nees_over_chi2_median": float(np.median(v[m]) / CHI2_6_MEDIAN),
                                                   "coverage_1sigma": s["coverage_1sigma"]}
    return out


def evaluate(e: dict[str, np.ndarray]) -> dict:
    """The fits with and without the points factor, their NEES per gap, NLL and the points test."""
    plain, with_pts = fit(e, False), fit(e, True)
    low = e["points"] <= np.quantile(e["points"], 1 / 3)
    high = e["points"] >= np.quantile(e["points"], 2 / 3)
    v = nees_of(e, plain, False)
    return {"fit": plain, "fit_with_points": with_pts,
            "nees_by_gap": {"placeholder": by_gap(e, nees_of(e, PLACEHOLDER, True)), "fit": by_gap(e, v),
                            "fit_with_points": by_gap(e, nees_of(e, with_pts, True))},
            "nll_per_edge": {"placeholder": nll(e, PLACEHOLDER, True), "fit": nll(e, plain, False),
                             "fit_with_points": nll(e, with_pts, True)},
            "fit_nees_over_6_by_points": {"fewest_third": float(np.mean(v[low]) / 6),
                                          "most_third": float(np.mean(v[high]) / 6),
                                          "points_thirds": [float(np.quantile(e["points"], q)) for q in (1 / 3, 2 / 3)]}}


def held_out(e: dict[str, np.ndarray]) -> dict[str, dict]:
    """Leave one range out: both models fitted on the other ranges, their NLL per edge and
    NEES/6 on the range left out (does the points factor carry over to another recording?)."""
    out = {}
    for name in np.unique(e["range"]):
        tr, te = ({k: v[m] for k, v in e.items()} for m in (e["range"] != name, e["range"] == name))
        plain, pts = fit(tr, False), fit(tr, True)
        out[str(name)] = {"nll_fit": nll(te, plain, False), "nll_fit_with_points": nll(te, pts, True),
                          "nees_over_6_fit": float(np.mean(nees_of(te, plain, False)) / 6),
                          "nees_over_6_fit_with_points": float(np.mean(nees_of(te, pts, True)) / 6)}
    return out


def collect(specs: list[str], vocabulary: Path, runs: int) -> tuple[dict, dict]:
    """Pooled edge errors of ``runs`` SLAM runs of every validation range, and a summary per run."""
    pooled: list[dict] = []
    summary: dict = {}
    for spec in specs:
        scene, a, b = spec.rsplit(":", 2)
        seq = open_scene(scene, frames=f"{a}:{b}")[0]
        name = f"{Path(scene).name if not scene.startswith('synthetic/') else scene}:{a}:{b}"
        summary[name] = []
        for k in range(runs):
            res = O.run_orbslam3(seq, vocabulary, mode="slam")
            e = edge_errors(seq, res)
            pooled.append({**e, "range": np.array([name] * len(e["gap"]))})
            summary[name].append({"frames": len(seq), "tracked": int(res.ok.sum()), "good_edges": len(e["gap"]),
                                  "seconds": res.seconds})
            print(f"{name} run {k + 1}: {summary[name][-1]}", file=sys.stderr, flush=True)
    return {key: np.concatenate([p[key] for p in pooled]) for key in ("gap", "points", "d", "range")}, summary


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--vocabulary", type=Path, required=True, help="DBoW2 vocabulary built from training frames")
    ap.add_argument("--scenes", nargs="+", default=VALIDATION, help="SCENE:START:STOP validation ranges")
    ap.add_argument("--runs", type=int, default=2, help="SLAM runs per range")
    record.add_arguments(ap, "orbslam3-covariance")
    args = ap.parse_args()
    if not args.vocabulary.is_file():
        ap.error(f"--vocabulary {args.vocabulary}: no such file")
    rec = record.from_args(args, placeholder=PLACEHOLDER)
    e, summary = collect(args.scenes, args.vocabulary, args.runs)
    figures = {"runs": summary, **evaluate(e), "held_out": held_out(e) if len(summary) > 1 else {}}
    for name in summary:  # the pooled fits' NEES on each range alone
        sub = {k: v[e["range"] == name] for k, v in e.items()}
        figures.setdefault("nees_by_range", {})[name] = {
            "placeholder": by_gap(sub, nees_of(sub, PLACEHOLDER, True))["all"],
            "fit": by_gap(sub, nees_of(sub, figures["fit"], False))["all"]}
    rec.finish(figures)
    f = figures["fit"]
    print(f"fit: sigma_t {1000 * f['sigma_trans_gap1_m']:.2f} mm, sigma_r {f['sigma_rot_gap1_deg']:.3f} deg, "
          f"exponent {f['gap_exponent']:.3f}; NLL {figures['nll_per_edge']}")
    for model, rows in figures["nees_by_gap"].items():
        print(model, {g: round(x["nees_over_6"], 2) for g, x in rows.items()})


if __name__ == "__main__":
    main()
