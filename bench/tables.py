"""The tables of bench/README.md and README.md, generated from the records in bench/results/.

Each table sits between ``<!-- table: NAME -->`` and ``<!-- /table -->``; everything else in
the documents is written by hand. A table lists the records it was made from (revision,
date, cores, load average), so a stale number shows up as a stale file.

    .venv/bin/python -m bench.tables           # rewrite the tables in both documents
    .venv/bin/python -m bench.tables --check   # exit 1 when a document is not what the records make
"""

from __future__ import annotations

import argparse
import re
import sys
from collections.abc import Callable
from pathlib import Path

from bench import record
from ctcvo.data.io import write_text
from ctcvo.data.metrics import BASELINES

DOCUMENTS = (record.REPO / "bench" / "README.md", record.REPO / "README.md")
BLOCK = re.compile(r"(<!-- table: (?P<name>[\w-]+) -->\n)(?P<body>.*?)(<!-- /table -->)", re.S)


# ----------------------------------------------------------------------------------
# formatting
# ----------------------------------------------------------------------------------
def num(x: float | None, digits: int = 1) -> str:
    return "-" if x is None else f"{x:.{digits}f}"


def mm(x: float | None, digits: int = 1) -> str:
    return "-" if x is None else f"{1000 * x:.{digits}f}"


def scene_label(spec: str) -> str:
    """A reader's name for a scene argument: ``redkitchen/seq-sample``, ``TUM fr1/xyz``, ``synthetic/lab``."""
    if spec.startswith("synthetic/"):
        return spec
    p = Path(spec)
    tum = re.match(r"rgbd_dataset_freiburg(\d)_(\w+)", p.name)
    return f"TUM fr{tum[1]}/{tum[2]}" if tum else f"{p.parent.name}/{p.name}"


def range_label(key: str) -> str:
    """``seq-sample:0:450`` -> ``redkitchen 0:450``; ``rgbd_dataset_freiburg3_teddy:0:200`` -> ``fr3/teddy 0:200``."""
    name, a, b = key.rsplit(":", 2)
    tum = re.match(r"rgbd_dataset_freiburg(\d)_(\w+)", name)
    name = f"fr{tum[1]}/{tum[2]}" if tum else "redkitchen" if name == "seq-sample" else name
    return f"{name} {a}:{b}"


def frames_label(config: dict) -> str:
    return f" {config['frames']}" if isinstance(config.get("frames"), str) else ""


def markdown(header: list[str], rows: list[list[str]]) -> list[str]:
    return ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)] + ["| " + " | ".join(r) + " |" for r in rows]


def provenance(recs: dict[str, dict]) -> str:
    """One line naming the records of a table, each with its revision, date, cores and load."""
    parts = []
    for name, r in recs.items():
        m = r["machine"]
        load = f"{m['load_average_start'][0]:.1f}-{m['load_average_end'][0]:.1f}"
        parts.append(f"`{name}` ({r['revision']}, {r['date_utc'][:10]}, {m['cpu_count']} cores, load {load})")
    return "Records: " + "; ".join(parts) + "."


def select(records: dict[str, dict], prefix: str) -> dict[str, dict]:
    return {n: r for n, r in records.items() if n == prefix or n.startswith(prefix + "-")}


def missing(command: str) -> list[str]:
    return [f"No record yet: `{command}`."]


# ----------------------------------------------------------------------------------
# the tables
# ----------------------------------------------------------------------------------
TEACHER_HEAD = ["scene", "frames", "method", "fps", "fps / Open3D", "gap-1 fails / lost frames", "gap-1 RPE mm",
                "gap-1 RPE deg", "1 s RPE mm", "1 s RPE deg", "ATE mm", "se(3) L2"]


def spread(x: dict, key: str, show: Callable[[float | None], str]) -> str:
    """``x[key]`` shown by ``show``; for a row of several runs (ORB-SLAM3) the median with
    its min-max over the runs."""
    lo_hi = x.get("spread", {}).get(key)
    if lo_hi is None or x.get("runs", 1) < 2:
        return show(x.get(key))
    return f"{show(x.get(key))} ({show(lo_hi[0])}-{show(lo_hi[1])})"


