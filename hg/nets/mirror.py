"""Mirror images of episodes across the probe line's vertical plane (X = line_x).

hg4's shapes are mirror-symmetric, so an object lying off the line to -x and its mirror image to +x are the same
object: a network that reads the prefixes whose touches lie to -x mirrored sees both sides as one, and the held-out
position cells to -x as the training cells that hold them mirrored (docs/findings.md). Chiral objects are not.
"""

import torch
from torch import Tensor


def left_of_line(points: Tensor, line_x: float) -> Tensor:
    """points (B, N, 4) (X, Y, Z, T) -> (B, N) bool: whether the touches of probes 1..k+1 have their mean X below
    line_x, the prefixes read mirrored. False while nothing is touched: misses alone say no side."""
    touched = (points[..., 3] > 0.5).to(points.dtype)
    count = touched.cumsum(1)
    return (count > 0) & ((touched * points[..., 0]).cumsum(1) < line_x * count)


def reflect(values: Tensor, component: int, about: float = 0.0, where: Tensor | None = None) -> Tensor:
    """values (..., C) with `component` reflected about `about` (v -> 2 about - v), in the rows where `where` (...)
    is True (all rows without it): X about line_x for points, Ux about 0 for probe requests."""
    v = values[..., component]
    mirrored = 2 * about - v
    out = values.clone()
    out[..., component] = mirrored if where is None else torch.where(where, mirrored, v)
    return out
