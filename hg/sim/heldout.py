"""Held-out pose regions closed under the objects' symmetries and the components' augmentations (the default).

A training episode moved along the probe line by whole candidate-place steps, or mirrored across the line, or an
object turned by one of its symmetries (hg.sim.symmetry), shows the same world as another pose: a held-out region
must hold no such image of a training pose. Shifts carry a pose to almost any Y and turns to other headings, but none
of these maps changes the object's distance across the line, |X - probe_x| (but for a few millimetres where an
object's mirror plane or turn axis misses its bounding-box centre). AcrossLineRegions therefore cuts the pose space
into bands of that distance, with margins given to no split, so every held-out pose is about the margin or more
away from every training pose and all its images. nearest_training_distance measures that for any regions
(PoseRegions included); drop_held_out tells which augmented library or teacher episodes leave the training region.
"""
from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import ClassVar, Protocol

import numpy as np
from scipy.ndimage import distance_transform_edt

from hg.sim.poses import SPLITS, PoseRegions, rotation_matrices
from hg.sim.scene import Scene
from hg.sim.symmetry import Symmetry, mirror_matrix, turn_matrix

MARGIN = -1  # split index of a pose in no split
Band = tuple[float, float, str]
DEFAULT_BANDS: tuple[Band, ...] = ((0.0, 0.025, "train"), (0.05, 0.07, "val"), (0.08, 0.10, "test"),
                                   (0.125, 0.15, "train"))
SHIFTS = 5  # the planner's library moves episodes by up to 5 place steps each way
PLACES, SPAN = 11, 0.5  # the planner's candidate places over the middle of the line (request units)
MIRROR_X = np.diag([-1.0, 1.0, 1.0])


class Regions(Protocol):
    """Pose regions (AcrossLineRegions, PoseRegions): a scene, the seed of the evaluation episodes drawn from them,
    the split index of poses, a sampler of a split's poses and how they cut the pose space (for teacher files)."""

    scene: Scene
    seed: int
    seeded: bool  # whether the seed shapes the regions (then a teacher must have been planned with the same one)

    def split_of(self, poses: np.ndarray) -> np.ndarray: ...

    def sample(self, split: str, n: int, rng: np.random.Generator) -> np.ndarray: ...

    def meta(self) -> dict: ...


@dataclass(frozen=True)
class AcrossLineRegions:
    """Splits by the object's distance across the probe line, |X - probe_x|, in `bands` (low, high, split) of
    metres; a distance in no band is a margin (split MARGIN). Y, Z, tilts and heading range over the whole scene
    in every split, so shifts along the line, the mirror across it and turns of the object keep every split."""

    scene: Scene = field(default_factory=Scene)
    seed: int = 0  # of the evaluation episodes drawn from these regions (data.eval_seed); the bands do not use it
    bands: tuple[Band, ...] = DEFAULT_BANDS
    heading_free: ClassVar[bool] = True  # split_of does not read the heading
    seeded: ClassVar[bool] = False  # the bands are fixed: a teacher planned here fits any eval_seed

    def __post_init__(self) -> None:
        bands = tuple((float(lo), float(hi), str(split)) for lo, hi, split in self.bands)
        reach = min(self.scene.probe_x - self.scene.object_x[0], self.scene.object_x[1] - self.scene.probe_x)
        for (lo, hi, split), following in zip(bands, bands[1:] + ((np.inf, np.inf, ""),)):
            if split not in SPLITS or not 0.0 <= lo < hi <= following[0]:
                raise ValueError(f"heldout bands={self.bands}: expected increasing, disjoint (low, high, split) with "
                                 f"0 <= low < high and split in {SPLITS}; ({lo}, {hi}, {split!r}) is not")
        if bands[-1][1] > reach + 1e-12:
            raise ValueError(f"heldout bands={self.bands}: reach |X - probe_x| = {bands[-1][1]} m, but the scene's "
                             f"object_x={self.scene.object_x} allows {reach:g} m on both sides of probe_x")
        if missing := set(SPLITS) - {split for _, _, split in bands}:
            raise ValueError(f"heldout bands={self.bands}: no band for {sorted(missing)}")
        object.__setattr__(self, "bands", bands)

    def meta(self) -> dict:
        """How the regions cut the pose space, as teacher files record it (their seed is `eval_seed`)."""
        return {"across_line": [list(band) for band in self.bands]}

    @property
    def gap_m(self) -> float:
        """The smallest distance across the line between a training band and a held-out band."""
        train = [b for b in self.bands if b[2] == "train"]
        return min(max(lo - t_hi, t_lo - hi) for lo, hi, split in self.bands if split != "train"
                   for t_lo, t_hi, _ in train)

    def split_of(self, poses: np.ndarray) -> np.ndarray:
        """Split index (0 train, 1 val, 2 test, MARGIN) of each pose (n, 6)."""
        across = np.abs(np.asarray(poses)[:, 0] - self.scene.probe_x)
        out = np.full(len(across), MARGIN, dtype=np.int64)
        for lo, hi, split in self.bands:
            out[(across >= lo) & (across <= hi)] = SPLITS.index(split)
        return out

    def sample(self, split: str, n: int, rng: np.random.Generator) -> np.ndarray:
        """n poses (X, Y, Z, Rx, Ry, Rz in degrees) uniform over the split's bands, either side of the line."""
        if split not in SPLITS:
            raise ValueError(f"split={split!r}: expected one of {SPLITS}")
        bands = np.array([(lo, hi) for lo, hi, s in self.bands if s == split])
        widths = bands[:, 1] - bands[:, 0]
        pick = rng.choice(len(bands), size=n, p=widths / widths.sum())
        unit = rng.random((n, 6))
        low, high = self.scene.pose_low, self.scene.pose_high
        poses = low + unit * (high - low)
        side = np.where(rng.random(n) < 0.5, -1.0, 1.0)
        poses[:, 0] = self.scene.probe_x + side * (bands[pick, 0] + unit[:, 0] * widths[pick])
        return poses


