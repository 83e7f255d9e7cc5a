"""The paper's location network (sec. 2.2 (b)): an autoregressive Gaussian over the next request (Py, Ux, Uy, Uz)
with tanh means and sigmoid stds, reading PCRN's state s_k; optionally started on a fixed scan."""
from __future__ import annotations

from collections.abc import Callable

import torch
from torch import Tensor

from hg.nets import LocationNetwork
from hg.nets.dims import Dims
from hg.policies.base import LearnedPolicy, Observation, PolicyEval
from hg.policies.scans import Scan


class GaussianPolicy(LearnedPolicy):
    """pi(a_k | s_k) of eq. (1), trained by REINFORCE (eq. (3)-(5)).

    Beyond the paper, with a `prior` scan the mean starts on the scan's requests (the mean head starts at zero and
    the scan's request is added before the tanh; components beyond +-0.9 start at +-0.9, where tanh still has a
    slope the policy can climb), so a classifier trained behind the scan keeps its probes when the policy takes over;
    `anchor` then charges for the mean's squared distance from the scan, so the policy
    moves only where the reward pays for it. `truncated`: samples re-drawn inside [-1, 1] with the truncated
    Gaussian's log-probability (LocationNetwork) instead of clamped."""

    def __init__(self, dims: Dims, hidden: int = 128, std_floor: float = 0.05, std_max: float = 1.0,
                 prior: Callable[[Dims], Scan] | None = None, anchor: float = 0.0,
                 reads_detached: bool = False, truncated: bool = False, reads_count: bool = False) -> None:
        """reads_count: the location network (and the baseline) also read how many probes were made, one-hot,
        beside the mean of PCRN's states, which says what was read but hardly how often: a scan is a schedule by
        probe count (beyond the paper; docs/findings.md, "Why the paper's rule collapses here")."""
        self.count_width = dims.n_probes if reads_count else 0  # one-hot of 1..n_probes probes made
        super().__init__(dims.rep + self.count_width, reads_detached)
        self.prior = prior(dims) if prior is not None else None
        if anchor < 0.0 or (anchor and self.prior is None):
            raise ValueError(f"GaussianPolicy: anchor={anchor}: must be >= 0, and needs a prior scan to hold to")
        self.anchor = anchor
        self.location = LocationNetwork(dims.rep + self.count_width, hidden=hidden, std_floor=std_floor,
                                        std_max=std_max, zero_mean=self.prior is not None, truncated=truncated)

    def counts(self, batch: int, probes: int, device: torch.device) -> Tensor | None:
        """(batch, probes, n_probes) one-hot of 1..probes, the count after each probe (None without reads_count)."""
        if not self.count_width:
            return None
        return torch.eye(self.count_width, device=device)[:probes].expand(batch, -1, -1)

    def offsets(self, points: Tensor) -> Tensor | None:
        """(B, N, 4) the prior scan's requests before the tanh (only requests beyond +-0.9, the ends of a full-span
        scan, are pulled inside tanh's range), or None without a prior."""
        if self.prior is None:
            return None
        return torch.atanh(self.prior.requests(points).clamp(-0.9, 0.9))

    def act(self, obs: Observation, deterministic: bool | Tensor, generator: torch.Generator) -> Tensor:
        counts = self.counts(len(obs.points), obs.k, obs.points.device) if obs.k else None  # a view, no copy
        state = self.location.state(obs.rep_sum, obs.k, batch_size=len(obs.points),
                                    extra=None if counts is None else counts[:, -1])
        offsets = self.offsets(obs.points)
        offset = None if offsets is None else offsets[:, obs.k].to(state.device)
        return self.location.sample(state, deterministic=deterministic, generator=generator, offset=offset)[0]

    def evaluate(self, rep: Tensor, actions: Tensor, points: Tensor, chosen: Tensor | None = None,
                 among: Tensor | None = None) -> PolicyEval:
        if among is not None:
            raise ValueError("GaussianPolicy.evaluate: `among` restricts a choice among candidates; "
                             "a Gaussian has none")
        states = self.location.states(self.policy_rep(rep), self.counts(*rep.shape[:2], rep.device))
        offsets = self.offsets(points)
        log_pi, mu, sigma = self.location.log_prob_and_moments(states, actions if chosen is None else chosen, offsets)
        evaluated = PolicyEval(log_pi, self.baseline(states.detach()), mu, sigma, stats=self.std_stats(sigma))
        if offsets is not None:
            # how far the mean policy has moved from its prior (request units, squared, summed over components)
            shift = (mu - torch.tanh(offsets)).pow(2).sum(-1).mean()
            evaluated.stats["prior_shift"] = shift.detach()
            if self.anchor:
                evaluated.losses["loss_anchor"] = self.anchor * shift
        return evaluated
