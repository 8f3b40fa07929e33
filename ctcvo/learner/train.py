"""``learner fit``: train the network on teacher (or ground-truth) labels.

Phase 1 (the first ``pretrain_steps`` optimiser steps, every step of the ``cnn-*``
variants) trains the encoder and the direct head on single pairs with L_reg only; phase 2
trains on windows of consecutive pairs, growing from ``window_min`` to ``window_max``, with
``alpha L_ctc + beta L_reg`` and BatchNorm statistics frozen. An epoch is ``eval_every``
steps, after which the run is evaluated (:mod:`learner.evaluate`) and checkpointed
(:mod:`learner.checkpoint`); batches and augmentation live in :mod:`learner.batches` and
:mod:`learner.augment`.

:func:`resolve_fit` turns options into a :class:`FitSpec` (pure), :func:`train_loop` runs
the epochs, :func:`fit` is the entry point (processes, the run folder, the rerun rule of
:mod:`data.runs`). The run folder holds ``config.json``, ``fingerprint.json``,
``checkpoint.pt`` (a rerun of the same inputs continues from it and reaches the same
weights: every epoch re-seeds from ``(seed, epoch)``), ``history.json``, ``cache/`` and,
with validation scenes, ``calibration.json`` (:func:`learner.calibrate.calibrate`). Teacher
labels are read, never made: missing ones stop the run naming the ``teacher generate``
command. Under ``torchrun`` each process trains on its share of every batch; only rank 0
writes files.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import math
import sys
import time
from collections.abc import Sequence as TypingSequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import Tensor

from ctcvo.data.errors import ConfigError, DataError, VOError
from ctcvo.data.io import git_revision, write_json
from ctcvo.data.runs import (
    Fingerprint,
    StaleOutputError,
    claim,
    differences,
    file_digest,
    frames_id,
    output_folder,
    read_fingerprint,
    scene_id,
    stage_dir,
    upstream_digest,
    write_fingerprint,
)
from ctcvo.data.scenes import open_scene
from ctcvo.data.sequence import frame_ranges_overlap
from ctcvo.learner import loss as L
from ctcvo.learner.batches import PhaseProgress, lr_at, pair_batches, pairs_step, window_batches, window_length, windows_step
from ctcvo.learner.calibrate import CALIBRATION_FILE
from ctcvo.learner.calibrate import calibrate as run_calibration
from ctcvo.learner.checkpoint import CHECKPOINT, load_checkpoint, save_checkpoint
from ctcvo.learner.config import (
    INVDEPTH_CHANNELS,
    Preset,
    TrainConfig,
    check_variant,
    get_preset,
    model_from_dict,
    to_dict,
)
from ctcvo.learner.dataset import SequenceData, check_labels, find_teacher_edges, hull_range, load_sequences
from ctcvo.learner.device import Dist, setup_dist
from ctcvo.learner.evaluate import LABEL_NAMES, Evaluator, epoch_line, warn_if_no_skill
from ctcvo.learner.model import CTCNet, load_pretrained_vgg

log = logging.getLogger(__name__)

#: Adam's (beta1, beta2): PyTorch's defaults, never tuned here
ADAM_BETAS = (0.9, 0.999)


@dataclass
class FitResult:
    """What a training run produced."""

    run_dir: Path
    checkpoint: Path
    epochs_done: int
    history: list[dict] = field(default_factory=list)
    calibration: Path | None = None
    """calibration.json, when validation scenes were given."""


# ----------------------------------------------------------------------------------
# fit: configuration (pure), training loop, entry point (processes, files)
# ----------------------------------------------------------------------------------
class FitInterrupted(Exception):
    """Ctrl-C during ``learner fit``; the message is the one line the CLI prints."""

    def __init__(self, epoch: int, run_dir: Path) -> None:
        super().__init__(f"interrupted at epoch {epoch}; `learner fit --resume --out {run_dir}` continues")
        self.epoch, self.run_dir = epoch, run_dir


@dataclass(frozen=True)
class FitSpec:
    """Everything that shapes a training run, resolved from the options (no file read)."""

    scenes: tuple[str, ...]
    val_scenes: tuple[str, ...]
    frames: str | None
    val_frames: str | None
    """The validation sequences' range (``frames`` unless given)."""
    split: str
    variant: str
    preset: Preset
    """The preset with ``--input`` and the training overrides applied."""
    uses_lstm: bool
    label_source: str
    teacher_root: Path | None
    pretrained: Path | None
    init: Path | None
    calibrate: bool
    bf16: bool
    val_frames_given: str | None = None

    def request(self) -> dict[str, Any]:
        """The options that reproduce this spec (saved in config.json; ``--resume`` reads them)."""
        return {"scenes": list(self.scenes), "val_scenes": list(self.val_scenes), "frames": self.frames,
                "val_frames": self.val_frames_given, "split": self.split, "variant": self.variant,
                "preset": self.preset.name, "model": to_dict(self.preset.model), "train": to_dict(self.preset.train),
                "teacher_root": _str(self.teacher_root), "pretrained": _str(self.pretrained), "init": _str(self.init),
                "calibrate": self.calibrate, "bf16": self.bf16}


