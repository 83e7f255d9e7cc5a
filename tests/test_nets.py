"""Properties the training loop relies on: causality over probes, the eq. (1) masking, the policy's
log-probability and sampling, and the point cloud baselines' shapes."""

import pytest
import torch

from hg.nets import (
    CentredPCRN,
    DGCNN,
    PCRN,
    P2CARB,
    CandidateLocationNetwork,
    Dims,
    FCClassifier,
    LinearClassifier,
    LocationNetwork,
    LSTMEncoder,
    NClassClassifier,
    PointNet,
    TouchSetClassifier,
)

B, N, K = 3, 6, 2  # batch, probes, the probe after which we perturb
DIMS = Dims(rep=8, n_probes=N, n_classes=4)


@pytest.fixture(autouse=True)
def _seed() -> None:
    torch.manual_seed(0)


def perturbed_after(x: torch.Tensor, k: int) -> torch.Tensor:
    y = x.clone()
    y[:, k + 1 :] += torch.randn_like(y[:, k + 1 :])
    return y


def assert_causal(f, *inputs: torch.Tensor) -> None:
    """Changing probes > K leaves outputs <= K untouched and changes outputs > K."""
    out = f(*inputs)
    out2 = f(*(perturbed_after(x, K) for x in inputs))
    assert torch.allclose(out[:, : K + 1], out2[:, : K + 1], atol=1e-6)
    for k in range(K + 1, N):
        assert not torch.allclose(out[:, k], out2[:, k], atol=1e-4)


@pytest.mark.parametrize("aggregate", ["sum", "mean"])
def test_p2carb_causal(aggregate: str) -> None:
    net = P2CARB(4, feat_dims=(8, 8, 16), att_width=16, aggregate=aggregate)
    assert net(torch.randn(B, N, 4)).shape == (B, N, net.out_dim)
    assert_causal(net, torch.randn(B, N, 4))


@pytest.mark.parametrize("aggregate", ["sum", "mean"])
def test_p2carb_step_by_step_equals_forward(aggregate: str) -> None:
    net = P2CARB(4, feat_dims=(8, 8, 16), att_width=16, aggregate=aggregate)
    x, memory = torch.randn(B, N, 4), None
    full = net(x)
    for k in range(N):
        out, memory = net.step(x[:, k], memory)
        assert torch.allclose(out, full[:, k], atol=1e-5)


def test_p2carb_rejects_unknown_aggregate() -> None:
    with pytest.raises(ValueError, match="aggregate"):
        P2CARB(4, aggregate="max")


@pytest.mark.parametrize(
    "make", [lambda: PCRN(width=16, out_dim=32), lambda: CentredPCRN(width=16, out_dim=32),
             lambda: LSTMEncoder(hidden=32)], ids=["PCRN", "CentredPCRN", "LSTM"]
)
def test_encoders_causal(make) -> None:
    encoder = make()
    requests, points = torch.randn(B, N, 4), torch.randn(B, N, 4)
    assert encoder(requests, points).shape == (B, N, encoder.out_dim) == (B, N, 32)
    assert_causal(encoder, requests, points)
    assert_causal(lambda r: encoder(r, points), requests)  # each sequence alone is causal too
    assert_causal(lambda p: encoder(requests, p), points)


def test_location_masking_follows_eq1() -> None:
    net = LocationNetwork(8, hidden=32)
    state, action = torch.randn(B, 8), torch.randn(B, 4)
    mu, sigma = net.distribution(state, action)
    for j in range(4):
        later = action.clone()
        later[:, j:] += 1.0
        mu2, sigma2 = net.distribution(state, later)
        assert torch.allclose(mu[:, j], mu2[:, j]) and torch.allclose(sigma[:, j], sigma2[:, j])
        if j >= 1:
            earlier = action.clone()
            earlier[:, :j] += 1.0
            mu3, sigma3 = net.distribution(state, earlier)
            assert not torch.allclose(mu[:, j], mu3[:, j]) and not torch.allclose(sigma[:, j], sigma3[:, j])
    mu4, _ = net.distribution(state + 1.0, action)
    assert not torch.allclose(mu[:, 0], mu4[:, 0])  # component 0 still reads the state


