"""Fixed policies: random probes and scans of the probe line. They learn nothing; a classifier trained behind them
shows what a learned policy's choice of probes buys."""
from __future__ import annotations

from typing import Literal

import torch
import torch.nn.functional as F
from torch import Tensor

from hg.nets import candidate_index
from hg.nets.dims import Dims
from hg.policies.base import Observation, Policy


class RandomProbes(Policy):
    """Requests drawn uniformly in [-1, 1]^4."""

    def __init__(self, dims: Dims) -> None:
        super().__init__()

    def act(self, obs: Observation, deterministic: bool, generator: torch.Generator) -> Tensor:
        return torch.rand(len(obs.points), 4, generator=generator) * 2 - 1


class Scan(Policy):
    """A fixed scan: its requests are a function of the points its earlier probes returned."""

    def requests(self, points: Tensor) -> Tensor:
        """(B, N, 4) the scan's requests given the points (B, N, 4) its probes returned; row k reads points[:, :k]."""
        raise NotImplementedError

    def possible_requests(self) -> Tensor:
        """(M, 4) every request the scan can make, whatever its probes return: what a choice that copies it must be
        able to choose."""
        raise NotImplementedError

    def act(self, obs: Observation, deterministic: bool, generator: torch.Generator) -> Tensor:
        return self.requests(obs.points)[:, obs.k]


class LineScan(Scan):
    """n_probes straight-down probes evenly spaced over the middle `span` of the probe line, swept from one end (the
    paper's kind of scan), or `centre_out`: nearest the centre first, alternating sides, which meets objects near
    the line's middle in the first probes instead of half-way through."""

    def __init__(self, dims: Dims, span: float = 1.0, order: Literal["sweep", "centre_out"] = "sweep") -> None:
        super().__init__()
        if not 0.0 < span <= 1.0:
            raise ValueError(f"LineScan: span={span}: the scanned share of the probe line must be in (0, 1]")
        if order not in ("sweep", "centre_out"):
            raise ValueError(f"LineScan: order={order!r}: expected 'sweep' or 'centre_out'")
        n = dims.n_probes
        py = torch.linspace(-span, span, n) if n > 1 else torch.zeros(1)
        if order == "centre_out":
            py = py[torch.argsort(py.abs(), stable=True)]
        self.register_buffer("places", py, persistent=False)  # py of request k

    def requests(self, points: Tensor) -> Tensor:
        n = len(self.places)
        scan = torch.stack([self.places, torch.zeros(n), torch.zeros(n), torch.ones(n)], 1)
        return scan.to(points.device).expand(len(points), -1, -1).clone()

    def possible_requests(self) -> Tensor:
        return self.requests(torch.zeros(1, len(self.places), 4))[0]


class SidePickingScan(LineScan):
    """Every probe leans across the line (uz = 1 - lean), towards the side the object lies on once a touch tells it.
    Straight probes see only the slice of the object under the line, which for an object lying off it looks alike
    across classes; a probe leaning its way cuts it nearer the middle. The first two probes enter at the line scan's
    first place leaning to +x, then -x, by `first_lean`; the later ones take the scan's places from its second on
    (its last is dropped). A steep first pair names the side; if it touched nothing the rest go straight down,
    because a probe leaning the wrong way misses what a straight one grazes. When both of the pair touched, the
    side of the higher touch is chosen: a probe leaning towards the object meets its surface first."""

    def __init__(self, dims: Dims, span: float = 0.5, order: Literal["sweep", "centre_out"] = "centre_out",
                 lean: float = 0.6, first_lean: float = 1.0) -> None:
        super().__init__(dims, span, order)
        if dims.n_probes < 2:
            raise ValueError(f"SidePickingScan needs n_probes >= 2, got {dims.n_probes}")
        for name, value in (("lean", lean), ("first_lean", first_lean)):
            if not 0.0 < value <= 2.0:
                raise ValueError(f"SidePickingScan: {name}={value}: must be in (0, 2] (1 - uz of the leaning probes)")
        self.lean, self.first_lean = lean, first_lean

    def requests(self, points: Tensor) -> Tensor:
        scan = super().requests(points)
        n = scan.shape[1]
        touched, z = points[..., 3] > 0.5, points[..., 2]
        none = torch.full_like(touched[:, 0], n, dtype=torch.long)  # index n: nothing touched
        first = torch.where(touched.any(1), touched.float().argmax(1), none)
        k = torch.arange(n, device=scan.device)
        alternate = torch.where(k % 2 == 0, 1.0, -1.0)
        both = (first == 0) & touched[:, 1]
        found = torch.where(both, torch.where(z[:, 0] >= z[:, 1], 1.0, -1.0), alternate[first.clamp(max=n - 1)])
        decided = (first[:, None] < k) & (k >= 2)  # request k reads probes 1..k only: both first ones from k = 2
        ux = torch.where(decided, found[:, None], alternate)
        uz = torch.where(k < 2, 1.0 - self.first_lean, 1.0 - self.lean).expand_as(ux)
        straight = (first[:, None] >= 2) & (k >= 2)  # the pair touched nothing: straight down
        ux, uz = torch.where(straight, 0.0, ux), torch.where(straight, 1.0, uz)
        py = scan[:, (k - 1).clamp(min=0), 0]
        return torch.stack([py, ux, torch.zeros_like(ux), uz], -1)

    def possible_requests(self) -> Tensor:
        """The first pair leaning each way at the first place; at each later place, leaning each way or straight."""
        first = [(self.places[0], ux, 1.0 - self.first_lean) for ux in (1.0, -1.0)]
        later = [(py, ux, uz) for py in self.places[1:-1] for ux, uz in ((1.0, 1.0 - self.lean),
                                                                         (-1.0, 1.0 - self.lean), (0.0, 1.0))]
        return torch.tensor([(float(py), ux, 0.0, uz) for py, ux, uz in first + later])


class Detours(Policy):
    """The `prior` scan's request, or with probability `explore` a candidate (C, 4) not yet probed, drawn at random
    (always drawn: `deterministic` reaches only the scan): the prober of hg.rl.ExploreAroundPrior's warm-up. Where the
    scan asks for a place probed already (an earlier detour took it), it detours again: the choice it teaches never
    probes a place twice."""

    def __init__(self, prior: Policy, candidates: Tensor, explore: float) -> None:
        super().__init__()
        self.prior, self.candidates, self.explore = prior, candidates.cpu(), explore

    def act(self, obs: Observation, deterministic: bool, generator: torch.Generator) -> Tensor:
        request = self.prior.act(obs, deterministic, generator).cpu()
        sent = candidate_index(obs.actions[:, :obs.k].cpu(), self.candidates)  # (B, k)
        probed = F.one_hot(sent, len(self.candidates)).bool().any(1)  # (B, C)
        draw = torch.rand(len(request), len(self.candidates), generator=generator).masked_fill(probed, -1.0)
        taken = probed.gather(1, candidate_index(request, self.candidates)[:, None])[:, 0] & ~probed.all(1)
        detour = (torch.rand(len(request), generator=generator) < self.explore) | taken
        return torch.where(detour[:, None], self.candidates[draw.argmax(-1)], request)
