"""Per-pair gap-1 errors of this teacher vs cv2.Odometry on redkitchen: which pairs both
methods get wrong (ground-truth / timing glitches) and which only the teacher does.

    .venv/bin/python -m bench.teacher_pairs [--scene PATH] [--threshold-mm 15]
"""

from __future__ import annotations

import argparse

import numpy as np

from bench import teacher as bench_teacher
from ctcvo.data import geometry as geo
from ctcvo.data.metrics import relative_pose_error
from ctcvo.data.scenes import open_scene
from ctcvo.teacher.config import TeacherConfig
from ctcvo.teacher.generate import run_sequence


def gap1_errors_mm(gt: np.ndarray, poses: np.ndarray) -> np.ndarray:
    """Translation error (mm) of every consecutive relative pose against ground truth."""
    return np.array([1000 * relative_pose_error(geo.relative_pose(gt[k], gt[k + 1]),
                                                geo.relative_pose(poses[k], poses[k + 1]))[0]
                     for k in range(len(gt) - 1)])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scene", default=str(bench_teacher.REDKITCHEN))
    ap.add_argument("--threshold-mm", type=float, default=15.0)
    args = ap.parse_args()
    seq = open_scene(args.scene)[0]
    gt = seq.groundtruth()
    ours = gap1_errors_mm(gt, run_sequence(seq, TeacherConfig(gaps=1), progress=False).poses)
    cv = gap1_errors_mm(gt, bench_teacher.run_opencv(seq)[0])
    rms = lambda x: float(np.sqrt(np.mean(x ** 2)))  # noqa: E731
    print(f"RMSE  ours {rms(ours):.2f} mm  cv2 {rms(cv):.2f} mm")
    print(f"median ours {np.median(ours):.2f} mm  cv2 {np.median(cv):.2f} mm")
    both = (ours > args.threshold_mm) & (cv > args.threshold_mm)
    ids = seq.ids()
    print(f"pairs > {args.threshold_mm:g} mm for both: {[int(ids[k]) for k in np.flatnonzero(both)]}")
    print(f"without them: ours {rms(ours[~both]):.2f} mm  cv2 {rms(cv[~both]):.2f} mm")
    worst = np.argsort(-ours)[:10]
    print("ours worst (first frame id, ours mm, cv2 mm):",
          [(int(ids[k]), round(float(ours[k]), 1), round(float(cv[k]), 1)) for k in worst])


if __name__ == "__main__":
    main()
