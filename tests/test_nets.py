"""Properties the training loop relies on: causality over probes, the eq. (1) masking, the policy's
log-probability and sampling, and the point cloud baselines' shapes."""

import math

import pytest
import torch

from hg.nets import (
    DGCNN,
    AlongLineClassifier,
    PCRN,
    P2CARB,
    FCClassifier,
    CandidateLocationNetwork,
    LocationNetwork,
    LibraryNamer,
    LSTMEncoder,
    NClassClassifier,
    PointNet,
    TouchSetClassifier,
)
from hg.nets.library import log_likelihood
from hg.sim import SensorNoise
from hg.sim.library import MISS

B, N, K = 3, 6, 2  # batch, probes, the probe after which we perturb


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
    "make", [lambda: PCRN(width=16, out_dim=32), lambda: LSTMEncoder(hidden=32)], ids=["PCRN", "LSTM"]
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
    log_prob = net.log_prob(state, action)
    expected = torch.distributions.Normal(mu, sigma).log_prob(action).sum(-1)
    assert log_prob.shape == (B, N) and torch.allclose(log_prob, expected)
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
    log_pi = net.log_prob(state, draws[0])
    torch.testing.assert_close(log_pi, log_probs.gather(-1, net.index_of(draws[0])[..., None])[..., 0])
    log_pi.sum().backward()
    assert net.net[0].weight.grad.abs().sum() > 0
    with pytest.raises(ValueError, match=r"request \[0.1, 0.0, 0.0, 1.0\] is not one of the 9 candidates"):
        net.log_prob(state[:, 0], torch.tensor([0.1, 0.0, 0.0, 1.0]).expand(B, 4))
    net.std_scale.fill_(1e-5)  # a cold choice: its draws are its most likely candidate
    assert torch.equal(net.sample(state, generator=torch.Generator().manual_seed(3))[0],
                       net.sample(state, deterministic=True)[0])


def test_along_line_choice_moves_with_the_readings_along_the_line() -> None:
    """choice_along_line: readings moved one place along the line (away from its ends) move the logits one place,
    whatever PCRN's state; an MLP over the same state does not."""
    from hg.sim import candidate_requests

    places, directions, probes, dim = 11, 3, 4, 5
    candidates = torch.from_numpy(candidate_requests(places, 0.5, [1.0])).float()
    readings = 3 * len(candidates) + probes
    torch.manual_seed(0)
    net = CandidateLocationNetwork(dim + readings, candidates, hidden=32, along_line=(readings, places))
    mlp_net = CandidateLocationNetwork(dim + readings, candidates, hidden=32)
    local = torch.zeros(2, 3, places, directions)
    local[:, :, 4:7] = torch.rand(2, 3, 3, directions)  # readings at places 4..6
    moved = torch.roll(local, 1, dims=2)  # at places 5..7
    rest = torch.randn(2, dim), torch.eye(probes)[[1, 2]]

    def state(local):
        return torch.cat([rest[0], local.reshape(2, -1), rest[1]], -1)

    for choice, moves in ((net, True), (mlp_net, False)):
        logits = choice.log_probs(state(local)).reshape(2, places, directions)
        logits_moved = choice.log_probs(state(moved)).reshape(2, places, directions)
        # log-probabilities differ by the normaliser only; places 4..5 see no end of the line (reach 4) either way
        shift = logits_moved[:, 5:7] - logits[:, 4:6]
        assert torch.allclose(shift, shift[:, :1, :1].expand_as(shift), atol=1e-5) == moves
    with pytest.raises(ValueError, match="AlongLineChoice: 10 readings in a state of 15 cannot hold 3 x 11"):
        CandidateLocationNetwork(15, candidates, along_line=(10, places))


