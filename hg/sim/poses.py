"""Held-out object poses: train, val and test draw from disjoint regions of the pose space.

The (X, Y) square is cut into cells and Rz into sectors. A few whole position cells (every Rz) belong to
test and a few to val, so test holds object positions never seen in training; in every other position
cell one Rz sector is held out (for test or val), so test also holds unseen (position, heading) pairs.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import ClassVar

import numpy as np

from hg.sim.objects import ObjectSet
from hg.sim.scene import Scene

SPLITS = ("train", "val", "test")


def rotation_matrices(angles_deg: np.ndarray) -> np.ndarray:
    """R = Rz Ry Rx for rows (Rx, Ry, Rz) in degrees: PyBullet's getQuaternionFromEuler convention."""
    rx, ry, rz = np.radians(np.asarray(angles_deg, dtype=np.float64)).T
    cx, sx, cy, sy, cz, sz = np.cos(rx), np.sin(rx), np.cos(ry), np.sin(ry), np.cos(rz), np.sin(rz)
    return np.stack([
        np.stack([cz * cy, cz * sy * sx - sz * cx, cz * sy * cx + sz * sx], -1),
        np.stack([sz * cy, sz * sy * sx + cz * cx, sz * sy * cx - cz * sx], -1),
        np.stack([-sy, cy * sx, cy * cx], -1),
    ], -2)


def quaternions(angles_deg: np.ndarray) -> np.ndarray:
    """Quaternions (x, y, z, w) of the same rotations: PyBullet's getQuaternionFromEuler, vectorised."""
    half = np.radians(np.asarray(angles_deg, dtype=np.float64)) / 2
    (sr, sp, sy), (cr, cp, cy) = np.sin(half).T, np.cos(half).T
    return np.column_stack([sr * cp * cy - cr * sp * sy, cr * sp * cy + sr * cp * sy,
                            cr * cp * sy - sr * sp * cy, cr * cp * cy + sr * sp * sy])


def check_below_ground(scene: Scene, objects: ObjectSet, grid: int = 5) -> None:
    """Raise when some allowed pose puts part of an object above Z=0 (Rz does not change heights)."""
    rx, ry = np.meshgrid(np.linspace(*scene.rot_x_deg, grid), np.linspace(*scene.rot_y_deg, grid))
    rot = rotation_matrices(np.column_stack([rx.ravel(), ry.ravel(), np.zeros(rx.size)]))
    for name, mesh in zip(objects.names, objects.meshes):
        heights = np.einsum("j,rjk,vk->rv", [0.0, 0.0, 1.0], rot, mesh.vertices).max(axis=1)
        worst = int(heights.argmax())
        top = scene.object_z[1] + heights[worst]
        if top >= 0.0:
            raise ValueError(
                f"scene.object_z={scene.object_z}: object '{name}' reaches Z={top:+.3f} m above ground at "
                f"Rx={rx.ravel()[worst]:.1f}, Ry={ry.ravel()[worst]:.1f} deg; lower object_z or the rotations")


@dataclass(frozen=True)
class PoseRegions:
    """Assigns every cell of (X cells x Y cells x Rz sectors) to one split, deterministically per seed."""

    scene: Scene = field(default_factory=Scene)
    seed: int = 0
    cells: tuple[int, int, int] = (4, 4, 6)
    held_out_positions: int = 2  # whole position cells given to each of val and test
    seeded: ClassVar[bool] = True  # the seed draws which cells are held out

    def __post_init__(self) -> None:
        nx, ny, nr = self.cells
        if min(self.cells) < 1 or nr < 2:
            raise ValueError(f"pose_regions.cells={self.cells}: need >= 1 position cell per axis and >= 2 Rz sectors")
        if 2 * self.held_out_positions >= nx * ny:
            raise ValueError(f"pose_regions.held_out_positions={self.held_out_positions}: leaves no position "
                             f"cell for training out of {nx * ny}")
        rng = np.random.default_rng(self.seed)
        table = np.zeros((nx * ny, nr), dtype=np.int64)  # 0 train, 1 val, 2 test
        order = rng.permutation(nx * ny)
        k = self.held_out_positions
        table[order[:k]] = 2
        table[order[k:2 * k]] = 1
        for i, cell in enumerate(order[2 * k:]):
            table[cell, rng.integers(nr)] = 2 if i % 2 == 0 else 1
        object.__setattr__(self, "table", table.reshape(nx, ny, nr))

    def meta(self) -> dict:
        """How the regions cut the pose space, as teacher files record it (their seed is `eval_seed`)."""
        return {"cells": list(self.cells), "held_out_positions": self.held_out_positions}

    def cell_of(self, poses: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Cell indices of poses (n, 6)."""
        s = self.scene
        idx = []
        for col, (lo, hi), n in ((0, s.object_x, self.cells[0]), (1, s.object_y, self.cells[1]),
                                 (5, s.rot_z_deg, self.cells[2])):
            frac = (poses[:, col] - lo) / max(hi - lo, 1e-12)
            idx.append(np.clip((frac * n).astype(np.int64), 0, n - 1))
        return tuple(idx)

    def split_of(self, poses: np.ndarray) -> np.ndarray:
        """Split index (0 train, 1 val, 2 test) of each pose."""
        return self.table[self.cell_of(np.asarray(poses))]

    def sample(self, split: str, n: int, rng: np.random.Generator) -> np.ndarray:
        """n poses (X, Y, Z, Rx, Ry, Rz in degrees) uniform over the split's region."""
        if split not in SPLITS:
            raise ValueError(f"split={split!r}: expected one of {SPLITS}")
        cells = np.argwhere(self.table == SPLITS.index(split))
        pick = cells[rng.integers(len(cells), size=n)]
        unit = rng.random((n, 6))
        s = self.scene
        low, high = s.pose_low, s.pose_high
        poses = low + unit * (high - low)
        for axis, col, n_cells in ((0, 0, self.cells[0]), (1, 1, self.cells[1]), (2, 5, self.cells[2])):
            width = (high[col] - low[col]) / n_cells
            poses[:, col] = low[col] + (pick[:, axis] + unit[:, col]) * width
        return poses


def sample_episodes(regions: PoseRegions, split: str, n: int, n_classes: int,
                    rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Class labels uniform over the object set and poses from the split's region."""
    labels = rng.integers(n_classes, size=n)
    return labels, regions.sample(split, n, rng)
