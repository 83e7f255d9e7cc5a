"""Where on the held-out poses does a model lose? Accuracy split by the kind of held-out pose.

The test (or val) split holds two kinds of pose (hg.sim.poses): whole position cells no training episode holds
(`unseen_position`), and one heading sector of a position cell whose other headings are trained on
(`unseen_heading`). A policy that learned where training objects lie can read the first kind worse than a fixed scan
does. For each checkpoint this rolls out the split's table episodes (data.eval_seed 0, as the tables do) once with
the stochastic policy and once with the mean action, and reports accuracy after each probe on each kind.

    .venv/bin/python scripts/accuracy_by_cell.py --ckpt A.ckpt B.ckpt --mode arm

Last line: JSON {"<ckpt>": {"unseen_position": {"episodes": .., "accuracy": [..], "accuracy_mean_action": [..]},
"unseen_heading": {...}}, ..., "split": .., "mode": .., "episodes": ..}.
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from hg.lightning import HapticGlance, ProbeDataModule  # noqa: E402
from hg.lightning.data import EvalEpisodes  # noqa: E402
from hg.sim import SPLITS  # noqa: E402


def pose_kinds(regions, poses: np.ndarray, split: str) -> np.ndarray:
    """(E,) bool: True where the pose's whole position cell belongs to `split` (every heading held out)."""
    x, y, _ = regions.cell_of(poses)
    return (regions.table[x, y] == SPLITS.index(split)).all(-1)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--ckpt", type=Path, nargs="+", required=True)
    parser.add_argument("--split", choices=["val", "test"], default="test")
    parser.add_argument("--episodes", type=int, help="default: the table's (1024 for val, 2048 for test)")
    parser.add_argument("--mode", choices=["ideal", "arm"], default="arm")
    args = parser.parse_args()
    for ckpt in args.ckpt:
        if not ckpt.is_file():
            parser.error(f"--ckpt {ckpt}: checkpoint not found")
    episodes = args.episodes or (2048 if args.split == "test" else 1024)
    if episodes < 1:
        parser.error(f"--episodes {episodes}: must be >= 1")
    torch.set_num_threads(1)
    results = {}
    for ckpt in args.ckpt:
        model = HapticGlance.load_from_checkpoint(ckpt, map_location="cpu").eval()
        data = ProbeDataModule(mode=args.mode, n_probes=model.hparams.n_probes)
        batches = EvalEpisodes(data.regions, args.split, episodes, 256, data.n_classes, seed=0).batches
        model.sim = data.make_simulator()
        correct = {False: [], True: []}
        kinds = []
        with torch.no_grad():
            for i, batch in enumerate(batches):
                kinds.append(pose_kinds(data.regions, batch["poses"].numpy(), args.split))
                for deterministic in (False, True):
                    rollout = model.rollout(batch["labels"], batch["poses"], int(batch["seed"]), deterministic)
                    _, logits = model.evaluate(rollout, batch["labels"], learn_policy=False)
                    correct[deterministic].append((logits.argmax(-1) == batch["labels"][:, None]).numpy())
        model.sim.close()
        kind = np.concatenate(kinds)
        stochastic, mean = (np.concatenate(correct[d]) for d in (False, True))
        results[str(ckpt)] = {
            name: {"episodes": int(rows.sum()),
                   "accuracy": [round(float(a), 4) for a in stochastic[rows].mean(0)],
                   "accuracy_mean_action": [round(float(a), 4) for a in mean[rows].mean(0)]}
            for name, rows in (("unseen_position", kind), ("unseen_heading", ~kind)) if rows.any()}
        for name, r in results[str(ckpt)].items():
            n = len(r["accuracy"])
            print(f"{ckpt}: {name} ({r['episodes']} episodes): after {(n + 1) // 2} {r['accuracy'][(n - 1) // 2]:.3f}, "
                  f"after {n} {r['accuracy'][-1]:.3f} (mean action {r['accuracy_mean_action'][-1]:.3f})", flush=True)
    print(json.dumps(results | {"split": args.split, "mode": args.mode, "episodes": episodes}))


if __name__ == "__main__":
    main()
