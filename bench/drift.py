"""Where the trajectories drift: RPE over time scales from one frame to 3 s, on validation ranges.

ATE and the 1 s RPE tell how far the teacher pose graph is from ORB-SLAM3, not at which time
scale it loses. For each validation range (redkitchen 0:450, TUM fr3/teddy 0:200) this
runs, on the same frames in one run, the teacher (its chained gap-1 trajectory and its pose
graph, as bench.teacher runs them), Open3D's hybrid RGB-D odometry and ORB-SLAM3 RGB-D SLAM
(``--orbslam3-runs`` runs, median of each figure). Per method and scale (seconds of
:data:`SCALES_S`, at the median frame step): the translation (mm) and rotation (deg) RPE,
and the rotation's scale, the median ratio of the estimated to the true relative rotation
angle over the pairs at 1 s (1: unbiased; 0.9: 10 % too little rotation). Record
``bench/results/drift.json``.

    python -m bench.drift --orbslam3-vocabulary VOC.txt [--scenes SPEC:START:STOP ...]
"""

from __future__ import annotations

if __name__ == "__main__":  # as `teacher generate` does: its worker imports while this process does
    from ctcvo.teacher import processes

    processes.start()

import argparse  # noqa: E402
import sys  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

from bench import orbslam3_peer, record  # noqa: E402
from bench.orbslam3_peer import METHOD as ORBSLAM3  # noqa: E402
from bench.orbslam3_peer import one_second  # noqa: E402
from bench.teacher import run_open3d, teacher_rows  # noqa: E402
from ctcvo.data import geometry as geo  # noqa: E402
from ctcvo.data.formats import Trajectory  # noqa: E402
from ctcvo.data.metrics import rpe_rmse  # noqa: E402
from ctcvo.data.scenes import open_scene  # noqa: E402
from ctcvo.teacher.config import TeacherConfig  # noqa: E402

VALIDATION = [f"{record.REDKITCHEN}:0:450", f"{record.TUM_TEDDY}:0:200"]
SCALES_S = (0.0, 1 / 3, 1.0, 2.0, 3.0)  # 0: one frame
_MIN_ANGLE_DEG = 0.3  # pairs turning less are left out of the rotation scale (the ratio is noise there)


def rotation_scale(gt: Trajectory, est: Trajectory, delta: int) -> float:
    """Median over the pairs ``delta`` frames apart that turn at least :data:`_MIN_ANGLE_DEG`
    of the estimated relative rotation angle over the true one (NaN: no such pair)."""
    ratios = []
    for k in range(len(gt.poses) - delta):
        true = geo.rotation_angle_deg(geo.inv_T(gt.poses[k]) @ gt.poses[k + delta])
        if true >= _MIN_ANGLE_DEG:
            ratios.append(geo.rotation_angle_deg(geo.inv_T(est.poses[k]) @ est.poses[k + delta]) / true)
    return float(np.median(ratios)) if ratios else float("nan")


def drift_figures(gt: Trajectory, est: Trajectory, second: int) -> dict:
    """RPE at each of :data:`SCALES_S` (``rpe_m`` / ``rpe_deg`` lists, in that order; NaN where
    the range is shorter) and the rotation scale at 1 s."""
    deltas = [max(1, int(round(s * second))) for s in SCALES_S]
    rpe = [rpe_rmse(gt, est, d) if d < len(gt.poses) else (float("nan"), float("nan")) for d in deltas]
    return {"deltas": deltas, "rpe_m": [t for t, _ in rpe], "rpe_deg": [r for _, r in rpe],
            "rotation_scale_1s": rotation_scale(gt, est, deltas[SCALES_S.index(1.0)])}


def orbslam3_figures(seq, vocabulary: Path, runs: int, second: int) -> dict:
    """:func:`drift_figures` of ``runs`` ORB-SLAM3 SLAM runs, median of each over the runs,
    each run over the frames it tracked (as bench.orbslam3_peer counts them)."""
    def figures(seq, result):
        gt, est, _ = orbslam3_peer.tracked(seq, result)
        return drift_figures(gt, est, second) if len(est.poses) >= 2 else None

    per_run = orbslam3_peer.each_run(seq, vocabulary, runs, figures)
    if not per_run:
        return {"runs": 0}
    med = {key: np.nanmedian([r[key] for r in per_run], axis=0).tolist() for key in ("rpe_m", "rpe_deg")}
    return {"deltas": per_run[0]["deltas"], **med, "runs": len(per_run),
            "rotation_scale_1s": float(np.nanmedian([r["rotation_scale_1s"] for r in per_run]))}


def bench_range(spec: str, vocabulary: Path | None, runs: int) -> list[dict]:
    """The rows of one range ``SPEC:START:STOP``: chain, teacher graph, Open3D, ORB-SLAM3."""
    scene, a, b = spec.rsplit(":", 2)
    seq = open_scene(scene, frames=f"{a}:{b}")[0]
    gt, second = Trajectory(seq.times(), seq.groundtruth()), one_second(seq.times())
    rows = [(r["method"], r["poses"]) for r in teacher_rows(seq, runs=1)]
    rows.append(("Open3D hybrid (gap 1)", run_open3d(seq)[0]))
    out = [{"range": spec, "method": m, **drift_figures(gt, Trajectory(seq.times(), p), second)} for m, p in rows]
    if vocabulary is not None:
        out.append({"range": spec, "method": ORBSLAM3, **orbslam3_figures(seq, vocabulary, runs, second)})
    for r in out:
        print(f"{spec}: {r}", file=sys.stderr, flush=True)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scenes", nargs="+", default=VALIDATION, help="SPEC:START:STOP of validation ranges")
    orbslam3_peer.add_arguments(ap, "rows")
    record.add_arguments(ap, "drift")
    args = ap.parse_args()
    orbslam3_peer.check_arguments(ap, args)
    rec = record.from_args(args, teacher=TeacherConfig(), scales_s=list(SCALES_S))
    rows: list[dict] = []
    for spec in args.scenes:
        rows += bench_range(spec, args.orbslam3_vocabulary, args.orbslam3_runs)
        rec.finish({"rows": rows})  # after every range: a run cut short keeps what it measured


if __name__ == "__main__":
    main()
