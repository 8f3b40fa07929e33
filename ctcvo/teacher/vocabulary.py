"""A DBoW2 ORB vocabulary built from training frames, for ORB-SLAM3 (:mod:`teacher.orbslam3`).

The tree is built as DBoW2 builds its own: hierarchical k-medians on Hamming distance
(k-means++ seeding, per-bit majority centroids) to ``levels`` levels, a node with at most
one distinct descriptor becoming a leaf; each leaf (word) is weighted by its IDF,
``ln(N_images / images containing the word)``. Files are DBoW2's text format, as ORB-SLAM's
``TemplatedVocabulary::loadFromTextFile`` reads it: a header ``k L scoring weighting``, then
one line per node in id order 1..N (the root, 0, is implicit): ``parent isLeaf d0 .. d31
weight``, with no trailing newline (the reader would add a bogus node).
"""

from __future__ import annotations

import logging
import os
import warnings
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
from numpy.typing import NDArray

from ctcvo.data.errors import ConfigError, DataError, FormatError
from ctcvo.data.sequence import Sequence

log = logging.getLogger(__name__)

#: bytes of an ORB descriptor
DESCRIPTOR_BYTES = 32
#: DBoW2's limits on the branching factor and depth (``loadFromTextFile`` refuses more)
MAX_K, MAX_LEVELS = 20, 10
#: most Lloyd iterations of one k-medians step (DBoW2 has no cap); a step that has not
#: converged by then takes its last centroids' nearest assignment, so descent still agrees
MAX_ITERATIONS = 50
_FIELDS = 2 + DESCRIPTOR_BYTES + 1  # parent, leaf flag, descriptor bytes, weight


@dataclass(frozen=True)
class Vocabulary:
    """A DBoW2 vocabulary tree; node 0 is the root.

    ``parents`` (N,) int64 (-1 for the root), ``is_leaf`` (N,) bool, ``descriptors`` (N, 32)
    uint8 (zeros for the root), ``weights`` (N,) float64 (IDF on leaves, 0 on inner nodes).
    ``scoring`` and ``weighting`` are DBoW2's codes (0 0: L1 norm, TF-IDF).
    """

    k: int
    levels: int
    parents: NDArray[np.int64]
    is_leaf: NDArray[np.bool_]
    descriptors: NDArray[np.uint8]
    weights: NDArray[np.float64]
    scoring: int = 0
    weighting: int = 0

    def __len__(self) -> int:
        """Number of nodes, the root included."""
        return len(self.parents)

    @property
    def words(self) -> int:
        return int(self.is_leaf.sum())

    def child_table(self) -> NDArray[np.int64]:
        """(N, k) child node ids of each node in id order (DBoW2's order of descent), -1 padded."""
        order = np.argsort(self.parents[1:], kind="stable") + 1
        par = self.parents[order]
        rank = np.arange(len(order)) - np.searchsorted(par, par)
        table = np.full((len(self), self.k), -1, dtype=np.int64)
        table[par, rank] = order
        return table

    def word_of(self, descriptors: NDArray[np.uint8]) -> NDArray[np.int64]:
        """Leaf node id each descriptor (n, 32) reaches by greedy descent from the root (at each
        node the child at the least Hamming distance, the first on a tie, as DBoW2's ``transform``)."""
        d = _pack(np.asarray(descriptors, dtype=np.uint8).reshape(-1, DESCRIPTOR_BYTES))
        table = self.child_table()
        packed = _pack(self.descriptors)
        node = np.zeros(len(d), dtype=np.int64)
        active = np.flatnonzero(~self.is_leaf[node])
        while len(active):
            kids = table[node[active]]  # (m, k)
            dist = np.zeros(kids.shape, dtype=np.int64)
            for w in range(d.shape[1]):
                dist += np.bitwise_count(d[active, w, None] ^ packed[kids, w])
            dist[kids < 0] = np.iinfo(np.int64).max
            node[active] = kids[np.arange(len(active)), np.argmin(dist, axis=1)]
            active = active[~self.is_leaf[node[active]]]
        return node


