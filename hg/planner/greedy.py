"""The greedy information-gain planner: each probe the candidate whose reading would leave the least class entropy.

Before each probe the planner weighs its library (hg.planner.LibraryClassifier: how well each library episode's
readings of the probes so far match this episode's) and takes the candidate whose reading would leave the least
entropy over the class, expected over the weighted library (readings binned by `bin`). After each probe the
classifier names the class. `evaluate` scores it on given episodes beside probes placed by no one (the straight
centre-out scan of the candidate places, unprobed candidates at random) named by the same classifier; under sensor
faults the planner weighs with the sensor's model and may probe a candidate again. By default it weighs a pruned
classifier's kept library episodes and ranks its candidates on a sample of them (GreedyPlanner): over ten times as
many decisions per second as weighing the whole library (`exact`, the reference), at its accuracy (docs/benchmarks.md).
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import scipy.sparse
import torch

from hg.planner.classifier import Choose, Kept, KeptWeights, LibraryClassifier
from hg.planner.kernels import candidate_mass, sampled_mass
from hg.planner.library import MISS, CandidateGrid, LibraryRecipe, readings
from hg.sim.objects import ObjectSet
from hg.sim.heldout import Regions
from hg.sim.robot import DEFAULT_URDF
from hg.sim.scene import Scene
from hg.sim.simulator import ProbeSimulator, SensorNoise

CHUNK = 128  # scored episodes planned side by side: their weights over the library are (CHUNK, L)
PROBERS = ("planner", "fixed", "random")
PRUNE = 20.0  # evaluate's classifier keeps the library episodes within exp(-20) of an episode's best (2e-9)
SAMPLES = 512  # per class: the kept library episodes drawn by weight to rank the candidates (GreedyPlanner)
REFINE = 3  # the best-ranked candidates whose entropy is then computed over every kept library episode


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
    return entropy_left(mass, weights.sum(-1, keepdim=True), noise)


def entropy_left(mass: torch.Tensor, total: torch.Tensor | float, noise: SensorNoise = SensorNoise()) -> torch.Tensor:
    """(Q, C) the class entropy left after reading each candidate, expected: mass (Q, C, bins, classes) the weight in
    each (binned reading, class) cell of each candidate (bin 0: a miss), total (Q, 1) the weight of all; with sensor
    faults `noise` as in expected_entropy."""
    n_bins = mass.shape[2]
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
    return (per_bin[..., 0] * entropy).sum(-1) / total


def reading_bins(readings: np.ndarray, width: float, n_bins: int) -> np.ndarray:
    """The entropy's bin of each reading: 0 for a miss, then `width`-wide bins along the ray."""
    return np.where(readings == MISS, 0, 1 + np.minimum(readings / width, n_bins - 2)).astype(np.int64)


