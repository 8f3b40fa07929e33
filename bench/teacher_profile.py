"""Where the teacher's CPU time goes, per frame, and whether a change moved its labels.

Runs :func:`teacher.generate.run_sequence` in this process (``workers`` 1: the main thread
estimates the edges, one helper thread decodes frames and extracts features) with the
teacher's expensive functions wrapped in timers of the CPU time of the thread that runs
them (``time.thread_time``: waits for the GIL or for the other thread do not count), and
prints:

* the process's CPU time per frame (``time.process_time``, both threads);
* per function: CPU ms per frame, calls, ms per call (inclusive: ``estimate_edge`` holds
  ``dense_refine`` holds ``point_to_plane_covariance`` ...);
* a SHA-1 of every edge's (i, j), pose and covariance bytes: equal digests mean labels
  equal to the bit;
* the gap-1 RPE, ATE and se(3) L2 of the run's report;
* with ``--why``: per gap, which path made each edge and, for every edge the keypoint
  estimates did not make (a wider matching, a dense fallback, none), the failure check that
  refused each keypoint attempt (``few_matches``, ``few_inliers``, ``low_inlier_ratio``,
  ``high_rmse``, ``degenerate``, ``implausible_motion``) and the numbers it refused on; with
  ground truth, the translation error of the refused estimate beside the label's that
  replaced it (was the refusal right?).

``--save-edges FILE.npz`` keeps the edges with the ground truth; ``--compare A.npz B.npz``
then compares two runs edge by edge against the ground truth: gap-1 and all edges, the
mean paired difference of squared translation errors with its standard error (the noise
figure for a label-changing choice: the teacher is deterministic, two runs are equal),
how far each label moved, and for each run the drift of its chained gap-1 edges over one second
(the relative pose error over every pair of frames 30 apart), the scale of its translations against the truth per gap,
the same scale of its rotation vectors, and its median and largest translation error per gap;
gap-1 and all-edge rotation errors are compared like the translations.

    OMP_NUM_THREADS=1 nice -n 10 .venv/bin/python -m bench.teacher_profile ../shared/data/7scenes/redkitchen --frames 350:450
    OMP_NUM_THREADS=1 nice -n 10 .venv/bin/python -m bench.teacher_profile synthetic/lab --frames 0:100 --set p2p_cov_stride=2 --save-edges /tmp/a.npz
    .venv/bin/python -m bench.teacher_profile --compare /tmp/a.npz /tmp/b.npz
    OMP_NUM_THREADS=1 .venv/bin/python -m bench.teacher_profile synthetic/lab --frames 0:150 \
        --sensor frame_repeat_prob=0 rgb_repeat_prob=0 depth_repeat_prob=0 rolling_shutter_s=0 --save-edges /tmp/gs.npz

``--sensor FIELD=VALUE ...`` renders a synthetic preset with parts of its sensor model
changed (data/synthetic/config.py ``SensorConfig``): which part of the sensor costs the
teacher what. Turn the repeated frames off in both runs of such a comparison: a repeated
frame repeats its pose, so the ground truth differs with them.
``--sensor-off`` starts from every part off (:data:`SENSOR_OFF`, repeats included), so that
``--sensor-off --sensor PART=VALUE`` measures one part alone. ``--open3d`` runs Open3D's hybrid
odometry (``bench.teacher``'s peer) on the same frames instead of the teacher and keeps its
gap-1 edges for ``--compare`` (bench/README.md, "Where the teacher's systematic errors on the
synthetic rooms come from")::

    OMP_NUM_THREADS=1 .venv/bin/python -m bench.teacher_profile synthetic/lab --frames 0:150 --sensor-off \
        --sensor depth_bias_coeff=0.001 --save-edges /tmp/bias.npz
    OMP_NUM_THREADS=1 .venv/bin/python -m bench.teacher_profile synthetic/lab --frames 0:150 --sensor-off \
        --sensor depth_bias_coeff=0.001 --open3d --save-edges /tmp/bias-o3d.npz

Choose parameters on validation ranges only (redkitchen 350:450, synthetic/lab; see
bench/README.md, "Ranges").
"""

from __future__ import annotations

import argparse
import collections
import dataclasses
import hashlib
import sys
import time
from collections.abc import Callable

