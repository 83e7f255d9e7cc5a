"""Probing B episodes N times with a policy: where the simulator is called, once per probe (and by a warm-up that
probes other candidates on the same episodes, ImitateBestProbe, through probe_points)."""
from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor, nn

from hg.policies import Observation, Policy
from hg.sim import ProbeResult, ProbeSimulator
from hg.sim.robot import achieved


@dataclass
class Rollout:
    """N probes of B episodes: what the policy asked for and what the sensor returned."""

    actions: Tensor  # (B, N, 4) raw requests (a Gaussian's log-probability is taken of these)
    requests: Tensor  # (B, N, 4) the requests executed: actions clamped to [-1, 1]
    points: Tensor  # (B, N, 4) X, Y, Z scaled by point_scale, and T
    reached: Tensor  # (B, N) bool: the arm achieved the request within 5 mm and 3 degrees


@torch.no_grad()
def rollout(sim: ProbeSimulator, policy: Policy, labels: Tensor, poses: Tensor, seed: int, n_probes: int,
            point_scale: float, encoder: nn.Module | None = None, deterministic: bool = False,
            requests: Tensor | None = None, faults: Tensor | None = None) -> Rollout:
    """Probe the episodes (labels (B,), poses (B, 6)) with `policy`, or with the given requests (B, N, 4) (a
    teacher's). The seed drives the policy's sampling and the sensor's faults, or the faults are the given (B, N, 2)
    uniforms (a teacher's, ProbeSimulator.probe). deterministic: the mean action. A learned policy reads the
    `encoder`'s representations of the probes so far, encoded one probe at a time (encoder.step)."""
    batch = len(labels)
    sim.reset(labels.cpu().numpy(), poses.cpu().numpy(), seed=seed)
    generator = torch.Generator().manual_seed(seed)
    actions, points = torch.zeros(batch, n_probes, 4), torch.zeros(batch, n_probes, 4)
    reached = torch.ones(batch, n_probes, dtype=torch.bool)
    device = next(encoder.parameters()).device if encoder is not None else torch.device("cpu")
    reads_encoder = requests is None and policy.learned
    memory = rep_sum = None  # the encoder's memory of the probes so far, and the sum of its outputs
    for k in range(n_probes):
        if requests is not None:
            action = requests[:, k].cpu()
        else:
            obs = Observation(k, actions.to(device), points.to(device), rep_sum)
            action = policy.act(obs, deterministic, generator).cpu()
        if not torch.isfinite(action).all():
            raise FloatingPointError(f"non-finite probe request from {type(policy).__name__} at probe {k + 1}")
        actions[:, k] = action
        points[:, k], result = probe_points(sim, action, point_scale, None if faults is None else faults[:, k])
        if sim.arm is not None:
            reached[:, k] = torch.from_numpy(achieved(result.pose_error))
        if reads_encoder and k + 1 < n_probes:  # the last representation is never read by the policy
            rep, memory = encoder.step(action.clamp(-1, 1).to(device), points[:, k].to(device), memory)
            rep_sum = rep if rep_sum is None else rep_sum + rep
    return Rollout(actions.to(device), actions.clamp(-1, 1).to(device), points.to(device), reached.to(device))


def probe_points(sim: ProbeSimulator, requests: Tensor, point_scale: float, faults: Tensor | None = None
                 ) -> tuple[Tensor, ProbeResult]:
    """Probe each episode of the simulator's last reset once with raw requests (B, 4), clamped to [-1, 1]: the points
    (B, 4) as the policy and the heads read them (X, Y, Z times point_scale, T), and the simulator's result."""
    result = sim.probe(requests.cpu().clamp(-1, 1).double().numpy(), None if faults is None else faults.cpu().numpy())
    points = torch.from_numpy(result.points).float()
    points[:, :3] *= point_scale  # the policy must see what the heads will see
    return points, result
