"""Where on the held-out poses does a model lose? Accuracy split by the kind of held-out pose.

The test (or val) split holds two kinds of pose (hg.sim.poses): whole position cells no training episode holds
(`unseen_position`), and one heading sector of a position cell whose other headings are trained on
(`unseen_heading`). A policy that learned where training objects lie can read the first kind worse than a fixed scan
does. For each checkpoint this rolls out the split's table episodes (data.eval_seed 0, as the tables do) once with
the stochastic policy and once with the mean action, and reports accuracy after each probe on each kind.

Is it where the probes went, or how the model's classifier reads them? With --namer TEACHER.. (a choice among the
planner's candidates only, model.location: candidates) the stochastic rollouts' probe sequences are also named by
the greedy planner's namer over its training library (`copy_planner.py`'s BayesNamer, the teacher files' library:
no held-out pose), which no policy's training shaped (`accuracy_namer`); with --planner also the planner itself on
the same episodes (`planner`, slow: ~0.5 s an episode), and the model's classifiers reading the planner's probes
(`accuracy_on_planner_probes`): a classifier that reads those well where its own policy's probes fail is held back by
its policy.

    .venv/bin/python scripts/accuracy_by_cell.py --ckpt A.ckpt B.ckpt --mode arm
    .venv/bin/python scripts/accuracy_by_cell.py --ckpt A.ckpt --mode arm \
        --namer data/planner/train_s10.npz data/planner/train_s20.npz --planner

Last line: JSON {"<ckpt>": {"unseen_position": {"episodes": .., "accuracy": [..], "accuracy_mean_action": [..]
[, "accuracy_namer": [..], "accuracy_on_planner_probes": [..]]}, "unseen_heading": {...}}, ... [, "planner": {"unseen_position": [..], ...}], "split": ..,
"mode": .., "episodes": ..}.
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "scripts"))

from hg.lightning import HapticGlance, ProbeDataModule  # noqa: E402
from hg.lightning.data import EvalEpisodes  # noqa: E402
from hg.sim import SPLITS, ProbeSimulator, candidate_requests  # noqa: E402


def pose_kinds(regions, poses: np.ndarray, split: str) -> np.ndarray:
    """(E,) bool: True where the pose's whole position cell belongs to `split` (every heading held out)."""
    x, y, _ = regions.cell_of(poses)
    return (regions.table[x, y] == SPLITS.index(split)).all(-1)


def by_kind(correct: np.ndarray, kind: np.ndarray) -> dict:
    """(E, N) bool correct after each probe -> accuracy after each probe on each kind of held-out pose."""
    return {name: [round(float(a), 4) for a in correct[rows].mean(0)]
            for name, rows in (("unseen_position", kind), ("unseen_heading", ~kind)) if rows.any()}


