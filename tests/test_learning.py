"""The hybrid update rule and the Lightning module on real rollouts in the simulator (ideal mode, tiny nets)."""
import copy
import csv
import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import pytorch_lightning as pl
import torch
import torch.nn.functional as F
from pytorch_lightning.callbacks import ModelCheckpoint

from hg.lightning import HapticGlance, ProbeDataModule, discounted_returns, hybrid_loss
from hg.lightning.callbacks import WeightEMA
from hg.lightning.module import Rollout, relative_to_first_touch
from hg.nets import reflect
from hg.sim.library import MISS, readings
from hg.sim.scene import Scene
from hg.sim.simulator import ProbeSimulator, SensorNoise

ROOT = Path(__file__).resolve().parents[1]
TINY = str(ROOT / "configs" / "tiny.yaml")


@pytest.fixture(scope="module")
def data():
    return ProbeDataModule(mode="ideal", batch_size=8, eval_batch_size=8, val_episodes=8, test_episodes=8, n_probes=4)


def make_model(data, **kwargs):
    torch.manual_seed(0)
    model = HapticGlance(n_classes=data.n_classes, n_probes=data.n_probes, width=16, representation=32, hidden=32,
                         **kwargs)
    model.sim = data.make_simulator()
    return model


def first_batch(data):
    return next(iter(data.train_dataloader()))


def test_discounted_returns():
    rewards = torch.tensor([[1.0, 0.0, 1.0], [0.0, 0.0, 1.0]])
    expected = torch.tensor([[1 + 0.5 ** 2, 0.5, 1.0], [0.25, 0.5, 1.0]])
    torch.testing.assert_close(discounted_returns(rewards, 0.5), expected)


def grads_of(model, loss):
    model.zero_grad()
    loss.backward(retain_graph=True)
    return {name: any(p.grad is not None and p.grad.abs().sum() > 0 for p in part.parameters())
            for name, part in (("encoder", model.encoder), ("classifier", model.classifier),
                               ("location", model.location), ("baseline", model.baseline))}


def test_gradient_routing(data):
    model = make_model(data)
    batch = first_batch(data)
    rollout = model.rollout(batch["labels"], batch["poses"], int(batch["seed"]))
    terms, _ = model.evaluate(rollout, batch["labels"])
    assert grads_of(model, terms["loss_policy"]) == {"encoder": True, "classifier": False, "location": True,
                                                      "baseline": False}
    assert grads_of(model, terms["loss_ce"]) == {"encoder": True, "classifier": True, "location": False,
                                                  "baseline": False}
    assert grads_of(model, terms["loss_baseline"]) == {"encoder": False, "classifier": False, "location": False,
                                                        "baseline": True}


@pytest.mark.parametrize("policy_reads_touch_set", [False, True], ids=["classifier only", "policy reads it"])
def test_touch_set_adds_to_the_classifier_and_learns_from_cross_entropy_only(data, policy_reads_touch_set):
    model = make_model(data, touch_set=True, policy_reads_touch_set=policy_reads_touch_set)
    batch = first_batch(data)
    rollout = model.rollout(batch["labels"], batch["poses"], int(batch["seed"]))
    terms, logits = model.evaluate(rollout, batch["labels"])
    rep = model.encoder(rollout.requests, rollout.points)
    torch.testing.assert_close(logits, model.classifier(rep) + model.touch_set(rollout.points))
    for loss, learns in (("loss_ce", True), ("loss_policy", False), ("loss_baseline", False)):
        model.zero_grad()
        terms[loss].backward(retain_graph=True)
        assert any(p.grad is not None and p.grad.abs().sum() > 0 for p in model.touch_set.parameters()) == learns
    assert make_model(data).touch_set is None  # off by default: the paper's rows are unchanged
    with pytest.raises(ValueError, match="policy_reads_touch_set=true needs model.touch_set=true"):
        make_model(data, policy_reads_touch_set=True)


def test_policy_warmup_trains_the_classifier_on_the_scan_and_leaves_the_policy_alone(data):
    def fit(warmup_steps: int) -> tuple[HapticGlance, HapticGlance]:
        model = make_model(data, prior="line_scan", policy_warmup_steps=warmup_steps)
        before = copy.deepcopy(model)
        trainer = pl.Trainer(max_steps=2, logger=False, enable_checkpointing=False, enable_progress_bar=False,
                             enable_model_summary=False, limit_val_batches=0, accelerator="cpu")
        trainer.fit(model, datamodule=data)
        return before, model

    def changed(a, b) -> bool:
        return any(not torch.equal(p, q) for p, q in zip(a.parameters(), b.parameters()))

    before, warming = fit(2)
    assert not changed(before.location, warming.location) and changed(before.classifier, warming.classifier)
    before, learning = fit(0)
    assert changed(before.location, learning.location)
    batch = first_batch(data)
    warming.sim = data.make_simulator()  # fit's teardown closed the model's own
    scan = warming.rollout(batch["labels"], batch["poses"], 0, follow_scan=True)
    torch.testing.assert_close(scan.requests, warming.line_scan_requests().expand_as(scan.requests))
    terms, _ = warming.evaluate(scan, batch["labels"], learn_policy=False)
    assert "loss_policy" not in terms and torch.equal(terms["loss"], terms["loss_ce"])
    warming.sim.close()
    with pytest.raises(ValueError, match="model.policy_warmup_steps=-1"):
        HapticGlance(policy_warmup_steps=-1)


@pytest.fixture(scope="module")
def teacher(tmp_path_factory):
    """A real planner's 4-probe episodes of training poses (scripts/planner_ceiling.py with a tiny library)."""
    path = tmp_path_factory.mktemp("teacher") / "teacher.npz"
    proc = subprocess.run([sys.executable, str(ROOT / "scripts" / "planner_ceiling.py"), "--library-split", "train",
                           "--split", "train", "--library", "256", "--episodes", "32", "--n-probes", "4",
                           "--save-rollouts", str(path)], capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-3000:]
    return path


def imitation_losses(model, data, steps):
    """Fit `model` for `steps` steps of its teacher's episodes (no validation); its imitation loss at each step."""
    losses = []

    class Record(pl.Callback):
        def on_train_batch_end(self, trainer, pl_module, outputs, batch, batch_idx):
            losses.append(float(trainer.callback_metrics["train/loss_imitation"]))

    trainer = pl.Trainer(max_steps=steps, logger=False, enable_checkpointing=False, enable_progress_bar=False,
                         enable_model_summary=False, limit_val_batches=0, accelerator="cpu", callbacks=[Record()])
    trainer.fit(model, datamodule=data)
    return losses


@pytest.mark.parametrize("location, reads_probes", [("gaussian", False), ("candidates", False), ("candidates", True)])
def test_imitation_warmup_probes_where_the_teacher_chose_and_copies_its_requests(data, teacher, location, reads_probes):
    model = make_model(data, policy_warmup_steps=30, imitate=(str(teacher),), location=location,
                       choice_reads_probes=reads_probes)
    losses = imitation_losses(model, data, 30)
    assert len(losses) == 30 and np.mean(losses[-5:]) < 0.8 * np.mean(losses[:5])  # the policy moves to the teacher
    episodes = model.teacher
    assert len(episodes["labels"]) == 32 and (data.regions.split_of(episodes["poses"].numpy()) == 0).all()
    model.sim = data.make_simulator()  # fit's teardown closed the model's own
    labels, poses, requests = episodes["labels"][:8], episodes["poses"][:8], episodes["requests"][:8]
    rollout = model.rollout(labels, poses, 0, requests=requests)
    torch.testing.assert_close(rollout.requests, requests.clamp(-1, 1))
    terms, _ = model.evaluate(rollout, labels, learn_policy="imitate")
    assert "loss_policy" not in terms
    torch.testing.assert_close(terms["loss"], terms["loss_ce"] + terms["loss_imitation"])
    model.sim.close()