class GreedyPlanner:
    """A `Choose` for LibraryClassifier.play: the unprobed candidate (any candidate, under sensor faults: a second
    reading can outvote a corrupted first one) whose reading would leave the least class entropy, expected over the
    classifier's weighting of its library, with the classifier's sensor model. Over a pruned classifier's kept library
    episodes (LibraryClassifier(prune=...)) it ranks the candidates by the entropy over `samples` of each class's kept
    episodes drawn by weight (all of them where it keeps no more) and takes, of the `refine` best-ranked, the one whose
    entropy over every kept episode is least (the samples' ranking is close, but near ties are common and need the exact
    figure). The choice before any probe, alike for every episode, is made once, over the whole library."""

    def __init__(self, classifier: LibraryClassifier, bin: float = 0.01, samples: int = SAMPLES,
                 refine: int = REFINE) -> None:
        if bin <= 0 or samples < 1 or refine < 1:
            raise ValueError(f"GreedyPlanner: bin={bin} must be > 0, samples={samples} and refine={refine} >= 1")
        self.noise, self.samples, self.refine = classifier.noise, samples, refine
        self.n_bins, self.n_classes = int(np.ceil(classifier.probe_length / bin)) + 2, classifier.n_classes
        bins = reading_bins(classifier.library.T.cpu().numpy(), bin, self.n_bins)  # (L, C), the classifier's order
        labels = classifier.labels.cpu().numpy()
        # the library's episodes as they were drawn (the classifier holds them by class): weighed in that order the
        # entropy rounds as it did before the planner moved into this package (743bddf), so it chooses the same
        # probes to the bit, and a rounding tie between two mirror-image candidates goes the same way
        self.drawn = classifier.drawn.cpu()
        self.cells = cell_matrix(bins[self.drawn.numpy()], labels[self.drawn.numpy()], self.n_bins, self.n_classes)
        self.repeats = bool(self.noise.miss_prob or self.noise.false_contact_prob)  # else a probe reads the same
        if classifier.prune is not None:
            # each library episode's (binned reading, class) cell per candidate, (L, C) for the samples (offset by the
            # candidate's first cell) and (C, L) for one candidate over every kept episode (hg.planner.kernels)
            codes = (bins * self.n_classes + labels[:, None]).astype(np.int32)
            size = self.n_bins * self.n_classes  # cells per candidate
            self.codes = np.ascontiguousarray(codes + np.arange(codes.shape[1], dtype=np.int32) * size)
            self.columns = np.ascontiguousarray(codes.T)
            self.first = self.entropy(torch.zeros(1, len(codes)), torch.zeros(1, codes.shape[1], dtype=torch.bool))[0]
            self.cells = None  # the whole library is weighed only before the first probe

    def entropy(self, log_w: torch.Tensor, used: torch.Tensor) -> torch.Tensor:
        """(Q, C) the class entropy each candidate would leave (inf where probed, unless it may probe again)."""
        weights = torch.exp(log_w - log_w.max(1, keepdim=True).values)  # relative to the most likely episode
        score = expected_entropy(self.cells, weights.cpu()[:, self.drawn], self.n_bins, self.n_classes, self.noise)
        return score if self.repeats else score.masked_fill(used.cpu(), math.inf)

    def __call__(self, k: int, log_w: torch.Tensor | KeptWeights, used: torch.Tensor) -> torch.Tensor:
        if not isinstance(log_w, KeptWeights):
            return self.entropy(log_w, used).argmin(1).to(log_w.device)
        shared: dict[tuple, int] = {}  # episodes whose probes so far were the same share a state and a choice
        for state, probed in zip(log_w, used.cpu()):
            if (key := (state, probed.numpy().tobytes())) not in shared:
                shared[key] = self.choose_kept(state, probed)
        return torch.tensor([shared[state, probed.numpy().tobytes()] for state, probed in zip(log_w, used.cpu())],
                            device=used.device)

    def choose_kept(self, state: Kept | None, probed: torch.Tensor) -> int:
        """The choice of one episode whose pruned weights are `state` (None: before any probe)."""
        score, sampled = (self.first.clone(), False) if state is None else self.sampled_entropy(state)
        if not self.repeats:
            score[probed] = math.inf
        if not sampled or self.refine == 1:
            return int(score.argmin())
        best = torch.topk(score, min(self.refine, len(score)), largest=False).indices
        best = best[torch.isfinite(score[best])]
        return int(best[self.kept_entropy(state, best.tolist()).argmin()])

    def sampled_entropy(self, state: Kept) -> tuple[torch.Tensor, bool]:
        """(C,) the entropy each candidate would leave over `samples` of each class's kept episodes drawn by weight
        (systematic: at every 1/samples of the class's weight, so an episode drawn m times weighs m/samples of it), or
        over all of a class's where it keeps no more; and whether any class was sampled."""
        mass, drawn = sampled_mass(self.codes, state.index, state.weight, state.ends, state.class_mass, self.samples,
                                   self.codes.shape[1] * self.n_bins * self.n_classes)
        return self.left(mass, state), drawn

    def kept_entropy(self, state: Kept, candidates: list[int]) -> torch.Tensor:
        """(len(candidates),) the entropy each of `candidates` would leave over every kept library episode."""
        return self.left(candidate_mass(self.columns, np.asarray(candidates, np.int64), state.index, state.weight,
                                        self.n_bins * self.n_classes), state)

    def left(self, mass: np.ndarray, state: Kept) -> torch.Tensor:
        """entropy_left of one episode's cell masses, flat (candidates * bins * classes,)."""
        mass = torch.from_numpy(mass).reshape(1, -1, self.n_bins, self.n_classes)
        return entropy_left(mass, float(state.class_mass.sum()), self.noise)[0]