def test_along_line_classifier_reads_probes_moved_along_the_line_or_mirrored_alike() -> None:
    """model.along_line_classifier: the same readings by candidate moved any number of places along the line (up to
    its ends) give the same logits, mirrored too (+x and -x leans swapped); other readings give others, and a
    prediction reads only the probes so far."""
    from hg.sim import candidate_requests

    places, leans = 11, [0.6, 1.0]
    candidates = torch.from_numpy(candidate_requests(places, 0.5, leans)).float()
    directions = 1 + 2 * len(leans)
    choice = CandidateLocationNetwork(8, candidates)
    net = AlongLineClassifier(4, places, directions, hidden=16, mirror=True)
    place, direction = torch.tensor([[0, 2, 1, 3] * 2]), torch.tensor([[0, 3, 1, 4, 2, 0, 4, 3]])  # 8 probes
    points = torch.rand(1, 8, 4) * torch.tensor([1.0, 1.0, -1.0, 1.0])
    points[..., 3] = torch.tensor([1.0, 0, 1, 1, 0, 1, 1, 0])

    def logits(place, direction, points=points):
        return net(choice.readings(candidates[place * directions + direction], points, 8)[0])

    first = logits(place, direction)
    for moved in range(1, places - 3):  # the probes span places 0..3
        torch.testing.assert_close(logits(place + moved, direction), first)
    mirrored = direction + torch.where(direction % 2 == 1, 1, -1) * (direction > 0)  # +x <-> -x of each lean
    torch.testing.assert_close(logits(place, mirrored), first)
    unmirrored = AlongLineClassifier(4, places, directions, hidden=16)
    unmirrored.load_state_dict(net.state_dict())
    assert not torch.allclose(unmirrored(choice.readings(candidates[place * directions + mirrored], points, 8)[0]),
                              unmirrored(choice.readings(candidates[place * directions + direction], points, 8)[0]))
    deeper = points.clone()
    deeper[:, 5, 2] -= 0.5  # probe 6 touched deeper: predictions 6.. change, those before do not
    other = logits(place, direction, deeper)
    torch.testing.assert_close(other[:, :5], first[:, :5])
    assert not torch.allclose(other[:, 5:], first[:, 5:])
    with pytest.raises(ValueError, match="AlongLineClassifier: 4 directions"):
        AlongLineClassifier(4, places, 4)


def test_choice_reading_from_a_feature_on_ignores_those_before_it() -> None:
    """model.choice_reads_state=false: the choice reads the readings only, so PCRN's state (the features before
    reads_from) changes nothing; the whole-state choice does change."""
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


def test_fc_classifier_causal() -> None:
    assert_causal(FCClassifier(8, 4, hidden=16), torch.randn(B, N, 8))


def test_nclass_classifier_reads_only_its_probe() -> None:
    clf = NClassClassifier(8, 4, n_probes=N, hidden=16)
    rep = torch.randn(B, N, 8)
    logits = clf(rep)
    assert logits.shape == (B, N, 4)
    for k in range(N):
        changed = rep.clone()
        changed[:, k] += 1.0
        differs = (clf(changed) - logits).abs().amax(dim=(0, 2)) > 1e-6
        assert differs.tolist() == [i == k for i in range(N)]
    assert torch.allclose(clf(rep[:, :3]), logits[:, :3])  # short rollouts use the first classifiers
    with pytest.raises(ValueError, match="n_probes"):
        clf(torch.randn(B, N + 1, 8))


def touched_points(touched: list[bool]) -> torch.Tensor:
    """(B, len(touched), 4) random X, Y, Z with the contact flag T set where `touched`."""
    points = torch.randn(B, len(touched), 4)
    points[..., 3] = torch.tensor(touched, dtype=torch.float32)
    return points


@pytest.mark.parametrize("misses", [False, True], ids=["small", "with misses"])
def test_touch_set_causal_and_blind_to_where_the_object_lies(misses) -> None:
    clf = TouchSetClassifier(4, shared=(8, 16, 32), hidden=16, misses=misses, layer_norm=misses)
    points = touched_points([True] * N)
    logits = clf(points)
    assert logits.shape == (B, N, 4)
    later = points.clone()
    later[:, K + 1:, :3] += 1.0
    differs = (clf(later) - logits).abs().amax(dim=(0, 2)) > 1e-5
    assert differs.tolist() == [k > K for k in range(N)]  # causal, and every later prefix reads its new probe
    moved = points.clone()
    moved[..., :3] += torch.tensor([0.3, -0.2, 0.1])  # the same touches, the object elsewhere
    assert torch.allclose(clf(moved), logits, atol=1e-5)