import numpy as np

from ctcvo.data import geometry as geo
from ctcvo.data.scenes import open_scene
from ctcvo.teacher import generate as gen
from ctcvo.teacher import odometry as od
from ctcvo.teacher import window as win
from ctcvo.teacher.config import TeacherConfig

#: teacher.odometry functions timed (module globals, so calls between them are timed too)
TIMED = ("estimate_edge", "match", "match_wide", "_estimate", "refine_two_way", "dense_refine",
         "point_to_plane_covariance", "hybrid_covariance", "rgbd_edge", "dense_edge", "_reproj_err", "depth_at",
         "dense_maps", "_fill_surface", "image_keys")


class Timers:
    """CPU time (of the calling thread) and calls per label."""

    def __init__(self) -> None:
        self.cpu: dict[str, float] = collections.defaultdict(float)
        self.calls: collections.Counter = collections.Counter()

    def wrap(self, f: Callable, label: str) -> Callable:
        def timed(*a, **k):
            t = time.thread_time()
            try:
                return f(*a, **k)
            finally:
                self.cpu[label] += time.thread_time() - t
                self.calls[label] += 1
        return timed


def instrument(timers: Timers, seq_cls: type) -> None:
    """Wrap the teacher's functions, OpenCV's PnP calls, Open3D's point-to-plane kernel and
    the sequence's image readers (this process only; for profiling, never in the tools)."""
    import cv2

    from ctcvo.data.open3d_import import o3d

    for name in TIMED:
        setattr(od, name, timers.wrap(getattr(od, name), name))
    win.estimate_edge = od.estimate_edge
    gen.extract = timers.wrap(gen.extract, "extract")

    class _CV:  # cv2 as teacher.odometry sees it, with its PnP calls timed
        def __getattr__(self, name):
            f = getattr(cv2, name)
            return timers.wrap(f, name) if name in ("solvePnPRansac", "solvePnPRefineLM") else f

    od.cv2 = _CV()
    kern = o3d.t.pipelines.odometry
    kern.compute_odometry_result_point_to_plane = timers.wrap(kern.compute_odometry_result_point_to_plane,
                                                              "open3d point-to-plane kernel")
    for name in ("rgb", "depth"):
        setattr(seq_cls, name, timers.wrap(getattr(seq_cls, name), f"read {name}"))


class Reasons:
    """Every keypoint attempt (:func:`teacher.odometry._estimate` call) of every edge, kept
    with the edge's final result (``--why``)."""

    def __init__(self) -> None:
        self.edges: list[tuple[od.EdgeEstimate, list[od.EdgeEstimate]]] = []
        self._cur: list[od.EdgeEstimate] | None = None

    def wrap(self) -> None:
        est, edge = od._estimate, od.estimate_edge

        def _estimate(*a, **k):
            res = est(*a, **k)
            if self._cur is not None:
                self._cur.append(res)
            return res

        def estimate_edge(*a, **k):
            self._cur = []
            try:
                res = edge(*a, **k)
                self.edges.append((res, self._cur))
                return res
            finally:
                self._cur = None

        od._estimate, od.estimate_edge = _estimate, estimate_edge
        win.estimate_edge = od.estimate_edge

    def report(self, ids, gt) -> None:
        pos = {int(i): k for k, i in enumerate(ids)}

        def err_mm(e: od.EdgeEstimate) -> float:
            if gt is None or e.T_i_j is None:
                return float("nan")
            G = geo.relative_pose(gt[pos[e.i]], gt[pos[e.j]])
            return 1000 * float(np.linalg.norm((geo.inv_T(G) @ e.T_i_j)[:3, 3]))

        by_gap: dict[int, list] = collections.defaultdict(list)
        for res, attempts in self.edges:
            by_gap[pos[res.j] - pos[res.i]].append((res, attempts))
        print("why: per gap, the paths that made the edges; for the edges the first keypoint attempt did "
              "not make, each attempt's status -> the path that made the edge")
        for g in sorted(by_gap):
            rows = by_gap[g]
            paths = collections.Counter(r.info.get("path", "none") if r.ok else "failed" for r, _ in rows)
            print(f"  gap {g}: {len(rows)} edges; paths " + ", ".join(f"{k} {v}" for k, v in paths.most_common()))
            reasons = collections.Counter()
            for r, att in rows:
                if att and att[0].ok and r.info.get("path") == att[0].info.get("source"):
                    continue
                path = r.info.get("path", "none") if r.ok else "failed"
                reasons[" > ".join(f"{a.info.get('source', '?')}:{a.status}" for a in att) + f" -> {path}"] += 1
            for k, v in reasons.most_common():
                print(f"      {v:4d}  {k}")
        refused = [(r, a) for r, att in self.edges for a in att if not a.ok and a.T_i_j is not None]
        if not refused:
            return
        print("  refused keypoint estimates (a pose was computed, a check refused it): status, count, "
              "inliers / ratio / rmse px median, their error and the final label's (mm, median / RMSE)")
        for status in sorted({a.status for _, a in refused}):
            sel = [(r, a) for r, a in refused if a.status == status]
            ea = np.array([err_mm(a) for _, a in sel])
            er = np.array([err_mm(r) if r.ok else np.nan for r, _ in sel])
            q = lambda x: f"{np.nanmedian(x):.2f} / {np.sqrt(np.nanmean(x ** 2)):.2f}" if np.isfinite(x).any() else "-"
            print(f"    {status:20s} {len(sel):4d}  {np.median([a.inliers for _, a in sel]):5.0f} / "
                  f"{np.median([a.inlier_ratio for _, a in sel]):.2f} / {np.median([a.rmse_px for _, a in sel]):.2f}"
                  f"  refused {q(ea)}  label {q(er)}")


