"""The simulator's per-probe arithmetic around PyBullet as compiled loops (numba).

Each probe step of 64 probes made some forty numpy calls on 64-row arrays (the request mapping, the tool
quaternions, the warm starts, the achieved axes and pose errors, the ray ends and the points), 1-2 us each: a tenth
of an arm step and a third of an ideal one beside the PyBullet calls themselves (docs/benchmarks.md, "Simulator").
Each loop does the numpy code's float64 operations in the same order, so points, entries and directions are the
same to the bit; the angle error may differ in its last bit, as numpy's arccos is its own SIMD routine, not libm's.
`tool_frames` replaces PyBullet's own forward kinematics (a joint reset and getLinkState per probe): it agrees with
it to about 1e-7 (PyBullet returns link orientations as float32 quaternions), not to the bit.
The loops do not check shapes: their callers in hg.sim do.
"""
from __future__ import annotations

import math

import numba
import numpy as np

FIXED, REVOLUTE, PRISMATIC = 0, 1, 2  # the kinds of a chain joint's motion, tool_frames


@numba.njit(cache=True)
def request_frames(requests: np.ndarray, probe_x: float, lo: float, hi: float,
                   tan_max: float) -> tuple[np.ndarray, np.ndarray]:
    """Scene.request_to_probe's mapping of requests (n, 4) to entry points and unit directions (n, 3) each."""
    n = requests.shape[0]
    points, directions = np.empty((n, 3)), np.empty((n, 3))
    half = 0.5 * (hi - lo)
    for i in range(n):
        py, ux = min(max(requests[i, 0], -1.0), 1.0), min(max(requests[i, 1], -1.0), 1.0)
        uy, uz = min(max(requests[i, 2], -1.0), 1.0), min(max(requests[i, 3], -1.0), 1.0)
        points[i, 0], points[i, 1], points[i, 2] = probe_x, lo + (py + 1.0) * half, 0.0
        scale = tan_max * 0.5 * (1.0 - uz) / max(1.0, math.hypot(ux, uy))
        dx, dy = ux * scale, uy * scale
        norm = math.sqrt(dx * dx + dy * dy + 1.0)
        directions[i, 0], directions[i, 1], directions[i, 2] = dx / norm, dy / norm, -1.0 / norm
    return points, directions


@numba.njit(cache=True)
def tool_quaternions(u: np.ndarray) -> np.ndarray:
    """robot.tool_orientations for unit directions u (n, 3): (1 - u_z, 0, u_x, -u_y), normalised."""
    q = np.empty((u.shape[0], 4))
    for i in range(u.shape[0]):
        a, b, c = 1.0 - u[i, 2], u[i, 0], -u[i, 1]
        norm = math.sqrt(a * a + 0.0 + b * b + c * c)
        q[i, 0], q[i, 1], q[i, 2], q[i, 3] = a / norm, 0.0 / norm, b / norm, c / norm
    return q


@numba.njit(cache=True)
def tool_axes(quaternions: np.ndarray) -> np.ndarray:
    """robot.z_axes: the third column of each quaternion's (x, y, z, w) rotation matrix."""
    axes = np.empty((quaternions.shape[0], 3))
    for i in range(quaternions.shape[0]):
        x, y, z, w = quaternions[i, 0], quaternions[i, 1], quaternions[i, 2], quaternions[i, 3]
        axes[i, 0] = 2 * (x * z + w * y)
        axes[i, 1] = 2 * (y * z - w * x)
        axes[i, 2] = 1 - 2 * (x * x + y * y)
    return axes


@numba.njit(cache=True)
def pose_errors(points: np.ndarray, dirs: np.ndarray, tips: np.ndarray, axes: np.ndarray) -> np.ndarray:
    """ProbeArm.pose_error: (n, 2) position error (m) and axis angle error (degrees) of achieved vs requested."""
    error = np.empty((points.shape[0], 2))
    for i in range(points.shape[0]):
        gx, gy, gz = tips[i, 0] - points[i, 0], tips[i, 1] - points[i, 1], tips[i, 2] - points[i, 2]
        error[i, 0] = math.sqrt(gx * gx + gy * gy + gz * gz)
        cosine = axes[i, 0] * dirs[i, 0] + axes[i, 1] * dirs[i, 1] + axes[i, 2] * dirs[i, 2]
        error[i, 1] = math.degrees(math.acos(min(max(cosine, -1.0), 1.0)))
    return error


