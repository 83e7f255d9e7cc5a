import os

import pytest

from hg.lightning.data import episode_batch
from hg.sim import PoseRegions, ProbeSimulator

os.environ.setdefault("WANDB_MODE", "disabled")  # tests never need the network
# tiny nets on a small machine: one torch thread per process (this one and the CLI runs it starts) is faster than
# threads that wait for each other, and leaves the other core to a DDP peer or a subprocess
os.environ.setdefault("OMP_NUM_THREADS", "1")


@pytest.fixture(scope="session", autouse=True)
def reach_cache(tmp_path_factory):
    """Reach maps are built fresh for the test session, never read from a user's cache."""
    path = tmp_path_factory.mktemp("hg-cache")
    os.environ["HG_CACHE_DIR"] = str(path)
    return path


@pytest.fixture(scope="module")
def sim():
    """An ideal-mode hg4 simulator for up to 16 episodes."""
    with ProbeSimulator("hg4", batch_size=16, mode="ideal") as sim:
        yield sim


@pytest.fixture(scope="module")
def batch():
    """8 seeded training episodes of hg4."""
    return episode_batch(PoseRegions(), "train", 8, 4, [0, 0, 0, 0])
