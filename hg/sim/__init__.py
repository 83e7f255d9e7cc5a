"""Simulator: headless PyBullet, no torch. One client owner, one robot adapter, one object-set loader, one scene."""
from hg.sim.objects import ObjectSet, load_object_set
from hg.sim.poses import SPLITS, PoseRegions, sample_episodes
from hg.sim.robot import DEFAULT_URDF, ProbeArm
from hg.sim.scene import Scene, candidate_requests
from hg.sim.simulator import MODES, ProbeResult, ProbeSimulator, SensorNoise
from hg.sim.symmetry import Symmetry, object_symmetries

__all__ = ["DEFAULT_URDF", "MODES", "SPLITS", "ObjectSet", "PoseRegions", "ProbeArm", "ProbeResult",
           "ProbeSimulator", "Scene", "SensorNoise", "Symmetry", "candidate_requests", "load_object_set",
           "object_symmetries", "sample_episodes"]
