"""PCRN: the point cloud representation network (paper sec. 2.2 (a))."""

import torch
from torch import Tensor, nn

from hg.nets.mlp import mlp
from hg.nets.p2carb import P2CARB
from hg.nets.pointcloud import prefix_touch_centres


class PCRN(nn.Module):
    """Embeds the probe request sequence S_R and the collected point sequence S_C into one mutual,
    causal representation per probe: two P2-CARBs, concatenated, fused by a shared two-layer MLP."""

    def __init__(self, request_dim: int = 4, point_dim: int = 4, width: int = 128, out_dim: int = 256) -> None:
        super().__init__()
        self.out_dim = out_dim
        self.requests = P2CARB(request_dim, feat_dims=(64, 64, width), att_width=width)
        self.points = P2CARB(point_dim, feat_dims=(64, 64, width), att_width=width)
        self.fuse = mlp([2 * width, out_dim, out_dim])

    def forward(self, requests: Tensor, points: Tensor) -> Tensor:
        """S_R (B, N, request_dim) (Py, Ux, Uy, Uz), S_C (B, N, point_dim) (X, Y, Z, T) -> (B, N, out_dim)."""
        return self.fuse(torch.cat([self.requests(requests), self.points(points)], -1))

    def step(self, request: Tensor, point: Tensor, memory: tuple | None) -> tuple[Tensor, tuple]:
        """One more probe, (B, request_dim), (B, point_dim) -> (B, out_dim) and the memory for the next one:
        row k of forward(), computed from probe k and the memory of probes 1..k - 1."""
        requests_memory, points_memory = memory if memory is not None else (None, None)
        r, requests_memory = self.requests.step(request, requests_memory)
        p, points_memory = self.points.step(point, points_memory)
        return self.fuse(torch.cat([r, p], -1)), (requests_memory, points_memory)


class CentredPCRN(PCRN):
    """Beyond the paper: PCRN whose point block reads each prefix's points relative to the mean of its touches (times
    `scale`), as PointNet centres its clouds. Where the object lies is no class cue, its shape is; PCRN reads points
    in the episode frame and learns that invariance slowly (docs/findings.md). Row k encodes probes 1..k around
    prefix k's own centre: N encodings of the point sequence instead of one."""

    def __init__(self, request_dim: int = 4, point_dim: int = 4, width: int = 128, out_dim: int = 256,
                 scale: float = 5.0) -> None:
        super().__init__(request_dim, point_dim, width, out_dim)
        self.scale = scale  # as TouchSetClassifier's: relative coordinates of an object to about unit size

    def forward(self, requests: Tensor, points: Tensor) -> Tensor:
        return self.fuse(torch.cat([self.requests(requests), self.point_rows(points)], -1))

    def around(self, points: Tensor, centres: Tensor) -> Tensor:
        """points (..., J, 4) relative to centres (..., 1, 3), scaled; T unchanged."""
        return torch.cat([(points[..., :3] - centres) * self.scale, points[..., 3:]], -1)

    def point_rows(self, points: Tensor) -> Tensor:
        """(B, N, 4) -> (B, N, width): row k is the point block over probes 1..k around prefix k's centre (the
        block is causal, so probes after k in the same sequence are not read)."""
        b, n = points.shape[:2]
        centres = prefix_touch_centres(points)[0]  # (B, K, 3)
        prefixes = self.around(points[:, None].expand(-1, n, -1, -1), centres[:, :, None])  # (B, K, J, 4)
        encoded = self.points(prefixes.flatten(0, 1)).view(b, n, n, -1)
        return encoded.diagonal(dim1=1, dim2=2).transpose(1, 2)

    def step(self, request: Tensor, point: Tensor, memory: tuple | None) -> tuple[Tensor, tuple]:
        """One more probe: the point block re-reads the probes so far around their new centre (one prefix)."""
        requests_memory, seen = memory if memory is not None else (None, point[:, None, :][:, :0])  # no probe yet
        r, requests_memory = self.requests.step(request, requests_memory)
        seen = torch.cat([seen, point[:, None]], 1)
        last = self.points(self.around(seen, prefix_touch_centres(seen)[0][:, -1:]))[:, -1]
        return self.fuse(torch.cat([r, last], -1)), (requests_memory, seen)
