"""Where the teacher's worker processes come from: a fork server that imports the teacher once;
and :class:`FeatureProcess`, the process ``vo-online`` extracts each frame's features in.

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
PRELOAD = ["teacher.generate"]


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


# ----------------------------------------------------------------------------------
# one process for a stream's per-frame features (vo-online)
# ----------------------------------------------------------------------------------
_worker: dict = {}  # in the feature process: the teacher's settings and the last frame's features


def _init_features(K, cfg, colour) -> None:
    import signal

    from teacher.odometry import make_orb

    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C is the caller's to handle; it shuts this down
    _worker.update(K=K, cfg=cfg, colour=colour, orb=make_orb(cfg), last=None)


def _features(rgb, depth):
    import time

    from teacher.odometry import extract

    w, cpu = _worker, time.thread_time()
    w["last"] = extract(rgb, depth, w["cfg"], w["orb"], w["K"], w["colour"], surface=False)
    return w["last"], time.thread_time() - cpu


def _surface() -> dict:
    from teacher.odometry import add_surface

    fk = _worker["last"]
    if fk is None or fk.dense is None:
        return {}
    before = dict(vars(fk.dense))
    add_surface(fk.dense, fk.depth, _worker["K"], _worker["cfg"])
    return {k: v for k, v in vars(fk.dense).items() if before.get(k) is not v}


class FeatureProcess:
    """A frame's teacher features (:func:`teacher.odometry.extract` without the surface
    maps, then :func:`teacher.odometry.add_surface`) computed in one worker process.

    Open3D's image filters hold Python's GIL, so in a thread of the estimating process they
    stall its Python code (bench/README.md, "Online mode"); in a process of their own they
    run beside it. The features come back pickled (bit for bit what the thread computes);
    the worker ignores SIGINT (the caller's Ctrl-C ends the run and :meth:`close` ends it).
    """

    def __init__(self, K, cfg, colour=None) -> None:
        from concurrent.futures import ProcessPoolExecutor

        start()
        self.pool = ProcessPoolExecutor(1, mp_context=context(), initializer=_init_features,
                                        initargs=(K, cfg, colour))
        self.pool.submit(int).result()  # started and initialised before the first frame
        self.cpu_s = 0.0

    def features(self, rgb, depth):
        """``extract(rgb, depth, ..., surface=False)`` of the stream's next frame (and
        ``cpu_s``: the CPU time it took in the worker)."""
        fk, self.cpu_s = self.pool.submit(_features, rgb, depth).result()
        return fk

    def finish(self, fk) -> None:
        """Add the surface maps of the last frame :meth:`features` gave (``fk``) to ``fk.dense``."""
        if fk.dense is not None:
            for k, v in self.pool.submit(_surface).result().items():
                setattr(fk.dense, k, v)

    def close(self) -> None:
        self.pool.shutdown(wait=False, cancel_futures=True)
