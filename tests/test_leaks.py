"""Resource leaks: simulators and environments made and closed many times, as sweeps and test suites do."""
import gc

import gymnasium
import numpy as np
import pybullet
import pytest

import hg.sim.gym_env  # noqa: F401  registers HapticGlance-v0
from hg.sim import ProbeSimulator
from hg.sim.objects import hg4

MAX_CLIENTS = 1024  # client ids PyBullet hands out are small: scanning this many covers any this process holds


def rss_mb() -> float:
    """Resident set size of this process (VmRSS in /proc/self/status), in MB."""
    with open("/proc/self/status") as status:
        for line in status:
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024
    raise RuntimeError("/proc/self/status: no VmRSS line")


def connected_clients() -> set[int]:
    return {i for i in range(MAX_CLIENTS) if pybullet.isConnected(physicsClientId=i)}


def use_and_close(objects, mode: str, batch_size: int = 2) -> None:
    """One simulator's life: build, place objects, probe once, close; its client must be gone at once."""
    sim = ProbeSimulator(objects, batch_size=batch_size, mode=mode)
    sim.reset(np.arange(batch_size) % len(sim.classes), np.tile([0.0, 0.0, -0.3, 0.0, 0.0, 0.0], (batch_size, 1)))
    sim.probe(np.tile([0.0, 0.0, 0.0, 1.0], (batch_size, 1)))
    client = sim.client.id
    sim.close()
    sim.close()  # closing twice is harmless
    assert not sim.client.connected and not pybullet.isConnected(physicsClientId=client)


def rss_growth(make_and_close, n: int) -> float:
    """RSS growth over n calls, after a few warm-up calls have filled allocator pools and caches."""
    for _ in range(3):
        make_and_close()
    gc.collect()
    before = rss_mb()
    for _ in range(n):
        make_and_close()
    gc.collect()
    return rss_mb() - before


def test_closed_simulators_leave_no_client_connected():
    before = connected_clients()
    objects = hg4()
    for _ in range(20):
        use_and_close(objects, "ideal")
    for _ in range(3):
        use_and_close(objects, "arm")
    assert connected_clients() == before


def test_failed_construction_closes_its_client():
    before = connected_clients()
    with pytest.raises(ValueError, match="no link named"):
        ProbeSimulator(batch_size=1, mode="arm", tool_link="no_such_link")
    assert connected_clients() == before


def test_closed_environments_leave_no_client_connected():
    before = connected_clients()
    for _ in range(5):
        env = gymnasium.make("HapticGlance-v0", n_probes=2, mode="ideal")
        env.reset(seed=0)
        env.step(env.action_space.sample())
        env.close()
    envs = gymnasium.make_vec("HapticGlance-v0", num_envs=3, vectorization_mode="vector_entry_point", n_probes=2,
                              mode="ideal")
    envs.reset(seed=0)
    envs.step(envs.action_space.sample())
    envs.close()
    assert connected_clients() == before


def test_making_and_closing_simulators_does_not_grow_memory():
    objects = "hg4"  # a fresh object set each time, as separate runs in one process would load it
    growth = rss_growth(lambda: use_and_close(objects, "ideal", batch_size=4), 200)
    growth += rss_growth(lambda: use_and_close(objects, "arm"), 10)
    assert growth < 50.0, f"RSS grew by {growth:.1f} MB over 200 ideal and 10 arm simulators"


def test_probing_does_not_grow_memory():
    """The hot path (resets, IK, ray batches) holds no references: long training runs stay flat."""
    rng = np.random.default_rng(0)
    with ProbeSimulator(batch_size=8, mode="arm") as sim:
        def episode():
            sim.reset(rng.integers(len(sim.classes), size=8), np.tile([0.0, 0.0, -0.3, 0.0, 0.0, 0.0], (8, 1)))
            for _ in range(10):
                sim.probe(rng.uniform(-1.0, 1.0, (8, 4)))
        growth = rss_growth(episode, 100)
    assert growth < 5.0, f"RSS grew by {growth:.1f} MB over 1000 probe steps of 8 episodes"