def edges_digest(edges) -> str:
    h = hashlib.sha1()
    for e in edges:
        h.update(np.int64([e.i, e.j]).tobytes())
        if e.ok:
            h.update(np.ascontiguousarray(e.T_i_j).tobytes())
            h.update(np.ascontiguousarray(e.cov).tobytes())
    return h.hexdigest()[:16]


def parse_set(items: list[str]) -> dict:
    """``key=value`` overrides of :class:`TeacherConfig` (:func:`_overrides`)."""
    return _overrides(items, TeacherConfig())


def parse_sensor(items: list[str], all_off: bool = False) -> dict:
    """``key=value`` overrides of a synthetic scene's :class:`SensorConfig` (:func:`_overrides`);
    ``all_off``: on top of :data:`SENSOR_OFF`."""
    from ctcvo.data.synthetic.config import SensorConfig

    return {**(SENSOR_OFF if all_off else {}), **_overrides(items, SensorConfig())}


#: the synthetic sensor model without repeated frames (a repeated frame repeats its pose, so
#: the ground truth differs with them)
NO_REPEATS = dict(frame_repeat_prob=0.0, rgb_repeat_prob=0.0, depth_repeat_prob=0.0)
#: the synthetic sensor model's depth without noise, bias, quantisation and holes
CLEAN_DEPTH = dict(depth_noise_coeff=0.0, depth_bias_coeff=0.0, disparity_step=0.0, dropout_prob=0.0,
                   hole_blob_fraction=0.0, edge_hole_px=0, projector_baseline_m=0.0, grazing_cos=0.0)
#: every part of the synthetic sensor model off (``--sensor-off``), field by field: unlike
#: ``noise_free`` the colour camera stays a separate camera (identity model), so that turning
#: one part back on (``--sensor PART=VALUE``) measures that part alone
SENSOR_OFF = {
    **NO_REPEATS, **CLEAN_DEPTH,
    "rolling_shutter_s": 0.0, "motion_blur_exposure": 0.0, "residual_distortion_k1": 0.0,
    "rgb_focal_scale": 1.0, "rgb_shift_px": (0.0, 0.0), "rgb_baseline_m": 0.0,
    "jpeg_quality": 0, "rgb_blur_sigma": 0.0, "exposure_log_sigma": 0.0, "vignetting": 0.0, "read_noise_dn": 0.0,
    "shot_noise_gain": 0.0, "invalid_right_cols": 0,
}


