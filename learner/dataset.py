"""Training data of the learner: cached small frames and per-pair labels.

Frames are decoded and resized once per sequence and cached as an uint8 ``.npy`` file
(``frames-<sequence>-<W>x<H>-<hash>.npy``, (N, 3, H, W)) in the run folder, so training
epochs never touch the image decoder.

Labels live in dense arrays indexed by gap and start position: ``labels[g, k]`` is the
twist ``xi = (v, w)`` of the pair (k, k + g) (positions in the sequence view), valid where
``mask[g, k]``. Teacher labels come from the teacher's ``edges.g2o`` (only good edges are in
it, so failed or missing edges stay masked), with their covariance for the ``*-aug``
variants; ground-truth labels come from the sequence's poses (``*-gt`` variants only).
"""

from __future__ import annotations

import hashlib
import json
import logging
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import Optional

import cv2
import numpy as np
import torch
from numpy.typing import NDArray
from torch import Tensor

from data import geometry as geo
from data.errors import DataError, VOError
from data.formats import read_g2o
from data.io import atomic_write
from data.scenes import scene_slug
from data.sequence import Sequence

log = logging.getLogger(__name__)


@dataclass
class SequenceData:
    """One sequence ready for training or prediction.

    ``frames`` (N, 3, H, W) uint8; ``labels`` (G+1, N, 6) float32 with ``mask`` (G+1, N)
    bool (row 0 unused); ``chol`` (G+1, N, 6, 6) Cholesky factors of the label covariances
    (teacher labels only, else ``None``); ``gt`` (N, 4, 4) ``T_world_cam`` or ``None``.
    """

    name: str
    ids: NDArray[np.int64]
    times: NDArray[np.float64]
    frames: Tensor
    labels: Tensor
    mask: Tensor
    chol: Optional[Tensor]
    gt: Optional[NDArray[np.float64]]

    def __len__(self) -> int:
        return len(self.ids)

    def pairs(self, i: Tensor, j: Tensor) -> Tensor:
        """Stacked frame pairs (n, 6, H, W) uint8 of positions ``i`` and ``j`` (n,)."""
        return torch.cat([self.frames[i], self.frames[j]], dim=1)


# ----------------------------------------------------------------------------------
# frames
# ----------------------------------------------------------------------------------
def _resize(img: NDArray[np.uint8], width: int, height: int) -> NDArray[np.uint8]:
    return cv2.resize(img, (width, height), interpolation=cv2.INTER_AREA)


def load_frames(seq: Sequence, width: int, height: int, cache_dir: Path) -> Tensor:
    """(N, 3, H, W) uint8 frames of ``seq`` resized to ``width x height``, cached as .npy."""
    ids = seq.ids()
    key = hashlib.sha1(np.ascontiguousarray(ids).tobytes() + str(getattr(seq, "root", seq.name)).encode()).hexdigest()[:10]
    path = Path(cache_dir) / f"frames-{seq.name}-{width}x{height}-{key}.npy"
    if path.is_file():
        try:
            arr = np.load(path)
            if arr.shape == (len(ids), 3, height, width) and arr.dtype == np.uint8:
                return torch.from_numpy(arr)
        except (OSError, ValueError):
            pass
        log.warning("ignoring unreadable frame cache %s", path)
    log.info("decoding %d frames of %s to %dx%d", len(ids), seq.name, width, height)
    with ThreadPoolExecutor(max_workers=4) as pool:
        imgs = list(pool.map(lambda k: _resize(seq.rgb(k), width, height), range(len(seq))))
    arr = np.ascontiguousarray(np.stack(imgs).transpose(0, 3, 1, 2))
    with atomic_write(path, "wb") as fh:
        np.save(fh, arr)
    return torch.from_numpy(arr)


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


def default_teacher_dir(spec: str, seq: Sequence, n_sequences: int, root: Optional[Path] = None) -> Path:
    """Where ``teacher generate`` writes a sequence by default (docs/formats.md)."""
    base = Path(root) if root is not None else Path("runs") / scene_slug(spec) / "teacher"
    return base / seq.name if n_sequences > 1 else base


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


def find_teacher_edges(spec: str, seqs: list[Sequence], split: str, frames: Optional[str],
                       teacher_root: Optional[Path]) -> list[Path]:
    """The teacher ``edges.g2o`` of every sequence; runs the teacher if they are missing.

    With an explicit ``teacher_root`` nothing is generated: missing labels are an error.
    """
    paths = [default_teacher_dir(spec, s, len(seqs), teacher_root) / "edges.g2o" for s in seqs]
    missing = [p for p in paths if not p.is_file()]
    if not missing:
        for seq, g2o in zip(seqs, paths):
            check_teacher_sequence(g2o, seq.name)
        return paths
    if teacher_root is not None:
        raise DataError(f"scene {spec} has no teacher labels: {missing[0]} is missing (run `teacher generate` first)")
    try:
        from teacher.generate import generate
    except ImportError as exc:
        raise DataError(f"scene {spec} has no teacher labels ({missing[0]} is missing) and the teacher "
                        f"cannot be run: {exc}") from None
    log.info("no teacher labels for %s: running the teacher", spec)
    generate(spec, split=split, frames=frames)
    missing = [p for p in paths if not p.is_file()]
    if missing:
        raise DataError(f"the teacher ran but wrote no {missing[0]}")
    return paths


def load_sequences(spec: str, seqs: list[Sequence], *, width: int, height: int, max_gap: int, label_source: str,
                   cache_dir: Path, split: str = "all", frames: Optional[str] = None,
                   teacher_root: Optional[Path] = None) -> list[SequenceData]:
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
        out.append(SequenceData(seq.name, seq.ids(), seq.times(), load_frames(seq, width, height, cache_dir),
                                labels, mask, chol, gt))
    return out


def check_labels(data: list[SequenceData]) -> None:
    if not any(bool(d.mask[1:].any()) for d in data):
        raise VOError("no usable labels in the training sequences")