def teacher_cells(x: dict, frames: str) -> list[str]:
    """One row of the teacher table: a method on one scene (bench.teacher's record rows)."""
    fails = (f"lost {'/'.join(map(str, x['lost_frames_per_run']))}" if "lost_frames_per_run" in x
             else str(x["gap1_failures"]))
    runs = f", {x['runs']} runs" if "runs" in x else ""
    return [scene_label(x["scene"]) + frames, str(x["frames"]), x["method"] + runs, spread(x, "fps", num),
            f"{num(x.get('fps_vs_open3d'))}x", fails, spread(x, "rpe_trans_rmse_m", lambda v: mm(v, 2)),
            spread(x, "rpe_rot_rmse_deg", lambda v: num(v, 3)), spread(x, "rpe_1s_trans_m", mm),
            spread(x, "rpe_1s_rot_deg", lambda v: num(v, 2)), spread(x, "ate_rmse_m", mm),
            spread(x, "se3_l2_mean", lambda v: num(v, 5))]


def teacher_records(records: dict[str, dict]) -> dict[str, dict]:
    """The records of bench.teacher (``teacher-*`` with rows of methods)."""
    return {n: r for n, r in select(records, "teacher").items()
            if r["figures"].get("rows") and "method" in r["figures"]["rows"][0]}


def teacher_table(records: dict[str, dict]) -> list[str]:
    recs = teacher_records(records)
    if not recs:
        return missing("python -m bench.teacher")
    rows = [teacher_cells(x, frames_label(r["config"])) for r in recs.values() for x in r["figures"]["rows"]]
    return markdown(TEACHER_HEAD, rows) + ["", provenance(recs)]


def learner_cell(x: dict) -> str:
    """The online run with a learner beside the teacher-only one of the same bench run."""
    if "learner_fps" not in x:
        return "-"
    lat, paced = x["learner_latency_ms"], x["learner_30hz_latency_ms"]
    return (f"{x.get('learner_preset', '?')} preset: {num(x['learner_fps'])} ({x['learner_fps'] / x['online_fps']:.2f}x), "
            f"{lat['p50']:.0f} / {lat['p95']:.0f}, {paced['p50']:.0f} / {paced['p95']:.0f}")


def learner_cost(r: dict | None) -> str:
    """The summary's words on what a learner costs ``ctcvo online`` (the ``online-learner`` record)."""
    if not r:
        return ""
    x = r["figures"]["rows"][0]
    cpu = x["learner_work_to_pose_cpu_ms"]["p50"] - x["online_work_to_pose_cpu_ms"]["p50"]
    return (f"; with a learner ({x['learner_preset']} preset, K=10, {x['scene']}{frames_label(r['config'])}) "
            f"{num(x['learner_fps'])} fps, {x['learner_fps'] / x['online_fps']:.2f}x the teacher alone in the same run "
            f"({cpu:.0f} ms more CPU a frame; {r['machine']['cpu_count']} cores at load "
            f"{r['machine']['load_average_start'][0]:.0f})")


def online_table(records: dict[str, dict]) -> list[str]:
    recs = select(records, "online")
    if not recs:
        return missing("python -m bench.online --frames 0:150")
    rows = []
    for r in recs.values():
        for x in r["figures"]["rows"]:
            a, b = x["ate_m"], x["batch_teacher_posegraph_ate_m"]
            lat, work, paced = x["online_latency_ms"], x["online_work_to_pose_ms"], x["online_30hz_latency_ms"]
            rows.append([f"{x['scene']}{frames_label(r['config'])}",
                         f"gaps {x['online_gaps']}" + (", pose after gap 1" if x["pose_after_gap1"] else "")
                         + {True: ", keyframes", False: ", window only"}.get(x.get("keyframes"), ""),
                         num(x["batch_fps"]), f"{num(x['online_fps'])} ({x['online_fps'] / x['batch_fps']:.2f}x)",
                         f"{lat['p50']:.0f} / {lat['p95']:.0f}", f"{work['p50']:.0f} / {work['p95']:.0f}",
                         f"{paced['p50']:.0f} / {paced['p95']:.0f}",
                         f"{mm(a['final'])} / {mm(a['causal'])} vs {mm(a['batch_posegraph'])}", mm(b),
                         learner_cell(x)])
    head = ["scene", "online settings", "batch teacher fps", "online fps (ratio)", "latency p50 / p95 ms",
            "own work until the pose p50 / p95 ms", "paced 30 Hz latency p50 / p95 ms",
            "ATE mm final / causal vs batch pose graph (same edges)", "batch pose graph ATE mm (default teacher)",
            "with a learner: fps (x teacher only), latency p50 / p95 ms, paced 30 Hz p50 / p95 ms"]
    return markdown(head, rows) + ["", provenance(recs)]


