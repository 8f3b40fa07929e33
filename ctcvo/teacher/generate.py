"""``teacher generate``: noisy relative-pose labels for every frame pair (i, i+g), g = 1..K.

Pipeline per sequence (frames streamed once, each frame's features reused by all its
edges):

0. the sequence is cut into chunks that worker processes handle independently;
1. a helper thread decodes frames and extracts ORB features ahead of the main loop;
2. the gap-1 edge (k-1, k) is matched with a constant-velocity prediction (guided
   matching) and estimated by PnP-RANSAC + two-way refinement;
3. its inlier matches extend feature tracks; each longer edge (k-g, k) is estimated
   from the tracks that survive from k-g to k (falling back to guided matching with
   the chained gap-1 motion, then to exhaustive matching);
4. the gap-1 trajectory is chained; a failed gap-1 edge is bridged by the shortest good
   edge that spans it, else by constant velocity, and the report lists every bridge.

Outputs (docs/formats.md): edges.g2o, edges.csv, trajectory.tum, groundtruth.tum (with
ground truth), report.json, config.json.
"""

from __future__ import annotations

import dataclasses
import logging
import sys
import threading
import time
from collections import Counter, deque
from collections.abc import Callable
from concurrent.futures import Future, ProcessPoolExecutor, ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray
from threadpoolctl import threadpool_limits
from tqdm import tqdm

from ctcvo.data.chain import chain_edges
from ctcvo.data.errors import ConfigError, DataError
from ctcvo.data.formats import Edge, Trajectory, write_edges_csv, write_g2o, write_observations, write_tum
from ctcvo.data.io import ensure_dir, git_revision, json_safe, write_json
from ctcvo.data.metrics import groundtruth_residuals, label_errors_by_gap, trajectory_report
from ctcvo.data.open3d_import import openmp_threads
from ctcvo.data.runs import Fingerprint, claim, frames_id, output_folder, scene_id, stage_dir, write_fingerprint
from ctcvo.data.scenes import open_scene
from ctcvo.data.sensor import ColourCamera
from ctcvo.data.sequence import Sequence
from ctcvo.data.uncertainty import mahalanobis2, nees_stats
from ctcvo.data.undistort import with_camera
from ctcvo.teacher import keyframes, processes, skips
from ctcvo.teacher.config import TeacherConfig, colour_camera_for, dense_method_for
from ctcvo.teacher.covariance_model import describe, gap_scale
from ctcvo.teacher.features import FrameFeatures, extract, image_keys, make_orb
from ctcvo.teacher.keyframes import depth_points, estimate_works, keyframe_works, merge_keyframe_edges
from ctcvo.teacher.loops import thumbnail
from ctcvo.teacher.maps import PhotoMaps
from ctcvo.teacher.observations import run_sightings
from ctcvo.teacher.record import EdgeEstimate, count_by_kind
from ctcvo.teacher.timing import rolling_shutter_for
from ctcvo.teacher.window import EdgeWindow

log = logging.getLogger(__name__)

OUTPUT_FILES = ("edges.g2o", "edges.csv", "observations.csv", "trajectory.tum", "groundtruth.tum", "config.json",
                "report.json")


@dataclass
class TeacherRun:
    """What :func:`run_sequence` computed (before writing)."""

    edges: list[EdgeEstimate]
    poses: NDArray[np.float64]  # (N, 4, 4) chained T_world_cam, frame 0 at the identity
    bridges: list[dict]
    seconds: float
    kinds: dict[tuple[int, int], str] = dataclasses.field(default_factory=dict)
    """``keyframe`` or ``loop`` for the edges :mod:`teacher.keyframes` added; others are ``window``."""
    frames: Sequence | None = None
    """The frames ``poses`` belong to: the sequence less the skipped ones (None: all of it)."""
    skipped: list[dict] = dataclasses.field(default_factory=list)
    """``report.json``'s ``frames_skipped`` (:func:`teacher.skips.report`)."""
    observations: NDArray[np.float64] | None = None
    """``observations.csv``'s table (:func:`teacher.observations.sightings`); None: not written."""


