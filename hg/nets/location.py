"""The location network (paper sec. 2.2 (b)): an autoregressive Gaussian policy over the next probe request; beyond
the paper, a categorical choice among fixed candidate requests."""

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from hg.nets.mlp import cumulative_mean, mlp


class MaskedLinear(nn.Linear):
    """Linear layer whose weight is multiplied by a fixed 0/1 mask (MADE, Germain et al. 2015)."""

    def __init__(self, in_degrees: Tensor, out_degrees: Tensor, strict: bool) -> None:
        super().__init__(len(in_degrees), len(out_degrees))
        # Unit o may read unit i if deg(i) <= deg(o) (hidden layers) or deg(i) < deg(o) (output layer).
        allowed = in_degrees[None, :] < out_degrees[:, None] if strict else in_degrees[None, :] <= out_degrees[:, None]
        self.register_buffer("mask", allowed.float())

    def forward(self, x: Tensor) -> Tensor:
        return F.linear(x, self.weight * self.mask, self.bias)


class PolicyState(nn.Module):
    """What a location network reads before probe k + 1: the mean of PCRN's first k representations (eq. (1)'s
    s_k), or a learned start before the first probe. Shared by every location network."""

    def __init__(self, in_dim: int) -> None:
        super().__init__()
        self.start = nn.Parameter(torch.zeros(in_dim))  # state before the first probe (empty history)
        # multiplies every std (the Gaussian's) or the temperature (the candidates'); a training schedule may shrink
        # it (beyond the paper). A buffer, so that a checkpoint is tested with the one it was trained with
        self.register_buffer("std_scale", torch.ones(()))

    def state(self, rep_sum: Tensor | None, k: int, batch_size: int | None = None,
              extra: Tensor | None = None) -> Tensor:
        """s_k from which request k + 1 is drawn: the mean of the first k representations, given as their sum
        rep_sum (B, D) (a rollout keeps it running), or the learned start for k = 0. With rep_sum None (k = 0
        only) batch_size must be given, so the start is never silently 1 row. extra (B, E): features of the first
        k probes read beside the mean (in_dim = D + E; beyond the paper)."""
        if k == 0:
            if rep_sum is None and batch_size is None:
                raise ValueError("LocationNetwork.state(None, 0) needs batch_size")
            return self.start.expand(rep_sum.shape[0] if rep_sum is not None else batch_size, -1)
        if rep_sum is None:
            raise ValueError(f"LocationNetwork.state: k={k} needs the sum of the first k representations")
        return rep_sum / k if extra is None else torch.cat([rep_sum / k, extra], -1)

    def states(self, rep: Tensor, extra: Tensor | None = None) -> Tensor:
        """All s_i of a rollout at once, (B, N, D) and extra (B, N, E) or None -> (B, N, D + E): row i is
        state(rep, i, extra=extra[:, i - 1])."""
        start = self.start.expand(rep.shape[0], 1, -1)
        summary = cumulative_mean(rep) if extra is None else torch.cat([cumulative_mean(rep), extra], -1)
        return torch.cat([start, summary[:, :-1]], 1)