def online_validation_table(records: dict[str, dict]) -> list[str]:
    """The online settings on the validation ranges (records ``val-*``, one setting each): per
    range, final and causal ATE and p95 latency as fast as frames come and paced at 30 Hz."""
    recs = select(records, "val")
    if not recs:
        return missing("python -m bench.online --scenes S --frames A:B [--no-pose-after-gap1] [--gaps K] --name val-X")
    order = [(5, False), (5, True), (4, True), (3, True)]  # (gaps, pose after gap 1) of the columns' cells
    cells: dict[str, dict] = {}
    for r in recs.values():
        for x in r["figures"]["rows"]:
            cells.setdefault(f"{x['scene']}{frames_label(r['config'])}", {})[(x["online_gaps"], x["pose_after_gap1"])] = x

    def cell(by: dict, f) -> str:
        return " / ".join(f(by[k]) if k in by else "-" for k in order)

    rows = [[rng, cell(by, lambda x: mm(x["ate_m"]["final"])), cell(by, lambda x: mm(x["ate_m"]["causal"])),
             cell(by, lambda x: f"{x['online_latency_ms']['p95']:.0f}"),
             cell(by, lambda x: f"{x['online_30hz_latency_ms']['p95']:.0f}")] for rng, by in sorted(cells.items())]
    head = ["validation range (gaps 5 / + pose after gap 1 / + gaps 4 / + gaps 3)", "final ATE mm", "causal ATE mm",
            "latency p95 ms", "paced 30 Hz p95 ms"]
    return markdown(head, rows) + ["", provenance(recs)]


def posegraph_table(records: dict[str, dict]) -> list[str]:
    recs = {n: r for n, r in select(records, "posegraph").items() if "sizes" in r["figures"]}
    if not recs:
        return missing("python -m bench.posegraph")
    rows = [[str(x["poses"]), str(x["edges"]), x["solver"].upper(), f"{x['build_s']:.2f} ({x['build_cpu_s']:.2f})",
             f"{x['solve_s']:.2f} ({x['solve_cpu_s']:.2f}), {x['iterations']}",
             f"{x['full_s']:.2f} ({x['full_cpu_s']:.2f})", f"{x['rss_mb']:.0f}", str(x["outliers"]),
             f"{x['end_error_m']:.3f}"]
            for r in recs.values() for x in r["figures"]["sizes"]]
    head = ["poses", "edges", "solver", "build s (CPU)", "optimiser s (CPU), iterations", "whole solve() s (CPU)",
            "peak RSS + MB", "outliers", "end-pose error m"]
    return markdown(head, rows) + ["", provenance(recs)]


