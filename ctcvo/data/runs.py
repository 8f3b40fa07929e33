"""Where every stage writes, and the one rerun rule they all follow.

Layout: ``runs/<scene-slug>/<stage>`` (:func:`stage_dir`), with the stages

* ``teacher``   - ``teacher generate``
* ``learner``   - ``learner fit`` (a training run: checkpoint, config, history)
* ``predict``   - ``learner predict`` (edges of a scene; never a training run's folder)
* ``posegraph`` - ``posegraph optimize``
* ``online``    - ``ctcvo online`` (pipeline/online.py)

Rerun rule. Beside its outputs each stage writes ``fingerprint.json``: the inputs that
shape its outputs (scene, selected frames, the stage's resolved config, the fingerprints
or content digests of the upstream outputs it read) and their SHA-256 ``digest``, which
also covers the stage's code version (:data:`STAGE_VERSIONS`). A rerun (:func:`claim`)

* with the same digest skips the work when the stage is done (and resumes it where the
  stage can, e.g. a killed ``learner fit``);
* with a different digest recomputes into the same folder only with ``overwrite`` (the
  stage's old outputs are removed first); otherwise it stops with a one-line
  :class:`StaleOutputError` naming what differs.

``learner calibrate`` writes one file into a training run's folder, whose
``fingerprint.json`` is the training's: it keeps its fingerprint inside that file
(``calibration.json``'s ``fingerprint``; ``claim(..., inside=...)``), written in the same
atomic step as its results; ``posegraph calibrate`` does the same in its ``--out`` file.

:func:`output_folder` removes the folders a failed stage created while they are still
empty, so a failure leaves no empty output folder behind.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import logging
import os
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ctcvo.data.errors import ConfigError, FormatError
from ctcvo.data.io import write_json

log = logging.getLogger(__name__)

#: the root of the default output folders (relative to the working directory)
RUNS_DIR = Path("runs")
#: the stages, in pipeline order; each one's default folder is ``runs/<scene-slug>/<stage>``
STAGES = ("camera", "teacher", "learner", "predict", "posegraph", "online")
FINGERPRINT_FILE = "fingerprint.json"
#: The code version of each fingerprinted stage (the fingerprint's ``stage`` name). A
#: change that alters what a stage writes for the same inputs bumps its number here, in
#: the same commit: the rerun rule then treats the older outputs as outputs of other
#: inputs instead of keeping them. Stages downstream of a file see its change through
#: the file's digest; ``online`` runs the teacher's code itself and records its version.
STAGE_VERSIONS: dict[str, int] = {
    # 2: issue 13's colour-camera model, fallback chain and hybrid gap-1 stage; 3: colour maps of
    # repeated frames, the hybrid stage on stale edges, photo_weight, the rgbd replacement of
    # far-moved sparse edges (synthetic labels change; real-data labels are bit-identical); 4: the
    # constant-velocity prediction scaled over a dropped frame (labels change where timestamps skip
    # one), the point-to-plane stage's fusion covariance from every 4th point (p2p_cov_stride),
    # gap-1 edges beside a colour repeat aligned by the depth alone (synthetic only, path ``depth``);
    # 5: huber_px 4 and refine_inlier_px 3 (re-selected on validation data; every label changes),
    # the plausibility bound from the moment a repeated image shows, the gap-1 rgbd fallback's
    # second start (fallback_span_start), colour-depth timing (depth_time_compensation: TUM
    # RGB-D and bag labels); 6: the dense step stops at 2 mm / 0.08 deg updates (dense_stop_m,
    # re-selected on validation data for speed) in the point-to-plane refinement; other dense
    # alignments keep 0.5 mm / 0.02 deg (align_stop_m); Open3D's kernels on
    # TeacherConfig.threads OpenMP threads in every process; max_rmse_px 2.25 (0.75
    # refine_inlier_px, the margin over the inlier gate it was written with; redkitchen labels
    # bit-identical, one synthetic/lab edge moves 0.06 mm, TUM's longer edges leave the rgbd
    # fallback); 7: the rolling shutter correction of the edges over 2+ frames
    # (TeacherConfig.rolling_shutter_s; every real recording's and noisy synthetic scene's longer
    # edges change, gap-1 edges and noise-free scenes are bit-identical); 8: no point-to-plane
    # step on a gap-1 edge of a registered colour camera without photometric maps (TUM RGB-D's
    # and noise-free scenes' gap-1 labels change), kinect-v1 covariance scales refitted (every
    # real recording's edges.g2o); noisy synthetic scenes' labels are bit-identical; 9: a dense
    # fallback's keyframe edge far from its prediction fails (``fallback_disagrees``); chunks of 75 frames;
    # keyframe edges' covariance scale times KEYFRAME_SCALES (real recordings' edges.g2o); 10: as
    # many chunks per worker (labels change where the chunk count did, e.g. 200 or 394 frames);
    # 11: keyframe edges corrected for the rolling shutter (the keyframe pass resolves
    # rolling_shutter_s and gives keyframes their velocity), no keyframe with one stream's image
    # repeated, synthetic KEYFRAME_SCALES 4 (every keyframe edge changes); 12: kinect-v1
    # KEYFRAME_SCALES 0.25 (real recordings' keyframe edges in edges.g2o); 13: TUM keyframes on 3x the
    # ORB features (REGISTERED_FEATURE_FACTOR: TUM keyframe edges change), observations.csv beside a
    # registered colour camera; 14: observations.csv adds the window's gap-1 feature tracks; 15 (for
    # one commit) dropped the point-to-plane step on TUM's longer window edges; 16: the step back;
    # 17: synthetic scenes' longer window edges beside a frame whose colour and depth show
    # different moments get MIXED_MOMENTS_SCALES (their edges.g2o)
    "teacher": 17,
    # posegraph 2: the bundle adjustment of a teacher folder's observations.csv
    "learner": 1, "predict": 1, "calibrate": 1, "posegraph": 2, "posegraph-calibrate": 1, "online": 1,
}
SYNTHETIC_PREFIX = "synthetic/"


class StaleOutputError(ConfigError):
    """A stage's folder holds outputs of other inputs and ``--overwrite`` was not given."""