class LocationNetwork(PolicyState):
    """pi(a_k | s_k) over a_k = (Py, Ux, Uy, Uz), factorised as in eq. (1): component j conditions on the
    state and on components < j. One MADE network gives all components at once (teacher forcing), so the
    log-probabilities of a whole rollout cost one pass; sampling takes one pass per component.

    Degrees: state inputs 0, action component j has j + 1; hidden units cycle through 0..action_dim - 1;
    mu_j and sigma_j have degree j + 1 and read only hidden units of lower degree.
    """

    def __init__(
        self, in_dim: int, action_dim: int = 4, hidden: int = 128, std_floor: float = 0.05, std_max: float = 1.0,
        zero_mean: bool = False, truncated: bool = False,
    ) -> None:
        """truncated: each component is drawn from the Gaussian truncated to [-1, 1] (samples outside re-drawn, as
        Fleer et al. do) and its log-probability is the truncated density's, instead of clamping the executed
        request while the log-probability is of the unclamped sample."""
        super().__init__(in_dim)
        self.truncated = truncated
        if not 0 < std_floor < std_max:
            raise ValueError(f"LocationNetwork needs 0 < std_floor < std_max, got {std_floor=}, {std_max=}")
        self.action_dim, self.std_floor, self.std_max = action_dim, std_floor, std_max
        d_in = torch.cat([torch.zeros(in_dim, dtype=torch.long), torch.arange(1, action_dim + 1)])
        d_hidden = torch.arange(hidden) % action_dim
        d_out = torch.arange(1, action_dim + 1).repeat(2)  # (mu_1..mu_A, sigma_1..sigma_A)
        self.net = nn.Sequential(
            MaskedLinear(d_in, d_hidden, strict=False),
            nn.ELU(),
            MaskedLinear(d_hidden, d_hidden, strict=False),
            nn.ELU(),
            MaskedLinear(d_hidden, d_out, strict=True),
        )
        if zero_mean:  # beyond the paper: mu starts at tanh(offset), so a policy starts exactly at its prior
            with torch.no_grad():
                self.net[-1].weight[:action_dim].zero_()
                self.net[-1].bias[:action_dim].zero_()

    def masked_layers(self) -> tuple[tuple[Tensor, Tensor], ...]:
        """(weight * mask, bias) of the three MADE layers: sampling computes them once for its A passes."""
        return tuple((layer.weight * layer.mask, layer.bias) for layer in self.net[::2])

    @staticmethod
    def state_input(state: Tensor, layers: tuple) -> Tensor:
        """The first layer's pre-activation from the state alone, bias included (`masked_layers()` as layers)."""
        weight, bias = layers[0]
        return F.linear(state, weight[:, :state.shape[-1]], bias)

    def distribution(self, state: Tensor, action: Tensor, offset: Tensor | None = None,
                     state_input: Tensor | None = None, layers: tuple | None = None) -> tuple[Tensor, Tensor]:
        """(mu, sigma) of every component, (..., D), (..., A) -> (..., A) twice; masking lets mu_j, sigma_j
        see only action[..., :j]. mu = tanh(.), sigma = (std_floor + (std_max - std_floor) * sigmoid(.)) * std_scale.
        Sampling passes what is the same for its A passes: `masked_layers()`, and `state_input`, the first layer's
        pre-activation from the state alone (bias included), so the state's columns, most of the first layer, are
        multiplied once per probe, not once per component."""
        layers = self.masked_layers() if layers is None else layers
        (w1, _), (w2, b2), (w3, b3) = layers
        if state_input is None:
            state_input = self.state_input(state, layers)
        hidden = F.elu(state_input + F.linear(action, w1[:, state.shape[-1]:]))  # self.net's layers, written out
        mu, pre_sigma = F.linear(F.elu(F.linear(hidden, w2, b2)), w3, b3).chunk(2, -1)
        if offset is not None:  # a prior request schedule, added before the tanh (beyond the paper)
            mu = mu + offset
        sigma = self.std_floor + (self.std_max - self.std_floor) * torch.sigmoid(pre_sigma)
        return torch.tanh(mu), sigma * self.std_scale

    def sample(
        self, state: Tensor, deterministic: bool | Tensor = False, generator: torch.Generator | None = None,
        offset: Tensor | None = None,
    ) -> tuple[Tensor, Tensor, Tensor]:
        """Draw a_k component by component as in eq. (1); returns the raw (unsquashed, detached) action and
        its (mu, sigma). deterministic=True gives the mean-action policy; a bool tensor of the state's batch shape
        gives it in its True rows only (the others draw the same numbers as without it)."""
        shape = (*state.shape[:-1], self.action_dim)
        if isinstance(deterministic, Tensor) or not deterministic:
            eps = torch.randn(shape, generator=generator, device=state.device, dtype=state.dtype)
            if isinstance(deterministic, Tensor):
                eps = eps.masked_fill(deterministic[..., None].to(state.device), 0.0)
        else:
            eps = torch.zeros(shape, device=state.device, dtype=state.dtype)
        action = torch.zeros_like(eps)
        layers = self.masked_layers()
        state_input = self.state_input(state, layers)
        for j in range(self.action_dim):
            mu, sigma = self.distribution(state, action, offset, state_input, layers)
            value = mu[..., j] + sigma[..., j] * eps[..., j]
            for _ in range(100 if self.truncated else 0):  # re-draw what fell outside [-1, 1]
                outside = value.abs() > 1
                if not outside.any():
                    break
                redraw = torch.randn(value.shape, generator=generator, device=state.device, dtype=state.dtype)
                value = torch.where(outside, mu[..., j] + sigma[..., j] * redraw, value)
            action[..., j] = value.clamp(-1, 1).detach() if self.truncated else value.detach()
        # The last pass already saw every component a mu_j / sigma_j may read, so (mu, sigma) belong to action.
        return action, mu, sigma

    def log_prob_and_moments(self, state: Tensor, action: Tensor, offset: Tensor | None = None
                             ) -> tuple[Tensor, Tensor, Tensor]:
        """log pi(a_k | s_k) summed over components, (..., D), (..., A) -> (...), with the (mu, sigma) it was taken
        under. The action is detached: the gradient flows only through mu and sigma, which gives eq. (4)/(5) and,
        weighted, eq. (3)."""
        action = action.detach()
        mu, sigma = self.distribution(state, action, offset)
        normal = torch.distributions.Normal(mu, sigma)
        log_p = normal.log_prob(action)
        if self.truncated:  # the density of the Gaussian truncated to [-1, 1]
            log_p = log_p - torch.log((normal.cdf(torch.ones_like(mu)) - normal.cdf(-torch.ones_like(mu))).clamp_min(1e-12))
        return log_p.sum(-1), mu, sigma

    def imitation_loss(self, log_pi: Tensor, mu: Tensor, action: Tensor, valid: Tensor | None = None) -> Tensor:
        """How far the policy is from a teacher's requests: the mean's squared distance from them, whose gradient
        stays on the cross-entropy's scale, where their log-likelihood under a narrow std would crowd the classifier
        out of the clipped gradient."""
        return valid_mean((mu - action.clamp(-1, 1)).pow(2).sum(-1), valid)