def _overrides(items: list[str], base) -> dict:
    """``key=value`` overrides of the dataclass ``base``, typed by the field's default: a
    bool from ``1/true/yes``, a pair as ``lo,hi``, an optional number (default None: auto)
    as a float or ``none`` / ``auto``."""
    out = {}
    for kv in items:
        key, _, value = kv.partition("=")
        if not hasattr(base, key):
            raise SystemExit(f"error: {type(base).__name__} has no field {key!r}")
        kind = type(getattr(base, key))
        if kind is bool:
            out[key] = value.lower() in ("1", "true", "yes")
        elif kind is tuple:
            out[key] = tuple(float(v) for v in value.split(","))
        elif kind is type(None):
            out[key] = None if value.lower() in ("none", "auto") else float(value)
        else:
            out[key] = kind(value)
    return out


def open_profiled(spec: str, frames: str, sensor: dict):
    """The scene ``spec``, frames ``frames``; a synthetic preset rendered with the sensor
    model's fields ``sensor`` replaced (cached like the preset, under its config's hash)."""
    if not sensor:
        return open_scene(spec, frames=frames)[0]
    if not spec.startswith("synthetic/"):
        raise SystemExit("error: --sensor takes a synthetic scene (synthetic/NAME)")
    from ctcvo.data.synthetic import synthetic_sequence
    from ctcvo.data.synthetic.config import resolve_preset

    name = spec.split("/", 1)[1]
    try:
        cfg = resolve_preset(name)
    except KeyError:
        raise SystemExit(f"error: unknown synthetic scene {name!r}") from None
    cfg = dataclasses.replace(cfg, sensor=dataclasses.replace(cfg.sensor, **sensor))
    start, _, stop = frames.partition(":")
    return synthetic_sequence(name, config=cfg).select(int(start) if start else None, int(stop) if stop else None)


def profile(spec: str, frames: str, overrides: dict, save: str | None, why: bool = False,
            sensor: dict | None = None) -> None:
    seq = open_profiled(spec, frames, sensor or {})
    timers = Timers()
    instrument(timers, type(seq))
    reasons = Reasons() if why else None
    if reasons:
        reasons.wrap()
    cfg = dataclasses.replace(TeacherConfig(), workers=1, **overrides)
    c0, w0 = time.process_time(), time.perf_counter()
    run = gen.run_sequence(seq, cfg, progress=False)
    cpu, wall = time.process_time() - c0, time.perf_counter() - w0
    if save:
        ok = [e for e in run.edges if e.ok]
        save_edges(save, seq, [(e.i, e.j) for e in ok], [e.T_i_j for e in ok], [e.cov for e in ok])
    n = len(seq)
    print(f"{spec} {frames}{' sensor ' + str(sensor) if sensor else ''}{' ' + str(overrides) if overrides else ''}: {n} frames, CPU {1000 * cpu / n:.1f} ms/frame, "
          f"wall {1000 * wall / n:.1f} ms/frame, edges sha1 {edges_digest(run.edges)}")
    rep = gen.build_report(seq, run, cfg)
    if "rpe_trans_rmse_m" in rep:
        print(f"  gap-1 RPE {1000 * rep['rpe_trans_rmse_m']:.3f} mm / {rep['rpe_rot_rmse_deg']:.4f} deg, "
              f"ATE {1000 * rep['ate_rmse_m']:.2f} mm, se(3) L2 {rep['se3_l2_mean']:.6f}, "
              f"failed edges {rep['failed_edges']}")
    for k, v in sorted(timers.cpu.items(), key=lambda x: -x[1]):
        c = timers.calls[k]
        print(f"  {k:30s} {1000 * v / n:7.2f} ms/frame {c:6d} calls {1000 * v / max(c, 1):6.2f} ms/call")
    if reasons:
        reasons.report(seq.ids(), seq.groundtruth() if seq.has_groundtruth else None)


def save_edges(path: str, seq, ij: list, T: list, cov: list) -> None:
    """The ``--save-edges`` file that ``--compare`` reads: the edges' frame ids ``ij`` (M, 2),
    poses ``T`` (M, 4, 4) and covariances ``cov`` (M, 6, 6), with the run's frame ids and
    ground truth (N, 4, 4; empty without one)."""
    np.savez(path, ij=np.array(ij, np.int64).reshape(-1, 2), T=np.array(T).reshape(-1, 4, 4),
             cov=np.array(cov).reshape(-1, 6, 6), ids=seq.ids(),
             gt=seq.groundtruth() if seq.has_groundtruth else np.zeros((0, 4, 4)))


