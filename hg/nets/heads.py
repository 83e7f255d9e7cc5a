"""Heads on the per-probe representation: the reinforcement baseline b_k and the classifiers (paper sec. 2.2 (c))."""

import torch
from torch import Tensor, nn

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
    prediction after probe k + 1, so every probe is rewarded on all the evidence gathered up to it."""

    def __init__(self, in_dim: int, n_classes: int, hidden: int = 256) -> None:
        super().__init__()
        self.net = mlp([in_dim, hidden, n_classes], last_act=False)

    def forward(self, rep: Tensor) -> Tensor:
        """(B, N, D) -> logits (B, N, n_classes)."""
        return self.net(cumulative_mean(rep))


class NClassClassifier(nn.Module):
    """PCRN-N-class: one two-layer FC classifier per probe. The paper's probe mask (the identity over
    probes) lets classifier k see only the current glance, i.e. row k of the representation, which the
    P2-CARBs have already made context aware of probes 1..k."""

    def __init__(self, in_dim: int, n_classes: int, n_probes: int, hidden: int = 256) -> None:
        super().__init__()
        self.classifiers = nn.ModuleList(mlp([in_dim, hidden, n_classes], last_act=False) for _ in range(n_probes))

    def forward(self, rep: Tensor) -> Tensor:
        """(B, N, D) -> logits (B, N, n_classes); a rollout shorter than n_probes uses the first classifiers."""
        n = rep.shape[1]
        if n > len(self.classifiers):
            raise ValueError(f"NClassClassifier has n_probes={len(self.classifiers)} classifiers, got {n} probes")
        return torch.stack([clf(rep[:, k]) for k, clf in enumerate(self.classifiers[:n])], 1)


class LinearClassifier(nn.Linear):
    """The LSTM baseline's classifier (Fleer et al. 2020): linear on the LSTM output at each probe,
    (B, N, D) -> logits (B, N, n_classes)."""

    def __init__(self, in_dim: int, n_classes: int) -> None:
        super().__init__(in_dim, n_classes)