def _str(p: Path | None) -> str | None:
    return None if p is None else str(p)


def resolve_fit(scenes: TypingSequence[str], *, variant: str = "ctc", preset: str | Preset = "cpu",
                val_scenes: TypingSequence[str] = (), frames: str | None = None, split: str = "all",
                val_frames: str | None = None, input: str | None = None, teacher_root: Path | None = None,
                pretrained: Path | None = None, init: Path | None = None, calibrate: bool = True,
                bf16: bool = False, **train_overrides: Any) -> FitSpec:
    """The :class:`FitSpec` of :func:`fit`'s options (pure: reads no file, starts nothing).

    ``train_overrides`` replace fields of the preset's :class:`TrainConfig` (``steps``
    alone keeps the preset's proportions of phase-1 and warm-up steps); ``input`` replaces
    ``ModelConfig.input``; the variant then fixes ``alpha`` (0 without CTC) and the phase-1
    length (every step for the ``cnn-*`` variants)."""
    if not scenes:
        raise ConfigError("give at least one --scene")
    uses_lstm, label_source, uses_ctc = check_variant(variant)
    p = get_preset(preset) if isinstance(preset, str) else preset
    if input is not None:
        try:
            p = dataclasses.replace(p, model=dataclasses.replace(p.model, input=input))
        except ConfigError as exc:
            raise ConfigError(f"--input: {exc}") from None
    overrides = {k: v for k, v in train_overrides.items() if v is not None}
    if "steps" in overrides:  # keep the preset's proportions
        n = overrides["steps"]
        overrides.setdefault("pretrain_steps", min(n, int(round(n * p.train.pretrain_steps / p.train.steps))))
        overrides.setdefault("warmup_steps", int(round(n * p.train.warmup_steps / p.train.steps)))
        overrides.setdefault("eval_every", max(1, min(p.train.eval_every, n)))
    try:
        cfg = dataclasses.replace(p.train, **overrides)
    except TypeError as exc:
        raise ConfigError(f"unknown training option: {exc}") from None
    if cfg.scale_aug > 0 and p.model.input not in INVDEPTH_CHANNELS:
        raise ConfigError(f"--scale-aug needs an input with depth ({', '.join(INVDEPTH_CHANNELS)}), "
                          f"not {p.model.input!r}")
    if not uses_ctc:
        cfg = dataclasses.replace(cfg, alpha=0.0)
    if not uses_lstm:
        cfg = dataclasses.replace(cfg, pretrain_steps=cfg.steps)
    p = dataclasses.replace(p, train=cfg)
    return FitSpec(tuple(scenes), tuple(val_scenes), frames, frames if val_frames is None else val_frames, split,
                   variant, p, uses_lstm, label_source, _path(teacher_root), _path(pretrained), _path(init),
                   bool(calibrate), bool(bf16), val_frames)


