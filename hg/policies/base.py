"""The policy interface: what request next, and for learned policies the log-probability and any extra loss terms.

A policy is built by the model with the sizes it needs (`Dims`), from YAML (`class_path` / `init_args`), so trying a
new policy means writing one class here and one config part, nothing else.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import torch
from torch import Tensor, nn

from hg.nets import Baseline
from hg.nets.dims import Dims

COMPONENTS = ("py", "ux", "uy", "uz")  # a request's components, in order


@dataclass
class Observation:
    """What a policy may read before probe k + 1 (k = 0 before the first): rows [:, :k] of the requests it sent
    and the points they returned (the rest are zeros), and, for a policy reading the encoder, the sum of its
    representations after probes 1..k (None before the first)."""

    k: int
    actions: Tensor  # (B, N, 4) raw requests (before clamping to [-1, 1])
    points: Tensor  # (B, N, 4) X, Y, Z (point coordinates) and the contact flag T
    rep_sum: Tensor | None = None  # (B, D)


@dataclass
class PolicyEval:
    """A learned policy's reading of a finished rollout: log pi(a_k | s_k) (B, N) of the requests it sent, b_k (B, N)
    from detached states, the request's mean and std per component (B, N, 4), and terms beyond the paper: `losses`
    are added to the loss (named, logged), `stats` only logged."""

    log_pi: Tensor
    baseline: Tensor
    mu: Tensor
    sigma: Tensor
    losses: dict[str, Tensor] = field(default_factory=dict)
    stats: dict[str, Tensor] = field(default_factory=dict)


@dataclass
class Imitation:
    """What an imitating policy learns to ask for in the states of a rollout: `requests` (B, N, 4), at the `valid`
    probes (B, N) bool (None: all; an exploring warm-up leaves out a request the policy may not make there), each
    chosen `among` the candidates (B, N, C) bool that are True (None: among all the policy may take; a teacher that
    compared a few is copied among those few, so that its pick is not read as a verdict on the ones it never saw)."""

    requests: Tensor
    valid: Tensor | None = None
    among: Tensor | None = None


class Policy(nn.Module):
    """Chooses request k + 1 of every episode from what probes 1..k returned. A fixed policy (scan, random) has
    no parameters and is not trained; the model only reads its requests."""

    learned = False
    copies_prior = False  # a policy that starts on its prior scan only by copying it (FollowPrior(imitate=True))

    def act(self, obs: Observation, deterministic: bool, generator: torch.Generator) -> Tensor:
        """(B, 4) raw requests for probe obs.k + 1; the simulator clamps them to [-1, 1]."""
        raise NotImplementedError


class LearnedPolicy(Policy):
    """A policy trained by the hybrid rule: it reads the encoder's states s_k, owns the baseline b_k that reads the
    same states, and gives log pi of a rollout's requests for REINFORCE (or copies a teacher's requests)."""

    learned = True

    def __init__(self, state_dim: int, reads_detached: bool) -> None:
        super().__init__()
        self.reads_detached = reads_detached  # beyond the paper: REINFORCE kept out of the encoder
        self.prior: Policy | None = None  # a scan the policy starts on (set by a subclass that takes one)
        self.baseline = Baseline(state_dim)  # b_k reads the state s_k the policy reads

    @property
    def std_scale(self) -> Tensor:
        """The factor on the policy's spread (a std, or a choice's temperature) a schedule may shrink."""
        return self.location.std_scale

    def evaluate(self, rep: Tensor, actions: Tensor, points: Tensor, chosen: Tensor | None = None,
                 among: Tensor | None = None) -> PolicyEval:
        """log pi of the requests `actions` (B, N, 4) that produced `points` (B, N, 4), from the encoder's
        representation after each probe rep (B, N, D), in one pass (teacher forcing). `chosen` (B, N, 4): take log pi
        of these requests instead, in the states the sent ones led to (a teacher's would-be requests, which an
        exploring warm-up did not always send); `among` (B, N, C) bool: of the choice restricted to these candidates
        (Imitation.among; a policy without candidates refuses it)."""
        raise NotImplementedError

    def imitation_loss(self, evaluated: PolicyEval, imitation: Imitation) -> Tensor:
        """How far the policy, `evaluated` on the imitation's requests, is from the teacher."""
        return self.location.imitation_loss(evaluated.log_pi, evaluated.mu, imitation.requests, imitation.valid)

    def policy_rep(self, rep: Tensor) -> Tensor:
        return rep.detach() if self.reads_detached else rep

    @staticmethod
    def std_stats(sigma: Tensor) -> dict[str, Tensor]:
        """Too large a std is the usual cause of poor accuracy: watch each component's."""
        sigma = sigma.detach().mean((0, 1))
        return {f"std_{c}": sigma[i] for i, c in enumerate(COMPONENTS)}


__all__ = ["COMPONENTS", "Dims", "Imitation", "LearnedPolicy", "Observation", "Policy", "PolicyEval"]
