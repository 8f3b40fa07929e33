"""Per-epoch evaluation of ``learner fit``: the se(3) L2 of the gap-1 estimates on the
training and validation frames beside zero motion and constant velocity, the epoch's log
line, and the warning that ends a run whose model is no better than zero motion."""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch
from numpy.typing import NDArray

from ctcvo.data import geometry as geo
from ctcvo.data.metrics import relative_poses
from ctcvo.learner.config import PredictConfig
from ctcvo.learner.dataset import Frames, SequenceData
from ctcvo.learner.mcdropout import mc_edges
from ctcvo.learner.model import CTCNet

log = logging.getLogger(__name__)


@dataclass
class _EvalSeq:
    frames: Frames
    """The cached inputs of a stretch of n frames of one sequence."""
    ref: NDArray[np.float64]
    """(n-1, 6) reference gap-1 twists; rows of NaN where there is none."""


class Evaluator:
    """The se(3) L2 error of the gap-1 estimates that ``learner predict`` writes (the LSTM
    head for LSTM variants, the direct head otherwise; no dropout) on the training and
    validation frames (``<set>_se3_l2``), beside the same figure of zero motion and of
    constant velocity (each step repeats the previous reference step) on the same pairs.
    LSTM variants also get the direct head's figure (``<set>_direct_se3_l2``; the LSTM
    head only trains in phase 2).

    The reference is the ground truth when every sequence of a set has it, else the
    teacher's gap-1 labels (``<set>_reference`` in the history says which). At most
    ``max_pairs`` pairs per set, the first frames of each sequence in turn, are scored.
    """

    def __init__(self, train: list[SequenceData], val: list[SequenceData], uses_lstm: bool, window: int,
                 max_pairs: int = 1000) -> None:
        self.uses_lstm, self.window = uses_lstm, window
        self.sets = {name: self._view(data, max_pairs) for name, data in (("train", train), ("val", val)) if data}
        self.baselines = {name: self._baselines(v) for name, v in self.sets.items()}

    @staticmethod
    def _view(data: list[SequenceData], max_pairs: int) -> tuple[str, list[_EvalSeq]]:
        use_gt = all(d.gt is not None for d in data)
        out, left = [], max_pairs
        for d in data:
            n = min(len(d), left + 1)
            if n < 2:
                break
            if use_gt:
                ref = np.array([geo.se3_log(T) for T in relative_poses(d.gt[:n])])
            else:
                ref = d.labels[1, : n - 1].double().numpy().copy()
                ref[~d.mask[1, : n - 1].numpy()] = np.nan
            out.append(_EvalSeq(d.frames.head(n), ref))
            left -= n - 1
        return ("ground truth" if use_gt else "teacher"), out

    @staticmethod
    def _score(seqs: list[_EvalSeq], preds: list[NDArray[np.float64]]) -> float:
        err = np.concatenate([np.linalg.norm(s.ref - p, axis=1) for s, p in zip(seqs, preds)])
        err = err[np.isfinite(err)]
        return float(err.mean()) if len(err) else float("nan")

    def _baselines(self, view: tuple[str, list[_EvalSeq]]) -> dict[str, float]:
        seqs = view[1]
        zero = [np.zeros_like(s.ref) for s in seqs]
        cv = [np.nan_to_num(np.vstack([np.zeros((1, 6)), s.ref[:-1]])) for s in seqs]
        return {"zero_motion": self._score(seqs, zero), "constant_velocity": self._score(seqs, cv)}

    @torch.no_grad()
    def __call__(self, model: CTCNet, device: torch.device) -> dict[str, Any]:
        was = model.training
        model.eval()
        cfg = PredictConfig(samples=1, drop=0.0, max_gap=1)
        out: dict[str, Any] = {}
        for name, (ref_kind, seqs) in self.sets.items():
            for lstm in (False, True) if self.uses_lstm else (False,):
                preds = [mc_edges(model, s.frames, uses_lstm=lstm, window=self.window, cfg=cfg).mean for s in seqs]
                out[f"{name}_{'lstm' if lstm else 'direct'}_se3_l2"] = self._score(seqs, preds)
            out[f"{name}_se3_l2"] = out[f"{name}_{'lstm' if self.uses_lstm else 'direct'}_se3_l2"]
            out[f"{name}_zero_motion_se3_l2"] = self.baselines[name]["zero_motion"]
            out[f"{name}_constant_velocity_se3_l2"] = self.baselines[name]["constant_velocity"]
            out[f"{name}_reference"] = ref_kind
        model.train(was)
        return out