REGIONS = {"across_line": AcrossLineRegions, "cells": PoseRegions}  # cells: the hg4 research's regions (archive)


def make_regions(kind: str, scene: Scene, seed: int = 0, field: str = "data.regions") -> AcrossLineRegions | PoseRegions:
    """The pose regions of a protocol by name (`field`, named in the error): `across_line`, closed under the objects'
    symmetries and the library's augmentations, or `cells`, the regions the archived hg4 rows were scored on."""
    if kind not in REGIONS:
        raise ValueError(f"{field}={kind!r}: expected one of {sorted(REGIONS)}")
    return REGIONS[kind](scene, seed=seed)


def place_step_m(scene: Scene, places: int = PLACES, span: float = SPAN) -> float:
    """How far apart along the line (m) the candidate places are (hg.sim.scene.candidate_requests)."""
    return 2 * span / (places - 1) * 0.5 * (scene.probe_y[1] - scene.probe_y[0])


def euler_deg(rotations: np.ndarray) -> np.ndarray:
    """(n, 3) Rx, Ry, Rz in degrees of rotations R = Rz Ry Rx (the inverse of hg.sim.poses.rotation_matrices)."""
    r = np.asarray(rotations)
    return np.degrees(np.column_stack([np.arctan2(r[:, 2, 1], r[:, 2, 2]),
                                       -np.arcsin(np.clip(r[:, 2, 0], -1.0, 1.0)),
                                       np.arctan2(r[:, 1, 0], r[:, 0, 0])]))


def _with_rotation(poses: np.ndarray, positions: np.ndarray, rotations: np.ndarray) -> np.ndarray:
    out = np.array(poses, dtype=np.float64)
    out[:, :3] = positions
    out[:, 3:] = euler_deg(rotations)
    return out


def turned(poses: np.ndarray, symmetry: Symmetry, deg: float) -> np.ndarray:
    """The same object's poses, described after a turn by `deg` about its symmetry axis (a symmetry when `deg` is a
    multiple of symmetry.turn_deg): the rotation R becomes R G and the centre moves by R (c - G c)."""
    poses = np.asarray(poses, dtype=np.float64)
    rot, g = rotation_matrices(poses[:, 3:]), turn_matrix(deg)
    centre = np.array([*symmetry.centre, 0.0])
    return _with_rotation(poses, poses[:, :3] + rot @ (centre - g @ centre), rot @ g)


