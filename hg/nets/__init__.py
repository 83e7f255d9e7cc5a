"""Plain torch networks of the reinforcement haptic glance framework (no Lightning here)."""

from hg.nets.heads import AlongLineClassifier, Baseline, FCClassifier, LinearClassifier, NClassClassifier
from hg.nets.location import CandidateLocationNetwork, LocationNetwork
from hg.nets.library import LibraryNamer
from hg.nets.lstm import LSTMEncoder
from hg.nets.mirror import left_of_line, reflect
from hg.nets.mlp import cumulative_mean, mlp
from hg.nets.p2carb import P2CARB
from hg.nets.pcrn import PCRN
from hg.nets.pointcloud import DGCNN, PointNet, TouchSetClassifier

__all__ = [
    "AlongLineClassifier",
    "DGCNN",
    "PCRN",
    "P2CARB",
    "Baseline",
    "CandidateLocationNetwork",
    "FCClassifier",
    "LSTMEncoder",
    "LibraryNamer",
    "LinearClassifier",
    "LocationNetwork",
    "NClassClassifier",
    "PointNet",
    "TouchSetClassifier",
    "cumulative_mean",
    "left_of_line",
    "mlp",
    "reflect",
]
