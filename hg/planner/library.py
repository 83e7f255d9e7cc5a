"""The library of simulated training episodes: episodes probed once with every candidate probe, read by nearest match.

What every candidate read in a library episode (how far along its ray it touched) is what the greedy planner
(hg.planner.greedy) weighs its library by and what its Bayes classifier (hg.planner.LibraryClassifier) names an
episode from. Any object set, scene and robot: the library is read in ideal mode, so only the scene's geometry and
the objects enter it.
"""
from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from hg.sim.heldout import Regions, drop_held_out
from hg.sim.poses import SPLITS, sample_episodes
from hg.sim.scene import candidate_requests, mirrored_directions
from hg.sim.simulator import ProbeSimulator
from hg.sim.symmetry import Symmetry, object_symmetries, require_mirror

MISS = -1.0  # the reading of a probe that touched nothing


@dataclass(frozen=True)
class CandidateGrid:
    """The candidate probes a planner (or a policy choosing among candidates) picks from: `places` evenly over the
    middle `span` of the line (request units) times a direction, straight down or leaning across the line to +x and
    -x by each of `leans` and along it to +y and -y by each of `along_leans` (hg.sim.candidate_requests)."""

    places: int = 11
    span: float = 0.5
    leans: tuple[float, ...] = (0.6, 1.0, 2.0)
    along_leans: tuple[float, ...] = ()

    def __post_init__(self) -> None:
        object.__setattr__(self, "leans", tuple(float(x) for x in self.leans))
        object.__setattr__(self, "along_leans", tuple(float(x) for x in self.along_leans))
        candidate_requests(self.places, self.span, self.leans, self.along_leans)  # raises on a bad grid

    def requests(self) -> np.ndarray:
        """(C, 4) the candidates' requests, place-major."""
        return candidate_requests(self.places, self.span, self.leans, self.along_leans)

    @property
    def directions(self) -> int:
        return 1 + 2 * len(self.leans) + 2 * len(self.along_leans)

    def meta(self) -> dict:
        """The grid as a teacher file's meta records it."""
        return {"places": self.places, "span": self.span, "leans": list(self.leans),
                "along_leans": list(self.along_leans)}

    @classmethod
    def from_meta(cls, meta: dict) -> "CandidateGrid":
        """The grid a teacher file's meta records (files from before along-line leans have none)."""
        return cls(meta["places"], meta["span"], tuple(meta["leans"]), tuple(meta.get("along_leans", ())))


