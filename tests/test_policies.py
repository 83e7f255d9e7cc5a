"""hg.policies: every policy behind the one protocol, the fixed scans' requests, the learned policies' reading of a
rollout (the log-probability is taken under the policy that acted) and their copying of a teacher, on real ray
casts (ideal mode) and tiny nets."""
from pathlib import Path

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from hg.lightning.data import ProbeDataModule
from hg.nets import PCRN, Dims, LSTMEncoder, candidate_index
from hg.policies import (CandidateChoice, Detours, GaussianPolicy, Imitation, LineScan, Observation, Policy,
                         RandomProbes, SidePickingScan)
from hg.rl import rollout

ROOT = Path(__file__).resolve().parents[1]
TEACHER = ROOT / "data" / "planner" / "train65k_s10.npz"  # the planner copy's teacher: 10 probes, 77 candidates
B, N = 8, 4
DIMS = Dims(rep=32, n_probes=N, n_classes=4)
CHOICE = dict(places=3, span=0.5, leans=(1.0,), hidden=32)  # 9 candidates for 4 probes


def side_scan(dims: Dims) -> SidePickingScan:
    return SidePickingScan(dims, span=0.5, order="centre_out", lean=0.6, first_lean=1.0)


POLICIES = {
    "random": lambda: RandomProbes(DIMS),
    "line_scan": lambda: LineScan(DIMS),
    "side_scan": lambda: side_scan(DIMS),
    "gaussian": lambda: GaussianPolicy(DIMS, hidden=32),
    "gaussian_on_side_scan": lambda: GaussianPolicy(DIMS, hidden=32, prior=side_scan, anchor=1.0),
    "candidate_choice": lambda: CandidateChoice(DIMS, **CHOICE),
}


def make(name: str):
    torch.manual_seed(0)
    return POLICIES[name]()


def observation(policy, k: int) -> Observation:
    """What the policy reads before probe k + 1: k earlier probes (touches and misses), zeros after them."""
    generator = torch.Generator().manual_seed(k)
    actions, points = torch.zeros(B, N, 4), torch.zeros(B, N, 4)
    if isinstance(policy, CandidateChoice):
        actions[:, :k] = policy.candidates[torch.arange(k)]  # distinct candidates
    else:
        actions[:, :k] = torch.rand(B, k, 4, generator=generator) * 2 - 1
    points[:, :k, :3] = torch.randn(B, k, 3, generator=generator)
    points[:, :k, 3] = (torch.rand(B, k, generator=generator) < 0.5).float()
    rep_sum = torch.randn(B, DIMS.rep, generator=generator) if policy.learned and k else None
    return Observation(k, actions, points, rep_sum)


@pytest.mark.parametrize("name", list(POLICIES))
def test_every_policy_acts_by_the_protocol_and_is_a_function_of_its_generator(name):
    policy = make(name)
    stochastic = name in ("random", "gaussian", "gaussian_on_side_scan", "candidate_choice")
    assert policy.learned == name.startswith(("gaussian", "candidate"))
    for k in (0, 2):
        obs = observation(policy, k)

        def act(seed, deterministic=False):
            return policy.act(obs, deterministic, torch.Generator().manual_seed(seed))

        action = act(1)
        assert action.shape == (B, 4) and torch.isfinite(action).all()
        torch.testing.assert_close(act(1), action)  # the same draws from the same seed
        assert torch.equal(act(2), action) != stochastic  # other draws from another, none for a fixed scan
        if policy.learned:  # the mean action draws nothing (a fixed policy has no mean action to score)
            torch.testing.assert_close(act(1, True), act(2, True))
    if name == "random":
        drawn = torch.stack([act(seed) for seed in range(32)])
        assert drawn.min() >= -1 and drawn.max() <= 1 and drawn.std() > 0.5  # uniform in [-1, 1]^4