def test_a_choice_reading_the_namers_belief_reads_it_from_the_teachers_episodes_and_as_it_probes(data, teacher):
    """model.choice_reads_belief: the teacher's episodes come with the namer's belief after each probe (read once
    in setup), the policy's own rollouts weigh the namer's library as they go, and the two agree on the same
    probes (ideal mode); the choice's state ends with the belief, and the copy learns beside it."""
    model = make_model(data, policy_warmup_steps=30, imitate=(str(teacher),), location="candidates",
                       choice_reads_probes=True, choice_reads_state=False, library_namer=str(teacher),
                       choice_reads_belief=True)
    losses = imitation_losses(model, data, 30)
    assert len(losses) == 30 and np.mean(losses[-5:]) < 0.8 * np.mean(losses[:5])
    beliefs = model.teacher["beliefs"]
    assert beliefs.shape == (32, data.n_probes, data.n_classes + 4)
    torch.testing.assert_close(beliefs[..., :data.n_classes].sum(-1), torch.ones(32, data.n_probes))
    model.sim = data.make_simulator()  # fit's teardown closed the model's own
    labels, poses, requests = (model.teacher[k][:8] for k in ("labels", "poses", "requests"))
    rollout = model.rollout(labels, poses, 0, requests=requests)  # the namer weighs its library as the probes go
    torch.testing.assert_close(rollout.beliefs, beliefs[:8], atol=1e-4, rtol=0)
    # it named them on the way, as the namer names the whole rollout
    torch.testing.assert_close(rollout.named, model.library_namer(*model.library_readings(rollout.actions,
                                                                                           rollout.points)))
    # the choice reads the belief: another belief, another choice
    extra, _ = model.policy_extra(rollout.actions, rollout.points, beliefs=rollout.beliefs)
    torch.testing.assert_close(extra[..., -(data.n_classes + 4):], rollout.beliefs)
    states = model.policy_states(model.encode(rollout), model.mirrored_states(rollout.points), extra)
    other = extra.clone()
    other[..., -(data.n_classes + 4):] = torch.flip(rollout.beliefs, [0])
    moved = model.policy_states(model.encode(rollout), model.mirrored_states(rollout.points), other)
    assert not torch.allclose(model.location.log_probs(states[:, 1:]), model.location.log_probs(moved[:, 1:]))
    scored = pl.Trainer(logger=False, enable_progress_bar=False, enable_model_summary=False, accelerator="cpu"
                        ).validate(model, datamodule=data)[0]  # its own probes, each chosen beside the namer's belief
    assert 0 <= scored["val/acc"] <= 1  # (validate's teardown closed the simulator)
    with pytest.raises(ValueError, match="model.choice_reads_belief=true reads the library namer's belief, so it needs "
                                         "model.location: candidates, model.library_namer"):
        HapticGlance(location="candidates", choice_reads_belief=True)


def test_a_teacher_planned_under_faults_is_replayed_with_its_faults_and_copied_by_a_choice_that_may_repeat(
        teacher, tmp_path):
    """Under sensor faults (planner_ceiling.py --noise) the teacher file holds the fault uniforms its planner read
    with: its episodes replay them whatever the batch seed, so the copy reads what the planner read; the choice may
    probe a candidate again (model.choice_repeats), and reads a repeated one by counts and mean depth. A teacher of
    another sensor than the run's is refused."""
    noisy = tmp_path / "noisy.npz"
    proc = subprocess.run([sys.executable, str(ROOT / "scripts" / "planner_ceiling.py"), "--library-split", "train",
                           "--split", "train", "--library", "256", "--episodes", "32", "--n-probes", "4",
                           "--noise", "0.3", "--save-rollouts", str(noisy)], capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-3000:]
    noise = SensorNoise(miss_prob=0.3, false_contact_prob=0.3)
    data = ProbeDataModule(mode="ideal", batch_size=8, eval_batch_size=8, val_episodes=8, test_episodes=8, n_probes=4,
                           noise=noise)
    model = make_model(data, policy_warmup_steps=3, imitate=(str(noisy),), location="candidates",
                       choice_reads_probes=True, choice_reads_state=False, choice_repeats=True)
    trainer = pl.Trainer(max_steps=3, logger=False, enable_checkpointing=False, enable_progress_bar=False,
                         enable_model_summary=False, limit_val_batches=0, accelerator="cpu")
    trainer.fit(model, datamodule=data)
    episodes = model.teacher
    assert episodes["faults"].shape == (32, 4, 2)
    model.sim = data.make_simulator()
    labels, poses, requests, faults = (episodes[k][:8] for k in ("labels", "poses", "requests", "faults"))
    replays = [model.rollout(labels, poses, seed, requests=requests, faults=faults).points for seed in (0, 1)]
    torch.testing.assert_close(replays[0], replays[1])  # the teacher's faults, not the batch seed's
    drawn = [model.rollout(labels, poses, seed, requests=requests).points[..., 3] for seed in range(4)]
    assert any(not torch.equal(d, drawn[0]) for d in drawn[1:])  # without them the seed draws the faults
    assert model.policy_extra(requests, replays[0])[1] is None  # no candidate is barred
    again = torch.cat([requests[:1, :1]] * 2, 1)  # one candidate twice: a touch 0.2 deep, then a miss
    features, probed = model.location.readings(again, torch.tensor([[[0.0, 0.0, -0.2, 1.0], [0.0, 0.0, -1.0, 0.0]]]), 4)
    c, n = model.location.index_of(again[0, 0]), len(model.location.candidates)
    assert features[0, 1, [c, n + c, 2 * n + c]].tolist() == pytest.approx([2.0, 1.0, 0.2]) and probed[0, 1, c]
    model.sim.close()
    for imitate, run in ((noisy, ProbeDataModule(mode="ideal", batch_size=8, n_probes=4)), (teacher, data)):
        refused = make_model(run, policy_warmup_steps=2, imitate=(str(imitate),), location="candidates")
        with pytest.raises(ValueError, match=f"{imitate}: planned with sensor faults at rate 0.(3|0)"):
            trainer.fit(refused, datamodule=run)
    with pytest.raises(ValueError, match="model.choice_repeats=true .* model.choice_reads_probes: true"):
        HapticGlance(location="candidates", choice_repeats=True)


def test_candidate_policy_acts_among_its_candidates_in_the_view_it_read_and_learns_by_reinforce(data):
    """A choice among the planner's candidates (model.location: candidates): every request is a candidate, the
    mean-action rollout took the candidate the loss pass finds most likely (in each state's view), and the hybrid
    rule's policy term reaches the choice."""
    model = make_model(data, location="candidates", candidate_places=5, candidate_leans=(1.0,), mirror_encoder=True)
    candidates = model.location.candidates
    assert candidates.shape == (15, 4)
    # lean the untrained choice towards the middle place's probe leaning to -x (in each state's view), so that some
    # episodes touch to -x whatever near-ties the initial logits hold on this CPU
    to_minus_x = int(((candidates[:, 0] == 0) & (candidates[:, 1] < 0)).nonzero()[0, 0])
    with torch.no_grad():
        model.location.net[-1].bias[to_minus_x] += 3.0
    batch = first_batch(data)
    for deterministic in (False, True):
        rollout = model.rollout(batch["labels"], batch["poses"], 1, deterministic=deterministic)
        assert ((rollout.actions[..., None, :] - candidates).abs().amax(-1).min(-1).values < 1e-6).all()
    mirrored = model.mirrored_states(rollout.points)
    assert mirrored.any()  # some episodes touched to -x: their policy acted mirrored
    states = model.policy_states(model.encode(rollout), mirrored)
    in_view = reflect(rollout.actions, 1, where=mirrored)
    torch.testing.assert_close(candidates[model.location.log_probs(states).argmax(-1)], in_view)
    terms, _ = model.evaluate(model.rollout(batch["labels"], batch["poses"], 2), batch["labels"])
    terms["loss"].backward()
    assert terms["loss_policy"].isfinite() and model.location.net[0].weight.grad.abs().sum() > 0
    assert 0 < terms["std_py"] < 1  # the request's spread under the choice, logged as a Gaussian's std
    with pytest.raises(ValueError, match="model.location='candidates' .* takes no prior"):
        HapticGlance(location="candidates", prior="line_scan")
    with pytest.raises(ValueError, match="model.candidate_places / candidate_span / candidate_leans: .*span=1.5"):
        HapticGlance(location="candidates", candidate_span=1.5)


@pytest.mark.parametrize("along_line, reads_state", [(False, True), (True, True), (False, False)],
                         ids=["mlp", "along the line", "readings only"])
def test_choice_reading_the_probes_never_repeats_one_and_the_loss_reads_what_the_rollout_read(data, along_line,
                                                                                              reads_state):
    """model.choice_reads_probes: the choice reads, beside PCRN's state, what each candidate read so far, and never
    probes a candidate twice; the loss pass rebuilds the states the rollout chose from, so the mean-action rollout's
    requests are the candidates the loss pass finds most likely (the probed ones excluded)."""
    model = make_model(data, location="candidates", candidate_places=3, candidate_leans=(1.0,),
                       choice_reads_probes=True, touch_set=True, policy_reads_touch_set=True,
                       choice_along_line=along_line, choice_reads_state=reads_state)
    candidates = model.location.candidates  # 9 candidates for the 4 probes of the test data
    batch = first_batch(data)
    for deterministic in (False, True):
        rollout = model.rollout(batch["labels"], batch["poses"], 1, deterministic=deterministic)
        index = model.location.index_of(rollout.actions)
        assert all(len(set(row.tolist())) == data.n_probes for row in index)  # no candidate twice
    extra, probed = model.policy_extra(rollout.actions, rollout.points, pooled=model.touch_set.pooled(rollout.points))
    assert probed[:, -1].sum(-1).eq(data.n_probes).all()
    touched = rollout.points[..., 3] > 0.5
    assert touched.any()
    readings = extra[..., -(3 * len(candidates) + data.n_probes):]
    b, k = touched.nonzero()[0].tolist()  # a touch is read at its candidate from that probe on
    column = len(candidates) + index[b, k]  # its "touched" reading
    assert readings[b, k:, column].eq(1).all() and readings[b, :k, column].eq(0).all()
    states = model.policy_states(model.encode(rollout), model.mirrored_states(rollout.points), extra)
    exclude = F.pad(probed[:, :-1], (0, 0, 1, 0), value=False)
    torch.testing.assert_close(candidates[model.location.log_probs(states, exclude).argmax(-1)], rollout.actions)
    terms, _ = model.evaluate(model.rollout(batch["labels"], batch["poses"], 2), batch["labels"])
    assert terms["loss_policy"].isfinite()
    with pytest.raises(ValueError, match="model.choice_reads_probes=true .* needs model.location: candidates"):
        HapticGlance(choice_reads_probes=True)
    with pytest.raises(ValueError, match="model.choice_along_line=true .* needs model.choice_reads_probes: true"):
        HapticGlance(location="candidates", choice_along_line=True)
    with pytest.raises(ValueError, match="model.choice_reads_state=false .* needs model.choice_reads_probes: true"):
        HapticGlance(location="candidates", choice_reads_state=False)


