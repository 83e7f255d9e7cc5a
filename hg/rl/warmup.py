"""What the first training steps probe with, before the policy learns by REINFORCE (beyond the paper): the policy
itself untrained, its prior scan (with random detours), or a teacher's recorded episodes to copy. The classifiers
learn meanwhile."""
from __future__ import annotations

from typing import Any, Protocol

import numpy as np
import torch
from torch import Tensor

from hg.policies import Detours, Imitation, Policy
from hg.rl.loss import log_p_true
from hg.rl.rollout import Rollout, probe_points
from hg.sim import ProbeSimulator


class WarmupModel(Protocol):
    """What a warm-up's targets may read of the model (hg.lightning.HapticGlance): its policy, its simulator, still
    holding the rollout's episodes, and its heads' prediction after each probe."""

    policy: Policy
    sim: ProbeSimulator
    hparams: Any  # .point_scale: how a rollout scales its points

    def predict(self, rollout: Rollout) -> tuple[Tensor, Tensor]: ...


class Warmup:
    """For the first `steps` training steps only the classifiers learn, on the probes of the untrained policy.
    `imitate`: the policy learns to copy the warm-up's requests (an imitation term beside the cross-entropy)."""

    imitate = False

    def __init__(self, steps: int) -> None:
        if steps < 1:
            raise ValueError(f"warmup.steps={steps}: must be >= 1")
        self.steps = steps

    def episodes(self, labels: Tensor, poses: Tensor, step: int) -> tuple[Tensor, Tensor, Tensor | None, Tensor | None]:
        """(labels, poses, requests (B, N, 4) or None, faults (B, N, 2) or None) of training step `step`: None
        requests leave the probing to `prober`."""
        return labels, poses, None, None

    def prober(self, policy: Policy) -> Policy:
        """What probes when the warm-up gives no requests."""
        return policy

    def targets(self, model: WarmupModel, rollout: Rollout, labels: Tensor, seed: int) -> Imitation:
        """What an imitating policy learns to ask for in the states of `rollout` (of the episodes `labels`, drawn with
        the batch's `seed`): by default the requests the warm-up sent."""
        return Imitation(rollout.actions)


class FollowPrior(Warmup):
    """The policy's prior scan probes, untrained, so that the policy then starts exactly where the classifiers
    learned. `imitate`: the policy learns to copy the scan meanwhile, for a policy that does not start on its prior
    (a choice among candidates; a Gaussian starts on it by construction)."""

    def __init__(self, steps: int, imitate: bool = False) -> None:
        super().__init__(steps)
        self.imitate = imitate

    def prober(self, policy: Policy) -> Policy:
        if getattr(policy, "prior", None) is None:
            raise ValueError(f"model.warmup: FollowPrior probes with the policy's prior scan; {type(policy).__name__} "
                             "has none (model.policy.init_args.prior)")
        return policy.prior


class ImitateTeacher(Warmup):
    """The teacher's episodes in turn, with the requests it chose (and the sensor faults it read), which the policy
    learns to copy: the greedy planner's, written by scripts/plan.py --save-rollouts."""

    imitate = True

    def __init__(self, steps: int, teachers: list[str]) -> None:
        super().__init__(steps)
        if not teachers:
            raise ValueError("warmup.teachers: give at least one teacher file (scripts/plan.py --save-rollouts)")
        self.teachers = list(teachers)
        self.teacher: dict[str, Tensor] | None = None  # loaded by the model's setup, which knows the world

    def episodes(self, labels: Tensor, poses: Tensor, step: int) -> tuple[Tensor, Tensor, Tensor | None, Tensor | None]:
        if self.teacher is None:
            raise RuntimeError("ImitateTeacher: the teacher files were not loaded (HapticGlance.setup)")
        n = len(self.teacher["labels"])
        rows = (step * len(labels) + torch.arange(len(labels))) % n
        faults = None if self.teacher["faults"] is None else self.teacher["faults"][rows]
        return (self.teacher["labels"][rows].to(labels.device), self.teacher["poses"][rows].to(poses.device),
                self.teacher["requests"][rows], faults)


class ExploreAroundPrior(FollowPrior):
    """FollowPrior(imitate=true) whose scan, at each probe with probability `explore`, gives way to one of the
    choice's candidates not yet probed, drawn at random; the choice learns to ask for what the scan would ask given
    what was really probed (Scan.requests of the rollout's points), except where that was probed already. Why: heads
    that learned behind the scan's probes alone read any other probe worse (docs/findings.md, section 17: they read
    a little better for it; a choice that also copied the detours lost)."""

    def __init__(self, steps: int, explore: float = 0.3) -> None:
        super().__init__(steps, imitate=True)
        if not 0.0 < explore <= 1.0:
            raise ValueError(f"warmup.explore={explore}: the share of probes drawn at random must be in (0, 1]")
        self.explore = explore

    def prober(self, policy: Policy) -> Policy:
        prior = super().prober(policy)
        require_candidates(policy, "ExploreAroundPrior draws its detours among")
        return Detours(prior, policy.candidates, self.explore)

    def targets(self, model: WarmupModel, rollout: Rollout, labels: Tensor, seed: int) -> Imitation:
        policy = model.policy
        wanted = policy.prior.requests(rollout.points)
        # request k repeats an earlier one: the choice never probes a place twice, so it cannot be copied there
        same = policy.location.index_of(wanted)[:, :, None] == policy.location.index_of(rollout.actions)[:, None]
        earlier = torch.ones(same.shape[1:], dtype=torch.bool, device=same.device).tril(-1)  # (k, j): j < k
        return Imitation(wanted, ~(same & earlier).any(-1))


