"""Gymnasium environments over the simulator core, for other RL libraries.

Observation: the requests and points so far (zero rows after the current probe) and the probe count.
Action: one request (py, ux, uy, uz) in [-1, 1]. Reward: with a `classifier` callback, 1 when its prediction
after this probe is the true class; without one, the contact flag T (1 when the probe touched the object).
An episode ends after `n_probes` probes.
"""
from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import gymnasium
import numpy as np
from gymnasium import spaces
from gymnasium.vector import AutoresetMode, VectorEnv
from gymnasium.vector.utils import batch_space

from hg.sim.heldout import make_regions
from hg.sim.poses import sample_episodes
from hg.sim.robot import DEFAULT_URDF
from hg.sim.scene import Scene
from hg.sim.simulator import ProbeSimulator, SensorNoise

POINT_BOUND = 10.0  # m: touched points and ray ends lie within U_len of the probe line; generous for user scenes
Classifier = Callable[[np.ndarray, np.ndarray], int]  # (requests (k, 4), points (k, 4)) -> class index


def observation_space(n_probes: int) -> spaces.Dict:
    return spaces.Dict({
        "requests": spaces.Box(-1.0, 1.0, (n_probes, 4), np.float32),
        "points": spaces.Box(-POINT_BOUND, POINT_BOUND, (n_probes, 4), np.float32),
        "count": spaces.Discrete(n_probes + 1),
    })


class _Episodes:
    """What both environments share: the simulator, the pose regions and the episode bookkeeping."""

    def __init__(self, num_envs: int, objects: str | Path, n_probes: int, split: str, mode: str, robot: str | Path,
                 scene: Scene, noise: SensorNoise, classifier: Classifier | None, eval_seed: int, regions: str) -> None:
        if n_probes < 1:
            raise ValueError(f"n_probes={n_probes}: must be >= 1")
        self.sim = ProbeSimulator(objects, num_envs, scene, mode, robot, noise=noise)
        self.regions = make_regions(regions, scene, eval_seed, field="regions")
        self.n_probes, self.split, self.classifier = n_probes, split, classifier
        self.requests = np.zeros((num_envs, n_probes, 4), np.float32)
        self.points = np.zeros((num_envs, n_probes, 4), np.float32)
        self.count = 0

    def new_episodes(self, rng: np.random.Generator) -> None:
        labels, poses = sample_episodes(self.regions, self.split, len(self.requests), len(self.sim.classes), rng)
        self.sim.reset(labels, poses, seed=int(rng.integers(2 ** 31)))
        self.requests[:], self.points[:], self.count = 0.0, 0.0, 0

    def probe(self, actions: np.ndarray) -> tuple[np.ndarray, np.ndarray, list[dict]]:
        actions = np.asarray(actions, dtype=np.float64).reshape(len(self.requests), 4)
        result = self.sim.probe(actions)
        k = self.count
        self.requests[:, k] = np.clip(actions, -1.0, 1.0)
        self.points[:, k] = result.points
        self.count += 1
        if self.classifier is None:
            rewards = result.points[:, 3].copy()
        else:
            rewards = np.array([float(self.classifier(self.requests[i, :k + 1], self.points[i, :k + 1]) == label)
                                for i, label in enumerate(self.sim.labels)])
        infos = [{"label": int(label), "class_name": self.sim.classes[label], "pose": self.sim.poses[i].copy(),
                  "pose_error": result.pose_error[i].copy(), "touched": bool(result.points[i, 3])}
                 for i, label in enumerate(self.sim.labels)]
        return rewards, np.full(len(rewards), self.count >= self.n_probes), infos

    def observation(self, i: int) -> dict:
        return {"requests": self.requests[i].copy(), "points": self.points[i].copy(), "count": self.count}


