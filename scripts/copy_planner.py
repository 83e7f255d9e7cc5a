"""Can a network that *chooses* among the planner's candidate probes copy it, and keep what its probes say? Offline.

Copying the greedy planner with the paper's Gaussian location network failed (`model.imitate`, 0.701 after 10
probes; `copy_teacher.py`: its mean hedges between the sides, the teacher's lean side matched 0.77-0.82). This
script asks whether the trouble is the Gaussian: a categorical choice over the planner's own candidates (its
--places x directions, as `planner_ceiling.py`) cannot average two sides. A small MLP reads what the probes so far
touched (for every candidate: probed, touched, distance along the ray) and the probe index, and learns the
teacher's next candidate by cross-entropy on the teacher files' episodes (`planner_ceiling.py --save-rollouts`;
the last --held-out share is scored for the top-1 match). It then probes the table's held-out test episodes
itself, one candidate after another from what it touched, and every probe sequence is read by the same namer: the
planner's weighting of its training library (the teacher file's library: split, size, shifts, mirror, seed), so
the figures differ only in where the probes went:
  - `copy`: the network's most likely unprobed candidate; `copy_sampled`: drawn from its distribution;
  - `fixed`: the straight centre-out scan over the same places; `random`: unprobed candidates at random;
  - `planner` (with --planner): the planner itself on the first --planner episodes (slow: ~0.5 s an episode).
If `copy` keeps most of the planner's accuracy over `fixed`, a location network with a categorical choice is worth
training (docs/training.md, Next (1)); if not, the planner's choices are not a function of the touches that its
episodes teach. The library and the scored episodes are read in ideal mode unless --mode arm.

With --dagger R the copy is also taught on the states it reaches itself (DAgger): R times it probes
--dagger-episodes fresh training episodes, drawing its choices, the planner names its own pick at every state they
reach (`probe_episodes(advice=)`), and the network is fitted again on the teacher's states and all of those. Why:
the teacher's episodes only hold the states the planner reaches, and a copy that strays once is in states no
teacher episode taught; the copy, not its teacher, is what falls short after 5 probes (docs/training.md).
With --soft T [T ...] the teacher's own states are also read by the planner again, and one copy per T learns its
ranking of every candidate there, softmax(-(entropy - least) / T), instead of its pick alone (distillation): the
planner's picks are close calls between candidates (a held-out top-1 of ~0.5), so its pick alone teaches little of
what the second best is worth.
With --belief the copy also reads, at every state, the namer's belief (BayesNamer.belief: the class posterior, where
along the line the object lies and how sure that is, its offset across the line): what the planner weighs its
candidates by, summed up. Why: the copy stays under its teacher on the unseen positions whatever else it is taught,
and it reads only what each candidate touched, from which the planner's weighing of a whole library is far to learn.

    .venv/bin/python scripts/copy_planner.py --teacher data/planner/train_s10.npz data/planner/train_s20.npz

Last line: JSON {"copy" | "copy_sampled" | "fixed" | "random" [| "planner"]: {"accuracy": [after probe 1..N], ...},
"top1": .., "train_ce": .., "teacher_episodes": .., "held_out": .., "episodes": .., "split": .., ...
[, "dagger": [{"round", "samples", "advice_match", "top1", "train_ce", "copy_sampled": accuracy} per round]]
[, "soft": [{"temperature", "top1", "train_ce", "copy", "copy_sampled": accuracy} per T]]};
"copy" and "copy_sampled" are the last fitted network's.
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np
import torch
from torch import nn

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "scripts"))

from hg.lightning.data import EvalEpisodes, load_teacher, teacher_meta  # noqa: E402
from hg.sim import PoseRegions, ProbeSimulator, candidate_requests, sample_episodes  # noqa: E402
from hg.sim.library import MISS, readings, teacher_library  # noqa: E402
from hg.nets.library import belief, log_likelihood  # noqa: E402
from planner_ceiling import CHUNK, cell_matrix, fixed_sequence, probe_episodes, random_choice, summary  # noqa: E402


class BayesNamer:
    """The planner's namer over its library, as a teacher file's meta made it (split, size, shifts, mirror, seed;
    `library` episodes in place of its size if given): it names any sequence of candidate probes, so that rows
    which probe differently are read alike, by a namer that no policy's training shaped."""

    def __init__(self, meta: dict, sim: ProbeSimulator, regions: PoseRegions, n_classes: int,
                 library: int | None = None) -> None:
        readings_, labels, positions = teacher_library(meta, sim, regions, n_classes, library)
        self.meta, self.n_classes = meta, n_classes
        # where each library episode's object lies, in units of the pose range's half-width (for `belief`)
        self.positions = torch.from_numpy(positions / max(sim.scene.object_y[1], sim.scene.object_x[1])).float()
        self.one_hot = torch.nn.functional.one_hot(torch.from_numpy(labels), n_classes).float()
        self.n_bins = int(np.ceil(sim.scene.probe_length / meta["bin"])) + 2
        bins = np.where(readings_ == MISS, 0, 1 + np.minimum(readings_ / meta["bin"], self.n_bins - 2)).astype(np.int64)
        self.cells = cell_matrix(bins, labels, self.n_bins, n_classes)
        self.library, self.labels = torch.from_numpy(readings_.T.copy()), torch.from_numpy(labels)

    def belief(self, log_w: torch.Tensor) -> torch.Tensor:
        """(Q, classes + 4) hg.nets.library.belief of episodes whose log weights over the library are log_w (Q, L):
        the planner's belief, which it weighs its candidates by, summed up for a network (--belief)."""
        return belief(log_w, self.one_hot, self.positions)

    def beliefs(self, chosen: torch.Tensor, query: torch.Tensor) -> torch.Tensor:
        """(N * E, classes + 4) the belief before each probe of episodes that probed `chosen` (E, N), in
        teacher_samples' order (probe-major): their log weights as probe_episodes weighs them."""
        out = []
        for rows in torch.split(torch.arange(len(chosen)), CHUNK):
            log_w, before = torch.zeros(len(rows), self.library.shape[1]), []
            for k in range(chosen.shape[1]):
                before.append(self.belief(log_w))
                c = chosen[rows, k]
                log_w += log_likelihood(query[rows, c][:, None], self.library[c], self.meta["sigma"],
                                        self.meta["mismatch"])
            out.append(torch.stack(before))
        return torch.cat(out, 1).reshape(-1, out[0].shape[-1])

    def probe(self, query: np.ndarray, n_probes: int, choose, advise: bool = False) -> tuple[np.ndarray, ...]:
        """(E, N) candidates probed and classes named after each probe, for episodes whose readings of every
        candidate are `query` (E, C): probe_episodes in chunks; choose(k, used, query, log_w) as there (None: the
        planner), given the chunk's rows of `query`, or an (E, N) array of the candidates already chosen. With `advise`, also
        (E, N, C) the planner's expected entropy of every candidate at every state the episodes reached (its pick
        is the argmin; slow: the planner's cost)."""
        out = []
        for i in range(0, len(query), CHUNK):
            rows = slice(i, min(i + CHUNK, len(query)))
            pick = fixed_choices(torch.from_numpy(choose[rows])) if isinstance(choose, np.ndarray) else choose
            advice = [] if advise else None
            chosen, named = probe_episodes(torch.from_numpy(query[rows]), self.library, self.cells, self.labels,
                                           n_probes, self.n_bins, self.n_classes, self.meta["sigma"],
                                           self.meta["mismatch"], pick, advice=advice)
            out.append((chosen, named) + ((torch.stack(advice, 1).numpy(),) if advise else ()))
        return tuple(map(np.concatenate, zip(*out)))


