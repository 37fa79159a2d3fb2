import os
from pathlib import Path

import pytest
import torch

ROOT = Path(__file__).resolve().parents[1]
SHARED = ROOT.parent / "shared" / "data" / "bandai-namco"
ARTIFACTS = ROOT / "test-artifacts"  # PNGs and exports for a person to look at (gitignored)

torch.set_num_threads(max(1, min(2, os.cpu_count() or 1)))


def pytest_addoption(parser):
    parser.addoption("--runslow", action="store_true", help="run slow tests (real data, minutes of CPU)")


def pytest_collection_modifyitems(config, items):
    if config.getoption("--runslow"):
        return
    skip = pytest.mark.skip(reason="slow: run with --runslow")
    for it in items:
        if "slow" in it.keywords:
            it.add_marker(skip)


@pytest.fixture
def artifacts():
    ARTIFACTS.mkdir(exist_ok=True)
    return ARTIFACTS


@pytest.fixture
def bandai():
    if not SHARED.exists():
        pytest.skip("../shared/data/bandai-namco is not present")
    return SHARED


@pytest.fixture(autouse=True)
def _isolated_cache(tmp_path, monkeypatch):
    # never touch the user's motion cache from tests
    monkeypatch.setenv("AVATAR_MOTOR_CACHE", str(tmp_path / "cache"))


@pytest.fixture(scope="session")
def quirky_files(tmp_path_factory):
    """The real-world skeleton fixtures (tests/fixture_tools.py QUIRKS) written to files with our
    own writer, made at test time: the 120 fps CMU one alone is 330 KB of text."""
    from avatar_motor.io.bvh import write_bvh
    from .fixture_tools import QUIRKS, quirky_bvh
    d = tmp_path_factory.mktemp("quirks")
    for naming in QUIRKS:
        write_bvh(d / f"mix_{naming}.bvh", quirky_bvh(naming), precision=5)
    return d
