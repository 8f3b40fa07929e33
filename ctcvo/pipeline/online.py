"""``ctcvo online``: odometry frame by frame, as the frames arrive.

Frames come from any scene read one at a time in order, or from a folder still being
written (:mod:`data.live`). For each new frame k:

1. the teacher's window (:class:`teacher.window.EdgeWindow`, the code ``teacher generate``
   runs) gives the edges (k-g, k), g = 1..K;
2. with a checkpoint, the learner (:class:`learner.online.OnlineLearner`) adds MC-dropout
   edges (k-g, k), g = 1..max_gap;
3. GTSAM's ISAM2 (:class:`posegraph.online.OnlineGraph`) is updated with the new pose and
   its edges;
4. the new pose's current estimate is appended to ``trajectory.tum`` and flushed;
5. with ``TeacherConfig.keyframes`` (the default, as in ``teacher generate``), the frame is
   offered to the keyframe worker (:mod:`pipeline.online_keyframes`), which estimates the
   keyframe and loop edges of each new keyframe in a helper thread; the edges it finished
   enter the graph after a later frame's pose, and the run waits for the rest at its end.

The frame loop is :mod:`pipeline.online_loop`, the outputs :mod:`pipeline.online_outputs`
(docs/formats.md, "Online mode"), the command line :mod:`pipeline.online_cli`. :func:`online`
follows the rerun rule of :mod:`data.runs` (``fingerprint.json`` beside the outputs).
"""

from __future__ import annotations

import dataclasses
import json
import logging
from dataclasses import dataclass, field
from pathlib import Path

from ctcvo.data.errors import ConfigError, DataError
from ctcvo.data.io import ensure_dir
from ctcvo.data.live import FollowFolder, FrameSource, SequenceSource, follow_folder
from ctcvo.data.runs import (
    FINGERPRINT_FILE,
    STAGE_VERSIONS,
    Fingerprint,
    claim,
    file_digest,
    frames_id,
    output_folder,
    scene_id,
    stage_dir,
    write_fingerprint,
)
from ctcvo.data.scenes import open_scene
from ctcvo.data.undistort import with_camera
from ctcvo.learner.config import PredictConfig, to_dict
from ctcvo.learner.online import OnlineLearner
from ctcvo.pipeline.online_keyframes import KeyframeWorker
from ctcvo.pipeline.online_loop import ONLINE_GAPS, Estimator, OnlineConfig, OnlineTeacher, drive
from ctcvo.pipeline.online_outputs import OUTPUT_FILES, REPORT, TRAJECTORY, TRAJECTORY_HEADER, percentiles_ms, write_outputs
from ctcvo.posegraph.config import ONLINE
from ctcvo.posegraph.online import OnlineGraph
from ctcvo.teacher.config import DEFAULT as TEACHER_DEFAULT
from ctcvo.teacher.config import colour_camera_for
from ctcvo.teacher.timing import rolling_shutter_for

log = logging.getLogger(__name__)
#: the teacher ``ctcvo online`` runs when given none: the default one, window ``ONLINE_GAPS``
TEACHER_ONLINE = dataclasses.replace(TEACHER_DEFAULT, gaps=ONLINE_GAPS)


@dataclass
class OnlineResult:
    """What a run did (also in ``report.json``)."""

    out: Path
    frames: int
    fps: float
    latency_ms: dict[str, float]
    interrupted: bool
    report: dict = field(default_factory=dict)
    kept: bool = False
    """A finished run of the same inputs was found and kept (nothing was computed)."""


def open_source(spec: str, frames: str | None = None, follow: bool = False,
                cfg: OnlineConfig = OnlineConfig(), camera: Path | None = None) -> FrameSource:
    """The frame source of ``spec`` (``follow``: a folder still being written; ``camera``: a
    camera file whose distortion undistorts the frames, as for ``teacher generate``)."""
    if follow:
        if frames:
            raise ConfigError("--frames does not apply with --follow (frames are taken as they arrive)")
        if camera is not None:
            raise ConfigError("--camera does not apply with --follow (a live folder is read as recorded)")
        return follow_folder(Path(spec), cfg.poll_s, cfg.timeout_s, cfg.drop_late)
    seqs = open_scene(spec, frames=frames)
    if len(seqs) != 1:
        raise ConfigError(f"{spec} holds {len(seqs)} sequences; give one sequence folder")
    return SequenceSource(seqs[0] if camera is None else with_camera(seqs[0], camera))


