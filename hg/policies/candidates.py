"""Beyond the paper: a categorical choice among fixed candidate requests, the greedy planner's grid (places along
the middle of the line x straight or leaning to +-x). A Gaussian copying a teacher that leans to either side ends
up between them; a choice cannot average two sides."""
from __future__ import annotations

from collections.abc import Callable

import torch
import torch.nn.functional as F
from torch import Tensor

from hg.nets import CandidateLocationNetwork
from hg.nets.dims import Dims
from hg.policies.base import LearnedPolicy, Observation, PolicyEval
from hg.policies.scans import Scan
from hg.sim import candidate_requests


class CandidateChoice(LearnedPolicy):
    """pi(a_k | s_k) over `places` x (straight, +-x by each of `leans`) candidates, reading what each candidate read
    so far (CandidateLocationNetwork.readings) and never probing one twice. With `reads_encoder` the choice also
    reads PCRN's state; without it, the readings only (the baseline always reads both): PCRN's state holds where
    the training objects lay, which held-out positions do not share. With a `prior` scan, whose requests must be
    among the candidates, a FollowPrior(imitate=true) warm-up teaches the choice to copy it before it learns by the
    hybrid rule: a learned policy that starts as good as the scan (ExploreAroundPrior: heads that also learn behind
    other candidates meanwhile)."""

    copies_prior = True

    def __init__(self, dims: Dims, places: int | None = 11, span: float = 0.5,
                 leans: tuple[float, ...] = (0.6, 1.0, 2.0), hidden: int = 128, reads_encoder: bool = False,
                 reads_detached: bool = False, prior: Callable[[Dims], Scan] | None = None) -> None:
        """places: None for one place per probe, a scan's places along the line (a prior scan's)."""
        places = dims.n_probes if places is None else places
        try:
            candidates = torch.from_numpy(candidate_requests(places, span, list(leans)))
        except ValueError as error:
            raise ValueError(f"CandidateChoice: places / span / leans: {error}") from None
        state_dim = dims.rep + 3 * len(candidates) + dims.n_probes
        if reads_detached and not reads_encoder:
            raise ValueError("CandidateChoice: reads_detached keeps REINFORCE out of the encoder, which this choice "
                             "does not read (reads_encoder: false)")
        super().__init__(state_dim, reads_detached)
        self.n_probes, self.grid = dims.n_probes, {"places": places, "span": span, "leans": list(leans)}
        self.location = CandidateLocationNetwork(state_dim, candidates, hidden=hidden,
                                                 reads_from=0 if reads_encoder else dims.rep)
        self.prior = prior(dims) if prior is not None else None
        if self.prior is not None:
            self._check_prior(dims)

    def _check_prior(self, dims: Dims) -> None:
        """Refuse, when built, a prior scan that can make a request the choice cannot copy."""
        try:
            self.location.index_of(self.prior.possible_requests())
        except NotImplementedError:
            raise ValueError(f"model.policy.init_args.prior: {type(self.prior).__name__} does not list the requests it "
                             "can make (Scan.possible_requests), so a choice cannot be checked to copy it") from None
        except ValueError as error:
            raise ValueError(f"model.policy.init_args.prior: {type(self.prior).__name__}: {error} of CandidateChoice("
                             f"places={self.grid['places']}, span={self.grid['span']}, leans={self.grid['leans']}); "
                             f"a scan over n_probes={dims.n_probes} places needs places={dims.n_probes} (or null) and "
                             f"the scan's span, and its leans (lean, first_lean) among the choice's") from None

    @property
    def candidates(self) -> Tensor:
        return self.location.candidates

    def act(self, obs: Observation, deterministic: bool | Tensor, generator: torch.Generator) -> Tensor:
        k, extra, exclude = obs.k, None, None
        if k > 0:  # what probes 1..k read
            extra, exclude = self.location.readings(obs.actions[:, :k], obs.points[:, :k], self.n_probes)
            extra, exclude = extra[:, -1], exclude[:, -1]
        state = self.location.state(obs.rep_sum, k, batch_size=len(obs.points), extra=extra)
        return self.location.sample(state, deterministic=deterministic, generator=generator, exclude=exclude)[0]

    def evaluate(self, rep: Tensor, actions: Tensor, points: Tensor, chosen: Tensor | None = None,
                 among: Tensor | None = None) -> PolicyEval:
        readings, probed = self.location.readings(actions, points, self.n_probes)
        states = self.location.states(self.policy_rep(rep), readings)
        exclude = F.pad(probed[:, :-1], (0, 0, 1, 0), value=False)  # state s_k excludes what probes 1..k probed
        if among is not None:
            exclude = exclude | ~among
        log_pi, mu, sigma = self.location.log_prob_and_moments(states, actions if chosen is None else chosen, exclude)
        return PolicyEval(log_pi, self.baseline(states.detach()), mu, sigma, stats=self.std_stats(sigma))