def test_along_line_classifier_is_added_to_every_prediction_and_learns_from_the_cross_entropy(data):
    """model.along_line_classifier: its logits of the readings by candidate are added to each prediction, the one
    after the last probe (the final touch set's) too, and the cross-entropy trains it."""
    model = make_model(data, location="candidates", candidate_places=3, candidate_leans=(1.0,),
                       choice_reads_probes=True, touch_set=True, final_touch_set=True, along_line_classifier=True)
    batch = first_batch(data)
    rollout = model.rollout(batch["labels"], batch["poses"], 1)
    terms, logits = model.evaluate(rollout, batch["labels"])
    terms["loss_ce"].backward()
    assert model.along_line_classifier.conv[0].weight.grad.abs().sum() > 0
    readings, _ = model.location.readings(rollout.actions, rollout.points, data.n_probes)
    added = model.along_line_classifier(readings)
    with torch.no_grad():
        model.along_line_classifier.head[-1].weight.zero_()
        model.along_line_classifier.head[-1].bias.zero_()
    _, without = model.evaluate(rollout, batch["labels"])
    torch.testing.assert_close(logits - without, added)
    assert added[:, -1].abs().sum() > 0
    with pytest.raises(ValueError, match="model.along_line_classifier=true .* needs model.location: candidates"):
        HapticGlance(along_line_classifier=True)


def test_a_teacher_with_held_out_poses_or_no_warmup_is_refused(data, teacher, tmp_path):
    with np.load(teacher) as f:
        episodes = dict(f)
    episodes["poses"] = data.regions.sample("test", len(episodes["poses"]), np.random.default_rng(0))
    leaking = tmp_path / "leaking.npz"
    np.savez(leaking, **episodes)
    model = make_model(data, policy_warmup_steps=2, imitate=(str(leaking),))
    trainer = pl.Trainer(max_steps=2, logger=False, enable_checkpointing=False, enable_progress_bar=False,
                         enable_model_summary=False, limit_val_batches=0, accelerator="cpu")
    with pytest.raises(ValueError, match=f"{leaking}: 32 of 32 poses lie outside the training region"):
        trainer.fit(model, datamodule=data)
    other = make_model(data, policy_warmup_steps=2, imitate=(str(teacher),), location="candidates",
                       candidate_places=5)  # not the teacher's candidates
    with pytest.raises(ValueError, match=r"model.imitate=.*is not one of the 35 candidates \(model.candidate_places"):
        trainer.fit(other, datamodule=data)
    with pytest.raises(ValueError, match="model.imitate=.*needs model.policy: learned, model.policy_warmup_steps > 0"):
        HapticGlance(imitate=(str(teacher),))


def test_library_namer_reads_the_probes_as_the_planner_read_its_library_and_refuses_held_out_poses(data, teacher,
                                                                                                   tmp_path):
    """model.library_namer: the teacher file's library rebuilt in setup, each probe read as how far from its entry
    point it touched (what hg.sim.library.readings gives the same episode), its log posterior added to what
    validation and test score; a library of held-out poses is refused."""
    model = make_model(data, location="candidates", library_namer=str(teacher))
    trainer = pl.Trainer(logger=False, enable_checkpointing=False, enable_progress_bar=False,
                         enable_model_summary=False, accelerator="cpu")
    scored = trainer.validate(model, datamodule=data)[0]
    assert model.library_namer.library.shape == (77, 256) and 0 <= scored["val/acc"] <= 1
    assert 0 <= scored[f"val/acc_namer@{data.n_probes}"] <= 1  # the namer alone on the same probes, logged beside
    assert "library_namer.library" not in model.state_dict()  # rebuilt from its recipe, not checkpointed
    assert (model.library_namer.noise, model.library_namer.probe_length) == (data.noise, data.scene.probe_length)
    batch = first_batch(data)
    model.sim = data.make_simulator()
    rollout = model.rollout(batch["labels"], batch["poses"], 1)
    chosen = model.location.index_of(rollout.actions)
    every = torch.from_numpy(readings(model.sim, batch["labels"].numpy(), batch["poses"].numpy(),
                                      model.location.candidates.numpy()))
    read = every.gather(1, chosen)
    assert (read != MISS).any()
    torch.testing.assert_close(model.library_log_posterior(rollout), model.library_namer(chosen, read), atol=1e-3,
                               rtol=0)
    model.sim.close()
    with np.load(teacher) as f:
        episodes = dict(f)
    episodes["meta"] = np.array(json.dumps({**json.loads(str(episodes["meta"])), "library_split": "val"}))
    leaking = tmp_path / "leaking.npz"
    np.savez(leaking, **episodes)
    with pytest.raises(ValueError, match=f"model.library_namer: {leaking}: meta library_split='val', this model needs "
                                         "'train'"):
        trainer.validate(make_model(data, location="candidates", library_namer=str(leaking)), datamodule=data)
    episodes["meta"] = np.array(json.dumps({**json.loads(str(episodes["meta"])), "library_split": "train",
                                            "along_leans": [1.0]}))
    along = tmp_path / "along.npz"
    np.savez(along, **episodes)
    with pytest.raises(ValueError, match=r"meta along_leans=\[1.0\], this model needs \[\]"):
        trainer.validate(make_model(data, location="candidates", library_namer=str(along)), datamodule=data)
    # a larger library than the teacher's, drawn with its seed (library_namer_episodes)
    larger = make_model(data, location="candidates", library_namer=str(teacher), library_namer_episodes=512)
    trainer.validate(larger, datamodule=data)
    assert larger.library_namer.library.shape == (77, 512)
    with pytest.raises(ValueError, match="model.library_namer=.* needs model.location: candidates"):
        HapticGlance(library_namer=str(teacher))
    with pytest.raises(ValueError, match="model.library_namer_episodes=512: must be >= 1, and needs model.library_namer"):
        HapticGlance(location="candidates", library_namer_episodes=512)


def test_std_schedule_shrinks_the_policy_std_and_travels_with_the_checkpoint(data, tmp_path):
    model = make_model(data, prior="line_scan", std_final_scale=0.1)
    trainer = pl.Trainer(max_steps=4, logger=False, enable_checkpointing=False, enable_progress_bar=False,
                         enable_model_summary=False, limit_val_batches=0, accelerator="cpu")
    trainer.fit(model, datamodule=data)
    scale = 1 - 0.9 * 3 / 4  # the last of steps 0..3
    assert model.location.std_scale.item() == pytest.approx(scale)
    state = torch.randn(16, model.location.start.numel())
    _, sigma = model.location.distribution(state, torch.zeros(16, 4))
    assert sigma.max().item() <= model.hparams.std_max * scale + 1e-6
    path = tmp_path / "model.ckpt"
    trainer.save_checkpoint(path)
    assert HapticGlance.load_from_checkpoint(path, weights_only=False).location.std_scale.item() == pytest.approx(scale)
    older = torch.load(path, weights_only=False)  # a checkpoint from before the schedule: its std scale was 1
    del older["state_dict"]["location.std_scale"]
    torch.save(older, path)
    assert HapticGlance.load_from_checkpoint(path, weights_only=False).location.std_scale.item() == 1.0
    with pytest.raises(ValueError, match="model.std_final_scale=0"):
        HapticGlance(std_final_scale=0)
    endless = make_model(data, std_final_scale=0.5)
    with pytest.raises(ValueError, match="needs trainer.max_steps"):
        pl.Trainer(max_epochs=1, logger=False, enable_checkpointing=False, enable_progress_bar=False,
                   limit_val_batches=0, accelerator="cpu").fit(endless, datamodule=data)


