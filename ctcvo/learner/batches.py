"""What each optimiser step of ``learner fit`` trains on: its learning rate and window
length, batches of labelled pairs (phase 1) and of windows of consecutive pairs (phase 2),
and the loss of a batch, its inputs gathered from the cached frames and augmented
(:mod:`learner.augment`)."""

from __future__ import annotations

import math

import numpy as np
import torch
from torch import Tensor
from tqdm import tqdm

from ctcvo.learner import loss as L
from ctcvo.learner.augment import augment, draw_labels, reversed_pairs
from ctcvo.learner.config import TrainConfig
from ctcvo.learner.dataset import SequenceData

#: the learning rate's end of the cosine, as a fraction of ``lr`` (set with the step schedule of
#: issue 11, commit 07e1812, in place of the paper's halving every few epochs; not tuned since)
LR_FINAL = 0.05


def lr_at(cfg: TrainConfig, step: int) -> float:
    """Learning rate of optimiser step ``step`` (0-based): linear warm-up, then a cosine
    from ``lr`` to ``lr * LR_FINAL`` at the last step."""
    if step < cfg.warmup_steps:
        return cfg.lr * (step + 1) / cfg.warmup_steps
    span = max(cfg.steps - cfg.warmup_steps - 1, 1)
    t = min(max(step - cfg.warmup_steps, 0) / span, 1.0)
    return cfg.lr * (LR_FINAL + (1.0 - LR_FINAL) * 0.5 * (1.0 + math.cos(math.pi * t)))


class PhaseProgress:
    """One progress bar per training phase, counting its optimiser steps (rate and ETA of the
    phase, across epochs; a resumed run starts at the steps done). Quiet unless ``enabled``
    (the command passes whether stderr is a terminal)."""

    def __init__(self, cfg: TrainConfig, enabled: bool) -> None:
        self.cfg, self.enabled = cfg, enabled
        self.bar: tqdm | None = None
        self.phase = ""

    def step(self, phase: str, step: int, postfix: dict[str, str]) -> None:
        """Count optimiser step ``step`` (0-based) of ``phase`` ("pairs" or "windows")."""
        if not self.enabled:
            return
        if phase != self.phase:
            self.close()
            p1 = min(self.cfg.pretrain_steps, self.cfg.steps)
            first, total = (0, p1) if phase == "pairs" else (p1, self.cfg.steps - p1)
            desc = "phase 1 (pairs, direct head)" if phase == "pairs" else "phase 2 (windows, LSTM + CTC)"
            self.bar = tqdm(total=total, initial=step - first, desc=desc, unit="step", leave=False)
            self.phase = phase
        assert self.bar is not None
        self.bar.update(1)
        self.bar.set_postfix(postfix, refresh=False)

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()
            self.bar, self.phase = None, ""


def window_length(cfg: TrainConfig, epoch: int) -> int:
    """Phase-2 window length (pairs) of ``epoch``: grows linearly from ``window_min`` in the
    first epoch holding phase-2 steps to ``window_max`` in the last one."""
    first = cfg.pretrain_steps // cfg.eval_every
    n2 = cfg.epochs - first
    if n2 <= 1:
        return cfg.window_max
    return int(round(cfg.window_min + (cfg.window_max - cfg.window_min) * (epoch - first) / (n2 - 1)))


def _cycle(rows: np.ndarray, n_batches: int, size: int, rng: np.random.Generator) -> list[np.ndarray]:
    """``n_batches`` batches of ``size`` rows, drawn from reshuffled passes over ``rows``."""
    out: list[np.ndarray] = []
    pool = rows[:0]
    while len(out) < n_batches:
        if len(pool) < size:
            pool = np.concatenate([pool, rows[rng.permutation(len(rows))]])
        out.append(pool[:size])
        pool = pool[size:]
    return out


def pair_batches(data: list[SequenceData], cfg: TrainConfig, rng: np.random.Generator,
                  n_batches: int | None = None) -> list[np.ndarray]:
    """Batches of rows (seq, k, gap) of labelled pairs: one shuffled pass (``n_batches``
    None), or ``n_batches`` batches from as many passes as they need."""
    rows = []
    for s, d in enumerate(data):
        g, k = np.nonzero(d.mask.numpy())
        rows.append(np.stack([np.full_like(k, s), k, g], 1))
    allrows = np.concatenate(rows)
    if n_batches is None:
        allrows = allrows[rng.permutation(len(allrows))]
        return [allrows[i:i + cfg.batch_pairs] for i in range(0, len(allrows), cfg.batch_pairs)]
    return _cycle(allrows, n_batches, min(cfg.batch_pairs, len(allrows)), rng)


