"""Episodes for training and evaluation, and the simulator configuration they run in.

Training draws endless seeded batches from the train pose region; val and test are fixed episode sets from
their held-out regions, identical for every model with the same seed. Every batch carries its own seed, which
drives the policy's sampling and the sensor noise, so a batch's rollout depends on that batch alone: runs
resume exactly, and `hg test` gives the same numbers twice.
"""
from __future__ import annotations

from dataclasses import asdict
from pathlib import Path

import numpy as np
import pytorch_lightning as pl
import torch
from torch.utils.data import DataLoader, Dataset, IterableDataset

from hg import planner
from hg.sim import SPLITS, DEFAULT_URDF, ProbeSimulator, Scene, SensorNoise, load_object_set, sample_episodes
from hg.sim.client import BulletClient
from hg.sim.heldout import Regions, make_regions
from hg.sim.poses import check_below_ground
from hg.sim.robot import load_robot

Batch = dict[str, torch.Tensor]


def episode_batch(regions: Regions, split: str, size: int, n_classes: int, seed: list[int]) -> Batch:
    """One batch of episodes, a pure function of its seed."""
    rng = np.random.default_rng(seed)
    labels, poses = sample_episodes(regions, split, size, n_classes, rng)
    return {"labels": torch.from_numpy(labels), "poses": torch.from_numpy(poses),
            "seed": torch.tensor(int(rng.integers(2 ** 31)))}


class TrainEpisodes(IterableDataset):
    """Endless training batches; batch i of rank r is seeded by (seed, r, i), starting at `start`."""

    def __init__(self, regions: Regions, n_classes: int, batch_size: int, seed: int, rank: int, start: int) -> None:
        self.regions, self.n_classes, self.batch_size = regions, n_classes, batch_size
        self.seed, self.rank, self.start = seed, rank, start

    def __iter__(self):
        index = self.start
        while True:
            yield episode_batch(self.regions, "train", self.batch_size, self.n_classes, [self.seed, 0, self.rank, index])
            index += 1


class EvalEpisodes(Dataset):
    """A fixed episode set of a held-out split, served in batches (one item = one batch)."""

    def __init__(self, regions: Regions, split: str, n_episodes: int, batch_size: int, n_classes: int,
                 seed: int) -> None:
        sizes = [min(batch_size, n_episodes - lo) for lo in range(0, n_episodes, batch_size)]
        code = SPLITS.index(split)
        self.batches = [episode_batch(regions, split, size, n_classes, [seed, 1, code, i]) for i, size in enumerate(sizes)]

    def __len__(self) -> int:
        return len(self.batches)

    def __getitem__(self, index: int) -> Batch:
        return self.batches[index]


class ProbeDataModule(pl.LightningDataModule):
    """Object set, robot, scene and episode sets: everything about the world the probes are made in.

    `seed` drives the training episodes (the CLI links it to seed_everything); `eval_seed` fixes the val/test
    episodes (and the `cells` regions' draw), so models trained with different seeds meet the same test set.
    `regions` names the held-out protocol (hg.sim.heldout.make_regions): `across_line`, bands of the distance across
    the probe line closed under the objects' symmetries and the library's augmentations (docs/benchmark.md), or
    `cells`, the regions the archived hg4 rows and their teacher files were made in.
    """

    def __init__(self, objects: str = "hg4", robot: str = str(DEFAULT_URDF), mode: str = "arm",
                 scene: Scene = Scene(), noise: SensorNoise = SensorNoise(), n_probes: int = 10,
                 batch_size: int = 64, eval_batch_size: int = 256, val_episodes: int = 1024,
                 test_episodes: int = 2048, seed: int = 0, eval_seed: int = 0, regions: str = "across_line") -> None:
        super().__init__()
        for name, value in (("n_probes", n_probes), ("batch_size", batch_size), ("eval_batch_size", eval_batch_size),
                            ("val_episodes", val_episodes), ("test_episodes", test_episodes)):
            if value < 1:
                raise ValueError(f"data.{name}={value}: must be >= 1")
        if mode not in ("arm", "ideal"):
            raise ValueError(f"data.mode={mode!r}: expected 'arm' or 'ideal'")
        if not Path(robot).is_file():
            raise FileNotFoundError(f"data.robot={robot}: URDF file not found")
        self.save_hyperparameters()
        self.object_set = load_object_set(objects)
        check_below_ground(scene, self.object_set)  # here, not in setup: bad input must fail before a run exists
        if mode == "arm":
            with BulletClient() as client:
                load_robot(client, robot)  # a URDF PyBullet cannot load, or without the tool link, fails here too
        self.regions = make_regions(regions, scene, eval_seed)
        self.scene, self.noise, self.n_probes = scene, noise, n_probes

    @property
    def n_classes(self) -> int:
        return len(self.object_set)

    @property
    def class_names(self) -> tuple[str, ...]:
        return self.object_set.names

    def make_simulator(self) -> ProbeSimulator:
        """One simulator per process, sized for the larger of the training and evaluation batches."""
        h = self.hparams
        return ProbeSimulator(self.object_set, max(h.batch_size, h.eval_batch_size), self.scene, h.mode, h.robot,
                              noise=self.noise, seed=h.seed)

    def train_dataloader(self) -> DataLoader:
        trainer = self.trainer
        rank, start = (trainer.global_rank, trainer.global_step) if trainer is not None else (0, 0)
        stream = TrainEpisodes(self.regions, self.n_classes, self.hparams.batch_size, self.hparams.seed, rank, start)
        return DataLoader(stream, batch_size=None)

    def _eval_loader(self, split: str, n_episodes: int) -> DataLoader:
        h = self.hparams
        return DataLoader(EvalEpisodes(self.regions, split, n_episodes, h.eval_batch_size, self.n_classes, h.eval_seed),
                          batch_size=None)

    def val_dataloader(self) -> DataLoader:
        return self._eval_loader("val", self.hparams.val_episodes)

    def test_dataloader(self) -> DataLoader:
        return self._eval_loader("test", self.hparams.test_episodes)

    def load_teacher(self, paths: list[str]) -> Batch:
        """A teacher's episodes made in this world (hg.planner.load_teacher checks they were)."""
        return planner.load_teacher(paths, object_set_name=self.object_set.name, scene=self.scene,
                                    regions=self.regions, n_probes=self.n_probes, noise=self.noise)

    def describe(self) -> dict:
        """What a results file should record about the world."""
        return {"objects": self.object_set.name, "classes": list(self.class_names), "regions": self.regions.meta(),
                "eval_seed": self.hparams.eval_seed, "mode": self.hparams.mode,
                "robot": self.hparams.robot, "scene": asdict(self.scene), "noise": asdict(self.noise)}
