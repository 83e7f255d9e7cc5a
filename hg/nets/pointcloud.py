"""Point cloud classifiers: PointNet and DGCNN on 10 sparse points for the paper's noise comparison (Fig. 4b), and
the touch-set classifier that reads the touched points of a rollout."""
from typing import Literal

import torch
from torch import Tensor, nn

from hg.nets.dims import Dims
from hg.nets.mirror import left_of_line, reflect
from hg.nets.mlp import mlp


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
        """(B, P, in_dim) -> logits (B, n_classes); a cloud of no more than k points is one neighbourhood (every
        point, itself included), so the net trained on 10 points can read fewer."""
        x, layers, k = points.transpose(1, 2), [], min(self.k, points.shape[1])
        for conv in self.edge_convs:
            x = conv(_edge_features(x, k)).amax(-1)
            layers.append(x)
        x = self.fuse(torch.cat(layers, 1))
        return self.head(torch.cat([x.amax(-1), x.mean(-1)], 1))


def prefix_touch_centres(points: Tensor) -> tuple[Tensor, Tensor]:
    """points (B, N, 4) -> the mean of the touched points among probes 1..k+1 at every k (B, N, 3), 0 before the
    first touch, and how many touched (B, N, 1): the centre a prefix's points are read around."""
    n = points.shape[1]
    touched = (points[..., 3] > 0.5).to(points.dtype)
    prefix = torch.ones(n, n, dtype=points.dtype, device=points.device).tril()  # [k, j]: probe j <= k
    mask = prefix * touched[:, None, :]  # (B, K, J): probe j touched and is in prefix k
    count = mask.sum(-1, keepdim=True)
    return (mask @ points[..., :3]) / count.clamp(min=1), count


class TouchSetClassifier(nn.Module):
    """Beyond the paper: a PointNet over every probe so far, its points taken relative to the mean of the touched
    ones. Where the object lies is no class cue, its shape is; PCRN reads points in the episode frame and learns
    this invariance slowly. logits[:, k] reads probes 1..k+1 only (causal), like every classifier of the rollout.

    Shared MLP on each probe (X, Y, Z relative to the touches' mean, T) -> max pool over the prefix -> (pooled,
    share of probes that touched) -> MLP -> logits; LayerNorm before every activation. A miss reports where its
    ray ended, so it says where the object is not, which tells where it ends.

    With `mirror`, each prefix's probes are mirrored across the probe line's vertical plane (X = `line_x`, point
    coordinates; the model sets it from its scene) when their touches' mean lies on its -x side: an object and its
    mirror image across the line then read alike. Only for object sets whose shapes are mirror-symmetric: `auto`
    mirrors when every object of the set is its own mirror image (the model decides when it attaches a simulator).

    With `last_only`, the head scores the whole episode only (one row): the model lets it replace the prediction
    after the last probe, where one head scoring every prefix reads a reordered scan's full set worse.
    """

    def __init__(self, dims: Dims, mirror: bool | Literal["auto"] = False, last_only: bool = False,
                 shared: tuple[int, ...] = (64, 128, 512), hidden: int = 256, scale: float = 5.0) -> None:
        super().__init__()
        self.mirror, self.last_only, self.line_x = mirror, last_only, 0.0
        self.scale = scale  # relative coordinates of a ~0.2 m object (x point_scale) to about unit size
        self.shared = mlp([4, *shared], layer_norm=True)
        self.pooled_dim = shared[-1] + 1  # the pooled features and the share of probes that touched
        self.head = mlp([self.pooled_dim, hidden, dims.n_classes], last_act=False, layer_norm=True)

    def forward(self, rep: Tensor | None, points: Tensor) -> Tensor:
        """points (B, N, 4): X, Y, Z and the contact flag T -> logits (B, N, n_classes), or (B, 1, n_classes) with
        last_only. rep is not read: the touch set reads the points alone."""
        return self.head(self.pooled(points, last_only=self.last_only))

    def pooled(self, points: Tensor, last_only: bool = False) -> Tensor:
        """points (B, N, 4) -> (B, N, pooled_dim): row k pools probes 1..k+1 and ends with their share of touches.
        last_only: only the last row, (B, 1, pooled_dim), from N pairs.

        The shared MLP runs once per (prefix k, probe j <= k) pair, N (N + 1) / 2 of them, not N x N: a point's
        features depend on the prefix (its centre), and the pairs with j > k would only be masked out. This MLP is
        most of a training step's time in the touch-set rows."""
        b, n = points.shape[:2]
        xyz, touched = points[..., :3], (points[..., 3] > 0.5).to(points.dtype)
        centre, count = prefix_touch_centres(points)
        if last_only:  # the pairs of the last prefix
            j = torch.arange(n, device=points.device)
            k = torch.full_like(j, n - 1)
        else:  # the pairs, prefix by prefix
            k, j = torch.tril_indices(n, n, device=points.device)
        at, centre_k = xyz[:, j], centre[:, k]  # (B, P, 3): each pair's point and its prefix's centre
        if self.mirror == "auto":
            raise RuntimeError("TouchSetClassifier(mirror='auto'): attach the model to a simulator first "
                               "(HapticGlance.attach decides from its object set)")
        if self.mirror:  # X -> 2 line_x - X for the prefixes whose touches lie on the -x side
            flip = left_of_line(points, self.line_x)[:, k]
            at, centre_k = (reflect(v, 0, self.line_x, flip) for v in (at, centre_k))
        relative = (at - centre_k) * self.scale  # (B, P, 3)
        features = self.shared(torch.cat([relative, touched[:, j, None]], -1))  # (B, P, F)
        width = features.shape[-1]
        features = features.new_full((b, n, width), float("-inf")).scatter_reduce(
            1, k[None, :, None].expand(b, -1, width), features, "amax")  # max over each prefix's pairs: (B, K, F)
        share = count / torch.arange(1, n + 1, dtype=points.dtype, device=points.device)[:, None]
        pooled = torch.cat([features, share], -1)
        return pooled[:, -1:] if last_only else pooled
