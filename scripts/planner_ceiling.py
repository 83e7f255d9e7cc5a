"""What probes chosen one by one from what they touch could say: a greedy information-gain planner over a library.

The fixed scans' nearest-neighbour ceilings (scan_coverage.py --fit-net knn) stay under 0.85 after 5 probes in
every order, span, lean and pair placement read so far, so that target needs probes placed by what the earlier
ones touched. This script asks how far that can go without learning anything. A library of episodes (objects at
poses of --library-split) is probed once with every candidate probe: the places of the scan (--places over the
middle --span of the line) times a direction (straight down, or leaning across the line to +x or -x by each of
--leans, as model.scan_side, and along it to +y or -y by each of --along-leans). Each episode of --split is then
probed --n-probes times; before each probe the planner weighs the library by how well each library episode's
readings of the probes so far match this episode's (a touch's distance along the ray within --sigma, touch against
miss by --mismatch), and takes the candidate whose reading would leave the least entropy over the class, expected
over the weighted library (readings binned by --bin). After each probe it names the class of most weight.

With the library drawn from the scored split's own poses (`--library-split val`, the default) it has seen the
held-out positions, as the nearest-neighbour ceilings have: a reading of what adaptive probes can say, not a
classifier of ours. With `--library-split train` it is a planner that could be used as it is (no held-out pose
enters it). `--fixed` scores the straight centre-out scan over the same places with the same weighing, to set the
planner against the scans' ceilings, and `--random` unprobed candidates drawn at random (with --seed): the same
namer reading probes placed by no one, the baselines of a policy named by this namer (`--no-planner`: those alone;
`--library-seed 10`: the library a teacher file of --seed 10 was planned over, hg.sim.library.teacher_library).
The library is read in ideal mode; `--mode arm` probes the scored episodes with the arm, whose achieved probes stray
from the requested ones (every candidate is read up front, as the arm would read the chosen one), and
`--table-episodes` scores the very episodes the tables score. Minutes on one core.
`--best-first-two` also scores the planner with its first two probes chosen by trying every pair on the library
(binned readings, in-sample) for the fewest errors after two probes, the greedy planner's after: how much the
greedy choice leaves on the table after 2 probes. `--two-step PROBES` also scores the planner looking two probes
ahead for its first PROBES probes (TwoStep): whether a probe that sets up the next beats the most telling one.

`--save-rollouts FILE` keeps the planner's episodes (classes, poses, the requests it chose) as a teacher for a policy
to copy (model.imitate, docs/training.md); the file records the splits and seeds, so a model can refuse a teacher
whose episodes are not training episodes.

    .venv/bin/python scripts/planner_ceiling.py                          # 1024 val episodes, library of 262144
    .venv/bin/python scripts/planner_ceiling.py --library-split train    # a planner that never saw the val poses
    .venv/bin/python scripts/planner_ceiling.py --library-split train --split test --episodes 2048 --table-episodes \
        --mode arm                                                       # ... on Table 1's own test episodes
    .venv/bin/python scripts/planner_ceiling.py --library-split train --split train --library 32768 --shifts 5 \
        --mirror --episodes 3072 --seed 10 --save-rollouts data/planner/train_s10.npz   # a teacher (model.imitate)

Last line: JSON {"planner" [and "fixed", "random", "best_first_two", "two_step"]: {"accuracy": [after probe 1, ..., N],
"touches": .., "touches_first_half": .., "tilt_deg": .., "leaning_towards_object": .., "leaning_along_line": ..,
"places": .., "repeats": ..}, "library": .., "library_split": .., "shifts": .., "mirror": .., "library_episodes": ..,
"noise": .., "episodes": .., "split": .., "mode": .., "table_episodes": .., "candidates": .., "along_leans": .. [,
"first_two_on_library": {"best" | "greedy": {"first": candidate, "accuracy": on the library after two probes}}]}.
"""
from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path
from typing import Callable

