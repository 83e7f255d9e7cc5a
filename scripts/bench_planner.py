"""Planner decisions per second: the exact greedy planner (the reference) against the default one, with a learned
policy's beside them, and both planners' validation accuracies, in one run.

One library (--library training episodes with their moves by up to --shifts place steps and, on a set of
mirror-symmetric objects, their mirror images, as docs/results/new_protocol's planner readings) and the same validation
episodes for both planners: --episodes drawn with --seed (as scripts/plan.py draws them) and, on such a set, the mirror
image of each across the line (its readings with each place's +x and -x leans swapped, as the library's mirror images
are made; the across-line regions keep a mirrored pose in its split). The exact planner breaks a tie between
mirror-image candidates by float rounding, and every episode faces one after the first, straight probe; an episode and
its mirror image meet it with the same readings, so each planner sends the pair down both branches whichever way it
breaks the tie, and the tie moves no accuracy. On a set with a chiral object (hg.sim.symmetry) a mirror image shows
another shape, so neither the library nor the episodes hold any (as scripts/reproduce_table1.py runs plan.py there,
without --mirror), and no tie is structural.

The reference is the planner as it was: the classifier weighs the whole library and the planner every library episode
(LibraryClassifier(prune=None)); the default keeps per episode the library episodes within PRUNE of its best and ranks
candidates on samples of them (hg.planner.greedy). Chunks of 128 episodes (plan.py's), timed interleaved: reference,
default, reference, default, ...; each planner's decisions per second is its median over the chunks. A decision is one
probe chosen for one episode, with the classifier's update by its reading and the class named after it, as plan.py runs
them; drawing the library and building the classifiers and planners are outside the clock. Accuracy: each planner's
classifier naming the class after 5 and 10 probes. The learned policy: CandidateChoice over PCRN (untrained; the
planner's candidates; configs/planner_copy.yaml) on the same episodes in ideal mode, 128 at a time, deterministic; a
decision is one policy.act for one episode (the network forward; the encoder's step and the simulator are outside the
clock). `--profile` prints cProfile's top functions of one chunk for each planner instead.

    .venv/bin/python scripts/bench_planner.py

Last line: JSON {"reference_decisions_per_s", "decisions_per_s", "speedup" (of the medians), "speedup_spread" (the
smallest and largest ratio of one chunk's two timings), "reference_acc5", "acc5", "reference_acc10", "acc10",
"learned_decisions_per_s", "episodes", "mirrored" (whether the library and the episodes hold mirror images),
"library_size", "prune", "samples", "refine", "objects", "host", "commit"}.
"""
from __future__ import annotations

import argparse
import cProfile
import json
import pstats
import time

import numpy as np
import torch

from hg.nets import PCRN, Dims
from hg.planner import CandidateGrid, GreedyPlanner, LibraryClassifier, LibraryRecipe, readings
from hg.planner.greedy import CHUNK, PRUNE, REFINE, SAMPLES, plan
from hg.policies import CandidateChoice, Observation, Policy
from hg.provenance import commit, hardware
from hg.rl.rollout import rollout
from hg.sim import ProbeSimulator, Scene, sample_episodes
from hg.sim.heldout import make_regions
from hg.sim.scene import mirrored_directions
from hg.sim.symmetry import all_mirror_symmetric

N_PROBES = 10


class Timed(Policy):
    """A policy whose act() calls are timed (seconds, summed)."""

    def __init__(self, policy: Policy) -> None:
        super().__init__()
        self.policy, self.learned, self.seconds = policy, policy.learned, 0.0

    def act(self, obs: Observation, deterministic: bool, generator: torch.Generator) -> torch.Tensor:
        start = time.perf_counter()
        action = self.policy.act(obs, deterministic, generator)
        self.seconds += time.perf_counter() - start
        return action


def mirrored(query: np.ndarray, grid: CandidateGrid) -> np.ndarray:
    """(E, C) the readings of each episode's mirror image across the line: each place's directions swapped."""
    swap = mirrored_directions(grid.directions, len(grid.along_leans))
    return query.reshape(len(query), grid.places, grid.directions)[..., swap].reshape(query.shape)


