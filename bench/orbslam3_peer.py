"""ORB-SLAM3 RGB-D as the peer of bench.teacher: N SLAM runs of one sequence, median and spread.

ORB-SLAM3 is multithreaded and its runs differ, so each sequence is tracked ``runs`` times
(:func:`ctcvo.teacher.orbslam3.run_orbslam3`, SLAM mode, the vocabulary given) and each
metric is reported as the median over the runs with its min-max spread. The trajectory is
the keyframe-refined one ORB-SLAM3 saves at shutdown (the backend's default labels) of the
frames it tracked ``OK``; a frame it lost (not initialised, lost, or missing from the saved
trajectory) is counted per run and left out of that run's metrics (an RPE pair may then
span more than its delta). fps counts the whole run (vocabulary load and shutdown included,
not the start of the process each run has);
``tracking_fps`` the tracking calls only.

Metrics (:func:`metrics`, also used for bench.teacher's other rows): ATE after SE(3)
alignment, RPE at 1 frame and at 1 s (the frames of one second at the median frame step),
the paper's se(3) L2, all through :mod:`ctcvo.data.metrics` (evo).
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

from ctcvo.data.formats import Trajectory
from ctcvo.data.metrics import rpe_rmse, trajectory_report
from ctcvo.teacher.orbslam3 import DEFAULT_LABELS, run_orbslam3

METHOD = "ORB-SLAM3 SLAM (keyframe-refined)"
#: the figures aggregated over runs (median and min-max)
AGGREGATED = ("fps", "tracking_fps", "ate_rmse_m", "rpe_trans_rmse_m", "rpe_rot_rmse_deg", "rpe_1s_trans_m",
              "rpe_1s_rot_deg", "se3_l2_mean")


def one_second(times: np.ndarray) -> int:
    """Frames in one second at the median frame step (at least 1)."""
    steps = np.diff(np.asarray(times, dtype=np.float64))
    steps = steps[steps > 0]
    return max(1, int(round(1.0 / float(np.median(steps))))) if len(steps) else 1


def metrics(gt: Trajectory, est: Trajectory, second: int) -> dict[str, float]:
    """ATE, gap-1 RPE, se(3) L2 (:func:`trajectory_report`) and RPE at ``second`` frames."""
    t, r = rpe_rmse(gt, est, second)
    return {**trajectory_report(gt, est), "rpe_1s_trans_m": t, "rpe_1s_rot_deg": r, "rpe_1s_frames": second}


def run_figures(seq, result) -> dict:
    """One run's figures: :func:`metrics` over the frames it tracked, its lost frames and fps."""
    gt, est, lost = tracked(seq, result)
    out = {"lost_frames": lost, "fps": result.fps,
           "tracking_fps": len(result.ok) / result.track_seconds if result.track_seconds > 0 else float("nan"),
           "map_changes": int(result.map_changed.sum())}
    if len(est.poses) >= 2:
        out.update(metrics(gt, est, one_second(seq.times())))
    return out


def aggregate(runs: list[dict]) -> dict:
    """Median over ``runs`` of each of :data:`AGGREGATED` (NaN where no run has it), its
    ``spread`` [min, max], every run's lost frames (``lost_frames_per_run``) and their maximum
    (``lost_frames``), and the runs themselves."""
    if not runs:
        raise ValueError("no ORB-SLAM3 run to aggregate")
    out: dict = {"runs": len(runs), "spread": {}}
    for key in AGGREGATED:
        vals = np.array([r[key] for r in runs if r.get(key) is not None and np.isfinite(r[key])], dtype=np.float64)
        out[key] = float(np.median(vals)) if len(vals) else float("nan")
        out["spread"][key] = [float(vals.min()), float(vals.max())] if len(vals) else [float("nan")] * 2
        out["spread"][key + "_runs"] = int(len(vals))
    lost = [int(r["lost_frames"]) for r in runs]
    out["lost_frames_per_run"] = lost
    out["lost_frames"] = max(lost)
    out["per_run"] = runs
    return out


def add_arguments(ap, what: str) -> None:
    """``--orbslam3-vocabulary`` (adds ORB-SLAM3's ``what``) and ``--orbslam3-runs``."""
    ap.add_argument("--orbslam3-vocabulary", type=Path, default=None,
                    help=f"a DBoW2 vocabulary (ctcvo teacher vocabulary, from training frames): adds ORB-SLAM3's {what}")
    ap.add_argument("--orbslam3-runs", type=int, default=3,
                    help="ORB-SLAM3 SLAM runs per sequence (median and min-max reported)")


def check_arguments(ap, args) -> None:
    """Stop with argparse's one-line error on a bad ``--orbslam3-*`` value."""
    if args.orbslam3_runs < 1:
        ap.error(f"--orbslam3-runs must be >= 1, got {args.orbslam3_runs}")
    if args.orbslam3_vocabulary is not None and not args.orbslam3_vocabulary.is_file():
        ap.error(f"--orbslam3-vocabulary {args.orbslam3_vocabulary}: no such file")


def tracked(seq, result) -> tuple[Trajectory, Trajectory, int]:
    """Ground truth and ORB-SLAM3's trajectory over the frames one run tracked, and the
    frames it lost."""
    poses = result.poses(DEFAULT_LABELS)
    have = result.ok & np.isfinite(poses).all(axis=(1, 2))
    times, gt = seq.times(), seq.groundtruth()
    return Trajectory(times[have], gt[have]), Trajectory(times[have], poses[have]), int(len(have) - have.sum())


def each_run(seq, vocabulary: Path, runs: int, figures) -> list[dict]:
    """``figures(seq, result)`` of ``runs`` ORB-SLAM3 SLAM runs over ``seq``, one after the
    other (a run whose figures are None is left out)."""
    out = []
    for k in range(runs):
        figs = figures(seq, run_orbslam3(seq, Path(vocabulary), mode="slam"))
        print(f"{seq.name}: ORB-SLAM3 run {k + 1}/{runs}: {figs}", file=sys.stderr, flush=True)
        if figs is not None:
            out.append(figs)
    return out


def orbslam3_row(seq, vocabulary: Path, runs: int) -> dict:
    """:func:`aggregate` of ``runs`` ORB-SLAM3 SLAM runs over ``seq``."""
    return {"method": METHOD, **aggregate(each_run(seq, vocabulary, runs, run_figures))}