def scene_slug(spec: str) -> str:
    """A folder-friendly name for ``spec``, the name the logs give its sequence:
    ``synthetic/office`` -> ``synthetic-office``; a 7-Scenes sequence folder (it holds
    ``frame-*.depth.png``) -> ``<scene>-<sequence>`` (``chess/seq-01`` -> ``chess-seq-01``,
    so two scenes' ``seq-01`` never share a folder); a bag -> its stem; another folder
    (a TUM sequence, a 7-Scenes scene) -> its name."""
    if spec.startswith(SYNTHETIC_PREFIX):
        return "synthetic-" + spec[len(SYNTHETIC_PREFIX):]
    path = Path(spec.partition("?")[0])  # a bag's topic options are not part of its name
    if path.suffix == ".bag":
        return path.stem or "scene"
    path = path.resolve()
    if path.parent.name and path.is_dir() and next(path.glob("frame-*.depth.png"), None) is not None:
        return f"{path.parent.name}-{path.name}"
    return path.name or "scene"


def stage_dir(scene: str, stage: str, root: Path | None = None) -> Path:
    """The default output folder of ``stage`` for ``scene``: ``runs/<scene-slug>/<stage>``."""
    if stage not in STAGES:
        raise ValueError(f"unknown stage {stage!r} (one of {', '.join(STAGES)})")
    return Path(root if root is not None else RUNS_DIR) / scene_slug(scene) / stage


# ----------------------------------------------------------------------------------
# fingerprints
# ----------------------------------------------------------------------------------
def scene_id(spec: str) -> str:
    """How a scene enters a fingerprint: ``synthetic/NAME`` as given, a folder as its
    absolute path (the same folder named two ways is one scene)."""
    return spec if spec.startswith(SYNTHETIC_PREFIX) else str(Path(spec).resolve())