def test_lr_schedule_falls_to_its_final_share_at_the_last_step(data):
    model = make_model(data, policy_lr_scale=0.3, lr_final_scale=0.1)
    trainer = pl.Trainer(max_steps=4, logger=False, enable_checkpointing=False, enable_progress_bar=False,
                         enable_model_summary=False, limit_val_batches=0, accelerator="cpu")
    trainer.fit(model, datamodule=data)
    rest, location = trainer.optimizers[0].param_groups
    assert rest["lr"] == pytest.approx(1e-3 * 0.1) and location["lr"] == pytest.approx(1e-3 * 0.3 * 0.1)
    steady = make_model(data)  # the default keeps the paper's constant rate
    assert isinstance(steady.configure_optimizers(), torch.optim.Adam)
    with pytest.raises(ValueError, match="model.lr_final_scale=0"):
        HapticGlance(lr_final_scale=0)
    with pytest.raises(ValueError, match="needs trainer.max_steps"):
        pl.Trainer(max_epochs=1, logger=False, enable_checkpointing=False, enable_progress_bar=False,
                   limit_val_batches=0, accelerator="cpu").fit(make_model(data, lr_final_scale=0.5), datamodule=data)


def test_weight_ema_scores_the_average_and_keeps_the_current_std_scale(data, tmp_path):
    class Record(pl.Callback):  # the live weights after each optimizer step
        def __init__(self):
            self.steps = []

        def on_train_batch_end(self, trainer, module, *args):
            self.steps.append([p.detach().clone() for p in module.parameters()])

    model, record = make_model(data, prior="line_scan", std_final_scale=0.1), Record()
    checkpoint = ModelCheckpoint(dirpath=tmp_path, every_n_train_steps=2, save_top_k=-1,
                                 filename="step{step}", auto_insert_metric_name=False)
    trainer = pl.Trainer(max_steps=3, logger=False, enable_progress_bar=False, enable_model_summary=False,
                         limit_val_batches=0, accelerator="cpu", callbacks=[WeightEMA(decay=0.5), record, checkpoint])
    trainer.fit(model, datamodule=data)
    first, second, third = record.steps
    average = [0.5 * (0.5 * a + 0.5 * b) + 0.5 * c for a, b, c in zip(first, second, third)]
    for name, (p, expected, live) in zip(dict(model.named_parameters()), zip(model.parameters(), average, third)):
        torch.testing.assert_close(p.detach(), expected, msg=f"{name} is not the moving average")
    assert any(not torch.equal(p, live) for p, live in zip(average, third))  # the average is not the live model
    assert model.location.std_scale.item() == pytest.approx(1 - 0.9 * 2 / 3)  # the schedule's, not averaged
    # testing a checkpoint after fit, as hg/lightning/experiment.py does, scores its average, not its live weights
    saved = torch.load(tmp_path / "step2.ckpt", weights_only=False)
    assert not torch.equal(saved["state_dict"]["classifier.net.0.weight"],
                           saved["current_model_state"]["classifier.net.0.weight"])
    model.sim = data.make_simulator()  # fit's teardown closed it
    trainer.test(model, datamodule=data, ckpt_path=tmp_path / "step2.ckpt", verbose=False,
                 weights_only=False)
    for name, p in model.state_dict().items():
        torch.testing.assert_close(p, saved["state_dict"][name], msg=f"{name}: tested weights are not the average")
    with pytest.raises(ValueError, match="WeightEMA decay=1"):
        WeightEMA(decay=1)


def test_policy_term_uses_detached_advantage():
    logits = torch.randn(5, 3, 4, requires_grad=True)
    labels = torch.randint(4, (5,))
    log_pi = torch.randn(5, 3, requires_grad=True)
    baseline = torch.randn(5, 3, requires_grad=True)
    terms = hybrid_loss(logits, labels, log_pi, baseline, gamma=0.9, beta=1.0)
    (grad_b,) = torch.autograd.grad(terms["loss_policy"], baseline, allow_unused=True)
    assert grad_b is None
    rewards = (logits.argmax(-1) == labels[:, None]).float()
    (grad_pi,) = torch.autograd.grad(terms["loss_policy"], log_pi)
    torch.testing.assert_close(grad_pi, -(discounted_returns(rewards, 0.9) - baseline.detach()) / log_pi.numel())


def test_rollout_is_a_function_of_the_batch_seed(data):
    model = make_model(data)
    batch = first_batch(data)
    first = model.rollout(batch["labels"], batch["poses"], 7)
    model.rollout(batch["labels"], batch["poses"], 8)  # other work in between changes nothing
    again = model.rollout(batch["labels"], batch["poses"], 7)
    torch.testing.assert_close(first.points, again.points)
    torch.testing.assert_close(first.actions, again.actions)
    mean_action = model.rollout(batch["labels"], batch["poses"], 7, deterministic=True)
    assert not torch.equal(first.actions, mean_action.actions)


@pytest.mark.parametrize("encoder, point_frame, reads_touch_set, mirror", [
    ("pcrn", "episode", False, False), ("pcrn", "first_touch", False, False), ("lstm", "episode", False, False),
    ("pcrn", "episode", True, False), ("pcrn", "episode", False, True), ("lstm", "episode", True, True)])
def test_log_prob_is_taken_under_the_policy_that_acted(data, encoder, point_frame, reads_touch_set, mirror):
    """The states rebuilt for the loss (whole sequences) must be those the rollout sampled from (one probe at a
    time): the mean-action rollout's requests are then exactly the means the loss pass computes (with
    mirror_encoder, in the view each state was read in)."""
    # the side-picking scan as prior, so that some episodes touch to -x and act in the mirrored view
    model = make_model(data, encoder=encoder, point_frame=point_frame, touch_set=reads_touch_set,
                       touch_set_net="wide", policy_reads_touch_set=reads_touch_set, mirror_encoder=mirror,
                       prior="line_scan", scan_side=0.6, scan_span=0.5, scan_order="centre_out")
    batch = first_batch(data)
    rollout = model.rollout(batch["labels"], batch["poses"], 1, deterministic=True)
    extra = model.touch_set.pooled(rollout.points) if reads_touch_set else None
    mirrored = model.mirrored_states(rollout.points)
    states = model.policy_states(model.encode(rollout), mirrored, extra)
    assert mirrored.any() == mirror
    offsets = reflect(model.prior_offsets(rollout.points), 1, where=mirrored)
    mu, _ = model.location.distribution(states, reflect(rollout.actions, 1, where=mirrored), offsets)
    torch.testing.assert_close(reflect(rollout.actions, 1, where=mirrored), mu)


def test_mirror_encoder_reads_an_episode_and_its_mirror_image_alike(data):
    """Mirrored across the line (X -> 2 line_x - X, Ux -> -Ux): the same answers and, in its own frame, the same
    policy wherever the probes so far touched something (before a touch no side is known, so no view is chosen)."""
    model = make_model(data, mirror_encoder=True, touch_set=True, touch_set_mirror=True)
    model.line_x = 0.03  # off the scene's line (0): the mirror must read where it is
    model.eval()  # no dropout
    batch = first_batch(data)
    rollout = model.rollout(batch["labels"], batch["poses"], 2)
    image = Rollout(reflect(rollout.actions, 1), reflect(rollout.requests, 1),
                    reflect(rollout.points, 0, model.line_x), rollout.reached)
    seen = (rollout.points[..., 3] > 0.5).cumsum(1) > 0  # (B, N): prefix k touched something
    assert seen.any() and (~seen).any()

    def read(r):
        _, logits = model.evaluate(r, batch["labels"])
        mirrored = model.mirrored_states(r.points)
        states = model.policy_states(model.encode(r), mirrored)
        return logits, model.location.distribution(states, reflect(r.actions, 1, where=mirrored))[0]

    (logits, mu), (image_logits, image_mu) = read(rollout), read(image)
    torch.testing.assert_close(logits[seen], image_logits[seen])
    state_seen = F.pad(seen[:, :-1], (1, 0), value=False)
    torch.testing.assert_close(mu[state_seen], image_mu[state_seen])
    assert not torch.allclose(logits[~seen], image_logits[~seen])  # the views differ: the mirror does the work
    plain = make_model(data, touch_set=True, touch_set_mirror=True)
    plain.line_x = 0.03
    plain.eval()
    assert not torch.allclose(plain.evaluate(rollout, batch["labels"])[1][seen],
                              plain.evaluate(image, batch["labels"])[1][seen])
    with pytest.raises(ValueError, match="mirror_encoder=true mirrors the episode frame"):
        HapticGlance(mirror_encoder=True, point_frame="first_touch")


def test_points_relative_to_first_touch():
    points = torch.tensor([[[1.0, 1.0, 1.0, 0.0], [2.0, 3.0, -1.0, 1.0], [5.0, 5.0, 5.0, 0.0], [3.0, 3.0, 0.0, 1.0]],
                           [[1.0, 2.0, 3.0, 0.0], [4.0, 5.0, 6.0, 0.0], [7.0, 8.0, 9.0, 0.0], [1.0, 1.0, 1.0, 0.0]]])
    out = relative_to_first_touch(points)
    expected = torch.tensor([[[1.0, 1.0, 1.0, 0.0], [0.0, 0.0, 0.0, 1.0], [3.0, 2.0, 6.0, 0.0], [1.0, 0.0, 1.0, 1.0]],
                             points[1].tolist()])
    torch.testing.assert_close(out, expected)  # before the first touch, and without any touch, nothing moves
    for k in range(1, 5):  # causal: a prefix gives the same rows
        torch.testing.assert_close(relative_to_first_touch(points[:, :k]), out[:, :k])
    with pytest.raises(ValueError, match="model.point_frame='touch'"):
        HapticGlance(point_frame="touch")


