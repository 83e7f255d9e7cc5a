"""Reinforcement learning without Lightning: the rollout (the only caller of the simulator during training and
evaluation) and the hybrid update rule, eq. (6)."""
from hg.rl.loss import HybridLoss, discounted_returns
from hg.rl.rollout import Rollout, rollout
from hg.rl.warmup import ExploreAroundPrior, FollowPrior, ImitateTeacher, Warmup

__all__ = ["ExploreAroundPrior", "FollowPrior", "HybridLoss", "ImitateTeacher", "Rollout", "discounted_returns",
           "rollout", "Warmup"]
