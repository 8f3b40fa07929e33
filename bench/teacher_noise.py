"""Teacher-noise sweep: does a learner trained on a teacher's labels end up more accurate
than that teacher (the paper's claim), and how does that depend on the teacher's noise?

Two commands.

``noisy`` writes a control teacher: a copy of a teacher output folder whose window labels
(gaps 1..K; keyframe and loop edges are left out) carry a calibrated amount of extra
Gaussian noise. Each good edge (i, i+g) becomes
``T_i_j exp(n)``, ``n ~ N(0, diag(s^2 sigma_g^2))`` in the project tangent order (v, w),
where ``sigma_g`` (6,) is the RMS error of the teacher's own gap-g labels per component
against the ground truth on ``--calib-frames`` (so the added noise has the shape of the
teacher's own error at every gap) and the one scale ``s`` is found by bisection so that
the noisy gap-1 labels' mean se(3) L2 error on ``--calib-frames`` equals ``--target``.
The draw is fixed by ``--seed`` (the same standard-normal draws for every ``s``). The
covariance of each edge grows by the added noise's, the chained trajectory, the g2o
vertices and the report's metrics are recomputed; config.json and report.json gain a
``label_noise`` block. Unlike a real teacher's, the added noise is independent between
edges (a real teacher's gap-g labels share keypoints and errors), which is the case most
favourable to the consistency term.

``run`` trains the learner variants on each teacher's labels of ``--frames`` (with
:func:`learner.train.fit`, as bench/ablation.py does), predicts ``--test-frames`` (held
out) and ``--frames`` again (the *transductive* protocol: fit on a recording's own teacher
labels, no ground truth, evaluate on those same frames), and reports each against the
ground truth beside the teacher's own label error on the same frames (its good gap-1
edges, se(3) L2 mean, RPE RMSE), zero motion and constant velocity. Runs live in
``OUT/<teacher>/<variant>/``; a finished checkpoint is reused (``--checkpoint
NAME/VARIANT=PATH`` takes one from elsewhere), so an interrupted sweep resumes and
``--no-train`` only reports. Writes ``OUT/sweep.json``, ``OUT/sweep.md`` (the tables) and
``OUT/sweep.png``: learner error against its teacher's error, with the line y = x (below
it the learner beats its teacher), one panel per protocol.

    S=../shared/data/7scenes/redkitchen/seq-sample
    .venv/bin/python -m ctcvo teacher generate --scene $S --out runs/i12/default
    .venv/bin/python -m ctcvo teacher generate --scene $S --preset paper --out runs/i12/paper
    .venv/bin/python -m bench.teacher_noise noisy --scene $S --teacher runs/i12/default \\
        --calib-frames 0:450 --target 0.0052 --out runs/i12/noisy52
    OMP_NUM_THREADS=1 .venv/bin/python -m bench.teacher_noise run --scene $S --frames 0:450 \\
        --test-frames 450:600 --teacher default=runs/i12/default --teacher paper=runs/i12/paper \\
        --teacher noisy52=runs/i12/noisy52 --variants ctc cnn-unsup lstm-unsup --out runs/i12/sweep

``run`` also writes the record ``bench/results/<name>.json`` (bench/record.py; default name
``teacher-noise``): its figures are the teachers', learners' and baselines' rows of sweep.json.
"""

from __future__ import annotations

import argparse
import json
import logging
import shutil
import sys
import time
from pathlib import Path

import numpy as np

from bench import record
from ctcvo.data import geometry as geo
from ctcvo.data.errors import VOError, one_line
from ctcvo.data.formats import Edge, Trajectory, read_edges_csv, read_g2o, read_tum, write_edges_csv, write_g2o, write_tum
from ctcvo.data.io import ensure_dir, git_revision, write_json, write_text
from ctcvo.data.metrics import BASELINES, baseline_reports, se3_l2_errors, trajectory_report
from ctcvo.data.scenes import open_scene

log = logging.getLogger("teacher_noise")


# ----------------------------------------------------------------------------------
# ground truth and label errors
# ----------------------------------------------------------------------------------
def groundtruth(scene: str, frames: str | None) -> tuple[np.ndarray, Trajectory]:
    """Frame ids (N,) and ground truth of the single sequence of ``scene`` / ``frames``."""
    seqs = open_scene(scene, frames=frames)
    if len(seqs) != 1 or seqs[0].groundtruth() is None:
        raise VOError(f"{scene} {frames or ''}: the sweep needs one sequence with ground truth")
    return seqs[0].ids(), Trajectory(seqs[0].times(), seqs[0].groundtruth())


