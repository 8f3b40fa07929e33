"""Learner checkpoints: ``checkpoint.pt`` written after every epoch of ``learner fit``, and
the network read back from one (docs/formats.md, "Learner")."""

from __future__ import annotations

from pathlib import Path

import torch

from ctcvo.data.errors import ConfigError, DataError
from ctcvo.data.io import atomic_write, git_revision
from ctcvo.learner.config import Preset, model_from_dict, to_dict
from ctcvo.learner.device import resolve_device
from ctcvo.learner.model import CTCNet

CHECKPOINT = "checkpoint.pt"
CHECKPOINT_FORMAT = 2
"""2: losses normalised by the labels' RMS, inputs normalised in raw units (``ModelConfig.input``)."""


def save_checkpoint(path: Path, model: CTCNet, opt: torch.optim.Optimizer, epoch: int, preset: Preset,
                    variant: str, history: list[dict]) -> None:
    """Write the weights, optimiser state, configs and history atomically to ``path``."""
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
        # torch's own text runs to many lines and advises weights_only=False, which would run
        # whatever the file holds: its type is all the message keeps
        raise DataError(f"{path} is not a readable learner checkpoint ({type(exc).__name__})") from None
    if not isinstance(state, dict) or "model" not in state or "format" not in state:
        raise DataError(f"{path} is not a learner checkpoint")
    if state["format"] != CHECKPOINT_FORMAT:
        raise DataError(f"{path} is a learner checkpoint of format {state['format']}, this version reads format "
                        f"{CHECKPOINT_FORMAT}: train it again")
    return state


def load_model(checkpoint: Path, preset: str | None = None, device: str = "auto") -> tuple[CTCNet, dict]:
    """The network of a checkpoint (eval mode, on ``device``: auto, cpu or cuda) and the
    checkpoint's metadata."""
    dev = resolve_device(device)
    state = load_checkpoint(checkpoint)
    if preset is not None and preset != state["preset"]:
        raise ConfigError(f"{checkpoint} was trained with preset {state['preset']!r}, not {preset!r}")
    model = CTCNet(model_from_dict(state["model_config"]))
    try:
        model.load_state_dict(state["model"])
    except RuntimeError as exc:
        raise ConfigError(f"{checkpoint} does not match its own model config: {str(exc).splitlines()[0]}") from None
    model.to(dev)
    model.eval()
    return model, state
