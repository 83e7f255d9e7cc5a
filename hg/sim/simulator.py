"""Batched tactile probing: B episodes side by side in one PyBullet world, one ray batch per probe step.

Episode i owns a slot, a patch of the world far from the others, holding its object at its pose. The arm
stands at slot 0; in arm mode IK puts `probe_tip` at P along u and each episode's ray starts from the achieved
tip pose shifted into its slot, so one arm serves all episodes and one `rayTestBatch` probes them all.
Points are returned in the episode's own frame.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pybullet
import trimesh

from hg.sim.client import GROUND_GROUP, OBJECT_GROUP, BulletClient
from hg.sim.kernels import episode_points, ray_segments
from hg.sim.objects import ObjectSet, load_object_set
from hg.sim.poses import check_below_ground, quaternions
from hg.sim.robot import DEFAULT_URDF, TOOL_LINK, ProbeArm
from hg.sim.scene import Scene

MODES = ("arm", "ideal")
SLOT_SPACING = 4.0  # m; a probe reaches at most U_len + the arm's tip error from its entry point
SLOTS_PER_ROW = 32
PARK_DEPTH = -100.0  # objects not in use wait here, far below any ray


_MESH_LISTS: dict[bytes, tuple[list, list]] = {}


def mesh_lists(mesh: trimesh.Trimesh) -> tuple[list, list]:
    """Vertices and flat indices as PyBullet takes them, the same list objects for the same mesh every time:
    pybullet 3.2.7's createCollisionShape/createVisualShape keep references to the lists they get, never freed."""
    key = mesh.vertices.tobytes() + b"|" + mesh.faces.tobytes()
    if key not in _MESH_LISTS:
        _MESH_LISTS[key] = (mesh.vertices.tolist(), mesh.faces.ravel().tolist())
    return _MESH_LISTS[key]


@dataclass(frozen=True)
class SensorNoise:
    """Tactile sensor faults, off by default: position noise (m), missed and false contacts (probabilities)."""

    position_std: float = 0.0
    miss_prob: float = 0.0
    false_contact_prob: float = 0.0

    def __post_init__(self) -> None:
        if not self.position_std >= 0:
            raise ValueError(f"noise.position_std={self.position_std}: must be >= 0")
        for name in ("miss_prob", "false_contact_prob"):
            if not 0.0 <= getattr(self, name) <= 1.0:
                raise ValueError(f"noise.{name}={getattr(self, name)}: must be a probability in [0, 1]")


NO_NOISE = SensorNoise()


@dataclass(frozen=True)
class ProbeResult:
    """One probe step for n episodes."""

    points: np.ndarray  # (n, 4): X, Y, Z, T in the episode frame; T=0 gives the ray's end point
    entry: np.ndarray  # (n, 3) requested entry point P
    direction: np.ndarray  # (n, 3) requested unit direction u
    pose_error: np.ndarray  # (n, 2) achieved-vs-requested tip position (m) and axis angle (deg); 0 in ideal mode
    clean_points: np.ndarray  # (n, 4) what a fault-free sensor reported (points itself without noise); for analysis


