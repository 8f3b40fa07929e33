"""Online mode benchmark: ``ctcvo online`` against the batch stages, side by side in one run.

For each scene, on the same frames:

* **batch teacher** (``ctcvo teacher generate``'s :func:`teacher.generate.run_sequence`, its
  default 2 worker processes): frames per second;
* **online, teacher only, as fast as frames come** (every frame already on disk): sustained
  frames per second and per-frame latency (frame handed over by the source -> its pose
  written and flushed);
* **online, teacher only, paced at 30 Hz** (a camera: frame k arrives, decoded, at
  ``k / 30`` s whether or not the run has taken the earlier ones): per-frame latency
  percentiles from the frame's arrival, every frame taken (a run slower than 30 fps falls
  further behind with each frame), and with ``drop_late`` (the newest frame taken, the
  ones in between skipped): frames taken and skipped, latency, final ATE on its frames;
* **online with the learner** (``--checkpoint``): as fast as frames come and paced at 30 Hz,
  frames per second (beside the teacher-only run's), latency, own work and its CPU time;
* **accuracy**: ATE of the online run's trajectories - causal (each frame's estimate when
  it arrived), ISAM2 after the last frame, final (ISAM2 then the batch solve warm-started
  from it) - against batch ``posegraph optimize`` on the same edges (the online run's
  ``teacher/`` folder), as ratios; with a cheaper online teacher (``--gaps``) also against
  batch ``posegraph optimize`` on the batch teacher's own edges (``ctcvo teacher generate``'s
  default), the figure the online run stands in for.

    OMP_NUM_THREADS=1 .venv/bin/python -m bench.online [--checkpoint CKPT] [--frames 0:300]
    OMP_NUM_THREADS=1 .venv/bin/python -m bench.online --frames 450:600 --gaps 4 --pose-after-gap1 \\
        --keyframes both --name online-low-latency
    OMP_NUM_THREADS=1 .venv/bin/python -m bench.online --frames 0:150 --keyframes both --name online-keyframes

The ``online-learner`` record's checkpoint (its fps do not depend on the weights: the demo
preset's network after 6 steps), trained first:

    .venv/bin/python -m ctcvo learner fit --scene ../shared/data/7scenes/redkitchen/seq-sample --frames 0:150 \
        --variant lstm-gt --preset demo --steps 6 --pretrain-steps 3 --eval-every 2 --warmup-steps 0 \
        --no-calibration --out runs/bench/online-learner-checkpoint
    OMP_NUM_THREADS=1 .venv/bin/python -m bench.online --scenes ../shared/data/7scenes/redkitchen/seq-sample \
        --frames 0:150 --checkpoint runs/bench/online-learner-checkpoint/checkpoint.pt --name online-learner

``--keyframes`` sets the online teacher's keyframe pass (``TeacherConfig.keyframes``, a helper
thread in ``ctcvo online``); ``both`` gives a row with it and one without, one after the other.

The record is ``bench/results/<name>.json`` (bench/record.py), with the machine's 1-min load
average at the start and end of each scene and the cores the online run got (its CPU time
over its wall time): on a shared machine the figures mean little without them. The runs'
outputs go to ``--out`` (default ``runs/bench/<name>``; each scene's folder there is emptied
first); stdout gets a Markdown table.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import sys
import time
from dataclasses import replace
from pathlib import Path

if __name__ == "__main__":  # as `teacher generate` does: its worker imports while this process does
    from ctcvo.teacher import processes

    processes.start()

from bench import record  # noqa: E402
from ctcvo.data import live  # noqa: E402
from ctcvo.data.scenes import open_scene  # noqa: E402
from ctcvo.data.sensor import KINECT_V1_READOUT_S  # noqa: E402
from ctcvo.learner.checkpoint import load_checkpoint  # noqa: E402
from ctcvo.pipeline import online  # noqa: E402
from ctcvo.teacher.config import DEFAULT  # noqa: E402

SCENES = [str(record.REDKITCHEN), str(record.TUM_XYZ)]


class Paced(live.FrameSource):
    """A camera at ``rate`` Hz: frame k arrives, decoded, at ``t0 + k / rate`` whether or
    not the run has taken the earlier ones (``frames``: the sequence decoded into memory
    beforehand); its latency counts from then. With ``drop_late`` it hands out the newest
    frame that has arrived, passing over older ones not taken (``skipped``)."""

    def __init__(self, seq, frames: list, rate: float, drop_late: bool = False) -> None:
        self.frames, self.rate, self.drop_late = frames, rate, drop_late
        self.name, self.intrinsics = seq.name, seq.intrinsics
        # the teacher settings this source got before sources carried a sensor (colour registered,
        # Kinect v1's readout), not seq.sensor: on a 7-Scenes folder they differ from the batch teacher's
        self.sensor = replace(seq.sensor, colour=None, readout_s=KINECT_V1_READOUT_S)
        self.skipped, self._arrived = 0, None

    def __iter__(self):
        t0, k = time.perf_counter(), -1
        while k + 1 < len(self.frames):
            arrived = int((time.perf_counter() - t0) * self.rate)  # the newest frame the camera has sent
            nk = min(max(arrived, k + 1), len(self.frames) - 1) if self.drop_late else k + 1
            wait = t0 + nk / self.rate - time.perf_counter()
            if wait > 0:
                time.sleep(wait)
            self.skipped += nk - k - 1
            k, self._arrived = nk, t0 + nk / self.rate
            yield self.frames[k]

    def arrival(self):
        return self._arrived


def bench_scene(spec: str, frames: str, checkpoint: Path | None, tmp: Path, tcfg=DEFAULT,
                ocfg: online.OnlineConfig = online.OnlineConfig()) -> dict:
    """One scene's row; ``tcfg``, ``ocfg``: the online runs' teacher (the batch teacher is
    ``DEFAULT``) and online settings."""
    from ctcvo.posegraph.optimize import optimize
    from ctcvo.teacher.generate import run_sequence, write_outputs

    seq = open_scene(spec, frames=frames)[0]
    shutil.rmtree(tmp / seq.name, ignore_errors=True)  # every run measured afresh
    row: dict = {"scene": seq.name, "frames": len(seq), "load_avg_1min": [os.getloadavg()[0]],
                 "online_gaps": tcfg.gaps, "keyframes": tcfg.keyframes,
                 "pose_after_gap1": ocfg.pose_after_gap1}
    run = run_sequence(seq, DEFAULT, progress=False)  # batch, 2 processes
    row["batch_fps"] = len(seq) / run.seconds
    # the batch pipeline's own figure: the pose graph on the batch teacher's edges
    write_outputs(seq, run, DEFAULT, tmp / seq.name / "batch_teacher", {})
    outs = optimize(teacher=tmp / seq.name / "batch_teacher", out=tmp / seq.name / "batch_teacher_pg")
    row["batch_teacher_posegraph_ate_m"] = json.loads((outs[0] / "report.json").read_text())["rows"]["fused"][
        "ate_rmse_m"]
    decoded = [seq.frame(k) for k in range(len(seq))]  # the paced camera's frames
    drop = replace(ocfg, drop_late=True)
    for name, src, cfg in (("online", live.SequenceSource(seq), ocfg),
                           ("online_30hz", Paced(seq, decoded, 30.0), ocfg),
                           ("online_30hz_drop", Paced(seq, decoded, 30.0, drop_late=True), drop)):
        wall, cpu = time.perf_counter(), time.process_time()
        res = online.run(src, tmp / seq.name / name, tcfg, cfg=cfg, progress=False)
        # the cores this process got (all its threads): on a shared machine, what the figures had
        row[f"{name}_cores_used"] = (time.process_time() - cpu) / (time.perf_counter() - wall)
        row[f"{name}_fps"] = res.fps
        row[f"{name}_latency_ms"] = res.latency_ms
        row[f"{name}_work_ms"] = res.report["work_ms"]
        row[f"{name}_work_to_pose_ms"] = res.report["work_to_pose_ms"]
        row[f"{name}_work_to_pose_cpu_ms"] = res.report["work_to_pose_cpu_ms"]
        row[f"{name}_frames"], row[f"{name}_skipped"] = res.frames, res.report["frames_skipped"]
        if name == "online_30hz_drop" and "final" in res.report:  # on the frames it took
            row["drop_ate_final_m"] = res.report["final"]["ate_rmse_m"]
        if name == "online":
            rep = res.report
            row["online_edges_by_kind"] = rep["teacher_edges_by_kind"]
            row["online_keyframes"] = rep["keyframes"]  # picked, dropped, wait at the end, lag in frames
            outs = optimize(teacher=tmp / seq.name / name / "teacher", out=tmp / seq.name / "batch_pg")
            pg = json.loads((outs[0] / "report.json").read_text())
            batch_ate = pg["rows"]["fused"]["ate_rmse_m"]
            row["ate_m"] = {"batch_posegraph": batch_ate, "final": rep["final"]["ate_rmse_m"],
                            "isam2": rep["final_isam2"]["ate_rmse_m"], "causal": rep["online"]["ate_rmse_m"],
                            "teacher_chain": rep["teacher_chain"]["ate_rmse_m"]}
            row["final_solve_s"] = (rep.get("final_polish") or {}).get("seconds")
    if checkpoint is not None:
        row["learner_preset"] = load_checkpoint(checkpoint)["preset"]
        for name, src in (("learner", live.SequenceSource(seq)), ("learner_30hz", Paced(seq, decoded, 30.0))):
            wall, cpu = time.perf_counter(), time.process_time()
            res = online.run(src, tmp / seq.name / name, tcfg, checkpoint=checkpoint, cfg=ocfg, progress=False)
            row[f"{name}_cores_used"] = (time.process_time() - cpu) / (time.perf_counter() - wall)
            row[f"{name}_fps"] = res.fps
            row[f"{name}_latency_ms"] = res.latency_ms
            row[f"{name}_work_ms"] = res.report["work_ms"]
            row[f"{name}_work_to_pose_cpu_ms"] = res.report["work_to_pose_cpu_ms"]
    row["load_avg_1min"].append(os.getloadavg()[0])
    return row


def table(rows: list[dict]) -> str:
    out = ["| scene | frames | load avg (start, end); cores the online run got | batch teacher fps "
           "| online fps (ratio) | online latency p50/p95 ms "
           "| own work p50/p95 ms (until its pose; its CPU time) | 30 Hz latency p50/p95 ms "
           "| 30 Hz with --drop-late: frames taken (skipped), latency p50/p95 ms, final ATE on its frames "
           "| ATE final / ISAM2 / causal vs batch pose graph | with learner fps, 30 Hz p95 ms |",
           "|---|---|---|---|---|---|---|---|---|---|---|"]
    if any("batch_teacher_posegraph_ate_m" in r for r in rows):
        out[0] += " online settings; final ATE vs the batch teacher's pose graph |"
        out[1] += "---|"
    for r in rows:
        a = r["ate_m"]
        b = a["batch_posegraph"]
        lrn = (f"{r['learner_fps']:.1f}, {r['learner_30hz_latency_ms']['p95']:.0f}" if "learner_fps" in r else "-")
        out.append(
            f"| {r['scene']} | {r['frames']} | {r['load_avg_1min'][0]:.1f}, {r['load_avg_1min'][-1]:.1f}; "
            f"{r['online_cores_used']:.2f} | {r['batch_fps']:.1f} | {r['online_fps']:.1f} "
            f"({r['online_fps'] / r['batch_fps']:.2f}x) | {r['online_latency_ms']['p50']:.0f} / "
            f"{r['online_latency_ms']['p95']:.0f} | "
            + (f"{r['online_work_ms']['p50']:.0f} / {r['online_work_ms']['p95']:.0f}" if "online_work_ms" in r else "-")
            + (f" ({r['online_work_to_pose_ms']['p50']:.0f} / {r['online_work_to_pose_ms']['p95']:.0f}; "
               f"{r['online_work_to_pose_cpu_ms']['p50']:.0f} / {r['online_work_to_pose_cpu_ms']['p95']:.0f})"
               if "online_work_to_pose_cpu_ms" in r else "")
            + f" | {r['online_30hz_latency_ms']['p50']:.0f} / "
            f"{r['online_30hz_latency_ms']['p95']:.0f} | {r['online_30hz_drop_frames']} "
            f"({r['online_30hz_drop_skipped']}), {r['online_30hz_drop_latency_ms']['p50']:.0f} / "
            f"{r['online_30hz_drop_latency_ms']['p95']:.0f}, "
            + (f"{1000 * r['drop_ate_final_m']:.1f} mm" if "drop_ate_final_m" in r else "-")
            + f" | {1000 * a['final']:.1f} / {1000 * a['isam2']:.1f} / "
            f"{1000 * a['causal']:.1f} mm vs {1000 * b:.1f} mm ({a['final'] / b:.2f}x / {a['isam2'] / b:.2f}x / "
            f"{a['causal'] / b:.2f}x) | {lrn} |"
            + (f" gaps {r['online_gaps']}{', pose after gap 1' if r.get('pose_after_gap1') else ''}"
               f"{', keyframes' if r.get('keyframes') else ', no keyframes' if 'keyframes' in r else ''}; "
               f"{1000 * a['final']:.1f} vs {1000 * r['batch_teacher_posegraph_ate_m']:.1f} mm "
               f"({a['final'] / r['batch_teacher_posegraph_ate_m']:.2f}x) |" if "batch_teacher_posegraph_ate_m" in r
               else ""))
    return "\n".join(out)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scenes", nargs="+", default=SCENES)
    ap.add_argument("--frames", default="0:300")
    ap.add_argument("--checkpoint", type=Path, help="learner checkpoint for the runs with the learner")
    ap.add_argument("--gaps", type=int, default=DEFAULT.gaps,
                    help=f"the online teacher's K (default: teacher generate's {DEFAULT.gaps}, as the val-* records ran; "
                    f"ctcvo online's own default is {online.ONLINE_GAPS}; batch: always the default's)")
    ap.add_argument("--pose-after-gap1", action=argparse.BooleanOptionalAction,
                    default=online.OnlineConfig.pose_after_gap1,
                    help="ctcvo online --pose-after-gap1 in the online runs (default: on, as ctcvo online)")
    ap.add_argument("--keyframes", choices=("on", "off", "both"), default="on",
                    help="the online teacher's keyframe and loop edges (both: a row each, in this order: on, off)")
    ap.add_argument("--out", type=Path, help="the runs' outputs (default runs/bench/NAME)")
    record.add_arguments(ap, "online")
    args = ap.parse_args()
    tcfg = replace(DEFAULT, gaps=args.gaps)
    ocfg = online.OnlineConfig(pose_after_gap1=args.pose_after_gap1)
    out = args.out or record.RUNS / args.name
    rec = record.from_args(args, out=out, teacher=tcfg, online=ocfg)
    rows = []
    for spec in args.scenes:
        for kf in {"on": (True,), "off": (False,), "both": (True, False)}[args.keyframes]:
            rows.append(bench_scene(spec, args.frames, args.checkpoint, out / ("keyframes" if kf else "window"),
                                    replace(tcfg, keyframes=kf), ocfg))
            rec.finish({"rows": rows})
    print(table(rows))
    return 0


if __name__ == "__main__":
    sys.exit(main())
