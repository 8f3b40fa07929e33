"""Resolve a ``--scene`` argument to sequences, the same way in every CLI.

``--scene`` accepts:
* ``synthetic/NAME`` - a built-in synthetic scene, rendered on first use and cached
  (see :mod:`data.synthetic`); ``synthetic/corpus-<COUNT>[x<FRAMES>]`` is the rooms
  ``room-0 .. room-<COUNT-1>`` of the training corpus, one sequence each;
* a 7-Scenes sequence folder (``.../seq-XX``) or any folder in that layout;
* a 7-Scenes scene folder (``.../redkitchen``) together with ``split`` (train/test/all);
* a TUM RGB-D sequence folder (``rgb.txt``, ``depth.txt``).

``frames`` (``START:STOP[:STEP]``) selects part of every sequence.
"""

from __future__ import annotations

from pathlib import Path
from typing import Optional

from data.errors import DataError
from data.runs import SYNTHETIC_PREFIX
from data.sequence import Sequence, parse_frame_range


def open_scene(spec: str, split: str = "all", frames: Optional[str] = None,
               cache_dir: Optional[Path] = None) -> list[Sequence]:
    """Open the sequences named by ``spec`` (see module docstring)."""
    start, stop, step = parse_frame_range(frames)
    seqs = _open(spec, split, cache_dir)
    if frames:
        seqs = [s.select(start, stop, step) for s in seqs]
    return seqs


def _open(spec: str, split: str, cache_dir: Optional[Path]) -> list[Sequence]:
    from data import sevenscenes

    if spec.startswith(SYNTHETIC_PREFIX):
        from data import synthetic

        return synthetic.synthetic_sequences(spec[len(SYNTHETIC_PREFIX):], cache_dir=cache_dir)
    path = Path(spec)
    if not path.exists():
        raise DataError(f"scene {spec!r} not found (give a sequence or scene folder, or synthetic/NAME)")
    if not path.is_dir():
        raise DataError(f"scene {spec!r} is not a folder")
    if (path / "rgb.txt").is_file() and (path / "depth.txt").is_file():
        from data import tum

        if split != "all":
            raise DataError(f"--split applies to a 7-Scenes scene folder; {spec} is a single TUM sequence")
        return [tum.TumSequence(path)]
    if sevenscenes.is_sequence_folder(path):
        if split != "all":
            raise DataError(f"--split applies to a scene folder; {spec} is a single sequence")
        return [sevenscenes.SevenScenesSequence(path)]
    if any(path.glob("seq-*")) or (path / "TrainSplit.txt").is_file():
        return sevenscenes.open_scene_folder(path, split)
    raise DataError(f"{spec} is neither a 7-Scenes sequence/scene folder nor a TUM sequence (no rgb.txt/depth.txt)")
