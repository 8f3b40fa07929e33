"""Atomic file output: a stage never leaves a half-written file behind.

Every writer goes through :func:`atomic_write` (write to a temporary file in the same
folder, flush, fsync, ``os.replace``), so a killed run leaves either the old file or the
new one, never a truncated one. Files get the mode a plain ``open`` would give them
(``0o666`` less the umask: 0644 by default), not the temporary file's 0600.
"""

from __future__ import annotations

import contextlib
import json
import logging
import math
import os
import subprocess
import tempfile
from collections.abc import Iterator
from pathlib import Path
from typing import Any, TextIO

import numpy as np

from ctcvo.data.errors import FormatError, VOError


def ensure_dir(path: Path) -> Path:
    """Create ``path`` (and parents); raise :class:`VOError` if it cannot be written."""
    path = Path(path)
    try:
        path.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise VOError(f"cannot create output folder {path}: {exc.strerror or exc}") from None
    if not os.access(path, os.W_OK):
        raise VOError(f"output folder {path} is not writable")
    return path


@contextlib.contextmanager
def atomic_write(path: Path, mode: str = "w") -> Iterator[TextIO]:
    """Open a temporary sibling of ``path`` for writing; rename it over ``path`` on success."""
    path = Path(path)
    ensure_dir(path.parent)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        os.fchmod(fd, 0o666 & ~current_umask())
        with os.fdopen(fd, mode) as fh:
            yield fh
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        raise


def current_umask() -> int:
    """The process's umask, read without changing it (Linux: /proc; elsewhere set and reset)."""
    try:
        with open("/proc/self/status") as fh:
            for line in fh:
                if line.startswith("Umask:"):
                    return int(line.split()[1], 8)
    except (OSError, ValueError):
        pass
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


def write_text(path: Path, text: str) -> None:
    with atomic_write(path) as fh:
        fh.write(text)


def json_safe(obj: Any) -> Any:
    """``obj`` with every non-finite float (NaN, inf) replaced by ``None`` (JSON ``null``),
    recursively through dicts, lists and tuples; NumPy scalars become Python numbers.
    Strict JSON has no NaN, and :func:`write_json` refuses it."""
    if isinstance(obj, (float, np.floating)):
        return float(obj) if math.isfinite(obj) else None
    if isinstance(obj, np.integer):
        return int(obj)
    if isinstance(obj, dict):
        return {k: json_safe(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [json_safe(v) for v in obj]
    return obj


def write_json(path: Path, obj: Any) -> None:
    """Write ``obj`` as strict JSON atomically (non-finite floats are an error; pass the
    object through :func:`json_safe` to write them as ``null``)."""
    with atomic_write(path) as fh:
        json.dump(obj, fh, indent=2, sort_keys=False, allow_nan=False)
        fh.write("\n")


def read_json_file(path: Path, what: str, fmt: int, key: str, kind: type) -> dict[str, Any]:
    """The JSON object in ``path``, checked to be ``what`` of format ``fmt`` with a ``key`` of
    type ``kind``; :class:`~data.errors.FormatError` says in one line what is wrong."""
    try:
        d = json.loads(Path(path).read_text())
    except (OSError, ValueError) as exc:
        raise FormatError(f"cannot read {what} {path}: {exc}") from None
    if not isinstance(d, dict) or d.get("format") != fmt or not isinstance(d.get(key), kind):
        raise FormatError(f"{path} is not a {what} (format {fmt} with {key})")
    return d


def git_revision() -> str:
    """The project's git revision (``unknown`` outside a checkout), ``-dirty`` when a tracked
    file other than a benchmark record (``bench/results/``) differs from it: records are
    outputs, and one benchmark after another would otherwise mark every later one dirty."""
    here = Path(__file__).resolve().parent
    try:
        out = subprocess.run(
            ["git", "rev-parse", "--short", "HEAD"], cwd=here, capture_output=True,
            text=True, timeout=5, check=True,
        )
        dirty = subprocess.run(
            ["git", "status", "--porcelain", "--untracked-files=no", "--", ":/", ":(top,exclude)bench/results"], cwd=here,
            capture_output=True, text=True, timeout=5,
        ).stdout.strip()
        return out.stdout.strip() + ("-dirty" if dirty else "")
    except (OSError, subprocess.SubprocessError):
        return "unknown"


#: the packages whose loggers the command-line tools show at INFO
PACKAGES = ("ctcvo",)


#: every log line starts with the wall-clock time (a long run shows when each step happened)
TIME_FORMAT = "%H:%M:%S"


def setup_logging(verbose: bool = False, fmt: str = "%(levelname)s %(name)s: %(message)s") -> None:
    """Log this project's messages at INFO (DEBUG with ``verbose``), other libraries' at WARNING.

    Every line is prefixed with the time (``HH:MM:SS``).

    Libraries log INFO lines of their own at import (numexpr, pulled in by evo's pandas:
    "NumExpr defaulting to 2 threads."), which are not the tools' output.
    """
    logging.basicConfig(level=logging.WARNING, format="%(asctime)s " + fmt, datefmt=TIME_FORMAT)
    for name in PACKAGES:
        logging.getLogger(name).setLevel(logging.DEBUG if verbose else logging.INFO)