@numba.njit(cache=True)
def grid_entries(points: np.ndarray, dirs: np.ndarray, origin: np.ndarray, step: np.ndarray, top: np.ndarray,
                 strides: np.ndarray) -> np.ndarray:
    """ReachGrid.nearest: the flat index of the grid entry nearest to each request (entry y, u_x, u_y)."""
    entries = np.zeros(points.shape[0], dtype=np.int64)
    for i in range(points.shape[0]):
        for k, value in enumerate((points[i, 1], dirs[i, 0], dirs[i, 1])):
            entries[i] += int(min(max(np.rint((value - origin[k]) / step[k]), 0.0), top[k])) * strides[k]
    return entries


@numba.njit(cache=True)
def ray_segments(starts: np.ndarray, axes: np.ndarray, length: float,
                 offsets: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Each probe's ray in the world (shifted into its episode's slot) and its end in the episode frame."""
    n = starts.shape[0]
    ends, world_from, world_to = np.empty((n, 3)), np.empty((n, 3)), np.empty((n, 3))
    for i in range(n):
        for j in range(3):
            ends[i, j] = starts[i, j] + length * axes[i, j]
            world_from[i, j] = starts[i, j] + offsets[i, j]
            world_to[i, j] = ends[i, j] + offsets[i, j]
    return ends, world_from, world_to


@numba.njit(cache=True)
def episode_points(hit: np.ndarray, positions: np.ndarray, offsets: np.ndarray, ends: np.ndarray) -> np.ndarray:
    """(n, 4) X, Y, Z, T in the episode frame: the touched point, or the ray's end where nothing was touched."""
    points = np.empty((hit.shape[0], 4))
    for i in range(hit.shape[0]):
        for j in range(3):
            points[i, j] = positions[i, j] - offsets[i, j] if hit[i] else ends[i, j]
        points[i, 3] = 1.0 if hit[i] else 0.0
    return points


@numba.njit(cache=True)
def _compose(a: np.ndarray, b: np.ndarray, out: np.ndarray) -> None:
    """out[:3] = (a @ b)[:3] for rigid transforms (4, 4) whose last row is (0, 0, 0, 1); out must not be a or b."""
    for r in range(3):
        for c in range(4):
            out[r, c] = a[r, 0] * b[0, c] + a[r, 1] * b[1, c] + a[r, 2] * b[2, c] + (a[r, 3] if c == 3 else 0.0)


@numba.njit(cache=True)
def tool_frames(qs: np.ndarray, origins: np.ndarray, kinds: np.ndarray, axes: np.ndarray,
                columns: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Forward kinematics of the URDF chain from the base to the tool link for joint positions qs (n, J): the tool
    link's position and +z axis (n, 3) each. Joint k of the chain: its origin (4, 4) in the parent link's frame, its
    kind, unit axis (3,) in its own frame and column of qs (-1 when fixed). A few 4x4 products per joint, where
    PyBullet's resetJointStatesMultiDof and getLinkState cost some 5 us a probe."""
    n = qs.shape[0]
    tips, probing = np.empty((n, 3)), np.empty((n, 3))
    frame, scratch, motion = np.eye(4), np.eye(4), np.eye(4)
    for i in range(n):
        frame[:] = np.eye(4)
        for k in range(kinds.shape[0]):
            _compose(frame, origins[k], scratch)
            frame[:] = scratch
            if kinds[k] == FIXED:
                continue
            q, x, y, z = qs[i, columns[k]], axes[k, 0], axes[k, 1], axes[k, 2]
            motion[:] = np.eye(4)
            if kinds[k] == REVOLUTE:  # Rodrigues' rotation by q about the axis
                c, s = math.cos(q), math.sin(q)
                t = 1.0 - c
                motion[0, 0], motion[0, 1], motion[0, 2] = c + x * x * t, x * y * t - z * s, x * z * t + y * s
                motion[1, 0], motion[1, 1], motion[1, 2] = y * x * t + z * s, c + y * y * t, y * z * t - x * s
                motion[2, 0], motion[2, 1], motion[2, 2] = z * x * t - y * s, z * y * t + x * s, c + z * z * t
            else:  # a translation by q along the axis
                motion[0, 3], motion[1, 3], motion[2, 3] = x * q, y * q, z * q
            _compose(frame, motion, scratch)
            frame[:] = scratch
        tips[i] = frame[:3, 3]
        probing[i] = frame[:3, 2]
    return tips, probing
