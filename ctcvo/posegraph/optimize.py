"""The ``posegraph optimize`` stage: edges in, fused trajectory and report out.

Inputs (see docs/formats.md, "Pose graph"): a teacher folder and/or a learner folder
(``edges.g2o`` + optional ``edges.csv``, ``trajectory.tum``, ``groundtruth.tum``), or
bare g2o files. Outputs in ``out``: ``trajectory.tum`` (fused), ``report.json``,
``report.md``, ``config.json``, PNG figures, and ``marginals.npz`` on request. Nothing is
written until every sequence has been solved and reported; each file is written
atomically.
"""

from __future__ import annotations

import io
import json
import logging
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from ctcvo.data.errors import ConfigError, DataError
from ctcvo.data.formats import Trajectory, write_tum
from ctcvo.data.io import atomic_write, ensure_dir, git_revision, write_json, write_text
from ctcvo.data.runs import (
    Fingerprint,
    claim,
    file_digest,
    output_folder,
    scene_id,
    stage_dir,
    upstream_digest,
    write_fingerprint,
)
from ctcvo.data.scenes import open_scene
from ctcvo.data.sequence import parse_frame_range
from ctcvo.posegraph import edges as pe
from ctcvo.posegraph import fusion
from ctcvo.posegraph import report as rep
from ctcvo.posegraph.calibration import GapScales, read_gap_scales
from ctcvo.posegraph.config import DEFAULT, PoseGraphConfig
from ctcvo.posegraph.graph import SolveResult, solve
from ctcvo.posegraph.plots import make_plots
from ctcvo.posegraph.sources import (
    Frames,
    Source,
    find_sequence_dirs,
    load_dir,
    load_edges_file,
    poses_for_frames,
    resolve_frames,
)

log = logging.getLogger(__name__)

#: what the stage writes per sequence (``--overwrite`` removes them first; plots are
#: overwritten by name)
OUTPUT_FILES = ("trajectory.tum", "marginals.npz", "config.json", "report.md", "report.json")


@dataclass
class SequenceOutput:
    """Everything one sequence writes, held in memory until all sequences succeeded."""

    out: Path
    trajectory: Trajectory
    report: dict
    markdown: str
    pngs: dict[str, bytes]
    marginals: bytes | None


@dataclass
class _Graph:
    """One solved graph of a sequence: the result, its bridge edges and where its initial values came from."""

    result: SolveResult
    edges: list
    """The graph's edges, bridges aside."""
    bridges: list
    initial_from: str


def default_dirs(scene: str) -> tuple[Path, Path, Path]:
    """(teacher, learner, out) folders of a scene: ``runs/<slug>/{teacher,predict,posegraph}``."""
    return stage_dir(scene, "teacher"), stage_dir(scene, "predict"), stage_dir(scene, "posegraph")


def optimize(scene: str | None = None, teacher: Path | None = None, learner: Path | None = None,
             edges: Sequence[Path] = (), out: Path | None = None, cfg: PoseGraphConfig = DEFAULT,
             split: str = "all", frames: str | None = None, overwrite: bool = False,
             teacher_calibration: Path | None = None) -> list[Path]:
    """Run the stage; return the output folders (one per sequence).

    With only ``scene``, the teacher/learner folders default to ``runs/<slug>/teacher`` and
    ``runs/<slug>/predict`` (each used if it exists). ``edges`` files are used instead of
    folders. Every source is cut to ``frames`` (positions in the scene's sequence, or in
    the sources' frame list without a scene); without ``frames``, to the frames that every
    source covers, so that a teacher run longer than the learner's never leaves frames
    that only one source connects. Outputs follow the rerun rule of :mod:`data.runs`.
    ``teacher_calibration``: a per-gap covariance calibration of the teacher's edges
    (``posegraph calibrate``, fitted on validation data) applied before the graph.
    """
    scales = None
    if teacher_calibration is not None:
        scales = read_gap_scales(Path(teacher_calibration))
        scales.info["path"] = str(teacher_calibration)
    teacher, learner, out = _folders(scene, teacher, learner, edges, out)
    jobs = _jobs(teacher, learner, edges)
    with output_folder(out):
        results = []
        for name, srcs in jobs:
            cut = cut_sources(srcs, _frame_selection(srcs, scene, split, name, frames))
            o = out / name if name else out
            fp = Fingerprint("posegraph", {
                "scene": scene_id(scene) if scene else None, "frames": cut, "config": cfg.to_dict(),
                "inputs": {n: _source_digest(s) for n, s in srcs.items()},
                "teacher_calibration": file_digest(Path(teacher_calibration)) if teacher_calibration else None})
            finished = (o / "report.json").is_file()
            if claim(o, fp, done=finished, has_outputs=finished, overwrite=overwrite, outputs=OUTPUT_FILES):
                log.info("%s: pose graph of the same inputs: kept", o)
                continue
            r = optimize_sequence(srcs, o, cfg, scene=scene, split=split, seq_name=name, frames_cut=cut,
                                  teacher_scales=scales)
            results.append((r, fp))
        for r, fp in results:  # write only after every sequence succeeded
            write_outputs(r, cfg, fp)
    return [out / name if name else out for name, _ in jobs]