TRAIN_FIELDS = frozenset(f.name for f in dataclasses.fields(TrainConfig))


def _plain(v: Any) -> Any:
    """An option as config.json holds it (paths as strings, sequences as lists)."""
    if isinstance(v, Path):
        return str(v)
    if isinstance(v, (list, tuple)):
        return [_plain(x) for x in v]
    return v


def _path(p: Path | str | None) -> Path | None:
    return None if p is None else Path(p)


def saved_options(run_dir: Path) -> dict[str, Any]:
    """The options of the training run in ``run_dir`` (its config.json), as :func:`fit` takes them."""
    path = Path(run_dir) / "config.json"
    if not path.is_file():
        raise DataError(f"{run_dir} holds no training run to resume (no config.json); start one with --scene")
    try:
        req = json.loads(path.read_text())["request"]
        preset = dataclasses.replace(get_preset(req["preset"]), model=model_from_dict(req["model"]))
    except (OSError, ValueError, KeyError, TypeError, ConfigError) as exc:
        raise DataError(f"{path} cannot be resumed (written by an older version?): {exc}") from None
    opts = {k: v for k, v in req.items() if k not in ("model", "train")}
    opts["preset"] = preset
    opts.update(req["train"])
    return opts


def fingerprint(spec: FitSpec, train_seqs: list[tuple[str, list]], val_seqs: list[tuple[str, list]],
                labels: dict[str, str]) -> Fingerprint:
    """The inputs of a training run: scenes, frames, variant, preset and resolved configs,
    the digests of the teacher labels and of the starting weights."""
    def seqs(items: list[tuple[str, list]]) -> list[list[str]]:
        return [[scene_id(spec_), s.name, frames_id(s.ids())] for spec_, ss in items for s in ss]

    return Fingerprint("learner", {
        "train_sequences": seqs(train_seqs), "val_sequences": seqs(val_seqs), "variant": spec.variant,
        "preset": spec.preset.name, "model": to_dict(spec.preset.model), "train": to_dict(spec.preset.train),
        "labels": labels, "pretrained": file_digest(spec.pretrained) if spec.pretrained else None,
        "init": file_digest(spec.init) if spec.init else None, "bf16": spec.bf16, "calibrate": spec.calibrate,
    })


def _finished(run_dir: Path, spec: FitSpec) -> tuple[bool, dict | None]:
    """(done, checkpoint state) of the run in ``run_dir``."""
    ckpt = run_dir / CHECKPOINT
    if not ckpt.is_file():
        return False, None
    state = load_checkpoint(ckpt)
    done = int(state["epoch"]) >= spec.preset.train.epochs
    if done and spec.calibrate and spec.val_scenes:
        done = (run_dir / CALIBRATION_FILE).is_file()
    return done, state


def _check_resumable(state: dict, ckpt_path: Path, spec: FitSpec) -> None:
    p = spec.preset
    if state["preset"] != p.name:
        raise ConfigError(f"{ckpt_path} was trained with preset {state['preset']!r}, not {p.name!r}")
    if state["model_config"] != to_dict(p.model):
        raise ConfigError(f"{ckpt_path} was trained with another network shape of preset {p.name!r} "
                          "(the preset changed since); start a new run")
    if state["variant"] != spec.variant:
        raise ConfigError(f"{ckpt_path} was trained as variant {state['variant']!r}, not {spec.variant!r}")


