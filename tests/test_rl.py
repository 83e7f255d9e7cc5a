"""hg.rl: the rollout (the one caller of the simulator, on real ray casts), the hybrid update rule of eq. (6) term by
term, and the warm-ups."""
import math

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from hg.lightning.data import episode_batch
from hg.nets import PCRN, Dims
from hg.policies import GaussianPolicy, LineScan, Observation, Policy
from hg.rl import FollowPrior, HybridLoss, ImitateTeacher, Warmup, discounted_returns, rollout
from hg.rl.loss import rewards_of
from hg.sim import PoseRegions, ProbeSimulator, SensorNoise

N_PROBES, POINT_SCALE = 4, 2.0
DIMS = Dims(rep=32, n_probes=N_PROBES, n_classes=4)


def encoder() -> PCRN:
    torch.manual_seed(0)
    return PCRN(width=16, out_dim=32)


def gaussian(**kwargs) -> GaussianPolicy:
    torch.manual_seed(0)
    return GaussianPolicy(DIMS, hidden=32, **kwargs)


# -- eq. (6) ---------------------------------------------------------------------------------------------------------
def test_discounted_returns():
    rewards = torch.tensor([[1.0, 0.0, 1.0], [0.0, 0.0, 1.0]])
    expected = torch.tensor([[1 + 0.5 ** 2, 0.5, 1.0], [0.25, 0.5, 1.0]])
    torch.testing.assert_close(discounted_returns(rewards, 0.5), expected)
    torch.testing.assert_close(discounted_returns(rewards, 0.0), rewards)


def loss_inputs():
    torch.manual_seed(0)
    logits = torch.randn(6, 3, 4, requires_grad=True)
    labels = torch.randint(4, (6,))
    log_pi = torch.randn(6, 3, requires_grad=True)
    baseline = torch.randn(6, 3, requires_grad=True)
    return logits, labels, log_pi, baseline


def test_hybrid_loss_terms_are_those_of_eq_6():
    """L = CE over every prefix + beta * policy_scale * REINFORCE with a detached advantage (G_k - b_k) + the
    baseline's MSE to G_k; each term is returned and each reaches only what it should train."""
    logits, labels, log_pi, baseline = loss_inputs()
    terms = HybridLoss(gamma=0.9, beta=0.7)(logits, labels, log_pi, baseline, policy_scale=0.5)
    correct = (logits.argmax(-1) == labels[:, None]).float()
    returns = discounted_returns(correct, 0.9)
    torch.testing.assert_close(terms["loss_ce"], F.cross_entropy(logits.flatten(0, 1), labels.repeat_interleave(3)))
    torch.testing.assert_close(terms["loss_policy"], -(log_pi * (returns - baseline)).mean())
    torch.testing.assert_close(terms["loss_baseline"], F.mse_loss(baseline, returns))
    torch.testing.assert_close(terms["loss"], terms["loss_ce"] + 0.7 * 0.5 * terms["loss_policy"]
                               + terms["loss_baseline"])
    torch.testing.assert_close(terms["reward"], correct.mean())
    torch.testing.assert_close(terms["acc"], correct[:, -1].mean())
    # the advantage is detached: the policy term never moves the baseline, and its gradient is -(G - b) / numel
    assert torch.autograd.grad(terms["loss_policy"], baseline, retain_graph=True, allow_unused=True)[0] is None
    (grad_pi,) = torch.autograd.grad(terms["loss_policy"], log_pi, retain_graph=True)
    torch.testing.assert_close(grad_pi, -(returns - baseline.detach()) / log_pi.numel())
    # the baseline's fit reaches neither the policy nor the classifier
    assert torch.autograd.grad(terms["loss_baseline"], [log_pi, logits], retain_graph=True,
                               allow_unused=True) == (None, None)
    # nothing of the policy without a policy to train (a fixed scan, a teacher's probes)
    alone = HybridLoss()(logits, labels)
    assert set(alone) == {"loss", "loss_ce", "reward", "acc"} and torch.equal(alone["loss"], alone["loss_ce"])


def test_normalized_advantages_have_unit_spread_per_probe_index():
    logits, labels, log_pi, baseline = loss_inputs()
    terms = HybridLoss(gamma=0.9, normalize_advantage=True)(logits, labels, log_pi, baseline)
    advantage = discounted_returns((logits.argmax(-1) == labels[:, None]).float(), 0.9) - baseline.detach()
    (grad_pi,) = torch.autograd.grad(terms["loss_policy"], log_pi)
    normalized = -grad_pi * log_pi.numel()
    torch.testing.assert_close(normalized, advantage / (advantage.std(0, keepdim=True) + 1e-6))
    torch.testing.assert_close(normalized.std(0), torch.ones(3), atol=1e-4, rtol=0)


