"""Where the teacher's worker processes come from: a fork server that imports the teacher once.

A worker that starts from a fresh interpreter spends ~1.4 s (2 s when the cores are
busy) importing Open3D and the rest, about a quarter of a 300-frame run. The fork server
does that once, while the caller is still importing or opening the scene, and every
worker is then forked from it ready to work (~10 ms).

Importing Open3D runs an OpenMP parallel region, which starts libgomp's thread pool; a
child forked from a process holding that pool hangs in its first parallel region with
more than one thread. The fork server therefore imports with ``OMP_NUM_THREADS=1``
(a single-thread region starts no pool); each worker sets its own thread count with
threadpoolctl, and its first region with more threads starts a fresh pool.
This module imports nothing heavy, so a CLI can call :func:`start` before its own imports.
"""

from __future__ import annotations

import multiprocessing
import os
from multiprocessing.context import BaseContext

#: what the fork server imports before it forks any worker
PRELOAD = ["ctcvo.teacher.generate"]


def context() -> BaseContext:
    """The multiprocessing context of the workers: the fork server where there is one."""
    return multiprocessing.get_context("forkserver" if "forkserver" in multiprocessing.get_all_start_methods()
                                       else "spawn")


def start() -> None:
    """Start the fork server (it imports :data:`PRELOAD` in the background); idempotent.

    Call it early: the workers' import then overlaps the caller's work. Without it, the
    first pool starts a fork server that preloads nothing, and each worker imports the
    teacher itself.
    """
    ctx = context()
    if ctx.get_start_method() != "forkserver":
        return
    from multiprocessing import forkserver

    ctx.set_forkserver_preload(PRELOAD)  # no effect once the server runs
    saved = os.environ.get("OMP_NUM_THREADS")
    os.environ["OMP_NUM_THREADS"] = "1"  # the server inherits the environment at its start
    try:
        forkserver.ensure_running()
    finally:
        if saved is None:
            os.environ.pop("OMP_NUM_THREADS", None)
        else:
            os.environ["OMP_NUM_THREADS"] = saved
