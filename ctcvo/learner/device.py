"""Where the learner runs: the torch device of one process, and the process group of a
``torchrun`` launch (DistributedDataParallel: gloo on the CPU, nccl on GPUs)."""

from __future__ import annotations

import os
from dataclasses import dataclass

import torch
import torch.distributed as dist

from ctcvo.data.errors import ConfigError


@dataclass
class Dist:
    """This process's rank among ``world`` processes and its device."""

    rank: int = 0
    world: int = 1
    device: torch.device = torch.device("cpu")

    @property
    def main(self) -> bool:
        return self.rank == 0

    def barrier(self) -> None:
        if self.world > 1:
            dist.barrier()


def resolve_device(choice: str = "auto") -> torch.device:
    """The torch device of a single process: ``auto`` (CUDA when available, else the CPU),
    ``cpu`` or ``cuda`` (an error without a GPU)."""
    if choice not in ("auto", "cpu", "cuda"):
        raise ConfigError(f"--device must be auto, cpu or cuda, got {choice!r}")
    cuda = torch.cuda.is_available()
    if choice == "cuda" and not cuda:
        raise ConfigError("--device cuda: no CUDA device is available")
    return torch.device("cuda" if choice == "cuda" or (choice == "auto" and cuda) else "cpu")


def setup_dist(device: str = "auto") -> Dist:
    """One process: the device of :func:`resolve_device`. Under torchrun (``WORLD_SIZE > 1``):
    a process group (nccl on GPUs, gloo on the CPU), one GPU per process by ``LOCAL_RANK``."""
    dev = resolve_device(device)
    world = int(os.environ.get("WORLD_SIZE", "1"))
    if world <= 1:
        return Dist(device=dev)
    cuda = dev.type == "cuda"
    if not dist.is_initialized():
        dist.init_process_group("nccl" if cuda else "gloo")
    rank = dist.get_rank()
    if cuda:
        local = int(os.environ.get("LOCAL_RANK", "0"))
        torch.cuda.set_device(local)
        dev = torch.device("cuda", local)
    return Dist(rank, dist.get_world_size(), dev)