def test_touch_set_ignores_missed_probes() -> None:
    """A miss reports no surface point: its coordinates must not matter, and a prefix of misses is finite."""
    clf = TouchSetClassifier(4, shared=(8, 16, 32), hidden=16)
    points = touched_points([False, True, False, True, True, False])
    changed = points.clone()
    changed[:, [0, 2, 5], :3] += 5.0
    logits = clf(points)
    assert torch.isfinite(logits).all()
    logits.square().sum().backward()  # the empty first prefix must not poison the gradient either
    assert all(torch.isfinite(p.grad).all() for p in clf.parameters())
    assert torch.allclose(clf(changed), logits)
    assert not torch.allclose(logits[:, 0], logits[:, 1])  # the first touch changes the prediction


def test_wide_touch_set_reads_where_probes_missed() -> None:
    """A miss reports where its ray ended: the wide variant reads it from its probe on, never before."""
    clf = TouchSetClassifier.wide(4)
    points = touched_points([True, True, False, True, False, True])
    changed = points.clone()
    changed[:, 2, :3] += 0.5
    differs = (clf(changed) - clf(points)).abs().amax(dim=(0, 2)) > 1e-5
    assert differs.tolist() == [k >= 2 for k in range(6)]


@pytest.mark.parametrize("miss_frame", ["touches", "line"])
def test_wide_touch_set_miss_frame_decides_whether_misses_say_where_the_object_lies(miss_frame) -> None:
    """The touches moved across the line and in depth, the misses left where their rays ended: in the touches'
    frame the misses then sit elsewhere relative to the object, in the line's frame only their Y is relative, so
    the answer changes in the first and not in the second. Moved along the line, touches and misses alike, it
    changes in neither."""
    clf = TouchSetClassifier.wide(4, miss_frame=miss_frame)
    points = touched_points([True, False, True, True, False, True])
    touched = points[..., 3:] > 0.5
    logits = clf(points)
    across = points.clone()
    across[..., :3] += torch.tensor([0.3, 0.0, -0.2]) * touched
    moved_across = not torch.allclose(clf(across), logits, atol=1e-5)
    assert moved_across == (miss_frame == "touches")
    along = points.clone()
    along[..., 1] += 0.4
    assert torch.allclose(clf(along), logits, atol=1e-5)


@pytest.mark.parametrize("miss_frame", ["touches", "line"])
def test_mirrored_touch_set_reads_an_episode_and_its_mirror_image_alike(miss_frame) -> None:
    """Mirrored across the line (X -> 2 line_x - X), touches and misses alike: the same answer with `mirror`, and
    another without it."""
    points = touched_points([True, False, True, True, False, True])
    points[..., 0] = points[..., 0].abs() + 0.1  # every touch on the +x side of a line at X = 0.05
    image = points.clone()
    image[..., 0] = 0.1 - points[..., 0]
    for mirror in (True, False):
        clf = TouchSetClassifier.wide(4, miss_frame=miss_frame, mirror=mirror)
        clf.line_x = 0.05
        assert torch.allclose(clf(image), clf(points), atol=1e-5) == mirror


def test_touch_set_miss_frame_is_checked() -> None:
    with pytest.raises(ValueError, match="miss_frame='side'"):
        TouchSetClassifier.wide(4, miss_frame="side")
    with pytest.raises(ValueError, match="needs misses=True"):
        TouchSetClassifier(4, miss_frame="line")


def test_touch_set_with_prefixes_tells_a_sparse_prefix_from_a_full_one() -> None:
    """The same touched points and share of touches, read after 2 probes and after 4: alike without the prefix
    input, told apart with it."""
    short = touched_points([True, False])
    full = touched_points([True, True, False, False])
    full[:, 1, :3] = full[:, 0, :3] = short[:, 0, :3]  # the same point touched twice: the same set, share 1/2
    for n_prefixes, alike in ((0, True), (4, False)):
        torch.manual_seed(0)
        clf = TouchSetClassifier(4, shared=(8, 16, 32), hidden=16, n_prefixes=n_prefixes)
        assert torch.allclose(clf(short)[:, 1], clf(full)[:, 3], atol=1e-6) == alike
    with pytest.raises(ValueError, match="n_prefixes=4"):
        clf(touched_points([True] * 5))


@pytest.mark.parametrize("make", [lambda: PointNet(4), lambda: DGCNN(4, k=9)], ids=["PointNet", "DGCNN"])
def test_pointcloud_shapes(make) -> None:
    net = make()
    assert net(torch.randn(2, 10, 3)).shape == (2, 4)
    net.eval()
    assert net(torch.randn(1, 10, 3)).shape == (1, 4)


