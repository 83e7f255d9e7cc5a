"""Policies: what request next. One protocol (hg.policies.base.Policy); the paper's Gaussian location network, a
choice among the planner's candidate probes, and fixed scans are small classes behind it, chosen in YAML."""
from hg.policies.base import COMPONENTS, Imitation, LearnedPolicy, Observation, Policy, PolicyEval
from hg.policies.candidates import CandidateChoice
from hg.policies.gaussian import GaussianPolicy
from hg.policies.scans import Detours, LineScan, RandomProbes, Scan, SidePickingScan

__all__ = ["COMPONENTS", "CandidateChoice", "Detours", "GaussianPolicy", "Imitation", "LearnedPolicy", "LineScan",
           "Observation", "Policy", "PolicyEval", "RandomProbes", "Scan", "SidePickingScan"]
