"""The hybrid update rule, eq. (6) of the paper, as a loss to minimise. Every term is returned for logging."""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

import torch
import torch.nn.functional as F
from torch import Tensor

REWARDS = ("correct", "log_gain", "touch", "new_touch")
Reward = str  # one of REWARDS, or a sum of them joined by "+" (e.g. "new_touch+correct")


def discounted_returns(rewards: Tensor, gamma: float) -> Tensor:
    """G_k = sum_{j >= k} gamma^(j - k) r_j over the probe axis (B, N): the return of request k (eq. 3). The paper
    writes G(k) = sum_{k' = k + 1}^{N - 1} gamma^(k' - k + 1) r_k'; we count the reward of the probe the request
    made (docs/findings.md, "Why the paper's rule collapses here")."""
    returns = torch.zeros_like(rewards)
    running = torch.zeros_like(rewards[:, 0])
    for k in range(rewards.shape[1] - 1, -1, -1):
        running = rewards[:, k] + gamma * running
        returns[:, k] = running
    return returns


def rewards_of(logits: Tensor, labels: Tensor, reward: Reward, points: Tensor | None = None,
               spread: float = 0.1) -> Tensor:
    """r_k (B, N) of the prediction after each probe: 1 when it is right (the paper), or beyond the paper
    "log_gain", what probe k added to log p(true class) (they sum to log p_N - log(1/C)); or paid by the probe itself,
    from its point (points (B, N, 4), X, Y, Z, T): "touch", 1 when probe k touched, a diagnostic of whether the policy
    gradient learns at all when the classifier's verdict is left out of the reward; "new_touch", a touch paid by its
    distance to the nearest earlier touch, in units of `spread` (capped at 1; a first touch earns 1), so that
    touching the same spot again earns nothing (issue #57's study). A sum, "new_touch+correct", pays each term."""
    if "+" in reward:
        return sum(rewards_of(logits, labels, term, points, spread) for term in reward.split("+"))
    if reward == "correct":
        return (logits.argmax(-1) == labels[:, None]).float()
    if reward in ("touch", "new_touch"):
        if points is None:
            raise ValueError(f"reward={reward!r} needs the probes' points")
        touched = points[..., 3] > 0.5
        if reward == "touch":
            return touched.float()
        earlier = torch.ones(points.shape[1], points.shape[1], dtype=torch.bool, device=points.device).tril(-1)
        distance = torch.cdist(points[..., :3], points[..., :3]).masked_fill(~(earlier & touched[:, None, :]),
                                                                             math.inf)
        return torch.where(touched, (distance.min(-1).values / spread).clamp(max=1.0), 0.0)
    if reward != "log_gain":
        raise ValueError(f"reward={reward!r}: expected one of {REWARDS}")
    log_p = log_p_true(logits.detach(), labels)
    return torch.diff(log_p, dim=1, prepend=torch.full_like(log_p[:, :1], -math.log(logits.shape[-1])))


def log_p_true(logits: Tensor, labels: Tensor) -> Tensor:
    """log p(true class) of logits (B, ..., C) for labels (B,): (B, ...), what a probe's reading is worth."""
    index = labels.view(-1, *[1] * (logits.dim() - 1)).expand(*logits.shape[:-1], 1)
    return logits.log_softmax(-1).gather(-1, index).squeeze(-1)


@dataclass(frozen=True)
class HybridLoss:
    """Eq. (6) and its settings: the discount gamma, the policy term's weight beta, the reward and, beyond the
    paper, advantages normalised per probe index. `advantage`: "return", (G_k - b_k) with b_k fitted to G_k (ours,
    REINFORCE with a baseline), or "reward", (r_k - b_k) with b_k fitted to r_k, eq. (6) as the paper writes it."""

    gamma: float = 0.95
    beta: float = 1.0
    reward: Reward = "correct"
    normalize_advantage: bool = False
    advantage: Literal["return", "reward"] = "return"
    spread: float = 0.1  # "new_touch": the distance (in the rollout's point units: 5 cm at point_scale 2) paid in full

    def __post_init__(self) -> None:
        if not 0.0 <= self.gamma <= 1.0:
            raise ValueError(f"loss.gamma={self.gamma}: the discount must be in [0, 1]")
        if not all(term in REWARDS for term in str(self.reward).split("+")):
            raise ValueError(f"loss.reward={self.reward!r}: expected one of {REWARDS}, or a sum of them joined by '+'")
        if not self.spread > 0:
            raise ValueError(f"loss.spread={self.spread}: the distance a new touch is paid in full must be > 0")
        if self.advantage not in ("return", "reward"):
            raise ValueError(f"loss.advantage={self.advantage!r}: expected 'return' or 'reward'")

    def policy_weight(self, policy_scale: float = 1.0) -> float:
        """The policy term's weight in the loss: beta, times the policy's spread scale (see __call__)."""
        return self.beta * policy_scale

    def __call__(self, logits: Tensor, labels: Tensor, log_pi: Tensor | None = None, baseline: Tensor | None = None,
                 policy_scale: float = 1.0, points: Tensor | None = None) -> dict[str, Tensor]:
        """logits (B, N, C), the prediction after each probe; log_pi (B, N) log pi(a_k | s_k) of the detached
        requests; baseline (B, N) b_k from detached states; points (B, N, 4) the probes' points (the rewards a probe
        pays itself read them). Without a policy to train (a fixed scan, or a teacher's probes) only the cross-entropy
        remains. policy_scale multiplies beta: the gradient of log N grows as 1 / std, so a shrinking std must not let
        the policy term crowd the others out of the clipped gradient."""
        n_probes = logits.shape[1]
        correct = (logits.argmax(-1) == labels[:, None]).float()
        rewards = rewards_of(logits, labels, self.reward, points, self.spread)  # r_k, no gradient
        # sum_o y_o log pi_c(o), on the prediction after every probe
        cross_entropy = F.cross_entropy(logits.flatten(0, 1), labels.repeat_interleave(n_probes))
        terms = {"loss_ce": cross_entropy, "reward": rewards.mean(), "acc": correct[:, -1].mean()}
        if log_pi is None:
            terms["loss"] = cross_entropy
            return terms
        # G_k, eq. (3), or r_k as eq. (6) writes it: what b_k is fitted to and the advantage is measured from
        returns = discounted_returns(rewards, self.gamma) if self.advantage == "return" else rewards
        advantage = (returns - baseline).detach()  # (G_k - b_k): the baseline reduces variance, not the gradient path
        terms.update(advantage_mean=advantage.mean(), advantage_std=advantage.std())
        if self.normalize_advantage:  # beyond the paper: unit-scale advantages per probe index
            advantage = advantage / (advantage.std(0, keepdim=True) + 1e-6)
        policy = -(log_pi * advantage).mean()  # autograd of log N(x; mu, sigma) gives xi_mu, xi_sigma of eq. (4), (5)
        baseline_mse = F.mse_loss(baseline, returns)  # b_k is fitted to the return
        terms.update(loss_policy=policy, loss_baseline=baseline_mse,
                     loss=cross_entropy + self.policy_weight(policy_scale) * policy + baseline_mse)
        return terms