def _teacher_labels(spec: FitSpec, opened: list[tuple[str, list]], val_opened: list[tuple[str, list]]
                    ) -> dict[str, str]:
    """Check that teacher labels cover every frame range the run uses (training and
    validation; a missing scene is named with the hull of its ranges, so one teacher run
    covers them all); return the digest of each sequence's labels."""
    need_train = spec.label_source in ("teacher", "aug")
    need_val = need_train or (spec.calibrate and bool(spec.val_scenes))
    ranges: dict[str, list[str | None]] = {}
    if need_train:
        for s in spec.scenes:
            ranges.setdefault(s, []).append(spec.frames)
    if need_val:
        for s in spec.val_scenes:
            ranges.setdefault(s, []).append(spec.val_frames)
    for s, rs in ranges.items():
        hull = hull_range(rs)
        find_teacher_edges(s, open_scene(s, split=spec.split, frames=hull), spec.split, hull, spec.teacher_root)
    digests: dict[str, str] = {}
    for items, frames, needed in ((opened, spec.frames, need_train), (val_opened, spec.val_frames, need_val)):
        if not needed:
            continue
        for s, seqs in items:
            for g2o in find_teacher_edges(s, seqs, spec.split, frames, spec.teacher_root):
                digests[f"{scene_id(s)}:{g2o.parent.name}"] = upstream_digest(g2o.parent, "edges.g2o")
    return digests


def fit(scenes: TypingSequence[str] = (), *, out: Path | None = None, resume: bool = False,
        overwrite: bool = False, device: str = "auto", progress: bool | None = None,
        **options: Any) -> FitResult:
    """Train a learner on the sequences of ``scenes`` and return the run's outputs.

    ``options`` are those of :func:`resolve_fit` (``variant``, ``preset``, ``val_scenes``,
    ``frames``, ``val_frames``, ``split``, ``input``, ``teacher_root``, ``pretrained``,
    ``init`` (fine-tune from another checkpoint's weights with a fresh optimiser and
    schedule), ``calibrate`` (fit calibration.json on the validation scenes' teacher labels
    at the end), ``bf16``, and training overrides such as ``steps=300``); ``device``:
    ``auto`` (CUDA when available), ``cpu`` or ``cuda``. A validation sequence may be a
    training sequence only with a disjoint range (train 0:375, validate 375:450).

    The run folder ``out`` (default ``runs/<first scene>/learner``) follows the rerun rule
    of :mod:`data.runs`: a run of the same inputs is kept when finished and continued
    from its checkpoint when not; a run of other inputs is replaced with ``overwrite``,
    otherwise an error. ``resume`` continues the run in ``out`` with its saved options
    (``options`` given here, all optional then, replace them; only training-schedule
    changes, such as more ``steps``, are accepted for an existing checkpoint).
    """
    options = {k: v for k, v in options.items() if v is not None}
    if resume:
        if out is None and not scenes:
            raise ConfigError("--resume needs --out DIR (the run to continue)")
        run_dir = Path(out) if out is not None else stage_dir(scenes[0], "learner")
        saved = saved_options(run_dir)
        given = {"scenes": list(scenes), **options} if scenes else options
        changed = [f"{k}: {saved[k]} -> {v}" for k, v in given.items()
                   if k in saved and k not in ("preset", "variant", "train") and k not in TRAIN_FIELDS
                   and _plain(v) != _plain(saved[k])]
        if changed:
            raise StaleOutputError(f"{run_dir} was trained with other options than those given with --resume "
                                   f"({'; '.join(changed)}); start a new run with another --out")
        options = {**saved, **options}
        scenes = list(scenes) or saved["scenes"]
        options.pop("scenes", None)
    spec = resolve_fit(scenes, **options)
    run_dir = Path(out) if out is not None else stage_dir(spec.scenes[0], "learner")
    dd = setup_dist(device)
    if progress is None:
        progress = sys.stderr.isatty()
    with output_folder(run_dir):
        return _fit(spec, run_dir, dd, resume=resume, overwrite=overwrite, progress=progress, device=device)


