"""The Bayes classifier over a library of simulated training episodes, and its one update loop.

An episode's probes so far weigh every library episode by the likelihood of their readings under that episode's
readings of the same candidates; the weights summed by class are the posterior. The greedy planner, the evaluation
path and any analysis update the weights with LibraryClassifier.update, probe after probe in LibraryClassifier.play.
Its library may hold the training episodes moved along the line and mirrored (hg.planner.library), so it reaches
positions its training poses never held (docs/findings.md). With `prune` it keeps, per episode, only the library
episodes whose log weight lies within `prune` of its best (Kept): what the fast planner weighs (docs/benchmarks.md).
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable

import numpy as np
import torch
from torch import Tensor, nn

from hg.planner.kernels import class_sums, likelihood_update
from hg.planner.library import MISS, CandidateGrid, LibraryRecipe
from hg.sim.heldout import Regions
from hg.sim.simulator import ProbeSimulator, SensorNoise

# (k, log_w (B, L) or KeptWeights, used (B, C) bool) -> (B,) the candidates of probe k, given the library's log weights
# after the probes so far and which candidates they probed
Choose = Callable[[int, Tensor, Tensor], Tensor]
# (k, chosen (B,)) -> (B,) what probe k read from the chosen candidates (MISS: nothing)
Read = Callable[[int, Tensor], Tensor]


def likelihood_terms(sigma: float, mismatch: float, noise: SensorNoise = SensorNoise(),
                     probe_length: float = 1.0) -> tuple[float, float, float, float, float]:
    """log_likelihood's numbers: the touch's Gaussian spread, and the log-likelihood where both missed, where only
    the library episode touched, where only the reading did, and the Gaussian's offset where both touched."""
    sigma = math.hypot(sigma, noise.position_std)
    kept = lambda p: math.log1p(-min(p, 1 - 1e-12))  # log(1 - p): a reading the fault left alone
    false_touch = noise.false_contact_prob * sigma * math.sqrt(2 * math.pi) / probe_length  # on the Gaussian's scale
    return (sigma, kept(noise.false_contact_prob), math.log(max(noise.miss_prob, mismatch)),
            math.log(max(false_touch, mismatch)), kept(noise.miss_prob))


def log_likelihood(readings: Tensor, library: Tensor, sigma: float, mismatch: float,
                   noise: SensorNoise = SensorNoise(), probe_length: float = 1.0) -> Tensor:
    """log p(each episode's reading (Q, 1) | each library episode's reading (Q, L)), up to a constant: a Gaussian in
    the touch's distance along the ray, log(mismatch) where one touched and the other did not. With sensor faults
    (`noise`, as the simulator makes them) that is the sensor's own model: a touch is reported as a miss with
    miss_prob, a miss as a touch anywhere along the probe_length-long ray with false_contact_prob, and the touch
    point is blurred by position_std; `mismatch` stays the floor of either mix-up (the library is read in ideal mode,
    the arm's probes stray). Without faults this is the plain rule."""
    sigma, both_missed, library_touched, library_missed, both_touched = likelihood_terms(sigma, mismatch, noise,
                                                                                         probe_length)
    touched = readings != MISS
    # in place over (Q, L), the classifier's and the planner's costliest step: 2.4x faster than torch.where over
    # fresh tensors, to the bit (the same operations in the same order; hg.planner.kernels repeats them for one reading)
    out = (library - readings).div_(sigma).square_().mul_(-0.5).add_(both_touched)  # both touched
    out.masked_fill_(~touched.expand_as(out), library_touched)  # a touch read as a miss
    library_missed = torch.where(touched, library_missed, both_missed)
    return torch.where(library == MISS, library_missed.to(out.dtype), out)


@dataclass(frozen=True, eq=False)
class Kept:
    """One episode's library weights as a pruned classifier keeps them: the library episodes within `prune` of its best
    log weight, by position in the classifier's library (ascending, so each class is one slice, ending before
    ends[class]), their log weights, their weights relative to the best and those summed by class (what the class
    posterior and the planner's samples read). Never changed in place: episodes whose readings so far are the same share
    one (LibraryClassifier.update)."""

    index: np.ndarray  # (S,) int32
    log_w: np.ndarray  # (S,) float32
    weight: np.ndarray  # (S,) float32, exp(log_w - max), as the exact planner weighs
    ends: np.ndarray  # (classes,)
    class_mass: np.ndarray  # (classes,) float64, weight summed by class

    @classmethod
    def weigh(cls, index: np.ndarray, log_w: np.ndarray, best: np.float32, class_ends: np.ndarray) -> "Kept":
        """The kept library episodes `index` with log weights log_w, the best of which is `best`."""
        weight, ends = np.exp(log_w - best), np.searchsorted(index, class_ends)
        return cls(index, log_w, weight, ends, class_sums(weight, ends))


