"""Trajectory metrics. ATE and RPE come from evo; only the paper's se(3) L2 error, which
evo lacks, is computed here.

All functions take two :class:`~data.formats.Trajectory` objects whose poses are
``T_world_cam`` at the *same* timestamps (the project writes trajectories frame by frame,
so no association is needed; :func:`associate` handles foreign files).
"""

from __future__ import annotations

import copy
from collections.abc import Iterable

import numpy as np
from numpy.typing import NDArray

from ctcvo.data import geometry as geo
from ctcvo.data.chain import chain_steps
from ctcvo.data.errors import VOError
from ctcvo.data.formats import Trajectory


def associate(gt: Trajectory, est: Trajectory, max_diff: float = 0.01) -> tuple[Trajectory, Trajectory]:
    """Match poses by timestamp with evo (``max_diff`` seconds)."""
    from evo.core import sync

    try:
        r, e = sync.associate_trajectories(gt.to_evo(), est.to_evo(), max_diff=max_diff)
    except sync.SyncException as exc:
        raise VOError(f"cannot associate trajectories: {exc}") from None
    return Trajectory.from_evo(r), Trajectory.from_evo(e)


def _check(gt: Trajectory, est: Trajectory) -> None:
    if len(gt) != len(est):
        raise VOError(f"trajectories differ in length ({len(gt)} vs {len(est)}); associate them first")
    if len(gt) < 2:
        raise VOError("need at least two poses to evaluate a trajectory")


def _aligned_rmse(ref_xyz: NDArray[np.float64], est_xyz: NDArray[np.float64]) -> float:
    """RMS distance of (N, 3) ``ref_xyz`` to ``R est_xyz + t`` for the best rotation and
    translation (Umeyama, no scale, as evo). Also defined where evo refuses to align: an
    estimate whose positions are all equal or collinear (any optimal ``R`` gives the same
    value)."""
    mx, my = est_xyz.mean(axis=0), ref_xyz.mean(axis=0)
    U, _, Vt = np.linalg.svd((ref_xyz - my).T @ (est_xyz - mx) / len(ref_xyz))
    S = np.diag([1.0, 1.0, np.sign(np.linalg.det(U) * np.linalg.det(Vt)) or 1.0])
    R = U @ S @ Vt
    err = ref_xyz - (est_xyz @ R.T + (my - R @ mx))
    return float(np.sqrt(np.mean(np.sum(err**2, axis=1))))


def ate_rmse(gt: Trajectory, est: Trajectory) -> float:
    """ATE RMSE in metres after SE(3) Umeyama alignment without scale (evo APE). Where evo
    cannot align (the estimate's positions are all equal or collinear, e.g. the zero-motion
    baseline) the same alignment is solved here (:func:`_aligned_rmse`)."""
    from evo.core import metrics
    from evo.core.geometry import GeometryException

    _check(gt, est)
    ref, e = gt.to_evo(), est.to_evo()
    e = copy.deepcopy(e)
    try:
        e.align(ref, correct_scale=False)
    except GeometryException:
        return _aligned_rmse(np.asarray(gt.poses)[:, :3, 3], np.asarray(est.poses)[:, :3, 3])
    ape = metrics.APE(metrics.PoseRelation.translation_part)
    ape.process_data((ref, e))
    return float(ape.get_statistic(metrics.StatisticsType.rmse))


def rpe_rmse(gt: Trajectory, est: Trajectory, delta: int = 1) -> tuple[float, float]:
    """RPE RMSE (translation metres, rotation degrees) over every frame pair ``delta`` apart
    (evo's ``all_pairs``, as TUM's ``evaluate_rpe.py`` pairs them). evo's default takes only
    the pairs (0, delta), (delta, 2 delta), ...: a 1 s RPE over 150 frames of 30 Hz would
    rest on 5 pairs. At ``delta`` 1 both are the same."""
    from evo.core import metrics

    _check(gt, est)
    if delta >= len(gt):
        return float("nan"), float("nan")
    ref, e = gt.to_evo(), est.to_evo()
    out = []
    for rel in (metrics.PoseRelation.translation_part, metrics.PoseRelation.rotation_angle_deg):
        rpe = metrics.RPE(rel, delta=delta, delta_unit=metrics.Unit.frames, all_pairs=True)
        rpe.process_data((ref, e))
        out.append(float(rpe.get_statistic(metrics.StatisticsType.rmse)))
    return out[0], out[1]


def relative_pose_error(T_ref_rel: NDArray[np.float64], T_est_rel: NDArray[np.float64]) -> tuple[float, float]:
    """Error of an estimated relative pose against the reference one: (translation m,
    rotation deg) of ``inv(T_ref_rel) @ T_est_rel`` (what evo's RPE measures per pair)."""
    d = geo.inv_T(T_ref_rel) @ np.asarray(T_est_rel, dtype=np.float64)
    return float(np.linalg.norm(d[:3, 3])), geo.rotation_angle_deg(d)