def label_errors(edges: list[Edge], ids: np.ndarray, gt: np.ndarray, gap: int = 1) -> dict[str, float]:
    """Error of the good gap-``gap`` labels between frames ``ids`` against the ground truth
    ``gt`` (N, 4, 4): se(3) L2 mean, translation and rotation RMSE, count and how many of
    the range's pairs have no good label."""
    pos = {int(f): k for k, f in enumerate(ids)}
    est, ref = [], []
    for e in edges:
        if e.i in pos and e.j in pos and pos[e.j] - pos[e.i] == gap:
            est.append(e.T_i_j)
            ref.append(geo.relative_pose(gt[pos[e.i]], gt[pos[e.j]]))
    if not est:
        raise VOError(f"no good gap-{gap} label between frames {ids[0]}..{ids[-1]}")
    est, ref = np.array(est), np.array(ref)
    d = [geo.inv_T(r) @ e for r, e in zip(ref, est)]
    return {"se3_l2_mean": float(np.mean(se3_l2_errors(ref, est))),
            "rpe_trans_rmse_m": float(np.sqrt(np.mean([np.sum(x[:3, 3] ** 2) for x in d]))),
            "rpe_rot_rmse_deg": float(np.sqrt(np.mean([geo.rotation_angle_deg(x) ** 2 for x in d]))),
            "edges": len(est), "missing": len(ids) - gap - len(est)}


def component_rms(edges: list[Edge], ids: np.ndarray, gt: np.ndarray, gap: int) -> np.ndarray:
    """RMS per tangent component (v, w) of ``log(T_gt^-1 T_label)`` of the good gap-``gap``
    labels between frames ``ids`` (6,)."""
    pos = {int(f): k for k, f in enumerate(ids)}
    r = [geo.se3_log(geo.inv_T(geo.relative_pose(gt[pos[e.i]], gt[pos[e.j]])) @ e.T_i_j)
         for e in edges if e.i in pos and e.j in pos and pos[e.j] - pos[e.i] == gap]
    if not r:
        raise VOError(f"no good gap-{gap} label between frames {ids[0]}..{ids[-1]} to calibrate on")
    return np.sqrt(np.mean(np.square(r), axis=0))


# ----------------------------------------------------------------------------------
# noisy control teacher
# ----------------------------------------------------------------------------------
def window_edges(teacher: Path) -> tuple[list[Edge], list[dict] | None]:
    """The good window edges (gaps 1..K, edges.csv kind ``window``) of ``teacher``'s g2o and
    their edges.csv rows (``None`` without an edges.csv). Keyframe and loop edges are left
    out of the noisy copy: their gaps have no per-gap error shape, and the learner reads
    gaps 1..K only."""
    edges, _ = read_g2o(teacher / "edges.g2o")
    if not (teacher / "edges.csv").is_file():
        return edges, None
    rows = [r for r in read_edges_csv(teacher / "edges.csv") if r.get("kind", "window") == "window"]
    keep = {(r["i"], r["j"]) for r in rows}
    return [e for e in edges if (e.i, e.j) in keep], rows