def mirrored(poses: np.ndarray, symmetry: Symmetry, scene: Scene) -> np.ndarray:
    """The poses that show the mirror image, across the probe line's vertical plane X = probe_x, of the object at
    `poses`. An object with a mirror plane P (through its centre c) shows itself, at rotation S R P and position
    S t + 2 probe_x + S R (I - P) c (S: X -> -X). A chiral object shows its mirror twin, no pose of itself: it gets
    the mirrored coordinates (S R S, S t + 2 probe_x), so that regions closed under them hold these images too."""
    poses = np.asarray(poses, dtype=np.float64)
    rot = rotation_matrices(poses[:, 3:])
    positions = poses[:, :3] @ MIRROR_X + np.array([2.0 * scene.probe_x, 0.0, 0.0])
    if not symmetry.mirror:
        return _with_rotation(poses, positions, MIRROR_X @ rot @ MIRROR_X)
    plane, centre = mirror_matrix(symmetry.mirror_deg), np.array([*symmetry.centre, 0.0])
    return _with_rotation(poses, positions + (MIRROR_X @ rot @ (centre - plane @ centre)), MIRROR_X @ rot @ plane)


def augmented(poses: np.ndarray, labels: np.ndarray, symmetries: Sequence[Symmetry], scene: Scene,
              shift_m: float | np.ndarray = 0.0, mirror: bool | np.ndarray = False) -> np.ndarray:
    """The poses an augmented episode shows: mirrored across the line where `mirror`, then moved `shift_m` along
    it (per episode or for all)."""
    poses = np.array(poses, dtype=np.float64)
    flip = np.broadcast_to(np.asarray(mirror, dtype=bool), (len(poses),))
    for label in np.unique(np.asarray(labels)[flip]):
        rows = flip & (np.asarray(labels) == label)
        poses[rows] = mirrored(poses[rows], symmetries[label], scene)
    poses[:, 1] += np.broadcast_to(np.asarray(shift_m, dtype=np.float64), (len(poses),))
    return poses


def _turns(symmetry: Symmetry, heading_free: bool, steps: int = 72) -> np.ndarray:
    """The turns (deg) that leave the object unchanged, as many as regions can tell apart (any-angle objects: every
    360/steps degrees, or none where the regions ignore the heading)."""
    if symmetry.turn_order is None:
        return np.zeros(1) if heading_free else np.arange(steps) * 360.0 / steps
    return np.arange(symmetry.turn_order) * symmetry.turn_deg


def _turn_splits(poses: np.ndarray, regions: Regions, symmetry: Symmetry, steps: int) -> np.ndarray:
    """(turns, n) split indices of the poses described after each turn of the object (_turns); MARGIN where a
    pose leaves the scene's Y range."""
    out_of_range = (poses[:, 1] < regions.scene.object_y[0]) | (poses[:, 1] > regions.scene.object_y[1])
    turns = _turns(symmetry, getattr(regions, "heading_free", False), steps)
    return np.stack([np.where(out_of_range, MARGIN, regions.split_of(turned(poses, symmetry, deg))) for deg in turns])


def drop_held_out(poses: np.ndarray, labels: np.ndarray, regions: Regions, symmetries: Sequence[Symmetry], *,
                  shift_m: float | np.ndarray = 0.0, mirror: bool | np.ndarray = False, steps: int = 72
                  ) -> np.ndarray:
    """True for each episode that a training library or teacher must drop: mirrored where `mirror` and moved
    `shift_m` along the line (hg.planner's augmentations), it shows a pose outside the training region (validation,
    test or margin) under some turn of the object (any-angle objects: every 360/steps degrees, unless the regions
    ignore the heading), or leaves the scene's Y range."""
    labels = np.asarray(labels)
    shown = augmented(poses, labels, symmetries, regions.scene, shift_m, mirror)
    drop = np.zeros(len(shown), dtype=bool)
    for label in np.unique(labels):
        rows = np.flatnonzero(labels == label)
        drop[rows] = (_turn_splits(shown[rows], regions, symmetries[label], steps) != SPLITS.index("train")).any(0)
    return drop


