"""``learner calibrate``: post-hoc covariance calibration against teacher labels, no ground truth.

MC-dropout spreads rank the learner's errors well but are far smaller than them (coverage 0
in the ablation, bench/README.md). On a *validation* scene (never a training or test one)
this module compares the MC-dropout edges with the teacher's good edges of the same pairs
and fits, per edge group (head and gap, see :class:`~learner.config.CalibrationConfig`) and
se(3) dimension d, the model

    r_d ~ N(0, a_d c_dd + b_d + t_dd),   r = log(inv(exp(mean)) @ T_teacher)   (6,) in (v, w)

where ``c`` is the MC-dropout covariance, ``t`` the teacher's edge covariance (optional) and
``a_d, b_d >= 0``: variance scaling (Levi et al. 2019, "sigma scaling", here one factor per
dimension) extended by a floor ``b`` for the error the dropout does not see. The fit is
maximum Gaussian likelihood, with pairs beyond ``trim_z`` calibrated sigmas left out and
re-estimated until stable (gross failures must not inflate every covariance). The
calibrated covariance of an edge is

    C' = D C D + diag(b),   D = diag(sqrt(a))

which keeps the MC correlations, is PSD when ``C`` is and positive definite as ``b > 0``.
The teacher's covariance only explains part of the residual during the fit; it is never
added to the learner's edges.

The result is written atomically as ``calibration.json`` beside the checkpoint
(docs/formats.md, "Learner"); ``learner predict`` applies it when present. The file records
the fingerprint of its inputs (checkpoint, validation sequences and frames, teacher labels,
settings): a rerun of the same inputs keeps it, other inputs replace it only with
``overwrite`` (the rerun rule of :mod:`data.runs`).
"""

from __future__ import annotations

import hashlib
import json
import logging
import sys
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy.optimize import minimize
from scipy.stats import chi2

from ctcvo.data import geometry as geo
from ctcvo.data.errors import ConfigError, DataError, FormatError
from ctcvo.data.formats import read_g2o
from ctcvo.data.io import git_revision, read_json_file, write_json
from ctcvo.data.runs import Fingerprint, claim, file_digest, frames_id, scene_id, upstream_digest
from ctcvo.data.scenes import open_scene
from ctcvo.data.sequence import frame_ranges_overlap
from ctcvo.data.uncertainty import mahalanobis2, nees_stats
from ctcvo.learner.checkpoint import load_model
from ctcvo.learner.config import CalibrationConfig, PredictConfig, check_variant, to_dict
from ctcvo.learner.dataset import find_teacher_edges, load_frames
from ctcvo.learner.mcdropout import COV_FLOOR, mc_edges
from ctcvo.learner.model import CTCNet

log = logging.getLogger(__name__)

CALIBRATION_FILE = "calibration.json"
CALIBRATION_FORMAT = 1
#: median of chi-square with 1 dof (robust start of the scale)
_CHI2_1_MEDIAN = float(chi2.ppf(0.5, 1))

# NEES and coverage (mahalanobis2, nees_stats, the chi-square bounds) come from
# data.uncertainty, the one implementation the pose graph's report uses too; imported above
# under their old names for learner.predict and the tests.


# ----------------------------------------------------------------------------------
# the fit (pure numpy)
# ----------------------------------------------------------------------------------
def _ml_fit(c: NDArray, r2: NDArray, t: NDArray, a0: float, b0: float, min_var: float,
            fit_floor: bool = True) -> tuple[float, float]:
    """Maximum-likelihood ``(a, b)`` of ``r2 ~ (a c + b + t) chi2_1`` with ``a >= 0, b >= min_var``
    (``b = min_var`` when not ``fit_floor``)."""
    sa = max(float(np.median(r2)) / max(float(np.median(c)), 1e-300), 1e-300)  # parameters of order 1
    sb = max(float(np.median(r2)), min_var)

    def nll(x: NDArray) -> tuple[float, NDArray]:
        v = x[0] * sa * c + x[1] * sb + t
        w = 1.0 / v - r2 / (v * v)  # d(log v + r2 / v) / dv
        return 0.5 * float(np.mean(np.log(v) + r2 / v)), 0.5 * np.array([np.mean(w * c) * sa, np.mean(w) * sb])

    x0 = np.array([a0 / sa, max(b0, min_var) / sb])
    if not fit_floor:
        x0[1] = min_var / sb
    res = minimize(nll, x0, jac=True, method="L-BFGS-B",
                   bounds=[(0.0, None), (min_var / sb, None if fit_floor else min_var / sb)])
    return float(res.x[0] * sa), float(res.x[1] * sb)