def profile_open3d(spec: str, frames: str, save: str | None, sensor: dict | None = None) -> None:
    """Open3D's hybrid RGB-D odometry (``bench.teacher``'s peer) on the same frames as
    :func:`profile` would run, its gap-1 edges kept like the teacher's (``--save-edges``), so
    that ``--compare`` sets it beside a teacher run on the same render."""
    from bench.teacher import run_open3d

    seq = open_profiled(spec, frames, sensor or {})
    P, secs, fails = run_open3d(seq)
    ids = seq.ids()
    if save:
        T = [geo.inv_T(P[k]) @ P[k + 1] for k in range(len(ids) - 1)]
        save_edges(save, seq, list(zip(ids[:-1], ids[1:])), T, [np.full((6, 6), np.nan)] * len(T))
    print(f"{spec} {frames}{' sensor ' + str(sensor) if sensor else ''}, Open3D hybrid odometry: {len(seq)} frames, "
          f"{len(seq) / secs:.2f} fps (wall), {fails} failed gap-1 alignments")


def compare(a_path: str, b_path: str) -> None:
    a, b = np.load(a_path), np.load(b_path)
    if len(a["gt"]) == 0:
        raise SystemExit("error: the runs were saved without ground truth")
    pos = {int(i): k for k, i in enumerate(a["ids"])}
    gt = a["gt"]

    def table(d) -> dict:
        out = {}
        for (i, j), T in zip(d["ij"], d["T"]):
            G = geo.relative_pose(gt[pos[int(i)]], gt[pos[int(j)]])
            E = geo.inv_T(G) @ T
            out[(int(i), int(j))] = (T, float(np.linalg.norm(E[:3, 3])), pos[int(j)] - pos[int(i)],
                                     float(np.degrees(np.linalg.norm(geo.se3_log(E)[3:]))))
        return out

    ea, eb = table(a), table(b)
    keys = sorted(set(ea) & set(eb))
    for name, keep in (("gap 1", lambda k: ea[k][2] == 1), ("all edges", lambda k: True)):
        ks = [k for k in keys if keep(k)]
        for what, col, scale, unit, fmt, dfmt in (("trans", 1, 1000, "mm", ".3f", ".4f"), ("rot", 3, 1, "deg", ".4f", ".6f")):
            ta = scale * np.array([ea[k][col] for k in ks])
            tb = scale * np.array([eb[k][col] for k in ks])
            d = tb ** 2 - ta ** 2
            se = d.std(ddof=1) / np.sqrt(len(d)) if len(d) > 1 else float("nan")
            print(f"{name}: {len(ks)} edges, {what} RMSE {np.sqrt(np.mean(ta ** 2)):{fmt}} -> {np.sqrt(np.mean(tb ** 2)):{fmt}} "
                  f"{unit}, paired difference of squared errors {d.mean():+{dfmt}} +- {se:{dfmt}} {unit}^2")
    moved = np.array([1000 * np.linalg.norm((geo.inv_T(ea[k][0]) @ eb[k][0])[:3, 3]) for k in keys])
    print(f"labels moved: median {np.median(moved):.4f} mm, max {moved.max():.4f} mm; "
          f"{int((moved > 0).sum())} of {len(keys)} edges; edges in one run only: {len(set(ea) ^ set(eb))}")
    for name, e in (("A", ea), ("B", eb)):
        print(f"{name}: drift of the chained gap-1 edges over {DRIFT_FRAMES} frames {_drift(e, a['ids'], gt)}; "
              f"translation scale against the truth per gap {_scales(e, gt, pos)}; "
              f"rotation scale per gap {_scales(e, gt, pos, rotation=True)}; "
              f"translation error per gap, median / max: {_errors(e)}")


#: frames of the drift figure: one second at 30 fps (redkitchen, TUM, the synthetic rooms)
DRIFT_FRAMES = 30


