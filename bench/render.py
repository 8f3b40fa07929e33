"""Benchmark: rendering speed of the synthetic scenes (decode/encode included).

Renders presets into ``--out`` (default ``runs/bench/<name>``) exactly as ``--scene synthetic/NAME`` does (scene
build, trajectory, ray casting, shading, sensor model, JPEG / PNG encoding and writing), then reads
every frame back through the 7-Scenes reader, and records frames/s (wall clock), CPU seconds
per frame, and a per-stage CPU breakdown of single-threaded frames in
``bench/results/<name>.json`` (bench/record.py). On a shared machine wall-clock frames/s drop
with other jobs while CPU seconds per frame stay comparable; the record has the load average.

    .venv/bin/python -m bench.render                       # office, kitchen, lab
    .venv/bin/python -m bench.render --presets lab --frames 60 --name render-lab60
"""

from __future__ import annotations

import argparse
import dataclasses
import resource
import shutil
import time
from pathlib import Path

import numpy as np

import ctcvo.data.synthetic as syn
from bench import record
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
    ap.add_argument("--out", type=Path, help="render folder, one sub-folder per preset (default runs/bench/NAME)")
    record.add_arguments(ap, "render")
    args = ap.parse_args()
    root = args.out or record.RUNS / args.name
    rec = record.from_args(args, out=root)
    results = {}
    print("| preset | frames | render frames/s | CPU ms/frame | read back frames/s |\n|---|---|---|---|---|")
    for name in args.presets:
        cfg = PRESETS[name]
        if args.frames:
            cfg = dataclasses.replace(cfg, frames=args.frames)
        out = root / name
        shutil.rmtree(out, ignore_errors=True)  # a fresh render, not the cached one
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
            "stages_cpu_ms": stage_breakdown(cfg),
        }
        results[name] = res
        print(f"| {name} | {cfg.frames} | {res['render_fps']} | {res['cpu_ms_per_frame']} | {res['decode_fps']} |")
    rec.finish({"presets": results})


if __name__ == "__main__":
    main()
