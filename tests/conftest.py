"""Shared fixtures. Real data lives beside the project in ../shared/data (never copied).

Tests that need it call :func:`require_real_data` (or use the ``real_data`` fixture): they
skip with a reason when it is absent, and fail when ``VO_REQUIRE_REAL_DATA=1``.
"""

from __future__ import annotations

import os
import shutil
import tempfile
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
SHARED_DATA = Path(os.environ.get("VO_SHARED_DATA", REPO.parent / "shared" / "data"))
REDKITCHEN = SHARED_DATA / "7scenes" / "redkitchen" / "seq-sample"
TUM_FR1_XYZ = SHARED_DATA / "tum" / "rgbd_dataset_freiburg1_xyz"
TUM_IMAGES = SHARED_DATA / "tum" / "images" / "rgbd_dataset_freiburg1_xyz"
TUM_TEDDY = SHARED_DATA / "tum" / "images" / "rgbd_dataset_freiburg3_teddy"


def require_real_data(path: Path) -> Path:
    """Return ``path`` if it exists; otherwise skip (or fail under VO_REQUIRE_REAL_DATA=1)."""
    if path.exists():
        return path
    msg = f"real data not found at {path} (see ../shared/data/README.md)"
    if os.environ.get("VO_REQUIRE_REAL_DATA") == "1":
        pytest.fail(msg + " and VO_REQUIRE_REAL_DATA=1")
    pytest.skip(msg)


@pytest.fixture(scope="session")
def redkitchen() -> Path:
    """Path of the real 7-Scenes redkitchen sample sequence."""
    return require_real_data(REDKITCHEN)


@pytest.fixture(scope="session")
def tum_fr1_xyz() -> Path:
    """Path of the real TUM fr1/xyz text files."""
    return require_real_data(TUM_FR1_XYZ)


@pytest.fixture(scope="session")
def tum_images() -> Path:
    """Path of the real TUM fr1/xyz folder with images (400 frames)."""
    return require_real_data(TUM_IMAGES)


@pytest.fixture(scope="session")
def tum_teddy() -> Path:
    """Path of the real TUM fr3/teddy folder with images (200 frames, motion capture)."""
    return require_real_data(TUM_TEDDY)


def pytest_configure(config) -> None:
    """Synthetic renders go to a per-session temporary cache, never to the user's
    ``~/.cache/ctcvo``: set before any fixture of any scope, test module or subprocess
    (which inherit the environment) can render."""
    os.environ["VO_CACHE_DIR"] = config._ctcvo_cache = tempfile.mkdtemp(prefix="ctcvo-test-cache-")


def pytest_unconfigure(config) -> None:
    cache = getattr(config, "_ctcvo_cache", None)
    if cache:
        shutil.rmtree(cache, ignore_errors=True)


@pytest.fixture(autouse=True)
def _isolated_cache(monkeypatch):
    """Each test sees the session's temporary cache, even after another test changed it."""
    monkeypatch.setenv("VO_CACHE_DIR", os.environ["VO_CACHE_DIR"])


@pytest.fixture(scope="module")
def one_torch_thread():
    """One torch intra-op thread for a test module (``pytestmark = usefixtures(...)``).

    The tiny learner networks are dominated by per-op overhead: one thread is faster than
    two and does not stall when the machine's cores are busy (OpenMP barriers of a
    2-thread pool wait for a descheduled thread)."""
    import torch

    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)
