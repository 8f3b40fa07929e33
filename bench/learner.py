"""CPU throughput of the learner's ``cpu`` preset (targets: training >= 100 pairs/s,
MC-dropout prediction with K=10 >= 100 pairs/s). Synthetic random frames; no data needed.

    .venv/bin/python bench/learner.py                    # cpu preset, defaults below
    .venv/bin/python bench/learner.py --steps 20 --threads 2

Training throughput counts encoder pairs per second in the two phases: single pairs
(phase 1, batch ``batch_pairs``) and windows of W consecutive pairs with all direct pairs
of gaps up to G (phase 2, CTC + regression, batch ``batch_windows``). Prediction counts
frame pairs per second through :func:`learner.predict.mc_edges` (encoder once, K dropout
samples of the heads), all gaps 1..max_gap.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

# this script is named like the package it measures: keep bench/ off the import path
sys.path = [q for q in sys.path if Path(q or ".").resolve() != Path(__file__).resolve().parent]

import torch  # noqa: E402

from learner import loss as L  # noqa: E402
from learner.config import PRESETS, PredictConfig  # noqa: E402
from learner.model import CTCNet  # noqa: E402
from learner.predict import mc_edges  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--preset", default="cpu")
    ap.add_argument("--steps", type=int, default=10)
    ap.add_argument("--threads", type=int, default=torch.get_num_threads())
    ap.add_argument("--window", type=int, default=18)
    ap.add_argument("--frames", type=int, default=200)
    ap.add_argument("--samples", type=int, default=10)
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    p = PRESETS[args.preset]
    m, t = p.model, p.train
    torch.manual_seed(0)
    net = CTCNet(m)
    opt = torch.optim.Adam(net.parameters(), lr=1e-4)
    out = {"preset": p.name, "threads": args.threads, "input": f"{m.width}x{m.height}"}

    def timed(fn, steps: int) -> float:
        fn()  # warm-up
        t0 = time.perf_counter()
        for _ in range(steps):
            fn()
        return (time.perf_counter() - t0) / steps

    # phase 1: single pairs
    B = t.batch_pairs
    x = torch.randint(0, 256, (B, 6, m.height, m.width), dtype=torch.uint8)
    lab = torch.zeros(B, 6)

    def step_pairs() -> None:
        xi, _ = net(x)
        terms = L.pair_loss(xi, lab, torch.ones(B), t.beta)
        opt.zero_grad()
        terms.total.backward()
        opt.step()

    net.train()
    dt = timed(step_pairs, args.steps)
    out["train_pairs_per_s_phase1"] = B / dt
    # phase 2: windows
    W, G, Bw = args.window, t.max_gap, t.batch_windows
    P = len(L.window_pairs(W, G))
    xw = torch.randint(0, 256, (Bw * P, 6, m.height, m.width), dtype=torch.uint8)
    labw = torch.zeros(Bw, P, 6)
    idx = torch.arange(Bw)[:, None] * P + torch.arange(W)[None]

    def step_windows() -> None:
        xi_d, xi_s = net(xw, idx)
        terms = L.window_loss(xi_s, xi_d.view(Bw, P, 6), labw[:, :W], torch.ones(Bw, W), labw, torch.ones(Bw, P),
                              G, t.alpha, t.beta)
        opt.zero_grad()
        terms.total.backward()
        opt.step()

    dt = timed(step_windows, max(1, args.steps // 3))
    out["train_pairs_per_s_phase2"] = Bw * P / dt
    out["phase2_window"] = W
    out["phase2_pairs_per_step"] = Bw * P
    # prediction
    net.eval()
    frames = torch.randint(0, 256, (args.frames, 3, m.height, m.width), dtype=torch.uint8)
    cfg = PredictConfig(samples=args.samples)
    t0 = time.perf_counter()
    edges = mc_edges(net, frames, uses_lstm=True, window=t.window_max, cfg=cfg)
    dt = time.perf_counter() - t0
    out["predict_pairs_per_s"] = len(edges.i) / dt
    out["predict_samples"] = args.samples
    out["predict_edges"] = len(edges.i)
    print(json.dumps({k: (round(v, 1) if isinstance(v, float) else v) for k, v in out.items()}, indent=2))


if __name__ == "__main__":
    main()