def test_classifier_none_scores_with_the_touch_set_alone(data):
    model = make_model(data, classifier="none", policy="line_scan", touch_set=True)
    batch = first_batch(data)
    rollout = model.rollout(batch["labels"], batch["poses"], int(batch["seed"]))
    terms, logits = model.evaluate(rollout, batch["labels"])
    assert model.classifier is None
    torch.testing.assert_close(logits, model.touch_set(rollout.points))
    terms["loss"].backward()
    assert any(p.grad is not None and p.grad.abs().sum() > 0 for p in model.touch_set.parameters())
    assert all(p.grad is None for p in model.encoder.parameters())  # PCRN takes no part
    for kwargs in ({"policy": "line_scan"}, {"policy": "learned", "touch_set": True}):
        with pytest.raises(ValueError, match="classifier='none'.*needs model.touch_set=true and a fixed policy"):
            make_model(data, classifier="none", **kwargs)


def test_ce_prefixes_last_scores_only_the_full_episode(data):
    model = make_model(data, policy="line_scan", ce_prefixes="last")
    batch = first_batch(data)
    rollout = model.rollout(batch["labels"], batch["poses"], int(batch["seed"]))
    terms, logits = model.evaluate(rollout, batch["labels"])
    torch.testing.assert_close(terms["loss"], F.cross_entropy(logits[:, -1], batch["labels"]))
    every = hybrid_loss(logits, batch["labels"], None, None, gamma=0.9, beta=1.0)["loss"]
    assert not torch.isclose(terms["loss"], every)  # the default scores every prefix
    with pytest.raises(ValueError, match="ce_prefixes='last' needs a fixed policy"):
        make_model(data, ce_prefixes="last")
    with pytest.raises(ValueError, match="model.ce_prefixes='first'"):
        make_model(data, policy="line_scan", ce_prefixes="first")


def test_final_touch_set_answers_after_the_last_probe_only(data):
    model = make_model(data, policy="line_scan", touch_set=True, final_touch_set=True)
    batch = first_batch(data)
    rollout = model.rollout(batch["labels"], batch["poses"], int(batch["seed"]))
    terms, logits = model.evaluate(rollout, batch["labels"])
    shared = model.classifier(model.encoder(rollout.requests, rollout.points)) + model.touch_set(rollout.points)
    torch.testing.assert_close(logits[:, :-1], shared[:, :-1])
    torch.testing.assert_close(logits[:, -1], model.final_touch_set(rollout.points)[:, -1])
    assert not torch.allclose(logits[:, -1], shared[:, -1])
    terms["loss"].backward()
    assert all(p.grad is not None and p.grad.abs().sum() > 0 for p in model.final_touch_set.parameters())


def test_touch_set_miss_frame_reaches_both_wide_touch_sets_and_needs_one():
    model = HapticGlance(policy="line_scan", touch_set=True, touch_set_net="wide", final_touch_set=True,
                         touch_set_miss_frame="line")
    assert model.touch_set.miss_frame == model.final_touch_set.miss_frame == "line"
    with pytest.raises(ValueError, match="touch_set_miss_frame='line': places the misses of a wide touch set"):
        HapticGlance(policy="line_scan", touch_set=True, touch_set_miss_frame="line")
    with pytest.raises(ValueError, match="model.touch_set_miss_frame='ray'"):
        HapticGlance(policy="line_scan", final_touch_set=True, touch_set_miss_frame="ray")


def test_touch_set_mirror_reaches_both_touch_sets_and_learns_where_the_line_is(data):
    model = make_model(data, policy="line_scan", touch_set=True, final_touch_set=True, touch_set_mirror=True)
    assert model.touch_set.mirror and model.final_touch_set.mirror
    model.sim = ProbeSimulator("hg4", batch_size=2, scene=Scene(probe_x=0.1), mode="ideal")
    assert model.touch_set.line_x == model.final_touch_set.line_x == pytest.approx(0.1 * model.hparams.point_scale)
    model.sim.close()
    with pytest.raises(ValueError, match="touch_set_mirror=true mirrors the touch sets' episodes"):
        HapticGlance(policy="line_scan", touch_set_mirror=True)


@pytest.mark.parametrize("policy", ["random", "line_scan"])
def test_ablation_policies(data, policy):
    model = make_model(data, policy=policy)
    batch = first_batch(data)
    rollout = model.rollout(batch["labels"], batch["poses"], 3)
    terms, logits = model.evaluate(rollout, batch["labels"])
    assert set(terms) == {"loss", "loss_ce", "reward", "acc"} and logits.shape == (8, 4, 4)
    if policy == "line_scan":
        torch.testing.assert_close(rollout.requests[0, :, 0], torch.linspace(-1, 1, 4))
        assert (rollout.requests[..., 3] == 1).all()
    else:
        assert rollout.requests[..., 0].std() > 0.3


def test_centre_out_scan_covers_the_middle_nearest_first():
    model = HapticGlance(n_probes=4, policy="line_scan", scan_span=0.5, scan_order="centre_out")
    torch.testing.assert_close(model.line_scan_requests()[:, 0], torch.tensor([-1 / 6, 1 / 6, -0.5, 0.5]))
    prior = HapticGlance(n_probes=4, prior="line_scan", scan_span=0.5, scan_order="centre_out")
    points = torch.rand(3, 4, 4)  # without scan_follow the scan ignores what it touched
    expected = torch.atanh(0.9 * model.line_scan_requests()).expand(3, -1, -1)
    torch.testing.assert_close(prior.prior_offsets(points), expected)
    fan = HapticGlance(n_probes=4, policy="line_scan", scan_span=0.5, scan_order="centre_out", scan_lean=0.4)
    expected = torch.tensor([[-1 / 6, 0.0, 1.0], [1 / 6, 1.0, 0.6], [-0.5, -1.0, 0.6], [0.5, 0.0, 1.0]])
    torch.testing.assert_close(fan.line_scan_requests()[:, [0, 1, 3]], expected)
    points, directions = Scene().request_to_probe(fan.line_scan_requests().double().numpy())
    tilt = np.degrees(np.arccos(-directions[:, 2]))
    np.testing.assert_allclose(tilt, [0.0, 11.31, 11.31, 0.0], atol=0.01)  # atan(tan(45 deg) * 0.4 / 2)
    assert directions[1, 0] > 0 > directions[2, 0]  # the fan leans to both sides of the line
    with pytest.raises(ValueError, match="model.scan_lean=3"):
        HapticGlance(scan_lean=3.0)
    with pytest.raises(ValueError, match="model.scan_span=0"):
        HapticGlance(scan_span=0.0)
    with pytest.raises(ValueError, match="model.scan_order='middle'"):
        HapticGlance(scan_order="middle")


def test_coarse_first_scan_spans_the_scan_in_its_first_half_then_fills_in():
    centre = HapticGlance(n_probes=10, policy="line_scan", scan_span=0.5, scan_order="centre_out")
    coarse = HapticGlance(n_probes=10, policy="line_scan", scan_span=0.5, scan_order="coarse_first")
    py_centre, py_coarse = centre.line_scan_requests()[:, 0], coarse.line_scan_requests()[:, 0]
    step = 1 / 9  # the grid over [-0.5, 0.5]
    torch.testing.assert_close(py_coarse[:5], torch.tensor([-0.5, 1.5, -2.5, 3.5, -4.5]) * step)
    torch.testing.assert_close(py_coarse.sort().values, py_centre.sort().values)  # the same probes after 10
    first = py_coarse[:5].sort().values
    assert first.diff().min() > 1.9 * step  # every second point of the grid
    assert first[-1] - first[0] > 1.8 * (py_centre[:5].max() - py_centre[:5].min())  # spans twice as far
    assert (py_coarse[5:].abs().diff() >= 0).all()  # the points between, nearest the centre first


