"""Training data of the learner: cached small frames and per-pair labels.

Frames are decoded and resized once per sequence and cached as an uint8 ``.npy`` file
(``frames-<sequence>-<W>x<H>-<hash>.npy``, (N, 3, H, W)) in the run folder, so training
epochs never touch the image decoder. The ``rgbd`` and ``flow`` inputs
(``ModelConfig.input``) also cache quantised inverse depth (``invdepth-...``, (N, 1, H, W)
uint8, 100 / metres, 0 = no depth) and ``flow`` grey frames at twice the resolution
(``grey2x-...``, (N, 2H, 2W) uint8), from which the optical flow of each pair is computed
when the pair is drawn (:class:`Frames`). The caches are memory-mapped, not read into RAM.

Labels live in dense arrays indexed by gap and start position: ``labels[g, k]`` is the
twist ``xi = (v, w)`` of the pair (k, k + g) (positions in the sequence view), valid where
``mask[g, k]``. Teacher labels come from the teacher's ``edges.g2o`` (only good edges are in
it, so failed or missing edges stay masked), with their covariance for the ``*-aug``
variants; ground-truth labels come from the sequence's poses (``*-gt`` variants only).
"""

from __future__ import annotations

import functools
import hashlib
import json
import logging
import shlex
import sys
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np
import torch
from numpy.typing import NDArray
from torch import Tensor
from tqdm import tqdm

from ctcvo.data import geometry as geo
from ctcvo.data.errors import DataError, MissingInputError, VOError
from ctcvo.data.formats import read_g2o
from ctcvo.data.io import atomic_write
from ctcvo.data.runs import stage_dir
from ctcvo.data.sequence import Sequence, parse_frame_range
from ctcvo.learner.config import FLOW_U_CHANNEL, INPUTS

log = logging.getLogger(__name__)


#: one inverse-depth unit of the uint8 cache, 1/m (100 units = 1 m^-1; 255 = 0.39 m)
INVDEPTH_UNIT = 0.01
#: most pairs whose flow a sequence keeps in memory (float16: 48 KB a pair at 128x96, so
#: about 1 GB); training draws the same pairs again and again (gaps 1..G of each frame, both
#: directions), evaluation every epoch
FLOW_CACHE_PAIRS = 20000


def _dis() -> cv2.DISOpticalFlow:
    return cv2.DISOpticalFlow_create(cv2.DISOPTICAL_FLOW_PRESET_FAST)


