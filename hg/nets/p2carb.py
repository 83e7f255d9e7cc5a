"""P2-CARB: per point context aware representation block (paper sec. 2.2 (a)), PointGrow's SACA-A made causal."""

from collections.abc import Sequence
from typing import Literal

import torch
from torch import Tensor, nn

from hg.nets.mlp import cumulative_mean, mlp


class P2CARB(nn.Module):
    """Self-attention context awareness (SACA-A, Sun et al. 2020) over a probe sequence.

    Output k aggregates probes 1..k only, so a representation can be read after every probe of a rollout.
    """

    def __init__(
        self,
        in_dim: int,
        feat_dims: Sequence[int] = (64, 64, 128),
        att_width: int = 128,
        aggregate: Literal["sum", "mean"] = "sum",
    ) -> None:
        super().__init__()
        if aggregate not in ("sum", "mean"):
            raise ValueError(f"P2CARB aggregate must be 'sum' or 'mean', got {aggregate!r}")
        self.aggregate = aggregate
        self.out_dim = feat_dims[-1]
        self.features = mlp([in_dim, *feat_dims])
        # W = ELU(MLP([F, C])): three layers, ELU on the last too (as PointGrow); last width matches F for F * W.
        self.attention = mlp([2 * self.out_dim, att_width, att_width, self.out_dim])

    def forward(self, x: Tensor) -> Tensor:
        """(B, N, in_dim) -> (B, N, out_dim); output k = sum (or mean) of F_j * W_j over j <= k."""
        f = self.features(x)
        context = cumulative_mean(f)  # C_k = mean(F_1..F_k)
        g = f * self.attention(torch.cat([f, context], -1))
        return g.cumsum(1) if self.aggregate == "sum" else cumulative_mean(g)

    def step(self, x: Tensor, memory: tuple[int, Tensor, Tensor] | None) -> tuple[Tensor, tuple[int, Tensor, Tensor]]:
        """One more probe, (B, in_dim) -> (B, out_dim): row k of forward() from the running sums of F and
        F * W over probes 1..k - 1, so a rollout encodes each probe once instead of its whole history."""
        f = self.features(x)
        count, f_sum, g_sum = memory if memory is not None else (0, torch.zeros_like(f), torch.zeros_like(f))
        count, f_sum = count + 1, f_sum + f
        g_sum = g_sum + f * self.attention(torch.cat([f, f_sum / count], -1))
        return (g_sum if self.aggregate == "sum" else g_sum / count), (count, f_sum, g_sum)