def test_line_scan_sweeps_or_goes_centre_out_straight_down():
    points = torch.randn(3, N, 4)  # a line scan reads nothing of what it touched
    sweep = LineScan(DIMS).requests(points)
    assert sweep.shape == (3, N, 4)
    torch.testing.assert_close(sweep[..., 0], torch.linspace(-1, 1, N).expand(3, -1))
    assert (sweep[..., 1:3] == 0).all() and (sweep[..., 3] == 1).all()
    centre = LineScan(DIMS, span=0.5, order="centre_out").requests(points)
    torch.testing.assert_close(centre[0, :, 0], torch.tensor([-1 / 6, 1 / 6, -0.5, 0.5]))
    assert torch.equal(LineScan(DIMS).requests(torch.zeros(3, N, 4)), sweep)
    with pytest.raises(ValueError, match="span=0"):
        LineScan(DIMS, span=0.0)
    with pytest.raises(ValueError, match="order='middle'"):
        LineScan(DIMS, order="middle")


def test_side_picking_scan_leans_both_ways_first_then_to_the_side_its_touches_show():
    dims = Dims(32, 6, 4)
    scan = side_scan(dims)
    # 0: both first probes touch, -x higher; 1: only -x touches; 2: nothing; 3: first touch at probe 4 (too late)
    points = torch.zeros(4, 6, 4)
    points[0, 0, 3] = points[0, 1, 3] = points[1, 1, 3] = points[3, 3, 3] = 1.0
    points[0, 0, 2], points[0, 1, 2] = -0.5, -0.4
    requests = scan.requests(points)
    places = LineScan(dims, span=0.5, order="centre_out").requests(points)[0, :, 0]
    torch.testing.assert_close(requests[..., 0], places[[0, 0, 1, 2, 3, 4]].expand(4, -1))  # first place twice
    torch.testing.assert_close(requests[..., 1], torch.tensor([[1.0, -1, -1, -1, -1, -1], [1, -1, -1, -1, -1, -1],
                                                              [1, -1, 0, 0, 0, 0], [1, -1, 0, 0, 0, 0]]))
    assert (requests[..., 2] == 0).all()
    # the steep first pair (uz = 1 - first_lean), then the lean (uz = 1 - lean), or straight down without a touch
    torch.testing.assert_close(requests[..., 3], torch.tensor([[0.0, 0, 0.4, 0.4, 0.4, 0.4]] * 2
                                                              + [[0.0, 0, 1, 1, 1, 1]] * 2))
    higher = points.clone()
    higher[0, 0, 2] = -0.3  # now the +x probe touched higher: the object lies to +x
    assert scan.requests(higher)[0, 2:, 1].tolist() == [1.0] * 4
    for k in range(6):  # request k reads probes 1..k only
        later = points.clone()
        later[:, k:] = torch.rand(4, 6 - k, 4)
        torch.testing.assert_close(scan.requests(later)[:, :k + 1], requests[:, :k + 1])
    with pytest.raises(ValueError, match="n_probes >= 2"):
        side_scan(Dims(32, 1, 4))
    with pytest.raises(ValueError, match="lean=3"):
        SidePickingScan(dims, lean=3.0)


@pytest.mark.parametrize("scan", [LineScan(DIMS, span=0.5, order="centre_out"), side_scan(Dims(32, 6, 4))])
def test_a_scan_lists_every_request_it_can_make(scan):
    """What a choice copying the scan is checked against: whatever the probes return (touches anywhere, at any
    heights), each request is one the scan lists, and each it lists is made in some episode."""
    n = len(scan.places)
    torch.manual_seed(0)
    points = torch.rand(512, n, 4)
    points[..., 3] = (torch.rand(512, n) < 0.3).float()
    made = scan.requests(points).reshape(-1, 4)
    listed = scan.possible_requests()
    found = (made[:, None] - listed).abs().amax(-1) < 1e-6
    assert found.any(1).all() and found.any(0).all()
    assert len(listed.unique(dim=0)) == len(listed)


