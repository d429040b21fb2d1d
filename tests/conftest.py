"""Shared test fixtures: where the real test scenes live.

The research-use scenes are read from ``../shared/data`` beside the repository (CI has
them there too); ``OMG4_SHARED_DATA`` overrides the location. They are never copied
into the repository.
"""

from __future__ import annotations

import atexit
import os
import shutil
import tempfile
from pathlib import Path

import pytest

REPO_ROOT = Path(__file__).resolve().parents[1]
SHARED_DATA = Path(os.environ.get("OMG4_SHARED_DATA", REPO_ROOT.parent / "shared" / "data"))


# Several tests compare the numba kernels with the torch forms bit for bit in float32. Torch's CPU matrix
# products run in MKL, whose kernels pick their instruction set per processor (AVX-512 on recent Intel chips) and
# round differently with each; its conditional numerical reproducibility mode makes them round alike everywhere.
os.environ.setdefault("MKL_CBWR", "COMPATIBLE")

# Under pytest-xdist (``-n 2``) every worker computes on one thread, so the workers share the cores instead of
# contending for them (torch's and numba's thread pools would otherwise each take every core).
if os.environ.get("PYTEST_XDIST_WORKER"):
    for variable in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "NUMBA_NUM_THREADS"):
        os.environ[variable] = "1"

# Keep frame caches and converted weights of a test session out of the user's cache folder,
# in a folder of the session's own that is removed when the session ends.
if "OMG4_CACHE_DIR" not in os.environ:
    os.environ["OMG4_CACHE_DIR"] = tempfile.mkdtemp(prefix="omg4-test-cache-")
    atexit.register(shutil.rmtree, os.environ["OMG4_CACHE_DIR"], ignore_errors=True)


def shared_scene(name: str) -> Path:
    """Path of a scene in the shared data folder; skips the test when it is absent."""
    path = SHARED_DATA / name
    if not path.exists():
        pytest.skip(f"shared test data {path} not available")
    return path


@pytest.fixture
def n3dv_basketball() -> Path:
    return shared_scene("n3dv_basketball")


@pytest.fixture
def panoptic_basketball() -> Path:
    return shared_scene("panoptic_basketball")


@pytest.fixture
def dnerf_mutant() -> Path:
    return shared_scene("dnerf_mutant")


@pytest.fixture
def lpips_calibration() -> Path:
    return shared_scene("lpips_calibration")


@pytest.fixture(scope="session")
def synthetic_scene(tmp_path_factory):
    """``write(name, **sizes)``: a synthetic N3DV scene of those :class:`~omg4.data.synthetic.SynthConfig` sizes
    in a new temporary folder; returns its path."""
    from omg4.data.synthetic import SynthConfig, write_synthetic_scene

    def write(name: str, **sizes):
        out = tmp_path_factory.mktemp(name) / "scene"
        write_synthetic_scene(out, SynthConfig(**sizes), progress=False)
        return out
    return write


@pytest.fixture(scope="session")
def tiny_scene_dir(synthetic_scene):
    """A tiny synthetic N3DV scene (5 cameras, 6 frames, 64×48) for training and compression tests."""
    return synthetic_scene("tiny", num_cameras=5, num_frames=6, width=64, height=48, num_points=600)


@pytest.fixture(scope="session")
def tiny_scene(tiny_scene_dir):
    from omg4.data import load_scene

    return load_scene(tiny_scene_dir, progress=False)


def pytest_collection_modifyitems(items):
    """The tests that drive Chromium (the web player's, through the ``chromium`` fixture, and those marked so) carry
    the ``browser`` marker, for the count :func:`pytest_terminal_summary` prints."""
    for item in items:
        if "chromium" in getattr(item, "fixturenames", ()):
            item.add_marker(pytest.mark.browser)


def pytest_terminal_summary(terminalreporter):
    """One line of how many browser tests ran, so a run whose browser tests all skipped says so."""
    ran, skipped = 0, 0
    for category in ("passed", "failed", "error", "skipped"):
        for report in terminalreporter.stats.get(category, ()):
            if "browser" not in getattr(report, "keywords", {}):
                continue
            if category == "skipped":
                skipped += 1
            elif report.when == "call" or category == "error":
                ran += 1
    terminalreporter.write_line(f"browser tests: {ran} ran, {skipped} skipped")


@pytest.fixture(scope="module")
def chromium(tmp_path_factory):
    """Headless Chromium with software WebGL2 (:class:`omg4.testing.browser.Browser`), one per test module; the test
    skips, with the reason, where Debian's ``chromium`` is missing (``.ci/run`` installs it)."""
    from omg4.testing.browser import CHROMIUM, Browser

    if CHROMIUM is None:
        pytest.skip("no Chromium to drive (Debian package 'chromium')")
    browser = Browser(tmp_path_factory.mktemp("profile"))
    yield browser
    browser.close()
