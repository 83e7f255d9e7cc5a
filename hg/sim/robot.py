"""Any URDF arm as a probe carrier: joints and links found by name, IK warm-started from a cached reach map.

PyBullet's IK from an arbitrary previous pose misses many requests; with restarts it is slow. So a reach map
(joint solutions over a grid of the request space, found once with restarts and cached on disk, keyed by the
URDF's hash) gives every probe a warm start, and one IK call per probe suffices.
"""
from __future__ import annotations

import functools
import hashlib
import io
import math
import os
import xml.etree.ElementTree as ET
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pybullet

from hg.atomic import write_atomic
from hg.sim.client import ROBOT_GROUP, BulletClient
from hg.sim.kernels import (FIXED, PRISMATIC, REVOLUTE, grid_entries, pose_errors, tool_axes, tool_frames,
                            tool_quaternions)
from hg.sim.scene import Scene

TOOL_LINK = "probe_tip"
DEFAULT_URDF = Path(__file__).resolve().parents[2] / "urdf" / "hg_probe_arm.urdf"
REACH_MAP_VERSION = 3  # 2: pose errors from the chain's forward kinematics, not float32 link quaternions; 3: joints
# that turn without limit wrapped into one turn, not clipped
POSITION_TOLERANCE = 0.005  # m: a probe counts as achieved within 5 mm ...
ANGLE_TOLERANCE_DEG = 3.0  # ... and 3 degrees


def achieved(pose_error: np.ndarray) -> np.ndarray:
    """Which probes reached their request within the tolerances, from `ProbeArm.pose_error` rows."""
    return (pose_error[..., 0] <= POSITION_TOLERANCE) & (pose_error[..., 1] <= ANGLE_TOLERANCE_DEG)


def cache_dir() -> Path:
    return Path(os.environ.get("HG_CACHE_DIR", Path.home() / ".cache" / "haptic-glance"))


def tool_orientations(directions: np.ndarray) -> np.ndarray:
    """Quaternions (x, y, z, w) turning the tool +z onto each direction u with one fixed roll convention.

    Straight down is a half turn about x; a tilted u adds the smallest rotation from straight down to u,
    normalise((0, 0, -1) x u, 1 - u_z). Their product, written out, is (1 - u_z, 0, u_x, -u_y) normalised.
    """
    return tool_quaternions(np.ascontiguousarray(directions, dtype=np.float64).reshape(-1, 3))


def z_axes(quaternions: np.ndarray) -> np.ndarray:
    """Third column of the rotation matrix of each quaternion (x, y, z, w): the tool's probing axis."""
    return tool_axes(np.ascontiguousarray(quaternions, dtype=np.float64).reshape(-1, 4))


def load_robot(client: BulletClient, urdf: str | Path, tool_link: str = TOOL_LINK) -> tuple[int, int]:
    """Load a URDF with a fixed base; return (body id, tool link index). Errors name the file and the fault."""
    path = Path(urdf)
    if not path.is_file():
        raise FileNotFoundError(f"robot URDF {path}: file not found")
    try:
        root = ET.parse(path).getroot()
    except ET.ParseError as exc:
        raise ValueError(f"robot URDF {path}: malformed XML ({exc})") from exc
    try:
        body = client.loadURDF(str(path), useFixedBase=True, flags=pybullet.URDF_USE_INERTIA_FROM_FILE)
    except pybullet.error as exc:
        from hg.sim.urdf_tools import resolve_mesh  # here: urdf_tools builds on this module
        for mesh in root.iter("mesh"):  # PyBullet only says it failed: name the file it could not find
            resolve_mesh(mesh.get("filename", ""), path)
        raise ValueError(f"robot URDF {path}: PyBullet cannot load it ({exc})") from exc
    links = {client.getJointInfo(body, j)[12].decode(): j for j in range(client.getNumJoints(body))}
    if tool_link not in links:
        raise ValueError(f"robot URDF {path}: no link named '{tool_link}' (links: {', '.join(links)})")
    for link in [-1, *links.values()]:
        client.setCollisionFilterGroupMask(body, link, ROBOT_GROUP, 0)
    return body, links[tool_link]


JOINT_KINDS = {"fixed": FIXED, "revolute": REVOLUTE, "continuous": REVOLUTE, "prismatic": PRISMATIC}