class ImitateBestProbe(Warmup):
    """The choice probes with its own draws and learns, at one probe k of each training step (drawn at random), to
    ask for whichever of `samples` candidates not yet probed, or the request it sent, the heads as they stand read
    best: log p(true class) after probes 1..k and that candidate. The targets are privileged (each candidate is
    probed on the training episode itself, pose and all); the choice learns from what it has read which candidate
    tends to win. Why: a choice that learns by the class reward of the probes it sampled stayed on the scan it
    started from (docs/findings.md, sections 15-17); this compares probes in the same state, with the same heads,
    every step, and needs no scan to start from. After `steps` it hands over to the hybrid rule as any warm-up does
    (configs/parts/best_probe.yaml sets them beyond the run: it never does)."""

    imitate = True

    def __init__(self, steps: int, samples: int = 8) -> None:
        super().__init__(steps)
        if samples < 1:  # fewer are compared where fewer are left (none at the last probe of n_probes candidates)
            raise ValueError(f"warmup.samples={samples}: compare the sent request with at least 1 other candidate")
        self.samples = samples

    def prober(self, policy: Policy) -> Policy:
        require_candidates(policy, "ImitateBestProbe compares")
        return policy

    @torch.no_grad()
    def targets(self, model: WarmupModel, rollout: Rollout, labels: Tensor, seed: int) -> Imitation:
        """The best of the sent request and the drawn candidates at probe k, by the heads' log p(true class) after
        probes 1..k and it (a tie goes to the sent one), to be copied among those compared (a choice over all the
        candidates would learn only how likely each is to be drawn and win, and stay nearly even); every other probe
        is left out (reading on to the episode's end, with the rollout's own later probes, did no better:
        docs/findings.md, section 19). Row k of a branch of k + 1 probes is what the full rollout's row k would be:
        every encoder and head reads probes 1..k + 1 only, and a head of whole episodes only where k + 1 = n_probes
        (HapticGlance.predict)."""
        policy, (batch, n_probes) = model.policy, rollout.actions.shape[:2]
        if not np.array_equal(model.sim.labels, labels.cpu().numpy()):
            raise RuntimeError("ImitateBestProbe.targets: model.sim no longer holds the rollout's episodes (probe the "
                               "candidates right after the rollout, before the simulator is reset)")
        rng = np.random.default_rng((seed, 1))  # not the rollout's stream (seed alone), nor the data's
        k = int(rng.integers(n_probes))
        sent = policy.location.index_of(rollout.actions[:, :k + 1])  # (B, k + 1): probes 1..k and the one sent
        n_candidates = len(policy.candidates)
        samples = max(0, min(self.samples, n_candidates - k - 1))
        # candidates not probed before and not sent, drawn without replacement: the lowest of random keys
        keys = torch.from_numpy(rng.random((batch, n_candidates))).to(sent.device)
        keys = keys.scatter(1, sent, 2.0)  # taken: never drawn
        drawn = torch.cat([sent[:, k:], keys.argsort(1)[:, :samples]], 1)  # (B, 1 + samples), the sent one first
        requests = policy.candidates[drawn]  # (B, S, 4)
        others = [probe_points(model.sim, requests[:, s], model.hparams.point_scale)[0].to(requests.device)
                  for s in range(1, drawn.shape[1])]
        points = torch.stack([rollout.points[:, k], *others], 1)  # the sent one's: what the rollout read
        logits = model.predict(Rollout(actions=branches(rollout.actions, requests, k),
                                       requests=branches(rollout.requests, requests, k),
                                       points=branches(rollout.points, points, k),
                                       reached=torch.ones(batch * drawn.shape[1], k + 1, dtype=torch.bool,
                                                          device=requests.device)))[0][:, k]
        read = log_p_true(logits.view(*drawn.shape, -1), labels)  # (B, S)
        wanted = rollout.actions.clone()
        wanted[:, k] = requests[torch.arange(batch, device=requests.device), read.argmax(1)]
        valid = torch.zeros(batch, n_probes, dtype=torch.bool, device=wanted.device)
        valid[:, k] = True
        among = torch.ones(batch, n_probes, n_candidates, dtype=torch.bool, device=wanted.device)
        among[:, k] = False
        among[:, k].scatter_(1, drawn, True)
        return Imitation(wanted, valid, among)


def require_candidates(policy: Policy, who: str) -> None:
    """Refuse a policy that chooses among no candidates, for a warm-up that draws or compares them."""
    if getattr(policy, "candidates", None) is None:
        raise ValueError(f"model.warmup: {who} the policy's candidates; {type(policy).__name__} has none "
                         "(hg.policies.CandidateChoice has)")


def branches(prefix: Tensor, last: Tensor, k: int) -> Tensor:
    """prefix (B, N, F) and last (B, S, F) -> (B x S, k + 1, F): rows 1..k of prefix followed by each of the S."""
    head = prefix[:, None, :k].expand(-1, last.shape[1], -1, -1)
    return torch.cat([head, last[:, :, None]], 2).flatten(0, 1)