def fit_variance_model(c: NDArray[np.float64], r2: NDArray[np.float64], t: NDArray[np.float64] | None = None,
                       config: CalibrationConfig = CalibrationConfig()) -> tuple[float, float, NDArray[np.bool_]]:
    """Robust maximum-likelihood fit of ``r2_e ~ (a c_e + b + t_e) chi2_1`` for one dimension.

    ``c`` (n,) MC-dropout variances, ``r2`` (n,) squared residuals, ``t`` (n,) known extra
    variances (the teacher's) or ``None``. Returns ``(a, b, kept)``: ``a >= 0``,
    ``b >= config.min_variance``, and the mask (n,) of pairs within ``trim_z`` calibrated
    sigmas that the final fit used. Starts from the scale alone estimated from the median
    (robust to gross outliers), then alternates fitting and trimming.
    """
    c = np.asarray(c, dtype=np.float64)
    r2 = np.asarray(r2, dtype=np.float64)
    t = np.zeros_like(c) if t is None else np.asarray(t, dtype=np.float64)
    if len(c) < 3 or c.shape != r2.shape or c.shape != t.shape:
        raise ValueError(f"need >= 3 matching (c, r2, t), got {c.shape}, {r2.shape}, {t.shape}")
    if np.any(c <= 0) or np.any(t < 0) or not np.all(np.isfinite(r2)):
        raise ValueError("variances must be positive (teacher: non-negative) and residuals finite")
    a = float(np.median(r2 / c)) / _CHI2_1_MEDIAN
    b = config.min_variance
    lim = config.trim_z ** 2
    keep = r2 <= lim * (a * c + b + t)
    for _ in range(config.max_iterations):
        if keep.sum() < 3:
            keep = np.ones_like(keep)
        a, b = _ml_fit(c[keep], r2[keep], t[keep], a, b, config.min_variance, config.fit_floor)
        new = r2 <= lim * (a * c + b + t)
        if np.array_equal(new, keep):
            break
        keep = new
    return a, b, keep


@dataclass(frozen=True)
class GroupFit:
    """Calibration of one edge group: ``head`` (``lstm``/``direct``, ``None`` = every
    head) and ``gap`` (``None`` = every gap), ``pairs`` used, per-dimension ``a`` and ``b``
    (6,) in (v, w) order, and ``trimmed`` (6,) pairs left out per dimension."""

    head: str | None
    gap: int | None
    pairs: int
    a: tuple[float, ...]
    b: tuple[float, ...]
    trimmed: tuple[int, ...] = (0, 0, 0, 0, 0, 0)

    def apply(self, cov: NDArray[np.float64]) -> NDArray[np.float64]:
        """``D C D + diag(b)`` of covariances (E, 6, 6)."""
        s = np.sqrt(np.asarray(self.a))
        return s[:, None] * np.asarray(cov) * s[None, :] + np.diag(self.b)

    def to_dict(self) -> dict[str, Any]:
        return {"head": self.head, "gap": self.gap, "pairs": self.pairs, "a": list(self.a), "b": list(self.b),
                "trimmed": list(self.trimmed)}


