"""What the first training steps probe with, before the policy learns by REINFORCE (beyond the paper): the policy
itself untrained, its prior scan (with random detours), or a teacher's recorded episodes to copy. The classifiers
learn meanwhile."""
from __future__ import annotations

import torch
from torch import Tensor

from hg.policies import Detours, Imitation, Policy
from hg.rl.rollout import Rollout


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

    def targets(self, policy: Policy, rollout: Rollout) -> Imitation:
        """What an imitating policy learns to ask for in the states of `rollout`: by default the requests the warm-up
        sent."""
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
        if getattr(policy, "candidates", None) is None:
            raise ValueError(f"model.warmup: ExploreAroundPrior draws its detours among the policy's candidates; "
                             f"{type(policy).__name__} has none (hg.policies.CandidateChoice has)")
        return Detours(prior, policy.candidates, self.explore)

    def targets(self, policy: Policy, rollout: Rollout) -> Imitation:
        wanted = policy.prior.requests(rollout.points)
        # request k repeats an earlier one: the choice never probes a place twice, so it cannot be copied there
        same = policy.location.index_of(wanted)[:, :, None] == policy.location.index_of(rollout.actions)[:, None]
        earlier = torch.ones(same.shape[1:], dtype=torch.bool, device=same.device).tril(-1)  # (k, j): j < k
        return Imitation(wanted, ~(same & earlier).any(-1))