def test_advantage_of_the_reward_as_eq_6_writes_it():
    """advantage="reward": (r_k - b_k), b_k fitted to r_k, instead of the return."""
    logits, labels, log_pi, baseline = loss_inputs()
    terms = HybridLoss(gamma=0.9, advantage="reward")(logits, labels, log_pi, baseline)
    rewards = (logits.argmax(-1) == labels[:, None]).float()
    torch.testing.assert_close(terms["loss_policy"], -(log_pi * (rewards - baseline)).mean())
    torch.testing.assert_close(terms["loss_baseline"], F.mse_loss(baseline, rewards))


def test_log_gain_rewards_add_up_to_the_final_log_probability():
    """r_k = log p_k(true) - log p_{k-1}(true), from log(1/C) before any probe: they sum to log p_N - log(1/C)."""
    torch.manual_seed(1)
    logits, labels = torch.randn(6, 5, 4), torch.randint(4, (6,))
    terms = HybridLoss(gamma=1.0, reward="log_gain")(logits, labels, torch.zeros(6, 5), torch.zeros(6, 5))
    final = logits[:, -1].log_softmax(-1).gather(-1, labels[:, None]).squeeze(-1)
    torch.testing.assert_close(terms["reward"] * 5, (final - math.log(1 / 4)).mean())
    # with gamma 1 the return of the first request is the whole sum, the baseline (0) is fitted to the returns
    torch.testing.assert_close(terms["loss_baseline"], discounted_returns(
        torch.diff(logits.log_softmax(-1).gather(-1, labels[:, None, None].expand(-1, 5, 1)).squeeze(-1), dim=1,
                   prepend=torch.full((6, 1), math.log(1 / 4))), 1.0).pow(2).mean())


def test_touch_rewards_are_the_contact_flags_whatever_the_classifier_says():
    """The diagnostic reward: r_k = T_k, so the returns count the touches to come and the prediction plays no part."""
    logits, labels, log_pi, baseline = loss_inputs()
    touched = torch.rand(log_pi.shape, generator=torch.Generator().manual_seed(0)) < 0.4
    points = torch.cat([torch.rand(*log_pi.shape, 3), touched[..., None].float()], -1)
    terms = HybridLoss(gamma=0.5, reward="touch")(logits, labels, log_pi, baseline, points=points)
    assert terms["reward"] == touched.float().mean()
    torch.testing.assert_close(terms["loss_baseline"], F.mse_loss(baseline, discounted_returns(touched.float(), 0.5)))
    flipped = HybridLoss(gamma=0.5, reward="touch")(-logits, labels, log_pi, baseline, points=points)
    torch.testing.assert_close(flipped["loss_policy"], terms["loss_policy"])
    with pytest.raises(ValueError, match="needs the probes' points"):
        HybridLoss(reward="touch")(logits, labels, log_pi, baseline)


def test_new_touch_rewards_pay_a_touch_by_its_distance_to_the_earlier_ones():
    """A first touch earns 1, a miss 0, a touch on an earlier touch's spot 0, one half a spread away 0.5; an earlier
    miss at the same spot does not count (episode 2: its touch is a first touch)."""
    points = torch.tensor([[[0.0, 0.0, 0.0, 1.0], [0.3, 0.0, 0.0, 0.0], [0.0, 0.0, 0.0, 1.0], [0.05, 0.0, 0.0, 1.0],
                            [0.0, 1.0, 0.0, 1.0]],
                           [[0.3, 0.0, 0.0, 0.0], [0.3, 0.0, 0.0, 1.0], [0.35, 0.0, 0.0, 1.0], [0.0, 0.0, 0.0, 0.0],
                            [0.3, 0.0, 0.0, 1.0]]])
    rewards = rewards_of(torch.zeros(2, 5, 2), torch.zeros(2, dtype=torch.long), "new_touch", points, spread=0.1)
    torch.testing.assert_close(rewards, torch.tensor([[1.0, 0.0, 0.0, 0.5, 1.0], [0.0, 1.0, 0.5, 0.0, 0.0]]))
    with pytest.raises(ValueError, match="loss.spread=0"):
        HybridLoss(reward="new_touch", spread=0)
    # a sum pays each term: here the class reward adds 1 where the prediction (class 0 of all-zero logits) is right
    labels = torch.tensor([0, 1])
    summed = rewards_of(torch.zeros(2, 5, 2), labels, "new_touch+correct", points, spread=0.1)
    torch.testing.assert_close(summed, rewards + torch.tensor([[1.0], [0.0]]))