def fit_group(cov: NDArray[np.float64], r: NDArray[np.float64], teacher_cov: NDArray[np.float64] | None,
              head: str | None, gap: int | None, config: CalibrationConfig = CalibrationConfig()) -> GroupFit:
    """Per-dimension fit of one group: MC covariances (n, 6, 6), residuals (n, 6),
    teacher covariances (n, 6, 6) or ``None``."""
    c = np.diagonal(cov, axis1=1, axis2=2)
    t = None if teacher_cov is None else np.clip(np.diagonal(teacher_cov, axis1=1, axis2=2), 0.0, None)
    a, b, trimmed = [], [], []
    for d in range(6):
        ad, bd, kept = fit_variance_model(c[:, d], r[:, d] ** 2, None if t is None else t[:, d], config)
        a.append(ad)
        b.append(bd)
        trimmed.append(int((~kept).sum()))
    return GroupFit(head, gap, len(r), tuple(a), tuple(b), tuple(trimmed))


def fit_groups(cov: NDArray[np.float64], r: NDArray[np.float64], heads: Sequence[str], gaps: NDArray[np.int64],
               teacher_cov: NDArray[np.float64] | None = None,
               config: CalibrationConfig = CalibrationConfig()) -> list[GroupFit]:
    """Fits of every (head, gap) group with ``config.min_pairs`` pairs, of every head
    (all its gaps) with that many, and of all pairs (the last fallback, always present)."""
    heads = np.asarray(heads)
    gaps = np.asarray(gaps)
    if len(r) < config.min_pairs:
        raise DataError(f"only {len(r)} validation pairs with teacher labels; calibration needs at least "
                        f"{config.min_pairs} (a longer --frames range or another validation scene)")

    def one(m: NDArray[np.bool_], head: str | None, gap: int | None) -> GroupFit:
        return fit_group(cov[m], r[m], None if teacher_cov is None else teacher_cov[m], head, gap, config)

    out = []
    for h in sorted(set(heads.tolist())):
        for g in sorted(set(gaps[heads == h].tolist())):
            m = (heads == h) & (gaps == g)
            if m.sum() >= config.min_pairs:
                out.append(one(m, h, int(g)))
        if (heads == h).sum() >= config.min_pairs:
            out.append(one(heads == h, h, None))
    out.append(one(np.ones(len(r), dtype=bool), None, None))
    return out


# ----------------------------------------------------------------------------------
# calibration.json
# ----------------------------------------------------------------------------------
@dataclass
class Calibration:
    """Fitted groups plus what they were fitted for (``info``: the JSON's other keys)."""

    groups: list[GroupFit]
    info: dict[str, Any] = field(default_factory=dict)

    def lookup(self, head: str, gap: int) -> GroupFit:
        """The group of an edge: its own (head, gap), else its head's, else every pair's."""
        by = {(g.head, g.gap): g for g in self.groups}
        for key in ((head, gap), (head, None), (None, None)):
            if key in by:
                return by[key]
        raise FormatError("calibration has no fit for every pair (head null, gap null)")

    def apply(self, cov: NDArray[np.float64], heads: Sequence[str], gaps: NDArray[np.int64]) -> NDArray[np.float64]:
        """Calibrated covariances (E, 6, 6) of MC covariances (E, 6, 6) with their heads and gaps (E,)."""
        heads = np.asarray(heads)
        gaps = np.asarray(gaps)
        out = np.array(cov, dtype=np.float64, copy=True)
        for h, g in sorted(set(zip(heads.tolist(), gaps.tolist()))):
            m = (heads == h) & (gaps == g)
            fit = self.lookup(h, int(g))
            if fit.gap != g or fit.head != h:
                log.debug("edges %s gap %d: calibration of head %s gap %s", h, g, fit.head, fit.gap)
            out[m] = fit.apply(cov[m])
        return out

    def to_dict(self) -> dict[str, Any]:
        return {"format": CALIBRATION_FORMAT, **self.info, "groups": [g.to_dict() for g in self.groups]}