def test_side_picking_scan_on_real_ray_casts(sim, batch):
    scan = side_scan(DIMS)
    out = rollout(sim, scan, batch["labels"], batch["poses"], 0, N, 2.0)
    touched = out.points[..., 3] > 0.5
    assert (out.requests[:, :2, 1] == torch.tensor([1.0, -1.0])).all()
    pair = touched[:, :2].any(1)
    assert pair.any()
    assert (out.requests[pair, 2:, 1].abs() == 1).all() and (out.requests[pair, 2:, 3] == 0.4).all()
    for i in pair.nonzero()[:, 0]:  # one side, the one the first touches showed
        assert len(set(out.requests[i, 2:, 1].tolist())) == 1
    assert (out.requests[~pair, 2:, 1] == 0).all()
    torch.testing.assert_close(out.requests, scan.requests(out.points))


@pytest.mark.parametrize("make_encoder, prior, reads_count", [(lambda: PCRN(width=16, out_dim=32), None, False),
                                                              (lambda: PCRN(width=16, out_dim=32), side_scan, False),
                                                              (lambda: PCRN(width=16, out_dim=32), None, True),
                                                              (lambda: LSTMEncoder(hidden=32), None, False),
                                                              (lambda: LSTMEncoder(hidden=32), side_scan, False)],
                         ids=["pcrn", "pcrn on side scan", "pcrn reading the count", "lstm", "lstm on side scan"])
def test_gaussian_log_prob_is_taken_under_the_policy_that_acted(sim, batch, make_encoder, prior, reads_count):
    """The loss reads whole sequences (teacher forcing), the rollout one probe at a time: the mean-action rollout's
    requests must be exactly the means the loss pass computes, and the stochastic rollout's log-probability that
    of the Gaussian it was drawn from (also when the policy reads the probe count)."""
    torch.manual_seed(0)
    encoder, policy = make_encoder(), GaussianPolicy(DIMS, hidden=32, prior=prior, reads_count=reads_count)
    mean = rollout(sim, policy, batch["labels"], batch["poses"], 1, N, 2.0, encoder, deterministic=True)
    evaluated = policy.evaluate(encoder(mean.requests, mean.points), mean.actions, mean.points)
    torch.testing.assert_close(evaluated.mu, mean.actions)
    assert evaluated.log_pi.shape == evaluated.baseline.shape == (B, N) and evaluated.sigma.shape == (B, N, 4)
    drawn = rollout(sim, policy, batch["labels"], batch["poses"], 1, N, 2.0, encoder)
    evaluated = policy.evaluate(encoder(drawn.requests, drawn.points), drawn.actions, drawn.points)
    expected = torch.distributions.Normal(evaluated.mu, evaluated.sigma).log_prob(drawn.actions).sum(-1)
    torch.testing.assert_close(evaluated.log_pi, expected)
    assert set(evaluated.stats) >= {"std_py", "std_ux", "std_uy", "std_uz"}
    if reads_count:  # the count reaches the requests: with the encoder's states held alike, every probe differs
        assert policy.location.start.shape == (32 + N,)
        states = policy.location.states(torch.zeros(1, N, 32), policy.counts(1, N, torch.device("cpu")))
        mu = policy.location.distribution(states, torch.zeros(1, N, 4))[0][0]
        assert torch.cdist(mu, mu).add(torch.eye(N)).min() > 0


def test_gaussian_on_a_scan_starts_on_the_scans_requests(sim, batch):
    """With a prior the untrained mean policy probes where its scan would, on the same touches (requests beyond
    +-0.9 are pulled inside tanh's range: GaussianPolicy.offsets)."""
    torch.manual_seed(0)
    encoder, policy = PCRN(width=16, out_dim=32), GaussianPolicy(DIMS, hidden=32, prior=side_scan)
    mean = rollout(sim, policy, batch["labels"], batch["poses"], 0, N, 2.0, encoder, deterministic=True)
    scan = policy.prior.requests(mean.points)
    torch.testing.assert_close(mean.requests, scan.clamp(-0.9, 0.9))
    assert mean.points[..., 3].any()
    assert policy.evaluate(encoder(mean.requests, mean.points), mean.actions, mean.points).stats["prior_shift"] == 0