def label_errors_by_gap(edges: Iterable[tuple[int, int, NDArray[np.float64]]], gt: NDArray[np.float64],
                        ids: NDArray[np.int64]) -> dict[str, dict[str, float]]:
    """RMS error per gap of relative-pose labels ``(i, j, T_i_j)`` (frame ids) against the
    ground truth ``gt`` (N, 4, 4) of the frames ``ids``: ``{"g": {edges, trans_rmse_m,
    rot_rmse_deg}}``, the gap counted in frames of the sequence."""
    pos = {int(f): p for p, f in enumerate(ids)}
    by_gap: dict[int, list[tuple[float, float]]] = {}
    for i, j, T in edges:
        a, b = pos[i], pos[j]
        by_gap.setdefault(b - a, []).append(relative_pose_error(geo.relative_pose(gt[a], gt[b]), T))
    out = {}
    for g, errs in sorted(by_gap.items()):
        e = np.array(errs)
        out[str(g)] = {"edges": len(e), "trans_rmse_m": float(np.sqrt(np.mean(e[:, 0] ** 2))),
                       "rot_rmse_deg": float(np.sqrt(np.mean(e[:, 1] ** 2)))}
    return out


def groundtruth_residuals(edges: Iterable, gt: NDArray[np.float64], ids: NDArray[np.int64]) -> NDArray[np.float64]:
    """(E, 6) error ``log(inv(T_i_j) @ T_gt_i_j)`` of each edge (anything with ``i``, ``j``
    frame ids and ``T_i_j``) against the ground truth ``gt`` (N, 4, 4) of the frames ``ids``:
    project order (v, w), a right perturbation at the edge, as its covariance is meant."""
    pos = {int(f): p for p, f in enumerate(ids)}
    d = [geo.se3_log(geo.inv_T(e.T_i_j) @ geo.relative_pose(gt[pos[e.i]], gt[pos[e.j]])) for e in edges]
    return np.array(d, dtype=np.float64).reshape(-1, 6)


def se3_l2_errors(gt_rel: NDArray[np.float64], est_rel: NDArray[np.float64]) -> NDArray[np.float64]:
    """The paper's local metric per pair: ``||log(T_gt_rel) - log(T_est_rel)||_2`` with
    ``log`` in the project se(3) order (v, w). Inputs are (N, 4, 4) relative poses."""
    gt_rel = np.asarray(gt_rel, dtype=np.float64).reshape(-1, 4, 4)
    est_rel = np.asarray(est_rel, dtype=np.float64).reshape(-1, 4, 4)
    return np.linalg.norm(geo.se3_log(gt_rel) - geo.se3_log(est_rel), axis=1)


def relative_poses(poses: NDArray[np.float64], delta: int = 1) -> NDArray[np.float64]:
    """``T_k_{k+delta}`` for every k of an (N, 4, 4) ``T_world_cam`` array."""
    return np.array([geo.relative_pose(poses[k], poses[k + delta])
                     for k in range(len(poses) - delta)]).reshape(-1, 4, 4)


def trajectory_report(gt: Trajectory, est: Trajectory) -> dict[str, float]:
    """The metric keys every stage's ``report.json`` carries (see docs/formats.md)."""
    t, r = rpe_rmse(gt, est, 1)
    return {
        "ate_rmse_m": ate_rmse(gt, est),
        "rpe_trans_rmse_m": t,
        "rpe_rot_rmse_deg": r,
        "se3_l2_mean": float(np.mean(se3_l2_errors(relative_poses(gt.poses), relative_poses(est.poses)))),
    }


#: names of the trivial baselines every learned figure is shown beside
BASELINES = ("zero motion", "constant velocity")
#: the JSON key of each baseline's row (``report.json`` ``rows``, ``ablation.json`` ``results``)
BASELINE_KEYS = {name: name.replace(" ", "_") for name in BASELINES}


def zero_motion_poses(gt_poses: NDArray[np.float64]) -> NDArray[np.float64]:
    """A camera that never moves: every pose is the first ground-truth pose, (N, 4, 4)."""
    gt_poses = np.asarray(gt_poses, dtype=np.float64)
    return np.repeat(gt_poses[:1], len(gt_poses), axis=0)


def constant_velocity_poses(gt_poses: NDArray[np.float64]) -> NDArray[np.float64]:
    """A constant-velocity motion model fed the true previous motion: step k -> k+1 repeats
    the ground-truth step k-1 -> k (the first step is zero motion), chained from the first
    pose, (N, 4, 4). Its relative error is what a predictor with a one-frame lag scores."""
    gt_poses = np.asarray(gt_poses, dtype=np.float64)
    steps = [np.eye(4)] + [geo.relative_pose(gt_poses[k - 1], gt_poses[k]) for k in range(1, len(gt_poses) - 1)]
    return chain_steps(steps[: len(gt_poses) - 1], gt_poses[0])


def baseline_trajectories(gt: Trajectory) -> dict[str, Trajectory]:
    """The trivial baselines (:data:`BASELINES`) as trajectories at the ground truth's times."""
    return {"zero motion": Trajectory(gt.timestamps, zero_motion_poses(gt.poses)),
            "constant velocity": Trajectory(gt.timestamps, constant_velocity_poses(gt.poses))}


def baseline_reports(gt: Trajectory) -> dict[str, dict[str, float]]:
    """:func:`trajectory_report` of each trivial baseline against ``gt``."""
    return {name: trajectory_report(gt, traj) for name, traj in baseline_trajectories(gt).items()}
