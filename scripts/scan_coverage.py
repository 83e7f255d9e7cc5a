"""How often fixed straight-down scans touch the buried object: a cheap check of where probes are worth spending.

A classifier can only name an object it has touched, so the touches a fixed scan collects, and how early, bound
what the line-scan baselines and the policies started from them (`model.prior: line_scan`) can reach. For each
scan (`model.scan_span` x `model.scan_order`, as in `HapticGlance.line_scan_requests`) on the same episodes of a
pose split: mean touches per episode after all probes and after half of them, and the share of episodes with
at least one touch. No training; seconds on one core.

    .venv/bin/python scripts/scan_coverage.py                        # 512 val episodes, ideal mode
    .venv/bin/python scripts/scan_coverage.py --mode arm --split test

Last line: JSON {"<order>-span<span>": {"touches": .., "touches_first_half": .., "any_touch": ..}, ...}.
"""
from __future__ import annotations

import argparse
import json

import numpy as np

from hg.lightning.module import HapticGlance
from hg.sim import PoseRegions, ProbeSimulator, sample_episodes


def scan_touches(sim: ProbeSimulator, labels: np.ndarray, poses: np.ndarray, requests: np.ndarray) -> np.ndarray:
    """(episodes, probes) contact flags of one fixed scan: the same request for every episode at each step."""
    sim.reset(labels, poses, seed=0)
    return np.stack([sim.probe(np.repeat(request[None], len(labels), 0)).points[:, 3] for request in requests], 1)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--episodes", type=int, default=512)
    parser.add_argument("--n-probes", type=int, default=10)
    parser.add_argument("--mode", choices=["ideal", "arm"], default="ideal")
    parser.add_argument("--split", choices=["train", "val", "test"], default="val")
    parser.add_argument("--spans", type=float, nargs="+", default=[1.0, 0.75, 0.5])
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()

    sim = ProbeSimulator("hg4", batch_size=args.episodes, mode=args.mode, seed=args.seed)
    labels, poses = sample_episodes(PoseRegions(sim.scene), args.split, args.episodes, len(sim.classes),
                                    np.random.default_rng(args.seed))
    half = args.n_probes // 2
    results = {}
    print(f"{args.episodes} {args.split} episodes, {args.mode} mode, {args.n_probes} straight-down probes")
    print(f"{'scan':>22} {'touches':>8} {f'after {half}':>9} {'any touch':>10}")
    for order in ("sweep", "centre_out"):
        for span in args.spans:
            model = HapticGlance(n_probes=args.n_probes, policy="line_scan", scan_span=span, scan_order=order)
            touches = scan_touches(sim, labels, poses, model.line_scan_requests().numpy())
            name = f"{order}-span{span:g}"
            results[name] = {"touches": round(float(touches.sum(1).mean()), 3),
                             "touches_first_half": round(float(touches[:, :half].sum(1).mean()), 3),
                             "any_touch": round(float((touches.sum(1) > 0).mean()), 3)}
            r = results[name]
            print(f"{name:>22} {r['touches']:8.2f} {r['touches_first_half']:9.2f} {r['any_touch']:10.2f}")
    sim.close()
    print(json.dumps(results))


if __name__ == "__main__":
    main()