def test_anchor_charges_the_mean_policy_for_leaving_its_prior(sim, batch):
    torch.manual_seed(0)
    encoder = PCRN(width=16, out_dim=32)
    policy = GaussianPolicy(DIMS, hidden=32, prior=side_scan, anchor=2.0)
    out = rollout(sim, policy, batch["labels"], batch["poses"], 0, N, 2.0, encoder)
    rep = encoder(out.requests, out.points).detach()
    on_prior = policy.evaluate(rep, out.actions, out.points)
    assert on_prior.stats["prior_shift"] == 0 and on_prior.losses["loss_anchor"] == 0
    with torch.no_grad():
        policy.location.net[-1].bias[0] += 0.3  # the mean moves Py off the scan
    moved = policy.evaluate(rep, out.actions, out.points)
    assert moved.stats["prior_shift"] > 0.01
    torch.testing.assert_close(moved.losses["loss_anchor"], 2.0 * moved.stats["prior_shift"])
    moved.losses["loss_anchor"].backward()
    assert policy.location.net[-1].bias.grad[0] > 0  # a gradient step pulls the mean back towards the scan
    free = GaussianPolicy(DIMS, hidden=32, prior=side_scan)  # no anchor: the shift is reported, not charged
    assert "loss_anchor" not in free.evaluate(rep, out.actions, out.points).losses
    with pytest.raises(ValueError, match="anchor=1.0: .*needs a prior scan"):
        GaussianPolicy(DIMS, anchor=1.0)
    with pytest.raises(ValueError, match="anchor=-1.0: must be >= 0"):
        GaussianPolicy(DIMS, prior=side_scan, anchor=-1.0)


@pytest.mark.parametrize("name", ["gaussian", "candidate_choice"])
@pytest.mark.parametrize("reads_detached", [False, True])
def test_what_the_policy_terms_reach_of_the_encoder(sim, batch, name, reads_detached):
    """log pi reaches the encoder's representation unless the policy reads it detached; b_k never does."""
    torch.manual_seed(0)
    policy = (GaussianPolicy(DIMS, hidden=32, reads_detached=reads_detached) if name == "gaussian"
              else CandidateChoice(DIMS, **CHOICE, reads_encoder=True, reads_detached=reads_detached))
    encoder = PCRN(width=16, out_dim=32)
    out = rollout(sim, policy, batch["labels"], batch["poses"], 0, N, 2.0, encoder)
    rep = encoder(out.requests, out.points)
    evaluated = policy.evaluate(rep, out.actions, out.points)
    grads = torch.autograd.grad(evaluated.baseline.sum(), rep, retain_graph=True, allow_unused=True)
    assert grads == (None,)
    (grad,) = torch.autograd.grad(evaluated.log_pi.sum(), rep, allow_unused=True)
    assert (grad is None) == reads_detached
    assert reads_detached or grad.abs().sum() > 0


def test_std_scale_narrows_the_gaussian_and_cools_the_choice():
    torch.manual_seed(0)
    gaussian, choice = GaussianPolicy(DIMS, hidden=32, std_max=0.5), CandidateChoice(DIMS, **CHOICE)
    state = torch.randn(16, DIMS.rep)
    _, _, sigma = gaussian.location.sample(state, deterministic=True)
    gaussian.std_scale.fill_(0.1)
    _, _, narrow = gaussian.location.sample(state, deterministic=True)
    torch.testing.assert_close(narrow, 0.1 * sigma)
    assert narrow.max() <= 0.05 + 1e-6
    obs = observation(choice, 0)
    choice.std_scale.fill_(1e-5)  # a cold choice: its draws are its most likely candidate
    torch.testing.assert_close(choice.act(obs, False, torch.Generator().manual_seed(3)), choice.act(obs, True, None))


