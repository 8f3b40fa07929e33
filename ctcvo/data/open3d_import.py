"""Open3D, imported without the two subpackages this project never uses until they are used.

``import open3d`` (0.19) always imports ``open3d.ml`` (its datasets import scikit-learn and
pandas) and ``open3d.visualization`` (its Plotly/Dash viewer). On the 2-core VM that is
about 1 s of the ~2 s the import takes when idle, 3-4 s when the cores are busy, in every
process that uses the teacher or the renderer (each ``teacher generate`` starts two).
The teacher and the renderer need only ``open3d.core``, ``geometry``, ``camera``,
``pipelines`` and ``t``, which are the compiled module.

:data:`o3d` is the ``open3d`` package imported with ``open3d.ml`` and
``open3d.visualization`` first registered as stand-ins (:class:`_Deferred`): the
package's own ``import open3d.ml`` finds the stand-in, and the stand-in imports the real
subpackage on the first access of an attribute it does not have (``open3d.ml.datasets``,
``import open3d.visualization.gui``, ...), so code that uses them sees no difference.
Where this cannot be arranged (Open3D already imported, its files not found), it is the
plain import.

:func:`openmp_threads` runs a block with Open3D's kernels on a given number of threads.
"""

from __future__ import annotations

import contextlib
import importlib
import importlib.machinery
import importlib.util
import os
import sys
import types
from collections.abc import Iterator

from threadpoolctl import threadpool_limits

_DEFERRED = ("ml", "visualization")


class _Deferred(types.ModuleType):
    """Stands in for ``open3d.<name>`` until one of its attributes is asked for."""

    def __getattr__(self, attr: str):
        name = self.__name__
        if sys.modules.get(name) is self:
            del sys.modules[name]
            real = importlib.import_module(name)  # runs the subpackage, binds it on open3d
        else:
            real = sys.modules[name]
        return getattr(real, attr)


def _defer_subpackages() -> list[str]:
    """Register the stand-ins; returns their names (none when Open3D is imported already
    or its files are not where a path finder looks)."""
    if "open3d" in sys.modules:
        return []
    spec = importlib.util.find_spec("open3d")  # the top-level spec: runs nothing
    if spec is None or not spec.submodule_search_locations:
        return []
    names = []
    for sub in _DEFERRED:
        full = f"open3d.{sub}"
        if full in sys.modules or importlib.machinery.PathFinder.find_spec(
                full, list(spec.submodule_search_locations)) is None:
            continue
        sys.modules[full] = _Deferred(full)
        names.append(full)
    return names


def _import():
    names = _defer_subpackages()
    try:
        import open3d
    except BaseException:
        for full in names:  # leave no stand-ins behind
            if isinstance(sys.modules.get(full), _Deferred):
                del sys.modules[full]
        raise
    for full in names:  # `import open3d.ml` found the stand-in and bound no attribute
        sub = full.split(".", 1)[1]
        if full in sys.modules and not hasattr(open3d, sub):
            setattr(open3d, sub, sys.modules[full])
    return open3d


o3d = _import()


@contextlib.contextmanager
def open3d_follows_openmp(n: int) -> Iterator[None]:
    """Within the block, Open3D's kernels run on OpenMP's thread count of the thread that
    calls them (``omp_set_num_threads``, what threadpoolctl sets).

    Open3D ignores that count and takes every physical core unless ``OMP_NUM_THREADS`` is in
    the environment (it reads the variable at each kernel call). So the block sets the
    variable (to ``n``) where it is absent; a caller then limits its threads with
    threadpoolctl. Without it, ``threadpool_limits(1)`` left the teacher's labels on
    redkitchen equal to its 2-thread labels, and differing from those of a process started
    with ``OMP_NUM_THREADS`` set. Set it before starting threads that call Open3D, and leave
    it until they are done: the environment is not safe to change while another thread
    reads it.
    """
    absent = "OMP_NUM_THREADS" not in os.environ
    if absent:
        os.environ["OMP_NUM_THREADS"] = str(n)
    try:
        yield
    finally:
        if absent:
            os.environ.pop("OMP_NUM_THREADS", None)


@contextlib.contextmanager
def openmp_threads(n: int) -> Iterator[None]:
    """Within the block, Open3D's kernels, OpenMP and BLAS in the calling thread use ``n``
    threads (:func:`open3d_follows_openmp` and ``threadpool_limits(n)``; another thread
    sets its own with ``threadpool_limits(n)``)."""
    with open3d_follows_openmp(n), threadpool_limits(n):
        yield
