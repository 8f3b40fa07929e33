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
from dataclasses import dataclass
from pathlib import Path
from typing import Optional, Sequence

import numpy as np
from numpy.typing import NDArray

from data.errors import ConfigError, DataError
from data.formats import Trajectory, write_tum
from data.io import atomic_write, ensure_dir, git_revision, write_json, write_text
from data.runs import (Fingerprint, claim, file_digest, output_folder, scene_id, stage_dir, upstream_digest,
                       write_fingerprint)
from posegraph import graph as pg
from posegraph import report as rep
from posegraph.config import DEFAULT, PoseGraphConfig
from posegraph.sources import (Frames, Source, find_sequence_dirs, load_dir, load_edges_file, poses_for_frames,
                               resolve_frames)

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
    marginals: Optional[bytes]


def default_dirs(scene: str) -> tuple[Path, Path, Path]:
    """(teacher, learner, out) folders of a scene: ``runs/<slug>/{teacher,predict,posegraph}``."""
    return stage_dir(scene, "teacher"), stage_dir(scene, "predict"), stage_dir(scene, "posegraph")


def optimize(scene: Optional[str] = None, teacher: Optional[Path] = None, learner: Optional[Path] = None,
             edges: Sequence[Path] = (), out: Optional[Path] = None, cfg: PoseGraphConfig = DEFAULT,
             split: str = "all", frames: Optional[str] = None, overwrite: bool = False) -> list[Path]:
    """Run the stage; return the output folders (one per sequence).

    With only ``scene``, the teacher/learner folders default to ``runs/<slug>/teacher`` and
    ``runs/<slug>/predict`` (each used if it exists). ``edges`` files are used instead of
    folders. Every source is cut to ``frames`` (positions in the scene's sequence, or in
    the sources' frame list without a scene); without ``frames``, to the frames that every
    source covers, so that a teacher run longer than the learner's never leaves frames
    that only one source connects. Outputs follow the rerun rule of :mod:`data.runs`.
    """
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
    out = Path(out)

    jobs: list[tuple[str, dict[str, Source]]] = []
    if edges:
        srcs = {}
        for p in edges:
            s = load_edges_file(Path(p))
            name = s.name if s.name not in srcs else f"{s.name}{len(srcs)}"
            for e in s.edges:
                e.extra["source"] = name
            s.name = name
            srcs[name] = s
        jobs.append(("", srcs))
    else:
        for d, what in ((teacher, "teacher"), (learner, "learner")):
            if d is not None and not d.is_dir():
                raise DataError(f"{what} folder {d} does not exist")
        names = find_sequence_dirs(teacher) if teacher else []
        if not names and learner:
            names = find_sequence_dirs(learner)
        for name in names or [""]:
            srcs = {}
            for d, what in ((teacher, "teacher"), (learner, "learner")):
                if d is not None:
                    srcs[what] = load_dir(d / name if name else d, what)
            jobs.append((name, srcs))

    with output_folder(out):
        results = []
        for name, srcs in jobs:
            cut = cut_sources(srcs, _frame_selection(srcs, scene, split, name, frames))
            o = out / name if name else out
            fp = Fingerprint("posegraph", {
                "scene": scene_id(scene) if scene else None, "frames": cut, "config": cfg.to_dict(),
                "inputs": {n: _source_digest(s) for n, s in srcs.items()}})
            finished = (o / "report.json").is_file()
            if claim(o, fp, done=finished, has_outputs=finished, overwrite=overwrite, outputs=OUTPUT_FILES):
                log.info("%s: pose graph of the same inputs: kept", o)
                continue
            r = optimize_sequence(srcs, o, cfg, scene=scene, split=split, seq_name=name, frames_cut=cut)
            results.append((r, fp))
        for r, fp in results:  # write only after every sequence succeeded
            write_outputs(r, cfg, fp)
    return [out / name if name else out for name, _ in jobs]


def _source_digest(s: Source) -> str:
    """A source folder's fingerprint digest (or its edges' content digest), a bare file's content digest."""
    return upstream_digest(s.path, "edges.g2o") if s.path.is_dir() else file_digest(s.path)


def _frame_selection(srcs: dict[str, Source], scene: Optional[str], split: str, seq_name: str,
                     frames: Optional[str]) -> Optional[set[int]]:
    """The frame ids to keep: ``frames`` of the scene's sequence (or of the sources' frame
    list without a scene); without ``frames`` the ids every source covers when they differ
    (None: keep everything)."""
    covered = [source_frame_ids(s) for s in srcs.values()]
    if frames:
        if scene:
            from data.scenes import open_scene

            seqs = open_scene(scene, split=split, frames=frames)
            seqs = [s for s in seqs if s.name == seq_name] or seqs
            return {int(k) for k in seqs[0].ids()}
        from data.sequence import parse_frame_range

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


def cut_sources(srcs: dict[str, Source], keep: Optional[set[int]]) -> Optional[str]:
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


def _scene_groundtruth(scene: str, split: str, seq_name: str, frames: Frames) -> Optional[NDArray[np.float64]]:
    from data.scenes import open_scene

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


