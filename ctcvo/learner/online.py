"""The learner frame by frame: MC-dropout edges of each new frame as frames arrive
(``ctcvo online``, pipeline/online.py), equal to ``learner predict``'s on the same frames.

The per-frame inputs are those :func:`learner.dataset.load_frames` caches for a whole
sequence; the network, its calibration and the MC-dropout settings are those of
:mod:`learner.predict`.
"""

from __future__ import annotations

import contextlib
import logging
from collections import deque
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import torch
from numpy.typing import NDArray

from ctcvo.data.sequence import Frame
from ctcvo.learner.calibrate import calibration_for
from ctcvo.learner.checkpoint import load_model
from ctcvo.learner.config import FLOW_U_CHANNEL, PredictConfig, check_variant
from ctcvo.learner.dataset import Frames, grey2x_input, invdepth_input, rgb_input
from ctcvo.learner.mcdropout import COV_FLOOR

log = logging.getLogger(__name__)

#: torch intra-op threads of :meth:`OnlineLearner.add`. torch's default (one per core) made the
#: learner 8x slower on the 2-core VM when the cores were busy (219 against 26 ms a frame,
#: redkitchen 0:80 at load 9; ``ctcvo online`` 2 against 8 fps, 0:150): its OpenMP workers
#: wait at each layer's barrier for a core that the teacher or another process holds. Five
#: pairs a frame at 128x96 give a second thread little to share even on an idle machine.
ONLINE_THREADS = 1


@contextlib.contextmanager
def torch_threads(n: int) -> Iterator[None]:
    """torch's intra-op thread count set to ``n`` within the block, then restored."""
    before = torch.get_num_threads()
    if before == n:
        yield
        return
    torch.set_num_threads(n)
    try:
        yield
    finally:
        torch.set_num_threads(before)


class OnlineLearner:
    """MC-dropout edges (k-g, k), g = 1..max_gap, of each new frame: the pairs are encoded
    once, the dropout layers resampled K times; gap 1 from the LSTM head (LSTM variants;
    chunks of ``window_max`` pairs as in ``learner predict``, the LSTM being causal the
    newest output equals the batch one), longer gaps from the direct head. Mean and
    covariance as in :func:`learner.mcdropout.mc_edges`, calibrated with the checkpoint's
    ``calibration.json`` when there is one."""

    def __init__(self, checkpoint: Path, cfg=None, device: str = "cpu", use_calibration: bool = True,
                 seed: int = 0) -> None:
        self.cfg = cfg or PredictConfig()
        self.model, state = load_model(Path(checkpoint), None, device)
        found = calibration_for(Path(checkpoint), self.cfg) if use_calibration else None
        self.calibration = found[1] if found is not None else None
        if found is None and use_calibration:
            log.info("no calibration.json beside %s: MC-dropout covariances used as they are", checkpoint)
        self.uses_lstm = check_variant(state["variant"])[0]
        self.window = int(state["train_config"]["window_max"])
        m = self.model.cfg
        self.width, self.height, self.mode = m.width, m.height, m.input
        self.buf: deque[tuple] = deque(maxlen=self.cfg.max_gap + 1)
        self.z1: list = []  # gap-1 latents of the current LSTM chunk
        self.n = 0
        torch.manual_seed(seed)

    def inputs(self, frame: Frame) -> tuple:
        """Per-frame network inputs (resized RGB, inverse depth, grey at 2x), as the learner caches them."""
        rgb = rgb_input(frame.rgb, self.width, self.height)
        inv = invdepth_input(frame.depth, self.width, self.height) if self.mode != "rgb" else None
        grey = (grey2x_input(frame.rgb, self.width, self.height)
                if self.mode in FLOW_U_CHANNEL else None)  # the inputs with optical flow
        return rgb, inv, grey

    def add(self, inputs: tuple) -> list[tuple[int, NDArray[np.float64], NDArray[np.float64], str]]:
        """(gap, mean twist (6,), covariance (6, 6), head) of the edges ending at the new frame."""
        self.buf.append(inputs)
        k, self.n = self.n, self.n + 1
        G = min(self.cfg.max_gap, len(self.buf) - 1)
        if G < 1:
            return []
        with torch_threads(ONLINE_THREADS), torch.no_grad():
            out = self._samples(k, G)
        res = []
        for g, (head, samples) in zip(range(1, G + 1), out):
            s = samples.double().cpu().numpy()
            mean = s.mean(0)
            dev = s - mean
            cov = dev.T @ dev / max(self.cfg.samples - 1, 1)
            cov = 0.5 * (cov + cov.T) + COV_FLOOR * np.eye(6)
            if self.calibration is not None:
                cov = self.calibration.apply(cov[None], [head], np.array([g]))[0]
            res.append((g, mean, cov, head))
        return res

    def _samples(self, k: int, G: int) -> list[tuple[str, torch.Tensor]]:
        """(head, K dropout samples (K, 6)) of the edges (k-g, k), g = 1..G: the G pairs in one
        encoder pass, each head's K samples in one pass of the layers after its dropout
        (:meth:`CTCNet.direct_mc`, :meth:`CTCNet.sequential_mc`)."""
        stack = [None if self.buf[0][c] is None else np.stack([b[c] for b in self.buf]) for c in range(3)]
        frames = Frames(stack[0], stack[1], stack[2], self.mode)
        last = len(self.buf) - 1
        gaps = torch.arange(1, G + 1)
        z = self.model.encode(frames.pairs(last - gaps, torch.full((G,), last)).to(self.model.output_scale.device))
        out: list[tuple[str, torch.Tensor]] = []
        rest = z
        if self.uses_lstm:
            if (k - 1) % self.window == 0:
                self.z1 = []
            self.z1.append(z[0])
            out.append(("lstm", self.model.sequential_mc(torch.stack(self.z1)[None], self.cfg.samples,
                                                         self.cfg.drop)[:, 0, -1]))
            rest = z[1:]
        if len(rest):
            d = self.model.direct_mc(rest, self.cfg.samples, self.cfg.drop)  # (K, G', 6)
            out += [("direct", d[:, n]) for n in range(d.shape[1])]
        return out