def _folders(scene: str | None, teacher: Path | None, learner: Path | None, edges: Sequence[Path],
             out: Path | None) -> tuple[Path | None, Path | None, Path]:
    """The (teacher, learner, out) folders of :func:`optimize`, defaults of ``scene`` filled in."""
    teacher = Path(teacher) if teacher else None
    learner = Path(learner) if learner else None
    if scene and not (teacher or learner or edges):
        t, l, o = default_dirs(scene)
        teacher = t if t.is_dir() else None
        learner = l if l.is_dir() else None
        if not (teacher or learner):
            raise DataError(f"neither {t} nor {l} exists; run `teacher generate --scene {scene}` first "
                            "or pass --teacher/--learner/--edges")
        out = out or o
    if scene and out is None:
        out = default_dirs(scene)[2]
    if out is None:
        raise ConfigError("--out is required without --scene")
    if not (teacher or learner or edges):
        raise ConfigError("give --scene, --teacher, --learner or --edges")
    if edges and (teacher or learner):
        raise ConfigError("--edges replaces --teacher/--learner; give one or the other")
    return teacher, learner, Path(out)


def _jobs(teacher: Path | None, learner: Path | None, edges: Sequence[Path]) -> list[tuple[str, dict[str, Source]]]:
    """(sequence name, sources by name) of every graph to solve: one for ``edges`` files,
    else one per sequence folder of the teacher (or learner) folder."""
    if edges:
        srcs = {}
        for p in edges:
            s = load_edges_file(Path(p))
            name = s.name if s.name not in srcs else f"{s.name}{len(srcs)}"
            for e in s.edges:
                e.extra["source"] = name
            s.name = name
            srcs[name] = s
        return [("", srcs)]
    for d, what in ((teacher, "teacher"), (learner, "learner")):
        if d is not None and not d.is_dir():
            raise DataError(f"{what} folder {d} does not exist")
    names = find_sequence_dirs(teacher) if teacher else []
    if not names and learner:
        names = find_sequence_dirs(learner)
    jobs = []
    for name in names or [""]:
        srcs = {}
        for d, what in ((teacher, "teacher"), (learner, "learner")):
            if d is not None:
                srcs[what] = load_dir(d / name if name else d, what)
        jobs.append((name, srcs))
    return jobs


def _source_digest(s: Source) -> str:
    """A source folder's fingerprint digest (or its edges' content digest), a bare file's content digest."""
    return upstream_digest(s.path, "edges.g2o") if s.path.is_dir() else file_digest(s.path)


def _frame_selection(srcs: dict[str, Source], scene: str | None, split: str, seq_name: str,
                     frames: str | None) -> set[int] | None:
    """The frame ids to keep: ``frames`` of the scene's sequence (or of the sources' frame
    list without a scene); without ``frames`` the ids every source covers when they differ
    (None: keep everything)."""
    covered = [source_frame_ids(s) for s in srcs.values()]
    if frames:
        if scene:
            seqs = open_scene(scene, split=split, frames=frames)
            seqs = [s for s in seqs if s.name == seq_name] or seqs
            return {int(k) for k in seqs[0].ids()}
        a, b, st = parse_frame_range(frames)
        return set(sorted(set().union(*covered))[slice(a, b, st)])
    if len(covered) > 1 and any(c != covered[0] for c in covered[1:]):
        keep = set.intersection(*covered)
        log.info("the sources cover different frames (%s): the graph uses the %d frames all of them cover "
                 "(--frames to choose)", ", ".join(f"{n} {len(c)}" for n, c in zip(srcs, covered)), len(keep))
        return keep
    return None