def _fit(spec: FitSpec, run_dir: Path, dd: Dist, *, resume: bool, overwrite: bool, progress: bool,
         device: str) -> FitResult:
    """The files and processes around :func:`train_loop`: scenes, teacher labels, the rerun
    rule, the cached data, the model, config.json / fingerprint.json, the calibration."""
    cfg = spec.preset.train
    ckpt_path = run_dir / CHECKPOINT
    if resume and ckpt_path.is_file():
        _check_resumable(load_checkpoint(ckpt_path), ckpt_path, spec)
    opened, val_opened = _open_scenes(spec)
    fp = fingerprint(spec, opened, val_opened, _teacher_labels(spec, opened, val_opened))
    kept, state = _claim_run(spec, run_dir, dd, fp, resume=resume, overwrite=overwrite)
    if kept is not None:
        return kept
    train_data, val_data, scale = _load_data(spec, opened, val_opened, run_dir / "cache", dd)
    evaluator = Evaluator(train_data, val_data, spec.uses_lstm, cfg.window_max)
    model, opt = _build_model(spec, state, scale, dd.device, ckpt_path)
    start_epoch = int(state["epoch"]) if state is not None else 0
    history: list[dict] = list(state["history"]) if state is not None else []
    if dd.main:
        write_json(run_dir / "config.json", {
            "preset": spec.preset.name, "variant": spec.variant, "model": to_dict(spec.preset.model),
            "train": to_dict(cfg), "scenes": list(spec.scenes), "val_scenes": list(spec.val_scenes),
            "frames": spec.frames, "val_frames": spec.val_frames, "split": spec.split,
            "train_sequences": sorted({s.name for _, seqs in opened for s in seqs}),
            "val_sequences": [d.name for d in val_data], "pretrained": _str(spec.pretrained), "init": _str(spec.init),
            "world_size": dd.world, "git_revision": git_revision(), "request": spec.request(),
        })
        write_fingerprint(run_dir, fp)
    stale = run_dir / CALIBRATION_FILE
    if dd.main and start_epoch < cfg.epochs and stale.exists():
        log.info("removing %s: it was fitted for the weights before this training", stale)
        stale.unlink()
    if start_epoch > 0:
        log.info("resuming %s after epoch %d/%d (step %d of %d)", run_dir, start_epoch, cfg.epochs,
                 min(start_epoch * cfg.eval_every, cfg.steps), cfg.steps)
    history = train_loop(model, opt, train_data, scale, evaluator, spec, dd, start_epoch=start_epoch,
                         history=history, run_dir=run_dir, progress=progress)
    if dd.main and history:
        warn_if_no_skill(history[-1])
    cal_path = None
    if dd.main and spec.calibrate and spec.val_scenes:
        cal_path = run_calibration(ckpt_path, list(spec.val_scenes), frames=spec.val_frames, split=spec.split,
                                   teacher_root=spec.teacher_root, progress=progress, device=device).path
    elif dd.main and spec.calibrate:
        log.info("no validation scene: no calibration.json (run `learner calibrate --checkpoint %s --scene VAL` "
                 "on a scene that is neither trained nor tested on)", ckpt_path)
    return FitResult(run_dir, ckpt_path, cfg.epochs, history, cal_path)


def _open_scenes(spec: FitSpec) -> tuple[list[tuple[str, list]], list[tuple[str, list]]]:
    """(scene, sequences) of the training and of the validation scenes; a validation
    sequence that is also a training one needs a disjoint frame range."""
    opened = [(s, open_scene(s, split=spec.split, frames=spec.frames)) for s in spec.scenes]
    val_opened = [(s, open_scene(s, split=spec.split, frames=spec.val_frames)) for s in spec.val_scenes]
    clash = {s.name for _, seqs in opened for s in seqs} & {s.name for _, seqs in val_opened for s in seqs}
    if clash and frame_ranges_overlap(spec.frames, spec.val_frames):
        raise ConfigError(f"validation sequence(s) {', '.join(sorted(clash))} are also training sequences (frames "
                          f"{spec.frames or 'all'} and {spec.val_frames or 'all'}): give disjoint --frames / --val-frames")
    return opened, val_opened


