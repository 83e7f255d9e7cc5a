"""Reinforcement learning without Lightning: the rollout (the caller of the simulator during training and evaluation,
but for ImitateBestProbe's look at other candidates) and the hybrid update rule, eq. (6)."""
from hg.rl.loss import HybridLoss, discounted_returns
from hg.rl.rollout import Rollout, rollout
from hg.rl.warmup import ExploreAroundPrior, FollowPrior, ImitateBestProbe, ImitateTeacher, Warmup

__all__ = ["ExploreAroundPrior", "FollowPrior", "HybridLoss", "ImitateBestProbe", "ImitateTeacher", "Rollout",
           "discounted_returns", "rollout", "Warmup"]