def add_label_noise(teacher: Path, scene: str, calib_frames: str | None, target: float, out: Path,
                    seed: int = 0) -> dict:
    """Write ``out``: ``teacher``'s folder with calibrated extra label noise (see the module
    docstring). Returns the ``label_noise`` block."""
    edges, rows = window_edges(teacher)
    ids, gt = groundtruth(scene, calib_frames)
    gaps = sorted({e.j - e.i for e in edges})
    shape = {g: component_rms(edges, ids, gt.poses, g) for g in gaps}
    z = np.random.default_rng(seed).standard_normal((len(edges), 6))

    def noisy(s: float) -> list[Edge]:
        return [Edge(e.i, e.j, e.T_i_j @ geo.se3_exp(s * shape[e.j - e.i] * zk),
                     e.cov + np.diag((s * shape[e.j - e.i]) ** 2)) for e, zk in zip(edges, z)]

    def err(s: float) -> float:
        return label_errors(noisy(s), ids, gt.poses)["se3_l2_mean"]

    base = err(0.0)
    if target <= base:
        raise VOError(f"--target {target} is not above the teacher's own gap-1 error {base:.5f} on {calib_frames}")
    lo, hi = 0.0, 1.0
    while err(hi) < target:
        lo, hi = hi, 2 * hi
        if hi > 1e3:
            raise VOError(f"--target {target} cannot be reached")
    for _ in range(40):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if err(mid) < target else (lo, mid)
    s = 0.5 * (lo + hi)
    new = noisy(s)
    info = {"source": str(teacher), "target_se3_l2_gap1": target, "calib_frames": calib_frames, "seed": seed,
            "scale": s, "teacher_se3_l2_gap1": base, "achieved_se3_l2_gap1": err(s),
            "sigma_by_gap": {str(g): (s * shape[g]).tolist() for g in gaps},
            "shape_by_gap": {str(g): shape[g].tolist() for g in gaps}}
    # chained gap-1 trajectory of the noisy labels (the teacher's own step where a gap-1 label is missing)
    old = read_tum(teacher / "trajectory.tum")
    step = {e.i: e.T_i_j for e in new if e.j - e.i == 1}
    vert_ids = sorted(read_g2o(teacher / "edges.g2o")[1])
    if len(vert_ids) != len(old):
        raise VOError(f"{teacher}: trajectory.tum and the g2o vertices disagree")
    poses = [old.poses[0]]
    for k in range(1, len(vert_ids)):
        T = step.get(vert_ids[k - 1], geo.relative_pose(old.poses[k - 1], old.poses[k]))
        poses.append(poses[-1] @ T)
    traj = Trajectory(old.timestamps, np.array(poses))
    ensure_dir(out)
    write_g2o(out / "edges.g2o", new, vertices=dict(zip(vert_ids, traj.poses)))
    write_tum(out / "trajectory.tum", traj)
    if rows is not None:
        write_edges_csv(out / "edges.csv", rows)
    if (teacher / "groundtruth.tum").is_file():
        shutil.copyfile(teacher / "groundtruth.tum", out / "groundtruth.tum")
    cfg = json.loads((teacher / "config.json").read_text()) if (teacher / "config.json").is_file() else {}
    write_json(out / "config.json", {**cfg, "label_noise": info, "git_revision": git_revision()})
    rep = json.loads((teacher / "report.json").read_text())
    if (out / "groundtruth.tum").is_file():
        rep.update(trajectory_report(read_tum(out / "groundtruth.tum"), traj))
    rep.pop("label_error_by_gap", None)  # of the source labels: no longer true
    write_json(out / "report.json", {**rep, "label_noise": info})
    return info


# ----------------------------------------------------------------------------------
# sweep
# ----------------------------------------------------------------------------------
def crossover(points: list[tuple[float, float]]) -> str:
    """Where learner error (y) = teacher error (x), linearly interpolated between the sweep's
    teachers sorted by x; or which side of y = x all points lie on."""
    pts = sorted(points)
    d = [y - x for x, y in pts]
    for (x0, _), (x1, _), d0, d1 in zip(pts, pts[1:], d, d[1:]):
        if d0 == 0:
            return f"at teacher error {x0:.5f}"
        if d0 * d1 < 0:
            t = d0 / (d0 - d1)
            return f"at teacher error ~{x0 + t * (x1 - x0):.5f} (interpolated)"
    if not pts:
        return "no points"
    side = "below (learner better)" if d[-1] < 0 else "above (learner worse)"
    return f"none in [{pts[0][0]:.5f}, {pts[-1][0]:.5f}]: every point {side} y = x"


def finished(run: Path) -> bool:
    """A learner run folder whose checkpoint has done all its configured steps."""
    try:
        hist = json.loads((run / "history.json").read_text())
        steps = json.loads((run / "config.json").read_text())["train"]["steps"]
    except (OSError, ValueError, KeyError):
        return False
    return (run / "checkpoint.pt").is_file() and bool(hist) and hist[-1].get("steps", 0) >= steps


