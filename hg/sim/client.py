"""The one owner of a headless PyBullet client, the collision groups and the chunked ray cast."""
from __future__ import annotations

import functools

import numpy as np
import pybullet

# Rays select objects only: robot links and the ground are put in groups the ray mask leaves out.
OBJECT_GROUP = 0b001
ROBOT_GROUP = 0b010
GROUND_GROUP = 0b100
RAY_CHUNK = pybullet.MAX_RAY_INTERSECTION_BATCH_SIZE - 1  # exactly MAX rays comes back empty (NOTES.md)


class BulletClient:
    """A DIRECT (headless) PyBullet connection; attribute access calls pybullet with this client's id."""

    def __init__(self) -> None:
        self.id = pybullet.connect(pybullet.DIRECT)
        if self.id < 0:
            raise RuntimeError("pybullet.connect(DIRECT) failed")

    def __getattr__(self, name: str):
        attr = getattr(pybullet, name)
        if callable(attr):
            return functools.partial(attr, physicsClientId=self.id)
        return attr

    @property
    def connected(self) -> bool:
        return self.id >= 0 and pybullet.isConnected(physicsClientId=self.id)

    def close(self) -> None:
        if self.connected:
            pybullet.disconnect(physicsClientId=self.id)
        self.id = -1

    def __enter__(self) -> "BulletClient":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def cast_rays(self, starts: np.ndarray, ends: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Cast rays that can only hit objects; returns (hit (n,), hit position (n, 3))."""
        n = len(starts)
        hit = np.zeros(n, dtype=bool)
        position = np.zeros((n, 3))
        for lo in range(0, n, RAY_CHUNK):
            hi = min(lo + RAY_CHUNK, n)
            results = pybullet.rayTestBatch(rayFromPositions=np.ascontiguousarray(starts[lo:hi], dtype=np.float64),
                                            rayToPositions=np.ascontiguousarray(ends[lo:hi], dtype=np.float64),
                                            collisionFilterMask=OBJECT_GROUP, physicsClientId=self.id)
            if len(results) != hi - lo:
                raise RuntimeError(f"rayTestBatch returned {len(results)} results for {hi - lo} rays")
            touched = [(lo + i, r[3]) for i, r in enumerate(results) if r[0] >= 0]  # one pass; most rays miss
            if touched:
                index, where = zip(*touched)
                hit[list(index)] = True
                position[list(index)] = where
        return hit, position