def _claim_run(spec: FitSpec, run_dir: Path, dd: Dist, fp: Fingerprint, *, resume: bool,
               overwrite: bool) -> tuple[FitResult | None, dict | None]:
    """The rerun rule of :mod:`data.runs` for the run folder: (the kept result of a finished
    run of the same inputs, None) or (None, the checkpoint state to continue from or None)."""
    cfg = spec.preset.train
    ckpt_path = run_dir / CHECKPOINT
    done, state = _finished(run_dir, spec)
    old = read_fingerprint(run_dir)
    if resume and state is not None and old is not None and old["digest"] != fp.digest:
        diff = differences(old["inputs"], fp.inputs, limit=99)
        if all(part.startswith("train.") for part in diff.split("; ")):
            log.info("resuming %s with a new schedule (%s)", run_dir, diff)
            old = None
            done = int(state["epoch"]) >= cfg.epochs and done
        else:
            raise StaleOutputError(f"{run_dir} was trained on other inputs than those given with --resume ({diff})")
    if old is not None and claim(run_dir, fp, done=done, has_outputs=state is not None, overwrite=overwrite,
                                 outputs=RUN_FILES if dd.main else ()):
        log.info("%s: finished training of the same inputs (epoch %d/%d): kept (--overwrite to train again)",
                 run_dir, state["epoch"], cfg.epochs)
        history = state.get("history", [])
        cal = run_dir / CALIBRATION_FILE
        return FitResult(run_dir, ckpt_path, int(state["epoch"]), history, cal if cal.is_file() else None), None
    if old is None and state is not None and not resume:  # a checkpoint without (matching) fingerprint
        claim(run_dir, fp, done=False, has_outputs=True, overwrite=overwrite, outputs=RUN_FILES if dd.main else ())
    dd.barrier()  # rank 0 removed a replaced run's files
    if not ckpt_path.is_file():
        state = None
    if state is not None:
        _check_resumable(state, ckpt_path, spec)
    return None, state


def _load_data(spec: FitSpec, opened: list[tuple[str, list]], val_opened: list[tuple[str, list]], cache: Path,
               dd: Dist) -> tuple[list[SequenceData], list[SequenceData], Tensor]:
    """Training and validation data (frames cached by rank 0 first; on the GPU with CUDA)
    and the target scale (G+1, 6) of the training labels."""
    cfg, mcfg = spec.preset.train, spec.preset.model

    def load(items: list[tuple[str, list]], frame_range: str | None) -> list[SequenceData]:
        out: list[SequenceData] = []
        for s, seqs in items:
            out += load_sequences(s, seqs, width=mcfg.width, height=mcfg.height, max_gap=cfg.max_gap,
                                  label_source=spec.label_source, cache_dir=cache, split=spec.split,
                                  frames=frame_range, teacher_root=spec.teacher_root, mode=mcfg.input)
        return out

    if dd.main:  # rank 0 decodes and fills the cache
        train_data, val_data = load(opened, spec.frames), load(val_opened, spec.val_frames)
    dd.barrier()
    if not dd.main:
        train_data, val_data = load(opened, spec.frames), load(val_opened, spec.val_frames)
    check_labels(train_data)
    scale = L.target_scale(torch.cat([d.labels for d in train_data], 1), torch.cat([d.mask for d in train_data], 1))
    log.info("target scale (gap-1 RMS of the %s it trains on): v %s mm, w %s mrad",
             LABEL_NAMES[spec.label_source], np.array2string(scale[1, :3].numpy() * 1e3, precision=2),
             np.array2string(scale[1, 3:].numpy() * 1e3, precision=2))
    if dd.device.type == "cuda":  # the cached frames live on the GPU: no host-to-device copy per step
        for d in train_data + val_data:
            d.frames = d.frames.to(dd.device)
    return train_data, val_data, scale.to(dd.device)


#: the files of a training run (removed by ``--overwrite`` before training anew)
RUN_FILES = (CHECKPOINT, "history.json", "config.json", CALIBRATION_FILE)