class ProbeSimulator:
    """The simulator core shared by training, evaluation, benchmarks and the gymnasium environment."""

    def __init__(self, objects: str | Path | ObjectSet = "hg4", batch_size: int = 64, scene: Scene = Scene(),
                 mode: str = "arm", robot: str | Path = DEFAULT_URDF, tool_link: str = TOOL_LINK,
                 noise: SensorNoise = NO_NOISE, seed: int = 0, visuals: bool = False) -> None:
        if mode not in MODES:
            raise ValueError(f"mode={mode!r}: expected one of {MODES}")
        if batch_size < 1:
            raise ValueError(f"batch_size={batch_size}: must be >= 1")
        self.objects = objects if isinstance(objects, ObjectSet) else load_object_set(objects)
        check_below_ground(scene, self.objects)
        self.scene, self.mode, self.noise, self.batch_size = scene, mode, noise, batch_size
        self.visuals = visuals  # object visual shapes, for pictures only: PyBullet never frees them
        self.rng = np.random.default_rng(seed)
        self.client = BulletClient()
        try:
            self.arm = ProbeArm(self.client, robot, scene, tool_link, seed=seed) if mode == "arm" else None
            self._build_world()
        except BaseException:
            self.client.close()
            raise
        self.labels = np.zeros(0, dtype=np.int64)
        self.poses = np.zeros((0, 6))

    @property
    def classes(self) -> tuple[str, ...]:
        return self.objects.names

    def _build_world(self) -> None:
        """Each object's concave shape is created once and shared by one static body per slot."""
        c = self.client
        slots = np.arange(self.batch_size)
        self.offsets = np.column_stack([(slots % SLOTS_PER_ROW) * SLOT_SPACING,
                                        (slots // SLOTS_PER_ROW) * SLOT_SPACING, np.zeros(len(slots))])
        self.parking = self.offsets + (0.0, 0.0, PARK_DEPTH)  # where each slot's objects wait when not in use
        ground_shape = c.createCollisionShape(c.GEOM_PLANE)
        soil = c.createVisualShape(c.GEOM_BOX, halfExtents=[1.0, 1.0, 0.001], rgbaColor=[0.55, 0.45, 0.3, 0.4])
        ground = c.createMultiBody(0, ground_shape, soil)
        c.setCollisionFilterGroupMask(ground, -1, GROUND_GROUP, 0)
        self.ground = ground
        self.bodies = np.zeros((len(self.objects), self.batch_size), dtype=np.int64)
        for k, mesh in enumerate(self.objects.meshes):
            vertices, indices = mesh_lists(mesh)
            shape = c.createCollisionShape(c.GEOM_MESH, vertices=vertices, indices=indices,
                                           flags=c.GEOM_FORCE_CONCAVE_TRIMESH)
            visual = c.createVisualShape(c.GEOM_MESH, vertices=vertices, indices=indices,
                                         rgbaColor=[0.2, 0.45, 0.8, 1.0]) if self.visuals else -1
            for i in slots:
                body = c.createMultiBody(0, shape, visual if i == 0 else -1, self.parking[i].tolist())
                c.setCollisionFilterGroupMask(body, -1, OBJECT_GROUP, OBJECT_GROUP)
                self.bodies[k, i] = body
        self.active = np.full(self.batch_size, -1, dtype=np.int64)


    def reset(self, labels: np.ndarray, poses: np.ndarray, seed: int | None = None) -> None:
        """Place episode i's object (class labels[i]) at poses[i] = (X, Y, Z, Rx, Ry, Rz in degrees).

        A seed restarts the sensor-noise stream, so a batch's probes depend on that batch alone (resume, eval).
        """
        labels = np.asarray(labels, dtype=np.int64).reshape(-1)
        poses = np.asarray(poses, dtype=np.float64)
        n = len(labels)
        if not 1 <= n <= self.batch_size:
            raise ValueError(f"labels: {n} episodes, but this simulator holds 1 to {self.batch_size}")
        if poses.shape != (n, 6) or not np.isfinite(poses).all():
            raise ValueError(f"poses: expected {n} finite rows (X, Y, Z, Rx, Ry, Rz), got shape {poses.shape}")
        if labels.min() < 0 or labels.max() >= len(self.objects):
            raise ValueError(f"labels: class indices must be in [0, {len(self.objects)}), got {labels.min()}..{labels.max()}")
        cid, move = self.client.id, pybullet.resetBasePositionAndOrientation
        bodies, moves = self.placement(labels, poses)
        for body, position, orientation in moves:
            move(body, position, orientation, physicsClientId=cid)
        self.active, self.labels, self.poses = bodies, labels, poses
        if seed is not None:
            self.rng = np.random.default_rng(seed)

    def placement(self, labels: np.ndarray, poses: np.ndarray) -> tuple[np.ndarray, list[tuple]]:
        """The body of each slot after a reset to (labels, poses), and the base moves that get there: objects
        leaving a slot go back to their parking place. Separate from `reset` so the benchmark can issue the
        very same PyBullet calls."""
        n = len(labels)
        bodies = np.full(self.batch_size, -1, dtype=np.int64)
        bodies[:n] = self.bodies[labels, np.arange(n)]
        leaving = np.flatnonzero((self.active >= 0) & (self.active != bodies))
        moves = list(zip(self.active[leaving].tolist(), self.parking[leaving].tolist(), [(0, 0, 0, 1)] * len(leaving)))
        moves += zip(bodies[:n].tolist(), (self.offsets[:n] + poses[:, :3]).tolist(),
                     quaternions(poses[:, 3:]).tolist())
        return bodies, moves

    def probe(self, requests: np.ndarray, faults: np.ndarray | None = None) -> ProbeResult:
        """Probe every episode once; requests (n, 4) in [-1, 1], one row per episode of the last reset. faults
        (n, 2) in [0, 1): the sensor's contact faults as given uniforms instead of its own draws (column 0 below
        miss_prob corrupts a touch, below false_contact_prob a miss; column 1 is where along the ray a false touch
        lies), so that a teacher's episodes replay the faults its planner read (hg.rl.ImitateTeacher under noise)."""
        n = len(self.labels)
        requests = np.asarray(requests, dtype=np.float64)
        if n == 0:
            raise RuntimeError("probe() before reset(): no objects are placed")
        if requests.shape != (n, 4):
            raise ValueError(f"requests: expected shape ({n}, 4) for the {n} episodes of the last reset, got {requests.shape}")
        if faults is not None and (np.shape(faults) != (n, 2) or not ((faults >= 0) & (faults < 1)).all()):
            raise ValueError(f"faults: expected shape ({n}, 2) with values in [0, 1), got {np.shape(faults)}")
        entry, direction = self.scene.request_to_probe(requests)
        if self.arm is None:
            start, axis, error = entry, direction, np.zeros((n, 2))
        else:
            start, axis, error = self.arm.reach(entry, direction)
        offset = self.offsets[:n]
        end, ray_from, ray_to = ray_segments(start, axis, self.scene.probe_length, offset)
        hit, position = self.client.cast_rays(ray_from, ray_to)
        points = episode_points(hit, position, offset, end)
        if self.noise == NO_NOISE:  # the common case, at every probe: nothing to corrupt, nothing to copy
            return ProbeResult(points, entry, direction, error, points)
        clean = points.copy()
        self._apply_noise(points, start, end, hit, faults)
        return ProbeResult(points, entry, direction, error, clean)

    def _apply_noise(self, points: np.ndarray, start: np.ndarray, end: np.ndarray, hit: np.ndarray,
                     faults: np.ndarray | None = None) -> None:
        """Sensor faults in place: a missed contact reports the ray's end, a false one a point along the ray
        (drawn here, or decided by the given `faults` uniforms, probe())."""
        noise, n = self.noise, len(points)
        if noise.position_std > 0:
            points[hit, :3] += self.rng.normal(0.0, noise.position_std, (int(hit.sum()), 3))
        if noise.miss_prob > 0:
            missed = hit & ((self.rng.random(n) if faults is None else faults[:, 0]) < noise.miss_prob)
            points[missed] = np.column_stack([end[missed], np.zeros(int(missed.sum()))])
        if noise.false_contact_prob > 0:
            false = ~hit & ((self.rng.random(n) if faults is None else faults[:, 0]) < noise.false_contact_prob)
            along = self.rng.random((int(false.sum()), 1)) if faults is None else faults[false, 1:]
            points[false] = np.column_stack([start[false] + along * (end[false] - start[false]), np.ones(int(false.sum()))])

    def close(self) -> None:
        self.client.close()

    def __enter__(self) -> "ProbeSimulator":
        return self

    def __exit__(self, *exc) -> None:
        self.close()