def source_frame_ids(s: Source) -> set[int]:
    """The frame ids a source lists (g2o vertices, edges.csv) or its edges use."""
    return {int(k) for k in s.vertices} | {int(k) for k in s.times} | {int(k) for e in s.edges for k in (e.i, e.j)}


def cut_sources(srcs: dict[str, Source], keep: set[int] | None) -> str | None:
    """Cut every source to the frames ``keep`` (in place); a readable description of the cut."""
    if keep is None:
        return None
    if len(keep) < 2:
        raise DataError(f"the frame selection leaves {len(keep)} frame(s) for the pose graph; the sources cover "
                        + ", ".join(f"{n} {_span(source_frame_ids(s))}" for n, s in srcs.items()))
    for n, s in srcs.items():
        s.edges = [e for e in s.edges if e.i in keep and e.j in keep]
        s.vertices = {k: v for k, v in s.vertices.items() if int(k) in keep}
        s.times = {k: t for k, t in s.times.items() if int(k) in keep}
        if not s.edges:
            raise DataError(f"{n} has no edges between the selected frames {_span(keep)}")
    return _span(keep)


def _span(ids: set[int]) -> str:
    return f"ids {min(ids)}..{max(ids)} ({len(ids)} frames)" if ids else "no frames"


def _scene_groundtruth(scene: str, split: str, seq_name: str, frames: Frames) -> NDArray[np.float64] | None:
    seqs = open_scene(scene, split=split)
    if seq_name:
        seqs = [s for s in seqs if s.name == seq_name] or seqs
    for s in seqs:
        gt = s.groundtruth()
        if gt is None:
            continue
        ids = {int(k): n for n, k in enumerate(s.ids())}
        if all(int(k) in ids for k in frames.ids):
            poses = np.stack([gt[ids[int(k)]] for k in frames.ids])
            if np.all(np.isfinite(poses)):
                return poses
    return None


def _groundtruth(srcs: dict[str, Source], frames: Frames, scene: str | None, split: str,
                 seq_name: str) -> tuple[NDArray[np.float64] | None, str | None]:
    """(ground-truth poses of the frames, where from): a source's ``groundtruth.tum``, else the scene's."""
    for s in srcs.values():
        if s.groundtruth is not None:
            gt = poses_for_frames(s.groundtruth, frames, partial=not frames.synthetic_times)
            has = rep.finite_rows(gt) if gt is not None else np.zeros(0, bool)
            if has.sum() < 2:
                raise DataError(f"{s.path}/groundtruth.tum does not cover the {len(frames.ids)} frames of the graph")
            if not has.all():  # the teacher left frames with a non-finite ground truth out
                missing = frames.ids[~has]
                log.warning("%s/groundtruth.tum has no pose for %d of the graph's %d frames (%s): the figures "
                            "against ground truth leave them out", s.path, len(missing), len(has),
                            ", ".join(map(str, missing[:5])) + (" ..." if len(missing) > 5 else ""))
            return gt, str(s.path / "groundtruth.tum")
    if scene:
        gt = _scene_groundtruth(scene, split, seq_name, frames)
        return gt, f"scene {scene}" if gt is not None else None
    return None, None


def _solve_graph(srcs: dict[str, Source], used: list[str], frames: Frames, edges: list, guide, cfg: PoseGraphConfig,
                 fixed: list[str], label: str) -> _Graph:
    """Solve the graph of ``edges`` (sources ``used``), bridged where it is disconnected,
    with the teacher's landmark sightings when it is used and has them; ``label`` names it
    in the solver's log lines."""
    bridges = pe.bridge_edges(frames.ids, edges, guide, pe.bridge_cov(frames.ids, edges))
    initial, init_how = fusion.initial_poses(srcs, used, frames, edges + bridges)
    obs = srcs["teacher"].observations if "teacher" in used else None
    result = solve(frames.ids, edges + bridges, initial, cfg, fixed_sources=fixed + ["bridge"], label=label,
                   observations=obs)
    return _Graph(result, edges, bridges, init_how)