def test_candidate_choice_never_repeats_a_candidate_and_the_loss_reads_what_the_rollout_read(sim, batch):
    """Every request is a candidate, none twice; the loss pass rebuilds the states the rollout chose from, so the
    mean-action rollout's requests are the candidates it finds most likely (the probed ones excluded)."""
    torch.manual_seed(0)
    policy, encoder = CandidateChoice(DIMS, **CHOICE), PCRN(width=16, out_dim=32)
    candidates = policy.candidates
    assert candidates.shape == (9, 4)
    location = policy.location
    for seed in range(3):
        for deterministic in (False, True):
            out = rollout(sim, policy, batch["labels"], batch["poses"], seed, N, 2.0, encoder, deterministic)
            index = location.index_of(out.actions)  # refuses a request that is no candidate
            assert all(len(set(row.tolist())) == N for row in index)
    readings, probed = location.readings(out.actions, out.points, N)
    assert probed[:, -1].sum(-1).eq(N).all()
    touched = out.points[..., 3] > 0.5
    assert touched.any()
    b, k = touched.nonzero()[0].tolist()  # a touch is read at its candidate from that probe on
    column = len(candidates) + index[b, k]
    assert readings[b, k:, column].eq(1).all() and readings[b, :k, column].eq(0).all()
    states = location.states(encoder(out.requests, out.points), readings)
    exclude = F.pad(probed[:, :-1], (0, 0, 1, 0), value=False)
    log_probs = location.log_probs(states, exclude)
    torch.testing.assert_close(candidates[log_probs.argmax(-1)], out.actions)
    evaluated = policy.evaluate(encoder(out.requests, out.points), out.actions, out.points)
    torch.testing.assert_close(evaluated.log_pi, log_probs.max(-1).values)
    assert 0 < evaluated.stats["std_py"] < 1  # the request's spread under the choice, logged as a Gaussian's std
    with pytest.raises(ValueError, match="CandidateChoice: places / span / leans: .*span=1.5"):
        CandidateChoice(DIMS, span=1.5)


def test_candidate_choice_without_the_encoder_reads_the_readings_only(sim, batch):
    torch.manual_seed(0)
    policy, encoder = CandidateChoice(DIMS, **CHOICE), PCRN(width=16, out_dim=32)
    out = rollout(sim, policy, batch["labels"], batch["poses"], 0, N, 2.0, encoder)
    rep = encoder(out.requests, out.points)
    evaluated = policy.evaluate(rep, out.actions, out.points)
    other = policy.evaluate(torch.randn_like(rep), out.actions, out.points)
    torch.testing.assert_close(other.log_pi, evaluated.log_pi)  # PCRN's state changes nothing of the choice
    assert not torch.allclose(other.baseline, evaluated.baseline)  # the baseline reads it
    reading = CandidateChoice(DIMS, **CHOICE, reads_encoder=True)
    assert not torch.allclose(reading.evaluate(rep, out.actions, out.points).log_pi,
                              reading.evaluate(torch.randn_like(rep), out.actions, out.points).log_pi)


@pytest.fixture(scope="module")
def teacher(sim):
    """16 of the planner's episodes (10 probes each) and what its requests read, in ideal mode."""
    data = ProbeDataModule(mode="ideal", n_probes=10, regions="cells")  # where the archived teacher was planned
    episodes = data.load_teacher([str(TEACHER)])
    labels, poses, requests = (episodes[k][:16] for k in ("labels", "poses", "requests"))
    out = rollout(sim, LineScan(Dims(32, 10, 4)), labels, poses, 0, 10, 2.0, requests=requests)
    torch.testing.assert_close(out.requests, requests.clamp(-1, 1))
    return out