def keyframes_table(records: dict[str, dict]) -> list[str]:
    """One row per variant of bench.keyframes' sweep: each validation range's graph ATE / 1 s RPE
    and gap-1 RPE (mm), the keyframe edges it added and the keyframe pass's seconds."""
    recs = select(records, "keyframes")
    if not recs:
        return missing("python -m bench.keyframes")
    r = next(iter(recs.values()))
    scenes = r["figures"]["scenes"]
    variants = list(next(iter(scenes.values())))
    rows, same, default = [], [], None
    for v in variants:
        cells = [v]
        for row in scenes.values():
            x = row[v]
            cells.append(f"{mm(x['ate_m'])} / {mm(x['rpe_1s_m'])} / {mm(x['rpe_gap1_m'], 2)}")
        kf = sum(row[v]["edges_by_kind"].get(k, 0) for row in scenes.values() for k in ("keyframe", "loop"))
        secs = sum(row[v].get("keyframe_pass_s", 0.0) for row in scenes.values())
        if v == "default":
            default = cells[1:] + [str(kf)]
        elif cells[1:] + [str(kf)] == default:
            same.append(v)  # every cell and edge count the default's
            continue
        rows.append(cells + [str(kf), num(secs)])
    head = ["variant"] + [range_label(k) for k in scenes] + ["keyframe + loop edges", "pass s"]
    note = [f"Same figures and edges as `default`: {', '.join(same)}."] if same else []
    return markdown(head, rows) + [""] + note + [provenance(recs)]


def dense_gap1_table(records: dict[str, dict]) -> list[str]:
    """bench.dense_gap1: per validation range, each variant's teacher graph ATE / gap-1 / 1 s
    RPE (mm) and the yaw's (camera y) scale error of its gap-1 edges."""
    recs = select(records, "dense-gap1")
    if not recs:
        return missing("python -m bench.dense_gap1")
    scenes = next(iter(recs.values()))["figures"]["scenes"]
    variants = list(next(iter(scenes.values())))
    rows = [[range_label(key)] + [f"{mm(x['ate_m'])} / {mm(x['rpe_gap1_m'], 2)} / {mm(x['rpe_1s_m'])}, "
                                  f"{x['rotation_scale_error']['1'][1]:+.2f}" for x in row.values()]
            for key, row in scenes.items()]
    return markdown(["range"] + variants, rows) + ["", provenance(recs)]


def depth_bias_table(records: dict[str, dict]) -> list[str]:
    """bench.depth_bias: per synthetic room, the chain's and the teacher graph's ATE and the
    graph's 1 s RPE (mm), as rendered -> with the true depth bias pattern removed."""
    recs = select(records, "depth-bias")
    if not recs:
        return missing("python -m bench.depth_bias --camera CAM.json")
    split = {"lab": "validation", "office": "training", "kitchen": "test"}
    rec, rows = next(iter(recs.values())), []
    for room, r in rec["figures"]["rooms"].items():
        a, b = r["as rendered"], r["bias removed"]
        rows.append([f"{room} ({split.get(room, 'training')})", f"{mm(a['chain_ate_m'])} -> {mm(b['chain_ate_m'])}",
                     f"{mm(a['ate_m'])} -> {mm(b['ate_m'])}", f"{mm(a['rpe_1s_m'])} -> {mm(b['rpe_1s_m'])}"])
    head = [f"room, frames {rec['config']['frames']}", "chain ATE mm", "teacher graph ATE mm", "graph 1 s RPE mm"]
    return markdown(head, rows) + ["", provenance(recs)]


def drift_table(records: dict[str, dict]) -> list[str]:
    """bench.drift: per validation range and method, the translation / rotation RPE at each
    time scale and the rotation's scale at 1 s."""
    recs = select(records, "drift")
    if not recs:
        return missing("python -m bench.drift --orbslam3-vocabulary VOC.txt")
    rec = next(iter(recs.values()))
    scales = rec["config"]["scales_s"]
    rows = []
    for r in rec["figures"]["rows"]:
        if "rpe_m" not in r:  # an ORB-SLAM3 that tracked no run
            continue
        method = f"{r['method']}, median of {r['runs']}" if "runs" in r else r["method"]
        rows.append([range_label(Path(r["range"]).name), method]
                    + [f"{mm(t)} / {num(d, 2)}" for t, d in zip(r["rpe_m"], r["rpe_deg"])]
                    + [num(r["rotation_scale_1s"], 3)])
    head = ["range", "method"] + ["1 frame" if s == 0 else f"{s:.2g} s" for s in scales] + ["rotation scale, 1 s"]
    return markdown(head, rows) + ["", provenance(recs)]


