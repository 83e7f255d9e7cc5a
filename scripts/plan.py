"""The greedy information-gain planner over a library of simulated training episodes (hg.planner), on one split.

A library of episodes (objects at poses of --library-split) is probed once with every candidate probe (--places over
the middle --span of the line times straight down, leaning across it by each of --leans and along it by each of
--along-leans). Each episode of --split is then probed --n-probes times, each probe the candidate whose reading
would leave the least class entropy over the weighted library; the library's Bayes classifier names the class after
each probe. `--fixed` also scores the straight centre-out scan of the candidate places and `--random` unprobed
candidates at random, named by the same classifier (`--no-planner`: those alone; `--library-seed S`: the library a
teacher file of seed S was planned over). The library is read in ideal mode; `--mode arm` probes the scored episodes
with the arm (--robot), `--noise RATE` through a sensor with contact faults (the planner weighs with the sensor's
model and may probe a candidate again), and `--table-episodes` scores the very episodes the tables score.
The library holds training poses (`--library-split train`, the default); `--library-split val` lets it see the
held-out positions it is scored on: a ceiling of what adaptive probes can say, never a result. By default the
classifier keeps per episode only the library episodes within exp(-20) of its best and the planner ranks candidates on
samples of them (hg.planner.GreedyPlanner; over ten times as fast at the same accuracy: docs/benchmarks.md); `--exact` weighs
the whole library, as every planner reading made before it did.

`--save-rollouts FILE` writes the planner's episodes as a teacher file for a policy to copy (hg.planner.save_teacher:
schema 1, with the world, seeds, candidate grid and library recipe it was planned with).

    .venv/bin/python scripts/plan.py --library 32768 --shifts 5 --mirror --episodes 512
    .venv/bin/python scripts/plan.py --library 32768 --shifts 5 --mirror --split train \
        --episodes 4096 --seed 10 --save-rollouts data/planner/train_s10.npz     # a teacher (hg.rl.ImitateTeacher)

Last line: JSON {"planner" [and "fixed", "random"]: {"accuracy": [after probe 1, ..., N], "touches": ..,
"touches_first_half": .., "tilt_deg": .., "leaning_towards_object": .., "leaning_along_line": .., "places": ..,
"repeats": ..}, "objects": .., "eval_seed": .., "library": .., "library_split": .., "library_seed": .., "shifts": ..,
"mirror": .., "library_episodes": .., "noise": .., "episodes": .., "split": .., "mode": .., "table_episodes": ..,
"candidates": .., "along_leans": .., "planner_settings": {"prune": .., "samples": .., "refine": ..}}.
"""
from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np
import torch

from hg.planner import CandidateGrid, LibraryRecipe, evaluate, save_teacher
from hg.provenance import repo_path
from hg.sim import DEFAULT_URDF, MODES, SPLITS, Scene, SensorNoise, load_object_set, sample_episodes
from hg.sim.heldout import REGIONS, Regions, make_regions