def test_loss_settings_are_checked():
    with pytest.raises(ValueError, match="loss.gamma=1.5"):
        HybridLoss(gamma=1.5)
    with pytest.raises(ValueError, match="loss.reward='contact'"):
        HybridLoss(reward="contact")
    with pytest.raises(ValueError, match="loss.reward='new_touch\\+contact'"):
        HybridLoss(reward="new_touch+contact")
    with pytest.raises(ValueError, match="loss.advantage='q'"):
        HybridLoss(advantage="q")


# -- the rollout -----------------------------------------------------------------------------------------------------
class Counted:
    """The real simulator, its calls recorded."""

    def __init__(self, sim: ProbeSimulator) -> None:
        self.sim, self.calls, self.requests = sim, [], []

    def reset(self, *args, **kwargs):
        self.calls.append("reset")
        return self.sim.reset(*args, **kwargs)

    def probe(self, requests, faults=None):
        self.calls.append("probe")
        self.requests.append(requests.copy())
        return self.sim.probe(requests, faults)

    def __getattr__(self, name):
        return getattr(self.sim, name)


class Watched(Policy):
    """A real policy whose observations are kept."""

    def __init__(self, policy: Policy) -> None:
        super().__init__()
        self.policy, self.seen = policy, []
        self.learned = policy.learned

    def act(self, obs: Observation, deterministic, generator):
        self.seen.append(Observation(obs.k, obs.actions.clone(), obs.points.clone(),
                                     None if obs.rep_sum is None else obs.rep_sum.clone()))
        return self.policy.act(obs, deterministic, generator)


def test_rollout_probes_once_per_probe_and_shows_the_policy_only_the_probes_so_far(sim, batch):
    counted, policy, net = Counted(sim), Watched(gaussian()), encoder()
    out = rollout(counted, policy, batch["labels"], batch["poses"], 3, N_PROBES, POINT_SCALE, net)
    assert counted.calls == ["reset"] + ["probe"] * N_PROBES
    for k, sent in enumerate(counted.requests):  # what was executed: the actions clamped to [-1, 1]
        np.testing.assert_allclose(sent, out.actions[:, k].clamp(-1, 1).double().numpy())
    torch.testing.assert_close(out.requests, out.actions.clamp(-1, 1))
    assert (out.actions.abs() > 1).any()  # the untrained Gaussian asks beyond the line's ends: clamped, not dropped
    rep = net(out.requests, out.points)
    assert [obs.k for obs in policy.seen] == list(range(N_PROBES))
    for obs in policy.seen:
        k = obs.k
        torch.testing.assert_close(obs.points[:, :k], out.points[:, :k])
        torch.testing.assert_close(obs.actions[:, :k], out.actions[:, :k])
        assert not obs.points[:, k:].any() and not obs.actions[:, k:].any()
        # the encoder's outputs, one probe at a time, summed: what the whole-sequence pass of the loss gives
        if k == 0:
            assert obs.rep_sum is None
        else:
            torch.testing.assert_close(obs.rep_sum, rep[:, :k].sum(1), atol=1e-5, rtol=1e-5)
    # X, Y, Z in units of point_scale: the policy sees what the heads see
    sim.reset(batch["labels"].numpy(), batch["poses"].numpy())
    for k in range(N_PROBES):
        direct = torch.from_numpy(sim.probe(out.requests[:, k].double().numpy()).points).float()
        torch.testing.assert_close(out.points[:, k, :3], direct[:, :3] * POINT_SCALE)
        torch.testing.assert_close(out.points[:, k, 3], direct[:, 3])
    assert out.points[..., 3].any() and out.reached.all()  # ideal mode: every request reached


def test_rollout_is_a_function_of_the_seed(sim, batch):
    policy, net = gaussian(), encoder()

    def roll(seed, deterministic=False):
        return rollout(sim, policy, batch["labels"], batch["poses"], seed, N_PROBES, POINT_SCALE, net, deterministic)

    first = roll(7)
    roll(8)  # other work in between changes nothing
    again = roll(7)
    torch.testing.assert_close(first.actions, again.actions)
    torch.testing.assert_close(first.points, again.points)
    assert not torch.equal(first.actions, roll(8).actions)
    mean_action = roll(7, deterministic=True)
    assert not torch.equal(first.actions, mean_action.actions)
    torch.testing.assert_close(mean_action.actions, roll(8, deterministic=True).actions)  # the seed draws nothing


