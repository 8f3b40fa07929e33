"""Composite transformation constraint (CTC) and label regression losses.

A window holds W consecutive frame pairs (W + 1 frames, positions 0..W). The LSTM gives
one twist per consecutive pair, ``xi_s[t]`` for (t, t+1); the direct head gives
``xi_d(i, j)`` for every pair with ``1 <= j - i <= G`` (:func:`window_pairs` fixes the
order: by gap, then by start). Then

* ``L_ctc = sum_{2 <= j-i <= G} || log(exp xi_s[i] ... exp xi_s[j-1]) - xi_d(i, j) ||^2``
* ``L_reg = sum over every prediction (LSTM and direct) of || xi - xi_label ||^2``, with
  labels masked out where the teacher edge is missing or failed,

summed inside a window and averaged over the windows of a batch;
``L = alpha L_ctc + beta L_reg``.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

from torch import Tensor

from learner import se3


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


def ctc_loss(xi_seq: Tensor, xi_direct: Tensor, G: int) -> Tensor:
    """L_ctc per window, (B,).

    Args:
        xi_seq: sequential estimates (B, W, 6) of the consecutive pairs.
        xi_direct: direct estimates (B, P, 6) in :func:`window_pairs` order.
        G: largest gap.
    """
    B, W, _ = xi_seq.shape
    sl = gap_slices(W, G)
    T = se3.se3_exp(xi_seq)  # (B, W, 4, 4)
    prod = T  # prod[:, i] = T_i ... T_{i+g-1} for the current g, i in 0..W-g
    total = xi_seq.new_zeros(B)
    for g in range(2, min(G, W) + 1):
        prod = prod[:, : W - g + 1] @ T[:, g - 1:]
        composed = se3.se3_log(prod)  # (B, W-g+1, 6)
        total = total + ((composed - xi_direct[:, sl[g]]) ** 2).sum(dim=(-1, -2))
    return total


def reg_loss(pred: Tensor, label: Tensor, mask: Tensor) -> Tensor:
    """Masked squared error summed over all but the first axis: (B, ..., 6) -> (B,)."""
    err = ((pred - label) ** 2).sum(-1) * mask.to(pred.dtype)
    return err.reshape(err.shape[0], -1).sum(-1)


@dataclass
class LossTerms:
    """Batch-mean loss terms (scalars) of one step."""

    total: Tensor
    ctc: Tensor
    reg: Tensor

    def items(self) -> dict[str, float]:
        return {"loss": float(self.total.detach()), "ctc": float(self.ctc.detach()), "reg": float(self.reg.detach())}


def window_loss(xi_seq: Tensor, xi_direct: Tensor, lab_seq: Tensor, mask_seq: Tensor, lab_direct: Tensor,
                mask_direct: Tensor, G: int, alpha: float, beta: float) -> LossTerms:
    """Phase-2 loss of B windows.

    Args:
        xi_seq, lab_seq, mask_seq: (B, W, 6), (B, W, 6), (B, W) sequential estimates and labels.
        xi_direct, lab_direct, mask_direct: (B, P, 6), (B, P, 6), (B, P) direct estimates.
    """
    ctc = ctc_loss(xi_seq, xi_direct, G).mean() if alpha > 0 else xi_seq.new_zeros(())
    reg = (reg_loss(xi_seq, lab_seq, mask_seq) + reg_loss(xi_direct, lab_direct, mask_direct)).mean()
    return LossTerms(alpha * ctc + beta * reg, ctc, reg)


def pair_loss(xi_direct: Tensor, label: Tensor, mask: Tensor, beta: float) -> LossTerms:
    """Phase-1 loss of N single pairs (N, 6): ``beta * mean masked ||xi - label||^2``."""
    reg = reg_loss(xi_direct[:, None], label[:, None], mask[:, None]).mean()
    return LossTerms(beta * reg, reg.new_zeros(()), reg)
