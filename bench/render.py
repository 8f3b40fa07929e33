"""Benchmark: rendering speed of the synthetic scenes (decode/encode included).

Renders presets into a temporary folder exactly as ``--scene synthetic/NAME`` does (scene
build, trajectory, ray casting, shading, sensor model, JPEG / PNG encoding and writing), then reads
every frame back through the 7-Scenes reader, and prints frames/s (wall clock), CPU seconds
per frame, and a per-stage CPU breakdown of single-threaded frames.

    .venv/bin/python -m bench.render                       # office, kitchen, lab
    .venv/bin/python -m bench.render --presets tiny --frames 60 --workers 1

The machine's load average is printed too: on a shared machine, wall-clock frames/s drop
with other jobs while CPU seconds per frame stay comparable.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import resource
import tempfile
import time
from pathlib import Path

import numpy as np

import ctcvo.data.synthetic as syn
from ctcvo.data.sevenscenes import SevenScenesSequence
from ctcvo.data.synthetic.config import PRESETS


def _cpu() -> float:
    ru = resource.getrusage(resource.RUSAGE_SELF)
    return ru.ru_utime + ru.ru_stime


def stage_breakdown(cfg: syn.SceneConfig, n: int = 5) -> dict[str, float]:
    """CPU milliseconds per frame of each stage, one thread, ``n`` frames."""
    import cv2

    from ctcvo.data.synthetic import PNG_PARAMS, depth_to_png_mm
    from ctcvo.data.synthetic.sensor import depth_sensor

    scene, poses = syn.build(cfg)
    fr = syn.FrameRenderer(cfg, scene, poses, nthreads=1)
    fr.frame(0)
    acc = {"raycast+shading (padded, rolling shutter)": 0.0, "depth sensor": 0.0,
           "colour sensor (incl. JPEG encode + decode)": 0.0, "depth png encode": 0.0}
    ks = np.linspace(0, len(poses) - 1, n).astype(int)
    for k in ks:
        t = time.process_time()
        padded = fr.renderer.render(fr.row_poses(int(k)))  # padded for the colour camera
        ex = padded.crop(*fr.pad)
        t1 = time.process_time()
        rng = np.random.default_rng(k)
        d = depth_sensor(ex.depth, ex.cos_incidence, cfg.fx, cfg.sensor, rng, fr.bank)
        t2 = time.process_time()
        rgb, jpeg = fr.colour_sensor.encoded(padded.colour, 1.0, fr.image_flow(int(k), ex), rng, padded.depth)
        t3 = time.process_time()
        if jpeg is None:  # the colour file is the sensor's JPEG, else a PNG (see data.synthetic)
            cv2.imencode(".png", cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR), PNG_PARAMS)
        cv2.imencode(".png", depth_to_png_mm(d), PNG_PARAMS)
        t4 = time.process_time()
        for key, dt in zip(acc, (t1 - t, t2 - t1, t3 - t2, t4 - t3)):
            acc[key] += dt
    return {k: round(1000 * v / n, 1) for k, v in acc.items()}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--presets", nargs="+", default=["office", "kitchen", "lab"])
    ap.add_argument("--frames", type=int, default=None, help="override the presets' frame count")
    ap.add_argument("--workers", type=int, default=None, help="render threads (default: cores, at most 4)")
    ap.add_argument("--json", type=Path, default=None, help="also write the results here")
    args = ap.parse_args()

    print(f"cores: {os.cpu_count()}, load average before: {os.getloadavg()[0]:.2f}")
    results = {}
    with tempfile.TemporaryDirectory(prefix="bench-render-") as tmp:
        for name in args.presets:
            cfg = PRESETS[name]
            if args.frames:
                cfg = dataclasses.replace(cfg, frames=args.frames)
            out = Path(tmp) / name
            w0, c0 = time.perf_counter(), _cpu()
            syn.render_scene(cfg, out, workers=args.workers)
            w1, c1 = time.perf_counter(), _cpu()
            seq = SevenScenesSequence(out / "seq-01")
            for k in range(len(seq)):
                seq.rgb(k), seq.depth(k)
            w2 = time.perf_counter()
            size_mb = sum(p.stat().st_size for p in (out / "seq-01").iterdir()) / 1e6
            res = {
                "frames": cfg.frames, "render_s": round(w1 - w0, 2), "render_fps": round(cfg.frames / (w1 - w0), 2),
                "cpu_ms_per_frame": round(1000 * (c1 - c0) / cfg.frames, 1),
                "decode_fps": round(cfg.frames / (w2 - w1), 1), "disk_mb": round(size_mb, 1),
                "load_average": round(os.getloadavg()[0], 2),
                "stages_cpu_ms": stage_breakdown(cfg),
            }
            results[name] = res
            print(f"{name:8s} {cfg.frames:4d} frames  render {res['render_s']:6.1f} s = {res['render_fps']:5.1f} frames/s  "
                  f"({res['cpu_ms_per_frame']:.0f} CPU ms/frame), read back {res['decode_fps']:.0f} frames/s, "
                  f"{res['disk_mb']:.0f} MB, load {res['load_average']:.2f}")
            print(f"         stages (CPU ms/frame, 1 thread): {res['stages_cpu_ms']}")
    total_frames = sum(r["frames"] for r in results.values())
    total_s = sum(r["render_s"] for r in results.values())
    print(f"all: {total_frames} frames in {total_s:.1f} s = {total_frames / total_s:.1f} frames/s")
    if args.json:
        args.json.write_text(json.dumps(results, indent=2) + "\n")


if __name__ == "__main__":
    main()