@dataclass(frozen=True)
class LibraryRecipe:
    """How a library is drawn and read: `size` episodes of the `split`'s poses drawn with `seed` (the rng of seed + 1,
    as every teacher file's library was drawn), with their moves along the line by up to `shifts` place steps each way
    and with `mirror` their mirror images (library_readings); the classifier's touch-distance tolerance `sigma` (m)
    and `mismatch`, the weight kept by a touch read as a miss or back (hg.planner.log_likelihood). `confined`: a
    training library leaves out the moved or mirrored copies that show a pose outside the training region (issue
    #56); teacher files written before it (schema < 2) were planned over unconfined libraries."""

    size: int = 262144
    split: str = "train"  # held-out poses enter a library only when asked for (scripts/plan.py --library-split)
    shifts: int = 0
    mirror: bool = False
    seed: int = 0
    sigma: float = 0.005
    mismatch: float = 1e-3
    confined: bool = True

    def __post_init__(self) -> None:
        if self.size < 1 or self.shifts < 0:
            raise ValueError(f"LibraryRecipe: size={self.size} must be >= 1 and shifts={self.shifts} >= 0")
        if self.split not in SPLITS:
            raise ValueError(f"LibraryRecipe: split={self.split!r}, expected one of {SPLITS}")
        if self.sigma <= 0 or not 0 < self.mismatch < 1:
            raise ValueError(f"LibraryRecipe: sigma={self.sigma} must be > 0 and mismatch={self.mismatch} in (0, 1)")

    def meta(self) -> dict:
        """The recipe as a teacher file's meta records it (the keys files have always used)."""
        return {"library": self.size, "library_split": self.split, "shifts": self.shifts, "mirror": self.mirror,
                "library_seed": self.seed, "sigma": self.sigma, "mismatch": self.mismatch, "confined": self.confined}

    @classmethod
    def from_meta(cls, meta: dict, size: int | None = None) -> "LibraryRecipe":
        """The recipe of a teacher file's library (`size` episodes in place of its own if given). Files from before
        schema 1 drew their library with the planner's seed, from before schema 2 unconfined."""
        return cls(size or meta["library"], meta["library_split"], meta["shifts"], meta["mirror"],
                   meta.get("library_seed", meta["seed"]), meta["sigma"], meta["mismatch"], meta.get("confined", False))

    def draw(self, sim: ProbeSimulator, regions: Regions, grid: CandidateGrid
             ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(L', C) readings, (L',) classes and (L', 2) object positions of the library (library_readings). `sim` must
        probe in ideal mode, as every library is read."""
        if sim.mode != "ideal":
            raise ValueError(f"LibraryRecipe.draw: the simulator probes in {sim.mode!r} mode; a library is read in "
                             "ideal mode")
        if self.mirror:
            require_mirror(sim.objects, "the library's mirror images (LibraryRecipe.mirror)")
        labels, poses = sample_episodes(regions, self.split, self.size, len(sim.classes),
                                        np.random.default_rng(self.seed + 1))
        confine = (regions, object_symmetries(sim.objects)) if self.confined and self.split == "train" else None
        return library_readings(sim, labels, poses, grid.places, grid.span, list(grid.leans), self.shifts,
                                self.mirror, list(grid.along_leans), confine)


def readings(sim: ProbeSimulator, labels: np.ndarray, poses: np.ndarray, candidates: np.ndarray,
             clean: bool = False, faults: np.ndarray | None = None) -> np.ndarray:
    """(E, C) float32: how far along each candidate's ray the probe touched the episode's object (m), MISS if not;
    episodes in batches of the simulator's size, every candidate for each batch. As the sensor read it (its faults
    drawn anew at every call, or each episode's given by `faults` (E, 2), ProbeSimulator.probe), or with `clean`
    what a fault-free sensor read."""
    out = np.empty((len(labels), len(candidates)), dtype=np.float32)
    for start in range(0, len(labels), sim.batch_size):
        end = min(start + sim.batch_size, len(labels))
        sim.reset(labels[start:end], poses[start:end])
        for c, request in enumerate(candidates):
            result = sim.probe(np.repeat(request[None], end - start, 0), None if faults is None else faults[start:end])
            points = result.clean_points if clean else result.points
            distance = np.linalg.norm(points[:, :3] - result.entry, axis=1)
            out[start:end, c] = np.where(points[:, 3] > 0.5, distance, MISS)
    return out


def library_readings(sim: ProbeSimulator, labels: np.ndarray, poses: np.ndarray, places: int, span: float,
                     leans: list[float], shifts: int, mirror: bool, along_leans: list[float] = (),
                     confine: tuple[Regions, Sequence[Symmetry]] | None = None
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(L', C) readings of the candidates, (L',) classes and (L', 2) object positions (x across the line from it, y
    along it; m) of the library: its episodes as drawn, and with `shifts`
    also moved along the line by 1..shifts place steps each way (kept where the object stays in the pose range),
    and with `mirror` mirrored across the line too. The ground is alike all along the line, so an object moved one
    step reads at each place what it read one place back; and the mirror image of an episode is an episode whose
    leaning probes swap sides only if every shape is its own mirror image across its x = 0 plane (hg4's are): use
    `mirror` for such object sets alone. Symmetries of the world, not poses of another split; but with regions that
    are not closed under them (the `cells` regions) a training library reaches poses its split never holds. With
    `confine` (regions, the objects' symmetries), every moved or mirrored copy that shows a pose outside the training
    region under some turn of its object is dropped (hg.sim.heldout.drop_held_out); the drawn episodes stay, being
    training poses (that a turn of the object may show a held-out pose is the regions' fault: the `cells` regions)."""
    step = 2 * span / (places - 1) if places > 1 else 0.0
    # the same places, `shifts` more each way
    wide = candidate_requests(places + 2 * shifts, span + shifts * step, leans, along_leans)
    n_directions = len(wide) // (places + 2 * shifts)
    full = readings(sim, labels, poses, wide).reshape(len(labels), places + 2 * shifts, n_directions)
    metres = step * 0.5 * (sim.scene.probe_y[1] - sim.scene.probe_y[0])  # one place step along the line
    swap = mirrored_directions(n_directions, len(along_leans))
    parts, part_labels, part_positions = [], [], []
    for j in range(-shifts, shifts + 1):  # the object moved j steps: it reads at place p what it read at p - j
        y = poses[:, 1] + j * metres
        in_range = (y >= sim.scene.object_y[0]) & (y <= sim.scene.object_y[1])
        for side, directions in zip((1, -1), [slice(None)] + [swap] * mirror):  # the mirror image: x across -> -x
            keep = in_range.copy()
            if confine is not None and (j or side < 0):  # the drawn episodes are training poses as they are
                keep[in_range] = ~drop_held_out(poses[in_range], labels[in_range], *confine, shift_m=j * metres,
                                                mirror=side < 0)
            parts.append(full[keep, shifts - j:shifts - j + places][..., directions].reshape(int(keep.sum()), -1))
            part_labels.append(labels[keep])
            part_positions.append(np.stack([side * (poses[keep, 0] - sim.scene.probe_x), y[keep]], 1))
    return np.concatenate(parts), np.concatenate(part_labels), np.concatenate(part_positions)


def teacher_library(meta: dict, sim: ProbeSimulator, regions: Regions, n_classes: int,
                    library: int | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(L', C) readings, (L',) classes and (L', 2) positions (library_readings) of the library a teacher file's
    planner read (its meta: library split, size, shifts, mirror, seed; `library` episodes in place of its size if
    given). `sim` must probe in ideal mode, as the planner's library was read."""
    if n_classes != len(sim.classes):
        raise ValueError(f"teacher_library: n_classes={n_classes}, the simulator's object set has {len(sim.classes)}")
    return LibraryRecipe.from_meta(meta, library).draw(sim, regions, CandidateGrid.from_meta(meta))