def _drift(edges: dict, ids, gt) -> str:
    """Over every pair of frames :data:`DRIFT_FRAMES` apart (overlapping: on 100 frames evo's
    RPE, which steps by the gap, would have three pairs), the RMSE of the relative pose error
    of the trajectory chained from the gap-1 edges: the error that accumulates, which the
    per-edge errors do not show."""
    from ctcvo.data.chain import chain_steps
    from ctcvo.data.metrics import relative_pose_error, relative_poses

    keys = [(int(i), int(j)) for i, j in zip(ids[:-1], ids[1:])]
    if any(k not in edges for k in keys) or len(ids) <= DRIFT_FRAMES:
        return "- (a gap-1 edge is missing, or too few frames)"
    est = relative_poses(chain_steps([edges[k][0] for k in keys]), DRIFT_FRAMES)
    err = np.array([relative_pose_error(G, E) for G, E in zip(relative_poses(gt, DRIFT_FRAMES), est)])
    trans, rot = np.sqrt(np.mean(err ** 2, axis=0))
    return f"{1000 * trans:.1f} mm / {rot:.2f} deg"


def _scales(edges: dict, gt, pos: dict, rotation: bool = False) -> str:
    """Per gap, the least-squares scale of the labels' translations against the truth's,
    ``sum(t_est . t_gt) / sum(t_gt . t_gt)``: 1 without a systematic over- or under-scale;
    ``rotation``: the same of their rotation vectors (a rotation under-estimated by a few
    per cent accumulates as drift however small the per-edge errors are)."""
    part = (lambda T: geo.se3_log(T)[3:]) if rotation else (lambda T: T[:3, 3])
    out = []
    for g in sorted({v[2] for v in edges.values()}):
        pairs = [(part(T), part(geo.relative_pose(gt[pos[i]], gt[pos[j]]))) for (i, j), (T, _, gap, _) in edges.items()
                 if gap == g]
        te, tg = (np.array(x) for x in zip(*pairs))
        den = float(np.sum(tg * tg))
        out.append(f"{g}: {float(np.sum(te * tg)) / den:.4f}" if den > 0 else f"{g}: -")  # -: the truth does not move
    return ", ".join(out)


def _errors(edges: dict) -> str:
    """Per gap, the median and the largest translation error of the labels (mm): the RMSE
    of a few hundred edges can be one wrong edge's."""
    out = []
    for g in sorted({v[2] for v in edges.values()}):
        err = 1000 * np.array([e for _, e, gap, _ in edges.values() if gap == g])
        out.append(f"{g}: {np.median(err):.2f} / {err.max():.1f}")
    return ", ".join(out) + " mm"


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("scene", nargs="?", help="a scene as `teacher generate --scene` takes it")
    ap.add_argument("--frames", default="0:100")
    ap.add_argument("--set", nargs="*", default=[], metavar="FIELD=VALUE", help="TeacherConfig overrides")
    ap.add_argument("--sensor", nargs="*", default=[], metavar="FIELD=VALUE",
                    help="synthetic scenes: sensor model overrides (data/synthetic/config.py SensorConfig)")
    ap.add_argument("--sensor-off", action="store_true",
                    help="synthetic scenes: every part of the sensor model off (SENSOR_OFF), then --sensor on top")
    ap.add_argument("--open3d", action="store_true",
                    help="run Open3D's hybrid odometry (bench.teacher's peer) instead of the teacher; gap-1 edges")
    ap.add_argument("--save-edges", metavar="FILE.npz")
    ap.add_argument("--compare", nargs=2, metavar=("A.npz", "B.npz"))
    ap.add_argument("--why", action="store_true", help="per gap, which failure check sent edges to the fallbacks")
    args = ap.parse_args(argv)
    if args.compare:
        compare(*args.compare)
    elif args.scene and args.open3d:
        if args.set or args.why:
            ap.error("--open3d runs Open3D, not the teacher: --set and --why do not apply")
        profile_open3d(args.scene, args.frames, args.save_edges, parse_sensor(args.sensor, args.sensor_off))
    elif args.scene:
        profile(args.scene, args.frames, parse_set(args.set), args.save_edges, args.why,
                parse_sensor(args.sensor, args.sensor_off))
    else:
        ap.error("give a scene, or --compare A.npz B.npz")


if __name__ == "__main__":
    sys.exit(main())