import numpy as np
import scipy.sparse
import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from hg.atomic import write_atomic  # noqa: E402
from hg.provenance import commit  # noqa: E402
from hg.nets.library import log_likelihood  # noqa: E402
from hg.sim import SPLITS, PoseRegions, ProbeSimulator, SensorNoise, candidate_requests, sample_episodes  # noqa: E402
from hg.sim.library import MISS, library_readings, readings  # noqa: E402

# (k, used, query, log_w) -> candidates or None; log_w (Q, L): the library's log weights after the probes so far
Choose = Callable[[int, torch.Tensor, torch.Tensor, torch.Tensor], "torch.Tensor | None"]
CHUNK = 128  # scored episodes planned side by side: their weights over the library are (CHUNK, L)


def cell_matrix(bins: np.ndarray, labels: np.ndarray, n_bins: int, n_classes: int) -> scipy.sparse.csc_matrix:
    """(C * n_bins * n_classes, L) sparse 0/1: which (candidate, binned reading, class) cell each library episode
    falls in, for every candidate at once; times the library's weights it gives each cell's weight. Column-major
    (each library episode's C cells together): its product reads the weights once, in order, which is 2.4x faster
    over a large library than torch's row-major sparse product, and adds in the same order, so to the bit the same."""
    n, n_candidates = bins.shape
    cell = (np.arange(n_candidates) * n_bins + bins) * n_classes + labels[:, None]
    columns = np.arange(0, cell.size + 1, n_candidates)  # library episode l's cells: cell[l]
    return scipy.sparse.csc_matrix((np.ones(cell.size, np.float32), cell.ravel(), columns),
                                   shape=(n_candidates * n_bins * n_classes, n))


def expected_entropy(cells: scipy.sparse.csc_matrix, weights: torch.Tensor, n_bins: int, n_classes: int,
                     noise: SensorNoise = SensorNoise()) -> torch.Tensor:
    """(Q, C) the class entropy left after reading each candidate, expected over each episode's weighting of the
    library (Q, L): the weights fall into (reading, class) cells per candidate (bin 0: a miss). With sensor faults
    (`noise`) the reading is the sensor's: a touch's weight goes to the miss bin with miss_prob, a miss's spreads over
    the ray's bins with false_contact_prob, so a reading the faults often corrupt is worth less."""
    mass = torch.from_numpy(cells @ np.ascontiguousarray(weights.numpy().T)).T.reshape(len(weights), -1, n_bins,
                                                                                     n_classes)
    if noise.miss_prob or noise.false_contact_prob:
        miss, touch = mass[:, :, :1], mass[:, :, 1:]
        ray_bins = n_bins - 2  # the last bin only holds touches exactly at the ray's end
        false = torch.zeros_like(touch)
        false[:, :, :ray_bins] = noise.false_contact_prob * miss / ray_bins
        mass = torch.cat([(1 - noise.false_contact_prob) * miss + noise.miss_prob * touch.sum(2, keepdim=True),
                          (1 - noise.miss_prob) * touch + false], 2)
    per_bin = mass.sum(-1, keepdim=True)
    p = mass / per_bin.clamp(min=1e-30)
    entropy = -(p * torch.log(p.clamp(min=1e-30))).sum(-1)
    return (per_bin[..., 0] * entropy).sum(-1) / weights.sum(-1, keepdim=True)


def reading_bins(readings: np.ndarray, width: float, n_bins: int) -> np.ndarray:
    """The entropy's bin of each reading: 0 for a miss, then `width`-wide bins along the ray."""
    return np.where(readings == MISS, 0, 1 + np.minimum(readings / width, n_bins - 2)).astype(np.int64)


def pair_mass(bins: np.ndarray, labels: np.ndarray, first: int, n_bins: int, n_classes: int,
              weights: np.ndarray | None = None) -> np.ndarray:
    """(n_bins, C, n_bins, n_classes) library episodes (their weight with `weights`) in each (binned reading of
    candidate `first`, second candidate, its binned reading, class) cell: what `first` and then each candidate tell."""
    n_candidates = bins.shape[1]
    cell = ((bins[:, first, None] * n_candidates + np.arange(n_candidates)) * n_bins + bins) * n_classes \
        + labels[:, None]
    return np.bincount(cell.ravel(), None if weights is None else np.repeat(weights, n_candidates),
                       minlength=n_bins * n_candidates * n_bins * n_classes
                       ).reshape(n_bins, n_candidates, n_bins, n_classes).astype(np.float64)