@dataclass
class Frames:
    """The cached inputs of one sequence at the network's resolution and the pairs built
    from them.

    ``rgb`` (N, 3, H, W) uint8; ``invdepth`` (N, 1, H, W) uint8 in units of
    :data:`INVDEPTH_UNIT` (``rgbd``, ``flow``); ``grey2x`` (N, 2H, 2W) uint8 (``flow``).
    ``rgb`` and ``invdepth`` are tensors or (memory-mapped) arrays: a batch copies only the
    frames it needs, so a corpus larger than RAM trains from its cache files.
    """

    rgb: Tensor | NDArray[np.uint8]
    invdepth: Tensor | NDArray[np.uint8] | None = None
    grey2x: NDArray[np.uint8] | None = None
    mode: str = "rgb"
    flow_cache: dict = field(default_factory=dict, repr=False)
    """Flows computed so far, (i, j) -> (2, H, W) float16, shared by :meth:`head` and
    :meth:`to` views; at most :data:`FLOW_CACHE_PAIRS` (then it stops growing)."""

    def __post_init__(self) -> None:
        if self.mode not in INPUTS:
            raise DataError(f"unknown input {self.mode!r} (choose from {', '.join(INPUTS)})")
        if self.mode != "rgb" and self.invdepth is None:
            raise DataError(f"input {self.mode!r} needs inverse depth")
        if self.mode in FLOW_U_CHANNEL and self.grey2x is None:
            raise DataError(f"input {self.mode!r} needs the grey frames at twice the resolution")

    def __len__(self) -> int:
        return len(self.rgb)

    @property
    def device(self) -> torch.device:
        return self.rgb.device if isinstance(self.rgb, Tensor) else torch.device("cpu")

    @staticmethod
    def _take(arr: Tensor | NDArray[np.uint8], k: Tensor) -> Tensor:
        if isinstance(arr, Tensor):
            return arr[k]
        return torch.from_numpy(np.ascontiguousarray(arr[k.numpy()]))

    def head(self, n: int) -> Frames:
        """The first ``n`` frames."""
        return Frames(self.rgb[:n], None if self.invdepth is None else self.invdepth[:n],
                      None if self.grey2x is None else self.grey2x[:n], self.mode, self.flow_cache)

    def to(self, device: torch.device) -> Frames:
        """The cached tensors on ``device`` (the flow is computed on the CPU, then moved)."""
        def move(a):
            return None if a is None else torch.as_tensor(np.asarray(a) if not isinstance(a, Tensor) else a).to(device)

        return Frames(move(self.rgb), move(self.invdepth), self.grey2x, self.mode, self.flow_cache)

    def flow(self, i: NDArray[np.int64], j: NDArray[np.int64]) -> Tensor:
        """Optical flow (n, 2, H, W) float32 in pixels of the network's resolution, from frame
        ``i`` to frame ``j`` (where the content of a pixel of i lies in j), by DIS on the
        grey frames at twice the resolution, then averaged down and rounded to float16;
        kept in :attr:`flow_cache`."""
        H, W = self.rgb.shape[-2:]
        dis = None
        out = np.empty((len(i), 2, H, W), np.float32)
        for n, (a, b) in enumerate(zip(i.tolist(), j.tolist())):
            hit = self.flow_cache.get((a, b))
            if hit is not None:
                out[n] = hit
                continue
            dis = dis or _dis()
            f = dis.calc(np.asarray(self.grey2x[a]), np.asarray(self.grey2x[b]), None)
            # rounded to float16 whether cached or not: a pair gives the same input every time
            # (a resumed run, with an empty cache, trains on the same numbers)
            half = (cv2.resize(f, (W, H), interpolation=cv2.INTER_AREA).transpose(2, 0, 1) * 0.5).astype(np.float16)
            out[n] = half
            if len(self.flow_cache) < FLOW_CACHE_PAIRS:
                self.flow_cache[(a, b)] = half
        return torch.from_numpy(out)

    def pairs(self, i: Tensor, j: Tensor) -> Tensor:
        """Network inputs (n, C, H, W) of the pairs (i, j), frame ``i`` first: uint8 for
        ``rgb`` (6 channels) and ``rgbd`` (8: RGB i, RGB j, inverse depth i, j), float32 for
        ``flow`` (9: RGB i, RGB j, flow i -> j in pixels, inverse depth i) and ``flowd`` (4:
        flow i -> j, inverse depth i, j)."""
        i = torch.as_tensor(i, device=self.device)
        j = torch.as_tensor(j, device=self.device)
        if self.mode == "flowd":  # no colour: its frames are never gathered
            flow = self.flow(i.cpu().numpy(), j.cpu().numpy()).to(self.device)
            return torch.cat([flow, self._take(self.invdepth, i).float(), self._take(self.invdepth, j).float()], dim=1)
        rgb_i, rgb_j = self._take(self.rgb, i), self._take(self.rgb, j)
        if self.mode == "rgb":
            return torch.cat([rgb_i, rgb_j], dim=1)
        inv_i = self._take(self.invdepth, i)
        if self.mode == "rgbd":
            return torch.cat([rgb_i, rgb_j, inv_i, self._take(self.invdepth, j)], dim=1)
        flow = self.flow(i.cpu().numpy(), j.cpu().numpy()).to(self.device)
        return torch.cat([rgb_i.float(), rgb_j.float(), flow, inv_i.float()], dim=1)


@dataclass
class SequenceData:
    """One sequence ready for training or prediction.

    ``frames`` the cached inputs (:class:`Frames`; an (N, 3, H, W) uint8 tensor is taken as
    the ``rgb`` input); ``labels`` (G+1, N, 6) float32 with ``mask`` (G+1, N)
    bool (row 0 unused); ``chol`` (G+1, N, 6, 6) Cholesky factors of the label covariances
    (teacher labels only, else ``None``); ``gt`` (N, 4, 4) ``T_world_cam`` or ``None``.
    """

    name: str
    ids: NDArray[np.int64]
    times: NDArray[np.float64]
    frames: Frames
    labels: Tensor
    mask: Tensor
    chol: Tensor | None
    gt: NDArray[np.float64] | None

    def __post_init__(self) -> None:
        if isinstance(self.frames, Tensor):
            self.frames = Frames(self.frames)

    def __len__(self) -> int:
        return len(self.ids)

    def pairs(self, i: Tensor, j: Tensor) -> Tensor:
        """Network inputs (n, C, H, W) of the pairs of positions ``i`` and ``j`` (n,)."""
        return self.frames.pairs(i, j)