def scored_episodes(regions: Regions, split: str, episodes: int, n_classes: int, seed: int,
                    table: bool) -> tuple[np.ndarray, np.ndarray]:
    """The classes and poses scored: the tables' own episodes of the split (EvalEpisodes, as the data module draws
    them with the regions' seed) or `episodes` drawn with `seed`."""
    if table:
        from hg.lightning.data import EvalEpisodes  # the tables' episode sets are the data module's
        batches = EvalEpisodes(regions, split, episodes, 256, n_classes, seed=regions.seed).batches
        return (np.concatenate([b["labels"].numpy() for b in batches]),
                np.concatenate([b["poses"].numpy() for b in batches]))
    return sample_episodes(regions, split, episodes, n_classes, np.random.default_rng(seed))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--objects", default="hg4", help="object set: hg4 or a folder of meshes")
    parser.add_argument("--robot", type=Path, default=DEFAULT_URDF, help="the arm's URDF (--mode arm)")
    parser.add_argument("--scene", type=json.loads, default={}, help="hg.sim.Scene fields as JSON, e.g. "
                        "'{\"probe_length\": 0.5}' (default: the default scene)")
    parser.add_argument("--eval-seed", type=int, default=0, help="the evaluation episodes' seed (data.eval_seed)")
    parser.add_argument("--regions", choices=sorted(REGIONS), default="across_line",
                        help="the held-out protocol (data.regions); the archived teacher files used cells")
    parser.add_argument("--episodes", type=int, default=1024)
    parser.add_argument("--split", choices=SPLITS, default="val")
    parser.add_argument("--table-episodes", action="store_true",
                        help="score the episodes the tables score on this split (--episodes: 1024 for val, 2048 for "
                             "test) instead of episodes drawn with --seed")
    parser.add_argument("--mode", choices=MODES, default="ideal",
                        help="how the scored episodes are probed (the library always in ideal mode)")
    parser.add_argument("--library", type=int, default=262144,
                        help="library episodes, each probed with every candidate")
    parser.add_argument("--library-split", choices=SPLITS, default="train")
    parser.add_argument("--shifts", type=int, default=0,
                        help="also the library's episodes moved along the line by up to this many place steps each way")
    parser.add_argument("--mirror", action="store_true", help="also the library's episodes mirrored across the line "
                        "(right for object sets whose shapes are their own mirror images, as hg4's)")
    parser.add_argument("--n-probes", type=int, default=10)
    parser.add_argument("--places", type=int, default=11, help="candidate places along the line")
    parser.add_argument("--span", type=float, default=0.5, help="the middle of the line they cover (request units)")
    parser.add_argument("--leans", type=float, nargs="*", default=[0.6, 1.0, 2.0],
                        help="leans across the line, as SidePickingScan's lean (0.6: 16.7 degrees, 1.0: 26.6, 2.0: 45)")
    parser.add_argument("--along-leans", type=float, nargs="*", default=[],
                        help="leans along the line, to +y and -y (the same sizes as --leans); none by default")
    parser.add_argument("--sigma", type=float, default=0.005, help="touch distance tolerance (m)")
    parser.add_argument("--mismatch", type=float, default=1e-3, help="weight kept by a touch read as a miss or back")
    parser.add_argument("--bin", type=float, default=0.01, help="reading bins for the planner's entropy (m)")
    parser.add_argument("--fixed", action="store_true", help="also score the straight centre-out scan")
    parser.add_argument("--random", action="store_true", help="also score unprobed candidates drawn at random (--seed)")
    parser.add_argument("--no-planner", action="store_true", help="score only --fixed / --random, not the planner")
    parser.add_argument("--library-seed", type=int, default=None,
                        help="draw the library with this seed instead of --seed (a teacher file's seed: its library)")
    parser.add_argument("--noise", type=float, default=0.0,
                        help="sensor fault rate of the scored episodes' probes: SensorNoise(miss_prob = "
                             "false_contact_prob = rate); the planner weighs with the sensor's model and may re-probe")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--exact", action="store_true", help="weigh the whole library (the reference planner, over ten "
                        "times slower) instead of each episode's kept library episodes")
    parser.add_argument("--save-rollouts", type=Path, help="write the planner's episodes here (.npz): a teacher")
    args = parser.parse_args()
    for name in ("episodes", "library", "n_probes", "places"):
        if getattr(args, name) < 1:
            parser.error(f"--{name.replace('_', '-')} {getattr(args, name)}: must be >= 1")
    if not 0 < args.span <= 1:
        parser.error(f"--span {args.span}: must be in (0, 1]")
    if args.shifts < 0 or (args.shifts and (args.places < 2
                                            or args.span * (1 + 2 * args.shifts / (args.places - 1)) > 1)):
        parser.error(f"--shifts {args.shifts}: must be >= 0, with --places >= 2, and keep the library's places on the "
                     "line (--span + shifts * place step <= 1)")
    for name in ("leans", "along_leans"):
        if any(not 0 < lean <= 2 for lean in getattr(args, name)):
            parser.error(f"--{name.replace('_', '-')} {getattr(args, name)}: each must be in (0, 2] "
                         "(uz = 1 - lean stays in [-1, 1])")
    if args.sigma <= 0 or args.bin <= 0 or not 0 < args.mismatch < 1:
        parser.error("--sigma and --bin must be > 0, --mismatch in (0, 1)")
    if not 0 <= args.noise < 1:
        parser.error(f"--noise {args.noise}: must be in [0, 1)")
    if args.no_planner and (not (args.fixed or args.random) or args.save_rollouts):
        parser.error("--no-planner: needs --fixed or --random, and no --save-rollouts")
    if args.save_rollouts and (args.split, args.library_split) != ("train", "train"):
        parser.error("--save-rollouts: a teacher is training data; plan it with --split train --library-split train")
    if args.library_seed is not None and args.save_rollouts:
        parser.error("--library-seed with --save-rollouts: plan a teacher with --seed alone (its library is drawn "
                     "with it, as readers of older teacher files expect)")
    if args.fixed and args.n_probes > args.places:
        parser.error(f"--fixed: the straight scan probes each of the {args.places} places once, --n-probes "
                     f"{args.n_probes}")
    try:
        scene = Scene(**args.scene)
        grid = CandidateGrid(args.places, args.span, tuple(args.leans), tuple(args.along_leans))
    except (TypeError, ValueError) as error:
        parser.error(f"--scene / candidate grid: {error}")
    if args.n_probes > len(grid.requests()):
        parser.error(f"--n-probes {args.n_probes}: more than the {len(grid.requests())} candidates")
    if not args.robot.is_file():
        parser.error(f"--robot {args.robot}: URDF file not found")
    library_seed = args.seed if args.library_seed is None else args.library_seed
    recipe = LibraryRecipe(args.library, args.library_split, args.shifts, args.mirror, library_seed, args.sigma,
                           args.mismatch)
    noise = SensorNoise(miss_prob=args.noise, false_contact_prob=args.noise)
    probers = (() if args.no_planner else ("planner",)) + (("fixed",) if args.fixed else ()) + (
        ("random",) if args.random else ())

    torch.set_num_threads(1)
    start = time.time()
    object_set = load_object_set(args.objects)
    regions = make_regions(args.regions, scene, args.eval_seed)
    labels, poses = scored_episodes(regions, args.split, args.episodes, len(object_set), args.seed, args.table_episodes)
    result = evaluate(object_set, labels, poses, regions, robot=args.robot, mode=args.mode, noise=noise, grid=grid,
                      recipe=recipe, bin=args.bin, n_probes=args.n_probes, probers=probers, seed=args.seed,
                      exact=args.exact)
    for name, rollouts in result.rollouts.items():
        r = rollouts.summary
        print(f"{name}: accuracy after each probe " + " ".join(f"{a:.3f}" for a in r["accuracy"])
              + f"; {r['touches']:.2f} touches ({r['touches_first_half']:.2f} in the first half), tilt "
              f"{r['tilt_deg']:.1f} deg, {r['places']:.1f} places", flush=True)
    print(f"{len(grid.requests())} candidates x {args.library} {args.library_split} library episodes "
          f"({result.library_episodes} with their shifts and mirror images), {len(labels)} {args.split} episodes "
          f"({args.mode} mode): {time.time() - start:.0f} s", flush=True)
    if args.save_rollouts:
        planner = result.rollouts["planner"]
        save_teacher(args.save_rollouts, labels, poses, planner.requests, object_set_name=object_set.name,
                     classes=object_set.names, regions=regions, robot=repo_path(args.robot), mode=args.mode,
                     noise=noise, seed=args.seed, grid=grid, recipe=recipe, bin=args.bin, faults=result.faults,
                     summary=planner.summary, settings=result.settings)
    print(json.dumps({name: rollouts.summary for name, rollouts in result.rollouts.items()} | {
        "objects": object_set.name, "eval_seed": args.eval_seed, "library": args.library,
        "library_split": args.library_split, "library_seed": library_seed, "shifts": args.shifts,
        "mirror": args.mirror, "library_episodes": result.library_episodes, "noise": args.noise,
        "episodes": len(labels), "split": args.split, "mode": args.mode, "table_episodes": args.table_episodes,
        "candidates": len(grid.requests()), "along_leans": args.along_leans,
        "planner_settings": result.settings}))


if __name__ == "__main__":
    main()