def pair_entropy(mass: np.ndarray) -> np.ndarray:
    """(first's bin, second candidate) class entropy left, times the weight, of pair_mass's cells."""
    p = mass / mass.sum(-1, keepdims=True).clip(min=1e-30)
    return -(mass * np.log(p.clip(min=1e-30))).sum((-2, -1))


def best_first_two(bins: np.ndarray, labels: np.ndarray, n_bins: int, n_classes: int) -> dict:
    """The first probe, and the second for each binned reading of the first, that name the library's own episodes
    best after two probes (each (bin, bin) cell named by its commonest class), found by trying every pair: the
    greedy planner's first two probes minimise the entropy left one probe ahead, not the error two ahead. Returns
    both rules' first probe, (n_bins,) second probes and accuracy on the library (in-sample, so a ceiling)."""
    n, n_candidates = bins.shape
    found = {}
    for first in range(n_candidates):
        mass = pair_mass(bins, labels, first, n_bins, n_classes)
        correct = mass.max(-1).sum(-1)  # (first's bin, second): episodes named right
        entropy = pair_entropy(mass)
        correct[:, first], entropy[:, first] = -1, np.inf  # in ideal mode a repeated probe reads the same
        first_mass = mass[:, 0].sum(1)  # (first's bin, class): every second candidate partitions the same episodes
        first_p = first_mass / first_mass.sum(-1, keepdims=True).clip(min=1)
        entropy_first = -(first_mass * np.log(first_p.clip(min=1e-30))).sum() / n
        for rule, second in (("best", correct.argmax(1)), ("greedy", entropy.argmin(1))):
            found.setdefault(rule, []).append({"first": first, "second": second, "entropy_first": entropy_first,
                                               "accuracy": correct[np.arange(n_bins), second].sum() / n})
    best = max(found["best"], key=lambda r: r["accuracy"])
    greedy = min(found["greedy"], key=lambda r: r["entropy_first"])
    return {"best": best, "greedy": greedy}


class TwoStep:
    """The planner looking two probes ahead for its first `probes` probes: of the `top` candidates with the least
    entropy one probe ahead, it takes the one whose reading, followed by the best second probe for that reading,
    leaves the least class entropy, expected over the weighted library. Why: the greedy planner's ceiling after 5
    probes stays near 0.83 (docs/training.md); a probe that says little itself may set up a telling one. Only library
    episodes within `keep` of the most likely one's weight are counted (a reading that contradicts one probe keeps
    1e-3 of the weight), for speed. Fault-free sensors only (the bins are the library's clean readings)."""

    def __init__(self, bins: np.ndarray, labels: np.ndarray, n_bins: int, n_classes: int, probes: int,
                 top: int = 6, keep: float = 2e-3) -> None:
        self.bins, self.labels, self.n_bins, self.n_classes = bins, labels, n_bins, n_classes
        self.probes, self.top, self.keep = probes, top, keep

    def entropy_after_two(self, weights: torch.Tensor, used: torch.Tensor, first: int) -> float:
        """Class entropy (times the weight) left after candidate `first` and, for each binned reading of it, the
        best unused second candidate; weights (L,) of one episode, used (C,) its candidates probed so far."""
        weights = weights.numpy()
        kept = np.nonzero(weights > self.keep * weights.max())[0]
        entropy = pair_entropy(pair_mass(self.bins[kept], self.labels[kept], first, self.n_bins, self.n_classes,
                                         weights[kept]))
        entropy[:, used.numpy()] = math.inf
        entropy[:, first] = math.inf
        return float(entropy.min(1).sum())

    def __call__(self, weights: torch.Tensor, used: torch.Tensor, score: torch.Tensor) -> torch.Tensor:
        """(Q,) candidates for episodes of weights (Q, L), given the one-step entropies `score` (Q, C)."""
        top = score.topk(min(self.top, int((~used[0]).sum())), dim=1, largest=False).indices
        rows = range(1) if not used.any() else range(len(weights))  # before any probe every episode is alike
        picks = torch.stack([top[q, int(torch.tensor([self.entropy_after_two(weights[q], used[q], int(c))
                                                      for c in top[q]]).argmin())] for q in rows])
        return picks.expand(len(weights)) if len(picks) < len(weights) else picks