def frames_id(ids: NDArray[np.int64]) -> str:
    """The selected frame ids, readable: ``450..599 (150 frames)``, with the step when it is
    not 1 and a digest when the ids are not evenly spaced."""
    ids = np.asarray(ids, dtype=np.int64)
    if len(ids) == 0:
        return "no frames"
    s = f"{int(ids[0])}..{int(ids[-1])} ({len(ids)} frames"
    steps = np.unique(np.diff(ids)) if len(ids) > 1 else np.array([1])
    if len(steps) == 1 and steps[0] != 1:
        s += f", step {int(steps[0])}"
    elif len(steps) > 1:
        s += f", ids {hashlib.sha256(ids.tobytes()).hexdigest()[:12]}"
    return s + ")"


def file_digest(path: Path) -> str:
    """SHA-256 of a file's content (``sha256:<hex>``)."""
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            h.update(block)
    return "sha256:" + h.hexdigest()


def upstream_digest(folder: Path, main_file: str) -> str:
    """How an upstream output enters a fingerprint: the digest in the folder's
    ``fingerprint.json`` when it has one, else the content digest of ``main_file``."""
    fp = read_fingerprint(folder)
    if fp is not None:
        return fp["digest"]
    return file_digest(Path(folder) / main_file)


@dataclass(frozen=True)
class Fingerprint:
    """The inputs of one stage's outputs (plain JSON values) and their digest."""

    stage: str
    inputs: dict[str, Any]
    version: int | None = None
    """The stage's code version; None takes the stage's :data:`STAGE_VERSIONS` entry (1
    for a stage not listed) when the fingerprint is made."""

    def __post_init__(self) -> None:  # as fingerprint.json will hold them (tuples become lists)
        object.__setattr__(self, "inputs", json.loads(json.dumps(self.inputs, allow_nan=False)))
        if self.version is None:
            object.__setattr__(self, "version", STAGE_VERSIONS.get(self.stage, 1))

    @property
    def digest(self) -> str:
        text = json.dumps({"stage": self.stage, "version": self.version, "inputs": self.inputs}, sort_keys=True,
                          allow_nan=False, separators=(",", ":"))
        return "sha256:" + hashlib.sha256(text.encode()).hexdigest()

    def to_dict(self) -> dict[str, Any]:
        return {"stage": self.stage, "version": self.version, "digest": self.digest, "inputs": self.inputs}


def read_fingerprint(folder: Path, inside: str | None = None) -> dict[str, Any] | None:
    """The fingerprint recorded in ``folder`` (None when there is none): its
    ``fingerprint.json``, or with ``inside`` the ``"fingerprint"`` entry of that JSON output
    file (a stage whose one output records its own inputs, written in one atomic step with
    them, e.g. ``calibration.json`` in a training run's folder, whose ``fingerprint.json`` is
    the training's)."""
    path = Path(folder) / (inside or FINGERPRINT_FILE)
    if not path.is_file():
        return None
    try:
        fp = json.loads(path.read_text())
    except (OSError, ValueError) as exc:
        raise FormatError(f"{path}: not a {'JSON file' if inside else 'fingerprint'} ({exc})") from None
    if inside is not None:
        fp = fp.get("fingerprint") if isinstance(fp, dict) else None
        if fp is None:
            return None
    if not isinstance(fp, dict) or not isinstance(fp.get("digest"), str) or not isinstance(fp.get("inputs"), dict):
        raise FormatError(f"{path}: not a fingerprint (needs 'digest' and 'inputs')")
    return fp


def write_fingerprint(folder: Path, fp: Fingerprint) -> None:
    write_json(Path(folder) / FINGERPRINT_FILE, fp.to_dict())


def differences(old: dict[str, Any], new: dict[str, Any], limit: int = 4) -> str:
    """What differs between two fingerprints' inputs, on one line:
    ``frames: 0..599 (600 frames) -> 0..15 (16 frames); teacher.gaps: 5 -> 2``."""
    flat_old, flat_new = _flatten(old), _flatten(new)
    keys = [k for k in dict.fromkeys([*flat_old, *flat_new]) if flat_old.get(k, _MISSING) != flat_new.get(k, _MISSING)]
    parts = [f"{k}: {_short(flat_old.get(k, _MISSING))} -> {_short(flat_new.get(k, _MISSING))}" for k in keys[:limit]]
    if len(keys) > limit:
        parts.append(f"and {len(keys) - limit} more")
    return "; ".join(parts) or "nothing listed (another version of the stage)"


