"""Building blocks shared by every network: pointwise ("shared") MLPs and the causal mean over probes."""

from collections.abc import Sequence

import torch
from torch import Tensor, nn


def mlp(dims: Sequence[int], act: type[nn.Module] = nn.ELU, last_act: bool = True,
        layer_norm: bool = False) -> nn.Sequential:
    """Linear layers dims[0] -> ... -> dims[-1] acting on the last dim, so one set of weights is shared by
    every probe of a (B, N, C) sequence (the paper's "shared MLPs"). layer_norm puts a LayerNorm before each
    activation: it steadies wide layers and, unlike BatchNorm, never mixes episodes or probes."""
    layers: list[nn.Module] = []
    for i, (d_in, d_out) in enumerate(zip(dims[:-1], dims[1:])):
        layers.append(nn.Linear(d_in, d_out))
        if last_act or i < len(dims) - 2:
            layers += [nn.LayerNorm(d_out), act()] if layer_norm else [act()]
    return nn.Sequential(*layers)


def cumulative_mean(x: Tensor) -> Tensor:
    """Mean of x[..., :k+1, :] at every probe k of (..., N, D): a mean pool that never sees later probes."""
    counts = torch.arange(1, x.shape[-2] + 1, device=x.device, dtype=x.dtype)
    return x.cumsum(-2) / counts.unsqueeze(-1)
