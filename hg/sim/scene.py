"""The probing scene: ground, probe line, probe length, tilt limit and the object pose ranges.

All lengths in metres, all angles in degrees. One dataclass so that every command reads the same numbers.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, fields

import numpy as np

from hg.sim.kernels import request_frames

Range = tuple[float, float]


@dataclass(frozen=True)
class Scene:
    """Geometry of the task (paper section 2.1): objects lie below Z=0, probes enter on the probe line."""

    probe_x: float = 0.0
    probe_y: Range = (-0.40, 0.40)
    probe_length: float = 0.60  # U_len
    max_tilt_deg: float = 45.0  # largest angle between the probe direction u and straight down
    object_x: Range = (-0.15, 0.15)
    object_y: Range = (-0.15, 0.15)
    object_z: Range = (-0.35, -0.20)
    rot_x_deg: Range = (-10.0, 10.0)
    rot_y_deg: Range = (-10.0, 10.0)
    rot_z_deg: Range = (-180.0, 180.0)

    def __post_init__(self) -> None:
        for f in fields(self):
            value = getattr(self, f.name)
            values = tuple(value) if isinstance(value, (tuple, list)) else (value,)
            if not all(isinstance(v, (int, float)) and math.isfinite(v) for v in values):
                raise ValueError(f"scene.{f.name}={value!r}: every value must be a finite number")
            if isinstance(value, (tuple, list)):
                if len(values) != 2 or values[0] > values[1]:
                    raise ValueError(f"scene.{f.name}={value!r}: expected a (low, high) pair with low <= high")
                object.__setattr__(self, f.name, (float(values[0]), float(values[1])))
        if self.probe_length <= 0:
            raise ValueError(f"scene.probe_length={self.probe_length}: U_len must be > 0")
        if not 0.0 <= self.max_tilt_deg < 90.0:
            raise ValueError(f"scene.max_tilt_deg={self.max_tilt_deg}: must be in [0, 90) so that u_z < 0")
        if self.object_z[1] >= 0:
            raise ValueError(f"scene.object_z={self.object_z}: object centres must lie below the ground Z=0")

    @property
    def pose_low(self) -> np.ndarray:
        """Lower corner of the pose space (X, Y, Z, Rx, Ry, Rz)."""
        return np.array([r[0] for r in self._pose_ranges()])

    @property
    def pose_high(self) -> np.ndarray:
        return np.array([r[1] for r in self._pose_ranges()])

    def _pose_ranges(self) -> tuple[Range, ...]:
        return (self.object_x, self.object_y, self.object_z, self.rot_x_deg, self.rot_y_deg, self.rot_z_deg)

    def line_request(self, y):
        """The py request whose entry point lies at y on the probe line (numbers, arrays or tensors): the inverse
        of request_to_probe's mapping, for policies that aim at a place they touched."""
        lo, hi = self.probe_y
        return (y - lo) / (0.5 * (hi - lo)) - 1

    def request_to_probe(self, requests: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Map requests (py, ux, uy, uz) in [-1, 1] to entry points P (B, 3) and unit directions u (B, 3).

        py moves P along the probe line; (ux, uy) is the lean (its direction and size, the unit disk) and uz how
        much of it is used: tan(tilt) = tan(max_tilt) |(ux, uy)| (1 - uz) / 2, so uz = 1 is straight down and
        u_z < 0 always. Uniform requests give every tilt inside the limit. Values outside [-1, 1] are clipped.
        """
        requests = np.asarray(requests, dtype=np.float64)
        if requests.ndim != 2 or requests.shape[1] != 4:
            raise ValueError(f"requests: expected shape (B, 4), got {requests.shape}")
        if not np.isfinite(requests.sum()):
            bad = np.argwhere(~np.isfinite(requests))[0]
            raise ValueError(f"requests: non-finite value {requests[tuple(bad)]} at episode {bad[0]}, component {bad[1]}")
        lo, hi = self.probe_y
        return request_frames(np.ascontiguousarray(requests), self.probe_x, lo, hi,
                              math.tan(math.radians(self.max_tilt_deg)))


def candidate_requests(places: int, span: float, leans: list[float] | tuple[float, ...],
                       along_leans: list[float] | tuple[float, ...] = ()) -> np.ndarray:
    """(C, 4) requests a discrete chooser picks from (the greedy planner, or a location network choosing among
    candidates): every place of a scan (evenly over the middle `span` of the line, in request units) with every
    direction, straight down first, then to +x and -x by each lean (ux = +-1, uz = 1 - lean, as hg.policies.SidePickingScan's lean),
    then along the line to +y and -y by each of `along_leans` (uy = +-1). The set is its own mirror image across the
    line (ux -> -ux), as the mirrored views need."""
    if places < 1 or not 0 < span <= 1 or any(not 0 < lean <= 2 for lean in (*leans, *along_leans)):
        raise ValueError(f"candidate_requests: places={places} must be >= 1, span={span} in (0, 1], leans={list(leans)} "
                         f"and along_leans={list(along_leans)} each in (0, 2] (uz = 1 - lean stays in [-1, 1])")
    directions = ([(0.0, 0.0, 1.0)] + [(side, 0.0, 1.0 - lean) for lean in leans for side in (1.0, -1.0)]
                  + [(0.0, side, 1.0 - lean) for lean in along_leans for side in (1.0, -1.0)])
    return np.array([(py, *d) for py in np.linspace(-span, span, places) for d in directions])


def mirrored_directions(directions: int, along: int = 0) -> list[int]:
    """candidate_requests' directions at one place, mirrored across the line: direction j of the mirror image
    is direction [j] of the original (straight down stays; +x and -x of each lean trade places; the last
    2 * `along`, leaning along the line, stay)."""
    across = directions - 2 * along
    if across % 2 != 1 or along < 0:
        raise ValueError(f"{directions} directions are not straight down, pairs of leans to +x and -x and {along} "
                         "pairs along the line (candidate_requests)")
    return [0] + [i + (1 if i % 2 else -1) for i in range(1, across)] + list(range(across, directions))