def fixed_choice(sequence: np.ndarray) -> Choose:
    """A `Choose`: candidate sequence[k] at probe k in every episode."""
    return lambda k, log_w, used: torch.full((len(used),), int(sequence[k]), device=used.device)


def random_choice(generator: torch.Generator) -> Choose:
    """A `Choose`: an unprobed candidate at random."""
    return lambda k, log_w, used: torch.multinomial((~used).float(), 1, generator=generator)[:, 0]


def centre_out_scan(grid: CandidateGrid) -> np.ndarray:
    """(places,) the straight-down candidate at each place, from the middle of the line outwards."""
    order = np.argsort(np.abs(np.linspace(-grid.span, grid.span, grid.places)), kind="stable")
    return order * grid.directions


def plan(classifier: LibraryClassifier, query: torch.Tensor, n_probes: int, choose: Choose,
         faulty: torch.Tensor | None = None, chunk: int = CHUNK) -> tuple[np.ndarray, np.ndarray]:
    """(Q, N) candidates probed in each episode and the class the classifier names after each probe, for episodes
    whose readings of every candidate are `query` (Q, C), choices by `choose` (GreedyPlanner, fixed_choice,
    random_choice...). With a faulty sensor `faulty` (N, Q, C) holds what probe k reads from each candidate (an
    independent draw of the sensor's faults per probe). `chunk` episodes side by side."""
    chosen, named = [], []
    for start in range(0, len(query), chunk):
        rows = torch.arange(start, min(start + chunk, len(query)))
        local = torch.arange(len(rows))
        source = query[rows] if faulty is None else faulty[:, rows]
        read = (lambda k, c: source[local, c]) if faulty is None else (lambda k, c: source[k, local, c])
        c, n = classifier.play(n_probes, len(rows), choose, read, classifier.name)
        chosen.append(c)
        named.append(n)
    return torch.cat(chosen).numpy(), torch.cat(named).numpy()


