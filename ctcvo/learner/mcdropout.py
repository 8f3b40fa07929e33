"""Monte-Carlo-dropout edges of one sequence: the encoder runs once per frame pair, the
dropout and the layers after it are resampled K times (:meth:`CTCNet.direct_mc`,
:meth:`CTCNet.sequential_mc`); per edge the K twists give a mean and a 6x6 sample
covariance in the project tangent order (v, w). ``learner predict``, ``learner calibrate``
and the per-epoch evaluation of ``learner fit`` all read edges from here."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from numpy.typing import NDArray
from tqdm import tqdm

from ctcvo.learner.config import PredictConfig
from ctcvo.learner.dataset import Frames
from ctcvo.learner.model import CTCNet

#: added to the covariance diagonal before inversion (rad^2 / m^2; set with the first MC-dropout
#: predict, 07e3e22, not tuned since): a 1-sample or drop-0 covariance stays invertible
COV_FLOOR = 1e-8
#: pairs per encoder forward pass (memory, not results)
ENCODE_BATCH = 64


@dataclass
class EdgeSet:
    """MC-dropout edges of one sequence, positions ``i < j`` (E,) into the sequence view,
    mean twists (E, 6), covariances (E, 6, 6), head name per edge."""

    i: NDArray[np.int64]
    j: NDArray[np.int64]
    mean: NDArray[np.float64]
    cov: NDArray[np.float64]
    head: list[str]

    @property
    def sigma(self) -> NDArray[np.float64]:
        """sqrt(trace(cov)) per edge (E,)."""
        return np.sqrt(np.trace(self.cov, axis1=1, axis2=2))




@torch.no_grad()
def mc_edges(model: CTCNet, frames: Frames | torch.Tensor, *, uses_lstm: bool, window: int, cfg: PredictConfig,
             progress: bool = False, seed: int = 0) -> EdgeSet:
    """MC-dropout edges of one sequence's cached inputs (:class:`learner.dataset.Frames`, or
    (N, 3, H, W) uint8 RGB frames)."""
    n = len(frames)
    device = model.output_scale.device  # the frames may live on the CPU or on the model's device
    if isinstance(frames, torch.Tensor):
        frames = Frames(frames)
    torch.manual_seed(seed)
    G = max(1, min(cfg.max_gap, n - 1))
    ii, jj, means, covs, heads = [], [], [], [], []
    bar = tqdm(total=sum(n - g for g in range(1, G + 1)), desc="encode", disable=not progress, leave=False)

    def latents(g: int) -> torch.Tensor:
        out = []
        for a in range(0, n - g, ENCODE_BATCH):
            k = torch.arange(a, min(a + ENCODE_BATCH, n - g))
            out.append(model.encode(frames.pairs(k, k + g).to(device)))
            bar.update(len(k))
        return torch.cat(out)

    for g in range(1, G + 1):
        z = latents(g)  # (n-g, C)
        if g == 1 and uses_lstm:
            chunks = [model.sequential_mc(z[a:a + window][None], cfg.samples, cfg.drop)[:, 0]
                      for a in range(0, len(z), window)]
            samples, head = torch.cat(chunks, dim=1), "lstm"  # (K, n-1, 6)
        else:
            samples, head = model.direct_mc(z, cfg.samples, cfg.drop), "direct"
        s = samples.double().cpu().numpy()
        mean = s.mean(0)
        dev = s - mean
        cov = np.einsum("kei,kej->eij", dev, dev) / max(cfg.samples - 1, 1)
        cov = 0.5 * (cov + cov.transpose(0, 2, 1)) + COV_FLOOR * np.eye(6)
        k = np.arange(n - g)
        ii.append(k)
        jj.append(k + g)
        means.append(mean)
        covs.append(cov)
        heads += [head] * len(k)
    bar.close()
    return EdgeSet(np.concatenate(ii), np.concatenate(jj), np.concatenate(means), np.concatenate(covs), heads)