@dataclass(frozen=True)
class NearestTraining:
    """Per held-out pose, after the maps (the object's turns, shifts along the line, the mirror across it):
    `reached`, it is an image of a training pose (split_of of the images); `position_m`, the distance in (X, Y) to
    the nearest position that holds a training pose at some heading; `heading_deg`, at the pose's own position, the
    heading gap to the nearest training heading modulo the object's turns (inf where that position holds none).
    The distances are read on a raster of (heading, X, Y) with steps `resolution` (m, deg)."""

    reached: np.ndarray
    position_m: np.ndarray
    heading_deg: np.ndarray
    resolution: tuple[float, float]

    def summary(self) -> dict:
        """Share reached; min / mean / max of position_m over all poses and its mean over the poses held out by
        position (position_m > 0, their share too); min / mean of the finite heading gaps."""
        finite = self.heading_deg[np.isfinite(self.heading_deg)]
        away = self.position_m[self.position_m > 0]
        return {"episodes": len(self.position_m), "reached": float(self.reached.mean()),
                "position_min_m": float(self.position_m.min()), "position_mean_m": float(self.position_m.mean()),
                "position_max_m": float(self.position_m.max()),
                "held_out_by_position": len(away) / len(self.position_m),
                "position_mean_m_of_those": float(away.mean()) if len(away) else None,
                "heading_min_deg": float(finite.min()) if len(finite) else None,
                "heading_mean_deg": float(finite.mean()) if len(finite) else None}


