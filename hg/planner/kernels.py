"""The pruned planner's passes over kept library episodes as compiled loops (numba): an episode keeps most of a
library of ~10^6 episodes, and numpy made some twenty passes over them per probe, each into a fresh array
(docs/benchmarks.md, "Planner"). The log weights are the exact classifier's (log_likelihood) to the bit: the same
float32 operations in the same order (tests/test_planner.py).
"""
from __future__ import annotations

import numba
import numpy as np

from hg.planner.library import MISS


@numba.njit(cache=True)
def likelihood_update(library_row: np.ndarray, index: np.ndarray, log_w: np.ndarray, reading: float, sigma: float,
                      both_missed: float, library_touched: float, library_missed: float, both_touched: float,
                      prune: float, kept_index: np.ndarray, kept_log_w: np.ndarray) -> tuple[int, np.float32]:
    """One probe's update of one episode's kept library episodes, and their pruning: library_row (L,) float32 what
    every library episode read with the probed candidate, index (S,) int32 the kept episodes, log_w (S,) float32
    theirs. The log-likelihood is hg.planner.classifier.log_likelihood's for one reading (reading MISS: both_missed
    where the library episode missed too, else library_touched; a touch: library_missed where the library episode
    missed, else both_touched - ((library - reading) / sigma)^2 / 2), in float32 like torch's, added to log_w. Writes
    the episodes within `prune` of the best to the first `kept` places of kept_index and kept_log_w (L,). Returns kept
    and the best log weight."""
    r, s, half, touched = np.float32(reading), np.float32(sigma), np.float32(-0.5), np.float32(both_touched)
    miss_miss, miss_touch, touch_miss = np.float32(both_missed), np.float32(library_touched), np.float32(library_missed)
    best = np.float32(-np.inf)
    # one loop per kind of reading, each free of branches: half the library misses, at random, and a branch inside
    # the loop (which the compiler does not take out of it) made it 7x slower
    if r == MISS:
        for i in range(len(index)):
            p = log_w[i] + (miss_miss if library_row[index[i]] == MISS else miss_touch)
            kept_log_w[i] = p
            best = max(best, p)
    else:
        for i in range(len(index)):
            value = library_row[index[i]]
            d = (value - r) / s
            p = log_w[i] + (touch_miss if value == MISS else d * d * half + touched)
            kept_log_w[i] = p
            best = max(best, p)
    threshold, kept = best - np.float32(prune), 0
    for i in range(len(index)):  # in place (kept <= i); written at every i and kept by moving on, branch-free too
        p = kept_log_w[i]
        kept_index[kept] = index[i]
        kept_log_w[kept] = p
        kept += p >= threshold
    return kept, best


@numba.njit(cache=True)
def class_sums(weight: np.ndarray, ends: np.ndarray) -> np.ndarray:
    """(classes,) float64 the weights summed by class, class c's ending before ends[c]."""
    out, start = np.zeros(len(ends)), 0
    for c in range(len(ends)):
        total = 0.0
        for i in range(start, ends[c]):
            total += weight[i]
        out[c], start = total, ends[c]
    return out


@numba.njit(cache=True)
def candidate_mass(columns: np.ndarray, candidates: np.ndarray, index: np.ndarray, weight: np.ndarray,
                   cells_per_candidate: int) -> np.ndarray:
    """(len(candidates) * cells_per_candidate,) float64: for each candidate, the kept episodes' weights summed by
    their (binned reading, class) cell; columns (C, L) each library episode's cell per candidate."""
    mass = np.zeros(len(candidates) * cells_per_candidate)
    for k in range(len(candidates)):
        row, offset = columns[candidates[k]], k * cells_per_candidate
        for i in range(len(index)):
            mass[offset + row[index[i]]] += weight[i]
    return mass


@numba.njit(cache=True)
def sampled_mass(codes: np.ndarray, index: np.ndarray, weight: np.ndarray, ends: np.ndarray, class_mass: np.ndarray,
                 samples: int, n_cells: int) -> tuple[np.ndarray, bool]:
    """(n_cells,) float64 every candidate's cells' weights over `samples` of each class's kept episodes drawn by
    weight, or all of a class's where it keeps no more than `samples`: systematic draws, at every 1/samples of the
    class's weight (class_mass[c]), each weighing 1/samples of it. codes (L, C) each library episode's cell per candidate, offset by
    the candidate's first cell; index, weight the kept episodes (each class one slice, ending before ends[c]).
    Returns the masses and whether any class was drawn."""
    mass, start, drawn = np.zeros(n_cells), 0, False
    for c in range(len(ends)):
        end = ends[c]
        if end - start <= samples:
            for i in range(start, end):
                row, w = codes[index[i]], weight[i]
                for j in range(len(row)):
                    mass[row[j]] += w
        else:
            drawn = True
            step, i, below = class_mass[c] / samples, start, 0.0  # below: the weight of the episodes before i
            for k in range(samples):
                tick = (k + 0.5) * step
                while i < end - 1 and below + weight[i] <= tick:
                    below += weight[i]
                    i += 1
                row = codes[index[i]]
                for j in range(len(row)):
                    mass[row[j]] += step
        start = end
    return mass, drawn
