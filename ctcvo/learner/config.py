"""Frozen configurations of the learner: model shape, training schedule, prediction.

Presets are instances (:data:`PRESETS`); change one with :func:`dataclasses.replace`, never
by mutation. The resolved configuration is saved as JSON next to every run
(``config.json``) and inside every checkpoint.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Any

from ctcvo.data.errors import ConfigError

#: encoder inputs (``ModelConfig.input``) and their channels: the paper's stacked RGB pair,
#: plus both frames' inverse depth, plus the pair's optical flow (DIS) and the first frame's
#: inverse depth; ``flowd`` is the flow and both frames' inverse depth without colour
INPUTS: dict[str, int] = {"rgb": 6, "rgbd": 8, "flow": 9, "flowd": 4}
#: the channel holding the horizontal flow, per input with flow (mirroring negates it)
FLOW_U_CHANNEL: dict[str, int] = {"flow": 6, "flowd": 0}
#: the channels holding inverse depth, per input with depth (scale augmentation divides them)
INVDEPTH_CHANNELS: dict[str, tuple[int, ...]] = {"rgbd": (6, 7), "flow": (8,), "flowd": (2, 3)}
#: conv widths of the VGG-11 stack (the ``M`` max-pools sit after conv 1, 2, 4, 6 and 8)
VGG11_WIDTHS: tuple[int, ...] = (64, 128, 256, 256, 512, 512, 512, 512)
#: the VGG-11 layout: an int is a 3x3 conv (index into the widths), ``"M"`` a 2x2 max-pool
VGG11_LAYOUT: tuple[Any, ...] = (0, "M", 1, "M", 2, 3, "M", 4, 5, "M", 6, 7, "M")


@dataclass(frozen=True)
class ModelConfig:
    """Shape of the CTCNet-style network (encoder, direct head, LSTM head)."""

    width: int = 320
    """Input image width in pixels (frames are resized to it once and cached)."""
    height: int = 240
    """Input image height in pixels."""
    conv_widths: tuple[int, ...] = VGG11_WIDTHS
    """Output channels of the eight 3x3 conv+BN+ReLU layers of the VGG-11-BN stack."""
    strided_widths: tuple[int, int] = (1024, 1024)
    """Output channels of the two 3x3 stride-2 convs after the VGG stack."""
    latent_dim: int = 1080
    """C, channels of the final 1x1 conv; global-average-pooled to the C-dim latent."""
    fc_dim: int = 1080
    """Width of the direct head's penultimate FC layer (dropout is applied after it)."""
    lstm_hidden: int = 1000
    """Units of the one-layer LSTM of the sequential head."""
    dropout: float = 0.3
    """Drop probability at the direct head's penultimate FC and at the LSTM output during
    training. The paper's 0.7 is read as TensorFlow's *keep* probability (drop 0.3)."""
    input: str = "rgb"
    """What the encoder sees of a pair (i, j): ``rgb`` the paper's two stacked RGB frames (6
    channels); ``rgbd`` plus both frames' inverse depth (8); ``flow`` the RGB pair plus the
    DIS optical flow i -> j and frame i's inverse depth (9); ``flowd`` the flow i -> j and
    both frames' inverse depth, no colour (4). Not in the paper (it lists RGB-D as future
    work); see bench/README.md for what each brings."""

    def __post_init__(self) -> None:
        if self.input not in INPUTS:
            raise ConfigError(f"input must be {', '.join(INPUTS)}, got {self.input!r}")
        if len(self.conv_widths) != 8 or len(self.strided_widths) != 2:
            raise ConfigError("conv_widths needs 8 entries and strided_widths 2")
        if min(self.width, self.height) < 32:
            raise ConfigError(f"input must be at least 32x32 for five 2x2 pools, got {self.width}x{self.height}")
        if not 0.0 <= self.dropout < 1.0:
            raise ConfigError(f"dropout must be in [0, 1), got {self.dropout}")