class HapticGlanceEnv(gymnasium.Env):
    """One episode at a time; `reset(seed=...)` draws the object and its pose from the split's region."""

    metadata = {"render_modes": []}

    def __init__(self, objects: str | Path = "hg4", n_probes: int = 10, split: str = "train", mode: str = "arm",
                 robot: str | Path = DEFAULT_URDF, scene: Scene = Scene(), noise: SensorNoise = SensorNoise(),
                 classifier: Classifier | None = None, eval_seed: int = 0, regions: str = "across_line") -> None:
        self.episodes = _Episodes(1, objects, n_probes, split, mode, robot, scene, noise, classifier, eval_seed,
                                  regions)
        self.observation_space = observation_space(n_probes)
        self.action_space = spaces.Box(-1.0, 1.0, (4,), np.float32)

    def reset(self, *, seed: int | None = None, options: dict | None = None) -> tuple[dict, dict]:
        super().reset(seed=seed)
        self.episodes.new_episodes(self.np_random)
        sim = self.episodes.sim
        return self.episodes.observation(0), {"label": int(sim.labels[0]), "class_name": sim.classes[sim.labels[0]]}

    def step(self, action: np.ndarray) -> tuple[dict, float, bool, bool, dict]:
        if self.episodes.count >= self.episodes.n_probes:
            raise RuntimeError("step() after the episode ended: call reset()")
        rewards, done, infos = self.episodes.probe(action)
        return self.episodes.observation(0), float(rewards[0]), bool(done[0]), False, infos[0]

    def close(self) -> None:
        self.episodes.sim.close()


class HapticGlanceVectorEnv(VectorEnv):
    """num_envs episodes in one simulator: one ray batch probes them all. Every episode lasts n_probes steps,
    so all end together; the step after the end resets them (gymnasium's next-step autoreset)."""

    metadata = {"render_modes": [], "autoreset_mode": AutoresetMode.NEXT_STEP}

    def __init__(self, num_envs: int = 8, objects: str | Path = "hg4", n_probes: int = 10, split: str = "train",
                 mode: str = "arm", robot: str | Path = DEFAULT_URDF, scene: Scene = Scene(),
                 noise: SensorNoise = SensorNoise(), classifier: Classifier | None = None, eval_seed: int = 0,
                 regions: str = "across_line") -> None:
        self.num_envs = num_envs
        self.episodes = _Episodes(num_envs, objects, n_probes, split, mode, robot, scene, noise, classifier, eval_seed,
                                  regions)
        self.single_observation_space = observation_space(n_probes)
        self.single_action_space = spaces.Box(-1.0, 1.0, (4,), np.float32)
        self.observation_space = batch_space(self.single_observation_space, num_envs)
        self.action_space = batch_space(self.single_action_space, num_envs)
        self._rng = np.random.default_rng()

    def _observations(self) -> dict:
        e = self.episodes
        return {"requests": e.requests.copy(), "points": e.points.copy(), "count": np.full(self.num_envs, e.count)}

    def reset(self, *, seed: int | None = None, options: dict | None = None) -> tuple[dict, dict]:
        if seed is not None:
            self._rng = np.random.default_rng(seed)
        self.episodes.new_episodes(self._rng)
        return self._observations(), {"label": self.episodes.sim.labels.copy()}

    def step(self, actions: np.ndarray) -> tuple[dict, np.ndarray, np.ndarray, np.ndarray, dict]:
        e = self.episodes
        if e.count >= e.n_probes:  # next-step autoreset: this step's actions are ignored
            observations, info = self.reset()
            zeros = np.zeros(self.num_envs, dtype=bool)
            return observations, np.zeros(self.num_envs), zeros, zeros, info
        rewards, done, infos = e.probe(actions)
        info = {"label": e.sim.labels.copy(), "touched": np.array([i["touched"] for i in infos])}
        return self._observations(), rewards, done, np.zeros(self.num_envs, dtype=bool), info

    def close_extras(self, **kwargs) -> None:
        self.episodes.sim.close()