def test_location_log_prob_and_bounds() -> None:
    net = LocationNetwork(8, hidden=32, std_floor=0.1, std_max=0.5)
    state = torch.randn(B, N, 8) * 5  # extra leading dim, large inputs to push the squashing
    action = torch.randn(B, N, 4, requires_grad=True)
    mu, sigma = net.distribution(state, action)
    assert ((sigma >= 0.1) & (sigma <= 0.5)).all() and ((mu > -1) & (mu < 1)).all()
    log_prob, mu2, sigma2 = net.log_prob_and_moments(state, action)
    expected = torch.distributions.Normal(mu, sigma).log_prob(action).sum(-1)
    assert log_prob.shape == (B, N) and torch.allclose(log_prob, expected)
    assert torch.equal(mu2, mu) and torch.equal(sigma2, sigma)
    log_prob.sum().backward()
    assert action.grad is None or not action.grad.any()
    assert net.net[0].weight.grad.abs().sum() > 0


def test_location_sample() -> None:
    net = LocationNetwork(8, hidden=32)
    state = torch.randn(B, 8)
    draws = [net.sample(state, generator=torch.Generator().manual_seed(7))[0] for _ in range(2)]
    assert torch.equal(draws[0], draws[1])
    assert not torch.equal(draws[0], net.sample(state, generator=torch.Generator().manual_seed(8))[0])
    action, mu, sigma = net.sample(state, deterministic=True)
    assert torch.allclose(action, mu) and not action.requires_grad
    # The returned (mu, sigma) are those of the returned action under teacher forcing.
    action, mu, sigma = net.sample(state, generator=torch.Generator().manual_seed(7))
    mu2, sigma2 = net.distribution(state, action)
    assert torch.allclose(mu, mu2) and torch.allclose(sigma, sigma2)


def test_location_offset_moves_the_mean_before_the_tanh() -> None:
    """A prior scan's request, given as an offset, is where a zero-mean network's mean starts, exactly."""
    net = LocationNetwork(8, hidden=32, zero_mean=True)
    state, offset = torch.randn(B, 8), torch.atanh(torch.rand(B, 4) * 1.8 - 0.9)
    action, mu, _ = net.sample(state, deterministic=True, offset=offset)
    torch.testing.assert_close(action, torch.tanh(offset))
    log_pi, mu2, _ = net.log_prob_and_moments(state, action, offset)
    torch.testing.assert_close(mu2, mu)


def test_truncated_location_draws_inside_the_line_with_the_truncated_density() -> None:
    """truncated: samples outside [-1, 1] are re-drawn, and log pi is the density of the Gaussian truncated there."""
    net = LocationNetwork(8, hidden=32, truncated=True)
    with torch.no_grad():
        net.net[-1].bias[:4] += 3.0  # means near the edge (tanh(3) = 0.995): half the plain draws would fall outside
    state = torch.randn(512, 8)
    action, mu, sigma = net.sample(state, generator=torch.Generator().manual_seed(0))
    assert action.abs().max() <= 1 and (mu > 0.9).float().mean() > 0.5
    log_pi, mu, sigma = net.log_prob_and_moments(state, action)
    normal = torch.distributions.Normal(mu, sigma)
    inside = normal.cdf(torch.ones_like(mu)) - normal.cdf(-torch.ones_like(mu))
    torch.testing.assert_close(log_pi, (normal.log_prob(action) - inside.log()).sum(-1))
    plain = LocationNetwork(8, hidden=32)
    plain.load_state_dict(net.state_dict())
    assert plain.sample(state, generator=torch.Generator().manual_seed(0))[0].abs().max() > 1