def covariance_table(records: dict[str, dict]) -> list[str]:
    recs = select(records, "teacher-covariance")
    if not recs:
        return missing("python -m bench.teacher_covariance")
    rows = []
    for r in recs.values():
        for model, fig in r["figures"].items():
            scales = ", ".join(f"{s:.3g}" for s in fig["gap_scales"])
            for name, row in fig["ranges"].items():
                raw, cal = row["raw"], row["calibrated"]
                rows.append([model, f"{', '.join(fig['fit'])} -> {scales}", f"{name} ({row['role']})",
                             f"{num(raw['nees_median_over_dof'])} / {num(raw['nees_over_dof'])}",
                             f"{num(cal['nees_median_over_dof'], 2)} / {num(cal['nees_over_dof'], 2)}",
                             f"{num(raw['coverage_2sigma'], 2)} -> {num(cal['coverage_2sigma'], 2)}"])
    head = ["noise model", "fitted on -> scales, gap 1-5", "range", "raw NEES/6 median / mean",
            "calibrated NEES/6 median / mean", "2-sigma coverage"]
    return markdown(head, rows) + ["", provenance(recs)]


def learner_table(records: dict[str, dict]) -> list[str]:
    recs = select(records, "learner")
    if not recs:
        return missing("python -m bench.learner")
    rows = []
    for r in recs.values():
        x = r["figures"]
        rows.append([x["preset"], x["input"], str(x["threads"]), x["size"]]
                    + [f"{x[f'{k}_pairs_per_s']:.0f} ({x[f'{k}_pairs_per_cpu_s']:.0f})"
                       for k in ("train_phase1", "train_phase2", "predict")])
    head = ["preset", "input", "threads", "size", "training, pairs / s (per CPU s)", "training with windows (CTC)",
            "MC-dropout prediction, K=10"]
    return markdown(head, rows) + ["", provenance(recs)]


def render_table(records: dict[str, dict]) -> list[str]:
    recs = select(records, "render")
    if not recs:
        return missing("python -m bench.render")
    rows = [[f"synthetic/{name}", str(x["frames"]), num(x["render_fps"]), num(x["cpu_ms_per_frame"], 0),
             num(x["decode_fps"], 0), num(x["disk_mb"])]
            for r in recs.values() for name, x in r["figures"]["presets"].items()]
    head = ["preset", "frames", "render frames / s", "CPU ms / frame", "read back frames / s", "disk MB"]
    return markdown(head, rows) + ["", provenance(recs)]


def realism_table(records: dict[str, dict]) -> list[str]:
    recs = select(records, "synthetic-realism")
    if not recs:
        return missing("python -m bench.synthetic_realism")
    rows = []
    for r in recs.values():
        scenes = r["figures"]["scenes"]
        real = scenes["redkitchen"]
        for name, x in scenes.items():
            rows.append([name if name == "redkitchen" else f"synthetic/{name}",
                         f"{x['gap1_trans_rmse_mm']:.2f} / {x['gap1_rot_rmse_deg']:.3f}",
                         f"{x['gap1_trans_median_mm']:.2f} / {x['gap1_rot_median_deg']:.3f}",
                         f"{x['gap5_trans_rmse_mm']:.2f} / {x['gap5_rot_rmse_deg']:.3f}",
                         f"{x['rpe30_trans_rmse_mm']:.1f} / {x['rpe30_rot_rmse_deg']:.2f}",
                         f"{x['gap1_trans_rmse_mm'] / real['gap1_trans_rmse_mm']:.2f} / "
                         f"{x['gap1_rot_rmse_deg'] / real['gap1_rot_rmse_deg']:.2f}"])
    head = ["scene", "gap-1 RMSE mm / deg", "gap-1 median mm / deg", "gap-5 RMSE mm / deg", "1 s RPE mm / deg",
            "gap-1 RMSE / real"]
    return markdown(head, rows) + ["", provenance(recs)]


