"""The paper's point-cloud baselines, PointNet and DGCNN, trained supervised on sparse surface points (no probing):
clouds of N_POINTS points sampled uniformly from the whole surface of the object at its pose, a `rate` share of them
replaced by points of the pose volume (hg.sim.pointclouds). They train on fresh poses of the training region and are
scored on the very validation and test episodes (labels and poses) the probing rows meet (EvalEpisodes), so Table 1
and the noise study read them beside the probing models.
"""
from __future__ import annotations

import copy
import time

import numpy as np
import torch
import torch.nn.functional as F

from hg.lightning.data import EvalEpisodes
from hg.nets import DGCNN, PointNet
from hg.sim import sample_episodes
from hg.sim.heldout import Regions
from hg.sim.objects import ObjectSet
from hg.sim.pointclouds import noisy_point_clouds

N_POINTS = 10
POINT_SCALE = 2.0  # as HapticGlance.point_scale: coordinates of order 1
NETS = {"pointnet": ("PointNet", lambda n_classes: PointNet(n_classes)),
        "dgcnn": ("DGCNN (k=9)", lambda n_classes: DGCNN(n_classes, k=9))}


def cloud_tensor(clouds: np.ndarray) -> torch.Tensor:
    """Centred on the cloud's mean (the usual PointNet normalisation; the pose's position is not a class cue)."""
    return torch.from_numpy((clouds - clouds.mean(1, keepdims=True)) * POINT_SCALE).float()


def fixed_clouds(regions: Regions, objects: ObjectSet, split: str, n_episodes: int, rate: float, eval_seed: int,
                 eval_batch_size: int = 256) -> tuple[torch.Tensor, torch.Tensor]:
    """The split's fixed episodes (the ones the probing models meet, drawn batch by batch as the data module's
    eval_batch_size draws them) as clouds, seeded by split and rate only."""
    batches = EvalEpisodes(regions, split, n_episodes, eval_batch_size, len(objects), eval_seed).batches
    labels = np.concatenate([b["labels"].numpy() for b in batches])
    poses = np.concatenate([b["poses"].numpy() for b in batches])
    rng = np.random.default_rng([eval_seed, split == "test", int(round(rate * 100))])
    clouds, _ = noisy_point_clouds(regions.scene, objects, labels, poses, N_POINTS, rate, rng)
    return cloud_tensor(clouds), torch.from_numpy(labels)


@torch.no_grad()
def accuracy(net: torch.nn.Module, clouds: torch.Tensor, labels: torch.Tensor) -> float:
    net.eval()
    return float((net(clouds).argmax(-1) == labels).float().mean())


def train_cloud_classifier(name: str, objects: ObjectSet, regions: Regions, rate: float, seed: int, steps: int,
                           batch_size: int, val_episodes: int, test_episodes: int, eval_seed: int,
                           first_k: bool = False, eval_batch_size: int = 256) -> dict:
    """Supervised training of NETS[name] on fresh train-region clouds at noise `rate`; the state best on the
    validation clouds (every 250 steps and at the end) is scored on the test clouds. Returns its test accuracy, best
    validation accuracy, sizes and training wall time; with `first_k` also `accuracy_first_k`, the test accuracy
    reading only the first k points of each cloud, k = 1..N_POINTS (a Table 1 row's accuracy after each "probe")."""
    if name not in NETS:
        raise ValueError(f"point-cloud baseline {name!r}: expected one of {sorted(NETS)}")
    torch.manual_seed(seed)
    val = fixed_clouds(regions, objects, "val", val_episodes, rate, eval_seed, eval_batch_size)
    test = fixed_clouds(regions, objects, "test", test_episodes, rate, eval_seed, eval_batch_size)
    net = NETS[name][1](len(objects))
    optimiser = torch.optim.Adam(net.parameters(), lr=1e-3)
    schedule = torch.optim.lr_scheduler.CosineAnnealingLR(optimiser, steps)
    rng = np.random.default_rng([seed, int(round(rate * 100))])
    best_val, best_state, start = -1.0, None, time.time()
    for step in range(1, steps + 1):
        labels, poses = sample_episodes(regions, "train", batch_size, len(objects), rng)
        clouds, _ = noisy_point_clouds(regions.scene, objects, labels, poses, N_POINTS, rate, rng)
        net.train()
        loss = F.cross_entropy(net(cloud_tensor(clouds)), torch.from_numpy(labels))
        optimiser.zero_grad()
        loss.backward()
        optimiser.step()
        schedule.step()
        if step % 250 == 0 or step == steps:
            val_acc = accuracy(net, *val)
            if val_acc > best_val:
                best_val, best_state = val_acc, copy.deepcopy(net.state_dict())
    net.load_state_dict(best_state)
    result = {"accuracy": round(accuracy(net, *test), 4), "best_val_acc": round(best_val, 4), "steps": steps,
              "batch_size": batch_size, "train_wall_s": round(time.time() - start, 1)}
    if first_k:  # the first k points, centred on their own mean as a cloud of k would be
        clouds, labels = test
        first = [clouds[:, :k] - clouds[:, :k].mean(1, keepdim=True) for k in range(1, N_POINTS)] + [clouds]
        result["accuracy_first_k"] = [round(accuracy(net, cloud, labels), 4) for cloud in first]
    return result
