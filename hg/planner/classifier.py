"""The Bayes classifier over a library of simulated training episodes, and its one update loop.

An episode's probes so far weigh every library episode by the likelihood of their readings under that episode's
readings of the same candidates; the weights summed by class are the posterior. The greedy planner, the evaluation
path and any analysis update the weights with LibraryClassifier.update, probe after probe in LibraryClassifier.play.
Its library may hold the training episodes moved along the line and mirrored (hg.planner.library), so it reaches
positions its training poses never held (docs/findings.md).
"""
from __future__ import annotations

import math
from typing import Callable

import torch
from torch import Tensor, nn

from hg.planner.library import MISS, CandidateGrid, LibraryRecipe
from hg.sim.heldout import Regions
from hg.sim.simulator import ProbeSimulator, SensorNoise

# (k, log_w (B, L), used (B, C) bool) -> (B,) the candidates of probe k, given the library's log weights after the
# probes so far and which candidates they probed
Choose = Callable[[int, Tensor, Tensor], Tensor]
# (k, chosen (B,)) -> (B,) what probe k read from the chosen candidates (MISS: nothing)
Read = Callable[[int, Tensor], Tensor]


def log_likelihood(readings: Tensor, library: Tensor, sigma: float, mismatch: float,
                   noise: SensorNoise = SensorNoise(), probe_length: float = 1.0) -> Tensor:
    """log p(each episode's reading (Q, 1) | each library episode's reading (Q, L)), up to a constant: a Gaussian in
    the touch's distance along the ray, log(mismatch) where one touched and the other did not. With sensor faults
    (`noise`, as the simulator makes them) that is the sensor's own model: a touch is reported as a miss with
    miss_prob, a miss as a touch anywhere along the probe_length-long ray with false_contact_prob, and the touch
    point is blurred by position_std; `mismatch` stays the floor of either mix-up (the library is read in ideal mode,
    the arm's probes stray). Without faults this is the plain rule."""
    sigma = math.hypot(sigma, noise.position_std)
    kept = lambda p: math.log1p(-min(p, 1 - 1e-12))  # log(1 - p): a reading the fault left alone
    touched = readings != MISS
    false_touch = noise.false_contact_prob * sigma * math.sqrt(2 * math.pi) / probe_length  # on the Gaussian's scale
    # in place over (Q, L), the classifier's and the planner's costliest step: 2.4x faster than torch.where over
    # fresh tensors, to the bit (the same operations in the same order)
    out = (library - readings).div_(sigma).square_().mul_(-0.5).add_(kept(noise.miss_prob))  # both touched
    out.masked_fill_(~touched.expand_as(out), math.log(max(noise.miss_prob, mismatch)))  # a touch read as a miss
    library_missed = torch.where(touched, math.log(max(false_touch, mismatch)), kept(noise.false_contact_prob))
    return torch.where(library == MISS, library_missed.to(out.dtype), out)