def run_sequence(seq: Sequence, cfg: TeacherConfig, progress: bool = True, strict: bool = False) -> TeacherRun:
    """Estimate every edge (i, i+g), g = 1..cfg.gaps, and the chained gap-1 trajectory.

    With ``cfg.workers > 1`` and enough frames, the sequence is cut into chunks of about
    ``cfg.chunk_frames`` frames that this process and ``workers - 1`` worker processes
    estimate independently (each chunk also reads the ``gaps`` frames after it, so no edge
    is lost at a boundary); processes, not threads, because the refinement is NumPy code
    that holds the GIL. They are forked by a fork server (:mod:`teacher.processes`; call
    its ``start()`` early to have them ready), so a script that calls this with
    ``workers > 1`` must guard its entry point with ``if __name__ == "__main__":`` (as
    multiprocessing requires).

    A frame that cannot be read is skipped and bridged by the longer edges, with a warning
    (:mod:`teacher.skips`; ``run.frames`` is the sequence without it); with ``strict`` its
    :class:`~data.errors.DataError` stops the run.
    """
    n = len(seq)
    t0 = time.perf_counter()
    bounds = _chunks(n, cfg)
    if cfg.keyframes and cfg.workers > 1:
        processes.start()  # the keyframe pass's workers, ready when the window is done
    bar = tqdm(total=n, desc=f"teacher {seq.name}", unit="frame", disable=not (progress and sys.stderr.isatty()))
    if len(bounds) == 1:
        edges, bad, looks = _run_chunk(seq, cfg, 0, n, bar.update, strict)
    else:
        edges, bad, looks = _run_chunks(seq, cfg, bounds, bar.update, strict)
    bar.close()
    edges.sort(key=lambda e: (e.i, e.j))
    skips.check(seq.ids(), bad, cfg.gaps)
    skips.warn(seq.name, seq.ids(), bad)
    skipped = skips.report(seq.ids(), bad, edges)
    frames = seq.without([f["frame"] for f in skipped]) if bad else seq
    poses, bridges = chain_trajectory(frames.ids(), edges)
    kinds: dict[tuple[int, int], str] = {}
    window = [e for e in edges if e.inlier_points is not None]  # before the keyframe edges join
    found = _keyframe_pass(frames, cfg, poses, looks) if cfg.keyframes and len(frames) >= 2 else []
    seen = None
    if colour_camera_for(frames.sensor, cfg) is None:  # registered colour: see teacher.observations
        seen = run_sightings([e for e, _ in found], window, frames.intrinsics)
    if found:
        kinds = merge_keyframe_edges(edges, found)
        edges.sort(key=lambda e: (e.i, e.j))
    for e in edges:
        e.inlier_pairs = e.inlier_points = None  # keeps results small
    return TeacherRun(edges, poses, bridges, time.perf_counter() - t0, kinds, frames, skipped, seen)


def features_of(seq: Sequence, cfg: TeacherConfig) -> Callable[[int], FrameFeatures]:
    """A keyframe's features by position: extracted as :func:`_run_chunk` extracts them, by
    :func:`teacher.keyframes.keyframe_orb`'s detector."""
    colour = colour_camera_for(seq.sensor, cfg)
    orb = keyframes.keyframe_orb(cfg, colour)
    cfg = dataclasses.replace(cfg, rolling_shutter_s=rolling_shutter_for(seq.sensor, cfg))
    return lambda k: keyframes.keyframe_features(seq.rgb(k), seq.depth(k), cfg, orb, seq.intrinsics.K, colour)


