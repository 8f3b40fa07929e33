"""CPU throughput of the learner (targets for the ``cpu`` preset: training >= 100 pairs/s,
MC-dropout prediction with K=10 >= 100 pairs/s). Random frames; no data needed.

    .venv/bin/python -m bench.learner                       # cpu preset, all cores
    .venv/bin/python -m bench.learner --threads 1 --steps 8 --name learner-cpu-1thread
    .venv/bin/python -m bench.learner --input flow           # with the optical-flow input

Training runs the real training step of ``learner fit`` (:func:`learner.batches.pairs_step`
/ :func:`learner.batches.windows_step`: gathering the cached uint8 frames and labels, the
forward pass, the loss, backward and Adam) on a sequence of ``--frames`` random frames with
teacher-style labels and covariances:

* phase 1: batches of ``batch_pairs`` single pairs of gaps 1..G (``*-aug`` label noise on);
* phase 2 (``ctc``): batches of ``batch_windows`` windows of ``--window`` consecutive pairs,
  each with all its direct pairs of gaps up to G (CTC + regression);

and counts encoder pairs per second. Prediction counts edges per second of
:func:`learner.mcdropout.mc_edges` (every pair of gaps 1..max_gap encoded once, K dropout
samples of the heads). Each figure is given per wall-clock second and per CPU second
of this process (``time.process_time``; on a busy machine the wall figure drops while the
CPU figure holds, and ``threads x`` the CPU figure bounds what an idle machine gives).
The record is ``bench/results/<name>.json`` (bench/record.py).
"""

from __future__ import annotations

import argparse
import dataclasses
import time
from collections.abc import Callable

import numpy as np
import torch

from bench import record
from ctcvo.learner import loss as L
from ctcvo.learner.batches import pair_batches, pairs_step, window_batches, windows_step
from ctcvo.learner.config import FLOW_U_CHANNEL, INPUTS, PRESETS, PredictConfig
from ctcvo.learner.dataset import Frames, SequenceData
from ctcvo.learner.mcdropout import mc_edges
from ctcvo.learner.model import CTCNet


def fake_sequence(n: int, width: int, height: int, max_gap: int, seed: int = 0, mode: str = "rgb") -> SequenceData:
    """``n`` random uint8 frames with small random labels of every gap and diagonal
    covariances (1 cm / 0.5 deg), as :func:`learner.dataset.load_sequences` returns; for the
    ``rgbd`` / ``flow`` / ``flowd`` inputs also random inverse depth and grey frames at twice the size
    (the optical flow is computed per drawn pair, as in training)."""
    g = torch.Generator().manual_seed(seed)
    rgb = torch.randint(0, 256, (n, 3, height, width), dtype=torch.uint8, generator=g)
    inv = torch.randint(20, 200, (n, 1, height, width), dtype=torch.uint8, generator=g) if mode != "rgb" else None
    grey = (torch.randint(0, 256, (n, 2 * height, 2 * width), dtype=torch.uint8, generator=g).numpy()
            if mode in FLOW_U_CHANNEL else None)
    frames = Frames(rgb, inv, grey, mode)
    labels = torch.randn(max_gap + 1, n, 6, generator=g) * 0.01
    mask = torch.ones(max_gap + 1, n, dtype=torch.bool)
    mask[0] = False
    for gap in range(1, max_gap + 1):
        mask[gap, n - gap:] = False
    chol = torch.diag(torch.tensor([0.01] * 3 + [0.01] * 3)).expand(max_gap + 1, n, 6, 6).contiguous()
    return SequenceData("bench", np.arange(n), np.arange(n) / 30.0, frames, labels, mask, chol, None)


