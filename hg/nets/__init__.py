"""Plain torch networks of the reinforcement haptic glance framework: tensors in, tensors out (no Lightning, no
simulator)."""

from hg.nets.dims import Dims
from hg.nets.heads import Baseline, FCClassifier, LinearClassifier, NClassClassifier
from hg.nets.location import CandidateLocationNetwork, LocationNetwork, candidate_index
from hg.nets.lstm import LSTMEncoder
from hg.nets.mirror import left_of_line, reflect
from hg.nets.mlp import cumulative_mean, mlp
from hg.nets.p2carb import P2CARB
from hg.nets.pcrn import CentredPCRN, PCRN
from hg.nets.pointcloud import DGCNN, PointNet, TouchSetClassifier

__all__ = [
    "CentredPCRN",
    "DGCNN",
    "PCRN",
    "P2CARB",
    "Baseline",
    "CandidateLocationNetwork",
    "Dims",
    "FCClassifier",
    "LSTMEncoder",
    "LinearClassifier",
    "LocationNetwork",
    "NClassClassifier",
    "PointNet",
    "TouchSetClassifier",
    "candidate_index",
    "cumulative_mean",
    "left_of_line",
    "mlp",
    "reflect",
]