def run_sweep(args: argparse.Namespace) -> dict:
    from ctcvo.learner.config import PredictConfig
    from ctcvo.learner.predict import predict
    from ctcvo.learner.train import fit

    teachers = dict(t.split("=", 1) for t in args.teacher)
    given = dict(c.split("=", 1) for c in args.checkpoint)
    ranges = {"held-out": args.test_frames, "transductive": args.frames}
    gts = {name: groundtruth(args.scene, fr) for name, fr in ranges.items()}
    out: dict = {"args": {k: str(v) for k, v in vars(args).items()}, "git_revision": git_revision(),
                 "started": time.strftime("%Y-%m-%d %H:%M:%S UTC", time.gmtime()), "ranges": ranges,
                 "baselines": {name: baseline_reports(gt) for name, (_, gt) in gts.items()},
                 "teachers": {}, "learners": {}}
    for tname, tdir in teachers.items():
        edges, _ = read_g2o(Path(tdir) / "edges.g2o")
        out["teachers"][tname] = {"folder": tdir, **{name: label_errors(edges, ids, gt.poses)
                                                    for name, (ids, gt) in gts.items()}}
    for tname, tdir in teachers.items():
        for v in args.variants:
            key = f"{tname}/{v}"
            run = args.out / tname / v
            ckpt = Path(given[key]) if key in given else run / "checkpoint.pt"
            row: dict = {"teacher": tname, "variant": v, "checkpoint": str(ckpt)}
            if key not in given and not finished(run):
                if args.no_train:
                    continue
                t0 = time.perf_counter()
                extra = {} if args.steps is None else {"steps": args.steps}
                fit([args.scene], variant=v, preset=args.preset, frames=args.frames, out=run, calibrate=False,
                    resume=ckpt.is_file(), teacher_root=Path(tdir), seed=args.seed, **extra)
                row["fit_s"] = round(time.perf_counter() - t0, 1)
            row["steps"] = json.loads((ckpt.parent / "config.json").read_text())["train"]["steps"]
            # the fit's own last evaluation on its training frames (no MC dropout): for ctc and
            # lstm-unsup also the direct head, whose gap-1 estimate predict does not write
            last = json.loads((ckpt.parent / "history.json").read_text())[-1]
            row["train_eval"] = {k: last.get(f"train_{k}_se3_l2") for k in ("direct", "lstm")}
            for name, fr in ranges.items():
                pdir = run / f"predict-{name}"
                if not (pdir / "report.json").is_file():
                    predict(ckpt, args.scene, frames=fr, out=pdir, config=PredictConfig(samples=args.samples))
                rep = json.loads((pdir / "report.json").read_text())
                row[name] = {k: rep[k] for k in ("se3_l2_mean", "rpe_trans_rmse_m", "rpe_rot_rmse_deg", "ate_rmse_m")}
                row[name]["vs_teacher"] = row[name]["se3_l2_mean"] / out["teachers"][tname][name]["se3_l2_mean"]
            out["learners"][key] = row
            write_json(args.out / "sweep.json", out)
    out["crossover"] = {name: {v: crossover([(out["teachers"][r["teacher"]][name]["se3_l2_mean"], r[name]["se3_l2_mean"])
                                            for r in out["learners"].values() if r["variant"] == v])
                               for v in args.variants} for name in ranges}
    write_json(args.out / "sweep.json", out)
    write_text(args.out / "sweep.md", tables(out))
    plot(out, args.out / "sweep.png")
    return out


def tables(res: dict) -> str:
    lines = []
    for name, fr in res["ranges"].items():
        lines += [f"### {name}: frames {fr}" + (" (the training frames themselves)" if name == "transductive" else ""), "",
                  "| row | teacher | se(3) L2 | / teacher | / zero motion | gap-1 RPE mm / deg |", "|---|---|---|---|---|---|"]
        zm = res["baselines"][name]["zero motion"]["se3_l2_mean"]
        for b in BASELINES:
            r = res["baselines"][name][b]
            lines.append(f"| {b} | - | {r['se3_l2_mean']:.5f} | - | {r['se3_l2_mean'] / zm:.2f} | "
                         f"{1e3 * r['rpe_trans_rmse_m']:.2f} / {r['rpe_rot_rmse_deg']:.3f} |")
        for tname, t in res["teachers"].items():
            r = t[name]
            lines.append(f"| teacher `{tname}` (its gap-1 labels) | {tname} | {r['se3_l2_mean']:.5f} | 1.00 | "
                         f"{r['se3_l2_mean'] / zm:.2f} | {1e3 * r['rpe_trans_rmse_m']:.2f} / {r['rpe_rot_rmse_deg']:.3f} |")
            for row in res["learners"].values():
                if row["teacher"] == tname and name in row:
                    q = row[name]
                    lines.append(f"| {row['variant']} | {tname} | {q['se3_l2_mean']:.5f} | **{q['vs_teacher']:.2f}** | "
                                 f"{q['se3_l2_mean'] / zm:.2f} | {1e3 * q['rpe_trans_rmse_m']:.2f} / "
                                 f"{q['rpe_rot_rmse_deg']:.3f} |")
        if name == "transductive":
            direct = [f"{r['teacher']}/{r['variant']} {r['train_eval']['direct']:.5f} "
                      f"({r['train_eval']['direct'] / res['teachers'][r['teacher']][name]['se3_l2_mean']:.2f}x its teacher)"
                      for r in res["learners"].values() if r.get("train_eval", {}).get("direct") is not None
                      and r["train_eval"].get("lstm") is not None]
            if direct:
                lines += ["", "Direct head of the LSTM variants on these frames (the fit's last evaluation, no MC "
                          "dropout; the table's rows use the LSTM head at gap 1): " + "; ".join(direct)]
        lines += ["", "Crossover (learner error = teacher error): " +
                  "; ".join(f"{v}: {c}" for v, c in res.get("crossover", {}).get(name, {}).items()), ""]
    return "\n".join(lines) + "\n"


