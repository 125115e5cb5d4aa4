import shutil
from pathlib import Path

import pytest

from calib3r_graph.simulate import SimOptions, simulate

REPO = Path(__file__).resolve().parents[1]
SAMPLE = REPO / "datasets" / "sample"
SHARED = REPO.parent / "shared"


@pytest.fixture(scope="session")
def simulated(tmp_path_factory):
    """Factory for seeded simulated datasets (predictions only unless images=True), cached per session."""
    cache = {}

    def make(**kw):
        key = tuple(sorted(kw.items()))
        if key not in cache:
            kw.setdefault("images", False)
            out = tmp_path_factory.mktemp("sim")
            cache[key] = simulate(out, SimOptions(**kw), progress=False)
        return cache[key]

    return make


@pytest.fixture
def sample_copy(tmp_path):
    """A writable copy of the shipped sample dataset."""
    dst = tmp_path / "sample"
    shutil.copytree(SAMPLE, dst)
    return dst
