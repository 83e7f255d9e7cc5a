"""Heads on the per-probe representation: the reinforcement baseline b_k and the classifiers (paper sec. 2.2 (c))."""

import torch
from torch import Tensor, nn

from hg.nets.location import by_place
from hg.nets.mlp import cumulative_mean, mlp
from hg.sim.scene import mirrored_directions


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


class AlongLineClassifier(nn.Module):
    """Beyond the paper: logits from what the probes so far read by candidate (CandidateLocationNetwork.readings:
    probed, touched, how deep), the same function of the readings around every place along the line, then the most
    of each feature over the places: an object moved along the line by whole place steps is read alike (reach: how
    many places one reading sees). Why: on the held-out position cells the greedy planner's namer, whose library
    holds its episodes moved along the line, named our policy's probes 0.947 where our classifiers read them 0.886
    (scripts/accuracy_by_cell.py --namer). With
    `mirror`, the mean of the logits of the readings and of their mirror image (each lean's +x and -x swapped), as
    hg4's mirror-symmetric shapes allow."""

    def __init__(self, n_classes: int, places: int, directions: int, hidden: int = 128, reach: int = 9,
                 mirror: bool = False) -> None:
        super().__init__()
        try:
            swap = mirrored_directions(directions)
        except ValueError as error:
            raise ValueError(f"AlongLineClassifier: {error}") from None
        self.places, self.directions, self.mirror = places, directions, mirror
        # every window of `reach` places that holds a place of the line, those hanging over its ends too (read as
        # places never probed), so that a pattern moved along the line meets the same windows: exactly invariant
        self.conv = nn.Sequential(nn.Conv1d(3 * directions, hidden, reach, padding=reach - 1), nn.ELU(),
                                  nn.Conv1d(hidden, hidden, 1), nn.ELU())
        self.head = mlp([hidden, hidden, n_classes], last_act=False)
        self.register_buffer("swap", torch.tensor(swap))

    def forward(self, readings: Tensor) -> Tensor:
        """(B, N, 3C + ...) readings after probes 1..k + 1 (only the first 3C, per candidate, are read) -> logits
        (B, N, n_classes)."""
        lead, n = readings.shape[:-1], 3 * self.places * self.directions
        local = by_place(readings[..., :n].reshape(-1, n), self.places, self.directions)
        views = [local]
        if self.mirror:
            views.append(local.reshape(len(local), 3, self.directions, self.places)[:, :, self.swap]
                         .reshape(local.shape))
        logits = [self.head(self.conv(view).amax(-1)) for view in views]
        return (sum(logits) / len(logits)).reshape(*lead, -1)