def plot(res: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = list(res["ranges"])
    fig, axes = plt.subplots(1, len(names), figsize=(5.5 * len(names), 5), squeeze=False)
    markers = {"ctc": "o", "cnn-unsup": "s", "lstm-unsup": "^"}
    for ax, name in zip(axes[0], names):
        xs = [t[name]["se3_l2_mean"] for t in res["teachers"].values()]
        ys = [r[name]["se3_l2_mean"] for r in res["learners"].values() if name in r]
        hi = 1.15 * max(xs + ys + [res["baselines"][name]["zero motion"]["se3_l2_mean"]])
        ax.plot([0, hi], [0, hi], "k--", lw=1, label="y = x (learner = its teacher)")
        for b, style in zip(BASELINES, (":", "-.")):
            ax.axhline(res["baselines"][name][b]["se3_l2_mean"], color="grey", ls=style, lw=1, label=b)
        for v in sorted({r["variant"] for r in res["learners"].values()}):
            pts = sorted((res["teachers"][r["teacher"]][name]["se3_l2_mean"], r[name]["se3_l2_mean"], r["teacher"])
                         for r in res["learners"].values() if r["variant"] == v and name in r)
            ax.plot([p[0] for p in pts], [p[1] for p in pts], marker=markers.get(v, "x"), label=v)
            for x, y, t in pts:
                ax.annotate(t, (x, y), textcoords="offset points", xytext=(4, 4), fontsize=7)
        ax.set_xlim(0, hi)
        ax.set_ylim(0, hi)
        ax.set_aspect("equal")
        ax.set_xlabel("teacher's gap-1 label error, se(3) L2")
        ax.set_ylabel("learner's gap-1 error, se(3) L2")
        ax.set_title(f"{name} (frames {res['ranges'][name]})")
        ax.legend(fontsize=7, loc="upper left")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = ap.add_subparsers(dest="command", required=True)
    n = sub.add_parser("noisy", help="write a teacher folder with calibrated extra label noise")
    n.add_argument("--scene", required=True)
    n.add_argument("--teacher", type=Path, required=True, help="source teacher output folder")
    n.add_argument("--calib-frames", required=True, help="frames whose ground truth calibrates the noise (training range)")
    n.add_argument("--target", type=float, required=True, help="gap-1 se(3) L2 mean of the noisy labels there")
    n.add_argument("--seed", type=int, default=0)
    n.add_argument("--out", type=Path, required=True)
    r = sub.add_parser("run", help="train, predict and report the sweep")
    r.add_argument("--scene", required=True)
    r.add_argument("--frames", required=True, help="training range (also the transductive evaluation range)")
    r.add_argument("--test-frames", required=True, help="held-out evaluation range")
    r.add_argument("--teacher", action="append", required=True, help="NAME=FOLDER (repeatable)")
    r.add_argument("--checkpoint", action="append", default=[], help="NAME/VARIANT=PATH: use this checkpoint")
    r.add_argument("--variants", nargs="+", default=["ctc", "cnn-unsup", "lstm-unsup"])
    r.add_argument("--preset", default="cpu")
    r.add_argument("--steps", type=int, help="optimiser steps per fit (default: the preset's)")
    r.add_argument("--samples", type=int, default=10, help="MC-dropout samples of predict")
    r.add_argument("--seed", type=int, default=0)
    r.add_argument("--no-train", action="store_true", help="report only the runs that exist")
    r.add_argument("--out", type=Path, required=True)
    record.add_arguments(r, "teacher-noise")
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    try:
        if args.command == "noisy":
            info = add_label_noise(args.teacher, args.scene, args.calib_frames, args.target, args.out, args.seed)
            print(json.dumps({k: info[k] for k in ("scale", "teacher_se3_l2_gap1", "achieved_se3_l2_gap1")}))
        else:
            for t in args.teacher:
                if "=" not in t:
                    ap.error(f"--teacher {t}: expected NAME=FOLDER")
            rec = record.from_args(args)
            res = run_sweep(args)
            print(tables(res))
            rec.finish({k: res[k] for k in ("ranges", "baselines", "teachers", "learners", "crossover")})
    except VOError as exc:
        print(f"error: {one_line(exc)}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
