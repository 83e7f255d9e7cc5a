"""Teacher files: the planner's chosen probes on training episodes, for a learned policy to imitate.

A file (.npz) holds (E,) classes, (E, 6) poses, (E, N, 4) requests, under sensor faults the (E, N, 2) fault uniforms
each probe read with (ProbeSimulator.probe), and `meta`, JSON: schema 1 records where the episodes came from (object
set, scene, robot, mode, sensor, seeds, pose regions), the candidate grid and the library recipe its planner weighed.
Files written before the schema (schema 0: data/planner/*.npz) carry some of that (objects, eval_seed, noise, the
grid, the recipe); they load, checked on what they carry.
"""
from __future__ import annotations

import io
import json
from dataclasses import asdict
from pathlib import Path

import numpy as np
import torch

from hg.atomic import write_atomic
from hg.planner.library import CandidateGrid, LibraryRecipe
from hg.provenance import commit
from hg.sim.heldout import Regions
from hg.sim.poses import SPLITS
from hg.sim.scene import Scene
from hg.sim.simulator import SensorNoise

SCHEMA = 2  # 1: the world and seeds recorded; 2: the library's confinement (LibraryRecipe.confined)
WRITE_ONE = "write one with scripts/plan.py --save-rollouts"
# what must agree between teacher files read together: one classifier reads every file's sequences, and they must
# have come from one world
PLANNER_FIELDS = ("places", "span", "leans", "along_leans", "library", "library_split", "shifts", "mirror", "sigma",
                  "mismatch", "bin", "objects", "eval_seed")
WORLD_FIELDS = ("scene", "regions", "sensor")  # recorded from schema 1 on


def fault_rate(noise: SensorNoise) -> float:
    """The one fault rate of a teacher's sensor (miss_prob = false_contact_prob, no position noise): the sensors a
    teacher file can record and replay."""
    if noise.position_std or noise.miss_prob != noise.false_contact_prob:
        raise ValueError(f"teacher sensor {noise}: a teacher replays contact faults at one rate (miss_prob = "
                         "false_contact_prob, position_std = 0) from their uniforms")
    return noise.miss_prob


def save_teacher(path: str | Path, labels: np.ndarray, poses: np.ndarray, requests: np.ndarray, *,
                 object_set_name: str, classes: tuple[str, ...], regions: Regions, robot: str | Path, mode: str,
                 noise: SensorNoise, seed: int, grid: CandidateGrid, recipe: LibraryRecipe, bin: float,
                 faults: np.ndarray | None = None, summary: dict | None = None, settings: dict | None = None) -> dict:
    """Write a teacher file in one atomic write: the planner's episodes (labels (E,), poses (E, 6)), the requests it
    chose (E, N, 4), under sensor faults the (E, N, 2) fault uniforms its probes read with, and their provenance
    (schema 1: the world, the seeds, the grid, the recipe, the commit; `summary` of the planner's run and its
    `settings`, Evaluation.settings). Returns the meta written."""
    e = len(labels)
    if poses.shape != (e, 6) or requests.ndim != 3 or requests.shape[0] != e or requests.shape[2] != 4:
        raise ValueError(f"save_teacher: {path}: labels {labels.shape}, poses {poses.shape} and requests "
                         f"{requests.shape}, expected (E,), (E, 6) and (E, N, 4)")
    rate = fault_rate(noise)
    if (faults is None) != (rate == 0) or (faults is not None and faults.shape != requests.shape[:2] + (2,)):
        raise ValueError(f"save_teacher: {path}: sensor fault rate {rate} with faults "
                         f"{None if faults is None else faults.shape}, expected "
                         f"{requests.shape[:2] + (2,) if rate else None}")
    meta = {"schema": SCHEMA, "objects": object_set_name, "classes": list(classes), "scene": asdict(regions.scene),
            "eval_seed": regions.seed, "regions": regions.meta(), "robot": str(robot), "mode": mode,
            "noise": rate, "sensor": asdict(noise), "seed": seed, "episodes": e, "n_probes": requests.shape[1],
            **grid.meta(), **recipe.meta(), "bin": bin, "commit": commit(("hg", "scripts")), "summary": summary,
            "planner_settings": settings}
    buffer = io.BytesIO()
    np.savez_compressed(buffer, labels=labels, poses=poses, requests=requests.astype(np.float32),
                        meta=np.array(json.dumps(meta)), **({} if faults is None else {"faults": faults}))
    write_atomic(path, buffer.getvalue())
    return meta


