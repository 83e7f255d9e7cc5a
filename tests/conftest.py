import os

import pytest

os.environ.setdefault("WANDB_MODE", "disabled")  # tests never need the network


@pytest.fixture(scope="session", autouse=True)
def reach_cache(tmp_path_factory):
    """Reach maps are built fresh for the test session, never read from a user's cache."""
    path = tmp_path_factory.mktemp("hg-cache")
    os.environ["HG_CACHE_DIR"] = str(path)
    return path