def fixed_choices(chosen: torch.Tensor):
    """A `choose` for probe_episodes: the candidates (Q, N) each episode probed, as a policy chose them."""
    return lambda k, used, query, log_w: chosen[:, k]


def state(used: torch.Tensor, query: torch.Tensor, k: int, n_probes: int, probe_length: float) -> torch.Tensor:
    """(Q, 3C + N): for every candidate whether it was probed, touched, and how far along the ray (/ U_len); and
    probe k one-hot."""
    touched = used & (query != MISS)
    distance = torch.where(touched, query / probe_length, 0.0)
    step = torch.nn.functional.one_hot(torch.full((len(used),), k), n_probes).float()
    return torch.cat([used.float(), touched.float(), distance, step], 1)


def teacher_samples(chosen: torch.Tensor, query: torch.Tensor, n_probes: int, probe_length: float,
                    targets: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Every (state, probed so far, teacher's next candidate) of episodes that probed `chosen` (E, N), (E * N, ...):
    the teacher's own episodes, or with `targets` (E, N) the planner's picks at the states another policy reached."""
    used = torch.zeros(query.shape, dtype=torch.bool)
    rows, states, masks = torch.arange(len(query)), [], []
    for k in range(n_probes):
        states.append(state(used, query, k, n_probes, probe_length))
        masks.append(used.clone())
        used[rows, chosen[:, k]] = True
    return torch.cat(states), torch.cat(masks), (chosen if targets is None else targets).T.reshape(-1)


def fit(states: torch.Tensor, masks: torch.Tensor, targets: torch.Tensor, steps: int, hidden: int, seed: int
        ) -> tuple[nn.Module, float]:
    """An MLP's logits over the candidates, trained by cross-entropy on the teacher's choices (probed ones masked):
    targets (S,) candidate indices, or (S, C) probabilities over the candidates (0 on the probed ones)."""
    torch.manual_seed(seed)
    net = nn.Sequential(nn.Linear(states.shape[1], hidden), nn.ELU(), nn.Linear(hidden, hidden), nn.ELU(),
                        nn.Linear(hidden, masks.shape[1]))
    optimizer = torch.optim.Adam(net.parameters(), lr=1e-3)
    generator, recent = torch.Generator().manual_seed(seed), []
    for _ in range(steps):
        rows = torch.randint(0, len(states), (256,), generator=generator)
        logits = net(states[rows]).masked_fill(masks[rows], -torch.inf)
        if targets.dim() == 1:
            loss = nn.functional.cross_entropy(logits, targets[rows])
        else:  # 0 log 0 on the probed candidates is 0
            p = targets[rows]
            loss = -torch.where(p > 0, p * logits.log_softmax(1), 0.0).sum(1).mean()
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
        recent = (recent + [loss.item()])[-200:]
    return net.eval(), sum(recent) / len(recent)


def network_choice(net: nn.Module, n_probes: int, probe_length: float, generator: torch.Generator | None,
                   namer: BayesNamer | None = None):
    """A `choose` for probe_episodes: the network's most likely unprobed candidate, or one drawn (with generator);
    with `namer` (the one probing), the network also reads its belief (BayesNamer.belief) of the probes so far."""
    def choose(k: int, used: torch.Tensor, query: torch.Tensor, log_w: torch.Tensor) -> torch.Tensor:
        x = state(used, query, k, n_probes, probe_length)
        if namer is not None:
            x = torch.cat([x, namer.belief(log_w)], 1)
        with torch.no_grad():
            logits = net(x).masked_fill(used, -torch.inf)
        if generator is None:
            return logits.argmax(1)
        return torch.multinomial(torch.softmax(logits, 1), 1, generator=generator)[:, 0]
    return choose


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--teacher", nargs="+", required=True, help="teacher files (planner_ceiling.py --save-rollouts)")
    parser.add_argument("--held-out", type=float, default=0.125, help="share of the teacher's episodes kept for top-1")
    parser.add_argument("--episodes", type=int, default=2048, help="the table's episodes scored (the first ones)")
    parser.add_argument("--split", choices=["val", "test"], default="test", help="whose table episodes are scored")
    parser.add_argument("--mode", choices=["ideal", "arm"], default="ideal", help="how the scored episodes are probed")
    parser.add_argument("--library", type=int, help="library episodes (default: the teacher's)")
    parser.add_argument("--planner", type=int, default=0, help="also score the planner on this many episodes")
    parser.add_argument("--steps", type=int, default=20000)
    parser.add_argument("--hidden", type=int, default=256)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--dagger", type=int, default=0, help="rounds of teaching the copy on its own states")
    parser.add_argument("--dagger-episodes", type=int, default=1024, help="fresh training episodes per round")
    parser.add_argument("--soft", type=float, nargs="*", default=[],
                        help="temperatures (nats) of copies taught the planner's ranking of every candidate")
    parser.add_argument("--belief", action="store_true",
                        help="the copy also reads the namer's belief (class, where the object lies) at every state")
    args = parser.parse_args()
    for path in args.teacher:
        if not Path(path).is_file():
            parser.error(f"--teacher {path}: file not found (write one with planner_ceiling.py --save-rollouts)")
    if (args.steps < 1 or args.hidden < 1 or args.episodes < 1 or args.planner < 0 or not 0 < args.held_out < 1
            or args.dagger < 0 or args.dagger_episodes < 1 or any(t <= 0 for t in args.soft)):
        parser.error("--steps, --hidden, --episodes, --dagger-episodes must be >= 1, --planner and --dagger >= 0, "
                     "--held-out in (0, 1), --soft > 0")
    if args.belief and (args.dagger or args.soft):
        parser.error("--belief: not with --dagger or --soft (their states are read without the belief)")
    meta = teacher_meta(args.teacher)
    torch.set_num_threads(1)
    start = time.time()
    sim = ProbeSimulator("hg4", batch_size=1024, mode="ideal", seed=args.seed)
    regions, n_classes = PoseRegions(sim.scene), len(sim.classes)
    teacher = load_teacher(args.teacher, regions, "hg4", meta["n_probes"])
    n_probes, probe_length = meta["n_probes"], sim.scene.probe_length
    candidates = candidate_requests(meta["places"], meta["span"], meta["leans"], meta["along_leans"])
    match = (teacher["requests"].numpy()[:, :, None] == candidates[None, None].astype(np.float32)).all(-1)
    if not match.any(-1).all():
        parser.error(f"--teacher: {int((~match.any(-1)).sum())} requests are not candidates of the teacher's meta")
    chosen = torch.from_numpy(match.argmax(-1))
    labels, poses = teacher["labels"].numpy(), teacher["poses"].numpy()
    teacher_query = torch.from_numpy(readings(sim, labels, poses, candidates))
    n_train = len(labels) - max(1, round(args.held_out * len(labels)))

    namer = BayesNamer(meta, sim, regions, n_classes, args.library)
    batches = EvalEpisodes(regions, args.split, args.episodes, 256, n_classes, seed=0).batches
    test_labels = np.concatenate([b["labels"].numpy() for b in batches])[:args.episodes]
    test_poses = np.concatenate([b["poses"].numpy() for b in batches])[:args.episodes]
    if args.mode == "arm":
        with ProbeSimulator("hg4", batch_size=256, mode="arm", seed=args.seed) as arm:
            query = readings(arm, test_labels, test_poses, candidates)
    else:
        query = readings(sim, test_labels, test_poses, candidates)
    print(f"read {len(labels)} teacher, {namer.library.shape[1]} library and {len(query)} test episodes in "
          f"{time.time() - start:.0f} s", flush=True)

    start = time.time()
    states, masks, targets = teacher_samples(chosen[:n_train], teacher_query[:n_train], n_probes, probe_length)
    held_states, held_masks, held_targets = teacher_samples(chosen[n_train:], teacher_query[n_train:], n_probes,
                                                            probe_length)
    believer = namer if args.belief else None  # the namer whose belief the copy reads
    if believer:
        states = torch.cat([states, namer.beliefs(chosen[:n_train], teacher_query[:n_train])], 1)
        held_states = torch.cat([held_states, namer.beliefs(chosen[n_train:], teacher_query[n_train:])], 1)
        print(f"the namer's belief at every teacher state in {time.time() - start:.0f} s", flush=True)
    net, train_ce = fit(states, masks, targets, args.steps, args.hidden, args.seed)

    def held_out_top1(net: nn.Module) -> float:
        """How often the net's most likely candidate is the teacher's on the held-out teacher episodes."""
        with torch.no_grad():
            return (net(held_states).masked_fill(held_masks, -torch.inf).argmax(1) == held_targets).float().mean().item()

    def scored(net: nn.Module, generator: torch.Generator | None) -> list[float]:
        """Accuracy after each probe on the scored episodes, the net choosing (drawing with `generator`)."""
        _, named = namer.probe(query, n_probes, network_choice(net, n_probes, probe_length, generator, believer))
        return [round(float(a), 4) for a in (named == test_labels[:, None]).mean(0)]

    top1 = held_out_top1(net)
    print(f"fitted in {time.time() - start:.0f} s: train cross-entropy {train_ce:.3f}, held-out top-1 {top1:.3f}",
          flush=True)
    soft = []
    if args.soft:
        start = time.time()
        _, _, scores = namer.probe(teacher_query[:n_train].numpy(), n_probes, chosen[:n_train].numpy(), advise=True)
        entropy = torch.from_numpy(scores).transpose(0, 1).reshape(-1, scores.shape[-1])  # teacher_samples' order
        replayed = (entropy.argmin(1) == targets).float().mean().item()
        print(f"the planner read the teacher's {n_train} episodes again in {time.time() - start:.0f} s: its pick is "
              f"the teacher's {replayed:.3f} of the time", flush=True)
        for temperature in args.soft:
            start = time.time()
            ranking = torch.softmax(-(entropy - entropy.min(1, keepdim=True).values) / temperature, 1)
            soft_net, soft_ce = fit(states, masks, ranking, args.steps, args.hidden, args.seed)
            soft_top1 = held_out_top1(soft_net)
            found = {"temperature": temperature, "top1": round(soft_top1, 4), "train_ce": round(soft_ce, 4),
                     "replayed_match": round(replayed, 4), "copy": scored(soft_net, None),
                     "copy_sampled": scored(soft_net, torch.Generator().manual_seed(args.seed))}
            soft.append(found)
            print(f"soft copy, T={temperature} ({time.time() - start:.0f} s): held-out top-1 {soft_top1:.3f}; accuracy "
                  "after each probe " + " ".join(f"{a:.3f}" for a in found["copy"]) + "; sampled "
                  + " ".join(f"{a:.3f}" for a in found["copy_sampled"]), flush=True)
    rounds = []
    for r in range(1, args.dagger + 1):
        start = time.time()
        own_labels, own_poses = sample_episodes(regions, "train", args.dagger_episodes, n_classes,
                                                np.random.default_rng([args.seed, 7, r]))
        own_query = readings(sim, own_labels, own_poses, candidates)
        own_chosen, _, advice = namer.probe(own_query, n_probes, network_choice(
            net, n_probes, probe_length, torch.Generator().manual_seed(args.seed + r)), advise=True)
        advice = advice.argmin(-1)  # the planner's pick
        more = teacher_samples(torch.from_numpy(own_chosen), torch.from_numpy(own_query), n_probes, probe_length,
                               torch.from_numpy(advice))
        states, masks, targets = (torch.cat([a, b]) for a, b in zip((states, masks, targets), more))
        net, train_ce = fit(states, masks, targets, args.steps, args.hidden, args.seed)
        top1 = held_out_top1(net)
        accuracy = scored(net, torch.Generator().manual_seed(args.seed))
        rounds.append({"round": r, "samples": len(states), "advice_match": round(float((own_chosen == advice).mean()), 4),
                       "top1": round(top1, 4), "train_ce": round(train_ce, 4), "copy_sampled": accuracy})
        print(f"DAgger round {r} ({time.time() - start:.0f} s): its own choices matched the planner's "
              f"{rounds[-1]['advice_match']:.3f}; refitted on {len(states)} states, held-out top-1 {top1:.3f}; "
              f"sampled copy's accuracy after each probe " + " ".join(f"{a:.3f}" for a in accuracy), flush=True)

    order = np.argsort(np.abs(np.linspace(-meta["span"], meta["span"], meta["places"])), kind="stable")
    runs = {"copy": (network_choice(net, n_probes, probe_length, None, believer), len(query)),
            "copy_sampled": (network_choice(net, n_probes, probe_length, torch.Generator().manual_seed(args.seed),
                                            believer), len(query)),
            "fixed": (fixed_sequence(order * (len(candidates) // meta["places"])), len(query)),
            "random": (random_choice(torch.Generator().manual_seed(args.seed)), len(query))}
    if args.planner:
        runs["planner"] = (None, min(args.planner, len(query)))
    offsets = test_poses[:, 0] - sim.scene.probe_x
    results = {}
    for name, (choose, n) in runs.items():
        start = time.time()
        chosen_test, named = namer.probe(query[:n], n_probes, choose)
        r = results[name] = summary(chosen_test, named, test_labels[:n], query[:n], candidates, offsets[:n], sim)
        print(f"{name} ({n} episodes): accuracy after each probe " + " ".join(f"{a:.3f}" for a in r["accuracy"])
              + f"; {r['touches']:.2f} touches, tilt {r['tilt_deg']:.1f} deg, {r['places']:.1f} places "
              f"({time.time() - start:.0f} s)", flush=True)
    sim.close()
    print(json.dumps(results | {"top1": round(top1, 4), "train_ce": round(train_ce, 4), "teacher_episodes": n_train,
                                "held_out": len(labels) - n_train, "episodes": len(query), "mode": args.mode,
                                "library_episodes": namer.library.shape[1], "steps": args.steps, "hidden": args.hidden,
                                "split": args.split, "belief": args.belief} | ({"dagger": rounds} if rounds else {})
                     | ({"soft": soft} if soft else {})))


if __name__ == "__main__":
    main()