_MISSING = "(none)"


def _flatten(d: Any, prefix: str = "") -> dict[str, Any]:
    if isinstance(d, dict):
        out: dict[str, Any] = {}
        for k, v in d.items():
            out.update(_flatten(v, f"{prefix}{k}."))
        return out
    return {prefix[:-1]: d}


def _short(v: Any, width: int = 40) -> str:
    s = v if isinstance(v, str) else json.dumps(v)
    if s.startswith("sha256:"):
        s = s[:19]
    return s if len(s) <= width else s[: width - 3] + "..."


def claim(folder: Path, fp: Fingerprint, *, done: bool, has_outputs: bool, overwrite: bool,
          outputs: Iterable[str] = (), inside: str | None = None,
          hint: str = "pass --overwrite to replace them, or choose another --out") -> bool:
    """Apply the rerun rule to ``folder``; True when the work is done and is to be skipped.

    ``done``: the stage's outputs in ``folder`` are complete; ``has_outputs``: it holds
    finished work of some run (a completed file, a checkpoint). With the same digest the
    stage skips when ``done`` and otherwise (re)computes or resumes. With another digest,
    or finished outputs without a fingerprint, ``overwrite`` removes the files named in
    ``outputs`` (paths relative to ``folder``; and ``fingerprint.json``) and the stage
    recomputes; without it this raises :class:`StaleOutputError` saying what differs,
    then ``hint``. ``inside``: the fingerprint is recorded in that output file rather than
    in ``fingerprint.json`` (:func:`read_fingerprint`), which is then left alone.
    """
    folder = Path(folder)
    old = read_fingerprint(folder, inside)
    if old is not None and old["digest"] == fp.digest:
        return done
    if old is None and not has_outputs:
        return False
    where = folder / inside if inside else folder
    if not overwrite:
        what = (f"outputs of version {old.get('version', 0)} of the {fp.stage} stage's code (now version "
                f"{fp.version})" if old is not None and old.get("version", 0) != fp.version
                else f"outputs of other inputs ({differences(old['inputs'], fp.inputs)})" if old is not None
                else f"{fp.stage} outputs without {'a fingerprint' if inside else 'a ' + FINGERPRINT_FILE} "
                     "(an older version wrote them)")
        raise StaleOutputError(f"{where} holds {what}; {hint}")
    log.info("%s: replacing the outputs of other inputs (--overwrite)", where)
    for name in [*outputs, *([] if inside else [FINGERPRINT_FILE])]:
        p = folder / name
        if p.is_file() or p.is_symlink():
            p.unlink(missing_ok=True)  # several processes of one run may get here
    return False


# ----------------------------------------------------------------------------------
# folders
# ----------------------------------------------------------------------------------
def check_writable(folder: Path) -> None:
    """Fail early, creating nothing, when ``folder`` cannot be created or written."""
    p = Path(folder).absolute()
    while not p.exists():
        p = p.parent
    if not p.is_dir():
        raise ConfigError(f"cannot create output folder {folder}: {p} is not a folder")
    if not os.access(p, os.W_OK | os.X_OK):
        raise ConfigError(f"output folder {folder} is not writable ({p})")


@contextlib.contextmanager
def output_folder(folder: Path) -> Iterator[Path]:
    """Run a stage that writes under ``folder``; if it fails, remove the folders it created
    (``folder`` and missing parents, and empty sub-folders) that are still empty."""
    folder = Path(folder)
    check_writable(folder)
    created = []
    p = folder.absolute()
    while not p.exists():
        created.append(p)
        p = p.parent
    try:
        yield folder
    except BaseException:
        for top in created[:1]:
            _remove_empty(top)
        for p in created[1:]:
            with contextlib.suppress(OSError):
                p.rmdir()
        raise


def _remove_empty(folder: Path) -> None:
    if not folder.is_dir():
        return
    for sub in folder.iterdir():
        if sub.is_dir() and not sub.is_symlink():
            _remove_empty(sub)
    with contextlib.suppress(OSError):
        folder.rmdir()  # only succeeds when empty
