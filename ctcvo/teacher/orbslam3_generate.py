"""ORB-SLAM3 as a teacher backend, and the ORB vocabulary it needs, for whole scenes.

``generate_orbslam3`` is ``teacher generate --backend orbslam3``: the same output folders,
file set and rerun rule as :func:`teacher.generate.generate` (ORB-SLAM3 is multithreaded
and not deterministic, so a finished run of the same inputs is kept, never redone).
``build_vocabulary_file`` is ``teacher vocabulary``: a DBoW2 text vocabulary from the ORB
descriptors of training frames, with a JSON sidecar that says which frames.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence as TypingSequence
from pathlib import Path

from ctcvo.data.errors import ConfigError
from ctcvo.data.io import git_revision, write_json
from ctcvo.data.runs import Fingerprint, claim, file_digest, frames_id, output_folder, scene_id, stage_dir, write_fingerprint
from ctcvo.data.scenes import open_scene
from ctcvo.teacher import skips
from ctcvo.teacher.orbslam3 import (
    DEFAULT_LABELS,
    GAP_EXPONENT,
    LABELS,
    MODES,
    SIGMA_ROT_GAP1_DEG,
    SIGMA_TRANS_GAP1_M,
    edges_from,
    run_orbslam3,
    write_outputs,
)
from ctcvo.teacher.vocabulary import build_vocabulary, descriptors_of, read_vocabulary, write_vocabulary

log = logging.getLogger(__name__)

OUTPUT_FILES = ("edges.g2o", "edges.csv", "trajectory.tum", "groundtruth.tum", "orbslam3.log", "config.json",
                "report.json")


def generate_orbslam3(spec: str, vocabulary: Path, out: Path | None = None, split: str = "all",
                      frames: str | None = None, gaps: int = 5, mode: str = "slam", labels: str = DEFAULT_LABELS,
                      settings: Path | None = None, n_features: int = 1000, overwrite: bool = False,
                      strict: bool = False) -> list[Path]:
    """Label every sequence of ``spec`` with ORB-SLAM3 RGB-D; one output folder per sequence.
    Unreadable frames and non-finite ground-truth poses as in :mod:`teacher.skips` (``strict``
    stops at the first)."""
    if gaps < 1:
        raise ConfigError(f"gaps must be >= 1, got {gaps}")
    if mode not in MODES or labels not in LABELS:
        raise ConfigError(f"mode must be one of {MODES} and labels one of {LABELS}, got {mode!r}, {labels!r}")
    vocabulary = Path(vocabulary)
    read_vocabulary(vocabulary)  # a missing or malformed vocabulary stops before any work
    base = Path(out) if out is not None else stage_dir(spec, "teacher")
    dirs = []
    with output_folder(base):
        seqs = open_scene(spec, split=split, frames=frames)
        for seq in seqs:
            d = base if len(seqs) == 1 else base / seq.name
            dirs.append(d)
            fp = Fingerprint("teacher", {
                "backend": "orbslam3", "scene": scene_id(spec), "sequence": seq.name, "frames": frames_id(seq.ids()),
                "vocabulary": file_digest(vocabulary), "mode": mode, "labels": labels, "gaps": gaps,
                "n_features": n_features, "settings": file_digest(settings) if settings is not None else None,
                "covariance": [SIGMA_TRANS_GAP1_M, SIGMA_ROT_GAP1_DEG, GAP_EXPONENT]})
            finished = (d / "report.json").is_file()
            if claim(d, fp, done=finished, has_outputs=finished, overwrite=overwrite, outputs=OUTPUT_FILES):
                log.info("%s: ORB-SLAM3 labels of the same inputs in %s: kept (runs are not deterministic)",
                         seq.name, d)
                continue
            skips.check_groundtruth(seq, strict)
            result = run_orbslam3(seq, vocabulary, mode, settings, n_features, strict)
            skips.check(seq.ids(), result.skipped, gaps)
            skips.warn(seq.name, seq.ids(), result.skipped)
            edges = edges_from(result, gaps, labels)
            write_fingerprint(d, fp)
            rep = write_outputs(d, seq, result, edges, labels, {"scene": spec, "split": split, "frames": frames})
            log.info("%s: ORB-SLAM3 %s, %d of %d frames tracked, %d of %d edges good, %.1f fps", seq.name, mode,
                     rep.get("tracked_frames", 0), len(seq), sum(e.good for e in edges), len(edges), result.fps)
    return dirs


def build_vocabulary_file(scenes: TypingSequence[str], out: Path, frames: TypingSequence[str | None] = (None,),
                          k: int = 10, levels: int = 5, n_features: int = 1000, seed: int = 0,
                          strict: bool = False) -> Path:
    """Build a DBoW2 vocabulary from the frames of ``scenes`` (``frames``: one range for all,
    or one per scene) and write it to ``out``, with ``out`` + ``.json`` naming its sources.
    Never give it test frames: a vocabulary is a trained model. An unreadable frame is left
    out with a warning (``strict``: it stops the run)."""
    if len(frames) not in (1, len(scenes)):
        raise ConfigError(f"give --frames once or once per --scene ({len(scenes)}), got {len(frames)}")
    ranges = list(frames) * len(scenes) if len(frames) == 1 else list(frames)
    images, sources = [], []
    for spec, rng in zip(scenes, ranges):
        for seq in open_scene(spec, frames=rng):
            images += descriptors_of(seq, n_features=n_features, strict=strict)
            sources.append({"scene": scene_id(spec), "sequence": seq.name, "frames": frames_id(seq.ids())})
    if not images or sum(len(d) for d in images) < k:
        raise ConfigError(f"too few ORB descriptors to build a k={k} vocabulary from {list(scenes)}")
    log.info("vocabulary: %d images, %d descriptors, k %d, L %d", len(images), sum(len(d) for d in images), k, levels)
    vocab = build_vocabulary(images, k=k, levels=levels, seed=seed)
    write_vocabulary(vocab, Path(out))
    write_json(Path(str(out) + ".json"), {"format": "ctcvo-orb-vocabulary", "words": int(vocab.words), "k": k,
                                          "levels": levels, "n_features": n_features, "seed": seed,
                                          "sources": sources, "git_revision": git_revision()})
    log.info("vocabulary: %d words -> %s", vocab.words, out)
    return Path(out)
