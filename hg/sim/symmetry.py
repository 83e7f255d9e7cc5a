"""Object symmetries found from the meshes: the turns about the vertical axis and the vertical mirror planes.

Only these matter for the scene's poses (small Rx/Ry tilts, any heading Rz): a half turn about a horizontal axis
turns an object upside down, which no allowed pose reaches. A candidate map is a symmetry when the symmetric
Chamfer distance between the surface and its image (sampled points, a fixed seed) is below `tolerance` times the
bounding-box diagonal. Every symmetry of a surface fixes its area centroid, so the axis and planes pass through it.
"""
from __future__ import annotations

import hashlib

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import trimesh
from scipy.spatial import cKDTree

from hg.sim.objects import ObjectSet

TURN_ORDERS = tuple(range(2, 13))  # turns of 360/n degrees tested
GENERIC_TURNS_DEG = (7.0, 23.5, 41.0, 97.0, 151.0)  # only a shape with hundreds of equal sectors survives all these
# Mean Chamfer distance, as a share of the bounding-box diagonal. Sampling alone leaves about 0.003; the nearly
# bilateral duck and teddy of data/objects/pyb10 sit near 0.008-0.010 and count as mirror-symmetric, the chiral
# blobs there are above 0.023.
TOLERANCE = 0.015


@dataclass(frozen=True)
class Symmetry:
    """How one object's pose can change without changing the object: turns about the vertical axis through
    `centre` and a vertical mirror plane through it. The errors are the relative Chamfer distances behind the
    verdicts (of the turn by 360/turn_order, or the half turn when turn_order is 1; of the best mirror plane)."""

    turn_order: int | None  # n: unchanged by a turn of 360/n degrees; None: by any angle; 1: by none
    mirror: bool  # some vertical plane through `centre` maps the object onto itself: it is its own mirror image
    mirror_deg: float | None  # that plane's normal, in degrees from the object's x axis (0: x -> -x, 90: y -> -y)
    centre: tuple[float, float]  # (x, y) of the vertical axis in the object's frame (m)
    turn_error: float
    mirror_error: float

    @property
    def turn_deg(self) -> float:
        """The smallest turn that leaves the object unchanged: 360 / turn_order, 0 for any angle, 360 for none."""
        return 0.0 if self.turn_order is None else 360.0 / self.turn_order

    def describe(self) -> str:
        """One line for logs and READMEs."""
        turns = "any turn" if self.turn_order is None else (
            "no turn" if self.turn_order == 1 else f"turns of {self.turn_deg:g} deg")
        mirror = f"mirror plane normal at {self.mirror_deg:.1f} deg" if self.mirror else "chiral (no mirror plane)"
        return f"{turns}, {mirror} (errors: turn {self.turn_error:.4f}, mirror {self.mirror_error:.4f})"


def turn_matrix(deg: float) -> np.ndarray:
    """Rotation by `deg` about the vertical axis."""
    c, s = math.cos(math.radians(deg)), math.sin(math.radians(deg))
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def mirror_matrix(normal_deg: float) -> np.ndarray:
    """Reflection across the vertical plane whose normal is at `normal_deg` from x (0: x -> -x)."""
    n = np.array([math.cos(math.radians(normal_deg)), math.sin(math.radians(normal_deg)), 0.0])
    return np.eye(3) - 2.0 * np.outer(n, n)


class _Surface:
    """A mesh's surface as a sparse probe sample and a dense reference sample around its area centroid."""

    def __init__(self, mesh: trimesh.Trimesh, points: int, seed: int) -> None:
        self.centre = np.asarray(mesh.triangles_center.T @ mesh.area_faces / mesh.area)
        self.size = float(np.linalg.norm(mesh.extents))
        corners = mesh.triangles - self.centre  # exact second moment of the surface: A/12 (sum v v^T + s s^T)
        total = corners.sum(axis=1)
        self.moment = np.einsum("f,fvi,fvj->ij", mesh.area_faces, corners, corners) + np.einsum(
            "f,fi,fj->ij", mesh.area_faces, total, total)
        probe, _ = trimesh.sample.sample_surface(mesh, points, seed=seed)
        dense, _ = trimesh.sample.sample_surface(mesh, 16 * points, seed=seed + 1)
        self.probe = probe - self.centre
        self.tree = cKDTree(dense - self.centre)

    def error(self, linear: np.ndarray) -> float:
        """Symmetric Chamfer distance between the surface and its image by `linear` (about the centre), over the
        size: the mean distance from the image of each probe point to the surface, and from each probe point to the
        image of the surface (the inverse map's image of the probe)."""
        there, _ = self.tree.query(self.probe @ linear.T, workers=-1)
        back, _ = self.tree.query(self.probe @ np.linalg.inv(linear).T, workers=-1)
        return 0.5 * float(there.mean() + back.mean()) / self.size