def _pack(d: NDArray[np.uint8]) -> NDArray[np.uint64]:
    """(n, 32) uint8 descriptors as (n, 4) uint64 words."""
    return np.ascontiguousarray(d, dtype=np.uint8).view(np.uint64).reshape(-1, DESCRIPTOR_BYTES // 8)


def _hamming(a: NDArray[np.uint64], b: NDArray[np.uint64]) -> NDArray[np.int64]:
    """Hamming distances (n, m) between packed descriptors a (n, 4) and b (m, 4)."""
    out = np.zeros((len(a), len(b)), dtype=np.int64)
    for w in range(a.shape[1]):
        out += np.bitwise_count(a[:, w, None] ^ b[None, :, w])
    return out


def _majority(bits: NDArray[np.uint8], labels: NDArray[np.int64], k: int) -> NDArray[np.uint8]:
    """Per-bit majority descriptor of each of ``k`` groups (DBoW2's rule: a bit is set where at
    least half the group has it); ``bits`` (n, 256) unpacked descriptors."""
    ones = np.stack([bits[labels == c].sum(axis=0, dtype=np.int64) for c in range(k)])
    counts = np.bincount(labels, minlength=k)
    return np.packbits((2 * ones >= counts[:, None]) & (counts[:, None] > 0), axis=1)


def _seed(packed: NDArray[np.uint64], k: int, rng: np.random.Generator) -> NDArray[np.int64]:
    """k-means++ seeding on Hamming distance: indices of ``k`` distinct descriptors."""
    chosen = [int(rng.integers(len(packed)))]
    dmin = _hamming(packed, packed[chosen])[:, 0].astype(np.float64)
    while len(chosen) < k:
        p = dmin ** 2
        if p.sum() == 0:
            break
        chosen.append(int(rng.choice(len(packed), p=p / p.sum())))
        dmin = np.minimum(dmin, _hamming(packed, packed[chosen[-1:]])[:, 0])
    return np.asarray(chosen)


def _kmedians(d: NDArray[np.uint8], k: int, rng: np.random.Generator) -> tuple[NDArray[np.uint8], NDArray[np.int64]]:
    """Split descriptors (n, 32) into at most ``k`` groups: (centroids (m, 32), labels (n,) in
    0..m-1); every descriptor's label is its nearest centroid (the first on a tie)."""
    uniq = np.unique(d, axis=0)
    if len(uniq) <= k:  # each distinct descriptor its own cluster
        centres = uniq
    else:
        packed = _pack(d)
        bits = np.unpackbits(d, axis=1)
        centres = d[_seed(packed, k, rng)]
        labels = None
        for _ in range(MAX_ITERATIONS):
            new = np.argmin(_hamming(packed, _pack(centres)), axis=1)
            if labels is not None and np.array_equal(new, labels):
                break
            labels = new
            centres = _majority(bits, labels, len(centres))
    labels = np.argmin(_hamming(_pack(d), _pack(centres)), axis=1)
    used = np.unique(labels)  # an emptied cluster is dropped
    remap = np.full(len(centres), -1, dtype=np.int64)
    remap[used] = np.arange(len(used))
    return centres[used], remap[labels]


def build_vocabulary(descriptors_per_image: list[NDArray[np.uint8]], k: int = 10, levels: int = 5,
                     seed: int = 0) -> Vocabulary:
    """A vocabulary from ORB descriptors ((n_i, 32) uint8 per training image) with branching
    ``k`` and depth ``levels``; IDF leaf weights over the images."""
    if not (2 <= k <= MAX_K and 1 <= levels <= MAX_LEVELS):
        raise ConfigError(f"vocabulary needs 2 <= k <= {MAX_K} and 1 <= levels <= {MAX_LEVELS}, got k {k}, levels {levels}")
    per_image = [np.asarray(d, dtype=np.uint8).reshape(-1, DESCRIPTOR_BYTES) for d in descriptors_per_image]
    pool = np.concatenate(per_image) if per_image else np.zeros((0, DESCRIPTOR_BYTES), np.uint8)
    if len(pool) < 2:
        raise ConfigError(f"vocabulary needs at least 2 descriptors, got {len(pool)}")
    rng = np.random.default_rng(seed)
    parents, descs, leaf = [-1], [np.zeros(DESCRIPTOR_BYTES, np.uint8)], [False]
    stack = [(0, np.arange(len(pool)), 0)]  # (node, its descriptors, its level): depth first, as DBoW2
    while stack:
        node, members, level = stack.pop()
        centres, labels = _kmedians(pool[members], k, rng)
        first = len(parents)
        for c in range(len(centres)):
            sub = members[labels == c]
            parents.append(node)
            descs.append(centres[c])
            leaf.append(level + 1 >= levels or len(np.unique(pool[sub], axis=0)) <= 1)
        stack.extend((first + c, members[labels == c], level + 1) for c in reversed(range(len(centres)))
                     if not leaf[first + c])
    vocab = Vocabulary(k, levels, np.asarray(parents, np.int64), np.asarray(leaf), np.stack(descs),
                       np.zeros(len(parents)))
    vocab.weights[:] = idf_weights(vocab, per_image)
    log.info("vocabulary: %d descriptors of %d images -> %d nodes, %d words", len(pool), len(per_image),
             len(vocab), vocab.words)
    return vocab


def idf_weights(vocab: Vocabulary, descriptors_per_image: list[NDArray[np.uint8]]) -> NDArray[np.float64]:
    """Node weights: ``ln(N_images / images containing the word)`` on leaves (0 for a word no
    image contains, as DBoW2), 0 on inner nodes."""
    sizes = [len(d) for d in descriptors_per_image]
    words = vocab.word_of(np.concatenate(descriptors_per_image)) if sum(sizes) else np.zeros(0, np.int64)
    image = np.repeat(np.arange(len(sizes)), sizes)
    pairs = np.unique(image * len(vocab) + words)  # each (image, word) once
    seen = np.bincount(pairs % len(vocab), minlength=len(vocab))
    w = np.zeros(len(vocab))
    hit = vocab.is_leaf & (seen > 0)
    w[hit] = np.log(len(descriptors_per_image) / seen[hit])
    return w


def write_vocabulary(vocab: Vocabulary, path: Path) -> None:
    """Write ``vocab`` in DBoW2's text format, atomically (a temporary file, then a rename)."""
    path = Path(path)
    lines = [f"{vocab.k} {vocab.levels} {vocab.scoring} {vocab.weighting}"]
    for n in range(1, len(vocab)):
        w = repr(float(vocab.weights[n])) if vocab.is_leaf[n] else "0"
        lines.append(f"{vocab.parents[n]} {int(vocab.is_leaf[n])} " + " ".join(map(str, vocab.descriptors[n])) + f" {w}")
    tmp = path.with_name(f".{path.name}.tmp{os.getpid()}")
    try:
        tmp.write_text("\n".join(lines))  # no trailing newline: DBoW2 would read one as a node
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)