def test_given_requests_are_probed_instead_of_the_policy(sim, batch):
    policy = gaussian()
    with torch.no_grad():
        policy.location.start.fill_(float("nan"))  # a policy that acted would fail
    with pytest.raises(FloatingPointError, match="non-finite probe request from GaussianPolicy at probe 1"):
        rollout(sim, policy, batch["labels"], batch["poses"], 0, N_PROBES, POINT_SCALE, encoder())
    requests = torch.rand(8, N_PROBES, 4) * 2.4 - 1.2
    out = rollout(sim, policy, batch["labels"], batch["poses"], 0, N_PROBES, POINT_SCALE, encoder(),
                  requests=requests)
    torch.testing.assert_close(out.actions, requests)
    torch.testing.assert_close(out.requests, requests.clamp(-1, 1))


def test_given_faults_replace_the_sensors_draws():
    """Under sensor faults the seed draws them, unless a teacher's uniforms are given: then every seed reads the
    same, uniforms above the fault rates read what a fault-free sensor reads, and zeros flip every contact."""
    labels_poses = episode_batch(PoseRegions(), "train", 8, 4, [0, 0, 0, 1])
    labels, poses = labels_poses["labels"], labels_poses["poses"]
    scan = LineScan(DIMS, span=0.5)
    noise = SensorNoise(miss_prob=0.3, false_contact_prob=0.3)
    with ProbeSimulator("hg4", batch_size=8, mode="ideal", noise=noise) as noisy, \
            ProbeSimulator("hg4", batch_size=8, mode="ideal") as clean:
        def roll(sim, seed, faults=None):
            return rollout(sim, scan, labels, poses, seed, N_PROBES, POINT_SCALE, faults=faults).points

        drawn = [roll(noisy, seed)[..., 3] for seed in range(4)]
        assert any(not torch.equal(d, drawn[0]) for d in drawn[1:])
        faults = torch.rand(8, N_PROBES, 2, generator=torch.Generator().manual_seed(0))
        torch.testing.assert_close(roll(noisy, 0, faults), roll(noisy, 1, faults))
        truth = roll(clean, 0)
        torch.testing.assert_close(roll(noisy, 5, torch.full((8, N_PROBES, 2), 0.99)), truth)
        assert torch.equal(roll(noisy, 5, torch.zeros(8, N_PROBES, 2))[..., 3], 1 - truth[..., 3])


def test_rollout_in_arm_mode_reports_what_the_arm_reached(batch):
    scan = LineScan(Dims(32, 2, 4), span=0.5)
    with ProbeSimulator("hg4", batch_size=8, mode="arm") as sim:
        out = rollout(sim, scan, batch["labels"], batch["poses"], 0, 2, POINT_SCALE)
    assert out.reached.dtype == torch.bool and out.reached.shape == (8, 2) and out.reached.float().mean() > 0.5


# -- warm-ups --------------------------------------------------------------------------------------------------------
def test_imitate_teacher_serves_the_teachers_episodes_in_turn():
    teacher = {"labels": torch.arange(5), "poses": torch.arange(5.0)[:, None].expand(5, 6),
               "requests": torch.arange(5.0)[:, None, None].expand(5, N_PROBES, 4), "faults": None}
    warmup = ImitateTeacher(3, ["teacher.npz"])
    with pytest.raises(RuntimeError, match="teacher files were not loaded"):
        warmup.episodes(torch.zeros(2), torch.zeros(2, 6), 0)
    warmup.teacher = teacher
    served = [warmup.episodes(torch.zeros(2, dtype=torch.long), torch.zeros(2, 6), step) for step in range(4)]
    assert [s[0].tolist() for s in served] == [[0, 1], [2, 3], [4, 0], [1, 2]]  # in turn, round and round
    for labels, poses, requests, faults in served:
        assert (poses[:, 0] == labels).all() and (requests[:, 0, 0] == labels).all() and faults is None
    assert warmup.imitate and not FollowPrior(3).imitate
    labels, poses = torch.zeros(2, dtype=torch.long), torch.zeros(2, 6)
    assert FollowPrior(3).episodes(labels, poses, 0)[2:] == (None, None)  # the prior scan probes
    with pytest.raises(ValueError, match="warmup.steps=0"):
        FollowPrior(0)


def test_a_warmup_probes_with_the_untrained_policy_or_its_prior_scan():
    plain, on_scan = gaussian(), gaussian(prior=LineScan)
    assert Warmup(2).prober(plain) is plain
    assert FollowPrior(2).prober(on_scan) is on_scan.prior and isinstance(on_scan.prior, LineScan)
    with pytest.raises(ValueError, match="FollowPrior probes with the policy's prior scan; GaussianPolicy has none"):
        FollowPrior(2).prober(plain)
    with pytest.raises(ValueError, match="warmup.teachers"):
        ImitateTeacher(3, [])