class KeptWeights(list):
    """A pruned classifier's weights of B episodes (LibraryClassifier.prior, update): one Kept per episode, None before
    its first probe (every library episode, at weight 1)."""


class LibraryClassifier(nn.Module):
    """log p(class | the readings of the candidates probed so far) over a library of episodes each read with every
    candidate: every library episode weighed by the likelihood of the readings, the weights summed by class (a
    uniform prior over the library's episodes). Nothing in it learns; the library is a buffer left out of
    checkpoints (it is rebuilt from its recipe, LibraryRecipe, and holds ~10^5-10^6 episodes). With `prune` (on the
    CPU) each episode keeps only the library episodes whose log weight lies within `prune` of its best, and drops the
    rest for good: a probe multiplies no weight by more than 1, so a dropped episode never weighs more than
    exp(-prune) of the best did when it was dropped. None weighs the whole library (the exact classifier)."""

    def __init__(self, library: Tensor, labels: Tensor, n_classes: int, sigma: float, mismatch: float,
                 noise: SensorNoise = SensorNoise(), probe_length: float = 1.0, chunk: int = 32,
                 positions: Tensor | None = None, prune: float | None = None) -> None:
        """library (L, C) readings (MISS where nothing was touched), labels (L,); `noise` the faults of the sensor
        whose readings it will name (log_likelihood); positions (L, 2) where each library episode's object lies (x
        across the line, y along it, in units of the pose range's half-width), for its `belief`; `chunk` rows of
        (chunk, L) weights at a time; `prune` the log-weight margin of the kept library episodes (None: all)."""
        super().__init__()
        if library.ndim != 2 or labels.shape != library.shape[:1]:
            raise ValueError(f"LibraryClassifier: library {tuple(library.shape)} and labels {tuple(labels.shape)}, "
                             "expected (L, C) and (L,)")
        if prune is not None and not prune > 0:
            raise ValueError(f"LibraryClassifier: prune={prune} must be > 0 (or None: the whole library)")
        if positions is not None and positions.shape != (len(labels), 2):
            raise ValueError(f"LibraryClassifier: positions {tuple(positions.shape)}, expected ({len(labels)}, 2)")
        missing = sorted(set(range(n_classes)) - set(labels.unique().tolist()))
        if missing:
            raise ValueError(f"LibraryClassifier: the library holds no episode of class {missing}")
        order = torch.argsort(labels, stable=True)  # by class, so each class's weights are one slice
        self.register_buffer("library", library[order].T.contiguous().float(), persistent=False)  # (C, L)
        self.register_buffer("labels", labels[order].long(), persistent=False)  # (L,) in the library's order
        self.register_buffer("drawn", torch.argsort(order), persistent=False)  # (L,) episode l as given: [:, drawn[l]]
        self.register_buffer("one_hot", torch.nn.functional.one_hot(labels[order], n_classes).float(),
                             persistent=False)
        self.register_buffer("positions", None if positions is None else positions[order].float(), persistent=False)
        self.ends = torch.bincount(labels, minlength=n_classes).cumsum(0).tolist()
        self.sigma, self.mismatch, self.chunk, self.prune = sigma, mismatch, chunk, prune
        self.noise, self.probe_length = noise, probe_length
        if prune is not None:  # update_kept's: the whole library at log weight 0, and where the kept episodes go
            # (scratch shared by every update: one update at a time per classifier)
            self.everything = np.arange(len(labels), dtype=np.int32), np.zeros(len(labels), np.float32)
            self.kept_index, self.kept_log_w = np.empty(len(labels), np.int32), np.empty(len(labels), np.float32)

    @classmethod
    def build(cls, sim: ProbeSimulator, regions: Regions, grid: CandidateGrid, recipe: LibraryRecipe,
              noise: SensorNoise = SensorNoise(), prune: float | None = None,
              drawn: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None) -> "LibraryClassifier":
        """The classifier over the library `recipe` draws, read by `sim` (ideal mode) with `grid`'s candidates,
        naming the readings of a sensor with faults `noise`; positions in units of the pose range's half-width.
        `drawn`: what recipe.draw returned, if the library was drawn already (one library, several classifiers)."""
        readings, labels, positions = recipe.draw(sim, regions, grid) if drawn is None else drawn
        half_width = max(sim.scene.object_y[1], sim.scene.object_x[1])  # the belief's unit of position
        return cls(torch.from_numpy(readings), torch.from_numpy(labels).long(), len(sim.classes), recipe.sigma,
                   recipe.mismatch, noise, sim.scene.probe_length,
                   positions=torch.from_numpy(positions / half_width).float(), prune=prune)

    @property
    def n_classes(self) -> int:
        return self.one_hot.shape[1]

    def forward(self, chosen: Tensor, readings: Tensor, ignore: Tensor | None = None) -> Tensor:
        """chosen (B, N) candidate indices, readings (B, N) what each read (MISS: nothing) -> (B, N, classes) log
        posteriors after probes 1..k+1. ignore (B, N) bool: readings left out (e.g. those a faulty sensor corrupted,
        when an analysis knows them)."""
        return self.after_each_probe(chosen, readings, self.log_posterior, ignore)

    def prior(self, batch: int) -> Tensor | KeptWeights:
        """(batch, L) the library's log weights before any probe (pruned: KeptWeights), for `update`."""
        if self.prune is not None:
            return KeptWeights([None] * batch)
        return torch.zeros(batch, self.library.shape[1], device=self.library.device)

    def update(self, log_w: Tensor | KeptWeights, chosen: Tensor, readings: Tensor,
               ignore: Tensor | None = None) -> Tensor | KeptWeights:
        """log_w (B, L) the library's log weights (pruned: KeptWeights), in place, after one more probe per row:
        candidate chosen (B,) that read `readings` (B,) (ignore (B,) bool: left out); `chunk` rows at a time. Returns
        log_w."""
        if isinstance(log_w, KeptWeights):
            return self.update_kept(log_w, chosen, readings, ignore)
        for start in range(0, len(chosen), self.chunk):
            rows = slice(start, start + self.chunk)  # a view of log_w, added to in place
            log_p = log_likelihood(readings[rows, None], self.library[chosen[rows]], self.sigma, self.mismatch,
                                   self.noise, self.probe_length)
            log_w[rows] += log_p if ignore is None else log_p.masked_fill(ignore[rows, None], 0.0)
        return log_w

    def update_kept(self, log_w: KeptWeights, chosen: Tensor, readings: Tensor,
                    ignore: Tensor | None = None) -> KeptWeights:
        """`update` of a pruned classifier's weights, episode by episode over its kept library episodes; episodes that
        shared a state and read the same share the next (every episode's first probe is the planner's same first
        choice, and every miss reads alike)."""
        if self.library.device.type != "cpu":
            raise ValueError(f"LibraryClassifier(prune={self.prune}): a pruned classifier runs on the CPU, its library "
                             f"is on {self.library.device}")
        library, ends = self.library.numpy(), np.asarray(self.ends, np.int32)  # the kept index's type: no cast
        terms = likelihood_terms(self.sigma, self.mismatch, self.noise, self.probe_length)
        left_out = [False] * len(log_w) if ignore is None else ignore.tolist()
        shared: dict[tuple, Kept] = {}
        for b, (state, c, reading, skip) in enumerate(zip(log_w, chosen.tolist(), readings.tolist(), left_out)):
            if skip:
                continue
            if (key := (state, c, reading)) not in shared:
                # the exact classifier's log_w += log_likelihood(...) over the kept episodes, then the pruning
                index, kept_log_w = self.everything if state is None else (state.index, state.log_w)
                kept, best = likelihood_update(library[c], index, kept_log_w, reading, *terms, self.prune,
                                               self.kept_index, self.kept_log_w)
                shared[key] = Kept.weigh(self.kept_index[:kept].copy(), self.kept_log_w[:kept].copy(), best, ends)
            log_w[b] = shared[key]
        return log_w

    def play(self, n_probes: int, batch: int, choose: Choose, read: Read, look: Callable[[Tensor], Tensor],
             ignore: Tensor | None = None) -> tuple[Tensor, Tensor]:
        """The one update loop: `n_probes` times, choose (B,) candidates from the library's log weights so far,
        read them, weigh the library (update) and look at the weights. Returns (B, N) the candidates chosen and
        (B, N, ...) look(log_w) after each probe. ignore (B, N) bool: readings left out."""
        log_w, device = self.prior(batch), self.library.device
        used = torch.zeros(batch, self.library.shape[0], dtype=torch.bool, device=device)
        rows, chosen, after = torch.arange(batch, device=device), [], []
        for k in range(n_probes):
            c = choose(k, log_w, used)
            used[rows, c] = True
            self.update(log_w, c, read(k, c), None if ignore is None else ignore[:, k])
            chosen.append(c)
            after.append(look(log_w))
        return torch.stack(chosen, 1), torch.stack(after, 1)

    def after_each_probe(self, chosen: Tensor, readings: Tensor, look: Callable[[Tensor], Tensor],
                         ignore: Tensor | None = None) -> Tensor:
        """(B, N, ...) look(log_w) of the library's log weights (b, L) after each of the given probes, chosen (B, N)
        that read `readings` (B, N); `chunk` rows at a time."""
        out = []
        for rows in torch.split(torch.arange(len(chosen)), self.chunk):  # (chunk, L) weights at a time
            given, read = chosen[rows], readings[rows]
            out.append(self.play(chosen.shape[1], len(rows), lambda k, log_w, used: given[:, k],
                                 lambda k, c: read[:, k], look, None if ignore is None else ignore[rows])[1])
        return torch.cat(out)

    def log_posterior(self, log_w: Tensor | KeptWeights) -> Tensor:
        """(B, classes) log p(class | readings) of episodes whose library log weights are log_w (B, L) (or kept)."""
        if isinstance(log_w, KeptWeights):
            sizes = np.diff(self.ends, prepend=0).astype(np.float64)  # before any probe: the classes' library shares
            with np.errstate(divide="ignore"):  # a class none of whose library episodes is kept: log 0
                mass = np.log(np.stack([sizes if state is None else state.class_mass for state in log_w]))
            return torch.log_softmax(torch.from_numpy(mass).float(), 1).to(self.library.device)
        starts = [0] + self.ends[:-1]
        return torch.log_softmax(torch.stack([torch.logsumexp(log_w[:, a:b], 1) for a, b in zip(starts, self.ends)],
                                             1), 1)

    def name(self, log_w: Tensor | KeptWeights) -> Tensor:
        """(B,) the most probable class of episodes whose library log weights are log_w (B, L) or KeptWeights."""
        return self.log_posterior(log_w).argmax(1)

    def beliefs(self, chosen: Tensor, readings: Tensor) -> Tensor:
        """(B, N, classes + 4) the classifier's belief (`belief`) after probes 1..k+1, for a choice to read."""
        return self.after_each_probe(chosen, readings, self.belief)

    def belief(self, log_w: Tensor | KeptWeights) -> Tensor:
        """(B, classes + 4) belief() of episodes whose library log weights are log_w (B, L) or KeptWeights."""
        if self.positions is None:
            raise ValueError("LibraryClassifier.belief: this classifier was built without its library's positions")
        if isinstance(log_w, KeptWeights):
            rows = []
            for state in log_w:  # before any probe: the whole library at weight 1
                kept = slice(None) if state is None else torch.from_numpy(state.index)
                weights = torch.zeros(1, len(self.labels)) if state is None else torch.from_numpy(state.log_w)[None]
                rows.append(belief(weights, self.one_hot[kept], self.positions[kept]))
            return torch.cat(rows)
        return belief(log_w, self.one_hot, self.positions)


def belief(log_w: Tensor, one_hot: Tensor, positions: Tensor) -> Tensor:
    """(Q, classes + 4) what a classifier believes of episodes whose log weights over its library are log_w (Q, L):
    the class posterior, where along the line the object lies and how sure that is (mean and spread of the library
    episodes' positions, weighed), its mean offset across the line and the chance it lies to +x. one_hot (L, classes)
    the library's classes, positions (L, 2) its objects' (x across the line, y along it). What the greedy planner
    weighs its candidates by, summed up for a choice to read: the readings by candidate alone leave a network far
    from the planner's weighing of a whole library."""
    w = torch.softmax(log_w, 1)
    x, y = positions.T
    mean_y = w @ y
    spread = (w @ y.square() - mean_y.square()).clamp_min(0).sqrt()
    return torch.cat([w @ one_hot, torch.stack([mean_y, spread, w @ x, w @ (x > 0).float()], 1)], 1)