def read_vocabulary(path: Path) -> Vocabulary:
    """Read and validate a DBoW2 text vocabulary; :class:`FormatError` naming the file and line
    when it is missing or malformed (what would make ORB-SLAM3 crash or build a wrong tree)."""
    path = Path(path)
    try:
        text = path.read_text()
    except (OSError, UnicodeDecodeError) as exc:
        raise FormatError(f"cannot read ORB vocabulary {path}: {exc}") from None
    lines = text.split("\n")
    head = lines[0].split()
    try:
        k, levels, scoring, weighting = (int(t) for t in head) if len(head) == 4 else (None,) * 4
    except ValueError:
        k = None
    if k is None:
        raise FormatError(f"{path}:1: a DBoW2 vocabulary starts with 'k L scoring weighting', got {lines[0][:60]!r}")
    if not (1 <= k <= MAX_K and 1 <= levels <= MAX_LEVELS and 0 <= scoring <= 5 and 0 <= weighting <= 3):
        raise FormatError(f"{path}:1: k {k} must be 1..{MAX_K}, L {levels} 1..{MAX_LEVELS}, scoring 0..5, weighting 0..3")
    if len(lines) < 2:
        raise FormatError(f"{path}: no nodes after the header")
    weights_text = []
    for lineno, line in enumerate(lines[1:], 2):
        toks = line.split()
        if len(toks) != _FIELDS:
            why = " (an empty last line: DBoW2 reads a trailing newline as a bogus node)" if not toks else ""
            raise FormatError(f"{path}:{lineno}: a node needs {_FIELDS} fields 'parent isLeaf d0..d31 weight', "
                              f"got {len(toks)}{why}")
        if not "".join(toks[:-1]).isdigit():
            raise FormatError(f"{path}:{lineno}: parent, leaf flag and descriptor bytes must be integers >= 0")
        weights_text.append(toks[-1])
    try:
        weights = np.array([float(t) for t in weights_text])
    except ValueError:
        bad = next(n for n, t in enumerate(weights_text) if not _is_float(t))
        raise FormatError(f"{path}:{bad + 2}: the weight must be a number, got {weights_text[bad]!r}") from None
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)  # numpy's note on a token it cannot read
        ints = np.fromstring(" ".join(line.rsplit(None, 1)[0] for line in lines[1:]), dtype=np.int64, sep=" ")
    ints = ints.reshape(len(lines) - 1, _FIELDS - 1)
    ids = np.arange(1, len(lines))
    checks = [
        (ints[:, 0] >= ids, "parent id must be a node before this one"),
        ((ints[:, 1] != 0) & (ints[:, 1] != 1), "leaf flag must be 0 or 1"),
        (((ints[:, 2:] < 0) | (ints[:, 2:] > 255)).any(axis=1), "descriptor bytes must be 0..255"),
        (~np.isfinite(weights) | (weights < 0), "weight must be a finite number >= 0"),
    ]
    is_leaf = np.concatenate([[False], ints[:, 1] == 1])
    parents = np.concatenate([[-1], ints[:, 0]])
    checks.append((is_leaf[np.clip(parents[1:], 0, len(parents) - 1)], "parent is a leaf"))
    for bad, why in checks:
        if bad.any():
            raise FormatError(f"{path}:{int(np.argmax(bad)) + 2}: {why}")
    descriptors = np.concatenate([np.zeros((1, DESCRIPTOR_BYTES), np.uint8), ints[:, 2:].astype(np.uint8)])
    return Vocabulary(k, levels, parents, is_leaf, descriptors, np.concatenate([[0.0], weights]), scoring, weighting)


def _is_float(t: str) -> bool:
    try:
        float(t)
    except ValueError:
        return False
    return True


def descriptors_of(seq: Sequence, frames: Iterable[int] | None = None, n_features: int = 1000,
                   strict: bool = True) -> list[NDArray[np.uint8]]:
    """ORB descriptors ((n, 32) uint8, ``cv2.ORB_create(n_features)``) of the given frame
    positions of ``seq`` (all by default), one array per frame; without ``strict`` a frame
    that cannot be read is left out with a warning instead of raising its :class:`DataError`."""
    orb = cv2.ORB_create(n_features)
    out = []
    for k in range(len(seq)) if frames is None else frames:
        try:
            rgb = seq.rgb(k)
        except DataError as exc:
            if strict:
                raise
            log.warning("%s: frame %d left out of the vocabulary (--strict stops instead): %s",
                        seq.name, int(seq.ids()[k]), exc)
            continue
        grey = cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY)
        _, d = orb.detectAndCompute(grey, None)
        out.append(np.zeros((0, DESCRIPTOR_BYTES), np.uint8) if d is None else d)
    return out