def _keyframe_pass(frames: Sequence, cfg: TeacherConfig, poses: NDArray[np.float64],
                   looks: dict[int, tuple[NDArray, NDArray, tuple]]) -> list[tuple[EdgeEstimate, str]]:
    """The keyframe and loop edges (:mod:`teacher.keyframes`) of ``frames``, whose window
    edges chained to ``poses``. The keyframes are picked here; their works are cut into up
    to ``cfg.workers`` runs of consecutive keyframes with about as many edges each, estimated
    by this process and worker processes (the edges do not depend on who estimates which)."""
    works = keyframe_works(frames, cfg, poses, looks)
    sizes = np.array([len(w.covisible) + len(w.loops) for w in works])
    parts = min(cfg.workers, int(sizes.sum()) // KF_EDGES_PER_WORKER)
    if parts < 2:
        return _estimate_works(frames, cfg, works)
    cuts = np.searchsorted(np.cumsum(sizes), sizes.sum() * np.arange(1, parts) / parts, side="right")
    groups = [works[a:b] for a, b in zip([0, *cuts], [*cuts, len(works)])]
    with ProcessPoolExecutor(parts - 1, mp_context=processes.context()) as children:
        futs = [children.submit(_estimate_works, frames, cfg, g) for g in groups[1:]]
        found = _estimate_works(frames, cfg, groups[0])
        for f in futs:
            found += f.result()
    return found


#: keyframe edges a worker process of the keyframe pass must have to be worth its start
KF_EDGES_PER_WORKER = 8


def _estimate_works(frames: Sequence, cfg: TeacherConfig, works: list) -> list[tuple[EdgeEstimate, str]]:
    """:func:`teacher.keyframes.estimate_works` with Open3D and BLAS on ``cfg.threads``, as
    the window runs them (the labels depend on the thread count)."""
    cfg = dataclasses.replace(cfg, rolling_shutter_s=rolling_shutter_for(frames.sensor, cfg))
    with openmp_threads(cfg.threads):
        return estimate_works(works, features_of(frames, cfg), frames.intrinsics, cfg)


def _run_chunks(seq: Sequence, cfg: TeacherConfig, bounds: list[tuple[int, int]],
                on_frame: Callable[[int], object], strict: bool = False) -> tuple[list[EdgeEstimate], dict[int, str]]:
    """Edges of all chunks, shared between this process and ``cfg.workers - 1`` children.

    Chunks are handed out one at a time as a process becomes free: children from the
    front, this process from the back. A child is sent its first chunk only once it has
    started (at once if :func:`teacher.processes.start` ran early enough; else about 2 s
    of imports), and this process works meanwhile. A chunk queued in a pool cannot be
    taken back, so handing all out up front left this process idle at the end
    (synthetic/office, 300 frames: 1.8 s of 7.4). The chunk bounds depend only on the
    sequence length, so the edges do not depend on who computes which chunk. Returns the
    edges, the unreadable frames and the looks, as :func:`_run_chunk`.
    """
    processes.start()
    todo = deque(bounds)
    lock = threading.Lock()

    def take(front: bool) -> tuple[int, int] | None:
        with lock:
            return None if not todo else todo.popleft() if front else todo.pop()

    bad: dict[int, str] = {}  # a frame read by two chunks (one reads past its end) gives one entry
    looks: dict[int, tuple] = {}

    def feed(children: ProcessPoolExecutor) -> list[EdgeEstimate]:
        """Keeps one child busy, one chunk at a time (runs in a thread of this process)."""
        out: list[EdgeEstimate] = []
        try:
            children.submit(_started).result()
            while (ab := take(front=True)) is not None:
                got, b, lk = children.submit(_run_chunk, seq, cfg, *ab, None, strict).result()
                out += got
                bad.update(b)
                looks.update(lk)
                on_frame(ab[1] - ab[0])
        except BaseException:
            todo.clear()  # the others stop after their current chunk
            raise
        return out

    edges: list[EdgeEstimate] = []
    with ProcessPoolExecutor(cfg.workers - 1, mp_context=processes.context()) as children, \
            ThreadPoolExecutor(cfg.workers - 1) as feeders:
        fed = [feeders.submit(feed, children) for _ in range(cfg.workers - 1)]
        try:
            while (ab := take(front=False)) is not None:
                got, b, lk = _run_chunk(seq, cfg, *ab, on_frame, strict)
                edges += got
                bad.update(b)
                looks.update(lk)
        except BaseException:
            todo.clear()
            raise
        for f in fed:
            edges += f.result()
    return edges, dict(sorted(bad.items())), looks


def _started() -> None:
    """A no-op a child runs to show it has started and imported this module."""


def _chunks(n: int, cfg: TeacherConfig) -> list[tuple[int, int]]:
    """Chunk ranges [a, b), ~``cfg.chunk_frames`` long, as many per process (lab 0:200 on 2: 3
    chunks 7.0 s, 2 chunks 6.0 s, figures unchanged); one when not worth splitting."""
    if cfg.workers <= 1 or n < 2 * cfg.chunk_frames:
        return [(0, n)]
    k = cfg.workers * max(1, round(n / (cfg.chunk_frames * cfg.workers)))
    edges = np.linspace(0, n, k + 1).round().astype(int)
    return [(int(a), int(b)) for a, b in zip(edges[:-1], edges[1:])]


def _run_chunk(seq: Sequence, cfg: TeacherConfig, k0: int, k1: int,
               on_frame: Callable[[int], object] | None = None,
               strict: bool = False) -> tuple[list[EdgeEstimate], dict[int, str]]:
    """Edges (i, j) whose first frame position lies in [k0, k1), with j - i <= gaps.

    Frames k0 .. k1 + gaps - 1 are streamed once: one helper thread decodes and extracts
    features ahead; the main thread hands each frame to a :class:`teacher.window.EdgeWindow`
    (the gap-1 edge guided by constant velocity, its inliers extending the feature tracks,
    then the longer edges ending at that frame from the tracks, predicted by the chained
    motion). Both threads run Open3D's kernels and BLAS with ``cfg.threads`` threads.

    Returns the edges, the frames that could not be read ({position: why}; skipped, see
    :mod:`teacher.skips`; with ``strict`` the first one's error stops the chunk, as does a
    run of ``gaps`` in a row) and, with ``cfg.keyframes``, what the keyframe pass needs of
    each frame of [k0, k1) (``looks``: {frame id: (depth points, thumbnail, image keys)}).
    """
    n = len(seq)
    ids, times, offsets = seq.ids(), seq.times(), seq.depth_offsets()
    intr = seq.intrinsics
    k_end = min(n, k1 + cfg.gaps)
    edges: list[EdgeEstimate] = []
    bad: dict[int, str] = {}
    orb = make_orb(cfg)
    colour = colour_camera_for(seq.sensor, cfg)  # it also picks the dense step's method (dense_method_for)
    cfg = dataclasses.replace(cfg, rolling_shutter_s=rolling_shutter_for(seq.sensor, cfg))

    looks: dict[int, tuple[NDArray, NDArray, tuple]] = {}

    def _extract(k: int) -> FrameFeatures:
        rgb, depth = seq.rgb(k), seq.depth(k)
        f = extract(rgb, depth, cfg, orb, intr.K, colour)  # one thread uses this ORB
        if cfg.keyframes and k < k1:  # what the keyframe pass needs of every frame, while the images are here
            looks[int(ids[k])] = (depth_points(depth, intr), thumbnail(rgb), f.keys)
        return f

    # fingerprints of the frame before the chunk, to tell whether frame k0 repeats it; the
    # walks back over earlier frames (rare) share them
    keys_of = _KeysOf(seq)
    prev_keys = keys_of(k0 - 1) if k0 > 0 else None  # None also when that frame cannot be read
    window = EdgeWindow(intr, cfg, prev_keys, until=k1 - k0,
                        prev_photo=lambda: _photo_before(seq, k0, cfg, orb, colour, keys_of),
                        prev_moments=lambda: _moments_before(seq, k0, keys_of), sightings=colour is None)
    # OpenMP's thread count is per calling thread: limit this one and the helper
    with openmp_threads(cfg.threads), \
            ThreadPoolExecutor(1, initializer=threadpool_limits, initargs=(cfg.threads,)) as pool:
        ahead = 3
        feat_futs: dict[int, Future] = {k: pool.submit(_extract, k) for k in range(k0, min(k_end, k0 + ahead))}
        for k in range(k0, k_end):
            try:
                fk = feat_futs.pop(k).result()
            except DataError as exc:
                if strict:
                    raise
                fk, bad[k] = None, str(exc)
            if k + ahead < k_end:
                feat_futs[k + ahead] = pool.submit(_extract, k + ahead)
            if fk is None:
                window.skip()
                if len(run := skips.runs_of(bad)[-1]) >= cfg.gaps:  # stop early: no edge can bridge it
                    raise skips.unbridgeable(ids, run, cfg.gaps, bad[run[0]])
            else:
                edges += window.add(int(ids[k]), float(times[k]), fk, float(offsets[k]))
            if on_frame is not None and k < k1:
                on_frame(1)
    return edges, bad, looks


class _KeysOf:
    """:func:`teacher.features.image_keys` of a sequence's frames by position, each frame
    decoded once: the walks back over the frames before a chunk (:func:`_moments_before`,
    :func:`_photo_before`) read the same frames."""

    def __init__(self, seq: Sequence) -> None:
        self.seq, self._keys = seq, {}

    def __call__(self, k: int) -> tuple[bytes, bytes] | None:
        """None for a frame that cannot be read (its own chunk reports it)."""
        if k not in self._keys:
            try:
                self._keys[k] = image_keys(self.seq.rgb(k), self.seq.depth(k))
            except DataError:
                self._keys[k] = None
        return self._keys[k]


def _moments_before(seq: Sequence, k: int, keys_of: _KeysOf | None = None) -> tuple[float, float]:
    """The moments (colour, depth; seconds) frame ``k - 1``'s images show, as a window that
    had seen the sequence from its start would hold them (:meth:`teacher.window.EdgeWindow._moments_of`):
    the timestamp of the last frame up to ``k - 1`` whose colour (depth) image differs from
    its predecessor's. For a chunk whose first frame repeats an image of the frame before it."""
    keys_of = keys_of or _KeysOf(seq)
    times = seq.times()
    found: list[float | None] = [None, None]
    j = k - 1
    while j > 0 and None in found:
        cur, prev = keys_of(j), keys_of(j - 1)
        if prev is None:  # an unreadable frame before: its images are new
            found = [float(times[j]) if m is None else m for m in found]
            break
        for c in (0, 1):
            if found[c] is None and cur[c] != prev[c]:
                found[c] = float(times[j])
        j -= 1
    return tuple(float(times[0]) if m is None else m for m in found)


def _photo_before(seq: Sequence, k: int, cfg: TeacherConfig, orb, colour: ColourCamera | None,
                  keys_of: _KeysOf | None = None) -> tuple[PhotoMaps | None, bool]:
    """The photometric maps and ``colour_behind`` mark of frame ``k - 1`` as a window that
    had seen the sequence from its start would hold them (:mod:`teacher.window`): back over
    the frames that repeat the previous frame's depth to the last one that does not, whose
    own maps (only their depth when its colour repeats: :meth:`PhotoMaps.depth_only`) they
    share; marked when that frame's colour repeats and every frame after it repeated its
    colour too. For a chunk whose first frame repeats the depth of the frame before it
    (rare: the frames are read again)."""
    keys_of = keys_of or _KeysOf(seq)
    j, behind, grey = k - 1, True, True
    while j > 0:
        cur, prev = keys_of(j), keys_of(j - 1)
        if prev is None:  # an unreadable frame before: this frame's own maps, as the sequence's first
            behind = False
            break
        behind = behind and cur[0] == prev[0]
        if cur[1] != prev[1]:  # new depth: this frame's own maps, only their depth when its colour repeats
            grey = cur[0] != prev[0]
            break
        j -= 1
    else:
        behind = False  # the sequence's first frame: its own maps
    f = extract(seq.rgb(j), seq.depth(j), cfg, orb, seq.intrinsics.K, colour)
    photo = f.dense.photo if f.dense is not None else None
    if photo is None:
        return None, False
    return (photo if grey else photo.depth_only()), behind


def chain_trajectory(ids: NDArray[np.int64], edges: list[EdgeEstimate]) -> tuple[NDArray[np.float64], list[dict]]:
    """Chain the good edges into ``T_world_cam`` (frame 0 at the identity) with
    :func:`data.chain.chain_edges`: gap-1 edges first, a failed gap-1 edge bridged by the
    shortest good edge spanning it, frames no good edge reaches placed by constant velocity.
    Returns (poses (N, 4, 4), bridges)."""
    at = {int(f): p for p, f in enumerate(ids)}
    good = [e for e in edges if e.ok]
    chained = chain_edges(ids, [(at[e.i], at[e.j]) for e in good], [e.T_i_j for e in good], fill_gaps=True)
    return chained.poses, chained.bridges


def _edge_rows(edges: list[EdgeEstimate], ts: dict[int, float], kinds: dict[tuple[int, int], str] | None = None,
               scale: dict[tuple[int, int], float] | None = None) -> list[dict]:
    kinds, scale = kinds or {}, scale or {}
    return [{
        "i": e.i, "j": e.j, "t_i": f"{ts[e.i]:.6f}", "t_j": f"{ts[e.j]:.6f}", "status": e.status,
        "matches": e.matches, "inliers": e.inliers, "inlier_ratio": float(e.inlier_ratio),
        "rmse_px": float(e.rmse_px), "trans_m": float(e.diag.trans_m), "rot_deg": float(e.diag.rot_deg),
        **_dense_cells(e), "path": e.diag.path, "kind": kinds.get((e.i, e.j), "window"),
        "cov_scale": scale.get((e.i, e.j), 1.0), "mixed_moments": int(e.diag.mixed_moments),
    } for e in edges]


def _nees(frames: Sequence, good: list[Edge]) -> dict:
    """NEES/6 (median and mean) and 2-sigma coverage of the written covariances against the
    ground truth, over the edges whose two frames have a finite one (nothing without)."""
    gt = frames.groundtruth(partial=True)
    if gt is None:
        return {}
    pos = {int(f): p for p, f in enumerate(frames.ids())}
    fine = [e for e in good if e.i in pos and e.j in pos and np.isfinite(gt[pos[e.i]]).all()
            and np.isfinite(gt[pos[e.j]]).all()]
    if not fine:
        return {}
    d2 = mahalanobis2(groundtruth_residuals(fine, gt, frames.ids()), np.array([e.cov for e in fine]))
    st = nees_stats(d2)
    return {"nees_median_over_dof": float(np.median(d2)) / 6, "nees_over_dof": st["nees_over_dof"],
            "coverage_2sigma": st["coverage_2sigma"]}


def _dense_cells(e: EdgeEstimate) -> dict:
    """``dense_fitness`` and ``dense_shift_m`` (0 when the dense result was rejected); no
    cells when the dense step did not run (failed edge or step disabled)."""
    d = e.diag.dense
    if d is None:
        return {}
    return {"dense_fitness": float(d.fitness), "dense_shift_m": float(d.shift_m) if d.accepted else 0.0}


def build_report(seq: Sequence, run: TeacherRun, cfg: TeacherConfig) -> dict:
    """``report.json`` content (keys documented in docs/formats.md)."""
    n = len(seq)
    status = Counter(e.status for e in run.edges)
    gap1 = [e for e, g in zip(run.edges, _gaps(seq, run.edges)) if g == 1]
    gap1_failed = [e for e in gap1 if not e.ok]
    rep: dict = {
        "sequence": seq.name,
        "frames": n,
        "edges": int(status.get("ok", 0)),
        "failed_edges": int(sum(v for s, v in status.items() if s != "ok")),
        "failed_gap1_edges": len(gap1_failed),
        "failures_by_reason": {s: int(v) for s, v in status.items() if s != "ok"},
        **_by_kind(run),
        "dense_rejected_edges": sum(1 for e in run.edges if e.diag.dense is not None and not e.diag.dense.accepted),
        "stale_stream_edges": sum(1 for e in run.edges if e.diag.dense is not None and e.diag.dense.stale_stream),
        "bridges": run.bridges,
        "constant_velocity_bridges": sum(1 for b in run.bridges if b["method"] == "constant velocity"),
        "edge_paths": dict(sorted(Counter(e.diag.path for e in run.edges).items())),
        "gap1_edge_paths": dict(sorted(Counter(e.diag.path for e in gap1).items())),
        "dense_method": dense_method_for(seq.sensor, cfg) if cfg.dense else "none",
        "fps": n / run.seconds if run.seconds > 0 else float("nan"),
        "seconds": run.seconds,
        "frames_skipped": run.skipped,
    }
    frames = run.frames or seq
    gt = frames.groundtruth(partial=True)
    if gt is not None:
        rep["groundtruth_dropped"] = frames.groundtruth_dropped()
        rep.update(_evaluation(seq, frames, run, gt))
    return rep


def _by_kind(run: TeacherRun) -> dict[str, dict[str, int]]:
    """``edges_by_kind`` and ``failed_edges_by_kind``: counts per edges.csv ``kind``."""
    return {"edges_by_kind": count_by_kind(run.edges, run.kinds, True),
            "failed_edges_by_kind": count_by_kind(run.edges, run.kinds, False)}


def _evaluation(seq: Sequence, frames: Sequence, run: TeacherRun, gt: NDArray[np.float64]) -> dict:
    """The report's figures against ground truth, over the frames that have a pose and a
    finite ground-truth pose (RPE pairs consecutive ones of those; label errors by the gap
    in frames of the sequence); none with fewer than 2 such frames."""
    has = np.isfinite(gt).all(axis=(1, 2))
    if has.sum() < 2:
        return {}
    times = frames.times()[has]
    out = trajectory_report(Trajectory(times, gt[has]), Trajectory(times, run.poses[has]))
    ok = set(frames.ids()[has].tolist())
    full = np.full((len(seq), 4, 4), np.nan)
    full[np.searchsorted(seq.ids(), frames.ids()[has])] = gt[has]
    good = [e for e in run.edges if e.ok and e.i in ok and e.j in ok]
    by_kind: dict[str, list] = {}
    for e in good:
        by_kind.setdefault(run.kinds.get((e.i, e.j), "window"), []).append((e.i, e.j, e.T_i_j))
    out["label_error_by_gap"] = label_errors_by_gap(by_kind.pop("window", []), full, seq.ids())
    out["label_error_by_kind"] = {k: _pooled(label_errors_by_gap(v, full, seq.ids())) for k, v in sorted(by_kind.items())}
    return out


def _pooled(by_gap: dict[str, dict[str, float]]) -> dict[str, float]:
    """One ``{edges, trans_rmse_m, rot_rmse_deg}`` over every gap of ``by_gap``."""
    n = np.array([v["edges"] for v in by_gap.values()])
    t, r = (np.array([v[k] for v in by_gap.values()]) for k in ("trans_rmse_m", "rot_rmse_deg"))
    return {"edges": int(n.sum()), "trans_rmse_m": float(np.sqrt(np.sum(n * t ** 2) / n.sum())),
            "rot_rmse_deg": float(np.sqrt(np.sum(n * r ** 2) / n.sum()))}


def _gaps(seq: Sequence, edges: list[EdgeEstimate]) -> list[int]:
    """Each edge's gap in positions of ``seq`` (frames apart in the sequence read, not in ids),
    for all edges at once: the frame ids read once and searched twice."""
    ids = seq.ids()
    return (np.searchsorted(ids, [e.j for e in edges]) - np.searchsorted(ids, [e.i for e in edges])).tolist()


def cov_scales(seq: Sequence, edges: list[EdgeEstimate], kinds: dict[tuple[int, int], str],
               covariance: str = "calibrated") -> dict[tuple[int, int], float]:
    """Each edge's covariance factor in edges.g2o (edges.csv's ``cov_scale``:
    :func:`teacher.covariance_model.gap_scale`; ``kinds`` as ``TeacherRun.kinds``), by (i, j)."""
    return {(e.i, e.j): gap_scale(seq.sensor.noise_model, g, covariance, kinds.get((e.i, e.j), "window"),
                                  e.diag.mixed_moments) for e, g in zip(edges, _gaps(seq, edges))}


def write_outputs(seq: Sequence, run: TeacherRun, cfg: TeacherConfig, out: Path, extra: dict,
                  fingerprint: Fingerprint | None = None) -> dict:
    """Write every output file atomically; then ``fingerprint.json``, and ``report.json``
    last (it marks completion)."""
    ensure_dir(out)
    frames = run.frames or seq  # a skipped frame has no pose (teacher.skips)
    ids, times = frames.ids(), frames.times()
    ts = {int(f): float(t) for f, t in zip(ids, times)}
    scale = cov_scales(seq, run.edges, run.kinds, cfg.covariance)
    good = [Edge(e.i, e.j, e.T_i_j, e.cov * scale[e.i, e.j]) for e in run.edges if e.ok]
    write_g2o(out / "edges.g2o", good, {int(f): T for f, T in zip(ids, run.poses)})
    write_edges_csv(out / "edges.csv", _edge_rows(run.edges, ts, run.kinds, scale))
    if run.observations is not None:
        write_observations(out / "observations.csv", run.observations)
    write_tum(out / "trajectory.tum", Trajectory(times, run.poses))
    gt = frames.groundtruth(partial=True)
    if gt is not None and (has := np.isfinite(gt).all(axis=(1, 2))).any():
        write_tum(out / "groundtruth.tum", Trajectory(times[has], gt[has]))  # without the dropped frames
    write_json(out / "config.json", {"teacher": cfg.to_dict(), "git_revision": git_revision(), **extra})
    report = build_report(seq, run, cfg)
    report["covariance"] = {**describe(seq.sensor.noise_model, cfg.covariance), **_nees(frames, good)}
    if fingerprint is not None:
        write_fingerprint(out, fingerprint)
    write_json(out / "report.json", json_safe(report))
    return report


def fingerprint(spec: str, seq: Sequence, cfg: TeacherConfig) -> Fingerprint:
    """The inputs of a sequence's teacher outputs: scene, sequence, frames, the config (the
    number of worker processes only through the chunk bounds, which are what shapes the
    edges)."""
    conf = cfg.to_dict()
    conf.pop("workers")
    inputs = {"scene": scene_id(spec), "sequence": seq.name, "frames": frames_id(seq.ids()), "teacher": conf,
              "chunks": [list(b) for b in _chunks(len(seq), cfg)]}
    if seq.undistortion is not None:  # the frames are the undistorted ones
        inputs["undistortion"] = list(seq.undistortion.coeffs)
    return Fingerprint("teacher", inputs)


def generate(spec: str, out: Path | None = None, split: str = "all", frames: str | None = None,
             config: TeacherConfig = TeacherConfig(), overwrite: bool = False, progress: bool = True,
             strict: bool = False, camera: Path | None = None) -> list[Path]:
    """Run the teacher on every sequence of ``spec``; returns one output folder per sequence.
    ``camera``: a camera file (``ctcvo teacher calibrate``) whose distortion undistorts the frames.

    A sequence whose folder holds the outputs of the same inputs (``fingerprint.json``,
    :mod:`data.runs`) is skipped; outputs of other inputs are replaced with ``overwrite``,
    otherwise they are an error that says what differs.
    """
    if config.workers > 1:
        processes.start()  # the workers import while the scene opens (or renders)
    base = Path(out) if out is not None else stage_dir(spec, "teacher")
    with output_folder(base):
        seqs = open_scene(spec, split=split, frames=frames)
        if camera is not None:
            seqs = [with_camera(seq, camera) for seq in seqs]
        dirs = []
        for seq in seqs:
            d = base if len(seqs) == 1 else base / seq.name
            dirs.append(d)
            fp = fingerprint(spec, seq, config)
            finished = (d / "report.json").is_file()
            if claim(d, fp, done=finished, has_outputs=finished, overwrite=overwrite, outputs=OUTPUT_FILES):
                log.info("%s: teacher output of the same inputs in %s: kept", seq.name, d)
                continue
            if len(seq) < 2:
                raise ConfigError(f"{seq.name}: need at least 2 frames, got {len(seq)}")
            skips.check_groundtruth(seq, strict)
            run = run_sequence(seq, config, progress, strict)
            extra = {"scene": spec, "split": split, "frames": frames}
            if seq.undistortion is not None:
                extra["undistortion"] = list(seq.undistortion.coeffs)
            rep = write_outputs(seq, run, config, d, extra, fp)
            log.info("%s", summary_line(seq.name, rep))
    return dirs


def summary_line(name: str, rep: dict) -> str:
    skipped = f" ({len(rep['frames_skipped'])} skipped)" if rep.get("frames_skipped") else ""
    s = (f"{name}: {rep['frames']} frames{skipped}, {rep['edges']} edges ({rep['failed_edges']} failed, "
         f"{rep['failed_gap1_edges']} at gap 1), {rep['fps']:.1f} fps")
    if "rpe_trans_rmse_m" in rep:
        s += (f"; gap-1 RPE {1000 * rep['rpe_trans_rmse_m']:.2f} mm / {rep['rpe_rot_rmse_deg']:.3f} deg, "
              f"ATE {1000 * rep['ate_rmse_m']:.1f} mm, se3 L2 {rep['se3_l2_mean']:.5f}")
    return s