def planner_namer(teacher: list[str], split: str, episodes: int, mode: str):
    """The planner's namer over the teacher files' library, the table episodes' readings of every candidate (in
    `mode`), the candidates, and the episodes' classes and kinds of held-out pose."""
    from copy_planner import BayesNamer

    from hg.lightning.data import teacher_meta
    from hg.sim.library import readings
    for path in teacher:
        if not Path(path).is_file():
            raise SystemExit(f"--namer {path}: teacher file not found (write one with planner_ceiling.py "
                             "--save-rollouts)")
    meta = teacher_meta(teacher)
    data = ProbeDataModule()
    regions = data.regions
    batches = EvalEpisodes(regions, split, episodes, 256, data.n_classes, seed=0).batches  # as the rollouts read them
    labels = np.concatenate([b["labels"].numpy() for b in batches])
    poses = np.concatenate([b["poses"].numpy() for b in batches])
    candidates = candidate_requests(meta["places"], meta["span"], meta["leans"], meta["along_leans"])
    start = time.time()
    with ProbeSimulator("hg4", batch_size=1024, mode="ideal", seed=0) as sim:
        namer = BayesNamer(meta, sim, regions, len(sim.classes))
    with ProbeSimulator("hg4", batch_size=256, mode=mode, seed=0) as sim:
        query = readings(sim, labels, poses, candidates)
    print(f"read the namer's library ({namer.library.shape[1]} episodes) and {len(query)} episodes' candidates in "
          f"{time.time() - start:.0f} s", flush=True)
    return namer, query, candidates, labels, pose_kinds(regions, poses, split)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--ckpt", type=Path, nargs="+", required=True)
    parser.add_argument("--split", choices=["val", "test"], default="test")
    parser.add_argument("--episodes", type=int, help="default: the table's (1024 for val, 2048 for test)")
    parser.add_argument("--mode", choices=["ideal", "arm"], default="arm")
    parser.add_argument("--namer", nargs="+", help="teacher files whose library names the probes as well")
    parser.add_argument("--planner", action="store_true", help="also the planner itself (needs --namer)")
    args = parser.parse_args()
    if args.planner and not args.namer:
        parser.error("--planner runs the planner of the --namer teacher files: give them")
    for ckpt in args.ckpt:
        if not ckpt.is_file():
            parser.error(f"--ckpt {ckpt}: checkpoint not found")
    episodes = args.episodes or (2048 if args.split == "test" else 1024)
    if episodes < 1:
        parser.error(f"--episodes {episodes}: must be >= 1")
    torch.set_num_threads(1)
    results, namer, planner_chosen = {}, None, None
    if args.namer:
        namer, query, candidates, labels, kind_of = planner_namer(args.namer, args.split, episodes, args.mode)
        if args.planner:
            start = time.time()
            planner_chosen, named = namer.probe(query, namer.meta["n_probes"], None)
            results["planner"] = by_kind(named == labels[:, None], kind_of)
            print(f"planner: {results['planner']} ({time.time() - start:.0f} s)", flush=True)
    for ckpt in args.ckpt:
        model = HapticGlance.load_from_checkpoint(ckpt, map_location="cpu").eval()
        if namer is not None and model.hparams.location != "candidates":
            raise SystemExit(f"--ckpt {ckpt}: --namer names choices among the planner's candidates; this model's "
                             f"location network is {model.hparams.location!r}")
        if namer is not None and (model.location.candidates.shape != candidates.shape
                                  or not np.allclose(model.location.candidates.numpy(), candidates, atol=1e-6)):
            raise SystemExit(f"--ckpt {ckpt}: its {len(model.location.candidates)} candidates are not the --namer "
                             f"teacher's {len(candidates)}")
        data = ProbeDataModule(mode=args.mode, n_probes=model.hparams.n_probes)
        batches = EvalEpisodes(data.regions, args.split, episodes, 256, data.n_classes, seed=0).batches
        model.sim = data.make_simulator()
        correct, chosen, on_planner = {False: [], True: []}, [], []
        kinds, first = [], 0
        with torch.no_grad():
            for i, batch in enumerate(batches):
                kinds.append(pose_kinds(data.regions, batch["poses"].numpy(), args.split))
                for deterministic in (False, True):
                    rollout = model.rollout(batch["labels"], batch["poses"], int(batch["seed"]), deterministic)
                    _, logits = model.evaluate(rollout, batch["labels"], learn_policy=False)
                    correct[deterministic].append((logits.argmax(-1) == batch["labels"][:, None]).numpy())
                    if namer is not None and not deterministic:
                        chosen.append(model.location.index_of(rollout.actions).numpy())
                if planner_chosen is not None:  # the model's classifiers reading the planner's probes
                    requests = model.location.candidates[planner_chosen[first:first + len(batch["labels"])]]
                    rollout = model.rollout(batch["labels"], batch["poses"], int(batch["seed"]), requests=requests)
                    _, logits = model.evaluate(rollout, batch["labels"], learn_policy=False)
                    on_planner.append((logits.argmax(-1) == batch["labels"][:, None]).numpy())
                first += len(batch["labels"])
        model.sim.close()
        kind = np.concatenate(kinds)
        stochastic, mean = (np.concatenate(correct[d]) for d in (False, True))
        results[str(ckpt)] = {
            name: {"episodes": int(rows.sum()),
                   "accuracy": [round(float(a), 4) for a in stochastic[rows].mean(0)],
                   "accuracy_mean_action": [round(float(a), 4) for a in mean[rows].mean(0)]}
            for name, rows in (("unseen_position", kind), ("unseen_heading", ~kind)) if rows.any()}
        if namer is not None:
            named = namer.probe(query, namer.meta["n_probes"], np.concatenate(chosen))[1]
            for name, accuracy in by_kind(named == labels[:, None], kind).items():
                results[str(ckpt)][name]["accuracy_namer"] = accuracy
        if on_planner:
            for name, accuracy in by_kind(np.concatenate(on_planner), kind).items():
                results[str(ckpt)][name]["accuracy_on_planner_probes"] = accuracy
        for name, r in results[str(ckpt)].items():
            n = len(r["accuracy"])
            print(f"{ckpt}: {name} ({r['episodes']} episodes): after {(n + 1) // 2} {r['accuracy'][(n - 1) // 2]:.3f}, "
                  f"after {n} {r['accuracy'][-1]:.3f} (mean action {r['accuracy_mean_action'][-1]:.3f}"
                  + (f", named by the planner's namer {r['accuracy_namer'][-1]:.3f}" if namer else "") + ")",
                  flush=True)
    print(json.dumps(results | {"split": args.split, "mode": args.mode, "episodes": episodes}))


if __name__ == "__main__":
    main()