def optimize_sequence(srcs: dict[str, Source], out: Path, cfg: PoseGraphConfig = DEFAULT,
                      scene: str | None = None, split: str = "all", seq_name: str = "",
                      frames_cut: str | None = None, teacher_scales: GapScales | None = None) -> SequenceOutput:
    """Solve one sequence and build its outputs in memory (nothing is written);
    ``frames_cut`` says how the sources were cut (:func:`cut_sources`) for the report.
    ``teacher_scales``: per-gap covariance scales of the teacher's edges fitted on
    validation data (:mod:`posegraph.calibration`); the teacher then keeps them in the
    graph (no per-source rescaling)."""
    used = fusion.graph_sources(srcs, cfg)
    frames = resolve_frames(list(srcs.values()))
    for s in srcs.values():
        pe.validate_edges(frames.ids, s.edges)  # unknown frames, bad covariances
    raw_teacher = None
    fixed: list[str] = []
    if teacher_scales is not None and "teacher" in srcs:
        raw_teacher = srcs["teacher"].edges
        srcs["teacher"].edges = teacher_scales.apply(frames.ids, raw_teacher)
        fixed.append("teacher")
    gates = {n: fusion.skill_gate(srcs[n], frames) for n in used}
    edges = fusion.graph_edges(srcs, used, frames, gates, cfg)
    fixed += [f"{n}:unskilled" for n in used]
    gt, gt_from = _groundtruth(srcs, frames, scene, split, seq_name)

    guide = fusion.guide_poses(srcs, used, frames)
    fused = _solve_graph(srcs, used, frames, edges, guide, cfg, fixed, rep.ROW_LABELS["fused"])
    if fused.bridges:
        log.warning("the graph's edges leave it disconnected: %d bridge edge(s) from %s (%s)", len(fused.bridges),
                    "the chained trajectory" if guide is not None else "zero motion",
                    ", ".join(f"{b.i}->{b.j}" for b in fused.bridges[:5]) + (" ..." if len(fused.bridges) > 5 else ""))
    teacher_graph = None  # the control; with the teacher's edges alone in the graph, the fused row is it
    if "teacher" in srcs and srcs["teacher"].edges and used != ["teacher"]:
        teacher_graph = _solve_graph(srcs, ["teacher"], frames, srcs["teacher"].edges, guide, cfg, fixed,
                                     rep.ROW_LABELS["teacher_graph"])
    rows, blocks = _rows(srcs, used, frames, gt, cfg, fused, teacher_graph, raw_teacher)
    report = {
        "stage": "posegraph", "scene": scene, "name": seq_name, "git": git_revision(), "config": cfg.to_dict(),
        "inputs": {n: str(s.path) for n, s in srcs.items()}, "graph_sources": used,
        "frames": len(frames.ids), "frames_listed_by": frames.listed_by, "frames_cut": frames_cut,
        "synthetic_timestamps": frames.synthetic_times, "has_groundtruth": gt is not None, "groundtruth_from": gt_from,
        "frames_without_groundtruth": [] if gt is None else [int(k) for k in frames.ids[~rep.finite_rows(gt)]],
        "initial_values": fused.initial_from, "edges_total": len(edges),
        "edges_per_source": {n: len(srcs[n].edges) for n in used},
        "bridges": {"fused": len(fused.bridges),
                    "teacher_graph": len(teacher_graph.bridges) if teacher_graph is not None else None},
        "teacher_calibration": None if teacher_scales is None else {
            "scales": {str(g): v for g, v in sorted(teacher_scales.scales.items())},
            "from": teacher_scales.info.get("path")},
        "skill_gate": {n: g for n, g in gates.items() if g is not None},
        "rows": blocks,
        **_solver_report(fused.result),
    }
    json.dumps(report, allow_nan=False)  # fail here, not half-way through writing
    result = fused.result
    pngs = {}
    if cfg.plots:
        first = result.first_residuals if result.first_residuals is not None else result.residuals
        pngs = make_plots(frames.times, rows, gt, frames.ids, fused.edges + fused.bridges, first, result.outliers,
                          cfg.residual_threshold)
    marg = None
    if result.marginals is not None:
        buf = io.BytesIO()
        np.savez_compressed(buf, frame_ids=frames.ids, timestamps=frames.times, cov=result.marginals)
        marg = buf.getvalue()
    return SequenceOutput(out, Trajectory(frames.times, result.poses), report, rep.report_markdown(report), pngs, marg)


