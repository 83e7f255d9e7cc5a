"""Heads on the per-probe representation: the reinforcement baseline b_k and the classifiers (paper sec. 2.2 (c)).

Every classifier is a head: `head(rep, points) -> logits (B, N, classes)`, row k the prediction after probe k + 1,
reading probes 1..k + 1 only. The model sums its heads' logits; a head with `last_only` scores the last probe only
and replaces that row (hg.lightning.module.HapticGlance.predict).
"""

import torch
from torch import Tensor, nn

from hg.nets.dims import Dims
from hg.nets.mlp import cumulative_mean, mlp


class Baseline(nn.Module):
    """b_k of the hybrid update rule, eq. (6): predicts the return to reduce the variance of eq. (3).

    The caller must pass a detached representation: the baseline is fitted by MSE on the return and must
    not shape the representation itself.
    """

    def __init__(self, in_dim: int, hidden: int = 64) -> None:
        super().__init__()
        self.net = mlp([in_dim, hidden, 1], last_act=False)

    def forward(self, rep: Tensor) -> Tensor:
        """(B, N, D) -> (B, N)."""
        return self.net(rep).squeeze(-1)


class FCClassifier(nn.Module):
    """PCRN-FC: mean pool of the probes collected so far, then two FC layers; logits[:, k] is the
    prediction after probe k, so every probe is rewarded on all the evidence gathered up to it."""

    last_only = False

    def __init__(self, dims: Dims, hidden: int = 256) -> None:
        super().__init__()
        self.net = mlp([dims.rep, hidden, dims.n_classes], last_act=False)

    def forward(self, rep: Tensor, points: Tensor) -> Tensor:
        """(B, N, D) -> logits (B, N, n_classes)."""
        return self.net(cumulative_mean(rep))


class NClassClassifier(nn.Module):
    """PCRN-N-class: one two-layer FC classifier per probe. The paper's probe mask (the identity over
    probes) lets classifier k see only the current glance, i.e. row k of the representation, which the
    P2-CARBs have already made context aware of probes 1..k."""

    last_only = False

    def __init__(self, dims: Dims, hidden: int = 256) -> None:
        super().__init__()
        self.classifiers = nn.ModuleList(mlp([dims.rep, hidden, dims.n_classes], last_act=False)
                                         for _ in range(dims.n_probes))

    def forward(self, rep: Tensor, points: Tensor) -> Tensor:
        """(B, N, D) -> logits (B, N, n_classes); a rollout shorter than n_probes uses the first classifiers."""
        n = rep.shape[1]
        if n > len(self.classifiers):
            raise ValueError(f"NClassClassifier has n_probes={len(self.classifiers)} classifiers, got {n} probes")
        return torch.stack([clf(rep[:, k]) for k, clf in enumerate(self.classifiers[:n])], 1)


class LinearClassifier(nn.Linear):
    """The LSTM baseline's classifier (Fleer et al. 2020): linear on the LSTM output at each probe,
    (B, N, D) -> logits (B, N, n_classes)."""

    last_only = False

    def __init__(self, dims: Dims) -> None:
        super().__init__(dims.rep, dims.n_classes)

    def forward(self, rep: Tensor, points: Tensor) -> Tensor:
        return super().forward(rep)
