"""Probes per second of the simulator (B episodes x N probes) against the bare PyBullet calls for the same work.

Bare arm cost per probe: one calculateInverseKinematics, the joint resets (one resetJointStatesMultiDof, as the
simulator does), getLinkState for the achieved tool pose, and the probe's share of one rayTestBatch per step.
Bare ideal cost: the rayTestBatch alone. Both also place each batch's objects with the same
resetBasePositionAndOrientation calls as `ProbeSimulator.reset` (so that the first ray batch after a reset pays
for the moved objects in both timings).
Last line: JSON with arm_probes_per_s, ideal_probes_per_s, bare_arm_probes_per_s, bare_ideal_probes_per_s.
"""
from __future__ import annotations

import argparse
import json
import time

import numpy as np
import pybullet

from hg.sim import PoseRegions, ProbeSimulator, sample_episodes
from hg.sim.client import OBJECT_GROUP
from hg.sim.robot import tool_orientations


def episodes(sim: ProbeSimulator, n_batches: int, n_probes: int, seed: int) -> list[tuple]:
    """Pre-drawn labels, poses and requests, so that timing covers only the simulator."""
    rng = np.random.default_rng(seed)
    regions = PoseRegions(sim.scene)
    return [(*sample_episodes(regions, "train", sim.batch_size, len(sim.classes), rng),
             rng.uniform(-1, 1, (n_probes, sim.batch_size, 4))) for _ in range(n_batches)]


def time_simulator(sim: ProbeSimulator, work: list[tuple]) -> float:
    start = time.perf_counter()
    for labels, poses, requests in work:
        sim.reset(labels, poses)
        for step in requests:
            sim.probe(step)
    return time.perf_counter() - start


def time_bare(sim: ProbeSimulator, work: list[tuple], arm: bool) -> float:
    """The same PyBullet calls issued directly, with request mapping and warm starts prepared outside the clock."""
    cid = sim.client.id
    prepared = []
    for labels, poses, requests in work:
        moves = sim.placement(labels, poses)[1]  # the object moves of this episode batch, issued in the clock
        sim.reset(labels, poses)
        for k, step in enumerate(requests):
            entry, direction = sim.scene.request_to_probe(step)
            rows = [(p.tolist(), o.tolist(), q.tolist()) for p, o, q in zip(
                entry, tool_orientations(direction), sim.arm.map_q[sim.arm.grid.nearest(sim.scene, entry, direction)])] \
                if arm else None
            starts = entry + sim.offsets
            ends = starts + sim.scene.probe_length * direction
            prepared.append((moves if k == 0 else [], rows, starts, ends))
    elapsed = 0.0
    for moves, rows, starts, ends in prepared:
        t0 = time.perf_counter()
        for body, position, orientation in moves:
            pybullet.resetBasePositionAndOrientation(body, position, orientation, physicsClientId=cid)
        if arm:
            body, tool, joints, damping = sim.arm.body, sim.arm.tool, sim.arm.joints, sim.arm.damping
            for point, orient, warm in rows:
                q = pybullet.calculateInverseKinematics(
                    body, tool, point, orient, currentPositions=warm, jointDamping=damping,
                    maxNumIterations=sim.arm.ik_iterations, residualThreshold=1e-6, physicsClientId=cid)
                pybullet.resetJointStatesMultiDof(body, joints, [[v] for v in q], physicsClientId=cid)
                pybullet.getLinkState(body, tool, computeForwardKinematics=True, physicsClientId=cid)
        pybullet.rayTestBatch(rayFromPositions=starts, rayToPositions=ends, collisionFilterMask=OBJECT_GROUP,
                              physicsClientId=cid)
        elapsed += time.perf_counter() - t0
    return elapsed


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--batch-size", type=int, default=64)
    parser.add_argument("--probes", type=int, default=10)
    parser.add_argument("--arm-batches", type=int, default=20)
    parser.add_argument("--ideal-batches", type=int, default=200)
    parser.add_argument("--repeats", type=int, default=3, help="best of this many timings")
    args = parser.parse_args()
    figures = {}
    for mode, n_batches in (("arm", args.arm_batches), ("ideal", args.ideal_batches)):
        with ProbeSimulator(batch_size=args.batch_size, mode=mode) as sim:
            work = episodes(sim, n_batches, args.probes, seed=0)
            n = n_batches * args.probes * args.batch_size
            figures[f"{mode}_probes_per_s"] = n / min(time_simulator(sim, work) for _ in range(args.repeats))
            figures[f"bare_{mode}_probes_per_s"] = n / min(time_bare(sim, work, mode == "arm")
                                                           for _ in range(args.repeats))
        ratio = figures[f"{mode}_probes_per_s"] / figures[f"bare_{mode}_probes_per_s"]
        print(f"{mode:5s}: {figures[f'{mode}_probes_per_s']:10.0f} probes/s, bare PyBullet "
              f"{figures[f'bare_{mode}_probes_per_s']:10.0f} probes/s, ratio {ratio:.2f}")
    figures.update(batch_size=args.batch_size, probes=args.probes)
    print(json.dumps({k: round(v, 1) if isinstance(v, float) else v for k, v in figures.items()}))


if __name__ == "__main__":
    main()