def _training_raster(regions: Regions, resolution_m: float, resolution_deg: float
                     ) -> tuple[np.ndarray, tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """(H, NX, NY) bool: is the pose at each grid (heading, X, Y) a training pose (Z and tilts mid-range)."""
    s = regions.scene
    xs = np.arange(s.object_x[0], s.object_x[1] + resolution_m / 2, resolution_m)
    ys = np.arange(s.object_y[0], s.object_y[1] + resolution_m / 2, resolution_m)
    hs = np.arange(-180.0, 180.0, resolution_deg)
    gx, gy = np.meshgrid(xs, ys, indexing="ij")
    poses = np.tile((s.pose_low + s.pose_high) / 2, (gx.size, 1))
    poses[:, 0], poses[:, 1] = gx.ravel(), gy.ravel()
    train = np.empty((len(hs), len(xs), len(ys)), dtype=bool)
    for i, h in enumerate(hs):
        poses[:, 5] = h
        train[i] = (regions.split_of(poses) == SPLITS.index("train")).reshape(gx.shape)
    return train, (hs, xs, ys)


def _circular_gap(train: np.ndarray) -> np.ndarray:
    """Steps along axis 0 (circular) from each cell to the nearest True cell of its column; inf for empty columns."""
    n = len(train)
    gap = np.full(train.shape, np.inf)
    for order in (range(2 * n), range(2 * n - 1, -1, -1)):
        run = np.full(train.shape[1:], np.inf)
        for k in order:
            run = np.where(train[k % n], 0.0, run + 1.0)
            gap[k % n] = np.minimum(gap[k % n], run)
    return gap


def nearest_training_distance(held_out: np.ndarray, labels: np.ndarray, regions: Regions,
                              symmetries: Sequence[Symmetry], *, shifts: int = SHIFTS, step_m: float | None = None,
                              mirror: bool = True, resolution_m: float = 0.002,
                              resolution_deg: float = 1.0) -> NearestTraining:
    """How far each held-out pose is from the training region of `regions`, after every map that shows the same
    world: the object's turns, moves along the line by up to `shifts` place steps of `step_m` (place_step_m by
    default) and, with `mirror`, the mirror across the line. Measured on a raster of (heading, X, Y) at the given
    resolution, so any regions with split_of can be measured (Z and tilts are taken mid-range)."""
    held_out, labels = np.asarray(held_out, dtype=np.float64), np.asarray(labels)
    train, (hs, xs, ys) = _training_raster(regions, resolution_m, resolution_deg)
    anywhere = train.any(axis=0)
    position = distance_transform_edt(~anywhere, sampling=resolution_m) if anywhere.any() else np.full(
        anywhere.shape, np.inf)
    heading = _circular_gap(train) * resolution_deg
    step = place_step_m(regions.scene) if step_m is None else step_m
    reached = np.zeros(len(held_out), dtype=bool)
    best_position = np.full(len(held_out), np.inf)
    best_heading = np.full(len(held_out), np.inf)
    for label in np.unique(labels):
        rows = np.flatnonzero(labels == label)
        symmetry = symmetries[label]
        free = symmetry.turn_order is None
        for flip in (False, True) if mirror else (False,):
            for k in range(-shifts, shifts + 1):
                moved = augmented(held_out[rows], np.full(len(rows), label), symmetries, regions.scene, k * step, flip)
                splits = _turn_splits(moved, regions, symmetry, round(360 / resolution_deg))
                reached[rows] |= (splits == SPLITS.index("train")).any(axis=0)
                for deg in _turns(symmetry, heading_free=True):
                    shown = turned(moved, symmetry, deg)
                    ix = np.rint((shown[:, 0] - xs[0]) / resolution_m).astype(np.int64)
                    iy = np.rint((shown[:, 1] - ys[0]) / resolution_m).astype(np.int64)
                    inside = (ix >= 0) & (ix < len(xs)) & (iy >= 0) & (iy < len(ys))
                    ih = np.rint((shown[:, 5] - hs[0]) / resolution_deg).astype(np.int64) % len(hs)
                    ix, iy = np.clip(ix, 0, len(xs) - 1), np.clip(iy, 0, len(ys) - 1)
                    here = np.where(inside, position[ix, iy], np.inf)
                    gap = np.where(anywhere[ix, iy], 0.0, np.inf) if free else heading[ih, ix, iy]
                    best_position[rows] = np.minimum(best_position[rows], here)
                    best_heading[rows] = np.minimum(best_heading[rows], np.where(inside, gap, np.inf))
    return NearestTraining(reached, best_position, best_heading, (resolution_m, resolution_deg))


def main(argv: list[str] | None = None) -> None:
    """Print nearest_training_distance's summary per object set, regions, split and maps (docs/benchmark.md)."""
    import argparse
    from dataclasses import replace

    from hg.sim.objects import load_object_set
    from hg.sim.poses import PoseRegions, sample_episodes
    from hg.sim.symmetry import object_symmetries

    parser = argparse.ArgumentParser(description=main.__doc__)
    parser.add_argument("--objects", nargs="+", default=["hg4", "data/objects/pyb10"])
    parser.add_argument("--episodes", type=int, default=2048, help="held-out poses drawn per split")
    parser.add_argument("--seed", type=int, default=0, help="of the draw (and of PoseRegions)")
    args = parser.parse_args(argv)
    print("| objects | regions | split | maps | reached | position min / mean / max (cm) | held out by position: "
          "share, mean (cm) | heading gap mean (deg) |\n|---|---|---|---|---|---|---|---|")
    for spec in args.objects:
        objects = load_object_set(spec)
        found = object_symmetries(objects)
        still = tuple(replace(s, turn_order=1) for s in found)
        maps = (("none", still, 0, False), ("turns", found, 0, False), ("shifts", still, SHIFTS, False),
                ("turns, shifts, mirror", found, SHIFTS, True))
        for regions in (PoseRegions(seed=args.seed), AcrossLineRegions()):
            for split in ("val", "test"):
                labels, poses = sample_episodes(regions, split, args.episodes, len(objects),
                                                np.random.default_rng(args.seed))
                for name, symmetries, shifts, mirror in maps:
                    s = nearest_training_distance(poses, labels, regions, symmetries, shifts=shifts,
                                                  mirror=mirror).summary()
                    mean = s["position_mean_m_of_those"]
                    those = "-" if mean is None else f"{100 * mean:.1f}"
                    heading = "-" if s["heading_mean_deg"] is None else f"{s['heading_mean_deg']:.1f}"
                    print(f"| {objects.name} | {type(regions).__name__} | {split} | {name} | {s['reached']:.3f} | "
                          f"{100 * s['position_min_m']:.1f} / {100 * s['position_mean_m']:.1f} / "
                          f"{100 * s['position_max_m']:.1f} | {s['held_out_by_position']:.2f}, {those} | {heading} |")


if __name__ == "__main__":
    main()
