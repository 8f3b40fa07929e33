"""Benchmark results as data: one JSON record per run, ``bench/results/<name>.json``.

A record holds the command line, the git revision, the UTC date, the machine (cores, load
average at the start and the end, platform, Python and key library versions), the resolved
configuration and the figures (plain JSON numbers; NaN and inf become ``null``). It is
written atomically, so a killed run leaves the previous record or the new one.

    rec = record.start("teacher-redkitchen", vars(args))
    ...
    rec.finish({"fps": 9.1, ...})             # -> bench/results/teacher-redkitchen.json
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import platform
import sys
import time
from importlib import metadata
from pathlib import Path
from typing import Any

from ctcvo.data.io import git_revision, json_safe, write_json

REPO = Path(__file__).resolve().parents[1]
RESULTS = REPO / "bench" / "results"
#: the team's recordings (../shared/data beside the checkout); every script takes its paths as arguments
DATA = REPO.parent / "shared" / "data"
REDKITCHEN = DATA / "7scenes" / "redkitchen" / "seq-sample"
TUM_XYZ = DATA / "tum" / "images" / "rgbd_dataset_freiburg1_xyz"
TUM_TEDDY = DATA / "tum" / "images" / "rgbd_dataset_freiburg3_teddy"
#: where a script writes the outputs it measures, unless given --out
RUNS = REPO / "runs" / "bench"
#: the distributions whose versions a record names
LIBRARIES = ("numpy", "scipy", "torch", "opencv-contrib-python-headless", "open3d-cpu", "gtsam", "evo")
#: the keys every record has (tests/test_bench_record.py)
FIELDS = ("name", "command", "revision", "date_utc", "machine", "config", "figures")


def add_arguments(ap: argparse.ArgumentParser, name: str) -> None:
    """``--name`` (the record's file name, default ``name``) and ``--results`` (its folder)."""
    ap.add_argument("--name", default=name, help=f"record name: RESULTS/NAME.json (default {name})")
    ap.add_argument("--results", type=Path, default=RESULTS, help="folder of the record (default bench/results)")


def versions() -> dict[str, str | None]:
    """Installed version of each of :data:`LIBRARIES` (``None`` where absent)."""
    out: dict[str, str | None] = {}
    for lib in LIBRARIES:
        try:
            out[lib] = metadata.version(lib)
        except metadata.PackageNotFoundError:
            out[lib] = None
    return out


def machine() -> dict[str, Any]:
    """Cores, 1/5/15-minute load average now, platform and Python of this machine."""
    return {"cpu_count": os.cpu_count(), "load_average_start": [round(x, 2) for x in os.getloadavg()],
            "platform": platform.platform(), "python": platform.python_version(), "libraries": versions()}


@dataclasses.dataclass
class Record:
    """A benchmark run under way; :meth:`finish` writes it."""

    name: str
    config: dict[str, Any]
    folder: Path = RESULTS
    command: list[str] = dataclasses.field(default_factory=lambda: ["python", "-m", _module()] + sys.argv[1:])
    revision: str = dataclasses.field(default_factory=git_revision)
    date_utc: str = dataclasses.field(default_factory=lambda: time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()))
    machine: dict[str, Any] = dataclasses.field(default_factory=machine)
    t0: float = dataclasses.field(default_factory=time.perf_counter)

    def finish(self, figures: dict[str, Any]) -> Path:
        """Write ``folder/<name>.json`` with ``figures`` and the load average now; returns its path."""
        mach = {**self.machine, "load_average_end": [round(x, 2) for x in os.getloadavg()]}
        rec = {"name": self.name, "command": self.command, "revision": self.revision, "date_utc": self.date_utc,
               "wall_s": round(time.perf_counter() - self.t0, 1), "machine": mach,
               "config": json_safe(_plain(self.config)), "figures": json_safe(_plain(figures))}
        path = Path(self.folder) / f"{self.name}.json"
        write_json(path, rec)
        print(f"record: {_shown(path)}", file=sys.stderr)
        return path


def start(name: str, config: dict[str, Any], folder: Path = RESULTS) -> Record:
    """Begin the record ``name`` of a run with the resolved ``config`` (arguments included)."""
    return Record(name, dict(config), Path(folder))


def from_args(args: argparse.Namespace, **config: Any) -> Record:
    """:func:`start` from a parser given :func:`add_arguments`: its arguments plus ``config``."""
    cfg = {k: v for k, v in vars(args).items() if k not in ("name", "results")}
    return start(args.name, {**cfg, **config}, args.results)


def load(folder: Path = RESULTS) -> dict[str, dict]:
    """Every record in ``folder``, by name."""
    return {p.stem: json.loads(p.read_text()) for p in sorted(Path(folder).glob("*.json"))}


def _module() -> str:
    main = sys.modules.get("__main__")
    spec = getattr(main, "__spec__", None)
    return spec.name if spec is not None and spec.name else Path(sys.argv[0]).name


def _shown(path: Path) -> str:
    """``path`` relative to the repository when it lies in the repository's folder (``../shared/...``)."""
    full = Path(path).resolve()
    return os.path.relpath(full, REPO) if full.is_relative_to(REPO.parent) else str(full)


def _plain(obj: Any) -> Any:
    """Paths as strings relative to the repository where beside it; dataclasses as dicts."""
    if isinstance(obj, Path):
        return _shown(obj)
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        return _plain(dataclasses.asdict(obj))
    if isinstance(obj, dict):
        return {str(k): _plain(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple, set)):
        return [_plain(v) for v in obj]
    if hasattr(obj, "tolist"):
        return obj.tolist()
    return obj