def test_dgcnn_k_must_be_below_point_count() -> None:
    with pytest.raises(ValueError, match="k=10"):
        DGCNN(4, k=10)(torch.randn(2, 10, 3))


@pytest.mark.parametrize(
    "make", [lambda: PCRN(width=16, out_dim=32), lambda: LSTMEncoder(hidden=32)], ids=["PCRN", "LSTM"]
)
def test_encoders_step_by_step_equal_forward(make) -> None:
    """The rollout encodes one probe at a time; evaluate() encodes whole sequences: they must agree."""
    encoder = make()
    requests, points, memory = torch.randn(B, N, 4), torch.randn(B, N, 4), None
    full = encoder(requests, points)
    for k in range(N):
        out, memory = encoder.step(requests[:, k], points[:, k], memory)
        assert torch.allclose(out, full[:, k], atol=1e-5), k


def test_library_namer_weighs_the_library_by_how_well_its_readings_match() -> None:
    """Class 0's episodes touch candidate 0 10 cm along the ray, class 1's miss it; both touch candidate 1, at 20 cm
    and 30 cm, and class 2's touch only candidate 2."""
    library = torch.tensor([[0.10, 0.20, MISS], [0.11, 0.20, MISS], [MISS, 0.30, MISS], [MISS, 0.31, MISS],
                            [MISS, MISS, 0.15]])
    labels = torch.tensor([0, 0, 1, 1, 2])
    namer = LibraryNamer(library, labels, 3, sigma=0.005, mismatch=1e-3, chunk=1)
    chosen = torch.tensor([[0, 1], [1, 0], [2, 0]])
    readings = torch.tensor([[0.102, 0.20], [0.30, MISS], [MISS, MISS]])
    log_p = namer(chosen, readings)
    assert log_p.shape == (3, 2, 3)
    torch.testing.assert_close(log_p.logsumexp(-1), torch.zeros(3, 2))
    assert log_p[0, 0].argmax() == 0 and log_p[0, 0, 0].exp() > 0.99  # a touch where only class 0 touches
    assert log_p[1, 0].argmax() == 1 and log_p[1, 1, 1].exp() > 0.99  # 30 cm on candidate 1, then a miss on 0
    # a miss on candidate 2 leaves classes 0 and 1 alike (each 2 library episodes), class 2 a mismatch away
    torch.testing.assert_close(log_p[2, 0, 0], log_p[2, 0, 1])
    assert log_p[2, 0, 2] < log_p[2, 0, 0] - 5
    torch.testing.assert_close(LibraryNamer(library, labels, 3, 0.005, 1e-3, chunk=64)(chosen, readings), log_p)
    with pytest.raises(ValueError, match=r"LibraryNamer: the library holds no episode of class \[3\]"):
        LibraryNamer(library, labels, 4, 0.005, 1e-3)
    # its belief (model.choice_reads_belief): the same class posterior, and where the weighed library's objects lie
    positions = torch.tensor([[0.5, -1.0], [0.5, -0.8], [-0.5, 0.2], [-0.5, 0.4], [0.1, 0.9]])
    believer = LibraryNamer(library, labels, 3, 0.005, 1e-3, chunk=2, positions=positions)
    beliefs = believer.beliefs(chosen, readings)
    assert beliefs.shape == (3, 2, 3 + 4)
    torch.testing.assert_close(beliefs[..., :3], log_p.exp(), atol=1e-6, rtol=0)
    # after a 10.2 cm touch on candidate 0: library episodes 0 and 1 (10 and 11 cm) weighed by their Gaussians, the
    # others a mismatch (1e-3) away
    w = torch.softmax(torch.tensor([-0.5 * 0.4 ** 2, -0.5 * 1.6 ** 2] + [math.log(1e-3)] * 3), 0)
    x, y = positions.T
    expected = torch.stack([w @ y, (w @ (y - w @ y) ** 2).sqrt(), w @ x, w[[0, 1, 4]].sum()])
    torch.testing.assert_close(beliefs[0, 0, 3:], expected, atol=1e-5, rtol=0)
    assert expected[0] < -0.9 and expected[3] > 0.99  # mostly where episodes 0 and 1 lie: along -y, to +x
    log_w = torch.zeros(3, 5)  # the rollout's incremental form reads the same
    for k in range(2):
        torch.testing.assert_close(believer.belief(believer.update(log_w, chosen[:, k], readings[:, k])), beliefs[:, k])
    with pytest.raises(ValueError, match=r"LibraryNamer: positions \(5, 3\), expected \(5, 2\)"):
        LibraryNamer(library, labels, 3, 0.005, 1e-3, positions=torch.zeros(5, 3))
    with pytest.raises(ValueError, match="built without its library's positions"):
        namer.belief(log_w)