def test_follow_scan_probes_around_the_touches_and_touches_more(data):
    model = make_model(data, policy="line_scan", scan_span=0.5, scan_order="centre_out", scan_follow=0.1)
    lo, hi = model.sim.scene.probe_y
    points = torch.zeros(2, 4, 4)  # episode 0 touches at probe 2 (y = 0.1 m) and 3 (y = 0.2 m); episode 1 never
    points[0, 1], points[0, 2] = torch.tensor([0.0, 0.1, -0.2, 1.0]), torch.tensor([0.0, 0.2, -0.2, 1.0])
    points[..., :3] *= model.hparams.point_scale
    requests = model.scan_requests(points)
    to_py = lambda y: (y - lo) / (0.5 * (hi - lo)) - 1  # noqa: E731
    # request 3 follows the first touch one step up; request 4 goes one step down from the mean of both touches
    torch.testing.assert_close(requests[0, :, 0], torch.tensor([-1 / 6, 1 / 6, to_py(0.1) + 0.1, to_py(0.15) - 0.1]))
    torch.testing.assert_close(requests[1], model.line_scan_requests())  # nothing touched: the plain scan
    causal = points.clone()
    causal[:, 3] = torch.tensor([0.0, 0.3, -0.2, 1.0])  # what the last probe returns cannot move any request
    torch.testing.assert_close(model.scan_requests(causal), requests)
    model.hparams.scan_lean = 0.4  # the fan: probe 2 leans to +x, probe 3 to -x; follow-ups keep probe 2's lean
    torch.testing.assert_close(model.scan_requests(points)[0, 2:, 1:], torch.tensor([[1.0, 0.0, 0.6]]).expand(2, 3))
    model.hparams.scan_lean = 0.0
    # on real ray casts, following the first touch collects more touches than walking on past the object
    batch = first_batch(data)
    touches = {}
    for follow in (0.0, 0.05):
        model.hparams.scan_follow = follow
        touches[follow] = model.rollout(batch["labels"], batch["poses"], 0).points[..., 3].sum()
    assert touches[0.05] > touches[0.0] > 0
    model.sim.close()
    with pytest.raises(ValueError, match="model.scan_follow=2"):
        HapticGlance(scan_follow=2.0)


def test_follow_scan_limited_to_k_probes_then_goes_on_where_it_stopped(data):
    model = make_model(data, policy="line_scan", scan_span=0.5, scan_order="centre_out", scan_follow=0.1,
                       scan_follow_probes=1)
    lo, hi = model.sim.scene.probe_y
    points = torch.zeros(2, 4, 4)  # episode 0 touches at its first probe (y = 0.1 m) and at its third; 1 never
    points[0, 0], points[0, 2] = torch.tensor([0.0, 0.1, -0.2, 1.0]), torch.tensor([0.0, 0.3, -0.2, 1.0])
    points[..., :3] *= model.hparams.point_scale
    requests = model.scan_requests(points)
    scan = model.line_scan_requests()
    to_py = lambda y: (y - lo) / (0.5 * (hi - lo)) - 1  # noqa: E731
    # one follow-up one step up from the touch, then the scan's 2nd and 3rd places (its last is dropped), even
    # after the later touch
    torch.testing.assert_close(requests[0, :, 0], torch.stack([scan[0, 0], torch.tensor(to_py(0.1) + 0.1),
                                                               scan[1, 0], scan[2, 0]]))
    torch.testing.assert_close(requests[1], scan)  # nothing touched: the plain scan
    causal = points.clone()
    causal[:, 3] = torch.tensor([0.0, 0.5, -0.2, 1.0])  # what the last probe returns cannot move any request
    torch.testing.assert_close(model.scan_requests(causal), requests)
    model.sim.close()
    with pytest.raises(ValueError, match="model.scan_follow_probes=4: must be in"):
        HapticGlance(n_probes=4, scan_follow=0.1, scan_follow_probes=4)
    with pytest.raises(ValueError, match="model.scan_follow_probes=1: .* needs model.scan_follow"):
        HapticGlance(scan_follow_probes=1)


def test_cross_scan_leans_both_ways_at_its_first_touch_then_goes_on(data):
    model = make_model(data, policy="line_scan", scan_span=0.5, scan_order="centre_out", scan_cross=1.0)
    points = torch.zeros(2, 4, 4)  # episode 0 first touches at probe 1; episode 1 never touches
    points[0, 0, 3] = points[0, 2, 3] = 1.0
    requests = model.scan_requests(points)
    scan = model.line_scan_requests()
    lean = lambda side: torch.tensor([scan[0, 0], side, 0.0, 0.0])  # noqa: E731  uz = 1 - scan_cross
    torch.testing.assert_close(requests[0], torch.stack([scan[0], lean(1.0), lean(-1.0), scan[1]]))
    torch.testing.assert_close(requests[1], scan)  # nothing touched: the plain scan
    causal = points.clone()
    causal[:, 3, 3] = 1.0  # what the last probe returns cannot move any request
    torch.testing.assert_close(model.scan_requests(causal), requests)
    # on real ray casts: every episode touched before its last two probes leans both ways right after its first touch
    batch = first_batch(data)
    rollout = model.rollout(batch["labels"], batch["poses"], 0)
    touched = rollout.points[..., 3] > 0.5
    first = touched.float().argmax(1)
    checked = [i for i in range(len(first)) if touched[i].any() and first[i] + 2 < model.hparams.n_probes]
    assert checked
    for i in checked:
        assert rollout.requests[i, first[i] + 1, 1] == 1.0 and rollout.requests[i, first[i] + 2, 1] == -1.0
    model.sim.close()
    with pytest.raises(ValueError, match="model.scan_cross=3"):
        HapticGlance(scan_cross=3.0)
    with pytest.raises(ValueError, match="choose one way"):
        HapticGlance(scan_cross=1.0, scan_follow=0.05)


def test_reach_scan_leans_while_it_touches_nothing_then_keeps_the_touching_direction(data):
    model = HapticGlance(n_probes=6, policy="line_scan", scan_span=0.5, scan_order="centre_out", scan_reach=0.6)
    points = torch.zeros(3, 6, 4)  # episode 0 first touches at probe 4 (leaning to -x), 1 never, 2 at probe 2
    points[0, 3, 3] = points[0, 4, 3] = points[2, 1, 3] = 1.0
    requests = model.scan_requests(points)
    torch.testing.assert_close(requests[..., 0], model.line_scan_requests()[:, 0].expand(3, -1))  # same places
    torch.testing.assert_close(requests[..., 1], torch.tensor([[0.0, 0, 1, -1, -1, -1], [0, 0, 1, -1, 1, -1],
                                                              [0, 0, 0, 0, 0, 0]]))
    torch.testing.assert_close(requests[..., 3], torch.where(requests[..., 1] == 0, 1.0, 0.4))
    causal = points.clone()
    causal[:, 5, 3] = 1.0  # what the last probe returns cannot move any request
    torch.testing.assert_close(model.scan_requests(causal), requests)
    model = make_model(data, policy="line_scan", scan_span=0.5, scan_order="centre_out", scan_reach=0.6)
    batch = first_batch(data)  # on real ray casts (4 probes: the first goes straight down)
    rollout = model.rollout(batch["labels"], batch["poses"], 0)
    touched = rollout.points[..., 3] > 0.5
    for i in range(len(touched)):
        first = int(touched[i].float().argmax()) if touched[i].any() else 4
        lean = [0.0] + [1.0 if min(k, first) % 2 else -1.0 if min(k, first) else 0.0 for k in range(1, 4)]
        assert rollout.requests[i, :, 1].tolist() == lean
    model.sim.close()
    with pytest.raises(ValueError, match="model.scan_reach=3"):
        HapticGlance(scan_reach=3.0)
    with pytest.raises(ValueError, match="choose one way"):
        HapticGlance(scan_reach=1.0, scan_lean=0.4)


def test_prior_lean_lets_a_small_ux_tilt_the_prior_s_straight_probes():
    scan = dict(n_probes=4, prior="line_scan", scan_span=0.5, scan_order="centre_out", scan_lean=0.4)
    plain, room = HapticGlance(**scan), HapticGlance(**scan, prior_lean=1.0)
    points = torch.zeros(2, 4, 4)
    a, b = plain.prior_offsets(points), room.prior_offsets(points)
    straight = plain.line_scan_requests()[:, 1] == 0
    torch.testing.assert_close(b[..., :3], a[..., :3])
    assert (b[:, straight, 3] == 0).all() and (b[:, ~straight, 3] == a[:, ~straight, 3]).all()  # uz 0; fan kept

    def tilt(offsets: torch.Tensor, ux: float) -> np.ndarray:
        requests = torch.tanh(offsets[0]).double()
        requests[:, 1] += ux * straight
        return np.degrees(np.arccos(-Scene().request_to_probe(requests.numpy())[1][:, 2]))[straight.numpy()]

    np.testing.assert_allclose(tilt(b, 0.0), 0.0, atol=1e-6)  # the same straight probes
    np.testing.assert_allclose(tilt(a, 0.1), np.degrees(np.arctan(0.1 * 0.1 / 2)), atol=1e-3)  # uz = 0.9: 0.3 deg
    np.testing.assert_allclose(tilt(b, 0.1), np.degrees(np.arctan(0.1 / 2)), atol=1e-3)  # uz = 0: 2.9 deg
    with pytest.raises(ValueError, match="model.prior_lean=2"):
        HapticGlance(prior="line_scan", prior_lean=2.0)
    with pytest.raises(ValueError, match="needs model.prior: line_scan"):
        HapticGlance(prior_lean=1.0)