def valid_mean(values: Tensor, valid: Tensor | None) -> Tensor:
    """The mean of `values` over the True entries of `valid` (all when None): a teacher's request the policy may not
    make (a candidate probed already, log pi = -inf) is left out of the imitation, not averaged in."""
    return values.mean() if valid is None else values[valid].mean()


def candidate_index(action: Tensor, candidates: Tensor) -> Tensor:
    """(..., 4) requests -> (...,) the index of each among the candidates (C, 4); refuses one that is none of them."""
    distance = (action.detach()[..., None, :] - candidates).abs().amax(-1)
    nearest, index = distance.min(-1)
    if (nearest > 1e-4).any():
        bad = action[nearest > 1e-4][0].tolist()
        raise ValueError(f"request {[round(v, 4) for v in bad]} is not one of the {len(candidates)} candidates")
    return index


class CandidateLocationNetwork(PolicyState):
    """Beyond the paper: pi(a_k | s_k) a categorical choice among fixed candidate requests (C, 4), e.g. the greedy
    planner's (hg.sim.candidate_requests). A Gaussian copying a teacher that leans to either side ends up between
    them (docs/findings.md); a choice cannot average two sides. Its temperature is std_scale, so a std schedule
    sharpens it as it would narrow a Gaussian. The returned moments (the request's mean and std per component under
    the choice) are what the training loop logs for a Gaussian."""

    def __init__(self, in_dim: int, candidates: Tensor, hidden: int = 128, reads_from: int = 0) -> None:
        """reads_from: the choice reads the state's features from this one on (the baseline reads them all): with
        the readings last, a choice that does not read PCRN's state, which holds where the training objects lay."""
        super().__init__(in_dim)
        if candidates.ndim != 2 or candidates.shape[1] != 4 or len(candidates) < 2:
            raise ValueError(f"CandidateLocationNetwork: candidates of shape {tuple(candidates.shape)}, expected (C, 4) "
                             "with C >= 2")
        self.register_buffer("candidates", candidates.float())
        if not 0 <= reads_from < in_dim:
            raise ValueError(f"CandidateLocationNetwork: reads_from={reads_from} must lie in [0, {in_dim})")
        self.reads_from = reads_from
        self.net = mlp([in_dim - reads_from, hidden, hidden, len(candidates)], last_act=False)

    def log_probs(self, state: Tensor, exclude: Tensor | None = None) -> Tensor:
        """(..., D) -> (..., C) log-probabilities of the candidates; exclude (..., C) bool: candidates never chosen
        (those probed already, whose reading would repeat)."""
        logits = self.net(state[..., self.reads_from:]) / self.std_scale
        return torch.log_softmax(logits if exclude is None else logits.masked_fill(exclude, -torch.inf), -1)

    def readings(self, actions: Tensor, points: Tensor, n_probes: int) -> tuple[Tensor, Tensor]:
        """What the probes so far read, by candidate (beyond the paper: what the greedy planner weighs its candidates
        by, with the touch's depth in place of its distance along the ray). actions
        (B, K, 4) candidates and the points (B, K, 4) they returned (X, Y, Z, T) -> row j, after probes 1..j + 1:
        features (B, K, 3C + n_probes), for every candidate whether it was probed, whether it touched and how
        deep (-Z), then the next probe's index one-hot; and the probed candidates (B, K, C) bool."""
        chosen = F.one_hot(self.index_of(actions), len(self.candidates)).float()  # (B, K, C)
        touched = chosen * (points[..., 3:] > 0.5).float()
        probes, touches = chosen.cumsum(1), touched.cumsum(1)
        depth = (touched * -points[..., 2:3]).cumsum(1) / touches.clamp(min=1)
        step = F.one_hot(torch.arange(1, actions.shape[1] + 1).clamp(max=n_probes - 1), n_probes).float()
        features = torch.cat([probes, touches, depth, step.to(actions.device).expand(len(actions), -1, -1)], -1)
        return features, probes > 0

    def moments(self, log_probs: Tensor) -> tuple[Tensor, Tensor]:
        """The request's mean and std per component under the choice, (..., 4) each."""
        p = log_probs.exp()
        mu = p @ self.candidates
        return mu, (p @ self.candidates.pow(2) - mu.pow(2)).clamp(min=0).sqrt()

    def index_of(self, action: Tensor) -> Tensor:
        """(..., 4) requests -> (...,) the index of each among the candidates (candidate_index)."""
        return candidate_index(action, self.candidates)

    def sample(self, state: Tensor, deterministic: bool | Tensor = False, generator: torch.Generator | None = None,
               exclude: Tensor | None = None) -> tuple[Tensor, Tensor, Tensor]:
        """A candidate per row, drawn (or the most likely: deterministic, everywhere or in its True rows; the
        others draw the same numbers as without it), with the moments of the choice; never an excluded one."""
        log_probs = self.log_probs(state, exclude).detach()
        index = log_probs.argmax(-1)
        if isinstance(deterministic, Tensor) or not deterministic:
            u = torch.rand(state.shape[:-1], generator=generator, device=state.device, dtype=state.dtype)
            drawn = (log_probs.exp().cumsum(-1) < u[..., None]).sum(-1).clamp(max=len(self.candidates) - 1)
            index = drawn if not isinstance(deterministic, Tensor) else torch.where(deterministic, index, drawn)
        return (self.candidates[index], *self.moments(log_probs))

    def log_prob_and_moments(self, state: Tensor, action: Tensor, exclude: Tensor | None = None
                             ) -> tuple[Tensor, Tensor, Tensor]:
        """log pi(a_k | s_k) of candidate requests, (..., D), (..., 4) -> (...), with the moments of the choice it
        was taken under."""
        log_probs = self.log_probs(state, exclude)
        log_pi = log_probs.gather(-1, self.index_of(action)[..., None])[..., 0]
        return (log_pi, *self.moments(log_probs))

    def imitation_loss(self, log_pi: Tensor, mu: Tensor, action: Tensor, valid: Tensor | None = None) -> Tensor:
        """How far the policy is from a teacher's choices: their cross-entropy."""
        return -valid_mean(log_pi, valid)
