"""Sparse point clouds of posed objects, with noise points: the input of the paper's PointNet / DGCNN baselines.

The baselines see what a perfect scanner would give, P points sampled uniformly (by area) from the whole
surface of the object at its pose; a noise rate replaces that share of them with points of the pose volume,
the space any object of the set can occupy, as a missed or false contact would report a point off the object.
"""
from __future__ import annotations

import numpy as np

from hg.sim.objects import ObjectSet
from hg.sim.poses import rotation_matrices
from hg.sim.scene import Scene


def pose_volume(scene: Scene, objects: ObjectSet) -> tuple[np.ndarray, np.ndarray]:
    """Lower and upper corners of the box holding every object at every pose of the scene (below the ground)."""
    radius = max(float(np.linalg.norm(mesh.vertices, axis=1).max()) for mesh in objects.meshes)
    low = np.array([scene.object_x[0], scene.object_y[0], scene.object_z[0]]) - radius
    high = np.array([scene.object_x[1], scene.object_y[1], scene.object_z[1]]) + radius
    high[2] = min(high[2], 0.0)
    return low, high


def surface_points(objects: ObjectSet, labels: np.ndarray, poses: np.ndarray, n_points: int,
                   rng: np.random.Generator) -> np.ndarray:
    """(B, n_points, 3): points uniform over the surface of object labels[i] placed at poses[i]."""
    labels, poses = np.asarray(labels), np.asarray(poses, dtype=np.float64)
    points = np.empty((len(labels), n_points, 3))
    rotations = rotation_matrices(poses[:, 3:])
    for k, mesh in enumerate(objects.meshes):
        episodes = np.flatnonzero(labels == k)
        if len(episodes) == 0:
            continue
        triangles = mesh.triangles  # (F, 3, 3)
        faces = rng.choice(len(triangles), size=(len(episodes), n_points), p=mesh.area_faces / mesh.area_faces.sum())
        a, b = rng.random((2, len(episodes), n_points, 1))
        flip = a + b > 1  # fold the unit square onto the triangle: uniform barycentric coordinates
        a, b = np.where(flip, 1 - a, a), np.where(flip, 1 - b, b)
        t = triangles[faces]
        local = t[..., 0, :] + a * (t[..., 1, :] - t[..., 0, :]) + b * (t[..., 2, :] - t[..., 0, :])
        points[episodes] = np.einsum("bij,bpj->bpi", rotations[episodes], local) + poses[episodes, None, :3]
    return points


def noisy_point_clouds(scene: Scene, objects: ObjectSet, labels: np.ndarray, poses: np.ndarray, n_points: int,
                       noise_rate: float, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Surface points with round(noise_rate * n_points) of each cloud, at random places in its order, replaced
    by uniform points of the pose volume. Returns the clouds (B, n_points, 3) and the noise mask (B, n_points)."""
    if not 0.0 <= noise_rate <= 1.0:
        raise ValueError(f"noise_rate={noise_rate}: must be in [0, 1]")
    clouds = surface_points(objects, labels, poses, n_points, rng)
    n_noise = int(round(noise_rate * n_points))
    mask = np.zeros(clouds.shape[:2], dtype=bool)
    if n_noise:
        slots = np.argsort(rng.random(mask.shape), axis=1)[:, :n_noise]
        np.put_along_axis(mask, slots, True, axis=1)
        low, high = pose_volume(scene, objects)
        clouds[mask] = low + rng.random((int(mask.sum()), 3)) * (high - low)
    return clouds, mask