def ablation_table(records: dict[str, dict]) -> list[str]:
    """Per record: the teacher and baselines, then each variant - with several seeds their
    mean +- std (the record keeps every seed's row)."""
    recs = select(records, "ablation")
    if not recs:
        return missing("python -m bench.ablation --scene S --frames 0:350 --val-scene S --val-frames 350:450 "
                       "--test-frames 450:600 --teacher T --teacher-eval T --name ablation-redkitchen")
    keys = (("se3_l2_mean", lambda x: num(x, 5)), ("se3_l2_x_teacher", lambda x: num(x, 2)),
            ("rpe_trans_rmse_m", lambda x: mm(x, 2)), ("rpe_rot_rmse_deg", lambda x: num(x, 3)),
            ("ate_rmse_m", mm))
    rows: list[list[str]] = []
    for name, rec in recs.items():
        seeds = {v: s for v, s in rec["figures"].get("seeds", {}).items() if len(s["seeds"]) > 1}
        for key, r in rec["figures"]["rows"].items():
            if r.get("variant") in seeds:
                continue
            cells = [r.get("label", key)] + [show(r.get(k)) for k, show in keys]
            same = next((x for x in rows if "variant" not in r and x[1:] == cells), None)
            if same is not None:  # a reference row another record of the same test frames shows
                same[0] += f", {name}"
            else:
                rows.append([name] + cells)
        for v, s in seeds.items():
            rows.append([name, f"{v} ({len(s['seeds'])} seeds)"] +
                        [f"{show(x['mean'])} +- {show(x['std'])}" if (x := s.get(k)) else "-" for k, show in keys])
    head = ["record", "row", "se(3) L2", "x teacher", "gap-1 RPE mm", "gap-1 RPE deg", "ATE mm"]
    return markdown(head, rows) + ["", provenance(recs)]


def _noise_cell(r: dict, names: list[str], ratio: bool) -> str:
    """se(3) L2 mean of a teacher-noise row on each range of ``names`` ("-" where it has none; with
    ``ratio``, also its ratio to its teacher)."""
    return " / ".join("-" if n not in r else num(r[n]["se3_l2_mean"], 5) +
                      (f" ({num(r[n]['vs_teacher'], 2)}x)" if ratio else "") for n in names)


def noise_table(records: dict[str, dict]) -> list[str]:
    """One row per teacher: its own labels' se(3) L2 mean, then each learner trained on them (its
    ratio to the teacher), on the held-out range / on the training range itself (transductive);
    under the table each record's ranges and zero motion's and constant velocity's errors there."""
    recs = select(records, "teacher-noise")
    if not recs:
        return missing("python -m bench.teacher_noise run ... (its docstring)")
    names = ["held-out", "transductive"]
    variants = list(dict.fromkeys(x["variant"] for r in recs.values() for x in r["figures"]["learners"].values()))
    rows, notes = [], []
    for rec in recs.values():
        f = rec["figures"]
        for tname, t in f["teachers"].items():
            by = {x["variant"]: x for x in f["learners"].values() if x["teacher"] == tname}
            rows.append([rec["name"], f"{tname}: {_noise_cell(t, names, False)}"] +
                        [_noise_cell(by[v], names, True) if v in by else "-" for v in variants])
        base = ", ".join(b + " " + " / ".join(num(f["baselines"][n][b]["se3_l2_mean"], 5) for n in names)
                         for b in BASELINES)
        notes.append(f"`{rec['name']}` ({' / '.join(n + ' ' + f['ranges'][n] for n in names)}): {base}.")
    head = ["record", "teacher's labels: held-out / transductive se(3) L2"] + variants
    return markdown(head, rows) + ["", " ".join(notes), provenance(recs)]