def fit_copy(policy, encoder, out, parameters, steps: int, lr: float) -> list[float]:
    """The warm-up's imitation term alone, minimised on a fixed rollout by Adam over `parameters`; its losses."""
    optimizer = torch.optim.Adam(parameters, lr=lr)
    losses = []
    for _ in range(steps):
        evaluated = policy.evaluate(encoder(out.requests, out.points), out.actions, out.points)
        loss = policy.imitation_loss(evaluated, Imitation(out.actions))
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
        losses.append(loss.item())
    return losses


@pytest.mark.parametrize("name", ["gaussian", "candidate_choice"])
def test_imitation_loss_falls_when_fitting_a_teacher(teacher, name):
    """The warm-up's copy of the planner: the policy (and the encoder it reads) fitted to the teacher's requests."""
    torch.manual_seed(0)
    dims = Dims(32, 10, 4)
    policy = (GaussianPolicy(dims, hidden=32) if name == "gaussian"
              else CandidateChoice(dims, places=11, span=0.5, leans=(0.6, 1.0, 2.0), hidden=32))
    encoder = PCRN(width=16, out_dim=32)
    losses = fit_copy(policy, encoder, teacher, [*policy.parameters(), *encoder.parameters()], steps=40, lr=3e-3)
    assert np.mean(losses[-5:]) < 0.8 * np.mean(losses[:5]), losses


def test_a_choice_with_a_prior_scan_learns_to_copy_it_and_refuses_a_scan_it_cannot(sim, batch):
    """FollowPrior(imitate=true)'s copy: fitted to the side-picking scan's own rollouts, the choice's most likely
    requests are the scan's, probe for probe, on the same episodes; a scan off the choice's grid is refused when
    built, naming the grid."""
    torch.manual_seed(0)
    choice = CandidateChoice(DIMS, places=N, span=0.5, leans=(0.6, 1.0), hidden=32, prior=side_scan)
    encoder = PCRN(width=16, out_dim=32)
    scanned = rollout(sim, choice.prior, batch["labels"], batch["poses"], 0, N, 2.0, encoder)
    assert (scanned.requests[..., 1] != 0).any()  # it leans: not a line scan
    fit_copy(choice, encoder, scanned, choice.parameters(), steps=150, lr=1e-2)  # the encoder stays as it is
    copied = rollout(sim, choice, batch["labels"], batch["poses"], 0, N, 2.0, encoder, deterministic=True)
    torch.testing.assert_close(copied.requests, scanned.requests)
    with pytest.raises(ValueError, match=r"model.policy.init_args.prior: SidePickingScan: request .* is not one of "
                                         r"the 25 candidates of CandidateChoice\(places=5, span=0.5.* needs places=4"):
        CandidateChoice(DIMS, places=N + 1, span=0.5, leans=(0.6, 1.0), prior=side_scan)


def test_detours_never_send_a_place_twice_even_where_the_scan_asks_for_it_again():
    """hg.policies.Detours: a detour may take the place the scan asks for later; the scan's request is then replaced
    by another detour, so that the exploring copy never probes a place twice (its choice cannot)."""
    class Again(Policy):  # a scan that asks for the first candidate at every probe
        def act(self, obs, deterministic, generator):
            return candidates[:1].expand(len(obs.actions), 4)

    candidates = torch.rand(6, 4, generator=torch.Generator().manual_seed(0)) * 2 - 1
    detours = Detours(Again(), candidates, explore=0.01)
    actions, generator = torch.zeros(B, 6, 4), torch.Generator().manual_seed(1)
    for k in range(6):
        actions[:, k] = detours.act(Observation(k, actions, torch.zeros(B, 6, 4)), False, generator)
    assert torch.equal(actions[:, 0], candidates[0].expand(B, 4))  # the scan's, where not taken yet (explore 0.01)
    sent = candidate_index(actions, candidates)
    assert (sent.sort(1).values == torch.arange(6)).all()  # every candidate once: no place twice