def read_meta(path: str | Path) -> dict:
    """A teacher file's meta, with its schema (0: written before the schema) and the defaults of old files (no
    along-line leans; the library drawn with the planner's seed). Refuses a missing file or a newer schema."""
    if not Path(path).is_file():
        raise FileNotFoundError(f"{path}: teacher file not found ({WRITE_ONE})")
    with np.load(path) as f:
        if "meta" not in f.files:
            raise ValueError(f"{path}: not a teacher file, no meta")
        meta = json.loads(str(f["meta"]))
    meta = {"schema": 0, "along_leans": []} | meta
    meta.setdefault("library_seed", meta.get("seed"))
    if meta["schema"] > SCHEMA:
        raise ValueError(f"{path}: teacher meta schema={meta['schema']}, this code reads schema <= {SCHEMA}")
    return meta


def load_teacher(paths: list[str | Path], *, object_set_name: str, scene: Scene, regions: Regions,
                 n_probes: int, noise: SensorNoise = SensorNoise()) -> dict[str, torch.Tensor | None]:
    """A teacher's episodes for a policy to copy: the classes, poses and requests of the files, concatenated, and
    the (E, N, 2) faults its probes read with ("faults"; None without sensor faults). Refuses a file made for another
    object set, scene or pose regions (eval_seed), another probe count or another sensor (a teacher that read other
    faults chose for readings the copy never sees), naming the file and the field, and any episode whose pose lies
    outside the training region: a teacher's episodes are training data, and held-out poses must not leak into
    them. Old files (schema 0) are checked on the fields they carry."""
    if not paths:
        raise ValueError("load_teacher: no teacher files")
    if regions.scene != scene:
        raise ValueError(f"load_teacher: the pose regions' scene {regions.scene} is not the run's {scene}")
    try:
        rate = fault_rate(noise)
    except ValueError as error:
        raise ValueError(f"load_teacher: this run's {error}") from None
    parts = []
    for path in paths:
        meta = read_meta(path)
        with np.load(path) as f:
            missing = {"labels", "poses", "requests"} - set(f.files)
            if missing:
                raise ValueError(f"{path}: not a teacher file, no {sorted(missing)}")
            labels, poses, requests = f["labels"], f["poses"], f["requests"]
            faults = f["faults"] if "faults" in f.files else None
        expected = json.loads(json.dumps({"objects": object_set_name, "noise": rate, "scene": asdict(scene),
                                          "regions": regions.meta(), "sensor": asdict(noise)}
                                         | ({"eval_seed": regions.seed} if regions.seeded else {})))  # as in meta
        if meta.get("library_split", "train") != "train":
            raise ValueError(f"{path}: teacher meta library_split={meta['library_split']!r}: its planner weighed "
                             "held-out poses; a teacher must be planned over training poses only")
        for field, want in expected.items():
            have = meta.get(field)
            if (meta["schema"] < 1 and field not in meta) or have == want:  # schema 0: checked on what it carries
                continue
            if field == "noise":
                raise ValueError(f"{path}: planned with sensor faults at rate {have} (teacher meta noise), this run's "
                                 f"rate is {want}: write a teacher with scripts/plan.py --noise {want}")
            raise ValueError(f"{path}: teacher meta {field}={have!r}, this run has {want!r}")
        if rate and (faults is None or faults.shape != requests.shape[:2] + (2,)):
            raise ValueError(f"{path}: planned under noise without its faults of shape {requests.shape[:2] + (2,)}")
        if requests.ndim != 3 or requests.shape[1:] != (n_probes, 4) or not len(labels) == len(poses) == len(requests):
            raise ValueError(f"{path}: teacher requests of shape {requests.shape} for {len(labels)} episodes, expected "
                             f"({len(labels)}, {n_probes}, 4) (n_probes={n_probes})")
        if (outside := int((regions.split_of(poses) != SPLITS.index("train")).sum())):
            raise ValueError(f"{path}: {outside} of {len(poses)} poses lie outside the training region (a teacher's "
                             "episodes are training data)")
        parts.append((labels, poses, requests, faults))
    labels, poses, requests, faults = zip(*parts)
    return {"labels": torch.from_numpy(np.concatenate(labels)).long(), "poses": torch.from_numpy(np.concatenate(poses)),
            "requests": torch.from_numpy(np.concatenate(requests)).float(),
            "faults": torch.from_numpy(np.concatenate(faults)) if rate else None}  # every file's rate is the run's


def teacher_meta(paths: list[str | Path]) -> dict:
    """The first file's meta (read_meta): the planner arguments and world the teacher files were made with. They
    must agree on those that shape the candidates and the library, and on the world (where both record it), since one
    classifier reads every sequence."""
    if not paths:
        raise ValueError("teacher_meta: no teacher files")
    metas = [read_meta(path) for path in paths]
    for path, meta in zip(paths[1:], metas[1:]):
        world = [k for k in WORLD_FIELDS if k in meta and k in metas[0]]  # both of schema >= 1
        if differ := [k for k in (*PLANNER_FIELDS, *world) if meta.get(k) != metas[0].get(k)]:
            raise ValueError(f"{path}: teacher meta {differ} differ from {paths[0]}'s")
    return metas[0]