# ----------------------------------------------------------------------------------
# frames
# ----------------------------------------------------------------------------------
def _resize(img: NDArray[np.uint8], width: int, height: int) -> NDArray[np.uint8]:
    return cv2.resize(img, (width, height), interpolation=cv2.INTER_AREA)


def _cached(seq: Sequence, what: str, shape: tuple[int, ...], cache_dir: Path,
            make: Callable[[int], NDArray[np.uint8]]) -> NDArray[np.uint8]:
    """(N, *shape) uint8 per-frame arrays of ``seq``, cached as a memory-mapped .npy file."""
    ids = seq.ids()
    key = hashlib.sha1(np.ascontiguousarray(ids).tobytes() + str(getattr(seq, "root", seq.name)).encode()).hexdigest()[:10]
    size = "x".join(map(str, shape[::-1][:2]))
    path = Path(cache_dir) / f"{what}-{seq.name}-{size}-{key}.npy"
    if path.is_file():
        try:
            arr = np.load(path, mmap_mode="r")
            if arr.shape == (len(ids), *shape) and arr.dtype == np.uint8:
                log.debug("%s of %s from the cache %s", what, seq.name, path)
                return arr
        except (OSError, ValueError):
            pass
        log.warning("ignoring unreadable cache %s", path)
    log.info("caching %s of %d frames of %s (%s)", what, len(ids), seq.name, size)
    with ThreadPoolExecutor(max_workers=4) as pool:
        arr = np.stack(list(tqdm(pool.map(make, range(len(seq))), total=len(seq), desc=f"caching {what}",
                                 unit="frame", leave=False, disable=not sys.stderr.isatty())))
    with atomic_write(path, "wb") as fh:
        np.save(fh, np.ascontiguousarray(arr))
    return np.load(path, mmap_mode="r")


def rgb_input(rgb: NDArray[np.uint8], width: int, height: int) -> NDArray[np.uint8]:
    """(3, H, W) uint8: one frame's colour at the network's resolution (the ``frames`` cache)."""
    return _resize(rgb, width, height).transpose(2, 0, 1)


def grey2x_input(rgb: NDArray[np.uint8], width: int, height: int) -> NDArray[np.uint8]:
    """(2H, 2W) uint8: one frame's grey image at twice the network's resolution, from which
    the optical flow is computed (the ``grey2x`` cache)."""
    return cv2.cvtColor(_resize(rgb, 2 * width, 2 * height), cv2.COLOR_RGB2GRAY)


def invdepth_input(depth: NDArray[np.float32], width: int, height: int) -> NDArray[np.uint8]:
    """(1, H, W) uint8 inverse depth in :data:`INVDEPTH_UNIT` (0 where depth is invalid)."""
    d = cv2.resize(depth, (width, height), interpolation=cv2.INTER_NEAREST)
    with np.errstate(divide="ignore"):
        q = np.where(d > 0, np.round(1.0 / (np.maximum(d, 1e-6) * INVDEPTH_UNIT)), 0)
    return np.clip(q, 0, 255).astype(np.uint8)[None]


def load_frames(seq: Sequence, width: int, height: int, cache_dir: Path, mode: str = "rgb") -> Frames:
    """The inputs of ``seq`` for the network input ``mode`` at ``width x height``, cached as
    memory-mapped .npy files in ``cache_dir`` (only the frames' RGB is then held in RAM)."""
    if mode not in INPUTS:
        raise DataError(f"unknown input {mode!r} (choose from {', '.join(INPUTS)})")
    rgb = _cached(seq, "frames", (3, height, width), cache_dir, lambda k: rgb_input(seq.rgb(k), width, height))
    inv = grey = None
    if mode != "rgb":
        inv = _cached(seq, "invdepth", (1, height, width), cache_dir,
                      lambda k: invdepth_input(seq.depth(k), width, height))
    if mode in FLOW_U_CHANNEL:
        grey = _cached(seq, "grey2x", (2 * height, 2 * width), cache_dir,
                       lambda k: grey2x_input(seq.rgb(k), width, height))
    return Frames(rgb, inv, grey, mode)


# ----------------------------------------------------------------------------------
# labels
# ----------------------------------------------------------------------------------
def gt_labels(gt: NDArray[np.float64], max_gap: int) -> tuple[Tensor, Tensor]:
    """Ground-truth labels (G+1, N, 6) and mask (G+1, N) from poses (N, 4, 4)."""
    n = len(gt)
    labels = np.zeros((max_gap + 1, n, 6))
    mask = np.zeros((max_gap + 1, n), dtype=bool)
    for g in range(1, max_gap + 1):
        for k in range(n - g):
            labels[g, k] = geo.se3_log(geo.relative_pose(gt[k], gt[k + g]))
            mask[g, k] = True
    return torch.tensor(labels, dtype=torch.float32), torch.from_numpy(mask)


