"""PCRN: the point cloud representation network (paper sec. 2.2 (a))."""

import torch
from torch import Tensor, nn

from hg.nets.mlp import mlp
from hg.nets.p2carb import P2CARB


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
