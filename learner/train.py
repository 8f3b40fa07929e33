"""``learner fit``: train the network on teacher (or ground-truth) labels.

Phase 1 (``pretrain_epochs``, and every epoch of the ``cnn-*`` variants) trains the
encoder and the direct head on single pairs of gaps 1..G with L_reg only. Phase 2 trains
on windows of consecutive pairs whose length grows linearly from ``window_min`` to
``window_max`` with ``alpha L_ctc + beta L_reg`` (``alpha = 0`` except for ``ctc``).

The run folder holds ``config.json`` (resolved configuration, variant, scenes, git
revision), ``checkpoint.pt`` (written atomically after every epoch; ``resume=True``
continues from it and reaches the same weights as an uninterrupted run, because every
epoch re-seeds its own shuffling, dropout and label noise from ``(seed, epoch)``),
``history.json`` (per-epoch losses) and ``cache/`` (resized frames). With validation scenes
(and ``calibrate``), the run ends with :func:`learner.calibrate.calibrate` on them, which
writes ``calibration.json`` (covariance calibration against the validation scenes' teacher
labels). Without validation scenes no calibration is fitted: held-out frames of the
training sequences would be a choice fit cannot make safely (the user's test frames are
unknown here); name them (``--val-scene`` the same sequence with a disjoint
``--val-frames``) or run ``learner calibrate`` on a separate scene instead. Training further
(``resume``) deletes a stale ``calibration.json`` first.

Runs under ``torchrun --nproc_per_node=N`` with DistributedDataParallel (gloo on CPU,
nccl on GPU): every process draws the same batches and trains on its share of each;
only rank 0 writes files.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import os
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Optional, Sequence as TypingSequence

import numpy as np
import torch
import torch.distributed as dist
from torch import Tensor
from tqdm import tqdm

from data.errors import ConfigError, DataError, VOError
from data.io import atomic_write, ensure_dir, git_revision, write_json
from data.scenes import open_scene, scene_slug
from data.sequence import frame_ranges_overlap
from learner import loss as L
from learner import se3
from learner.calibrate import CALIBRATION_FILE
from learner.calibrate import calibrate as run_calibration
from learner.config import Preset, TrainConfig, check_variant, get_preset, to_dict
from learner.dataset import SequenceData, check_labels, find_teacher_edges, load_sequences
from learner.model import CTCNet, load_pretrained_vgg

log = logging.getLogger(__name__)

CHECKPOINT = "checkpoint.pt"
CHECKPOINT_FORMAT = 1


@dataclass
class FitResult:
    """What a training run produced."""

    run_dir: Path
    checkpoint: Path
    epochs_done: int
    history: list[dict] = field(default_factory=list)
    calibration: Optional[Path] = None
    """calibration.json, when validation scenes were given."""


@dataclass
class _Dist:
    rank: int = 0
    world: int = 1
    device: torch.device = torch.device("cpu")

    @property
    def main(self) -> bool:
        return self.rank == 0

    def barrier(self) -> None:
        if self.world > 1:
            dist.barrier()


def _setup_dist() -> _Dist:
    world = int(os.environ.get("WORLD_SIZE", "1"))
    if world <= 1:
        return _Dist()
    cuda = torch.cuda.is_available()
    if not dist.is_initialized():
        dist.init_process_group("nccl" if cuda else "gloo")
    rank = dist.get_rank()
    device = torch.device("cpu")
    if cuda:
        local = int(os.environ.get("LOCAL_RANK", "0"))
        torch.cuda.set_device(local)
        device = torch.device("cuda", local)
    return _Dist(rank, dist.get_world_size(), device)


def default_run_dir(scene: str) -> Path:
    return Path("runs") / scene_slug(scene) / "learner"


# ----------------------------------------------------------------------------------
# batches
# ----------------------------------------------------------------------------------
def window_length(cfg: TrainConfig, epoch: int) -> int:
    """Phase-2 window length (pairs) of ``epoch`` (linear growth min -> max)."""
    n2 = cfg.epochs - cfg.pretrain_epochs
    e2 = epoch - cfg.pretrain_epochs
    if n2 <= 1:
        return cfg.window_max
    return int(round(cfg.window_min + (cfg.window_max - cfg.window_min) * e2 / (n2 - 1)))


def _pair_batches(data: list[SequenceData], cfg: TrainConfig, rng: np.random.Generator) -> list[np.ndarray]:
    """Shuffled batches of rows (seq, k, gap) of labelled pairs."""
    rows = []
    for s, d in enumerate(data):
        g, k = np.nonzero(d.mask.numpy())
        rows.append(np.stack([np.full_like(k, s), k, g], 1))
    allrows = np.concatenate(rows)
    allrows = allrows[rng.permutation(len(allrows))]
    return [allrows[i:i + cfg.batch_pairs] for i in range(0, len(allrows), cfg.batch_pairs)]


def _window_batches(data: list[SequenceData], W: int, cfg: TrainConfig, rng: np.random.Generator) -> list[np.ndarray]:
    """Shuffled batches of rows (seq, start) of non-overlapping windows of W pairs."""
    rows = []
    for s, d in enumerate(data):
        n = len(d)
        if n - 1 < W:
            continue
        off = int(rng.integers(0, min(W, n - W)))
        starts = np.arange(off, n - W, W)
        rows += [(s, int(k)) for k in starts]
    if not rows:
        return []
    arr = np.array(rows)[rng.permutation(len(rows))]
    return [arr[i:i + cfg.batch_windows] for i in range(0, len(arr), cfg.batch_windows)]


def _labels(d: SequenceData, k: Tensor, g: Tensor, aug: bool, gen: torch.Generator) -> tuple[Tensor, Tensor]:
    """Labels (n, 6) and mask (n,) of pairs (k, k+g); ``aug`` draws each label from
    N(teacher, teacher covariance) as a right perturbation ``log(exp(xi) exp(L eps))``."""
    lab, m = d.labels[g, k], d.mask[g, k]
    if aug and d.chol is not None:
        eps = torch.randn(lab.shape, generator=gen)
        delta = (d.chol[g, k] @ eps[..., None])[..., 0]
        lab = se3.se3_log(se3.se3_exp(lab.double()) @ se3.se3_exp(delta.double())).float()
    return lab, m


# ----------------------------------------------------------------------------------
# checkpoints
# ----------------------------------------------------------------------------------
def save_checkpoint(path: Path, model: CTCNet, opt: torch.optim.Optimizer, epoch: int, preset: Preset,
                    variant: str, history: list[dict]) -> None:
    state = {
        "format": CHECKPOINT_FORMAT, "epoch": epoch, "preset": preset.name, "variant": variant,
        "model_config": to_dict(preset.model), "train_config": to_dict(preset.train),
        "model": model.state_dict(), "optimizer": opt.state_dict(), "history": history,
        "git_revision": git_revision(),
    }
    with atomic_write(path, "wb") as fh:
        torch.save(state, fh)


def load_checkpoint(path: Path) -> dict:
    """Read a learner checkpoint; clear error when missing or not one."""
    path = Path(path)
    if not path.is_file():
        raise DataError(f"checkpoint {path} does not exist")
    try:
        state = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # noqa: BLE001 - corrupt pickles raise many types
        raise DataError(f"cannot read checkpoint {path}: {exc}") from None
    if not isinstance(state, dict) or state.get("format") != CHECKPOINT_FORMAT or "model" not in state:
        raise DataError(f"{path} is not a learner checkpoint")
    return state


# ----------------------------------------------------------------------------------
# fit
# ----------------------------------------------------------------------------------
def _open_all(scenes: TypingSequence[str], split: str, frames: Optional[str]) -> list[tuple[str, list]]:
    return [(s, open_scene(s, split=split, frames=frames)) for s in scenes]


def fit(scenes: TypingSequence[str], *, variant: str = "ctc", preset: str | Preset = "cpu",
        val_scenes: TypingSequence[str] = (), frames: Optional[str] = None, split: str = "all",
        val_frames: Optional[str] = None, out: Optional[Path] = None, resume: bool = False,
        pretrained: Optional[Path] = None, teacher_root: Optional[Path] = None,
        progress: Optional[bool] = None, calibrate: bool = True,
        **train_overrides: Any) -> FitResult:
    """Train a learner on the sequences of ``scenes`` and return the run's outputs.

    ``train_overrides`` replace fields of the preset's :class:`TrainConfig`
    (e.g. ``epochs=3, seed=1, steps_per_epoch=10``). ``calibrate``: fit the covariance
    calibration on ``val_scenes`` (their teacher labels, never ground truth) at the end.
    ``val_frames`` is the frame range of the validation sequences (default: ``frames``); a
    validation sequence may be a training sequence only with a disjoint range (e.g. train
    on 0:375, validate on 375:450, test on 450:).
    """
    if not scenes:
        raise ConfigError("give at least one --scene")
    uses_lstm, label_source, uses_ctc = check_variant(variant)
    p = get_preset(preset) if isinstance(preset, str) else preset
    overrides = {k: v for k, v in train_overrides.items() if v is not None}
    if "epochs" in overrides and "pretrain_epochs" not in overrides:  # keep the phase proportion
        overrides["pretrain_epochs"] = min(overrides["epochs"], int(round(
            overrides["epochs"] * p.train.pretrain_epochs / p.train.epochs)))
    if "epochs" in overrides and "lr_halve_every" not in overrides:  # and the lr schedule's
        overrides["lr_halve_every"] = max(1, int(round(overrides["epochs"] * p.train.lr_halve_every / p.train.epochs)))
    try:
        p = dataclasses.replace(p, train=dataclasses.replace(p.train, **overrides))
    except TypeError as exc:
        raise ConfigError(f"unknown training option: {exc}") from None
    cfg, mcfg = p.train, p.model
    if not uses_ctc:
        cfg = dataclasses.replace(cfg, alpha=0.0)
    if not uses_lstm:
        cfg = dataclasses.replace(cfg, pretrain_epochs=cfg.epochs)
    p = dataclasses.replace(p, train=cfg)

    dd = _setup_dist()
    run_dir = Path(out) if out is not None else default_run_dir(scenes[0])
    ckpt_path = run_dir / CHECKPOINT
    state = None
    if resume:
        state = load_checkpoint(ckpt_path)
        if state["preset"] != p.name:
            raise ConfigError(f"{ckpt_path} was trained with preset {state['preset']!r}, not {p.name!r}")
        if state["model_config"] != to_dict(mcfg):
            raise ConfigError(f"{ckpt_path} was trained with another network shape of preset {p.name!r} "
                              "(the preset changed since); start a new run")
        if state["variant"] != variant:
            raise ConfigError(f"{ckpt_path} was trained as variant {state['variant']!r}, not {variant!r}")
    elif ckpt_path.exists():
        raise ConfigError(f"{run_dir} already holds a checkpoint; pass --resume to continue it or choose another --out")

    # -------------------------------------------------------------- data
    if dd.main:
        ensure_dir(run_dir)
    vframes = frames if val_frames is None else val_frames
    opened = _open_all(scenes, split, frames)
    val_opened = _open_all(val_scenes, split, vframes)
    train_names = {s.name for _, seqs in opened for s in seqs}
    clash = train_names & {s.name for _, seqs in val_opened for s in seqs}
    if clash and frame_ranges_overlap(frames, vframes):
        raise ConfigError(f"validation sequence(s) {', '.join(sorted(clash))} are also training sequences "
                          f"(frames {frames or 'all'} and {vframes or 'all'}): give disjoint --frames / --val-frames")
    cache = run_dir / "cache"

    def _load(items: list[tuple[str, list]], frame_range: Optional[str]) -> list[SequenceData]:
        out_: list[SequenceData] = []
        for spec, seqs in items:
            out_ += load_sequences(spec, seqs, width=mcfg.width, height=mcfg.height, max_gap=cfg.max_gap,
                                   label_source=label_source if label_source != "aug" else "aug",
                                   cache_dir=cache, split=split, frames=frame_range, teacher_root=teacher_root)
        return out_

    if dd.main:  # rank 0 decodes, runs the teacher if needed and fills the cache
        train_data, val_data = _load(opened, frames), _load(val_opened, vframes)
        if calibrate:  # the calibration's teacher labels must exist before training, not after it
            for spec, seqs in val_opened:
                find_teacher_edges(spec, seqs, split, vframes, teacher_root)
    dd.barrier()
    if not dd.main:
        train_data, val_data = _load(opened, frames), _load(val_opened, vframes)
    check_labels(train_data)

    # -------------------------------------------------------------- model
    torch.manual_seed(cfg.seed)
    model = CTCNet(mcfg)
    if state is None:
        if pretrained is not None:
            load_pretrained_vgg(model, Path(pretrained))
        model.output_scale.copy_(_label_scale(train_data))
    else:
        try:
            model.load_state_dict(state["model"])
        except RuntimeError as exc:
            raise ConfigError(f"{ckpt_path} does not fit preset {p.name!r}: {str(exc).splitlines()[0]}") from None
    model.to(dd.device)
    opt = torch.optim.Adam(model.parameters(), lr=cfg.lr, betas=(cfg.beta1, 0.999))
    if state is not None:
        opt.load_state_dict(state["optimizer"])
    start_epoch = int(state["epoch"]) if state is not None else 0
    history: list[dict] = list(state["history"]) if state is not None else []
    net: torch.nn.Module = model
    if dd.world > 1:
        net = torch.nn.parallel.DistributedDataParallel(
            model, device_ids=[dd.device.index] if dd.device.type == "cuda" else None, find_unused_parameters=True)

    if dd.main:
        write_json(run_dir / "config.json", {
            "preset": p.name, "variant": variant, "model": to_dict(mcfg), "train": to_dict(cfg),
            "scenes": list(scenes), "val_scenes": list(val_scenes), "frames": frames, "val_frames": vframes,
            "split": split,
            "train_sequences": sorted(train_names), "val_sequences": [d.name for d in val_data],
            "pretrained": str(pretrained) if pretrained else None, "world_size": dd.world,
            "git_revision": git_revision(),
        })
    if progress is None:
        progress = sys.stderr.isatty()
    stale = run_dir / CALIBRATION_FILE
    if dd.main and start_epoch < cfg.epochs and stale.exists():
        log.info("removing %s: it was fitted for the weights before this training", stale)
        stale.unlink()

    # -------------------------------------------------------------- epochs
    for epoch in range(start_epoch, cfg.epochs):
        lr = cfg.lr * 0.5 ** (epoch // cfg.lr_halve_every)
        for group in opt.param_groups:
            group["lr"] = lr
        phase = "pairs" if epoch < cfg.pretrain_epochs else "windows"
        rng = np.random.default_rng([cfg.seed, epoch])
        gen = torch.Generator().manual_seed(int(rng.integers(2**31)) + dd.rank)
        torch.manual_seed(cfg.seed * 100_003 + epoch * 101 + dd.rank)  # dropout masks
        W = window_length(cfg, epoch) if phase == "windows" else 0
        batches = _pair_batches(train_data, cfg, rng) if phase == "pairs" else _window_batches(train_data, W, cfg, rng)
        # every process needs a share; batch norm needs two pairs per share (a window has several)
        min_len = (min(cfg.batch_pairs, 2) if phase == "pairs" else 1) * dd.world
        batches = [b for b in batches if len(b) >= min_len]
        if cfg.steps_per_epoch is not None:
            batches = batches[: cfg.steps_per_epoch]
        if not batches:
            raise DataError(f"epoch {epoch + 1}: no training {phase} (sequences too short for windows of {W} pairs?)")
        net.train()
        sums = {"loss": 0.0, "ctc": 0.0, "reg": 0.0}
        bar = tqdm(batches, desc=f"epoch {epoch + 1}/{cfg.epochs} {phase}" + (f" W={W}" if W else ""),
                   disable=not (progress and dd.main), leave=False)
        for step, batch in enumerate(bar):
            mine = batch[dd.rank::dd.world]
            if phase == "pairs":
                terms = _pairs_step(net, train_data, mine, cfg, label_source == "aug", gen, dd.device)
            else:
                terms = _windows_step(net, train_data, mine, W, cfg, label_source == "aug", gen, dd.device)
            items = terms.items()
            if not all(math.isfinite(v) for v in items.values()):
                raise VOError(f"non-finite loss at epoch {epoch + 1} step {step + 1} ({_fmt(items)}); "
                              f"last good checkpoint kept at {ckpt_path if ckpt_path.exists() else 'none yet'}")
            opt.zero_grad(set_to_none=True)
            terms.total.backward()
            opt.step()
            for k in sums:
                sums[k] += items[k]
            bar.set_postfix({k: f"{v:.3g}" for k, v in items.items()})
        entry: dict[str, Any] = {"epoch": epoch + 1, "phase": phase, "window": W, "lr": lr, "steps": len(batches)}
        entry.update({k: v / len(batches) for k, v in sums.items()})
        if val_data and dd.main:
            entry["val_reg"] = evaluate_reg(model, val_data, cfg, dd.device)
        history.append(entry)
        log.info("epoch %d/%d %s: %s", epoch + 1, cfg.epochs, phase,
                 _fmt({k: v for k, v in entry.items() if k in ("loss", "ctc", "reg", "val_reg")}))
        if dd.main:
            save_checkpoint(ckpt_path, model, opt, epoch + 1, p, variant, history)
            write_json(run_dir / "history.json", history)
        dd.barrier()
    cal_path = None
    if dd.main and calibrate and val_scenes:
        cal_path = run_calibration(ckpt_path, val_scenes, frames=vframes, split=split, teacher_root=teacher_root,
                                   progress=progress).path
    elif dd.main and calibrate:
        log.info("no validation scene: no calibration.json (run `learner calibrate --checkpoint %s --scene VAL` "
                 "on a scene that is neither trained nor tested on)", ckpt_path)
    return FitResult(run_dir, ckpt_path, cfg.epochs, history, cal_path)


def _fmt(d: dict) -> str:
    return ", ".join(f"{k}={v:.4g}" for k, v in d.items())


def _label_scale(data: list[SequenceData]) -> Tensor:
    """Per-dimension spread (6,) of the gap-1 training labels, used as the output scale."""
    labs = torch.cat([d.labels[1][d.mask[1]] for d in data])
    if len(labs) < 2:
        return torch.full((6,), 0.01)
    return labs.std(0).clamp(min=1e-4)


_MIRROR = torch.tensor([-1.0, 1.0, 1.0, 1.0, -1.0, -1.0])
"""Twist of a left-right mirrored motion, per component (see ``TrainConfig.flip_prob``)."""


def _mirror(x: Tensor, lab: Tensor, flip: Tensor) -> tuple[Tensor, Tensor]:
    """Mirror the samples ``flip`` (B,) bool of images ``x`` (B, ..., W) and labels
    ``lab`` (B, ..., 6)."""
    if not bool(flip.any()):
        return x, lab
    x, lab = x.clone(), lab.clone()
    x[flip] = x[flip].flip(-1)
    lab[flip] = lab[flip] * _MIRROR
    return x, lab


def _reverse(x: Tensor, lab: Tensor, rev: Tensor) -> tuple[Tensor, Tensor]:
    """Play the samples ``rev`` (B,) bool backwards: the two frames of each pair in ``x``
    (B, ..., 6, H, W) swap places, labels ``lab`` (B, ..., 6) become ``log(T^-1) = -log(T)``."""
    if not bool(rev.any()):
        return x, lab
    x, lab = x.clone(), lab.clone()
    x[rev] = torch.cat([x[rev][..., 3:, :, :], x[rev][..., :3, :, :]], dim=-3)
    lab[rev] = -lab[rev]
    return x, lab


def _pairs_step(net, data, rows: np.ndarray, cfg: TrainConfig, aug: bool, gen, device) -> L.LossTerms:
    x, labs, masks = [], [], []
    for s in np.unique(rows[:, 0]):
        r = rows[rows[:, 0] == s]
        d = data[int(s)]
        k, g = torch.from_numpy(r[:, 1]), torch.from_numpy(r[:, 2])
        x.append(d.pairs(k, k + g))
        lab, m = _labels(d, k, g, aug, gen)
        labs.append(lab)
        masks.append(m)
    x, lab = torch.cat(x), torch.cat(labs)
    if cfg.flip_prob > 0:
        x, lab = _mirror(x, lab, torch.rand(len(x), generator=gen) < cfg.flip_prob)
    if cfg.reverse_prob > 0:
        x, lab = _reverse(x, lab, torch.rand(len(x), generator=gen) < cfg.reverse_prob)
    xi_d, _ = net(x.to(device))
    return L.pair_loss(xi_d, lab.to(device), torch.cat(masks).to(device), cfg.beta)


def _windows_step(net, data, rows: np.ndarray, W: int, cfg: TrainConfig, aug: bool, gen, device) -> L.LossTerms:
    pairs = L.window_pairs(W, cfg.max_gap)
    P = len(pairs)
    pi = torch.tensor([i for i, _ in pairs])
    pg = torch.tensor([j - i for i, j in pairs])
    B = len(rows)
    # a reversed window: its pair (i, j) is the original pair (start + W - j, start + W - i)
    # played backwards (its frames swapped and its label negated by _reverse below)
    rev = (torch.rand(B, generator=gen) < cfg.reverse_prob) if cfg.reverse_prob > 0 else torch.zeros(B, dtype=torch.bool)
    x, labs, masks = [], [], []
    for b, (s, start) in enumerate(rows):
        d = data[int(s)]
        k = int(start) + W - pi - pg if rev[b] else pi + int(start)
        x.append(d.pairs(k, k + pg))
        lab, m = _labels(d, k, pg, aug, gen)
        labs.append(lab)
        masks.append(m)
    x, lab = torch.stack(x), torch.stack(labs)  # (B, P, 6, H, W), (B, P, 6)
    x, lab = _reverse(x, lab, rev)
    if cfg.flip_prob > 0:  # a whole window at a time
        x, lab = _mirror(x, lab, torch.rand(B, generator=gen) < cfg.flip_prob)
    seq_index = (torch.arange(B)[:, None] * P + torch.arange(W)[None, :]).to(device)  # gap-1 block first
    xi_d, xi_s = net(x.flatten(0, 1).to(device), seq_index)
    lab = lab.to(device)
    mask = torch.stack(masks).to(device)
    xi_d = xi_d.view(B, P, 6)
    # the LSTM's consecutive pairs share the labels of the direct gap-1 pairs
    return L.window_loss(xi_s, xi_d, lab[:, :W], mask[:, :W], lab, mask, cfg.max_gap, cfg.alpha, cfg.beta)


@torch.no_grad()
def evaluate_reg(model: CTCNet, data: list[SequenceData], cfg: TrainConfig, device: torch.device,
                 max_pairs: int = 512) -> float:
    """Mean squared error (sum over the 6 dims) of the direct head on labelled pairs."""
    was = model.training
    model.eval()
    total, count = 0.0, 0
    for d in data:
        g, k = np.nonzero(d.mask.numpy())
        for a in range(0, min(len(k), max_pairs), 64):
            kk, gg = torch.from_numpy(k[a:a + 64]), torch.from_numpy(g[a:a + 64])
            xi, _ = model(d.pairs(kk, kk + gg).to(device))
            total += float(((xi.cpu() - d.labels[gg, kk]) ** 2).sum())
            count += len(kk)
    model.train(was)
    return total / max(count, 1)