def orbslam3_covariance_table(records: dict[str, dict]) -> list[str]:
    r = records.get("orbslam3-covariance")
    if not r:
        return missing("python -m bench.orbslam3_covariance --vocabulary VOC.txt")
    f = r["figures"]
    by = f["nees_by_gap"]
    def cell(x: dict) -> str:
        return f"{num(x['nees_over_6'], 2)} / {num(x['median_nees_over_chi2_median'], 2)} / {num(x['coverage_1sigma'], 2)}"

    rows = [[g, str(x["edges"])] + [cell(by[m][g]) for m in ("placeholder", "fit", "fit_with_points")]
            for g, x in by["fit"].items()]
    fit, fp, nll = f["fit"], f["fit_with_points"], f["nll_per_edge"]
    text = (f"Fit: sigma_trans(1) {mm(fit['sigma_trans_gap1_m'], 2)} mm, sigma_rot(1) {num(fit['sigma_rot_gap1_deg'], 3)} deg, "
            f"gap exponent {num(fit['gap_exponent'], 2)}; with the points factor {mm(fp['sigma_trans_gap1_m'], 2)} mm, "
            f"{num(fp['sigma_rot_gap1_deg'], 3)} deg, {num(fp['gap_exponent'], 2)}. NLL per edge: placeholder "
            f"{num(nll['placeholder'], 2)}, fit {num(nll['fit'], 2)}, fit with points {num(nll['fit_with_points'], 2)}.")
    head = ["gap", "edges", "placeholder: NEES/6 / median NEES/chi2 / 1-sigma coverage", "fit (no points factor)",
            "fit with points factor"]
    return markdown(head, rows) + ["", text, "", provenance({"orbslam3-covariance": r})]


def demo_table(records: dict[str, dict], dated: bool = True) -> list[str]:
    """The demo's rows and time; ``dated``: with the record's revision, date and load (README.md's
    copy names the record only: a first-contact document has no run history)."""
    r = records.get("demo")
    if not r:
        return missing("python -m bench.demo")
    f = r["figures"]
    rows = [[x["label"], mm(x["ate_rmse_m"]), f"{mm(x['rpe_g1_trans_m'], 2)} / {num(x['rpe_g1_rot_deg'], 3)}",
             mm(x["rpe_1s_trans_m"]), num(x["se3_l2_mean"], 4)] for x in f["rows"].values()]
    head = [f"{f['test_scene']}, {f['frames']} frames", "ATE mm", "gap-1 RPE mm / deg", "RPE 1 s mm", "se(3) L2"]
    return markdown(head, rows) + ["", f"`ctcvo demo` took {f['wall_s'] / 60:.0f} min ({f['cpu_s'] / 60:.0f} min of CPU; "
                                       f"rooms already rendered: {', '.join(r['config']['rooms_in_render_cache']) or 'none'}). "
                                       + (provenance({"demo": r}) if dated else
                                          f"On {r['machine']['cpu_count']} cores busy with other jobs (load "
                                          f"{r['machine']['load_average_start'][0]:.0f}); record `demo`."
                                          if r['machine']['load_average_start'][0] >= 1.5 else
                                          f"On {r['machine']['cpu_count']} idle cores; record `demo`.")]


def summary_table(records: dict[str, dict]) -> list[str]:
    """README.md's table of what each stage does, one measured figure each."""
    rows = []
    t = records.get("teacher-redkitchen-test")
    if t:
        by = {x["method"].split()[0]: x for x in t["figures"]["rows"]}
        me, o3d = by["this"], by["Open3D"]
        rows.append(["`ctcvo teacher generate`",
                     "RGB-D frames -> relative-pose labels of gaps 1-5 and keyframe pairs, with 6x6 covariances",
                     f"redkitchen 450:600: gap-1 error {mm(me['rpe_trans_rmse_m'], 2)} mm / "
                     f"{num(me['rpe_rot_rmse_deg'], 3)} deg (Open3D {mm(o3d['rpe_trans_rmse_m'], 2)} / "
                     f"{num(o3d['rpe_rot_rmse_deg'], 3)}), {num(me['fps'])} fps ({num(me['fps_vs_open3d'])}x Open3D)"])
    lr = records.get("learner-cpu")
    if lr:
        x = lr["figures"]
        rows.append(["`ctcvo learner fit` / `predict`", "labels -> CNN+LSTM relative poses with MC-dropout covariances",
                     f"cpu preset: trains {x['train_phase1_pairs_per_s']:.0f} pairs/s, predicts "
                     f"{x['predict_pairs_per_s']:.0f} pairs/s (K=10) on {lr['machine']['cpu_count']} cores"])
    pg = records.get("posegraph")
    if pg:
        big = max(pg["figures"]["sizes"], key=lambda x: (x["solver"] == "lm", x["poses"]))
        rows.append(["`ctcvo posegraph optimize`", "teacher + learner edges -> fused trajectory, ATE / RPE report",
                     f"{big['poses']} poses / {big['edges']} edges solved in {big['full_s']:.1f} s"])
    r = records.get("online-low-latency")
    if r:
        x = r["figures"]["rows"][0]
        rows.append(["`ctcvo online`", "frames as they arrive -> a pose per frame, ISAM2-smoothed",
                     f"{x['scene']}{frames_label(r['config'])}, gaps {x['online_gaps']}: {num(x['online_fps'])} fps, "
                     f"latency p95 {x['online_latency_ms']['p95']:.0f} ms" + learner_cost(records.get("online-learner"))])
    return markdown(["command", "what it does", "measured (bench/results/)"], rows)


