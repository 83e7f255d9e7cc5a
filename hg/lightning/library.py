"""The model's library classifier: built from a teacher file's recipe, it names a rollout's probes (hg.planner)."""
from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path

import torch
from torch import Tensor, nn

from hg.nets import candidate_index
from hg.planner import MISS, CandidateGrid, LibraryClassifier, LibraryRecipe, teacher_meta
from hg.rl import Rollout
from hg.sim import ProbeSimulator


@dataclass
class LibrarySource:
    """Where the library classifier comes from: the library recipe of a teacher file (its planner's), with
    `episodes` training episodes in place of the file's library size if given, drawn in the run's regions (the
    file's, checked) and always confined: no moved or mirrored copy outside the training region, even where the
    file's planner read an unconfined library (teacher files before schema 2)."""

    teacher: str
    episodes: int | None = None

    def build(self, data, grid: dict | None) -> "LibraryScorer":
        if not Path(self.teacher).is_file():
            raise FileNotFoundError(f"model.library_classifier.teacher: {self.teacher}: teacher file not found "
                                    "(write one with scripts/plan.py --save-rollouts)")
        if self.episodes is not None and self.episodes < 1:
            raise ValueError(f"model.library_classifier.episodes={self.episodes}: must be >= 1")
        meta = teacher_meta([self.teacher])
        file_grid = CandidateGrid.from_meta(meta)
        for field, have, want in (("library_split", meta.get("library_split"), "train"),
                                  ("objects", meta.get("objects"), data.object_set.name),
                                  *((("eval_seed", meta.get("eval_seed"), data.regions.seed),)
                                    if data.regions.seeded else ()),
                                  ("regions", meta.get("regions", data.regions.meta()), data.regions.meta()),
                                  *(((k, meta.get(k), v) for k, v in grid.items()) if grid else ()),
                                  ("along_leans", meta.get("along_leans", []), [])):
            if have != want:
                raise ValueError(f"model.library_classifier: {self.teacher}: meta {field}={have!r}, this model needs "
                                 f"{want!r} (held-out poses must not enter the library; its candidates must be the "
                                 "policy's)")
        with ProbeSimulator(data.object_set, 1024, data.scene, "ideal", seed=0) as sim:
            classifier = LibraryClassifier.build(sim, data.regions, file_grid,
                                                 replace(LibraryRecipe.from_meta(meta, self.episodes), confined=True),
                                                 data.noise)
        candidates = file_grid.requests()
        return LibraryScorer(classifier, torch.from_numpy(candidates).float(),
                             torch.from_numpy(data.scene.request_to_probe(candidates)[0]).float())


class LibraryScorer(nn.Module):
    """A library classifier scoring rollouts: which candidate each probe was and what it read (how far from its
    entry point it touched, MISS where nothing was touched), as the planner read its candidates."""

    def __init__(self, classifier: nn.Module, candidates: Tensor, entries: Tensor) -> None:
        """candidates (C, 4) requests and their entry points (C, 3) on the probe line (metres)."""
        super().__init__()
        self.classifier = classifier
        self.register_buffer("candidates", candidates, persistent=False)
        self.register_buffer("entries", entries, persistent=False)

    def name(self, rollout: Rollout, point_scale: float) -> Tensor:
        """(B, N, classes) the library classifier's log posterior after each probe."""
        try:
            chosen = candidate_index(rollout.requests, self.candidates)
        except ValueError as error:
            raise ValueError(f"library classifier: {error}: only the planner's candidates can be named") from None
        distance = (rollout.points[..., :3] / point_scale - self.entries.to(rollout.points)[chosen]).norm(dim=-1)
        readings = torch.where(rollout.points[..., 3] > 0.5, distance, MISS)
        return self.classifier(chosen, readings)