def teacher_labels(g2o: Path, ids: NDArray[np.int64], max_gap: int) -> tuple[Tensor, Tensor, Tensor]:
    """Teacher labels (G+1, N, 6), mask (G+1, N) and covariance Cholesky factors
    (G+1, N, 6, 6) of the frames ``ids`` from a teacher ``edges.g2o``."""
    edges, _ = read_g2o(g2o)
    pos = {int(f): k for k, f in enumerate(ids)}
    n = len(ids)
    labels = np.zeros((max_gap + 1, n, 6))
    mask = np.zeros((max_gap + 1, n), dtype=bool)
    chol = np.tile(np.eye(6), (max_gap + 1, n, 1, 1))
    used = 0
    for e in edges:
        if e.i not in pos or e.j not in pos:
            continue
        k, g = pos[e.i], pos[e.j] - pos[e.i]
        if not 1 <= g <= max_gap:
            continue
        labels[g, k] = geo.se3_log(e.T_i_j)
        mask[g, k] = True
        cov = 0.5 * (e.cov + e.cov.T) + 1e-12 * np.eye(6)
        chol[g, k] = np.linalg.cholesky(cov)
        used += 1
    if used == 0:
        raise DataError(f"{g2o} has no edges between the selected frames (ids {ids[0]}..{ids[-1]})")
    return (torch.tensor(labels, dtype=torch.float32), torch.from_numpy(mask),
            torch.tensor(chol, dtype=torch.float32))


def default_teacher_dir(spec: str, seq: Sequence, n_sequences: int, root: Path | None = None) -> Path:
    """Where ``teacher generate`` writes a sequence by default (docs/formats.md)."""
    base = Path(root) if root is not None else stage_dir(spec, "teacher")
    return base / seq.name if n_sequences > 1 else base


def hull_range(ranges: list[str | None]) -> str | None:
    """One frame range that holds every range of ``ranges`` (``None``: the whole sequence):
    the teacher runs once over it, and each range's labels are cut from that run."""
    parsed = [parse_frame_range(r) for r in ranges]
    if not parsed or any(r is None or r == "" for r in ranges):
        return None
    if any(step not in (None, 1) for _, _, step in parsed):
        return ranges[0] if len(set(ranges)) == 1 else None
    if any(v is not None and v < 0 for a, b, _ in parsed for v in (a, b)):
        return None
    start = min(a or 0 for a, _, _ in parsed)
    stops = [b for _, b, _ in parsed]
    return f"{start}:" if None in stops else f"{start}:{max(stops)}"


def _labelled_ids(g2o: Path) -> frozenset[int]:
    """The frame ids a teacher ``edges.g2o`` covers (its vertices; else its edges' ends)."""
    st = g2o.stat()
    return _labelled_ids_of(str(g2o.resolve()), st.st_mtime_ns, st.st_size)


@functools.lru_cache(maxsize=64)
def _labelled_ids_of(path: str, mtime_ns: int, size: int) -> frozenset[int]:  # read once per file version
    """The ids of the ``VERTEX_SE3:QUAT`` lines (the file is parsed strictly, by
    :func:`data.formats.read_g2o`, when its labels are read; this only scans it)."""
    ids = set()
    with open(path) as fh:
        for line in fh:
            if line.startswith("VERTEX_SE3:QUAT"):
                parts = line.split(maxsplit=2)
                if len(parts) > 1 and parts[1].lstrip("-").isdigit():
                    ids.add(int(parts[1]))
    if ids:
        return frozenset(ids)
    edges, _ = read_g2o(Path(path))
    return frozenset(int(k) for e in edges for k in (e.i, e.j))


def check_teacher_sequence(g2o: Path, name: str) -> None:
    """Teacher folders record their sequence in report.json: refuse another sequence's
    labels (``--teacher DIR`` of a single-sequence scene is the folder itself, so one
    folder given for several scenes would otherwise label them all)."""
    rep = g2o.parent / "report.json"
    if rep.is_file():
        try:
            seq = json.loads(rep.read_text()).get("sequence")
        except (OSError, ValueError, AttributeError):
            return
        if seq is not None and seq != name:
            raise DataError(f"teacher labels {g2o} are of sequence {seq!r}, not {name!r} (wrong --teacher?)")