def read_calibration(path: Path) -> Calibration:
    """Read and validate a ``calibration.json``; :class:`FormatError` says what is wrong."""
    path = Path(path)
    d = read_json_file(path, "learner calibration", CALIBRATION_FORMAT, "groups", list)
    groups = []
    for k, g in enumerate(d["groups"]):
        try:
            a, b = [float(x) for x in g["a"]], [float(x) for x in g["b"]]
            fit = GroupFit(g["head"], None if g["gap"] is None else int(g["gap"]), int(g["pairs"]), tuple(a), tuple(b),
                           tuple(int(x) for x in g.get("trimmed", [0] * 6)))
        except (KeyError, TypeError, ValueError) as exc:
            raise FormatError(f"{path}: group {k} is malformed ({exc})") from None
        if len(a) != 6 or len(b) != 6 or not all(np.isfinite(a + b)) or min(a) < 0 or min(b) <= 0:
            raise FormatError(f"{path}: group {k} needs 6 finite a >= 0 and 6 finite b > 0")
        groups.append(fit)
    if not any(g.head is None and g.gap is None for g in groups):
        raise FormatError(f"{path}: no group for every pair (head null, gap null)")
    info = {k: v for k, v in d.items() if k not in ("format", "groups")}
    return Calibration(groups, info)


def file_sha1(path: Path) -> str:
    h = hashlib.sha1()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def calibration_for(checkpoint: Path, config: PredictConfig) -> tuple[Path, Calibration] | None:
    """The ``calibration.json`` beside ``checkpoint`` if there is one, checked against it.

    A calibration fitted for other weights (the checkpoint trained on since) or another
    MC-dropout ratio is an error (re-run ``learner calibrate`` or pass ``--no-calibration``);
    another sample count only warns (the variance estimate is unbiased for any K)."""
    path = Path(checkpoint).parent / CALIBRATION_FILE
    if not path.is_file():
        return None
    cal = read_calibration(path)
    fix = f"run `learner calibrate --checkpoint {checkpoint} --scene VAL` again or pass --no-calibration"
    if cal.info.get("checkpoint_sha1") != file_sha1(Path(checkpoint)):
        raise ConfigError(f"{path} was fitted for other weights than {checkpoint} (epoch "
                          f"{cal.info.get('checkpoint_epoch')}); {fix}")
    if cal.info.get("drop") != config.drop:
        raise ConfigError(f"{path} was fitted with MC-dropout ratio {cal.info.get('drop')}, not {config.drop}; "
                          f"pass --drop {cal.info.get('drop')} or {fix}")
    if cal.info.get("samples") != config.samples:
        log.warning("%s was fitted with %s MC samples, predicting with %d", path, cal.info.get("samples"),
                    config.samples)
    return path, cal


# ----------------------------------------------------------------------------------
# residuals against the teacher
# ----------------------------------------------------------------------------------
def teacher_matches(i: NDArray[np.int64], j: NDArray[np.int64], ids: NDArray[np.int64],
                    g2o: Path) -> tuple[NDArray[np.int64], NDArray[np.float64], NDArray[np.float64]]:
    """Edges (positions ``i < j`` (E,) into frames ``ids``) that the teacher's ``edges.g2o``
    also has: indices (m,) into the edges, teacher ``T_i_j`` (m, 4, 4) and covariances (m, 6, 6)."""
    teacher, _ = read_g2o(g2o)
    pos = {int(f): k for k, f in enumerate(ids)}
    where = {(int(a), int(b)): e for e, (a, b) in enumerate(zip(i, j))}
    idx, T, C = [], [], []
    for t in teacher:
        e = where.get((pos.get(t.i, -1), pos.get(t.j, -1)))
        if e is not None:
            idx.append(e)
            T.append(t.T_i_j)
            C.append(t.cov)
    return np.array(idx, dtype=np.int64), np.array(T).reshape(-1, 4, 4), np.array(C).reshape(-1, 6, 6)


def residuals(mean: NDArray[np.float64], T_ref: NDArray[np.float64]) -> NDArray[np.float64]:
    """``log(inv(exp(mean)) @ T_ref)`` (E, 6): the reference in the tangent space at the
    estimate, (v, w) order (the edge covariances' right perturbation)."""
    return np.array([geo.se3_log(geo.inv_T(geo.se3_exp(m)) @ T) for m, T in zip(mean, T_ref)]).reshape(-1, 6)


