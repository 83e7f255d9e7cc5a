"""Point cloud classifiers for the paper's noise comparison (Fig. 4b): PointNet and DGCNN on 10 sparse points."""

import torch
from torch import Tensor, nn


def _bn_act(layer: nn.Module, width: int, act: nn.Module, bn: type[nn.Module] = nn.BatchNorm1d) -> nn.Sequential:
    """layer -> BatchNorm -> activation, the unit both networks are built from."""
    return nn.Sequential(layer, bn(width), act)


def _head(in_dim: int, n_classes: int, act: nn.Module, dropout: float) -> nn.Sequential:
    """Global feature -> 512 -> 256 -> class logits, the classification head shared by PointNet and DGCNN."""
    return nn.Sequential(
        _bn_act(nn.Linear(in_dim, 512, bias=False), 512, act),
        nn.Dropout(dropout),
        _bn_act(nn.Linear(512, 256, bias=False), 256, act),
        nn.Dropout(dropout),
        nn.Linear(256, n_classes),
    )


class PointNet(nn.Module):
    """Vanilla PointNet (Qi et al. 2017) without the input and feature T-nets: shared MLP 64-64-128-1024,
    max pool (order invariant), then 512-256-classes with BatchNorm and dropout."""

    def __init__(self, n_classes: int, in_dim: int = 3, dropout: float = 0.3) -> None:
        super().__init__()
        dims = [in_dim, 64, 64, 128, 1024]
        self.shared = nn.Sequential(
            *(_bn_act(nn.Conv1d(a, b, 1, bias=False), b, nn.ReLU()) for a, b in zip(dims[:-1], dims[1:]))
        )
        self.head = _head(1024, n_classes, nn.ReLU(), dropout)

    def forward(self, points: Tensor) -> Tensor:
        """(B, P, in_dim) -> logits (B, n_classes)."""
        return self.head(self.shared(points.transpose(1, 2)).amax(-1))


def _edge_features(x: Tensor, k: int) -> Tensor:
    """EdgeConv input (x_j - x_i, x_i) over the k nearest neighbours in feature space: (B, C, P) -> (B, 2C, P, k)."""
    dist = torch.cdist(x.transpose(1, 2), x.transpose(1, 2))  # (B, P, P)
    idx = dist.topk(k, dim=-1, largest=False).indices  # includes the point itself, as in the reference code
    neighbours = torch.gather(
        x.unsqueeze(2).expand(-1, -1, x.shape[2], -1), 3, idx.unsqueeze(1).expand(-1, x.shape[1], -1, -1)
    )  # (B, C, P, k): neighbours[b, c, i, m] = x[b, c, idx[b, i, m]]
    centre = x.unsqueeze(-1).expand_as(neighbours)
    return torch.cat([neighbours - centre, centre], 1)


class DGCNN(nn.Module):
    """DGCNN (Wang et al. 2019): EdgeConv 64-64-128-256 on a kNN graph rebuilt in feature space at every
    layer, concatenated -> 1024, max + average pool, then 512-256-classes."""

    def __init__(self, n_classes: int, k: int = 9, in_dim: int = 3, dropout: float = 0.5) -> None:
        super().__init__()
        self.k = k
        act = nn.LeakyReLU(0.2)
        dims = [in_dim, 64, 64, 128, 256]
        self.edge_convs = nn.ModuleList(
            _bn_act(nn.Conv2d(2 * a, b, 1, bias=False), b, act, nn.BatchNorm2d) for a, b in zip(dims[:-1], dims[1:])
        )
        self.fuse = _bn_act(nn.Conv1d(sum(dims[1:]), 1024, 1, bias=False), 1024, act)
        self.head = _head(2 * 1024, n_classes, act, dropout)

    def forward(self, points: Tensor) -> Tensor:
        """(B, P, in_dim) -> logits (B, n_classes); needs k < P."""
        if self.k >= points.shape[1]:
            raise ValueError(f"DGCNN k={self.k} must be below the number of points P={points.shape[1]}")
        x, layers = points.transpose(1, 2), []
        for conv in self.edge_convs:
            x = conv(_edge_features(x, self.k)).amax(-1)
            layers.append(x)
        x = self.fuse(torch.cat(layers, 1))
        return self.head(torch.cat([x.amax(-1), x.mean(-1)], 1))