#: what each label source of a variant (``learner.config.VARIANTS``) trains on, for the log
LABEL_NAMES = {"gt": "ground-truth labels", "teacher": "teacher labels",
               "aug": "teacher labels redrawn from their covariances"}


def reference(entry: dict, name: str) -> str:
    """What set ``name``'s se(3) L2 figures of a history entry were measured against."""
    ref = entry.get(f"{name}_reference", "the reference")
    return "teacher labels" if ref == "teacher" else ref


def epoch_line(entry: dict) -> str:
    """The epoch's log line: the loss terms (1.0 = zero motion on the training labels, which
    it names), then each set's se(3) L2 beside zero motion and constant velocity, naming the
    reference; an LSTM head not trained yet (phase 1, pairs only) is marked so."""
    terms = ", ".join(f"{k}={entry[k]:.4g}" for k in ("pairs_reg", "windows_reg", "windows_ctc") if k in entry)
    labels = LABEL_NAMES.get(entry.get("labels", ""), "training labels")  # histories before the key: unnamed
    parts = [f"loss x zero motion on the {labels}: {terms}"] if terms else []
    lstm_untrained = "windows" not in str(entry.get("phase", "windows"))
    for name in ("train", "val"):
        if f"{name}_se3_l2" in entry:
            lstm = f"lstm {entry[f'{name}_lstm_se3_l2']:.5f}" if f"{name}_lstm_se3_l2" in entry else ""
            if lstm and lstm_untrained:
                lstm += " (not trained yet: phase 1 trains the direct head)"
            heads = (f"direct {entry[f'{name}_direct_se3_l2']:.5f}, {lstm}" if lstm
                     else f"{entry[f'{name}_se3_l2']:.5f}")
            parts.append(f"{name} se(3) L2 vs {reference(entry, name)} {heads} (zero motion "
                         f"{entry[f'{name}_zero_motion_se3_l2']:.5f}, constant velocity "
                         f"{entry[f'{name}_constant_velocity_se3_l2']:.5f})")
    return " | ".join(parts)


def warn_if_no_skill(entry: dict) -> None:
    """Say loudly when the trained model is no better than a camera that never moves, or
    than one that repeats its previous step (constant velocity), on its validation frames
    (without them, its training frames)."""
    for name in ("val", "train"):
        err, zero = entry.get(f"{name}_se3_l2"), entry.get(f"{name}_zero_motion_se3_l2")
        if err is None or zero is None or not (math.isfinite(err) and math.isfinite(zero)):
            continue
        where = "validation" if name == "val" else "training"
        ref = reference(entry, name)
        cv = entry.get(f"{name}_constant_velocity_se3_l2")
        if err >= zero:
            log.warning("!!! the trained model is NOT better than zero motion on its %s frames: se(3) L2 %.5f vs "
                        "%.5f for a camera that never moves (both against %s). Its predictions carry no usable "
                        "motion.", where, err, zero, ref)
            return
        log.info("%s se(3) L2 %.5f = %.2fx zero motion (%.5f), against %s", name, err, err / zero, zero, ref)
        if cv is not None and math.isfinite(cv) and err >= cv:
            log.warning("!!! the trained model is NOT better than constant velocity on its %s frames: se(3) L2 "
                        "%.5f vs %.5f for a camera that repeats its previous step (both against %s).",
                        where, err, cv, ref)
        return