def constant_velocity_l2(i: NDArray[np.int64], j: NDArray[np.int64], log_t: NDArray[np.float64]) -> NDArray[np.float64]:
    """(E,) se(3) L2 distance of a constant-velocity guess to the teacher's label of each
    pair ``(i, j)`` (positions): ``(j - i)`` times the teacher's previous step ``i-1 -> i``
    (the bridge the teacher itself uses over failed edges); NaN where that step has no label."""
    step = {int(a): log_t[n] for n, (a, b) in enumerate(zip(i, j)) if b - a == 1}
    out = np.full(len(i), np.nan)
    for n, (a, b) in enumerate(zip(i, j)):
        prev = step.get(int(a) - 1)
        if prev is not None:
            out[n] = float(np.linalg.norm(log_t[n] - (b - a) * prev))
    return out


def skill_figures(l2: NDArray[np.float64], l2_zero: NDArray[np.float64], gaps: NDArray[np.int64],
                  l2_cv: NDArray[np.float64] | None = None) -> dict[str, Any]:
    """``validation.skill`` of calibration.json: the mean se(3) L2 distance (E,) of the
    learner's edges to the teacher's labels and of zero motion (the identity) to them, their
    ratio (below 1: the learner predicts the labels better than a camera that never moves),
    overall and per gap; with ``l2_cv`` (E,) also ``ratio_cv`` against the constant-velocity
    guess of :func:`constant_velocity_l2` (on the pairs that have it). The pose graph weighs
    a learner with ``ratio >= 1`` as nothing, and lets it bridge a failed teacher stretch
    only where ``ratio_cv < 1``."""
    l2_cv = np.full(len(l2), np.nan) if l2_cv is None else np.asarray(l2_cv)

    def one(m: NDArray[np.bool_]) -> dict[str, Any]:
        a, z = float(np.mean(l2[m])), float(np.mean(l2_zero[m]))
        out = {"pairs": int(m.sum()), "se3_l2_mean": a, "zero_motion_se3_l2_mean": z,
               "ratio": a / z if z > 0 else float("inf")}
        c = m & np.isfinite(l2_cv)
        if c.any():
            cv = float(np.mean(l2_cv[c]))
            out.update({"constant_velocity_se3_l2_mean": cv,
                        "ratio_cv": float(np.mean(l2[c])) / cv if cv > 0 else float("inf")})
        return out

    gaps = np.asarray(gaps)
    return {"reference": "teacher", **one(np.ones(len(l2), dtype=bool)),
            "by_gap": {str(int(g)): one(gaps == g) for g in sorted(set(gaps.tolist()))}}


# ----------------------------------------------------------------------------------
# the stage
# ----------------------------------------------------------------------------------
@dataclass
class CalibrationResult:
    """Where calibration.json went, the calibration, and the JSON written."""

    path: Path
    calibration: Calibration
    report: dict


