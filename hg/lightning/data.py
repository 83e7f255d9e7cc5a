"""Episodes for training and evaluation, and the simulator configuration they run in.

Training draws endless seeded batches from the train pose region; val and test are fixed episode sets from
their held-out regions, identical for every model with the same seed. Every batch carries its own seed, which
drives the policy's sampling and the sensor noise, so a batch's rollout depends on that batch alone: runs
resume exactly, and `hg test` gives the same numbers twice.
"""
from __future__ import annotations

import json
from dataclasses import asdict
from pathlib import Path

import numpy as np
import pytorch_lightning as pl
import torch
from torch.utils.data import DataLoader, Dataset, IterableDataset

from hg.sim import SPLITS, DEFAULT_URDF, PoseRegions, ProbeSimulator, Scene, SensorNoise, load_object_set, sample_episodes

Batch = dict[str, torch.Tensor]


def episode_batch(regions: PoseRegions, split: str, size: int, n_classes: int, seed: list[int]) -> Batch:
    """One batch of episodes, a pure function of its seed."""
    rng = np.random.default_rng(seed)
    labels, poses = sample_episodes(regions, split, size, n_classes, rng)
    return {"labels": torch.from_numpy(labels), "poses": torch.from_numpy(poses),
            "seed": torch.tensor(int(rng.integers(2 ** 31)))}


def load_teacher(paths: list[str], regions: PoseRegions, objects: str, n_probes: int,
                 noise: SensorNoise = SensorNoise()) -> Batch:
    """A teacher's episodes for a policy to copy (model.imitate): the classes, poses and requests of the files that
    `scripts/planner_ceiling.py --save-rollouts` writes, concatenated, and the (E, N, 2) faults its probes read with
    ("faults", ProbeSimulator.probe; None without noise). Refuses a file made for other objects, another probe count,
    other pose regions or another sensor (`noise`: a teacher that read other faults chose for readings the copy never
    sees), and any episode whose pose lies outside the training region: a teacher's episodes are training data, and
    held-out poses must not leak into them."""
    parts = []
    for path in paths:
        if not Path(path).is_file():
            raise FileNotFoundError(f"model.imitate: {path}: teacher file not found (write one with "
                                    "scripts/planner_ceiling.py --save-rollouts)")
        with np.load(path) as f:
            missing = {"labels", "poses", "requests", "meta"} - set(f.files)
            if missing:
                raise ValueError(f"model.imitate: {path}: not a teacher file, no {sorted(missing)}")
            labels, poses, requests, meta = f["labels"], f["poses"], f["requests"], json.loads(str(f["meta"]))
            faults = f["faults"] if "faults" in f.files else None
        for field, want in (("objects", objects), ("eval_seed", regions.seed)):
            if meta.get(field) != want:
                raise ValueError(f"model.imitate: {path}: meta {field}={meta.get(field)!r}, this run has {want!r}")
        rate = meta.get("noise", 0.0)  # planner_ceiling.py --noise: miss and false-contact probabilities both
        if (noise.miss_prob, noise.false_contact_prob, noise.position_std) != (rate, rate, 0.0):
            raise ValueError(f"model.imitate: {path}: planned with sensor faults at rate {rate} (miss_prob = "
                             f"false_contact_prob), this run's data.noise is {noise}: write a teacher with "
                             "scripts/planner_ceiling.py --noise at the run's rate")
        if rate and (faults is None or faults.shape != requests.shape[:2] + (2,)):
            raise ValueError(f"model.imitate: {path}: planned under noise without its faults of shape "
                             f"{requests.shape[:2] + (2,)}")
        if requests.ndim != 3 or requests.shape[1:] != (n_probes, 4) or not len(labels) == len(poses) == len(requests):
            raise ValueError(f"model.imitate: {path}: requests of shape {requests.shape} for {len(labels)} episodes, "
                             f"expected ({len(labels)}, {n_probes}, 4) (data.n_probes={n_probes})")
        if (outside := int((regions.split_of(poses) != SPLITS.index("train")).sum())):
            raise ValueError(f"model.imitate: {path}: {outside} of {len(poses)} poses lie outside the training region")
        parts.append((labels, poses, requests, faults))
    labels, poses, requests, faults = zip(*parts)
    return {"labels": torch.from_numpy(np.concatenate(labels)).long(), "poses": torch.from_numpy(np.concatenate(poses)),
            "requests": torch.from_numpy(np.concatenate(requests)).float(),
            "faults": torch.from_numpy(np.concatenate(faults)) if rate else None}  # every file's rate is the run's


def teacher_meta(paths: list[str]) -> dict:
    """The planner arguments the teacher files were made with; they must agree on those that shape the candidates
    and the library, since one namer reads every sequence."""
    metas = []
    for path in paths:
        with np.load(path) as f:
            metas.append({"along_leans": []} | json.loads(str(f["meta"])))  # files from before along-line leans
    keys = ("places", "span", "leans", "along_leans", "library", "library_split", "shifts", "mirror", "sigma",
            "mismatch", "bin")
    for path, meta in zip(paths[1:], metas[1:]):
        if (differ := [k for k in keys if meta.get(k) != metas[0].get(k)]):
            raise ValueError(f"{path}: planner arguments {differ} differ from {paths[0]}'s")
    return metas[0]


class TrainEpisodes(IterableDataset):
    """Endless training batches; batch i of rank r is seeded by (seed, r, i), starting at `start`."""

    def __init__(self, regions: PoseRegions, n_classes: int, batch_size: int, seed: int, rank: int, start: int) -> None:
        self.regions, self.n_classes, self.batch_size = regions, n_classes, batch_size
        self.seed, self.rank, self.start = seed, rank, start

    def __iter__(self):
        index = self.start
        while True:
            yield episode_batch(self.regions, "train", self.batch_size, self.n_classes, [self.seed, 0, self.rank, index])
            index += 1


class EvalEpisodes(Dataset):
    """A fixed episode set of a held-out split, served in batches (one item = one batch)."""

    def __init__(self, regions: PoseRegions, split: str, n_episodes: int, batch_size: int, n_classes: int,
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

    `seed` drives the training episodes (the CLI links it to seed_everything); `eval_seed` fixes the held-out
    pose regions and the val/test episodes, so models trained with different seeds meet the same test set.
    """

    def __init__(self, objects: str = "hg4", robot: str = str(DEFAULT_URDF), mode: str = "arm",
                 scene: Scene = Scene(), noise: SensorNoise = SensorNoise(), n_probes: int = 10,
                 batch_size: int = 64, eval_batch_size: int = 256, val_episodes: int = 1024,
                 test_episodes: int = 2048, seed: int = 0, eval_seed: int = 0) -> None:
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
        self.regions = PoseRegions(scene, seed=eval_seed)
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

    def describe(self) -> dict:
        """What a results file should record about the world."""
        return {"objects": self.object_set.name, "classes": list(self.class_names), "mode": self.hparams.mode,
                "robot": self.hparams.robot, "scene": asdict(self.scene), "noise": asdict(self.noise)}