def accuracy(named: np.ndarray, labels: np.ndarray, after: int) -> float:
    return round(float((named[:, after - 1] == labels).mean()), 4)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--objects", default="hg4")
    parser.add_argument("--episodes", type=int, default=512,
                        help="validation episodes drawn (and as many mirrored, on a set of mirror-symmetric objects)")
    parser.add_argument("--library", type=int, default=32768, help="library episodes drawn, before moves and mirrors")
    parser.add_argument("--shifts", type=int, default=5)
    parser.add_argument("--seed", type=int, default=0, help="of the validation episodes (plan.py's --seed)")
    parser.add_argument("--profile", action="store_true", help="profile one chunk of each planner instead")
    args = parser.parse_args()
    torch.set_num_threads(1)

    regions, grid = make_regions("across_line", Scene(), 0), CandidateGrid()
    with ProbeSimulator(args.objects, batch_size=1024, mode="ideal", seed=0) as sim:
        mirror = all_mirror_symmetric(sim.objects)
        recipe = LibraryRecipe(args.library, "train", args.shifts, mirror, 0)
        library = recipe.draw(sim, regions, grid)
        classifiers = {name: LibraryClassifier.build(sim, regions, grid, recipe, prune=prune, drawn=library)
                       for name, prune in (("reference", None), ("default", PRUNE))}
        n_classes = len(sim.classes)
        labels, poses = sample_episodes(regions, "val", args.episodes, n_classes, np.random.default_rng(args.seed))
        drawn = readings(sim, labels, poses, grid.requests(), clean=True)
    query = torch.from_numpy(np.concatenate([drawn, mirrored(drawn, grid)]) if mirror else drawn)
    labels2 = np.concatenate([labels, labels]) if mirror else labels
    planners = {name: GreedyPlanner(classifier) for name, classifier in classifiers.items()}

    if args.profile:
        for name in planners:
            profile = cProfile.Profile()
            profile.runcall(plan, classifiers[name], query[:CHUNK], N_PROBES, planners[name])
            print(f"--- {name} planner, {CHUNK} episodes x {N_PROBES} probes")
            pstats.Stats(profile).sort_stats("tottime").print_stats(12)
        return

    seconds = {name: [] for name in planners}
    named = {name: [] for name in planners}
    for start in range(0, len(query), CHUNK):
        for name in planners:
            begin = time.perf_counter()
            named[name].append(plan(classifiers[name], query[start:start + CHUNK], N_PROBES, planners[name])[1])
            seconds[name].append(time.perf_counter() - begin)
    sizes = np.diff(list(range(0, len(query), CHUNK)) + [len(query)])
    rate = {name: float(np.median(sizes * N_PROBES / np.array(s))) for name, s in seconds.items()}
    ratios = np.array(seconds["reference"]) / np.array(seconds["default"])  # chunk by chunk, side by side in time
    named = {name: np.concatenate(n) for name, n in named.items()}

    encoder = PCRN()
    policy = Timed(CandidateChoice(Dims(encoder.out_dim, N_PROBES, n_classes), grid.places, grid.span, grid.leans))
    with ProbeSimulator(args.objects, batch_size=CHUNK, mode="ideal", seed=0) as sim, torch.no_grad():
        for start in range(0, len(labels), CHUNK):
            rollout(sim, policy, torch.from_numpy(labels[start:start + CHUNK]),
                    torch.from_numpy(poses[start:start + CHUNK]), args.seed, N_PROBES, 2.0, encoder, deterministic=True)
    learned = len(labels) * N_PROBES / policy.seconds

    result = {"reference_decisions_per_s": round(rate["reference"], 1), "decisions_per_s": round(rate["default"], 1),
              "speedup": round(rate["default"] / rate["reference"], 2),
              "speedup_spread": [round(float(ratios.min()), 2), round(float(ratios.max()), 2)],
              "reference_acc5": accuracy(named["reference"], labels2, 5),
              "acc5": accuracy(named["default"], labels2, 5),
              "reference_acc10": accuracy(named["reference"], labels2, 10),
              "acc10": accuracy(named["default"], labels2, 10), "learned_decisions_per_s": round(learned, 1),
              "episodes": len(query), "mirrored": mirror, "library_size": len(library[0]), "prune": PRUNE,
              "samples": SAMPLES, "refine": REFINE, "objects": args.objects, "host": hardware(), "commit": commit()}
    spread = f"chunk by chunk {ratios.min():.2f}x to {ratios.max():.2f}x"
    print(f"reference {rate['reference']:.1f} decisions/s, default {rate['default']:.1f} ({result['speedup']}x; "
          f"{spread}), learned policy {learned:.1f}; accuracy after 5 / 10 probes: reference "
          f"{result['reference_acc5']} / {result['reference_acc10']}, default {result['acc5']} / {result['acc10']} "
          f"({len(query)} validation episodes, {len(library[0])} library episodes)", flush=True)
    print(json.dumps(result))


if __name__ == "__main__":
    main()