def window_batches(data: list[SequenceData], W: int, cfg: TrainConfig, rng: np.random.Generator,
                    n_batches: int | None = None) -> list[np.ndarray]:
    """Batches of rows (seq, start) of windows of W pairs (frames start..start+W), every
    start position of every sequence long enough: one shuffled pass (``n_batches`` None),
    or ``n_batches`` batches from as many passes as they need."""
    rows = [(s, k) for s, d in enumerate(data) for k in range(max(len(d) - W, 0))]
    if not rows:
        return []
    arr = np.array(rows)
    if n_batches is None:
        arr = arr[rng.permutation(len(arr))]
        return [arr[i:i + cfg.batch_windows] for i in range(0, len(arr), cfg.batch_windows)]
    return _cycle(arr, n_batches, min(cfg.batch_windows, len(arr)), rng)



def pairs_step(net, data, rows: np.ndarray, cfg: TrainConfig, aug: bool, gen, device,
                scale: Tensor) -> L.LossTerms:
    """Phase-1 loss of the pairs ``rows`` (seq, k, gap), drawn reversed, mirrored and
    rescaled as ``cfg`` says."""
    x, labs, masks, gaps = [], [], [], []
    for s in np.unique(rows[:, 0]):
        r = rows[rows[:, 0] == s]
        d = data[int(s)]
        k, g = torch.from_numpy(r[:, 1]), torch.from_numpy(r[:, 2])
        rev = torch.rand(len(k), generator=gen) < cfg.reverse_prob if cfg.reverse_prob > 0 \
            else torch.zeros(len(k), dtype=torch.bool)
        x.append(reversed_pairs(d, k, k + g, rev))
        lab, m = draw_labels(d, k, g, aug, gen)
        lab = torch.where(rev[:, None], -lab, lab)  # log(T^-1) = -log(T)
        labs.append(lab)
        masks.append(m)
        gaps.append(g)
    x, lab = augment(torch.cat(x), torch.cat(labs), cfg, gen, data[0].frames.mode)
    xi_d, _ = net(x.to(device))
    return L.pair_loss(xi_d.float(), lab.to(device), torch.cat(masks).to(device), torch.cat(gaps).to(device),
                       cfg.beta, scale)


def windows_step(net, data, rows: np.ndarray, W: int, cfg: TrainConfig, aug: bool, gen, device,
                  scale: Tensor) -> L.LossTerms:
    """Phase-2 loss of the windows ``rows`` (seq, start) of W pairs, each window reversed,
    mirrored and rescaled as a whole."""
    pairs = L.window_pairs(W, cfg.max_gap)
    P = len(pairs)
    pi = torch.tensor([i for i, _ in pairs])
    pg = torch.tensor([j - i for i, j in pairs])
    B = len(rows)
    # a reversed window: its pair (i, j) is the original pair (start + W - j, start + W - i)
    # played backwards (built as (j, i), its label negated)
    rev = (torch.rand(B, generator=gen) < cfg.reverse_prob) if cfg.reverse_prob > 0 else torch.zeros(B, dtype=torch.bool)
    x, labs, masks = [], [], []
    for b, (s, start) in enumerate(rows):
        d = data[int(s)]
        k = int(start) + W - pi - pg if rev[b] else pi + int(start)
        x.append(reversed_pairs(d, k, k + pg, rev[b].expand(len(k))))
        lab, m = draw_labels(d, k, pg, aug, gen)
        labs.append(-lab if rev[b] else lab)  # log(T^-1) = -log(T)
        masks.append(m)
    # (B, P, C, H, W), (B, P, 6), augmented a whole window at a time
    x, lab = augment(torch.stack(x), torch.stack(labs), cfg, gen, data[0].frames.mode)
    seq_index = (torch.arange(B)[:, None] * P + torch.arange(W)[None, :]).to(device)  # gap-1 block first
    xi_d, xi_s = net(x.flatten(0, 1).to(device), seq_index)
    lab = lab.to(device)
    mask = torch.stack(masks).to(device)
    xi_d = xi_d.float().view(B, P, 6)
    # the LSTM's consecutive pairs share the labels of the direct gap-1 pairs
    with torch.autocast(device.type, enabled=False):  # se(3) maps in float32
        return L.window_loss(xi_s.float(), xi_d, lab[:, :W], mask[:, :W], lab, mask, cfg.max_gap, cfg.alpha,
                             cfg.beta, scale)