@dataclass(frozen=True)
class TrainConfig:
    """Training schedule (two phases, counted in optimiser steps), loss and augmentation.

    An *epoch* is ``eval_every`` optimiser steps: the unit of logging, evaluation,
    checkpointing and window growth, not a pass over the data.
    """

    steps: int = 60000
    """Total optimiser steps (phase 1 + phase 2)."""
    pretrain_steps: int = 20000
    """Phase-1 steps: encoder + direct head on single pairs of gaps 1..max_gap, L_reg only
    (every step for the ``cnn-*`` variants)."""
    eval_every: int = 1000
    """Steps per epoch: evaluation, log line and checkpoint after each."""
    max_gap: int = 5
    """Largest frame gap of a direct-head pair (phase-1 pairs and the CTC's G)."""
    batch_pairs: int = 32
    """Phase 1: pairs per optimiser step (global, split across DDP processes)."""
    batch_windows: int = 4
    """Phase 2: windows per optimiser step (global, split across DDP processes)."""
    window_min: int = 3
    """Phase 2: window length (consecutive pairs) of its first epoch."""
    window_max: int = 18
    """Phase 2: window length of its last epoch (grows linearly in between)."""
    alpha: float = 1.0
    """Weight of the composite transformation constraint L_ctc."""
    beta: float = 3.0
    """Weight of the label regression L_reg."""
    lr: float = 1e-4
    """Peak Adam learning rate, reached after the warm-up and decayed by a cosine."""
    warmup_steps: int = 500
    """Linear learning-rate warm-up from 0 over this many steps."""
    seed: int = 0
    """Seed of sampling, dropout, label noise and initialisation."""
    flip_prob: float = 0.0
    """Mirror each training pair or window left-right with this probability, its labels
    ``(v, w) -> (-vx, vy, vz, wx, -wy, -wz)`` with it (exact for a centred principal point)."""
    reverse_prob: float = 0.0
    """Play each training pair or window backwards with this probability, its labels
    negated (exact)."""
    scale_aug: float = 0.0
    """Depth-scale augmentation (inputs with depth only): each pair or window is drawn as
    if the world were scaled by ``2**u``, ``u`` uniform in [-scale_aug, scale_aug] (exact)."""

    @property
    def epochs(self) -> int:
        """Number of epochs of ``eval_every`` steps (the last one may be shorter)."""
        return -(-self.steps // self.eval_every)

    def __post_init__(self) -> None:
        if self.steps < 1 or not 0 <= self.pretrain_steps <= self.steps or self.eval_every < 1:
            raise ConfigError(f"need steps >= 1, 0 <= pretrain_steps <= steps and eval_every >= 1, got "
                              f"{self.steps}/{self.pretrain_steps}/{self.eval_every}")
        if not 0 <= self.warmup_steps or self.lr <= 0:
            raise ConfigError("need lr > 0 and warmup_steps >= 0")
        if self.max_gap < 1 or self.window_min < 1 or self.window_max < self.window_min:
            raise ConfigError("need max_gap >= 1 and 1 <= window_min <= window_max")
        if self.batch_pairs < 1 or self.batch_windows < 1:
            raise ConfigError("batch sizes must be positive")
        if not (self.alpha >= 0 and self.beta >= 0):
            raise ConfigError(f"need alpha >= 0 and beta >= 0, got {self.alpha} and {self.beta}")
        for name in ("flip_prob", "reverse_prob"):
            if not 0.0 <= getattr(self, name) <= 1.0:
                raise ConfigError(f"{name} must be in [0, 1], got {getattr(self, name)}")
        if not 0.0 <= self.scale_aug <= 3.0:
            raise ConfigError(f"scale_aug must be in [0, 3] (log2 of the largest scale), got {self.scale_aug}")


@dataclass(frozen=True)
class PredictConfig:
    """Monte-Carlo-dropout prediction."""

    samples: int = 10
    """K, stochastic passes per pair (dropout resampled, conv features computed once)."""
    drop: float = 0.1
    """Drop probability of the MC passes (the paper uses 10%)."""
    max_gap: int = 5
    """Direct-head edges are written for gaps 2..max_gap besides the gap-1 edges."""

    def __post_init__(self) -> None:
        if self.samples < 1:
            raise ConfigError(f"--samples must be >= 1, got {self.samples}")
        if not 0.0 <= self.drop < 1.0:
            raise ConfigError(f"drop ratio must be in [0, 1), got {self.drop}")
        if self.max_gap < 1:
            raise ConfigError(f"--max-gap must be >= 1, got {self.max_gap}")


@dataclass(frozen=True)
class CalibrationConfig:
    """Post-hoc calibration of the MC-dropout covariances against teacher labels
    (:mod:`learner.calibrate`): per edge group and dimension, ``r_d ~ N(0, a_d c_dd + b_d + t_dd)``."""

    min_pairs: int = 30
    """Fewest labelled pairs for a group of its own (head and gap); smaller groups fall
    back to their head's fit, then to the fit of every pair."""
    trim_z: float = 4.0
    """Pairs beyond this many calibrated standard deviations in a dimension are left out
    of its fit (re-estimated until stable)."""
    max_iterations: int = 10
    """Rounds of fitting and trimming."""
    fit_floor: bool = True
    """Fit the floor ``b``; ``False`` fits the scale ``a`` alone (plain variance scaling)."""
    teacher_variance: bool = True
    """Model the teacher's own variance in the residual, so that ``a, b`` describe the
    learner's error only."""
    min_variance: float = 1e-8
    """Lower bound of ``b`` (m^2 / rad^2): no dimension is claimed more precise than
    0.1 mm / 0.1 mrad."""

    def __post_init__(self) -> None:
        if self.min_pairs < 3 or self.trim_z <= 1.0 or self.max_iterations < 1 or self.min_variance <= 0:
            raise ConfigError("calibration needs min_pairs >= 3, trim_z > 1, max_iterations >= 1, min_variance > 0")


@dataclass(frozen=True)
class Preset:
    """A named pair of model and training configurations."""

    name: str
    """Preset name (stored in checkpoints; a checkpoint only loads with its own preset)."""
    model: ModelConfig = field(default_factory=ModelConfig)
    """Network shape."""
    train: TrainConfig = field(default_factory=TrainConfig)
    """Training schedule."""


def _div(widths: tuple[int, ...], k: int) -> tuple[int, ...]:
    return tuple(max(1, w // k) for w in widths)


#: The paper's network: 320x240 input, full VGG-11 widths, C = 1080, LSTM 1000.
PAPER = Preset("paper", ModelConfig(), TrainConfig())
#: A network that trains on a 2-core CPU: 128x96 input, VGG-11 widths / 8 (8..64
#: channels), strided convs 256, C = 256, LSTM 256, RGB + flow + inverse depth input;
#: 1500 optimiser steps (1000 on single pairs), lr 1e-3 after a 100-step warm-up, half the
#: pairs and windows played backwards. Widths, input and reversal were chosen on the
#: validation range redkitchen 350:450, trained on 0:350 (bench/README.md, "Learner").
CPU = Preset(
    "cpu",
    ModelConfig(width=128, height=96, conv_widths=_div(VGG11_WIDTHS, 8), strided_widths=(256, 256),
                latent_dim=256, fc_dim=256, lstm_hidden=256, input="flow"),
    TrainConfig(steps=1500, pretrain_steps=1000, eval_every=100, batch_pairs=32, batch_windows=2, window_max=18,
                lr=1e-3, warmup_steps=100, reverse_prob=0.5),
)
#: A toy network for the tests only (it learns nothing useful).
TINY = Preset(
    "tiny",
    ModelConfig(width=64, height=48, conv_widths=_div(VGG11_WIDTHS, 16), strided_widths=(16, 16),
                latent_dim=16, fc_dim=16, lstm_hidden=16),
    TrainConfig(steps=4, pretrain_steps=2, eval_every=2, max_gap=3, batch_pairs=4, batch_windows=2, window_min=3,
                window_max=4, lr=1e-3, warmup_steps=0),
)
#: The demo's learner: the cpu preset on the flow and both frames' inverse depth, no
#: colour (0.81x zero motion's se(3) L2 on the validation scene lab, trained on office,
#: against 1.05-1.12x with the cpu preset's RGB + flow input, which fits the one training
#: room's appearance), with depth scaling (|u| <= 1) and left-right mirroring besides time
#: reversal (chosen on the validation scenes lab, lab at double speed and room-0..3, two
#: seeds: all six below zero motion, mean 0.82-0.88x, against two of six above it without;
#: bench/README.md, "Learner: does it learn?", 5 and 6).
DEMO = Preset("demo", dataclasses.replace(CPU.model, input="flowd"),
              dataclasses.replace(CPU.train, scale_aug=1.0, flip_prob=0.5))
PRESETS: dict[str, Preset] = {p.name: p for p in (PAPER, CPU, TINY, DEMO)}

#: variant -> (uses LSTM, label source, CTC on)
VARIANTS: dict[str, tuple[bool, str, bool]] = {
    "cnn-gt": (False, "gt", False),
    "lstm-gt": (True, "gt", False),
    "cnn-unsup": (False, "teacher", False),
    "lstm-unsup": (True, "teacher", False),
    "cnn-aug": (False, "aug", False),
    "lstm-aug": (True, "aug", False),
    "ctc": (True, "teacher", True),
}


def get_preset(name: str) -> Preset:
    if name not in PRESETS:
        raise ConfigError(f"unknown preset {name!r} (choose from {', '.join(PRESETS)})")
    return PRESETS[name]


def check_variant(name: str) -> tuple[bool, str, bool]:
    """(uses_lstm, label_source in {gt, teacher, aug}, uses_ctc) of a variant name."""
    if name not in VARIANTS:
        raise ConfigError(f"unknown variant {name!r} (choose from {', '.join(VARIANTS)})")
    return VARIANTS[name]


def to_dict(obj: Any) -> dict:
    """Plain-JSON form of a config dataclass (tuples become lists)."""
    return dataclasses.asdict(obj)


def model_from_dict(d: dict) -> ModelConfig:
    d = dict(d)
    d.setdefault("input", "rgb")
    d["conv_widths"] = tuple(d["conv_widths"])
    d["strided_widths"] = tuple(d["strided_widths"])
    return ModelConfig(**d)


def train_from_dict(d: dict) -> TrainConfig:
    return TrainConfig(**d)