def probe_episodes(query: torch.Tensor, library: torch.Tensor, cells: torch.Tensor, labels: torch.Tensor,
                   n_probes: int, n_bins: int, n_classes: int, sigma: float, mismatch: float,
                   choose: Choose | None = None,
                   faulty: torch.Tensor | None = None, noise: SensorNoise = SensorNoise(), probe_length: float = 1.0,
                   two_step: TwoStep | None = None, advice: list | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(Q, N) candidates probed in each episode (its readings of every candidate: `query`, (Q, C)) and the class
    named after each probe: the planner's choices, or those of `choose(k, used, query, log_w)` -> (Q,) candidate
    indices (a fixed sequence, or a network copying the planner; None: the planner's), used (Q, C) bool marking the
    candidates probed so far, log_w (Q, L) the library's log weights after them (what the namer believes).
    library: (C, L) readings. With a faulty sensor, `faulty` (N, Q, C) holds what probe k reads from each candidate
    (an independent draw of the sensor's faults per probe) and `noise` its fault rates: the library is weighed with
    the sensor's model (log_likelihood), and the planner may probe a candidate again, since a second reading can
    outvote a corrupted first one. With `two_step`, the planner looks two probes ahead for its first probes. With
    `advice` (a list), the planner's view of every state the episodes reach is appended to it, also where `choose`
    decides: (Q, C) per probe, the class entropy each candidate would leave (inf where probed in ideal mode), whose
    argmin is its pick one probe ahead; to teach a copy on the copy's own states, or on the planner's ranking."""
    log_w = torch.zeros(len(query), library.shape[1])
    weights = torch.ones_like(log_w)  # exp(log_w) relative to each episode's most likely library episode
    used = torch.zeros(query.shape, dtype=torch.bool)
    rows, chosen, named = torch.arange(len(query)), [], []
    one_hot = torch.nn.functional.one_hot(labels, n_classes).float()
    for k in range(n_probes):
        c = None if choose is None else choose(k, used, query, log_w)
        if c is None or advice is not None:
            score = expected_entropy(cells, weights, n_bins, n_classes, noise)
            if faulty is None:  # in ideal mode a repeated probe reads the same
                score = score.masked_fill(used, math.inf)
            if advice is not None:
                advice.append(score)
            if c is None:
                c = score.argmin(1) if two_step is None or k >= two_step.probes else two_step(weights, used, score)
        used[rows, c] = True
        chosen.append(c)
        read = query[rows, c] if faulty is None else faulty[k, rows, c]
        log_w = log_w + log_likelihood(read[:, None], library[c], sigma, mismatch, noise, probe_length)
        weights = torch.exp(log_w - log_w.max(1, keepdim=True).values)
        named.append((weights @ one_hot).argmax(1))
    return torch.stack(chosen, 1).numpy(), torch.stack(named, 1).numpy()


def fixed_sequence(sequence: np.ndarray) -> Choose:
    """A `choose` for probe_episodes: candidate sequence[k] at probe k in every episode."""
    return lambda k, used, query, log_w: torch.full((len(query),), int(sequence[k]))


def random_choice(generator: torch.Generator) -> Choose:
    """A `choose` for probe_episodes: an unprobed candidate at random."""
    def choose(k: int, used: torch.Tensor, query: torch.Tensor, log_w: torch.Tensor) -> torch.Tensor:
        return torch.multinomial((~used).float(), 1, generator=generator)[:, 0]
    return choose


def first_two(rule: dict, width: float, n_bins: int) -> Choose:
    """A `choose` for probe_episodes: best_first_two's rule for the first two probes, the planner's after."""
    def choose(k: int, used: torch.Tensor, query: torch.Tensor, log_w: torch.Tensor) -> torch.Tensor | None:
        if k == 0:
            return torch.full((len(query),), rule["first"])
        if k == 1:
            return torch.from_numpy(rule["second"][reading_bins(query[:, rule["first"]].numpy(), width, n_bins)])
        return None
    return choose


def summary(chosen: np.ndarray, named: np.ndarray, labels: np.ndarray, query: np.ndarray, candidates: np.ndarray,
            offsets: np.ndarray, sim: ProbeSimulator) -> dict:
    """Accuracy after each probe, touches per episode (all, first half), mean tilt from vertical, the share of
    probes leaning across the line that lean towards the object's side, the share of probes leaning along it,
    distinct places per episode, and probes per episode that read a candidate again (under faults)."""
    touched = np.take_along_axis(query, chosen, 1) != MISS
    requests = candidates[chosen]
    direction = sim.scene.request_to_probe(requests.reshape(-1, 4))[1].reshape(*requests.shape[:2], 3)
    tilt = np.degrees(np.arccos(np.clip(-direction[..., 2], -1, 1)))
    across, along = np.abs(direction[..., 0]) > 1e-6, np.abs(direction[..., 1]) > 1e-6
    towards = np.sign(direction[..., 0]) == np.sign(offsets)[:, None]
    return {"accuracy": [round(float(a), 4) for a in (named == labels[:, None]).mean(0)],
            "touches": round(float(touched.sum(1).mean()), 3),
            "touches_first_half": round(float(touched[:, :chosen.shape[1] // 2].sum(1).mean()), 3),
            "tilt_deg": round(float(tilt.mean()), 2),
            "leaning_towards_object": round(float(towards[across].mean()), 3) if across.any() else None,
            "leaning_along_line": round(float(along.mean()), 3),
            "places": round(float(np.mean([len(set(requests[i, :, 0])) for i in range(len(requests))])), 2),
            "repeats": round(float(np.mean([chosen.shape[1] - len(set(row)) for row in chosen.tolist()])), 3)}


def save_rollouts(path: Path, labels: np.ndarray, poses: np.ndarray, requests: np.ndarray, meta: dict,
                  faults: np.ndarray | None = None) -> None:
    """Write the planner's episodes, (E,) classes, (E, P) poses and (E, N, 4) requests, and under noise the (E, N, 2)
    fault uniforms its probes read with (ProbeSimulator.probe), with `meta` (the run's arguments and summary, the
    objects, the pose regions' seed and the commit) as JSON, in one atomic write."""
    import io
    meta = {k: str(v) if isinstance(v, Path) else v for k, v in meta.items()}
    meta |= {"objects": "hg4", "eval_seed": 0, "commit": commit(("hg", "scripts"))}
    buffer = io.BytesIO()
    np.savez_compressed(buffer, labels=labels, poses=poses, requests=requests.astype(np.float32),
                        meta=np.array(json.dumps(meta)), **({} if faults is None else {"faults": faults}))
    write_atomic(path, buffer.getvalue())


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--episodes", type=int, default=1024)
    parser.add_argument("--split", choices=SPLITS, default="val")
    parser.add_argument("--table-episodes", action="store_true",
                        help="score the episodes the tables score on this split (data.eval_seed 0; --episodes: 1024 "
                             "for val, 2048 for test) instead of episodes drawn with --seed")
    parser.add_argument("--mode", choices=["ideal", "arm"], default="ideal",
                        help="how the scored episodes are probed (the library always in ideal mode)")
    parser.add_argument("--library", type=int, default=262144, help="library episodes, each probed with every candidate")
    parser.add_argument("--library-split", choices=SPLITS, default="val")
    parser.add_argument("--shifts", type=int, default=0,
                        help="also the library's episodes moved along the line by up to this many place steps each way")
    parser.add_argument("--mirror", action="store_true", help="also the library's episodes mirrored across the line")
    parser.add_argument("--n-probes", type=int, default=10)
    parser.add_argument("--places", type=int, default=11, help="candidate places along the line")
    parser.add_argument("--span", type=float, default=0.5, help="the middle of the line they cover (request units)")
    parser.add_argument("--leans", type=float, nargs="*", default=[0.6, 1.0, 2.0],
                        help="leans across the line, as model.scan_side (0.6: 16.7 degrees, 1.0: 26.6, 2.0: 45)")
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
                        help="sensor fault rate of the scored episodes' probes: SensorNoise(miss_prob = false_contact_prob "
                             "= rate), as reproduce_noise.py; the planner weighs with the sensor's model and may re-probe")
    parser.add_argument("--best-first-two", action="store_true",
                        help="also score the planner with its first two probes chosen to name the library best after "
                             "two (best_first_two), not greedily")
    parser.add_argument("--two-step", type=int, default=0, metavar="PROBES",
                        help="also score the planner looking two probes ahead for its first PROBES probes (TwoStep)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--save-rollouts", type=Path, help="write the planner's episodes here (.npz): a teacher")
    args = parser.parse_args()
    for name in ("episodes", "library", "n_probes", "places"):
        if getattr(args, name) < 1:
            parser.error(f"--{name.replace('_', '-')} {getattr(args, name)}: must be >= 1")
    if not 0 < args.span <= 1:
        parser.error(f"--span {args.span}: must be in (0, 1]")
    if args.shifts < 0 or (args.shifts and (args.places < 2 or args.span * (1 + 2 * args.shifts / (args.places - 1)) > 1)):
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
    if args.two_step and (args.noise or not 0 < args.two_step < args.n_probes):
        parser.error(f"--two-step {args.two_step}: needs a fault-free sensor (no --noise) and 0 < PROBES < --n-probes")
    if args.no_planner and (not (args.fixed or args.random) or args.save_rollouts or args.best_first_two
                            or args.two_step):
        parser.error("--no-planner: needs --fixed or --random, and no option that scores or saves the planner "
                     "(--save-rollouts, --best-first-two, --two-step)")
    if args.library_seed is not None and args.save_rollouts:
        parser.error("--library-seed with --save-rollouts: a teacher file records one seed, its library's "
                     "(hg.sim.library.teacher_library), so plan it with --seed alone")
    library_seed = args.seed if args.library_seed is None else args.library_seed
    if args.best_first_two and (args.noise or args.n_probes < 2):
        parser.error("--best-first-two: needs --n-probes >= 2 and a fault-free sensor (no --noise); its rule for the "
                     "second probe reads the first's clean reading")
    candidates = candidate_requests(args.places, args.span, args.leans, args.along_leans)
    if args.n_probes > len(candidates):
        parser.error(f"--n-probes {args.n_probes}: more than the {len(candidates)} candidates")

    torch.set_num_threads(1)
    start = time.time()
    sim = ProbeSimulator("hg4", batch_size=1024, mode="ideal", seed=args.seed)
    regions, n_classes = PoseRegions(sim.scene), len(sim.classes)
    if args.table_episodes:  # the tables' own episodes: EvalEpisodes as ProbeDataModule builds them
        from hg.lightning.data import EvalEpisodes
        batches = EvalEpisodes(regions, args.split, args.episodes, 256, n_classes, seed=0).batches
        query_labels = np.concatenate([b["labels"].numpy() for b in batches])
        query_poses = np.concatenate([b["poses"].numpy() for b in batches])
    else:
        query_labels, query_poses = sample_episodes(regions, args.split, args.episodes, n_classes,
                                                    np.random.default_rng(args.seed))
    labels, poses = sample_episodes(regions, args.library_split, args.library, n_classes,
                                    np.random.default_rng(library_seed + 1))
    library, labels, _ = library_readings(sim, labels, poses, args.places, args.span, args.leans, args.shifts,
                                       args.mirror, args.along_leans)
    noise = SensorNoise(miss_prob=args.noise, false_contact_prob=args.noise)
    with ProbeSimulator("hg4", batch_size=256 if args.mode == "arm" else 1024, mode=args.mode, noise=noise,
                        seed=args.seed) as probe:  # in arm mode its achieved probes stray from the requested ones
        query = readings(probe, query_labels, query_poses, candidates, clean=True)
        faults = faulty = None
        if args.noise:  # each episode's probe k's faults, drawn up front so that a teacher file can replay them
            faults = np.random.default_rng(args.seed + 2).random((len(query), args.n_probes, 2))
            faulty = torch.from_numpy(np.stack([readings(probe, query_labels, query_poses, candidates,
                                                         faults=faults[:, k]) for k in range(args.n_probes)]))
    print(f"{len(candidates)} candidates x {args.library} {args.library_split} library episodes "
          f"({len(library)} with their shifts and mirror images), "
          f"{args.episodes} {args.split} episodes ({args.mode} mode): probed in {time.time() - start:.0f} s", flush=True)
    n_bins = int(np.ceil(sim.scene.probe_length / args.bin)) + 2
    bins = reading_bins(library, args.bin, n_bins)
    cells = cell_matrix(bins, labels, n_bins, n_classes)
    library_t, labels_t, query_t = torch.from_numpy(library.T.copy()), torch.from_numpy(labels), torch.from_numpy(query)
    offsets = query_poses[:, 0] - sim.scene.probe_x
    order = np.argsort(np.abs(np.linspace(-args.span, args.span, args.places)), kind="stable")
    fixed = fixed_sequence(order * (len(candidates) // args.places))  # straight down, centre out
    runs = ({} if args.no_planner else {"planner": (None, None)}) | ({"fixed": (fixed, None)} if args.fixed else {}) | (
        {"random": (random_choice(torch.Generator().manual_seed(args.seed)), None)} if args.random else {})
    if args.two_step:
        runs["two_step"] = (None, TwoStep(bins, labels, n_bins, n_classes, args.two_step))
    results = {}
    if args.best_first_two:
        start = time.time()
        rules = best_first_two(bins, labels, n_bins, n_classes)
        results["first_two_on_library"] = {name: {"first": int(r["first"]), "accuracy": round(float(r["accuracy"]), 4)}
                                           for name, r in rules.items()}
        print(f"first two probes named on the library: {results['first_two_on_library']} ({time.time() - start:.0f} s)",
              flush=True)
        runs["best_first_two"] = (first_two(rules["best"], args.bin, n_bins), None)
    for name, (choose, two_step) in runs.items():
        start = time.time()
        chosen, named = map(np.concatenate, zip(*(
            probe_episodes(query_t[i:i + CHUNK], library_t, cells, labels_t, args.n_probes, n_bins, n_classes,
                           args.sigma, args.mismatch, choose, None if faulty is None else faulty[:, i:i + CHUNK],
                           noise, sim.scene.probe_length, two_step) for i in range(0, len(query), CHUNK))))
        r = results[name] = summary(chosen, named, query_labels, query, candidates, offsets, sim)
        if name == "planner" and args.save_rollouts:
            save_rollouts(args.save_rollouts, query_labels, query_poses, candidates[chosen], vars(args) | {"summary": r},
                          faults)
        print(f"{name}: accuracy after each probe " + " ".join(f"{a:.3f}" for a in r["accuracy"])
              + f"; {r['touches']:.2f} touches ({r['touches_first_half']:.2f} in the first half), tilt "
              f"{r['tilt_deg']:.1f} deg, {r['places']:.1f} places ({time.time() - start:.0f} s)", flush=True)
    sim.close()
    print(json.dumps(results | {"library": args.library, "library_split": args.library_split,
                                "library_seed": library_seed, "shifts": args.shifts, "mirror": args.mirror,
                                "library_episodes": len(library),
                                "noise": args.noise, "episodes": args.episodes, "split": args.split, "mode": args.mode,
                                "table_episodes": args.table_episodes, "candidates": len(candidates),
                                "along_leans": args.along_leans}))


if __name__ == "__main__":
    main()
