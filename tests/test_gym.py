"""The gymnasium environments over the real simulator."""
import subprocess
import sys

import gymnasium
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

from hg.sim import ProbeSimulator
from hg.sim.gym_env import HapticGlanceEnv, HapticGlanceVectorEnv


@pytest.fixture
def env():
    environment = HapticGlanceEnv(n_probes=4, mode="ideal")
    yield environment
    environment.close()


def test_passes_the_gymnasium_checker(env):
    check_env(env, skip_render_check=True)


def test_episode_length_and_observations(env):
    observation, info = env.reset(seed=3)
    assert observation["count"] == 0 and not observation["points"].any()
    for k in range(1, 5):
        observation, reward, terminated, truncated, info = env.step(np.array([0.0, 0.0, 0.0, 1.0], np.float32))
        assert observation["count"] == k and terminated == (k == 4) and not truncated
        assert reward == float(info["touched"]) == observation["points"][k - 1, 3]
    with pytest.raises(RuntimeError, match="reset"):
        env.step(np.zeros(4, np.float32))


def test_same_seed_same_episode(env):
    runs = []
    for _ in range(2):
        _, info = env.reset(seed=11)
        steps = [env.step(np.array([0.1 * k, 0.3, -0.2, 0.0], np.float32)) for k in range(4)]
        runs.append((info["label"], np.stack([s[0]["points"] for s in steps])))
    assert runs[0][0] == runs[1][0]
    np.testing.assert_array_equal(runs[0][1], runs[1][1])


def test_classifier_callback_reward():
    def always_ball(requests, points):
        assert requests.shape == points.shape and requests.shape[1] == 4
        return 2  # hg4 class order: pipe, box, ball, tire
    env = HapticGlanceEnv(n_probes=2, mode="ideal", classifier=always_ball)
    rewards = []
    for seed in range(12):
        _, info = env.reset(seed=seed)
        reward = env.step(np.zeros(4, np.float32))[1]
        assert reward == float(info["label"] == 2)
        rewards.append(reward)
    env.close()
    assert 0 < sum(rewards) < 12


def test_arm_mode_episode():
    env = gymnasium.make("HapticGlance-v0", n_probes=2)
    env.reset(seed=0)
    _, _, _, _, info = env.step(np.array([0.0, 0.5, 0.0, 0.0], np.float32))
    assert info["pose_error"][0] < 0.005 and info["pose_error"][1] < 3.0
    env.close()


def test_vector_env_probes_all_with_one_step_and_autoresets():
    envs = gymnasium.make_vec("HapticGlance-v0", num_envs=5, vectorization_mode="vector_entry_point", n_probes=3,
                              mode="ideal")
    assert isinstance(envs.unwrapped, HapticGlanceVectorEnv)
    observations, info = envs.reset(seed=2)
    assert observations["points"].shape == (5, 3, 4)
    for k in range(3):
        observations, rewards, terminated, truncated, info = envs.step(envs.action_space.sample())
        assert rewards.shape == (5,) and (terminated == (k == 2)).all()
        np.testing.assert_array_equal(rewards, info["touched"].astype(float))
    poses = envs.unwrapped.episodes.sim.poses.copy()
    observations, rewards, terminated, _, info = envs.step(envs.action_space.sample())  # the autoreset step
    assert (observations["count"] == 0).all() and not rewards.any() and not terminated.any()
    assert not np.array_equal(poses, envs.unwrapped.episodes.sim.poses)  # new episodes
    envs.close()


def test_random_policy_rollout_via_make():
    env = gymnasium.make("HapticGlance-v0", n_probes=5, mode="ideal")
    env.action_space.seed(0)
    observation, info = env.reset(seed=0)
    steps, terminated, truncated = 0, False, False
    while not (terminated or truncated):
        observation, reward, terminated, truncated, info = env.step(env.action_space.sample())
        steps += 1
        assert observation in env.observation_space and reward in (0.0, 1.0)
    assert steps == 5 and observation["count"] == 5 and info["class_name"] in env.unwrapped.episodes.sim.classes
    env.close()


def test_vector_env_matches_probing_each_episode_alone():
    """One ray batch over all sub-environments gives what a one-episode simulator gives for each of them."""
    envs = HapticGlanceVectorEnv(num_envs=4, n_probes=3, mode="ideal")
    envs.reset(seed=7)
    envs.action_space.seed(7)
    steps = [envs.step(envs.action_space.sample()) for _ in range(3)]
    assert any(step[4]["touched"].any() for step in steps)  # contacts as well as misses are compared
    sim = envs.episodes.sim
    observations = steps[-1][0]
    with ProbeSimulator(batch_size=1, mode="ideal") as alone:
        for i in range(4):
            alone.reset(sim.labels[i:i + 1], sim.poses[i:i + 1])
            for k in range(3):
                point = alone.probe(observations["requests"][i, k][None].astype(np.float64)).points[0]
                np.testing.assert_allclose(observations["points"][i, k], point, atol=1e-5)
                assert steps[k][1][i] == point[3] == float(steps[k][4]["touched"][i])
    envs.close()


@pytest.mark.parametrize("code", [
    "import hg, sys; print(int('hg.sim.gym_env' in sys.modules), int('torch' in sys.modules)); import gymnasium; "
    "env = gymnasium.make('HapticGlance-v0', n_probes=2, mode='ideal')",
    "import gymnasium; env = gymnasium.make('hg:HapticGlance-v0', n_probes=2, mode='ideal')"])
def test_the_environment_registers_on_import_hg(code):
    """As panda-gym does on `import panda_gym`: no need to know about hg.sim.gym_env, and nothing heavy on import."""
    done = subprocess.run([sys.executable, "-c", f"{code}; env.reset(seed=0); print(env.spec.id)"],
                          capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr[-2000:]
    lines = done.stdout.split()
    assert lines[-1].endswith("HapticGlance-v0")
    if code.startswith("import hg,"):
        assert lines[:2] == ["0", "0"]  # registered, yet neither the simulator nor torch imported