def _solver_report(result: SolveResult) -> dict:
    """The report's entries on the fused solve: scales, outliers, residuals, solver figures."""
    return {
        "covariance_scales": result.source_scales,
        "covariance_calibration": result.calibration,
        "outliers": [o.to_dict() for o in result.outliers],
        "residuals": {"median": float(np.median(result.residuals)), "max": float(np.max(result.residuals))},
        "solver": {"name": result.solver, "iterations": result.iterations, "initial_error": result.initial_error,
                   "final_error": result.final_error, "time_s": result.time_s, "cpu_s": result.cpu_s},
        "bundle": result.bundle,
    }


def _rows(srcs: dict[str, Source], used: list[str], frames: Frames, gt: NDArray[np.float64] | None,
          cfg: PoseGraphConfig, fused: _Graph, teacher_graph: _Graph | None,
          raw_teacher: list | None) -> tuple[dict[str, NDArray[np.float64]], dict[str, dict]]:
    """(poses, report block) of every row: each source's trajectory, the teacher graph, the
    fused graph and the baselines (those only with ground truth)."""
    rows: dict[str, NDArray[np.float64]] = {}
    blocks: dict[str, dict] = {}
    for n, s in srcs.items():
        traj = poses_for_frames(s.trajectory, frames)
        how = f"{s.path}/trajectory.tum"
        if traj is None:
            try:
                traj = pe.chain_poses(frames.ids, s.edges)
                how = "chained edges (spanning tree, smallest gaps first)"
            except pe.GraphError as exc:
                log.warning("no chained %s row: %s", n, exc)
                continue
        rows[n] = traj
        blocks[n] = rep.row_block(n, traj, frames.ids, frames.times, gt, s.edges, s.edges, how)
        if n == "teacher" and raw_teacher is not None:
            blocks[n]["calibration_raw"] = rep.calibration(raw_teacher, frames.ids, gt)
        if n == "teacher" and teacher_graph is not None:
            t_bridges = teacher_graph.bridges
            rows["teacher_graph"] = teacher_graph.result.poses
            blocks["teacher_graph"] = rep.row_block(
                "teacher_graph", teacher_graph.result.poses, frames.ids, frames.times, gt, s.edges, None,
                f"{cfg.solver} over the teacher's edges alone" + (f" and {len(t_bridges)} bridge edge(s)"
                                                                   if t_bridges else ""))
    bridges = fused.bridges
    rows["fused"] = fused.result.poses
    blocks["fused"] = rep.row_block("fused", fused.result.poses, frames.ids, frames.times, gt,
                                    fused.edges, None,
                                    f"{cfg.solver} over {'+'.join(used)} edges"
                                    + (f" and {len(bridges)} bridge edge(s)" if bridges else ""))
    blocks.update(rep.baseline_blocks(frames.ids, frames.times, gt))  # absent without ground truth
    return rows, blocks


def write_outputs(r: SequenceOutput, cfg: PoseGraphConfig, fp: Fingerprint | None = None) -> None:
    """Write one sequence's outputs atomically, file by file; fingerprint.json, then
    report.json last (it marks completion)."""
    ensure_dir(r.out)
    write_tum(r.out / "trajectory.tum", r.trajectory)
    for name, data in r.pngs.items():
        with atomic_write(r.out / name, "wb") as fh:
            fh.write(data)
    if r.marginals is not None:
        with atomic_write(r.out / "marginals.npz", "wb") as fh:
            fh.write(r.marginals)
    write_json(r.out / "config.json", {"git": r.report["git"], **cfg.to_dict()})
    write_text(r.out / "report.md", r.markdown)
    if fp is not None:
        write_fingerprint(r.out, fp)
    write_json(r.out / "report.json", r.report)
    log.info("wrote %s", r.out)


__all__ = ["optimize", "optimize_sequence", "default_dirs", "write_outputs", "SequenceOutput"]