def results_table(records: dict[str, dict]) -> list[str]:
    """README.md's table of current results: the teacher beside its peers on the real recordings."""
    recs = {n: r for n, r in teacher_records(records).items()
            if not r["figures"]["rows"][0]["scene"].startswith("synthetic/")}
    if not recs:
        return missing("python -m bench.teacher")
    rows = []
    for r in recs.values():
        by = {x["method"].split()[0]: x for x in r["figures"]["rows"]}
        cells = [f"{mm(x['rpe_trans_rmse_m'], 2)} / {num(x['rpe_rot_rmse_deg'], 3)} / {mm(x['ate_rmse_m'])}"
                 if x else "-" for x in (by.get("this"), by.get("teacher"), by.get("ORB-SLAM3"), by.get("Open3D"),
                                         by.get("cv2.Odometry"))]
        me = by["this"]
        rows.append([scene_label(me["scene"]) + frames_label(r["config"]), *cells,
                     f"{num(me['fps'])} ({num(me.get('fps_vs_open3d'))}x)"])
    head = ["recording, frames", "teacher: gap-1 mm / deg / ATE mm", "teacher pose graph", "ORB-SLAM3 (median of runs)",
            "Open3D hybrid", "OpenCV RGB_DEPTH", "teacher fps (x Open3D)"]
    return markdown(head, rows) + ["", "Records: " + ", ".join(f"`{n}`" for n in recs) + " (bench/README.md)."]


TABLES: dict[str, Callable[[dict[str, dict]], list[str]]] = {
    "teacher": teacher_table, "online": online_table, "online-validation": online_validation_table,
    "posegraph": posegraph_table, "keyframes": keyframes_table, "dense-gap1": dense_gap1_table,
    "depth-bias": depth_bias_table, "drift": drift_table,
    "learner": learner_table, "teacher-covariance": covariance_table,
    "render": render_table, "synthetic-realism": realism_table, "ablation": ablation_table,
    "teacher-noise": noise_table, "orbslam3-covariance": orbslam3_covariance_table, "demo": demo_table,
    "demo-readme": lambda r: demo_table(r, dated=False), "summary": summary_table,
    "results": results_table,
}


def update(text: str, records: dict[str, dict]) -> str:
    """``text`` with every table block regenerated from ``records``."""

    def block(m: re.Match) -> str:
        name = m["name"]
        if name not in TABLES:
            raise SystemExit(f"unknown table {name!r} (known: {', '.join(TABLES)})")
        return m.group(1) + "\n".join(TABLES[name](records)) + "\n" + m.group(4)

    return BLOCK.sub(block, text)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--check", action="store_true", help="change nothing; exit 1 when a document is stale")
    ap.add_argument("--results", type=Path, default=record.RESULTS)
    args = ap.parse_args(argv)
    records = record.load(args.results)
    stale = []
    for doc in DOCUMENTS:
        text = doc.read_text()
        new = update(text, records)
        if new != text:
            stale.append(doc)
            if not args.check:
                write_text(doc, new)
    for doc in stale:
        print(f"{'stale' if args.check else 'updated'}: {doc.relative_to(record.REPO)}", file=sys.stderr)
    return 1 if args.check and stale else 0


if __name__ == "__main__":
    sys.exit(main())