class LibraryClassifier(nn.Module):
    """log p(class | the readings of the candidates probed so far) over a library of episodes each read with every
    candidate: every library episode weighed by the likelihood of the readings, the weights summed by class (a
    uniform prior over the library's episodes). Nothing in it learns; the library is a buffer left out of
    checkpoints (it is rebuilt from its recipe, LibraryRecipe, and holds ~10^5-10^6 episodes)."""

    def __init__(self, library: Tensor, labels: Tensor, n_classes: int, sigma: float, mismatch: float,
                 noise: SensorNoise = SensorNoise(), probe_length: float = 1.0, chunk: int = 32,
                 positions: Tensor | None = None) -> None:
        """library (L, C) readings (MISS where nothing was touched), labels (L,); `noise` the faults of the sensor
        whose readings it will name (log_likelihood); positions (L, 2) where each library episode's object lies (x
        across the line, y along it, in units of the pose range's half-width), for its `belief`; `chunk` rows of
        (chunk, L) weights at a time."""
        super().__init__()
        if library.ndim != 2 or labels.shape != library.shape[:1]:
            raise ValueError(f"LibraryClassifier: library {tuple(library.shape)} and labels {tuple(labels.shape)}, "
                             "expected (L, C) and (L,)")
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
        self.sigma, self.mismatch, self.chunk = sigma, mismatch, chunk
        self.noise, self.probe_length = noise, probe_length

    @classmethod
    def build(cls, sim: ProbeSimulator, regions: Regions, grid: CandidateGrid, recipe: LibraryRecipe,
              noise: SensorNoise = SensorNoise()) -> "LibraryClassifier":
        """The classifier over the library `recipe` draws, read by `sim` (ideal mode) with `grid`'s candidates,
        naming the readings of a sensor with faults `noise`; positions in units of the pose range's half-width."""
        readings, labels, positions = recipe.draw(sim, regions, grid)
        half_width = max(sim.scene.object_y[1], sim.scene.object_x[1])  # the belief's unit of position
        return cls(torch.from_numpy(readings), torch.from_numpy(labels).long(), len(sim.classes), recipe.sigma,
                   recipe.mismatch, noise, sim.scene.probe_length,
                   positions=torch.from_numpy(positions / half_width).float())

    @property
    def n_classes(self) -> int:
        return self.one_hot.shape[1]

    def forward(self, chosen: Tensor, readings: Tensor, ignore: Tensor | None = None) -> Tensor:
        """chosen (B, N) candidate indices, readings (B, N) what each read (MISS: nothing) -> (B, N, classes) log
        posteriors after probes 1..k+1. ignore (B, N) bool: readings left out (e.g. those a faulty sensor corrupted,
        when an analysis knows them)."""
        return self.after_each_probe(chosen, readings, self.log_posterior, ignore)

    def prior(self, batch: int) -> Tensor:
        """(batch, L) the library's log weights before any probe, for `update`."""
        return torch.zeros(batch, self.library.shape[1], device=self.library.device)

    def update(self, log_w: Tensor, chosen: Tensor, readings: Tensor, ignore: Tensor | None = None) -> Tensor:
        """log_w (B, L) the library's log weights, in place, after one more probe per row: candidate chosen (B,)
        that read `readings` (B,) (ignore (B,) bool: left out); `chunk` rows at a time. Returns log_w."""
        for start in range(0, len(chosen), self.chunk):
            rows = slice(start, start + self.chunk)  # a view of log_w, added to in place
            log_p = log_likelihood(readings[rows, None], self.library[chosen[rows]], self.sigma, self.mismatch,
                                   self.noise, self.probe_length)
            log_w[rows] += log_p if ignore is None else log_p.masked_fill(ignore[rows, None], 0.0)
        return log_w

    def play(self, n_probes: int, batch: int, choose: Choose, read: Read, look: Callable[[Tensor], Tensor],
             ignore: Tensor | None = None) -> tuple[Tensor, Tensor]:
        """The one update loop: `n_probes` times, choose (B,) candidates from the library's log weights so far,
        read them, weigh the library (update) and look at the weights. Returns (B, N) the candidates chosen and
        (B, N, ...) look(log_w) after each probe. ignore (B, N) bool: readings left out."""
        log_w = self.prior(batch)
        used = torch.zeros(batch, self.library.shape[0], dtype=torch.bool, device=log_w.device)
        rows, chosen, after = torch.arange(batch, device=log_w.device), [], []
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

    def log_posterior(self, log_w: Tensor) -> Tensor:
        """(B, classes) log p(class | readings) of episodes whose library log weights are log_w (B, L)."""
        starts = [0] + self.ends[:-1]
        return torch.log_softmax(torch.stack([torch.logsumexp(log_w[:, a:b], 1) for a, b in zip(starts, self.ends)],
                                             1), 1)

    def name(self, log_w: Tensor) -> Tensor:
        """(B,) the most probable class of episodes whose library log weights are log_w (B, L)."""
        return self.log_posterior(log_w).argmax(1)

    def beliefs(self, chosen: Tensor, readings: Tensor) -> Tensor:
        """(B, N, classes + 4) the classifier's belief (`belief`) after probes 1..k+1, for a choice to read."""
        return self.after_each_probe(chosen, readings, self.belief)

    def belief(self, log_w: Tensor) -> Tensor:
        """(B, classes + 4) belief() of episodes whose library log weights are log_w (B, L)."""
        if self.positions is None:
            raise ValueError("LibraryClassifier.belief: this classifier was built without its library's positions")
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