def optimize_sequence(srcs: dict[str, Source], out: Path, cfg: PoseGraphConfig = DEFAULT,
                      scene: Optional[str] = None, split: str = "all", seq_name: str = "",
                      frames_cut: Optional[str] = None) -> SequenceOutput:
    """Solve one sequence and build its outputs in memory (nothing is written);
    ``frames_cut`` says how the sources were cut (:func:`cut_sources`) for the report."""
    used = _graph_sources(srcs, cfg)
    frames = resolve_frames(list(srcs.values()), cfg.fps)
    pos = {int(k): p for p, k in enumerate(frames.ids)}
    for s in srcs.values():
        pg.validate_edges(frames.ids, s.edges)  # unknown frames, bad covariances
        if cfg.max_gap is not None:
            s.edges = [e for e in s.edges if abs(pos[e.j] - pos[e.i]) <= cfg.max_gap]
    edges = [e for n in used for e in srcs[n].edges]
    if not edges:
        raise DataError("no edges left for the pose graph")

    gt = None
    gt_from = None
    for s in srcs.values():
        if s.groundtruth is not None:
            gt = poses_for_frames(s.groundtruth, frames)
            if gt is None:
                raise DataError(f"{s.path}/groundtruth.tum does not cover the {len(frames.ids)} frames of the graph")
            gt_from = str(s.path / "groundtruth.tum")
            break
    if gt is None and scene:
        gt = _scene_groundtruth(scene, split, seq_name, frames)
        gt_from = f"scene {scene}" if gt is not None else None

    initial, init_how = _initial(srcs, used, frames, edges, cfg)
    result = pg.solve(frames.ids, edges, initial, cfg)

    rows: dict[str, NDArray[np.float64]] = {}
    blocks: dict[str, dict] = {}
    for n, s in srcs.items():
        traj = poses_for_frames(s.trajectory, frames)
        how = f"{s.path}/trajectory.tum"
        if traj is None:
            try:
                traj = pg.chain_poses(frames.ids, s.edges)
                how = "chained edges (spanning tree, smallest gaps first)"
            except pg.GraphError as exc:
                log.warning("no chained %s row: %s", n, exc)
                continue
        rows[n] = traj
        blocks[n] = rep.row_block(n, traj, frames.ids, frames.times, gt, s.edges, s.edges, how)
    rows["fused"] = result.poses
    blocks["fused"] = rep.row_block("fused", result.poses, frames.ids, frames.times, gt, edges, None,
                                    f"{cfg.solver} over {'+'.join(used)} edges")
    blocks.update(rep.baseline_blocks(frames.ids, frames.times, gt))  # absent without ground truth

    report = {
        "stage": "posegraph",
        "scene": scene,
        "name": seq_name,
        "git": git_revision(),
        "config": cfg.to_dict(),
        "inputs": {n: str(s.path) for n, s in srcs.items()},
        "graph_sources": used,
        "frames": len(frames.ids),
        "frames_listed_by": frames.listed_by,
        "frames_cut": frames_cut,
        "synthetic_timestamps": frames.synthetic_times,
        "has_groundtruth": gt is not None,
        "groundtruth_from": gt_from,
        "initial_values": init_how,
        "edges_total": len(edges),
        "edges_per_source": {n: len(srcs[n].edges) for n in used},
        "rows": blocks,
        "covariance_scales": result.source_scales,
        "covariance_calibration": result.calibration,
        "outliers": [o.to_dict() for o in result.outliers],
        "residuals": {"median": float(np.median(result.residuals)), "max": float(np.max(result.residuals))},
        "solver": {"name": result.solver, "iterations": result.iterations, "initial_error": result.initial_error,
                   "final_error": result.final_error, "time_s": result.time_s, "cpu_s": result.cpu_s},
    }
    json.dumps(report, allow_nan=False)  # fail here, not half-way through writing
    md = rep.report_markdown(report)
    pngs = {}
    if cfg.plots:
        from posegraph.plots import make_plots  # matplotlib only when figures are wanted

        pngs = make_plots(
            frames.times, rows, gt, frames.ids, edges, result.residuals, ~result.used)
    marg = None
    if result.marginals is not None:
        buf = io.BytesIO()
        np.savez_compressed(buf, frame_ids=frames.ids, timestamps=frames.times, cov=result.marginals)
        marg = buf.getvalue()
    return SequenceOutput(out, Trajectory(frames.times, result.poses), report, md, pngs, marg)


def _graph_sources(srcs: dict[str, Source], cfg: PoseGraphConfig) -> list[str]:
    if cfg.sources == "auto":
        return list(srcs)
    need = ["teacher", "learner"] if cfg.sources == "fused" else [cfg.sources]
    missing = [n for n in need if n not in srcs]
    if missing:
        raise ConfigError(f"--use {cfg.sources} needs the {' and '.join(missing)} folder")
    return need


def _initial(srcs: dict[str, Source], used: list[str], frames: Frames, edges, cfg: PoseGraphConfig):
    if cfg.init in ("teacher", "learner"):
        s = srcs.get(cfg.init)
        traj = poses_for_frames(s.trajectory, frames) if s else None
        if traj is None:
            raise DataError(f"--init {cfg.init}: no {cfg.init} trajectory.tum covering every frame")
        return traj, f"{s.path}/trajectory.tum"
    if cfg.init == "auto":
        for n in used:
            traj = poses_for_frames(srcs[n].trajectory, frames)
            if traj is not None:
                return traj, f"{srcs[n].path}/trajectory.tum"
    return pg.chain_poses(frames.ids, edges), "chained edges"


def write_outputs(r: SequenceOutput, cfg: PoseGraphConfig, fp: Optional[Fingerprint] = None) -> None:
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