def timed(fn: Callable[[], int], steps: int) -> tuple[float, float, int]:
    """(wall s, CPU s, pairs) of ``steps`` calls after one warm-up call."""
    fn()
    t0, c0, pairs = time.perf_counter(), time.process_time(), 0
    for _ in range(steps):
        pairs += fn()
    return time.perf_counter() - t0, time.process_time() - c0, pairs


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--preset", default="cpu", choices=list(PRESETS))
    ap.add_argument("--steps", type=int, default=6, help="timed optimiser steps per training phase")
    ap.add_argument("--threads", type=int, default=torch.get_num_threads(), help="torch intra-op threads")
    ap.add_argument("--window", type=int, help="phase-2 window length (default: the preset's window_max)")
    ap.add_argument("--frames", type=int, default=200, help="frames of the random sequence")
    ap.add_argument("--samples", type=int, default=10, help="K, MC-dropout samples")
    ap.add_argument("--input", choices=list(INPUTS), help="encoder input (default: the preset's)")
    record.add_arguments(ap, "learner-cpu")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    p = PRESETS[args.preset]
    if args.input:
        p = dataclasses.replace(p, model=dataclasses.replace(p.model, input=args.input))
    m, t = p.model, p.train
    rec = record.from_args(args, model=m, train=t)
    torch.manual_seed(0)
    net = CTCNet(m)
    with torch.no_grad():
        net.output_scale.fill_(0.01)
    opt = torch.optim.Adam(net.parameters(), lr=1e-4)
    data = [fake_sequence(args.frames, m.width, m.height, t.max_gap, mode=m.input)]
    rng = np.random.default_rng(0)
    gen = torch.Generator().manual_seed(0)
    scale = torch.full((t.max_gap + 1, 6), 0.01)  # the losses' target scale (any value costs the same)
    out: dict = {"preset": p.name, "input": m.input, "threads": args.threads, "size": f"{m.width}x{m.height}",
                 "conv_widths": ",".join(map(str, m.conv_widths)), "batch_pairs": t.batch_pairs}

    def optimise(terms: L.LossTerms) -> None:
        terms.items()  # the fit loop reads the loss values every step
        opt.zero_grad(set_to_none=True)
        terms.total.backward()
        opt.step()

    net.train()
    # phase 1: single pairs, aug labels (the costliest label path)
    batches = iter(pair_batches(data, t, rng) * 10)

    def step_pairs() -> int:
        rows = next(batches)
        optimise(pairs_step(net, data, rows, t, True, gen, torch.device("cpu"), scale))
        return len(rows)

    wall, cpu, n = timed(step_pairs, args.steps)
    out.update(train_phase1_pairs_per_s=n / wall, train_phase1_pairs_per_cpu_s=n / cpu)
    # phase 2: windows, CTC on
    W = args.window or t.window_max
    wins = iter(window_batches(data, W, t, rng) * 10)
    P = len(L.window_pairs(W, t.max_gap))

    def step_windows() -> int:
        rows = next(wins)
        optimise(windows_step(net, data, rows, W, t, False, gen, torch.device("cpu"), scale))
        return len(rows) * P

    wall, cpu, n = timed(step_windows, max(1, args.steps // 2))
    out.update(train_phase2_pairs_per_s=n / wall, train_phase2_pairs_per_cpu_s=n / cpu,
               phase2_window=W, phase2_pairs_per_step=t.batch_windows * P)
    # prediction
    net.eval()
    cfg = PredictConfig(samples=args.samples)
    frames = data[0].frames
    mc_edges(net, frames.head(20), uses_lstm=True, window=t.window_max, cfg=cfg)  # warm-up
    t0, c0 = time.perf_counter(), time.process_time()
    edges = mc_edges(net, frames, uses_lstm=True, window=t.window_max, cfg=cfg)
    wall, cpu = time.perf_counter() - t0, time.process_time() - c0
    out.update(predict_pairs_per_s=len(edges.i) / wall, predict_pairs_per_cpu_s=len(edges.i) / cpu,
               predict_samples=args.samples, predict_edges=len(edges.i))
    res = {k: (round(v, 1) if isinstance(v, float) else v) for k, v in out.items()}
    print("| figure | pairs / s | pairs / CPU s |\n|---|---|---|")
    for k in ("train_phase1", "train_phase2", "predict"):
        print(f"| {k} | {res[f'{k}_pairs_per_s']} | {res[f'{k}_pairs_per_cpu_s']} |")
    rec.finish(res)


if __name__ == "__main__":
    main()