def test_prior_exact_starts_the_mean_policy_on_the_scan_it_warmed_up_behind(data):
    scan = dict(prior="line_scan", scan_span=0.5, scan_order="centre_out")
    batch = first_batch(data)
    requests = {}
    for exact in (False, True):
        model = make_model(data, **scan, prior_exact=exact)
        requests[exact] = model.rollout(batch["labels"], batch["poses"], 0, deterministic=True).requests
        model.sim.close()
    expected = model.scan_requests(torch.zeros(len(batch["labels"]), data.n_probes, 4))
    # the same straight probes at the same places (uz 0.9 stays inside tanh's range; with ux = uy = 0 it is moot)
    torch.testing.assert_close(requests[True][..., :3], expected[..., :3])
    torch.testing.assert_close(requests[True][..., 3], torch.full_like(expected[..., 3], 0.9))
    # without it the mean starts off the scan: Py shrunk by 0.9 and moved by the untrained head
    assert (requests[False][..., 0] - expected[..., 0]).abs().max() > 0.005
    with pytest.raises(ValueError, match="model.prior_exact=True: needs model.prior: line_scan"):
        HapticGlance(prior_exact=True)


def test_prior_anchor_charges_the_mean_policy_for_leaving_its_prior(data):
    model = make_model(data, prior="line_scan", scan_span=0.5, scan_order="centre_out", prior_exact=True,
                       prior_anchor=2.0)
    batch = first_batch(data)
    rollout = model.rollout(batch["labels"], batch["poses"], 0)
    model.sim.close()
    assert model.evaluate(rollout, batch["labels"])[0]["prior_shift"] == 0  # on its prior: nothing to charge
    with torch.no_grad():
        model.location.net[-1].bias[0] += 0.3  # the mean moves Py off the scan
    losses, pulls = {}, {}
    for weight in (2.0, 0.0):
        model.hparams.prior_anchor = weight
        terms, _ = model.evaluate(rollout, batch["labels"])
        model.zero_grad()
        terms["loss"].backward()
        losses[weight], pulls[weight] = terms["loss"].detach(), model.location.net[-1].bias.grad[0].item()
    assert terms["prior_shift"] > 0.01
    torch.testing.assert_close(losses[2.0] - losses[0.0], 2.0 * terms["prior_shift"])
    assert pulls[2.0] - pulls[0.0] > 0  # a gradient step pulls the mean back towards the scan
    model.hparams.prior_anchor, model.hparams.prior_anchor_free = 2.0, ("py",)  # Py left to the policy
    free, _ = model.evaluate(rollout, batch["labels"])
    torch.testing.assert_close(free["loss"].detach(), losses[0.0])  # only Py moved: nothing left to charge
    torch.testing.assert_close(free["prior_shift"], terms["prior_shift"])  # the shift is still reported whole
    with pytest.raises(ValueError, match="model.prior_anchor=1.0: needs model.prior: line_scan"):
        HapticGlance(prior_anchor=1.0)
    with pytest.raises(ValueError, match="model.prior_anchor=-1.0: must be >= 0"):
        HapticGlance(prior="line_scan", prior_anchor=-1.0)
    with pytest.raises(ValueError, match=r"model.prior_anchor_free=\['ux'\]: .* needs model.prior_anchor > 0"):
        HapticGlance(prior="line_scan", prior_anchor_free=("ux",))
    with pytest.raises(ValueError, match=r"model.prior_anchor_free: \['lean'\] not among"):
        HapticGlance(prior="line_scan", prior_anchor=1.0, prior_anchor_free=("lean",))


def test_mean_action_share_probes_some_episodes_with_the_mean_and_trains_the_policy_on_the_others(data):
    model = make_model(data, mean_action_share=0.5)
    batch = first_batch(data)
    labels, half = batch["labels"], len(batch["labels"]) // 2
    mean_rows = torch.arange(len(labels)) < half
    mixed, mean, sampled = (model.rollout(labels, batch["poses"], 0, deterministic=d) for d in (mean_rows, True, False))
    model.sim.close()
    torch.testing.assert_close(mixed.actions[:half], mean.actions[:half])
    torch.testing.assert_close(mixed.actions[half:], sampled.actions[half:])  # the same draws as without the share
    assert not torch.equal(mean.actions[half:], sampled.actions[half:])
    torch.manual_seed(0)
    logits, log_pi, baseline = torch.randn(len(labels), 10, 4), torch.randn(len(labels), 10), torch.rand(len(labels), 10)
    both = hybrid_loss(logits, labels, log_pi, baseline, 0.9, 1.0, sampled=~mean_rows)
    only = hybrid_loss(logits[half:], labels[half:], log_pi[half:], baseline[half:], 0.9, 1.0)
    full = hybrid_loss(logits, labels, log_pi, baseline, 0.9, 1.0)
    torch.testing.assert_close(both["loss_policy"], only["loss_policy"])  # the policy learns from sampled episodes
    torch.testing.assert_close(both["loss_baseline"], only["loss_baseline"])
    torch.testing.assert_close(both["loss_ce"], full["loss_ce"])  # the classifier from every episode
    with pytest.raises(ValueError, match="model.mean_action_share=1.0: must be in"):
        HapticGlance(mean_action_share=1.0)


def test_side_scan_leans_both_ways_first_then_to_the_side_its_touches_show(data):
    model = HapticGlance(n_probes=6, policy="line_scan", scan_span=0.5, scan_order="centre_out", scan_side=0.6)
    points = torch.zeros(4, 6, 4)  # 0: both first probes touch, -x higher; 1: only -x; 2: nothing; 3: probe 4 (-x)
    points[0, 0, 3] = points[0, 1, 3] = points[1, 1, 3] = points[3, 3, 3] = 1.0
    points[0, 0, 2], points[0, 1, 2] = -0.5, -0.4
    requests = model.scan_requests(points)
    places = model.line_scan_requests()[:, 0]
    torch.testing.assert_close(requests[..., 0], places[[0, 0, 1, 2, 3, 4]].expand(4, -1))  # first place twice
    torch.testing.assert_close(requests[..., 1], torch.tensor([[1.0, -1, -1, -1, -1, -1], [1, -1, -1, -1, -1, -1],
                                                              [1, -1, 1, -1, 1, -1], [1, -1, 1, -1, -1, -1]]))
    assert (requests[..., 3] == 0.4).all() and (requests[..., 2] == 0).all()
    higher = points.clone()
    higher[0, 0, 2] = -0.3  # now the +x probe touched higher: the object lies to +x
    assert model.scan_requests(higher)[0, 2:, 1].tolist() == [1.0] * 4
    causal = points.clone()
    causal[:, 5, 3] = 1.0  # what the last probe returns cannot move any request
    torch.testing.assert_close(model.scan_requests(causal), requests)
    model = make_model(data, policy="line_scan", scan_span=0.5, scan_order="centre_out", scan_side=0.6)
    batch = first_batch(data)  # on real ray casts: every probe leans 16.7 degrees, to one side from the third on
    rollout = model.rollout(batch["labels"], batch["poses"], 0)
    model.sim.close()
    assert (rollout.requests[:, :2, 1] == torch.tensor([1.0, -1.0])).all() and (rollout.requests[..., 1] != 0).all()
    steep = HapticGlance(n_probes=6, policy="line_scan", scan_span=0.5, scan_order="centre_out", scan_side=0.6,
                         scan_side_first=1.0)  # a steeper first pair that alone picks the side, the same places
    steep_requests = steep.scan_requests(points)
    torch.testing.assert_close(steep_requests[:2, :, :3], requests[:2, :, :3])  # the pair touched: as before
    assert (steep_requests[:, :2, 3] == 0.0).all() and (steep_requests[:2, 2:, 3] == 0.4).all()
    assert (steep_requests[2:, 2:, 1] == 0).all() and (steep_requests[2:, 2:, 3] == 1.0).all()  # else straight
    apart = HapticGlance(n_probes=6, policy="line_scan", scan_span=0.5, scan_order="centre_out", scan_side=0.6,
                         scan_side_pair_apart=True)  # the pair at the scan's first two places: every place once
    apart_requests = apart.scan_requests(points)
    torch.testing.assert_close(apart_requests[..., 0], places.expand(4, -1))
    torch.testing.assert_close(apart_requests[..., 1:], requests[..., 1:])  # the same leans and sides
    with pytest.raises(ValueError, match="model.scan_side_pair_apart=True: .* needs model.scan_side > 0"):
        HapticGlance(scan_side_pair_apart=True)
    with pytest.raises(ValueError, match="model.scan_side=3"):
        HapticGlance(scan_side=3.0)
    with pytest.raises(ValueError, match="model.scan_side_first=1.0: .* needs model.scan_side > 0"):
        HapticGlance(scan_side_first=1.0)
    with pytest.raises(ValueError, match="n_probes >= 2"):
        HapticGlance(scan_side=0.6, n_probes=1)
    with pytest.raises(ValueError, match="choose one way"):
        HapticGlance(scan_side=0.6, scan_reach=1.0)