def find_symmetry(mesh: trimesh.Trimesh, tolerance: float = TOLERANCE, points: int = 2000, seed: int = 0) -> Symmetry:
    """The object's turns about the vertical axis (the largest n in 2..12 whose turn by 360/n passes, or any angle
    when turns by GENERIC_TURNS_DEG pass too) and its best vertical mirror plane (_best_mirror), each accepted when
    its error is at most `tolerance`."""
    surface = _Surface(mesh, points, seed)
    turn_errors = {n: surface.error(turn_matrix(360.0 / n)) for n in TURN_ORDERS}
    passing = [n for n, e in turn_errors.items() if e <= tolerance]
    if passing and all(surface.error(turn_matrix(a)) <= tolerance for a in GENERIC_TURNS_DEG):
        order, turn_error = None, max(surface.error(turn_matrix(a)) for a in GENERIC_TURNS_DEG)
    elif passing:
        order = max(passing)
        turn_error = turn_errors[order]
    else:
        order, turn_error = 1, turn_errors[2]
    angle, mirror_error = _best_mirror(surface, order, tolerance)
    mirror = mirror_error <= tolerance
    return Symmetry(turn_order=order, mirror=mirror, mirror_deg=round(angle, 1) % 180.0 if mirror else None,
                    centre=(float(surface.centre[0]), float(surface.centre[1])),
                    turn_error=float(turn_error), mirror_error=mirror_error)


def _best_mirror(surface: _Surface, order: int | None, tolerance: float) -> tuple[float, float]:
    """The vertical plane through the centre whose reflection changes the surface least, as (normal in degrees,
    error). A surface of revolution is its own image in every such plane; any other mirror plane is a principal
    direction of the surface's horizontal spread, unless that spread is round (a turn order of 3 or more, or by
    chance), in which case the planes are searched in 1 degree steps over 180/n degrees (an object with n turns has
    n mirror planes 180/n apart, or none). A candidate within half the tolerance is kept as it is; otherwise the
    best is refined in 0.25 degree steps within 1 degree."""
    if order is None:
        return 0.0, surface.error(mirror_matrix(0.0))
    spread, axes = np.linalg.eigh(surface.moment[:2, :2])
    if spread[0] < 0.99 * spread[1]:
        candidates = np.round(np.degrees(np.arctan2(axes[1], axes[0])), 6) % 180.0
    else:
        candidates = np.arange(0.0, 180.0 / max(order, 1), 1.0)
    coarse = [surface.error(mirror_matrix(a)) for a in candidates]
    if min(coarse) <= tolerance / 2:  # an exact principal direction needs no refining
        return float(candidates[int(np.argmin(coarse))]), float(min(coarse))
    fine = candidates[int(np.argmin(coarse))] + np.arange(-1.0, 1.05, 0.25)
    errors = [surface.error(mirror_matrix(a)) for a in fine]
    best = int(np.argmin(errors))
    return float(round(float(fine[best]), 2) % 180.0), float(errors[best])


def object_symmetries(objects: ObjectSet, tolerance: float = TOLERANCE, points: int = 2000,
                      seed: int = 0) -> tuple[Symmetry, ...]:
    """find_symmetry for every object of the set, in class order; remembered per mesh content, since every
    component that mirrors episodes asks."""
    key = (tuple(hashlib.md5(m.vertices.tobytes() + m.faces.tobytes()).hexdigest() for m in objects.meshes),
           tolerance, points, seed)
    if key not in _FOUND:
        _FOUND[key] = tuple(find_symmetry(mesh, tolerance, points, seed) for mesh in objects.meshes)
    return _FOUND[key]


_FOUND: dict[tuple, tuple[Symmetry, ...]] = {}


def all_mirror_symmetric(objects: ObjectSet) -> bool:
    """Whether every object of the set is its own mirror image across the probe line's plane (up to a turn), so a
    component may read an episode and its mirror image alike."""
    return all(s.mirror for s in object_symmetries(objects))


def require_mirror(objects: ObjectSet, who: str) -> None:
    """Refuse a component (`who`) that reads an episode and its mirror image across the probe line alike, for an
    object set with chiral objects (check_mirror)."""
    try:
        check_mirror(objects.names, object_symmetries(objects))
    except ValueError as error:
        raise ValueError(f"{who}: {error}") from None


def check_mirror(names: Sequence[str], symmetries: Sequence[Symmetry]) -> None:
    """Raise for an object set with chiral objects: a mirror image of one of their episodes shows no pose of the
    object (it shows its mirror twin), so a mirror augmentation would teach false episodes."""
    chiral = [name for name, s in zip(names, symmetries) if not s.mirror]
    if chiral:
        raise ValueError(f"mirror augmentation: objects {chiral} are not their own mirror images (hg.sim.symmetry); "
                         "switch the mirror off for this object set or for these classes")
