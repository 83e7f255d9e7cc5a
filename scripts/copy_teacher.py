"""How well can the location network copy a teacher's probes, and from which state? Offline, in minutes.

`model.imitate` trains the policy's mean to copy a teacher (the greedy planner's choices, saved by
`planner_ceiling.py --save-rollouts`) inside a training run, an hour per try. This script asks the same question
offline: the teacher's episodes are probed once with its requests (ideal mode), a checkpoint's encoder reads them,
and a fresh location network (its hidden width `--hidden`) learns the teacher's requests by the same squared error
from each kind of state, on the first episodes; the rest score it:
  - `pcrn`: the mean of PCRN's representations of the probes so far (the state a policy reads, the paper's);
  - `pcrn_touch_set`: that and the touch set's pooled features (`model.policy_reads_touch_set`);
  - `points`: the probes so far themselves, flattened, with the probe index: a state that hides nothing.
For each it reports the mean absolute error of each request component on the held-out episodes, with the earlier
components the teacher's (`forced`) and the network's own (`own`, as a policy would act), and the share of the
teacher's leaning probes the network's own mean leans to the same side (`lean_side`). If even `points` copies
badly, the teacher's choices are not a smooth function of what its probes touched that the episodes teach.

    .venv/bin/python scripts/copy_teacher.py --ckpt CKPT --teacher data/planner/train_s10.npz --episodes 4096

Last line: JSON {"<state>": {"forced": [py, ux, uy, uz], "own": [...], "lean_side": .., "train_mse": ..}, ...,
"episodes": .., "held_out": .., "steps": .., "hidden": ..}.
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from hg.lightning import HapticGlance, ProbeDataModule  # noqa: E402
from hg.lightning.data import load_teacher  # noqa: E402
from hg.nets import LocationNetwork  # noqa: E402

STATES = ("pcrn", "pcrn_touch_set", "points")


def teacher_states(model: HapticGlance, episodes: dict[str, torch.Tensor], batch: int) -> dict[str, torch.Tensor]:
    """(E, N, D) states before each of the teacher's requests, of every kind in STATES, from its probes."""
    parts: dict[str, list[torch.Tensor]] = {name: [] for name in STATES}
    with torch.no_grad():
        for i in range(0, len(episodes["labels"]), batch):
            labels, poses, requests = (episodes[k][i:i + batch] for k in ("labels", "poses", "requests"))
            rollout = model.rollout(labels, poses, 0, requests=requests)
            pcrn = model.location.states(model.encode(rollout)[0])
            parts["pcrn"].append(pcrn)
            if model.touch_set is not None:
                pooled = model.touch_set.pooled(rollout.points)  # row k: probes 1..k + 1, for request k + 2
                before = torch.cat([torch.zeros_like(pooled[:, :1]), pooled[:, :-1]], 1)
                parts["pcrn_touch_set"].append(torch.cat([pcrn, before], -1))
            n, k = rollout.points.shape[:2]
            seen = torch.arange(k)[None, :, None] < torch.arange(k)[:, None, None]  # (N, N, 1): probe j before row k
            points = (rollout.points[:, None] * seen).reshape(n, k, -1)
            parts["points"].append(torch.cat([points, torch.eye(k).expand(n, k, k)], -1))
    return {name: torch.cat(p) for name, p in parts.items() if p}


def fit_and_score(states: torch.Tensor, requests: torch.Tensor, n_train: int, steps: int, hidden: int,
                  seed: int) -> dict:
    """Train a fresh location network's mean on the first n_train episodes; score it on the rest."""
    torch.manual_seed(seed)
    net = LocationNetwork(states.shape[-1], hidden=hidden, std_floor=0.02, std_max=0.08)
    optimizer = torch.optim.Adam(net.parameters(), lr=1e-3)
    generator = torch.Generator().manual_seed(seed)
    recent = []
    for _ in range(steps):
        rows = torch.randint(0, n_train, (64,), generator=generator)
        mu, _ = net.distribution(states[rows], requests[rows])
        loss = (mu - requests[rows]).pow(2).sum(-1).mean()
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
        recent = (recent + [loss.item()])[-100:]
    held, target = states[n_train:], requests[n_train:]
    with torch.no_grad():
        forced = net.distribution(held, target)[0]
        own = net.sample(held, deterministic=True)[0].clamp(-1, 1)
    leaning = target[..., 1] != 0
    same_side = (torch.sign(own[..., 1]) == torch.sign(target[..., 1]))[leaning]
    return {"forced": [round(v, 3) for v in (forced - target).abs().mean((0, 1)).tolist()],
            "own": [round(v, 3) for v in (own - target).abs().mean((0, 1)).tolist()],
            "lean_side": round(same_side.float().mean().item(), 3) if leaning.any() else None,
            "train_mse": round(sum(recent) / len(recent), 3)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--ckpt", type=Path, required=True, help="a checkpoint whose encoder reads the probes")
    parser.add_argument("--teacher", nargs="+", required=True, help="teacher files (planner_ceiling.py --save-rollouts)")
    parser.add_argument("--episodes", type=int, default=4096, help="teacher episodes used (the first ones)")
    parser.add_argument("--held-out", type=float, default=0.125, help="share of them scored, not trained on")
    parser.add_argument("--steps", type=int, default=3000)
    parser.add_argument("--hidden", type=int, default=128)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    if not args.ckpt.is_file():
        parser.error(f"--ckpt {args.ckpt}: checkpoint not found")
    if args.steps < 1 or args.hidden < 1 or not 0 < args.held_out < 1:
        parser.error("--steps and --hidden must be >= 1, --held-out in (0, 1)")
    torch.set_num_threads(1)
    model = HapticGlance.load_from_checkpoint(args.ckpt, map_location="cpu").eval()
    data = ProbeDataModule(mode="ideal", n_probes=model.hparams.n_probes, batch_size=256, eval_batch_size=256)
    episodes = load_teacher(args.teacher, data.regions, data.object_set.name, model.hparams.n_probes)
    episodes = {k: v[:args.episodes] for k, v in episodes.items() if v is not None}  # no faults: a noise-free teacher
    n = len(episodes["labels"])
    n_train = n - max(1, round(args.held_out * n))
    if n_train < 1:
        parser.error(f"--episodes {args.episodes}: {n} teacher episodes leave none to train on")
    model.sim = data.make_simulator()
    states = teacher_states(model, episodes, 256)
    model.sim.close()
    results = {}
    for name, s in states.items():
        results[name] = fit_and_score(s, episodes["requests"], n_train, args.steps, args.hidden, args.seed)
        print(f"{name}: |error| forced {results[name]['forced']}, own {results[name]['own']}, lean side "
              f"{results[name]['lean_side']}", flush=True)
    print(json.dumps(results | {"episodes": n, "held_out": n - n_train, "steps": args.steps, "hidden": args.hidden}))


if __name__ == "__main__":
    main()