def calibrate(checkpoint: Path, scenes: str | Sequence[str], *, frames: str | None = None, split: str = "all",
              teacher_root: Path | None = None, config: PredictConfig = PredictConfig(),
              cal_config: CalibrationConfig = CalibrationConfig(), progress: bool | None = None,
              device: str = "auto", overwrite: bool = False) -> CalibrationResult:
    """Fit the covariance calibration of ``checkpoint`` on validation ``scenes`` and write
    ``calibration.json`` beside it (the network runs on ``device``: auto, cpu or cuda).

    The MC-dropout edges come from :func:`learner.mcdropout.mc_edges` with ``config`` (the
    same sample count, drop ratio and gaps ``learner predict`` uses); residuals are taken
    against the teacher's good edges (``teacher_root`` as in ``learner fit``; missing labels
    are an error naming the ``teacher generate`` command). Ground truth is never read.

    Rerun rule: a ``calibration.json`` fitted on the same inputs (its ``fingerprint``) is
    kept and returned; one of other inputs is replaced only with ``overwrite``, otherwise
    this raises :class:`data.runs.StaleOutputError` naming what differs.
    """
    checkpoint = Path(checkpoint)
    scenes = [scenes] if isinstance(scenes, str) else list(scenes)
    if not scenes:
        raise ConfigError("give at least one validation --scene to calibrate on")
    if config.drop <= 0 or config.samples < 2:
        raise ConfigError(f"calibration scales MC-dropout variances: needs --drop > 0 and --samples >= 2, "
                          f"got {config.drop} and {config.samples}")
    model, state = load_model(checkpoint, device=device)
    opened = []  # (scene, sequence, teacher edges.g2o)
    for spec in scenes:
        seqs = open_scene(spec, split=split, frames=frames)
        opened += [(spec, seq, g2o) for seq, g2o in zip(seqs, find_teacher_edges(spec, seqs, split, frames,
                                                                                  teacher_root))]
    path = checkpoint.parent / CALIBRATION_FILE
    fp = fingerprint(checkpoint, opened, config, cal_config)
    # with overwrite the old file stays until the new one replaces it (one atomic write)
    if claim(checkpoint.parent, fp, done=path.is_file(), has_outputs=path.is_file(), overwrite=overwrite,
             inside=CALIBRATION_FILE, hint="pass --overwrite to replace it"):
        log.info("%s: calibration of the same inputs: kept", path)
        cal = read_calibration(path)
        return CalibrationResult(path, cal, cal.to_dict())
    res = _residuals(model, state, checkpoint, opened, frames, config,
                     sys.stderr.isatty() if progress is None else progress)
    t_model = res.tcov if cal_config.teacher_variance else None
    cal = Calibration(fit_groups(res.cov, res.r, res.heads, res.gaps, t_model, cal_config), {
        "checkpoint": checkpoint.name, "checkpoint_sha1": file_sha1(checkpoint),
        "checkpoint_epoch": int(state["epoch"]), "preset": state["preset"], "variant": state["variant"],
        "scenes": scenes, "frames": frames, "split": split, "sequences": res.used,
        "samples": config.samples, "drop": config.drop, "max_gap": config.max_gap, "cov_floor": COV_FLOOR,
        "config": to_dict(cal_config), "pairs": len(res.r), "order": "v_x v_y v_z w_x w_y w_z",
        "git_revision": git_revision(),
    })
    extra = res.tcov if cal_config.teacher_variance else 0.0
    v = cal.info["validation"] = {
        "before": nees_stats(mahalanobis2(res.r, res.cov + extra)),
        "after": nees_stats(mahalanobis2(res.r, cal.apply(res.cov, res.heads, res.gaps) + extra)),
        "skill": skill_figures(res.l2, res.l2_zero, res.gaps, res.l2_cv)}
    cal.info["fingerprint"] = fp.to_dict()  # in the file itself: written in the same atomic step
    report = cal.to_dict()
    write_json(path, report)
    log.info("calibration of %s on %d validation pairs: 1-sigma coverage %.3f -> %.3f, 2-sigma %.3f -> %.3f, "
             "se(3) L2 %.3gx zero motion's (all against teacher labels) -> %s", checkpoint, len(res.r),
             v["before"]["coverage_1sigma"], v["after"]["coverage_1sigma"], v["before"]["coverage_2sigma"],
             v["after"]["coverage_2sigma"], v["skill"]["ratio"], path)
    return CalibrationResult(path, cal, report)


@dataclass
class _Residuals:
    """The validation pairs with teacher labels, over every sequence: MC-dropout
    covariances ``cov`` (n, 6, 6), residuals ``r`` (n, 6), teacher covariances ``tcov``
    (n, 6, 6), heads and gaps (n,), se(3) L2 distances to the labels of the learner, of
    zero motion and of constant velocity (n,), and one record per sequence (``used``)."""

    cov: NDArray[np.float64]
    r: NDArray[np.float64]
    tcov: NDArray[np.float64]
    heads: list[str]
    gaps: NDArray[np.int64]
    l2: NDArray[np.float64]
    l2_zero: NDArray[np.float64]
    l2_cv: NDArray[np.float64]
    used: list[dict[str, Any]]