def test_candidate_location_chooses_among_its_candidates() -> None:
    from hg.sim import candidate_requests

    candidates = torch.from_numpy(candidate_requests(3, 0.5, [1.0])).float()  # 3 places x (straight, +x, -x)
    assert torch.equal(candidates[:, 0], torch.tensor([-0.5] * 3 + [0.0] * 3 + [0.5] * 3))
    mirrored = candidates * torch.tensor([1.0, -1.0, 1.0, 1.0])  # the set is its own mirror image across the line
    assert ((mirrored[:, None] - candidates).abs().amax(-1).min(-1).values == 0).all()
    net = CandidateLocationNetwork(8, candidates, hidden=32)
    state = torch.randn(B, N, 8)
    draws = [net.sample(state, generator=torch.Generator().manual_seed(7))[0] for _ in range(2)]
    assert torch.equal(draws[0], draws[1]) and draws[0].shape == (B, N, 4)
    log_probs = net.log_probs(state)
    best, mu, sigma = net.sample(state, deterministic=True)
    assert torch.equal(best, candidates[log_probs.argmax(-1)])
    torch.testing.assert_close(mu, log_probs.exp() @ candidates)
    assert (sigma >= 0).all() and sigma[..., 2].abs().max() < 1e-3  # no candidate leans along the line
    some = torch.zeros(B, N, dtype=torch.bool)
    some[0] = True  # the mean action in these rows only; the others draw what they drew without it
    mixed = net.sample(state, deterministic=some, generator=torch.Generator().manual_seed(7))[0]
    assert torch.equal(mixed[0], best[0]) and torch.equal(mixed[1:], draws[0][1:])
    log_pi, mu2, _ = net.log_prob_and_moments(state, draws[0])
    torch.testing.assert_close(log_pi, log_probs.gather(-1, net.index_of(draws[0])[..., None])[..., 0])
    torch.testing.assert_close(mu2, mu)
    log_pi.sum().backward()
    assert net.net[0].weight.grad.abs().sum() > 0
    with pytest.raises(ValueError, match=r"request \[0.1, 0.0, 0.0, 1.0\] is not one of the 9 candidates"):
        net.log_prob_and_moments(state[:, 0], torch.tensor([0.1, 0.0, 0.0, 1.0]).expand(B, 4))
    net.std_scale.fill_(1e-5)  # a cold choice: its draws are its most likely candidate
    assert torch.equal(net.sample(state, generator=torch.Generator().manual_seed(3))[0],
                       net.sample(state, deterministic=True)[0])


def test_candidate_location_never_chooses_an_excluded_candidate() -> None:
    from hg.sim import candidate_requests

    net = CandidateLocationNetwork(8, torch.from_numpy(candidate_requests(3, 0.5, [1.0])).float(), hidden=32)
    state = torch.randn(64, 8)
    exclude = torch.rand(64, 9, generator=torch.Generator().manual_seed(0)) < 0.7
    exclude[:, 4] = False  # at least one left
    for seed in range(5):
        action = net.sample(state, generator=torch.Generator().manual_seed(seed), exclude=exclude)[0]
        assert not exclude.gather(1, net.index_of(action)[:, None]).any()
    best = net.sample(state, deterministic=True, exclude=exclude)[0]
    assert not exclude.gather(1, net.index_of(best)[:, None]).any()
    log_pi, _, _ = net.log_prob_and_moments(state, best, exclude)
    torch.testing.assert_close(log_pi, net.log_probs(state, exclude).max(-1).values)
    assert (net.log_probs(state, exclude)[exclude] == -torch.inf).all()


def test_choice_reading_from_a_feature_on_ignores_those_before_it() -> None:
    """CandidateChoice(reads_encoder=False): the choice reads the readings only, so PCRN's state (the features
    before reads_from) changes nothing; the whole-state choice does change."""
    candidates = torch.eye(4)[[0, 1, 2]]
    torch.manual_seed(0)
    state = torch.randn(2, 9)
    other = torch.cat([torch.randn(2, 5), state[:, 5:]], -1)  # PCRN's part changed, the readings kept
    for reads_from, changes in ((5, False), (0, True)):
        net = CandidateLocationNetwork(9, candidates, hidden=16, reads_from=reads_from)
        assert (not torch.allclose(net.log_probs(state), net.log_probs(other))) == changes
    with pytest.raises(ValueError, match="reads_from=9 must lie in"):
        CandidateLocationNetwork(9, candidates, reads_from=9)