def run(source: FrameSource, out: Path, teacher_cfg=None, checkpoint: Path | None = None,
        predict_cfg=None, graph_cfg=None, cfg: OnlineConfig = OnlineConfig(), device: str = "cpu",
        max_frames: int | None = None, progress: bool = True) -> OnlineResult:
    """Run the online pipeline over ``source`` (see the module docstring); KeyboardInterrupt
    ends it early with every output written for the frames so far (``interrupted``)."""
    teacher_cfg = teacher_cfg or TEACHER_ONLINE
    out = ensure_dir(Path(out))
    learner = OnlineLearner(checkpoint, predict_cfg, device) if checkpoint is not None else None
    graph = OnlineGraph(graph_cfg)
    sensor = source.sensor  # the teacher's colour camera model and readout, as teacher generate picks them
    teacher = OnlineTeacher(source.intrinsics,
                            dataclasses.replace(teacher_cfg, rolling_shutter_s=rolling_shutter_for(sensor, teacher_cfg)),
                            colour_camera_for(sensor, teacher_cfg), sensor.noise_model)
    with open(out / TRAJECTORY, "w") as fh:
        fh.write(TRAJECTORY_HEADER)
        kf = KeyframeWorker(teacher.intr, teacher.cfg, teacher.colour) if teacher_cfg.keyframes else None
        est = Estimator(teacher, learner, graph, cfg, fh, kf)
        interrupted, seconds, skipped = drive(source, est, cfg, max_frames, progress)
    if est.n == 0:
        (out / TRAJECTORY).unlink(missing_ok=True)  # nothing to keep
        raise DataError(f"{source.name}: no frame arrived")
    est.trim()
    tm = est.timings
    lat_ms = percentiles_ms(tm.latency)
    timing = {"latency_ms": lat_ms, "frames_skipped": skipped, "work_ms": percentiles_ms(tm.work),
              "work_to_pose_ms": percentiles_ms(tm.to_pose), "work_to_pose_cpu_ms": percentiles_ms(tm.cpu_to_pose)}
    report = write_outputs(out, source.name, est, teacher_cfg, seconds, timing, interrupted, checkpoint)
    return OnlineResult(out, est.n, est.n / seconds, lat_ms, interrupted, report)


def fingerprint(spec: str, source: FrameSource, teacher_cfg, checkpoint: Path | None = None, predict_cfg=None,
                graph_cfg=None, cfg: OnlineConfig = OnlineConfig()):
    """The inputs of an online run (``data.runs.Fingerprint``): scene, sequence, frames (with
    ``--follow``: as they arrive), the teacher's config (without its process settings), the
    checkpoint and the calibration beside it (content digests), the MC-dropout settings and
    the graph's config."""
    tconf = teacher_cfg.to_dict()
    for k in ("workers", "chunk_frames"):  # how batch runs share the work; no effect here
        tconf.pop(k, None)
    follow = isinstance(source, FollowFolder)
    cal = Path(checkpoint).parent / "calibration.json" if checkpoint is not None else None
    und = source.seq.undistortion if isinstance(source, SequenceSource) else None  # the frames' lens undistortion
    if checkpoint is not None:
        pconf = to_dict(predict_cfg or PredictConfig())
    return Fingerprint("online", {
        "scene": scene_id(spec), "sequence": source.name,
        "frames": "as they arrive" if follow else frames_id(source.seq.ids()) if isinstance(source, SequenceSource)
        else None, "follow": follow, "teacher": tconf, "teacher_version": STAGE_VERSIONS["teacher"],
        "checkpoint": file_digest(checkpoint) if checkpoint is not None else None,
        "calibration": file_digest(cal) if cal is not None and cal.is_file() else None,
        "predict": pconf if checkpoint is not None else None, "graph": (graph_cfg or ONLINE).to_dict(),
        "pose_after_gap1": cfg.pose_after_gap1,
        **({"drop_late": True} if cfg.drop_late else {}),  # absent when off: earlier runs stay valid
        **({"undistortion": list(und.coeffs)} if und is not None else {})})


def online(spec: str, out: Path | None = None, *, frames: str | None = None, follow: bool = False,
           teacher_cfg=None, checkpoint: Path | None = None, predict_cfg=None, graph_cfg=None,
           cfg: OnlineConfig = OnlineConfig(), device: str = "cpu", overwrite: bool = False,
           progress: bool = True, camera: Path | None = None) -> OnlineResult:
    """``ctcvo online``: :func:`run` over the scene ``spec`` into ``out`` (default
    ``runs/<scene-slug>/online``), under the rerun rule of :mod:`data.runs`.

    A finished run of the same inputs is kept (returned from its ``report.json``; with
    ``follow``, only while the folder holds no frame the run did not take); an interrupted
    or killed one is run again; outputs of other inputs are replaced with ``overwrite``,
    otherwise :class:`data.runs.StaleOutputError` says what differs. A run is finished when
    its ``report.json`` (written last) says it was not interrupted."""
    teacher_cfg = teacher_cfg or TEACHER_ONLINE
    out = Path(out) if out is not None else stage_dir(spec, "online")
    with output_folder(out):
        source = open_source(spec, frames, follow, cfg, camera)
        fp = fingerprint(spec, source, teacher_cfg, checkpoint, predict_cfg, graph_cfg, cfg)
        report = None
        if (out / REPORT).is_file():
            try:
                report = json.loads((out / REPORT).read_text())
            except (OSError, ValueError):
                report = None  # unreadable: not a finished run
        done = isinstance(report, dict) and report.get("interrupted") is False
        if done and follow:
            done = report.get("frame_ids") == frames_id(source.present_ids())
        if claim(out, fp, done=done, has_outputs=report is not None, overwrite=overwrite, outputs=OUTPUT_FILES):
            log.info("%s: online run of the same inputs: kept", out)
            lat = report.get("latency_ms") or {}
            return OnlineResult(out, int(report["frames"]), float(report.get("fps") or 0.0), lat, False, report,
                                kept=True)
        for name in OUTPUT_FILES:  # an unfinished run of the same inputs: start afresh, report.json first
            (out / name).unlink(missing_ok=True)
        write_fingerprint(ensure_dir(out), fp)
        try:
            return run(source, out, teacher_cfg, checkpoint, predict_cfg, graph_cfg, cfg, device, progress=progress)
        except BaseException:
            if not (out / TRAJECTORY).exists():  # not one frame taken: leave nothing behind
                (out / FINGERPRINT_FILE).unlink(missing_ok=True)
            raise
