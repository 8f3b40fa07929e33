"""Composite transformation constraint (CTC) and label regression losses.

A window holds W consecutive frame pairs (W + 1 frames, positions 0..W). The LSTM gives
one twist per consecutive pair, ``xi_s[t]`` for (t, t+1); the direct head gives
``xi_d(i, j)`` for every pair with ``1 <= j - i <= G`` (:func:`window_pairs` fixes the
order: by gap, then by start). Then

* ``L_ctc = mean_{2 <= j-i <= G} || (log(exp xi_s[i] ... exp xi_s[j-1]) - xi_d(i, j)) / s_{j-i} ||^2 / 6``
* ``L_reg = mean over every prediction (LSTM and direct) of || (xi - xi_label) / s_g ||^2 / 6``,
  with labels masked out where the teacher edge is missing or failed,

``L = alpha L_ctc + beta L_reg``. ``s_g`` (6,) is the per-dimension *target scale* of gap g:
the root mean square of the training labels of that gap and dimension
(:func:`target_scale`). Dividing by it gives translation (metres) and rotation (radians)
the same weight, whatever their units and magnitudes, and makes every term a mean, so
that the loss does not grow with the window length and reads directly against zero
motion: a network that always predicts zero motion scores ``L_reg = 1`` on its training
labels.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import torch
from torch import Tensor

from ctcvo.learner import se3


@lru_cache(maxsize=64)
def window_pairs(W: int, G: int) -> tuple[tuple[int, int], ...]:
    """Direct-head pairs (i, j) of a window of W pairs: gap 1..min(G, W), then start."""
    return tuple((i, i + g) for g in range(1, min(G, W) + 1) for i in range(W - g + 1))


def gap_slices(W: int, G: int) -> dict[int, slice]:
    """Slice of :func:`window_pairs` holding the pairs of each gap."""
    out, k = {}, 0
    for g in range(1, min(G, W) + 1):
        out[g] = slice(k, k + W - g + 1)
        k += W - g + 1
    return out


def target_scale(labels: Tensor, mask: Tensor, floor: float = 1e-4) -> Tensor:
    """Per-gap, per-dimension target scale (G+1, 6): the root mean square of the labelled
    twists ``labels`` (G+1, N, 6) where ``mask`` (G+1, N), at least ``floor``. The RMS about
    zero (not the standard deviation) is what a zero-motion prediction's error is, so the
    normalised loss of zero motion is 1 even when the motion has a mean (a camera that
    keeps moving forward). Row 0 (unused) and gaps without labels get the gap-1 scale."""
    G1 = labels.shape[0]
    out = torch.full((G1, 6), 0.01)
    for g in range(1, G1):
        m = mask[g]
        if int(m.sum()) >= 2:
            out[g] = labels[g][m].double().pow(2).mean(0).sqrt().float()
    have = [g for g in range(1, G1) if int(mask[g].sum()) >= 2]
    if have:
        for g in range(G1):
            if g not in have:
                out[g] = out[have[0]]
    return out.clamp(min=floor)


def ctc_loss(xi_seq: Tensor, xi_direct: Tensor, G: int, scale: Tensor) -> Tensor:
    """L_ctc per window, (B,): the mean over the window's constraints of the normalised
    squared residual (mean over the 6 dimensions).

    Args:
        xi_seq: sequential estimates (B, W, 6) of the consecutive pairs.
        xi_direct: direct estimates (B, P, 6) in :func:`window_pairs` order.
        G: largest gap.
        scale: target scale (G+1, 6) (:func:`target_scale`).
    """
    B, W, _ = xi_seq.shape
    sl = gap_slices(W, G)
    T = se3.se3_exp(xi_seq)  # (B, W, 4, 4)
    prod = T  # prod[:, i] = T_i ... T_{i+g-1} for the current g, i in 0..W-g
    total = xi_seq.new_zeros(B)
    count = 0
    for g in range(2, min(G, W) + 1):
        prod = prod[:, : W - g + 1] @ T[:, g - 1:]
        composed = se3.se3_log(prod)  # (B, W-g+1, 6)
        total = total + (((composed - xi_direct[:, sl[g]]) / scale[g]) ** 2).mean(-1).sum(-1)
        count += W - g + 1
    return total / max(count, 1)


def reg_error(pred: Tensor, label: Tensor, mask: Tensor, scale: Tensor) -> tuple[Tensor, Tensor]:
    """Masked normalised squared error (mean over the 6 dims) summed over all but the
    first axis, and the number of labelled predictions: (B, ..., 6) -> (B,), (B,).
    ``scale`` (..., 6) broadcasts against ``pred``."""
    err = (((pred - label) / scale) ** 2).mean(-1)
    w = mask.to(pred.dtype)
    err = err * w
    return err.reshape(err.shape[0], -1).sum(-1), w.reshape(w.shape[0], -1).sum(-1)


@dataclass
class LossTerms:
    """Batch-mean loss terms (scalars) of one step."""

    total: Tensor
    ctc: Tensor
    reg: Tensor

    def items(self) -> dict[str, float]:
        return {"loss": float(self.total.detach()), "ctc": float(self.ctc.detach()), "reg": float(self.reg.detach())}


def window_loss(xi_seq: Tensor, xi_direct: Tensor, lab_seq: Tensor, mask_seq: Tensor, lab_direct: Tensor,
                mask_direct: Tensor, G: int, alpha: float, beta: float, scale: Tensor) -> LossTerms:
    """Phase-2 loss of B windows: ``L_reg`` the mean over every labelled
    prediction (LSTM and direct) of the batch, ``L_ctc`` the mean over its windows.

    Args:
        xi_seq, lab_seq, mask_seq: (B, W, 6), (B, W, 6), (B, W) sequential estimates and labels.
        xi_direct, lab_direct, mask_direct: (B, P, 6), (B, P, 6), (B, P) direct estimates.
        scale: target scale (G+1, 6) (:func:`target_scale`).
    """
    W = xi_seq.shape[1]
    gaps = torch.tensor([j - i for i, j in window_pairs(W, G)], device=xi_direct.device)
    ctc = ctc_loss(xi_seq, xi_direct, G, scale).mean() if alpha > 0 else xi_seq.new_zeros(())
    es, ns = reg_error(xi_seq, lab_seq, mask_seq, scale[1])
    ed, nd = reg_error(xi_direct, lab_direct, mask_direct, scale[gaps])
    reg = (es.sum() + ed.sum()) / (ns.sum() + nd.sum()).clamp(min=1)
    return LossTerms(alpha * ctc + beta * reg, ctc, reg)


def pair_loss(xi_direct: Tensor, label: Tensor, mask: Tensor, gap: Tensor, beta: float, scale: Tensor) -> LossTerms:
    """Phase-1 loss of N single pairs (N, 6) of gaps ``gap`` (N,): ``beta`` times the mean
    normalised squared error over the labelled pairs."""
    e, n = reg_error(xi_direct[:, None], label[:, None], mask[:, None], scale[gap][:, None])
    reg = e.sum() / n.sum().clamp(min=1)
    return LossTerms(beta * reg, reg.new_zeros(()), reg)