@pytest.mark.parametrize("extra_dim", [0, 3], ids=["summary only", "with extra features"])
def test_location_states_match_state(extra_dim) -> None:
    net = LocationNetwork(8 + extra_dim, hidden=32)
    with torch.no_grad():
        net.start.normal_()
    rep = torch.randn(B, N, 8)
    extra = torch.randn(B, N, extra_dim) if extra_dim else None
    states = net.states(rep, extra)
    assert states.shape == (B, N, 8 + extra_dim)
    for i in range(N):
        step_extra = extra[:, i - 1] if extra_dim and i else None  # s_i reads the features of probes 1..i
        assert torch.allclose(states[:, i], net.state(rep[:, :i].sum(1), i, extra=step_extra), atol=1e-6)
    assert torch.equal(net.state(None, 0, batch_size=B), net.start.expand(B, -1))
    with pytest.raises(ValueError, match="batch_size"):
        net.state(None, 0)


def touched_points(touched: list[bool]) -> torch.Tensor:
    """(B, len(touched), 4) random X, Y, Z with the contact flag T set where `touched`."""
    points = torch.randn(B, len(touched), 4)
    points[..., 3] = torch.tensor(touched, dtype=torch.float32)
    return points


def test_fc_and_linear_classifiers_causal() -> None:
    points = touched_points([True] * N)
    for clf in (FCClassifier(DIMS, hidden=16), LinearClassifier(DIMS)):
        assert clf(torch.randn(B, N, 8), points).shape == (B, N, 4)
        assert_causal(lambda rep: clf(rep, points), torch.randn(B, N, 8))


def test_nclass_classifier_reads_only_its_probe() -> None:
    clf = NClassClassifier(DIMS, hidden=16)
    rep, points = torch.randn(B, N, 8), touched_points([True] * N)
    logits = clf(rep, points)
    assert logits.shape == (B, N, 4)
    for k in range(N):
        changed = rep.clone()
        changed[:, k] += 1.0
        differs = (clf(changed, points) - logits).abs().amax(dim=(0, 2)) > 1e-6
        assert differs.tolist() == [i == k for i in range(N)]
    assert torch.allclose(clf(rep[:, :3], points[:, :3]), logits[:, :3])  # short rollouts use the first classifiers
    with pytest.raises(ValueError, match="n_probes"):
        clf(torch.randn(B, N + 1, 8), touched_points([True] * (N + 1)))


def touch_set(**kwargs) -> TouchSetClassifier:
    return TouchSetClassifier(DIMS, shared=(8, 16, 32), hidden=16, **kwargs)


def test_touch_set_causal_and_blind_to_where_the_object_lies() -> None:
    clf = touch_set()
    points = touched_points([True, False, True, True, False, True])
    logits = clf(None, points)
    assert logits.shape == (B, N, 4)
    later = points.clone()
    later[:, K + 1:, :3] += 1.0
    differs = (clf(None, later) - logits).abs().amax(dim=(0, 2)) > 1e-5
    assert differs.tolist() == [k > K for k in range(N)]  # causal, and every later prefix reads its new probe
    moved = points.clone()
    moved[..., :3] += torch.tensor([0.3, -0.2, 0.1])  # the same touches and misses, the object elsewhere
    assert torch.allclose(clf(None, moved), logits, atol=1e-5)
    assert torch.equal(clf(torch.randn(B, N, 8), points), logits)  # it reads the points alone


def test_centred_pcrn_reads_its_points_wherever_the_object_lies_once_touched() -> None:
    encoder = CentredPCRN(width=16, out_dim=32)
    requests, points = torch.randn(B, N, 4), touched_points([False, True, False, True, True, False])
    moved = points.clone()
    moved[..., :3] += torch.tensor([0.3, -0.2, 0.1])
    differs = (encoder(requests, moved) - encoder(requests, points)).abs().amax(dim=(0, 2)) > 1e-5
    assert differs.tolist() == [True] + [False] * (N - 1)  # the first probe missed: nothing to read it around yet