def teacher_skipped(g2o: Path) -> set[int]:
    """The frame ids the teacher skipped as unreadable (report.json's ``frames_skipped``)."""
    try:
        rep = json.loads((g2o.parent / "report.json").read_text())
        return {int(f["frame"]) for f in rep.get("frames_skipped") or []}
    except (OSError, ValueError, AttributeError, TypeError, KeyError):
        return set()


def find_teacher_edges(spec: str, seqs: list[Sequence], split: str, frames: str | None,
                       teacher_root: Path | None) -> list[Path]:
    """The teacher ``edges.g2o`` of every sequence, covering each sequence's frames
    (``teacher_root``: the teacher's ``--out``; default ``runs/<scene>/teacher``). Labels
    are never made here: missing ones raise :class:`MissingInputError` naming the
    ``teacher generate`` command that makes them (callers that use several ranges of one
    scene check the :func:`hull_range` of them first, so that one command covers all)."""
    paths = [default_teacher_dir(spec, s, len(seqs), teacher_root) / "edges.g2o" for s in seqs]
    for seq, g2o in zip(seqs, paths):
        if not g2o.is_file():
            raise MissingInputError(f"no teacher labels for {spec} at {g2o.parent}: run "
                                    f"`{teacher_command(spec, split, frames, teacher_root)}` first")
        check_teacher_sequence(g2o, seq.name)
        lack = set(map(int, seq.ids())) - _labelled_ids(g2o)
        if lack and (skipped := sorted(lack & teacher_skipped(g2o))):
            raise DataError(f"the teacher skipped frame(s) {', '.join(map(str, skipped[:5]))} of {seq.name} as "
                            f"unreadable ({g2o.parent}/report.json): repair them and rerun it with --overwrite, "
                            "or train on --frames that leave them out")
        if lack:
            raise MissingInputError(
                f"no teacher labels for {len(lack)} of the {len(seq)} frames {seq.ids()[0]}..{seq.ids()[-1]} of "
                f"{seq.name} of {spec} at {g2o.parent}: run "
                f"`{teacher_command(spec, split, frames, teacher_root, overwrite=True)}` first")
    return paths


def teacher_command(spec: str, split: str, frames: str | None, teacher_root: Path | None,
                    overwrite: bool = False) -> str:
    """The ``ctcvo teacher generate`` command line that writes the labels
    :func:`find_teacher_edges` looks for."""
    args = ["ctcvo", "teacher", "generate", "--scene", spec]
    if split != "all":
        args += ["--split", split]
    if frames:
        args += ["--frames", frames]
    if teacher_root is not None:
        args += ["--out", str(teacher_root)]
    if overwrite:
        args.append("--overwrite")
    return shlex.join(args)


def load_sequences(spec: str, seqs: list[Sequence], *, width: int, height: int, max_gap: int, label_source: str,
                   cache_dir: Path, split: str = "all", frames: str | None = None,
                   teacher_root: Path | None = None, mode: str = "rgb") -> list[SequenceData]:
    """Frames and labels of the sequences of one ``--scene``.

    ``label_source`` is ``gt`` (poses), ``teacher``/``aug`` (teacher edges) or ``none``.
    """
    edges = (find_teacher_edges(spec, seqs, split, frames, teacher_root)
             if label_source in ("teacher", "aug") else [None] * len(seqs))
    out = []
    for seq, g2o in zip(seqs, edges):
        if len(seq) < 2:
            raise DataError(f"sequence {seq.name} needs at least 2 frames, has {len(seq)}")
        gt = seq.groundtruth()
        chol = None
        n = len(seq)
        if label_source == "gt":
            if gt is None:
                raise DataError(f"variant needs ground truth but sequence {seq.name} has none")
            labels, mask = gt_labels(gt, max_gap)
        elif label_source in ("teacher", "aug"):
            labels, mask, chol = teacher_labels(g2o, seq.ids(), max_gap)
        else:
            labels, mask = torch.zeros(max_gap + 1, n, 6), torch.zeros(max_gap + 1, n, dtype=torch.bool)
        log.debug("%s: %d frames (ids %d..%d), labels from %s%s: %s", seq.name, n, seq.ids()[0], seq.ids()[-1],
                  label_source, f" ({g2o})" if g2o is not None else "",
                  ", ".join(f"gap {g} {int(mask[g].sum())}" for g in range(1, max_gap + 1)))
        out.append(SequenceData(seq.name, seq.ids(), seq.times(), load_frames(seq, width, height, cache_dir, mode),
                                labels, mask, chol, gt))
    return out


def check_labels(data: list[SequenceData]) -> None:
    if not any(bool(d.mask[1:].any()) for d in data):
        raise VOError("no usable labels in the training sequences")