def test_log_likelihood_in_place_is_the_plain_formula_to_the_bit() -> None:
    """log_likelihood works in place for speed; the teachers and figures made before must come out the same, so it
    must equal the formula written with torch.where over fresh tensors, bit for bit, with and without faults."""
    generator = torch.Generator().manual_seed(0)
    library = torch.rand(6, 500, generator=generator) * 0.3
    library[torch.rand(6, 500, generator=generator) < 0.5] = MISS
    readings = torch.tensor([[0.1], [MISS], [0.25], [MISS], [0.0], [0.3]])
    for noise in (SensorNoise(), SensorNoise(miss_prob=0.2, false_contact_prob=0.1, position_std=0.002)):
        sigma = math.hypot(0.005, noise.position_std)
        false_touch = noise.false_contact_prob * sigma * math.sqrt(2 * math.pi) / 0.6
        touched, library_touched = readings != MISS, library != MISS
        both = torch.where(touched, math.log1p(-noise.miss_prob) - 0.5 * ((library - readings) / sigma) ** 2,
                           math.log1p(-noise.false_contact_prob))
        one = torch.where(library_touched, math.log(max(noise.miss_prob, 1e-3)), math.log(max(false_touch, 1e-3)))
        plain = torch.where(touched == library_touched, both, one)
        assert torch.equal(log_likelihood(readings, library, 0.005, 1e-3, noise, probe_length=0.6), plain)


def test_library_namer_models_the_sensor_faults_it_reads() -> None:
    """With missed and false contacts the likelihood is the sensor's own: a library touch read as a miss keeps
    miss_prob, a library miss read as a touch false_contact_prob spread along the ray, so a faulty reading leaves
    the posterior what Bayes says instead of all but ruling the true class out."""
    noise = SensorNoise(miss_prob=0.2, false_contact_prob=0.1)
    library = torch.tensor([[0.20, 0.20, MISS, MISS]])
    ll = log_likelihood(torch.tensor([[0.20], [MISS]]), library.expand(2, 4) + torch.tensor([0, 0.01, 0, 0]), 0.005,
                        1e-3, noise, probe_length=0.6)
    sigma_scale = 0.005 * math.sqrt(2 * math.pi) / 0.6
    false_touch = math.log(0.1 * sigma_scale)
    expected = torch.tensor([[math.log(0.8), math.log(0.8) - 2.0, false_touch, false_touch],
                             [math.log(0.2), math.log(0.2), math.log(0.9), math.log(0.9)]])
    torch.testing.assert_close(ll, expected)
    plain = log_likelihood(torch.tensor([[0.20], [MISS]]), library.expand(2, 4), 0.005, 1e-3)
    torch.testing.assert_close(plain, torch.tensor([[0.0, 0.0, math.log(1e-3), math.log(1e-3)],
                                                    [math.log(1e-3), math.log(1e-3), 0.0, 0.0]]))
    # class 0 touches candidate 0, class 1 does not; both touch candidate 1 at 20 cm. A miss on 0 then 20 cm on 1:
    library = torch.tensor([[0.10, 0.20], [MISS, 0.20]])
    chosen, read = torch.tensor([[0, 1]]), torch.tensor([[MISS, 0.20]])
    aware = LibraryNamer(library, torch.tensor([0, 1]), 2, 0.005, 1e-3, noise, probe_length=0.6)(chosen, read)
    torch.testing.assert_close(aware[0, 1, 0].exp(), torch.tensor(0.2 / (0.2 + 0.9)))
    plain = LibraryNamer(library, torch.tensor([0, 1]), 2, 0.005, 1e-3)(chosen, read)
    assert plain[0, 1, 0].exp() < 1e-2
    dropped = LibraryNamer(library, torch.tensor([0, 1]), 2, 0.005, 1e-3)(chosen, read, torch.tensor([[True, False]]))
    torch.testing.assert_close(dropped[0].exp(), torch.full((2, 2), 0.5))  # the miss left out, 20 cm fits both