def test_touch_set_reads_where_probes_missed_from_their_probe_on() -> None:
    """A miss reports where its ray ended, which says where the object is not."""
    clf = touch_set()
    points = touched_points([True, True, False, True, False, True])
    changed = points.clone()
    changed[:, 2, :3] += 0.5
    differs = (clf(None, changed) - clf(None, points)).abs().amax(dim=(0, 2)) > 1e-5
    assert differs.tolist() == [k >= 2 for k in range(6)]


def test_touch_set_before_any_touch_is_finite() -> None:
    clf = touch_set()
    points = touched_points([False, False, True, True, False, True])
    logits = clf(None, points)
    assert torch.isfinite(logits).all()
    logits.square().sum().backward()  # the untouched first prefixes must not poison the gradient either
    assert all(torch.isfinite(p.grad).all() for p in clf.parameters())
    assert not torch.allclose(logits[:, 1], logits[:, 2])  # the first touch changes the prediction


def test_mirrored_touch_set_reads_an_episode_and_its_mirror_image_alike() -> None:
    """Mirrored across the line (X -> 2 line_x - X), touches and misses alike: the same answer with `mirror`, and
    another without it."""
    points = touched_points([True, False, True, True, False, True])
    points[..., 0] = points[..., 0].abs() + 0.1  # every touch on the +x side of a line at X = 0.05
    image = points.clone()
    image[..., 0] = 0.1 - points[..., 0]
    for mirror in (True, False):
        torch.manual_seed(0)
        clf = touch_set(mirror=mirror)
        clf.line_x = 0.05
        assert torch.allclose(clf(None, image), clf(None, points), atol=1e-5) == mirror


def test_last_only_touch_set_scores_the_whole_episode_once() -> None:
    every, last = touch_set(), touch_set(last_only=True)
    last.load_state_dict(every.state_dict())
    points = touched_points([True, False, True, True, False, True])
    torch.testing.assert_close(last(None, points), every(None, points)[:, -1:])
    assert last.last_only and not every.last_only


@pytest.mark.parametrize("make", [lambda: PointNet(4), lambda: DGCNN(4, k=9)], ids=["PointNet", "DGCNN"])
def test_pointcloud_shapes(make) -> None:
    net = make()
    assert net(torch.randn(2, 10, 3)).shape == (2, 4)
    net.eval()
    assert net(torch.randn(1, 10, 3)).shape == (1, 4)


def test_dgcnn_reads_a_cloud_of_no_more_than_k_points_as_one_neighbourhood() -> None:
    """Fewer points than neighbours (Table 1's DGCNN row reads the first k of its 10): every point is each one's
    neighbour, so the output is the same whatever the neighbour count beyond the cloud's size."""
    torch.manual_seed(0)
    net, cloud = DGCNN(4, k=9).eval(), torch.randn(2, 5, 3)
    wider = DGCNN(4, k=12).eval()
    wider.load_state_dict(net.state_dict())
    torch.testing.assert_close(net(cloud), wider(cloud))
    assert net(cloud[:, :1]).shape == (2, 4) and torch.isfinite(net(cloud[:, :1])).all()


@pytest.mark.parametrize(
    "make", [lambda: PCRN(width=16, out_dim=32), lambda: CentredPCRN(width=16, out_dim=32),
             lambda: LSTMEncoder(hidden=32)], ids=["PCRN", "CentredPCRN", "LSTM"]
)
def test_encoders_step_by_step_equal_forward(make) -> None:
    """The rollout encodes one probe at a time; evaluate() encodes whole sequences: they must agree."""
    encoder = make()
    requests, points, memory = torch.randn(B, N, 4), torch.randn(B, N, 4), None
    full = encoder(requests, points)
    for k in range(N):
        out, memory = encoder.step(requests[:, k], points[:, k], memory)
        assert torch.allclose(out, full[:, k], atol=1e-5), k