def kinematic_chain(urdf: Path, tool_link: str, joint_names: list[str]) -> tuple[np.ndarray, ...]:
    """The URDF's joints from the base down to the tool link as kernels.tool_frames takes them: their origins (K, 4,
    4), kinds, unit axes (K, 3) and each movable joint's column among `joint_names` (the order of PyBullet's IK
    solution; -1 for a fixed joint)."""
    from hg.sim.urdf_tools import chain_joints, load_urdf  # here: urdf_tools builds on this module
    chain = chain_joints(load_urdf(urdf).robot, tool_link)
    unknown = [f"'{j.name}' ({j.type})" for j in chain if j.type not in JOINT_KINDS]
    if unknown:
        raise ValueError(f"robot URDF {urdf}: the chain to '{tool_link}' has joints an arm cannot have: "
                         f"{', '.join(unknown)}")
    unmoved = [j.name for j in chain if j.type != "fixed" and j.name not in joint_names]
    if unmoved:
        raise ValueError(f"robot URDF {urdf}: chain joints {unmoved} are not among the joints PyBullet moves "
                         f"({joint_names})")
    origins = np.array([np.eye(4) if j.origin is None else j.origin for j in chain], dtype=np.float64)
    axes = np.array([(1.0, 0.0, 0.0) if j.axis is None else j.axis for j in chain], dtype=np.float64)  # URDF default
    axes /= np.maximum(np.linalg.norm(axes, axis=1, keepdims=True), 1e-12)
    kinds = np.array([JOINT_KINDS[j.type] for j in chain], dtype=np.int64)
    columns = np.array([joint_names.index(j.name) if j.type != "fixed" else -1 for j in chain], dtype=np.int64)
    return origins.reshape(-1, 4, 4), kinds, axes.reshape(-1, 3), columns


@dataclass(frozen=True)
class ReachGrid:
    """Grid of the request space: entry y on the probe line x the horizontal components of u."""

    n_y: int = 17
    n_dir: int = 9

    def axes(self, scene: Scene) -> tuple[np.ndarray, np.ndarray]:
        s = math.sin(math.radians(scene.max_tilt_deg))
        return np.linspace(*scene.probe_y, self.n_y), np.linspace(-s, s, self.n_dir)

    def targets(self, scene: Scene) -> tuple[np.ndarray, np.ndarray]:
        """Entry points and directions of every grid entry; directions beyond the tilt limit are clamped."""
        ys, hs = self.axes(scene)
        gy, gx, gz = np.meshgrid(ys, hs, hs, indexing="ij")
        lean = np.stack([gx.ravel(), gz.ravel()], 1)
        s = math.sin(math.radians(scene.max_tilt_deg))
        norm = np.linalg.norm(lean, axis=1, keepdims=True)
        lean = np.where(norm > s, lean * s / np.maximum(norm, 1e-12), lean)
        dirs = np.column_stack([lean, -np.sqrt(1.0 - (lean ** 2).sum(1))])
        points = np.column_stack([np.full(gy.size, scene.probe_x), gy.ravel(), np.zeros(gy.size)])
        return points, dirs

    def nearest(self, scene: Scene, points: np.ndarray, dirs: np.ndarray) -> np.ndarray:
        """Flat index of the grid entry nearest to each request (entry y, u_x, u_y)."""
        return grid_entries(points, dirs, *self._frame(scene))

    @functools.lru_cache(maxsize=8)
    def _frame(self, scene: Scene) -> tuple[np.ndarray, ...]:
        """Origin, spacing, last index and flat strides of the grid: computed once, `nearest` runs every probe."""
        ys, hs = self.axes(scene)
        origin = np.array([ys[0], hs[0], hs[0]])
        counts = np.array([self.n_y, self.n_dir, self.n_dir])
        step = np.maximum((np.array([ys[-1], hs[-1], hs[-1]]) - origin) / np.maximum(counts - 1, 1), 1e-12)
        return origin, step, counts - 1, np.array([self.n_dir * self.n_dir, self.n_dir, 1])