def _build_model(spec: FitSpec, state: dict | None, scale: Tensor, device: torch.device, ckpt_path: Path
                 ) -> tuple[CTCNet, torch.optim.Optimizer]:
    """The network (fresh, fine-tuned from ``spec.init``, or the checkpoint's) and its optimiser."""
    p, cfg, mcfg = spec.preset, spec.preset.train, spec.preset.model
    torch.manual_seed(cfg.seed)
    model = CTCNet(mcfg)
    if state is None and spec.init is not None:
        src = load_checkpoint(spec.init)
        if src["model_config"] != to_dict(mcfg):
            raise ConfigError(f"--init {spec.init} has another network shape or input than preset {p.name!r} "
                              f"(input {mcfg.input!r}): {src['preset']!r} with input {src['model_config'].get('input')!r}")
        model.load_state_dict(src["model"])  # keeps the output scale its weights were trained with
        log.info("fine-tuning %s (%s, %s, %d steps)", spec.init, src["preset"], src["variant"],
                 src["history"][-1]["steps"] if src.get("history") else 0)
    elif state is None:
        if spec.pretrained is not None:
            load_pretrained_vgg(model, spec.pretrained)
        model.output_scale.copy_(scale[1])
    else:
        try:
            model.load_state_dict(state["model"])
        except RuntimeError as exc:
            raise ConfigError(f"{ckpt_path} does not fit preset {p.name!r}: {str(exc).splitlines()[0]}") from None
    model.to(device)
    opt = torch.optim.Adam(model.parameters(), lr=cfg.lr, betas=ADAM_BETAS)
    if state is not None:
        opt.load_state_dict(state["optimizer"])
    return model, opt


def train_loop(model: CTCNet, opt: torch.optim.Optimizer, train_data: list[SequenceData], scale: Tensor,
               evaluator: Evaluator, spec: FitSpec, dd: Dist, *, start_epoch: int, history: list[dict],
               run_dir: Path, progress: bool) -> list[dict]:
    """Train epochs ``start_epoch .. epochs-1``; after each one evaluate, log, and (rank 0)
    write the checkpoint and history.json. Every epoch re-seeds its shuffling, dropout and
    label noise from ``(seed, epoch)``, so a resumed run reaches the same weights. Ctrl-C
    raises :class:`FitInterrupted`."""
    cfg = spec.preset.train
    ckpt_path = run_dir / CHECKPOINT
    net: torch.nn.Module = model
    if dd.world > 1:
        net = torch.nn.parallel.DistributedDataParallel(
            model, device_ids=[dd.device.index] if dd.device.type == "cuda" else None, find_unused_parameters=True)
    aug = spec.label_source == "aug"
    epoch = start_epoch
    bars = PhaseProgress(cfg, progress and dd.main)
    try:
        for epoch in range(start_epoch, cfg.epochs):
            history.append(_train_epoch(net, model, opt, train_data, scale, evaluator, spec, dd, epoch, aug,
                                        ckpt_path, bars))
            if dd.main:
                log.info("epoch %d/%d (step %d): %s", epoch + 1, cfg.epochs, history[-1]["steps"],
                         epoch_line(history[-1]))
                save_checkpoint(ckpt_path, model, opt, epoch + 1, spec.preset, spec.variant, history)
                write_json(run_dir / "history.json", history)
            dd.barrier()
    except KeyboardInterrupt:
        raise FitInterrupted(epoch + 1, run_dir) from None
    finally:
        bars.close()
    return history


