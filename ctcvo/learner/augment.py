"""Training-time augmentation of pairs and windows, each exact (compositions stay
consistent, so the CTC still holds): label noise drawn from the teacher's covariances
(``*-aug`` variants), time reversal (``reverse_prob``), left-right mirroring
(``flip_prob``) and depth scaling (``scale_aug``) of :class:`learner.config.TrainConfig`."""

from __future__ import annotations

import torch
from torch import Tensor

from ctcvo.learner import se3
from ctcvo.learner.config import FLOW_U_CHANNEL, INVDEPTH_CHANNELS, TrainConfig
from ctcvo.learner.dataset import SequenceData


def draw_labels(d: SequenceData, k: Tensor, g: Tensor, aug: bool, gen: torch.Generator) -> tuple[Tensor, Tensor]:
    """Labels (n, 6) and mask (n,) of pairs (k, k+g); ``aug`` draws each label from
    N(teacher, teacher covariance) as a right perturbation ``log(exp(xi) exp(L eps))``."""
    lab, m = d.labels[g, k], d.mask[g, k]
    if aug and d.chol is not None:
        eps = torch.randn(lab.shape, generator=gen)
        delta = (d.chol[g, k] @ eps[..., None])[..., 0]
        lab = se3.se3_log(se3.se3_exp(lab.double()) @ se3.se3_exp(delta.double())).float()
    return lab, m


MIRROR = torch.tensor([-1.0, 1.0, 1.0, 1.0, -1.0, -1.0])
"""Twist of a left-right mirrored motion, per component (see ``TrainConfig.flip_prob``)."""


def mirror(x: Tensor, lab: Tensor, flip: Tensor, mode: str = "rgb") -> tuple[Tensor, Tensor]:
    """Mirror the samples ``flip`` (B,) bool of images ``x`` (B, ..., C, H, W) of input
    ``mode`` and labels ``lab`` (B, ..., 6); an input with flow also has its horizontal
    flow negated."""
    if not bool(flip.any()):
        return x, lab
    x, lab = x.clone(), lab.clone()
    x[flip] = x[flip].flip(-1)
    if mode in FLOW_U_CHANNEL:
        x[flip, ..., FLOW_U_CHANNEL[mode], :, :] *= -1
    lab[flip] = lab[flip] * MIRROR
    return x, lab


def rescale(x: Tensor, lab: Tensor, u: Tensor, mode: str) -> tuple[Tensor, Tensor]:
    """Scale the world of the samples of images ``x`` (B, ..., C, H, W) and labels ``lab``
    (B, ..., 6) by ``2**u`` (B,) (``TrainConfig.scale_aug``): inverse depth / s, translation
    * s; colour and flow are unchanged."""
    s = torch.exp2(u).float()
    x = x.float().clone()
    for c in INVDEPTH_CHANNELS[mode]:
        x[..., c, :, :] /= s.view((len(s),) + (1,) * (x.dim() - 2))
    lab = lab.clone()
    lab[..., :3] *= s.view((len(s),) + (1,) * (lab.dim() - 1))
    return x, lab


def augment(x: Tensor, lab: Tensor, cfg: TrainConfig, gen: torch.Generator, mode: str) -> tuple[Tensor, Tensor]:
    """Mirror (``flip_prob``) and rescale (``scale_aug``) whole samples: pairs (B, C, H, W)
    or windows (B, P, C, H, W), with their labels (B, [P,] 6)."""
    if cfg.flip_prob > 0:
        x, lab = mirror(x, lab, torch.rand(len(x), generator=gen) < cfg.flip_prob, mode)
    if cfg.scale_aug > 0:
        x, lab = rescale(x, lab, (2 * torch.rand(len(x), generator=gen) - 1) * cfg.scale_aug, mode)
    return x, lab


def reversed_pairs(d: SequenceData, i: Tensor, j: Tensor, rev: Tensor) -> Tensor:
    """Inputs of the pairs (i, j), those with ``rev`` played backwards: built as (j, i),
    the later frame first (the flow and depth of the ``flow`` input come out right too)."""
    return d.pairs(torch.where(rev, j, i), torch.where(rev, i, j))