class ProbeArm:
    """Puts the tool link at P along u with one IK call warm-started from the reach map."""

    def __init__(self, client: BulletClient, urdf: str | Path, scene: Scene, tool_link: str = TOOL_LINK,
                 grid: ReachGrid = ReachGrid(), ik_iterations: int = 20, ik_damping: float = 1e-3,
                 seed: int = 0) -> None:
        self.client, self.scene, self.grid, self.urdf = client, scene, grid, Path(urdf)
        self.body, self.tool = load_robot(client, urdf, tool_link)
        info = [client.getJointInfo(self.body, j) for j in range(client.getNumJoints(self.body))]
        self.joints = [i[0] for i in info if i[2] in (pybullet.JOINT_REVOLUTE, pybullet.JOINT_PRISMATIC)]
        self.joint_names = [info[j][1].decode() for j in self.joints]
        lower = np.array([info[j][8] for j in self.joints])
        upper = np.array([info[j][9] for j in self.joints])
        unlimited = lower >= upper  # URDF continuous joints or missing limits
        self.lower = np.where(unlimited, -2 * math.pi, lower)
        self.upper = np.where(unlimited, 2 * math.pi, upper)
        # a joint that turns without limit is wrapped into one turn, which keeps its pose; clipping would move it
        self.wraps = unlimited & np.array([info[j][2] == pybullet.JOINT_REVOLUTE for j in self.joints], dtype=bool)
        self.ik_iterations = ik_iterations
        self.damping = [ik_damping] * len(self.joints)  # PyBullet's default damping converges slowly
        self.chain = kinematic_chain(self.urdf, tool_link, self.joint_names)
        self._check_kinematics()
        self.grid_targets = grid.targets(scene)
        self._neighbour_cache: dict[tuple[int, int], np.ndarray] = {}
        self.key = self._cache_key(tool_link)
        self.map_q, self.map_error = self._reach_map(seed)

    # -- poses --------------------------------------------------------------------------------------
    def set_joints(self, q: np.ndarray) -> None:
        self.client.resetJointStatesMultiDof(self.body, self.joints, [[float(v)] for v in q])

    def place(self, points: np.ndarray, orientations: np.ndarray, starts: np.ndarray,
              iterations: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """One IK call per target from its warm start; solutions outside the joint limits are clipped into them
        (wrapped into [-pi, pi) for a joint that turns without limit).

        Returns joint positions, achieved tool positions and probing axes (+z of the URDF tool link frame), the
        poses from the URDF chain's forward kinematics (checked against PyBullet's when the arm is built), so the
        probe's hot path is one PyBullet call per target. PyBullet's IK reads its start from `currentPositions`
        alone, not from the arm's joints, which stay where they were.
        """
        cid, body, tool, damping = self.client.id, self.body, self.tool, self.damping
        ik = pybullet.calculateInverseKinematics
        flat = []
        for point, orientation, start in zip(points.tolist(), orientations.tolist(), starts.tolist()):
            flat += ik(body, tool, point, orientation, currentPositions=start, jointDamping=damping,
                       maxNumIterations=iterations, residualThreshold=1e-6, physicsClientId=cid)
        qs = np.array(flat).reshape(len(points), len(self.joints))
        if self.wraps.any():  # into [-pi, pi), inside the +-2 pi bounds the clip then leaves alone
            qs[:, self.wraps] = np.remainder(qs[:, self.wraps] + math.pi, 2 * math.pi) - math.pi
        qs = np.clip(qs, self.lower, self.upper, out=qs)
        tips, axes = tool_frames(qs, *self.chain)
        return qs, tips, axes

    def _check_kinematics(self, samples: int = 8) -> None:
        """The chain's forward kinematics against PyBullet's at random joint positions: a URDF the chain reads
        otherwise than PyBullet does is refused here, not found later in the probes."""
        low, high = np.maximum(self.lower, -math.pi), np.minimum(self.upper, math.pi)
        qs = np.random.default_rng(0).uniform(low, high, (samples, len(self.joints)))
        tips, axes = tool_frames(qs, *self.chain)
        for q, tip, axis in zip(qs, tips, axes):
            self.set_joints(q)
            state = self.client.getLinkState(self.body, self.tool, computeForwardKinematics=True)
            gap = max(np.abs(tip - state[4]).max(), np.abs(axis - z_axes(np.array(state[5]))[0]).max())
            if gap > 1e-5:
                raise ValueError(f"robot URDF {self.urdf}: the tool link's pose from the URDF's joint chain is "
                                 f"{gap:.2g} off PyBullet's at joint positions {np.round(q, 3).tolist()}")

    def reach(self, points: np.ndarray, dirs: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Solve the tool's pose for each (P, u); return achieved tip positions and +z axes (n, 3) each, and their
        pose errors (n, 2) as `pose_error` gives them. The arm is left standing at the last one (for pictures)."""
        orients = tool_orientations(dirs)
        starts = self.map_q[self.grid.nearest(self.scene, points, dirs)]
        qs, tips, axes = self.place(points, orients, starts, self.ik_iterations)
        errors = self.pose_error(points, dirs, tips, axes)
        for i in np.flatnonzero(~achieved(errors)):
            qs[i], tips[i], axes[i] = self._retry(points[i], dirs[i], orients[i])
            errors[i] = self.pose_error(points[i:i + 1], dirs[i:i + 1], tips[i:i + 1], axes[i:i + 1])[0]
        if len(qs):
            self.set_joints(qs[-1])
        return tips, axes, errors

    def _retry(self, point: np.ndarray, direction: np.ndarray, orientation: np.ndarray,
               tries: int = 6) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Rare slow path: warm starts from the reach-map entries next to the nearest one; the first pose within
        the tolerances, or else the closest. Returns its joints, tip and axis."""
        best = None
        for entry in self._neighbours(int(self.grid.nearest(self.scene, point[None], direction[None])[0]), tries):
            q, tip, axis = self.place(point[None], orientation[None], self.map_q[entry][None], self.ik_iterations)
            err = self.pose_error(point[None], direction[None], tip, axis)[0]
            if achieved(err):
                return q[0], tip[0], axis[0]
            if best is None or err[0] + 1e-3 * err[1] < best[0]:
                best = (err[0] + 1e-3 * err[1], q[0], tip[0], axis[0])
        return best[1:]

    def _neighbours(self, entry: int, count: int) -> np.ndarray:
        """The `count` grid entries closest to `entry` (itself excluded), in request space: cached per arm, as
        the same hard corners of the request space come back."""
        if (entry, count) not in self._neighbour_cache:
            grid_points, grid_dirs = self.grid_targets
            distance = np.abs(grid_points[:, 1] - grid_points[entry, 1]) + np.abs(grid_dirs - grid_dirs[entry]).sum(1)
            distance[entry] = np.inf
            self._neighbour_cache[entry, count] = np.argsort(distance, kind="stable")[:count]
        return self._neighbour_cache[entry, count]

    # -- reach map ----------------------------------------------------------------------------------
    def _cache_key(self, tool_link: str) -> str:
        s = self.scene
        text = f"{REACH_MAP_VERSION}|{tool_link}|{s.probe_x}|{s.probe_y}|{s.max_tilt_deg}|{self.grid}|"
        return hashlib.sha256(text.encode() + self.urdf.read_bytes()).hexdigest()[:20]

    def _reach_map(self, seed: int) -> tuple[np.ndarray, np.ndarray]:
        path = cache_dir() / "reach" / f"{self.urdf.stem}-{self.key}.npz"
        if path.is_file():
            with np.load(path) as data:
                return data["q"], data["error"]
        q, error = self._build_reach_map(seed)
        buffer = io.BytesIO()
        np.savez(buffer, q=q, error=error)
        write_atomic(path, buffer.getvalue())
        return q, error

    def pose_error(self, points: np.ndarray, dirs: np.ndarray, tips: np.ndarray, axes: np.ndarray) -> np.ndarray:
        """(n, 2): position error in metres and angle error in degrees of achieved vs requested poses."""
        shapes = {name: np.shape(a) for name, a in (("points", points), ("dirs", dirs), ("tips", tips), ("axes", axes))}
        if len(set(shapes.values())) > 1 or np.ndim(points) != 2 or np.shape(points)[1] != 3:
            raise ValueError(f"pose_error: expected four (n, 3) arrays, got shapes {shapes}")
        return pose_errors(points, dirs, tips, axes)

    def _build_reach_map(self, seed: int, restarts: int = 12) -> tuple[np.ndarray, np.ndarray]:
        """Best IK solution per grid entry: warm starts from the neighbour, the middle pose, random poses."""
        rng = np.random.default_rng(seed)
        points, dirs = self.grid_targets
        orients = tool_orientations(dirs)
        middle = np.clip((self.lower + self.upper) / 2, -math.pi, math.pi)
        q_map = np.zeros((len(points), len(self.joints)))
        err_map = np.zeros((len(points), 2))
        previous = middle
        for i in range(len(points)):
            best, best_err = None, None
            starts = [previous, middle] + [rng.uniform(np.maximum(self.lower, -math.pi),
                                                       np.minimum(self.upper, math.pi)) for _ in range(restarts)]
            for start in starts:
                q, tip, axis = self.place(points[i:i + 1], orients[i:i + 1], start[None], 200)
                err = self.pose_error(points[i:i + 1], dirs[i:i + 1], tip, axis)[0]
                if best_err is None or err[0] / POSITION_TOLERANCE + err[1] / ANGLE_TOLERANCE_DEG < \
                        best_err[0] / POSITION_TOLERANCE + best_err[1] / ANGLE_TOLERANCE_DEG:
                    best, best_err = q[0], err
                if err[0] < 0.2 * POSITION_TOLERANCE and err[1] < 0.2 * ANGLE_TOLERANCE_DEG:
                    break
            q_map[i], err_map[i] = best, best_err
            previous = best
        return q_map, err_map
