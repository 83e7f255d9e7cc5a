"""The greedy planner's library: episodes probed once with every candidate probe, read by nearest match.

What every candidate read in an episode (how far along its ray it touched) is what the planner (scripts/
planner_ceiling.py) weighs its library by, what its namer names an episode from (model.library_namer,
hg.nets.LibraryNamer) and what copy_planner.py's policy reads. numpy only, like the rest of hg.sim.
"""
from __future__ import annotations

import numpy as np

from hg.sim.poses import PoseRegions, sample_episodes
from hg.sim.scene import candidate_requests, mirrored_directions
from hg.sim.simulator import ProbeSimulator

MISS = -1.0  # the reading of a probe that touched nothing


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
                     leans: list[float], shifts: int, mirror: bool, along_leans: list[float] = ()
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(L', C) readings of the candidates, (L',) classes and (L', 2) object positions (x across the line from it, y
    along it; m) of the library: its episodes as drawn, and with `shifts`
    also moved along the line by 1..shifts place steps each way (kept where the object stays in the pose range),
    and with `mirror` mirrored across the line too. The ground is alike all along the line, so an object moved one
    step reads at each place what it read one place back; and hg4's shapes are mirror-symmetric, so the mirror image
    of an episode is an episode whose leaning probes swap sides. Symmetries of the world, not poses of another split:
    with them a training library reaches positions its split never holds (the held-out cells)."""
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
        keep = (y >= sim.scene.object_y[0]) & (y <= sim.scene.object_y[1])
        view = full[keep, shifts - j:shifts - j + places]
        for side, directions in zip((1, -1), [slice(None)] + [swap] * mirror):  # the mirror image: x across -> -x
            parts.append(view[..., directions].reshape(int(keep.sum()), -1))
            part_labels.append(labels[keep])
            part_positions.append(np.stack([side * (poses[keep, 0] - sim.scene.probe_x), y[keep]], 1))
    return np.concatenate(parts), np.concatenate(part_labels), np.concatenate(part_positions)


def teacher_library(meta: dict, sim: ProbeSimulator, regions: PoseRegions, n_classes: int,
                    library: int | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(L', C) readings, (L',) classes and (L', 2) positions (library_readings) of the library a teacher file's
    planner read (its meta: library split, size, shifts, mirror, seed; `library` episodes in place of its size if
    given), drawn as planner_ceiling.py draws it. `sim` must probe in ideal mode, as the planner's library was read."""
    labels, poses = sample_episodes(regions, meta["library_split"], library or meta["library"], n_classes,
                                    np.random.default_rng(meta["seed"] + 1))
    return library_readings(sim, labels, poses, meta["places"], meta["span"], meta["leans"], meta["shifts"],
                            meta["mirror"], meta.get("along_leans", []))