def _residuals(model: CTCNet, state: dict, checkpoint: Path, opened: list[tuple[str, Any, Path]],
               frames: str | None, config: PredictConfig, progress: bool) -> _Residuals:
    """MC-dropout edges of every validation sequence against its teacher labels."""
    uses_lstm, _, _ = check_variant(state["variant"])
    window = int(state["train_config"]["window_max"])
    train_seqs = _training_sequences(checkpoint)
    covs, res, tcovs, heads, gaps, used, l2, l2_zero, l2_cv = [], [], [], [], [], [], [], [], []
    for spec, seq, g2o in opened:
        if seq.name in train_seqs and frame_ranges_overlap(train_seqs[seq.name], frames):
            log.warning("%s is also a training sequence of %s (trained on frames %s, calibrating on %s): "
                        "residuals on trained frames under-estimate the error", seq.name, checkpoint,
                        train_seqs[seq.name] or "all", frames or "all")
        if len(seq) < 2:
            raise DataError(f"sequence {seq.name} needs at least 2 frames to calibrate")
        x = load_frames(seq, model.cfg.width, model.cfg.height, checkpoint.parent / "cache", model.cfg.input)
        edges = mc_edges(model, x, uses_lstm=uses_lstm, window=window, cfg=config, progress=progress)
        idx, T_t, C_t = teacher_matches(edges.i, edges.j, seq.ids(), g2o)
        log.info("%s: %d of %d edges have teacher labels", seq.name, len(idx), len(edges.i))
        covs.append(edges.cov[idx])
        res.append(residuals(edges.mean[idx], T_t))
        log_t = np.array([geo.se3_log(T) for T in T_t]).reshape(-1, 6)
        l2.append(np.linalg.norm(log_t - edges.mean[idx], axis=1))
        l2_zero.append(np.linalg.norm(log_t, axis=1))
        l2_cv.append(constant_velocity_l2(edges.i[idx], edges.j[idx], log_t))
        tcovs.append(C_t)
        heads += [edges.head[e] for e in idx]
        gaps.append(edges.j[idx] - edges.i[idx])
        used.append({"scene": spec, "sequence": seq.name, "frames": len(seq), "edges": len(edges.i),
                     "pairs": len(idx), "teacher": str(g2o)})
    cat = np.concatenate
    return _Residuals(cat(covs), cat(res), cat(tcovs), heads, cat(gaps), cat(l2), cat(l2_zero), cat(l2_cv), used)


def fingerprint(checkpoint: Path, opened: list[tuple[str, Any, Path]], config: PredictConfig,
                cal_config: CalibrationConfig) -> Fingerprint:
    """The inputs of a calibration: the checkpoint's content, the validation sequences
    (scene, sequence, frames) with their teacher labels' digests, the MC-dropout and the
    calibration settings (not the device)."""
    return Fingerprint("calibrate", {
        "checkpoint": file_digest(checkpoint),
        "sequences": {f"{scene_id(spec)}:{seq.name}": frames_id(seq.ids()) for spec, seq, _ in opened},
        "labels": {f"{scene_id(spec)}:{seq.name}": upstream_digest(g2o.parent, "edges.g2o")
                   for spec, seq, g2o in opened},
        "predict": to_dict(config), "calibration": to_dict(cal_config)})


def _training_sequences(checkpoint: Path) -> dict[str, str | None]:
    """Training sequence name -> trained frame range, from the run's config.json (empty when absent)."""
    cfg = Path(checkpoint).parent / "config.json"
    try:
        d = json.loads(cfg.read_text())
        return {str(n): d.get("frames") for n in d.get("train_sequences", [])}
    except (OSError, ValueError, AttributeError, TypeError):
        return {}