def _train_epoch(net: torch.nn.Module, model: CTCNet, opt: torch.optim.Optimizer, train_data: list[SequenceData],
                 scale: Tensor, evaluator: Evaluator, spec: FitSpec, dd: Dist, epoch: int, aug: bool,
                 ckpt_path: Path, bars: PhaseProgress) -> dict[str, Any]:
    """One epoch of ``eval_every`` optimiser steps; its history entry."""
    cfg = spec.preset.train
    first, last = epoch * cfg.eval_every, min((epoch + 1) * cfg.eval_every, cfg.steps)
    n_pairs = max(0, min(last, cfg.pretrain_steps) - first)
    n_windows = (last - first) - n_pairs
    rng = np.random.default_rng([cfg.seed, epoch])
    gen = torch.Generator().manual_seed(int(rng.integers(2**31)) + dd.rank)
    torch.manual_seed(cfg.seed * 100_003 + epoch * 101 + dd.rank)  # dropout masks
    W = window_length(cfg, epoch) if n_windows else 0
    # every process needs a share of each batch
    plan = [("pairs", b) for b in (pair_batches(train_data, cfg, rng, n_pairs) if n_pairs else [])]
    if n_windows:
        wins = window_batches(train_data, W, cfg, rng, n_windows)
        if not wins:
            raise DataError(f"epoch {epoch + 1}: no training windows (sequences too short for windows of {W} pairs)")
        plan += [("windows", b) for b in wins]
    if any(len(b) < dd.world for _, b in plan):
        raise DataError(f"epoch {epoch + 1}: batches smaller than the {dd.world} processes")
    net.train()
    t_epoch = time.perf_counter()
    sums: dict[str, dict[str, float]] = {}
    for i, (phase, batch) in enumerate(plan):
        step = first + i
        for group in opt.param_groups:
            group["lr"] = lr_at(cfg, step)
        if phase == "windows":  # since 07e1812 (issue 11); live statistics were never A/B-tested (bench/README.md)
            _freeze_batchnorm(model)
        mine = batch[dd.rank::dd.world]
        with torch.autocast(dd.device.type, dtype=torch.bfloat16, enabled=spec.bf16):
            if phase == "pairs":
                terms = pairs_step(net, train_data, mine, cfg, aug, gen, dd.device, scale)
            else:
                terms = windows_step(net, train_data, mine, W, cfg, aug, gen, dd.device, scale)
        items = terms.items()
        if not all(math.isfinite(v) for v in items.values()):
            raise VOError(f"non-finite loss at step {step + 1} (epoch {epoch + 1}, {_fmt(items)}); "
                          f"last good checkpoint kept at {ckpt_path if ckpt_path.exists() else 'none yet'}")
        opt.zero_grad(set_to_none=True)
        terms.total.backward()
        opt.step()
        acc = sums.setdefault(phase, {"loss": 0.0, "ctc": 0.0, "reg": 0.0, "steps": 0})
        for k in items:
            acc[k] += items[k]
        acc["steps"] += 1
        bars.step(phase, step, {"epoch": f"{epoch + 1}/{cfg.epochs}", **({"W": str(W)} if W else {}),
                                **{k: f"{v:.3g}" for k, v in items.items()}})
    entry: dict[str, Any] = {"epoch": epoch + 1, "steps": last, "phase": "+".join(sums), "window": W,
                             "lr": lr_at(cfg, last - 1), "train_seconds": round(time.perf_counter() - t_epoch, 2),
                             "labels": spec.label_source}
    for phase, acc in sums.items():  # losses are normalised: 1.0 = zero motion on the labels
        entry.update({f"{phase}_{k}": acc[k] / acc["steps"] for k in ("loss", "ctc", "reg")})
    if dd.main:
        entry.update(evaluator(model, dd.device))
    return entry


def _fmt(d: dict) -> str:
    return ", ".join(f"{k}={v:.4g}" for k, v in d.items())


def _freeze_batchnorm(model: torch.nn.Module) -> None:
    """Put every BatchNorm layer in eval mode: phase 2 normalises with phase 1's running
    statistics (a batch of a few windows of correlated pairs has other statistics than test
    time); the affine parameters still train."""
    for m in model.modules():
        if isinstance(m, torch.nn.modules.batchnorm._BatchNorm):
            m.eval()
