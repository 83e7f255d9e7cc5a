"""Probes per second of the simulator (B episodes x N probes) against the bare PyBullet calls for the same work.

Bare arm cost per probe: one calculateInverseKinematics, then what a PyBullet program calls to read the pose the
arm achieved (one resetJointStatesMultiDof, one getLinkState), and the probe's share of one rayTestBatch per step.
The simulator reads that pose from the URDF chain's own forward kinematics instead (hg.sim.kernels.tool_frames,
checked against getLinkState when the arm is built), so it can beat this bare figure; `arm_floor_ratio` times it
against the IK calls and rays alone, which nothing that solves IK with PyBullet can go under.
Bare ideal cost: the rayTestBatch alone. Both also place each batch's objects with the same
resetBasePositionAndOrientation calls as `ProbeSimulator.reset`, from the same world (so that the first ray batch
after a reset pays for the moved objects in both timings).
Timings alternate episode batch by episode batch (simulator, bare[, IK and rays alone], simulator, ...), so that a
change in the machine's speed reaches all alike; each of `--repeats` passes over the batches gives one ratio, and the
figure is their median, with their spread (min, max).
Last line: JSON with, per mode, probes/s of both (medians), `<mode>_ratio` and `<mode>_ratio_spread`, and
`arm_floor_ratio` with its spread.
"""
from __future__ import annotations

import argparse
import json
import time

import numpy as np
import pybullet

from hg.provenance import hardware
from hg.sim import PoseRegions, ProbeSimulator, sample_episodes
from hg.sim.client import OBJECT_GROUP
from hg.sim.robot import tool_orientations


def episodes(sim: ProbeSimulator, n_batches: int, n_probes: int, seed: int) -> list[tuple]:
    """Pre-drawn labels, poses and requests, so that timing covers only the simulator."""
    rng = np.random.default_rng(seed)
    regions = PoseRegions(sim.scene)
    return [(*sample_episodes(regions, "train", sim.batch_size, len(sim.classes), rng),
             rng.uniform(-1, 1, (n_probes, sim.batch_size, 4))) for _ in range(n_batches)]


def prepare_bare(sim: ProbeSimulator, work: list[tuple], arm: bool) -> list[tuple]:
    """Per episode batch, what the bare timing issues: the reset's object moves, then per probe step the IK targets
    with their warm starts (arm mode) and the rays; the request mapping and warm-start lookup are left outside the
    clock."""
    prepared = []
    sim.reset(*work[-1][:2])  # every pass over the batches starts where the last one ended
    for labels, poses, requests in work:
        moves = sim.placement(labels, poses)[1]  # the object moves of this episode batch, issued in the clock
        sim.reset(labels, poses)
        steps = []
        for step in requests:
            entry, direction = sim.scene.request_to_probe(step)
            rows = [(p.tolist(), o.tolist(), q.tolist()) for p, o, q in zip(
                entry, tool_orientations(direction), sim.arm.map_q[sim.arm.grid.nearest(sim.scene, entry, direction)])] \
                if arm else None
            starts = entry + sim.offsets
            steps.append((rows, starts, starts + sim.scene.probe_length * direction))
        prepared.append((moves, steps))
    return prepared


def bare_batch(sim: ProbeSimulator, moves: list[tuple], steps: list[tuple], read_pose: bool = True) -> None:
    """One episode batch as bare PyBullet calls: the object moves, per probe the IK call and (read_pose) the calls
    that read the achieved tool pose, per step the ray batch."""
    cid = sim.client.id
    for body, position, orientation in moves:
        pybullet.resetBasePositionAndOrientation(body, position, orientation, physicsClientId=cid)
    for rows, starts, ends in steps:
        if rows is not None:
            body, tool, joints, damping = sim.arm.body, sim.arm.tool, sim.arm.joints, sim.arm.damping
            for point, orient, warm in rows:
                q = pybullet.calculateInverseKinematics(
                    body, tool, point, orient, currentPositions=warm, jointDamping=damping,
                    maxNumIterations=sim.arm.ik_iterations, residualThreshold=1e-6, physicsClientId=cid)
                if read_pose:
                    pybullet.resetJointStatesMultiDof(body, joints, [[v] for v in q], physicsClientId=cid)
                    pybullet.getLinkState(body, tool, computeForwardKinematics=True, physicsClientId=cid)
        pybullet.rayTestBatch(rayFromPositions=starts, rayToPositions=ends, collisionFilterMask=OBJECT_GROUP,
                              physicsClientId=cid)