def summary(chosen: np.ndarray, named: np.ndarray, labels: np.ndarray, query: np.ndarray, candidates: np.ndarray,
            poses: np.ndarray, scene: Scene) -> dict:
    """Accuracy after each probe, touches per episode (all, first half), mean tilt from vertical, the share of
    probes leaning across the line that lean towards the object's side, the share of probes leaning along it,
    distinct places per episode, and probes per episode that read a candidate again (under faults)."""
    touched = np.take_along_axis(query, chosen, 1) != MISS
    requests = candidates[chosen]
    direction = scene.request_to_probe(requests.reshape(-1, 4))[1].reshape(*requests.shape[:2], 3)
    tilt = np.degrees(np.arccos(np.clip(-direction[..., 2], -1, 1)))
    across, along = np.abs(direction[..., 0]) > 1e-6, np.abs(direction[..., 1]) > 1e-6
    towards = np.sign(direction[..., 0]) == np.sign(poses[:, 0] - scene.probe_x)[:, None]
    return {"accuracy": [round(float(a), 4) for a in (named == labels[:, None]).mean(0)],
            "touches": round(float(touched.sum(1).mean()), 3),
            "touches_first_half": round(float(touched[:, :chosen.shape[1] // 2].sum(1).mean()), 3),
            "tilt_deg": round(float(tilt.mean()), 2),
            "leaning_towards_object": round(float(towards[across].mean()), 3) if across.any() else None,
            "leaning_along_line": round(float(along.mean()), 3),
            "places": round(float(np.mean([len(set(requests[i, :, 0])) for i in range(len(requests))])), 2),
            "repeats": round(float(np.mean([chosen.shape[1] - len(set(row)) for row in chosen.tolist()])), 3)}


@dataclass
class Rollouts:
    """One way of probing the scored episodes: (E, N) candidates probed, (E, N) classes named after each probe,
    (E, N, 4) their requests, and summary() of them."""

    chosen: np.ndarray
    named: np.ndarray
    requests: np.ndarray
    summary: dict


@dataclass
class Evaluation:
    """evaluate()'s result: each prober's rollouts, the (E, N, 2) fault uniforms every probe read with (None without
    sensor faults: a teacher file replays them), the library's size with its moves and mirror images and the planner's
    settings (prune, samples, refine; all None for the exact planner)."""

    rollouts: dict[str, Rollouts]
    faults: np.ndarray | None
    library_episodes: int
    settings: dict


def evaluate(objects: str | Path | ObjectSet, labels: np.ndarray, poses: np.ndarray, regions: Regions, *,
             robot: str | Path = DEFAULT_URDF, mode: str = "ideal", noise: SensorNoise = SensorNoise(),
             grid: CandidateGrid = CandidateGrid(), recipe: LibraryRecipe = LibraryRecipe(), bin: float = 0.01,
             n_probes: int = 10, probers: tuple[str, ...] = ("planner",), seed: int = 0, exact: bool = False
             ) -> Evaluation:
    """Probe the episodes (labels (E,), poses (E, 6)) of regions.scene `n_probes` times by each of `probers`: the
    greedy planner, the straight centre-out scan of the candidate places ("fixed") and unprobed candidates at
    random ("random", drawn with `seed`), every sequence named by one LibraryClassifier over `recipe`'s library of
    `regions` poses. The library is read in ideal mode; the scored episodes in `mode` with `robot` (in arm mode its
    achieved probes stray from the requested ones; every candidate is read up front, as the arm would read the chosen
    one), through a sensor with faults `noise` (contact faults only: each probe's fault uniforms are drawn with
    seed + 2, so that a teacher file can replay them). The classifier keeps per episode the library episodes within
    PRUNE of its best and the planner ranks on samples of them (GreedyPlanner), and every prober's probes are named
    by it; `exact` weighs the whole library (the reference, over ten times slower: docs/benchmarks.md)."""
    if unknown := sorted(set(probers) - set(PROBERS)):
        raise ValueError(f"evaluate: probers {unknown}, expected some of {PROBERS}")
    candidates = grid.requests()
    if n_probes < 1 or n_probes > len(candidates):
        raise ValueError(f"evaluate: n_probes={n_probes} must be in [1, {len(candidates)}] (the candidates)")
    if "fixed" in probers and n_probes > grid.places:
        raise ValueError(f"evaluate: the fixed scan probes each of the {grid.places} places once, n_probes={n_probes}")
    if noise.position_std:
        raise ValueError(f"evaluate: noise.position_std={noise.position_std}: the planner's faults are contact faults "
                         "only (miss_prob, false_contact_prob), replayable from their uniforms")
    scene = regions.scene
    with ProbeSimulator(objects, batch_size=1024, scene=scene, mode="ideal", seed=seed) as sim:
        classifier = LibraryClassifier.build(sim, regions, grid, recipe, noise, None if exact else PRUNE)
        object_set = sim.objects
    with ProbeSimulator(object_set, batch_size=256 if mode == "arm" else 1024, scene=scene, mode=mode, robot=robot,
                        noise=noise, seed=seed) as probe:
        query = readings(probe, labels, poses, candidates, clean=True)
        faults = faulty = None
        if noise.miss_prob or noise.false_contact_prob:  # probe k's faults, drawn up front for a teacher to replay
            faults = np.random.default_rng(seed + 2).random((len(query), n_probes, 2))
            faulty = torch.from_numpy(np.stack([readings(probe, labels, poses, candidates, faults=faults[:, k])
                                                for k in range(n_probes)]))
    choose = {"planner": lambda: GreedyPlanner(classifier, bin),
              "fixed": lambda: fixed_choice(centre_out_scan(grid)),
              "random": lambda: random_choice(torch.Generator().manual_seed(seed))}
    rollouts = {}
    for name in probers:
        chosen, named = plan(classifier, torch.from_numpy(query), n_probes, choose[name](), faulty)
        rollouts[name] = Rollouts(chosen, named, candidates[chosen],
                                  summary(chosen, named, labels, query, candidates, poses, scene))
    settings = dict.fromkeys(("prune", "samples", "refine")) if exact else \
        {"prune": PRUNE, "samples": SAMPLES, "refine": REFINE}
    return Evaluation(rollouts, faults, classifier.library.shape[1], settings)
