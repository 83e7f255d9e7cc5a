"""The LSTM baseline encoder of Fleer et al. 2020 (Haptic-Attention-Model), adapted to our requests and points."""

import torch
from torch import Tensor, nn

from hg.nets.mlp import mlp


class LSTMEncoder(nn.Module):
    """Drop-in alternative to PCRN (same forward and out_dim): touch 4 -> 256 -> 64 and request 4 -> 64,
    concatenated -> 256 -> 256, then a 256-unit LSTM; causal because the LSTM runs forward in time."""

    def __init__(self, request_dim: int = 4, point_dim: int = 4, hidden: int = 256) -> None:
        super().__init__()
        self.out_dim = hidden
        self.touch = mlp([point_dim, 256, 64], act=nn.ReLU)
        self.request = mlp([request_dim, 64], act=nn.ReLU)
        self.fuse = mlp([128, 256, 256], act=nn.ReLU)
        self.lstm = nn.LSTM(256, hidden, batch_first=True)

    def forward(self, requests: Tensor, points: Tensor) -> Tensor:
        """S_R (B, N, request_dim), S_C (B, N, point_dim) -> LSTM output after each probe (B, N, hidden)."""
        out, _ = self.lstm(self.fuse(torch.cat([self.request(requests), self.touch(points)], -1)))
        return out

    def step(self, request: Tensor, point: Tensor, memory: tuple[Tensor, Tensor] | None) -> tuple[Tensor, tuple]:
        """One more probe, (B, request_dim), (B, point_dim) -> (B, hidden): row k of forward(), the LSTM
        carried on from its (h, c) after probes 1..k - 1."""
        out, memory = self.lstm(self.fuse(torch.cat([self.request(request), self.touch(point)], -1))[:, None], memory)
        return out[:, 0], memory