def time_pair(sim: ProbeSimulator, work: list[tuple], prepared: list[tuple],
              floor: bool = False) -> tuple[float, float, float]:
    """Seconds of the simulator, of the bare calls and (floor) of the bare calls without reading the achieved pose,
    over all episode batches, alternating batch by batch, so that the machine's speed changes reach all alike."""
    simulator = bare = bare_floor = 0.0
    previous = work[-1]
    for (labels, poses, requests), (moves, steps) in zip(work, prepared):
        t0 = time.perf_counter()
        sim.reset(labels, poses)
        for step in requests:
            sim.probe(step)
        simulator += time.perf_counter() - t0
        # the bare calls start from the world the simulator found: their object moves are real moves (moving an
        # object where it already is costs PyBullet less), and the first ray batch pays for them alike
        for read_pose in (True, False) if floor else (True,):
            ProbeSimulator.reset(sim, *previous[:2])  # the class's method: untimed by breakdown() too
            t1 = time.perf_counter()
            bare_batch(sim, moves, steps, read_pose)
            if read_pose:
                bare += time.perf_counter() - t1
            else:
                bare_floor += time.perf_counter() - t1
        ProbeSimulator.reset(sim, labels, poses)  # the simulator's record of what each slot holds, back in step
        previous = (labels, poses, requests)
    return simulator, bare, bare_floor


def breakdown(sim: ProbeSimulator, work: list[tuple], prepared: list[tuple]) -> dict[str, float]:
    """Microseconds per probe step inside the simulator (its reset, probe, the arm's reach, place and retries, the ray
    cast) and of the bare calls, from one more pass with those methods timed (the timers cost a little themselves)."""
    spent: dict[str, float] = {}
    targets = {"reset": sim, "probe": sim, "cast_rays": sim.client}
    if sim.arm is not None:
        targets |= {"reach": sim.arm, "place": sim.arm, "_retry": sim.arm}
    for name, owner in targets.items():
        def timed(*args, _original=getattr(owner, name), _name=name, **kwargs):
            start = time.perf_counter()
            try:
                return _original(*args, **kwargs)
            finally:
                spent[_name] = spent.get(_name, 0.0) + time.perf_counter() - start
        setattr(owner, name, timed)
    try:
        spent["bare"] = time_pair(sim, work, prepared)[1]
    finally:
        for name, owner in targets.items():
            delattr(owner, name)  # the instance attribute goes; the class's method is back
    steps = sum(len(requests) for _, _, requests in work)
    return {name: round(1e6 * seconds / steps, 1) for name, seconds in spent.items()}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--batch-size", type=int, default=64)
    parser.add_argument("--probes", type=int, default=10)
    parser.add_argument("--arm-batches", type=int, default=20)
    parser.add_argument("--ideal-batches", type=int, default=200)
    parser.add_argument("--repeats", type=int, default=7, help="interleaved (simulator, bare) timing pairs, >= 5")
    parser.add_argument("--breakdown", action="store_true", help="also time the simulator's parts (us per probe step)")
    args = parser.parse_args()
    if args.repeats < 5:
        parser.error(f"--repeats {args.repeats}: the ratios are medians of at least 5 pairs")
    figures = {}
    for mode, n_batches in (("arm", args.arm_batches), ("ideal", args.ideal_batches)):
        with ProbeSimulator(batch_size=args.batch_size, mode=mode) as sim:
            work = episodes(sim, n_batches, args.probes, seed=0)
            prepared = prepare_bare(sim, work, mode == "arm")
            n = n_batches * args.probes * args.batch_size
            time_pair(sim, work, prepared)  # one untimed pass: caches and allocations settle
            pairs = np.array([time_pair(sim, work, prepared, floor=mode == "arm") for _ in range(args.repeats)])
            if args.breakdown:
                figures[f"{mode}_us_per_step"] = breakdown(sim, work, prepared)
                print(f"{mode:5s}: us per probe step {figures[f'{mode}_us_per_step']}")
        ratios = pairs[:, 1] / pairs[:, 0]
        figures.update({f"{mode}_probes_per_s": round(n / float(np.median(pairs[:, 0])), 1),
                        f"bare_{mode}_probes_per_s": round(n / float(np.median(pairs[:, 1])), 1),
                        f"{mode}_ratio": round(float(np.median(ratios)), 3),
                        f"{mode}_ratio_spread": [round(float(ratios.min()), 3), round(float(ratios.max()), 3)]})
        if mode == "arm":
            floor = pairs[:, 2] / pairs[:, 0]
            figures.update(arm_floor_ratio=round(float(np.median(floor)), 3),
                           arm_floor_ratio_spread=[round(float(floor.min()), 3), round(float(floor.max()), 3)])
        print(f"{mode:5s}: {figures[f'{mode}_probes_per_s']:10.0f} probes/s, bare PyBullet "
              f"{figures[f'bare_{mode}_probes_per_s']:10.0f} probes/s, ratio {figures[f'{mode}_ratio']:.2f} "
              f"(median of {args.repeats} pairs, spread {ratios.min():.2f}-{ratios.max():.2f})"
              + (f"; against the IK and ray calls alone {figures['arm_floor_ratio']:.2f}" if mode == "arm" else ""))
    figures.update(batch_size=args.batch_size, probes=args.probes, repeats=args.repeats, host=hardware())
    print(json.dumps(figures))


if __name__ == "__main__":
    main()