def test_eval_sets_are_fixed_and_disjoint_from_training():
    one = ProbeDataModule(mode="ideal", val_episodes=40, test_episodes=40, eval_batch_size=16, seed=1)
    two = ProbeDataModule(mode="ideal", val_episodes=40, test_episodes=40, eval_batch_size=16, seed=2)
    for a, b in zip(one.test_dataloader(), two.test_dataloader()):
        torch.testing.assert_close(a["poses"], b["poses"])  # the training seed never changes the test set
    train = next(iter(one.train_dataloader()))
    assert (one.regions.split_of(train["poses"].numpy()) == 0).all()
    assert (one.regions.split_of(next(iter(one.test_dataloader()))["poses"].numpy()) == 2).all()


# -- the CLI, end to end in subprocesses ---------------------------------------------------------------
def hg(*args, cwd):
    env = {**os.environ, "WANDB_MODE": "offline", "WANDB_SILENT": "true"}
    proc = subprocess.run([sys.executable, "-m", "hg.lightning.cli", *args], cwd=cwd, env=env,
                          capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-3000:]
    return proc


def latest_csv(folder):
    files = sorted(Path(folder).glob("runs/wandb/offline-run-*/files/per_probe_accuracy.csv"),
                   key=lambda p: p.stat().st_mtime)
    return list(csv.reader(files[-1].open()))


def test_fit_then_test_from_checkpoint(tmp_path):
    hg("fit", "--config", TINY, cwd=tmp_path)
    checkpoints = list(tmp_path.glob("runs/haptic-glance/*/checkpoints/last.ckpt"))
    assert len(checkpoints) == 1
    runs = list(tmp_path.glob("runs/wandb/offline-run-*"))
    assert len(runs) == 1 and (runs[0] / "files" / "config.yaml").is_file()
    assert list(runs[0].glob("*.wandb"))
    curve = list(csv.reader((runs[0] / "files" / "val_curve.csv").open()))  # one row per validation: steps 2, 4
    assert curve[0][:2] == ["step", "stochastic@1"] and len(curve[0]) == 1 + 2 * 4
    assert [row[0] for row in curve[1:]] == ["2", "4"] and all(0 <= float(v) <= 1 for v in curve[1][1:])
    hg("test", "--config", TINY, "--ckpt_path", str(checkpoints[0]), cwd=tmp_path)
    first = latest_csv(tmp_path)
    hg("test", "--config", TINY, "--ckpt_path", str(checkpoints[0]), cwd=tmp_path)
    assert latest_csv(tmp_path) == first
    assert first[0] == ["probes", "stochastic", "mean_action"] and len(first) == 1 + 4


def test_scoring_a_checkpoint_trains_nothing_and_gives_what_its_run_gave(tmp_path, monkeypatch):
    """fit_and_test with a checkpoint (reproduce_table1's rows that score another row's runs): no training; the
    checkpoint's validation and test accuracy, as the run that trained it measured them."""
    from hg.lightning.experiment import fit_and_test

    monkeypatch.setenv("WANDB_MODE", "disabled")
    kwargs = {"eval_seed": 0, "test_episodes": 32}
    trained = fit_and_test(Path(TINY), 0, tmp_path / "trained", **kwargs)
    best = ROOT / trained["best_checkpoint"]  # (relative to the repository when inside it)
    scored = fit_and_test(Path(TINY), 0, tmp_path / "scored", checkpoint=best, **kwargs)
    assert trained["train_wall_s"] > 0 and scored["train_wall_s"] == 0.0
    # run again in its folder: it resumes from last.ckpt at its last step, trains nothing more, and still reports
    # the time its steps took (TrainingClock's total rides in the checkpoint), not the empty attempt's
    again = fit_and_test(Path(TINY), 0, tmp_path / "trained", **kwargs)
    assert again["resumed_from_step"] == trained["max_steps"] and again["accuracy"] == trained["accuracy"]
    saved = torch.load(tmp_path / "trained" / "checkpoints" / "last.ckpt", weights_only=False)["callbacks"]
    # (the checkpoint is written before the attempt ends, so it holds a little less than the attempt's total; how much
    # less depends on the machine's load, so only the order is asserted)
    assert 0 < saved["TrainingClock"]["seconds"] <= trained["train_wall_s"] + 0.05  # (train_wall_s is rounded to 0.1)
    assert again["train_wall_s"] >= saved["TrainingClock"]["seconds"] - 0.05
    # asked to resume it as another run (another discount here; another teacher or sensor alike): refused, untouched
    last = tmp_path / "trained" / "checkpoints" / "last.ckpt"
    before = last.read_bytes()
    with pytest.raises(ValueError, match=r"last.ckpt: trained with model.gamma=0.9\d* \(now 0.5\).*Move .*trained away"):
        fit_and_test(Path(TINY), 0, tmp_path / "trained", extra_args=["--model.gamma", "0.5"], **kwargs)
    assert last.read_bytes() == before
    assert not (tmp_path / "scored" / "checkpoints").exists()
    assert scored["accuracy"] == trained["accuracy"] and scored["best_val_acc"] == trained["best_val_acc"]
    assert scored["best_checkpoint"] == trained["best_checkpoint"]
    with pytest.raises(FileNotFoundError, match="nope.ckpt: the checkpoint to score is missing"):
        fit_and_test(Path(TINY), 0, tmp_path / "none", checkpoint=tmp_path / "nope.ckpt", **kwargs)


def test_same_seed_same_training(tmp_path):
    for _ in range(2):  # the second fit in the same folder must work too
        hg("fit", "--config", TINY, "--seed_everything", "5", cwd=tmp_path)
    states = [torch.load(p, weights_only=False)["state_dict"]
              for p in sorted(tmp_path.glob("runs/haptic-glance/*/checkpoints/last.ckpt"))]
    assert len(states) == 2 and states[0].keys() == states[1].keys()
    for key in states[0]:
        torch.testing.assert_close(states[0][key], states[1][key])


def test_log_gain_rewards_add_up_to_the_final_log_probability():
    logits = torch.randn(6, 5, 4)
    labels = torch.randint(4, (6,))
    terms = hybrid_loss(logits, labels, None, None, gamma=1.0, beta=1.0, reward="log_gain")
    final = logits[:, -1].log_softmax(-1).gather(-1, labels[:, None]).squeeze(-1)
    torch.testing.assert_close(terms["reward"] * 5, (final + torch.log(torch.tensor(4.0))).mean())


def test_non_finite_policy_output_is_reported_with_its_step(data):
    model = make_model(data)
    with torch.no_grad():
        model.location.start.fill_(float("nan"))
    batch = first_batch(data)
    with pytest.raises(FloatingPointError, match=r"probe 1, global step 0"):
        model.rollout(batch["labels"], batch["poses"], 0)


def test_random_probe_episodes_are_probed_where_drawn_and_train_the_classifiers_only(data):
    """model.random_probe_share: the last episodes of a training batch are probed with distinct candidates drawn
    at random, the others as the policy alone would; the policy term leaves the random ones out."""
    model = make_model(data, location="candidates", candidate_places=3, candidate_leans=(1.0,),
                       choice_reads_probes=True, random_probe_share=0.25)
    batch = first_batch(data)
    rows = torch.arange(8) >= 6
    requests = model.random_candidates(rows, int(batch["seed"]))
    assert requests[:6].isnan().all() and requests[6:].isfinite().all()
    index = model.location.index_of(requests[6:])
    assert all(len(set(row.tolist())) == data.n_probes for row in index)  # distinct
    mixed = model.rollout(batch["labels"], batch["poses"], int(batch["seed"]), requests=requests)
    alone = model.rollout(batch["labels"], batch["poses"], int(batch["seed"]))
    torch.testing.assert_close(mixed.actions[6:], requests[6:])
    torch.testing.assert_close(mixed.actions[:6], alone.actions[:6])  # the policy's episodes are untouched
    assert not torch.equal(mixed.actions[6:], alone.actions[6:])
    # the policy term over the sampled episodes only: changing a random episode's reward changes nothing
    terms, _ = model.evaluate(mixed, batch["labels"], sampled=~rows)
    other = batch["labels"].clone()
    other[7] = (other[7] + 1) % data.n_classes
    terms_other, _ = model.evaluate(mixed, other, sampled=~rows)
    assert terms["loss_policy"].item() == pytest.approx(terms_other["loss_policy"].item())
    assert terms["loss_ce"].item() != pytest.approx(terms_other["loss_ce"].item())
    trainer = pl.Trainer(max_steps=2, logger=False, enable_checkpointing=False, enable_progress_bar=False,
                         enable_model_summary=False, limit_val_batches=0, accelerator="cpu")
    trainer.fit(model, datamodule=data)  # a training step with random episodes runs
    with pytest.raises(ValueError, match="model.random_probe_share=0.5 probes with candidates drawn at random"):
        HapticGlance(random_probe_share=0.5)
    with pytest.raises(ValueError, match="model.random_probe_share=0.6: must be in"):
        HapticGlance(location="candidates", random_probe_share=0.6, mean_action_share=0.5)
