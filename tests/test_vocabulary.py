"""The DBoW2 vocabulary builder: known answers on hand-made descriptors, agreement with a
plain greedy descent on ORB descriptors of textured images, the file format and its reader."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from ctcvo.data.errors import FormatError
from ctcvo.teacher import vocabulary as V


def _desc(byte: int, flip: int | None = None) -> np.ndarray:
    """A descriptor of 32 equal bytes, with bit ``flip`` (0..255) inverted."""
    d = np.full(32, byte, dtype=np.uint8)
    if flip is not None:
        d[flip // 8] ^= np.uint8(1 << (flip % 8))
    return d


def _hand_images() -> tuple[list[np.ndarray], dict[str, np.ndarray]]:
    """Three images over three well-separated clusters (0x00, 0xFF, 0x0F bytes), each cluster
    with two distinct descriptors: with k 3 the root splits into the clusters and each
    distinct descriptor becomes its own leaf."""
    d = {"a0": _desc(0x00), "a1": _desc(0x00, 3), "b0": _desc(0xFF), "b1": _desc(0xFF, 100),
         "c0": _desc(0x0F), "c1": _desc(0x0F, 200)}
    images = [np.stack([d["a0"], d["a1"], d["b0"]]), np.stack([d["a0"], d["b1"], d["c0"]]),
              np.stack([d["a0"], d["c0"], d["c1"], d["c1"]])]
    return images, d


def test_hand_made_tree_and_idf():
    images, d = _hand_images()
    vocab = V.build_vocabulary(images, k=3, levels=2, seed=0)
    assert len(vocab) == 1 + 3 + 6 and vocab.words == 6
    assert np.array_equal(vocab.parents[1:4], [0, 0, 0]) and not vocab.is_leaf[1:4].any()
    # IDF = ln(3 images / images containing the word)
    expected = {"a0": 0.0, "a1": math.log(3), "b0": math.log(3), "b1": math.log(3), "c0": math.log(3 / 2),
                "c1": math.log(3)}
    for name, idf in expected.items():
        leaf = int(vocab.word_of(d[name][None])[0])
        assert vocab.is_leaf[leaf] and np.array_equal(vocab.descriptors[leaf], d[name])
        assert vocab.weights[leaf] == pytest.approx(idf, abs=1e-12)
    assert np.all(vocab.weights[~vocab.is_leaf] == 0)


def test_majority_centroid_sets_a_bit_held_by_half():
    bits = np.unpackbits(np.stack([_desc(0x00), _desc(0x01), _desc(0x01), _desc(0x03)]), axis=1)
    centre = V._majority(bits, np.zeros(4, np.int64), 1)[0]
    assert centre[0] == 0x01  # bit 0: 3 of 4; bit 1: 1 of 4
    centre2 = V._majority(bits[:2], np.zeros(2, np.int64), 1)[0]
    assert centre2[0] == 0x01  # 1 of 2: a tie sets the bit, as DBoW2's meanValue


def _textured_images(n: int, seed: int = 0) -> list[np.ndarray]:
    """ORB descriptors of ``n`` random textured 320x240 images."""
    rng = np.random.default_rng(seed)
    orb = cv2.ORB_create(300)
    out = []
    for _ in range(n):
        img = cv2.GaussianBlur((rng.random((240, 320)) * 255).astype(np.uint8), (5, 5), 1.5)
        out.append(orb.detectAndCompute(img, None)[1])
    return out


def _descend(vocab: V.Vocabulary, d: np.ndarray) -> int:
    """Greedy descent with plain Python Hamming distances (the first child on a tie)."""
    kids = {n: [c for c in range(1, len(vocab)) if vocab.parents[c] == n] for n in range(len(vocab))}
    node = 0
    while not vocab.is_leaf[node]:
        dist = [sum(bin(int(x) ^ int(y)).count("1") for x, y in zip(d, vocab.descriptors[c])) for c in kids[node]]
        node = kids[node][int(np.argmin(dist))]
    return node


@pytest.fixture(scope="module")
def orb_vocab():
    images = _textured_images(4)
    return images, V.build_vocabulary(images, k=3, levels=2, seed=1)


def test_every_descriptor_reaches_the_leaf_of_a_plain_descent(orb_vocab):
    images, vocab = orb_vocab
    assert vocab.words > 3 and vocab.levels == 2
    d = np.concatenate(images)
    words = vocab.word_of(d)
    assert vocab.is_leaf[words].all()
    assert all(_descend(vocab, x) == w for x, w in zip(d[::7], words[::7]))
    seen = {w: sum(w in set(vocab.word_of(img)) for img in images) for w in np.flatnonzero(vocab.is_leaf)}
    for w, n in seen.items():
        assert vocab.weights[w] == pytest.approx(math.log(len(images) / n) if n else 0.0, abs=1e-12)


def test_file_round_trips_without_trailing_newline(orb_vocab, tmp_path):
    _, vocab = orb_vocab
    path = tmp_path / "voc.txt"
    V.write_vocabulary(vocab, path)
    text = path.read_text()
    assert not text.endswith("\n") and text.split("\n")[0] == "3 2 0 0"
    assert len(text.split("\n")) == len(vocab)  # the header and one line per node but the root
    assert all(len(line.split()) == 35 for line in text.split("\n")[1:])
    back = V.read_vocabulary(path)
    assert back.k == 3 and back.levels == 2
    assert np.array_equal(back.parents, vocab.parents) and np.array_equal(back.is_leaf, vocab.is_leaf)
    assert np.array_equal(back.descriptors, vocab.descriptors) and np.array_equal(back.weights, vocab.weights)
    assert list(tmp_path.iterdir()) == [path]  # no temporary file left


def _edited(lines: list[str], line: int, field: int | None, value: str | None) -> list[str]:
    """``lines`` with line ``line`` (1-based) replaced by ``value`` (``field`` None), its token
    ``field`` replaced (``value``) or dropped (None); a line past the end is appended."""
    out = list(lines)
    if line > len(out):
        return out + [value]
    if field is None:
        out[line - 1] = value
    else:
        toks = out[line - 1].split()
        toks[field:field + 1] = [] if value is None else [value]
        out[line - 1] = " ".join(toks)
    return out


@pytest.mark.parametrize("line, field, value, why", [
    (1, None, "3 2 0", "k L scoring weighting"),
    (1, None, "21 2 0 0", "k 21"),
    (1, None, "3 11 0 0", "L 11"),
    (99999, None, "", "trailing newline"),
    (3, 34, None, "35 fields"),
    (3, 2, "256", "0..255"),
    (3, 1, "2", "leaf flag"),
    (2, 0, "7", "parent id"),
    (3, 0, "x", "integers"),
    (3, 0, "-1", "integers"),
    (3, 34, "w", "weight must be a number"),
    (3, 34, "nan", "finite"),
])
def test_malformed_files_give_one_line_format_errors(orb_vocab, tmp_path, line, field, value, why):
    _, vocab = orb_vocab
    path = tmp_path / "voc.txt"
    V.write_vocabulary(vocab, path)
    lines = _edited(path.read_text().split("\n"), line, field, value)
    path.write_text("\n".join(lines))
    with pytest.raises(FormatError) as exc:
        V.read_vocabulary(path)
    msg = str(exc.value)
    assert "\n" not in msg and why in msg
    assert f"{path}:{min(line, len(lines))}" in msg


def test_a_leaf_parent_and_a_missing_file_are_errors(orb_vocab, tmp_path):
    _, vocab = orb_vocab
    path = tmp_path / "voc.txt"
    V.write_vocabulary(vocab, path)
    lines = path.read_text().split("\n")
    leaf = int(np.flatnonzero(vocab.is_leaf)[0])
    lines.append(f"{leaf} 1 " + " ".join(["0"] * 32) + " 0.5")
    path.write_text("\n".join(lines))
    with pytest.raises(FormatError, match=f"{path}:{len(lines)}: parent is a leaf"):
        V.read_vocabulary(path)
    with pytest.raises(FormatError, match="cannot read ORB vocabulary"):
        V.read_vocabulary(tmp_path / "absent.txt")
