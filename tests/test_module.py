"""The composed model through Lightning's CLI: every experiment config and Table 1 row fits and tests at smoke size
(configs/parts/tiny.yaml last), its components are the ones its configs name, the schedules, refusals of compositions
that cannot work, and what each loss term reaches, on real rollouts (ideal mode)."""
import copy
import csv
import json
import os
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import pytorch_lightning as pl
import torch
import torch.nn.functional as F
import yaml
from torch import nn

from hg.lightning import HapticGlance, ProbeDataModule
from hg.lightning.callbacks import GradientDiagnostics
from hg.lightning.cli import cli
from hg.nets import PCRN, FCClassifier, TouchSetClassifier
from hg.policies import CandidateChoice, GaussianPolicy, LineScan, SidePickingScan
from hg.rl import ExploreAroundPrior, FollowPrior, ImitateBestProbe, Rollout
from hg.rl.rollout import probe_points
from hg.sim import ProbeSimulator, Scene

ROOT = Path(__file__).resolve().parents[1]
CONFIGS = ROOT / "configs"
TEACHERS = [str(ROOT / "data" / "planner" / "across_line" / f"hg4_train65k_s{s}.npz") for s in (10, 20)]
QUIET = ["--trainer.logger", "false", "--trainer.enable_progress_bar", "false", "--trainer.enable_model_summary",
         "false"]

# every kept composition: each experiment config alone and the rows of Table 1 (README), as reproduce_table1 runs them
ROWS = {
    "pcrn_fc": ["pcrn_fc.yaml"],
    "pcrn_nclass": ["pcrn_nclass.yaml"],
    "lstm": ["lstm.yaml"],
    "random": ["random.yaml"],
    "line_scan": ["line_scan.yaml"],
    "side_scan": ["side_scan.yaml"],
    "gaussian_on_side_scan": ["gaussian_on_side_scan.yaml"],
    "planner_copy": ["planner_copy.yaml"],
    "side_scan_row": ["side_scan.yaml", "parts/touch_sets.yaml", "parts/long.yaml"],
    "gaussian_row": ["gaussian_on_side_scan.yaml", "parts/stable_rl.yaml", "parts/touch_sets.yaml", "parts/long.yaml"],
    "planner_copy_row": ["planner_copy.yaml", "parts/stable_rl.yaml", "parts/touch_sets.yaml", "parts/long.yaml"],
    "planner_copy_library_row": ["planner_copy.yaml", "parts/stable_rl.yaml", "parts/touch_sets.yaml",
                                 "parts/long.yaml", "parts/library_classifier.yaml"],
    "quickstart": ["gaussian_on_side_scan.yaml", "parts/stable_rl.yaml", "parts/touch_sets.yaml",
                   "parts/quickstart.yaml"],
    "pcrn_nclass_repaired": ["pcrn_nclass.yaml", "parts/centred_points.yaml", "parts/new_touch.yaml"],
    "choice_on_side_scan": ["side_scan.yaml", "parts/choice_on_scan.yaml", "parts/stable_rl.yaml",
                            "parts/touch_sets.yaml"],
    "exploring_choice_on_side_scan": ["side_scan.yaml", "parts/choice_on_scan.yaml", "parts/explore_copy.yaml",
                                      "parts/stable_rl.yaml", "parts/touch_sets.yaml"],
    "best_probe_choice": ["side_scan.yaml", "parts/choice_on_scan.yaml", "parts/best_probe.yaml",
                          "parts/stable_rl.yaml", "parts/touch_sets.yaml"],
}
# what each config sets, as the configs compose: a later one overrides an earlier one (set_by)
POLICY = {"pcrn_fc.yaml": "GaussianPolicy", "pcrn_nclass.yaml": "GaussianPolicy", "lstm.yaml": "GaussianPolicy",
          "random.yaml": "RandomProbes", "line_scan.yaml": "LineScan", "side_scan.yaml": "SidePickingScan",
          "gaussian_on_side_scan.yaml": "GaussianPolicy", "planner_copy.yaml": "CandidateChoice",
          "parts/choice_on_scan.yaml": "CandidateChoice"}
WARMUP = {"gaussian_on_side_scan.yaml": "FollowPrior", "planner_copy.yaml": "ImitateTeacher",
          "parts/choice_on_scan.yaml": "FollowPrior", "parts/explore_copy.yaml": "ExploreAroundPrior",
          "parts/best_probe.yaml": "ImitateBestProbe"}
IMITATES = {"gaussian_on_side_scan.yaml": False, "planner_copy.yaml": True,  # the warm-up copies a teacher or a scan
            "parts/choice_on_scan.yaml": True, "parts/explore_copy.yaml": True, "parts/best_probe.yaml": True}
PRIOR = {"gaussian_on_side_scan.yaml": "SidePickingScan", "parts/choice_on_scan.yaml": "SidePickingScan",
         "parts/best_probe.yaml": None}  # None: the part removes the scan
COMPARE_WITH = {"parts/best_probe.yaml": "SidePickingScan"}  # the scan the policy no longer starts on
HEAD = {"pcrn_nclass.yaml": "NClassClassifier", "lstm.yaml": "LinearClassifier"}
ENCODER = {"lstm.yaml": "LSTMEncoder", "parts/centred_points.yaml": "CentredPCRN"}
N_PROBES = {"planner_copy.yaml": 10}  # its teachers' probes (args_of); tiny.yaml's 4 otherwise
STD_FINAL = {"gaussian_on_side_scan.yaml": 0.1, "planner_copy.yaml": 0.1}


def set_by(parts: list[str], setting: dict, default=None):
    """What the composition's configs set, the last of them that sets it winning, as in the CLI."""
    return next((setting[part] for part in reversed(parts) if part in setting), default)


def args_of(parts: list[str], *extra: str) -> list[str]:
    """The configs of a composition, smoke-sized (tiny last), with what a tiny run of it needs: the planner's
    teachers have 10 probes, and a warm-up of 2 of the 4 steps leaves 2 for the policy to learn in."""
    args = [a for part in [*parts, "parts/tiny.yaml"] for a in ("--config", str(CONFIGS / part))]
    if set_by(parts, WARMUP) == "ImitateTeacher":
        args += ["--data.n_probes", str(set_by(parts, N_PROBES)), "--model.warmup.init_args.teachers",
                 json.dumps(TEACHERS)]
    if set_by(parts, WARMUP):
        args += ["--model.warmup.init_args.steps", "2"]
    if "parts/library_classifier.yaml" in parts:
        args += ["--model.library_classifier.teacher", TEACHERS[0], "--model.library_classifier.episodes", "64"]
    return [*args, *QUIET, *extra]


def test_the_side_scan_is_the_same_wherever_a_config_names_it():
    """The scan a choice starts on (prior) and the one a choice from no scan is compared with (compare_with) are
    configs/side_scan.yaml's, written out again in each part: an edit to one must reach the others."""
    def model(part: str) -> dict:
        return yaml.safe_load((CONFIGS / part).read_text())["model"]

    scan = model("side_scan.yaml")["policy"]
    assert scan["class_path"] == "hg.policies.SidePickingScan"
    assert model("parts/choice_on_scan.yaml")["policy"]["init_args"]["prior"] == scan
    assert model("parts/best_probe.yaml")["compare_with"] == scan
    assert model("gaussian_on_side_scan.yaml")["policy"]["init_args"]["prior"] == scan


def test_every_config_file_is_in_a_tested_composition():
    shipped = {str(p.relative_to(CONFIGS)) for p in CONFIGS.rglob("*.yaml")}
    assert shipped - {"parts/tiny.yaml"} == {part for parts in ROWS.values() for part in parts}


@pytest.mark.parametrize("row", list(ROWS))
def test_composition_fits_and_tests_through_the_cli(row, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)  # nothing may be written beside the run's own folder
    parts, root = ROWS[row], tmp_path / "run"
    fit = cli(["fit", *args_of(parts, "--trainer.default_root_dir", str(root))])
    model, trainer = fit.model, fit.trainer
    # the components are the ones the configs name
    touch_sets = "parts/touch_sets.yaml" in parts
    n_probes = set_by(parts, N_PROBES, 4)
    repaired = "parts/new_touch.yaml" in parts
    assert type(model.encoder).__name__ == set_by(parts, ENCODER, "PCRN")
    if repaired:
        assert model.policy.reads_detached and model.policy.count_width == n_probes
    assert type(model.policy).__name__ == set_by(parts, POLICY)
    assert type(getattr(model.policy, "prior", None)).__name__ == (set_by(parts, PRIOR) or "NoneType")
    assert type(model.compare_with).__name__ == set_by(parts, COMPARE_WITH, "NoneType")
    heads = [type(h).__name__ for h in model.heads]
    assert heads == ([set_by(parts, HEAD, "FCClassifier")] + ["TouchSetClassifier"] * 2 * touch_sets)
    if touch_sets:
        assert [(h.mirror, h.last_only) for h in model.heads[1:]] == [(True, False), (True, True)]
    assert model.hparams.n_probes == n_probes == fit.datamodule.n_probes
    assert type(model.warmup).__name__ == set_by(parts, WARMUP, "NoneType")
    assert getattr(model.warmup, "imitate", False) == set_by(parts, IMITATES, False)
    stable = "parts/stable_rl.yaml" in parts
    assert (model.loss.reward, model.loss.normalize_advantage) == (("log_gain", True) if stable else
                                                                  ("new_touch" if repaired else "correct", False))
    assert model.hparams.policy_lr_scale == (0.3 if stable else 1.0)
    assert trainer.gradient_clip_val == (1.0 if stable else None)
    lr_final = 0.05 if {"parts/long.yaml", "parts/quickstart.yaml"} & set(parts) else 1.0
    callbacks = {type(c).__name__: c for c in trainer.callbacks}
    assert callbacks["CosineLR"].final_scale == lr_final
    assert callbacks["StdDecay"].final_scale == set_by(parts, STD_FINAL, 1.0)
    # it trained: 4 steps (tiny.yaml overrides the long schedules), validated at 2 and 4, saved what it resumes from
    assert trainer.global_step == 4 and (root / "checkpoints" / "last.ckpt").is_file()
    assert [row[0] for row in csv.reader((root / "val_curve.csv").open())] == ["step", "2", "4"]
    logged = trainer.callback_metrics
    if model.policy.learned:  # the policy learned by REINFORCE after any warm-up; the copy imitated before it
        assert torch.isfinite(logged["train/loss_policy"])
        assert ("train/loss_imitation" in logged) == set_by(parts, IMITATES, False)
    else:
        assert "train/loss_policy" not in logged
    if "parts/library_classifier.yaml" in parts:  # 64 training episodes, moved along the line and mirrored
        episodes = model.library.classifier.library
        assert episodes.shape[0] == 77 and 64 <= episodes.shape[1] <= 64 * 11 * 2
        assert not any(key.startswith("library") for key in model.state_dict())  # rebuilt, never checkpointed
    saved = yaml.safe_load((root / "config.yaml").read_text())
    assert saved["model"]["policy"]["class_path"] == f"hg.policies.{type(model.policy).__name__}"
    # a checkpoint rebuilds the composed model without its configs
    loaded = HapticGlance.load_from_checkpoint(root / "checkpoints" / "last.ckpt", map_location="cpu")
    assert type(loaded.policy) is type(model.policy)
    assert [type(h) for h in loaded.heads] == [type(h) for h in model.heads]
    for key, value in model.state_dict().items():
        torch.testing.assert_close(loaded.state_dict()[key], value, msg=key)
    # hg test of the last checkpoint: single-rollout accuracy after each probe, for the heads, the mean-action
    # policy of a learned one, the same heads behind a learned policy's prior scan or the scan it is compared with,
    # and the library classifier alone and mixed with the heads
    test = cli(["test", *args_of(parts, "--trainer.default_root_dir", str(root)),
                "--ckpt_path", str(root / "checkpoints" / "last.ckpt")])
    library = "parts/library_classifier.yaml" in parts
    on_prior = model.policy.learned and (set_by(parts, PRIOR) or set_by(parts, COMPARE_WITH)) is not None
    rollouts = ["stochastic", *["mean_action"] * model.policy.learned, *["prior"] * on_prior]
    columns = [*rollouts, *(f"{r}_{who}" for who in ("library", "mixed") for r in rollouts if library)]
    table = list(csv.reader((root / "per_probe_accuracy.csv").open()))
    assert table[0] == ["probes", *columns] and len(table) == 1 + n_probes
    assert all(0 <= float(v) <= 1 for line in table[1:] for v in line[1:])
    metrics = test.trainer.callback_metrics
    for who in ["", *(["_library", "_mixed"] if library else [])]:
        for suffix in ["", *["_mean_action"] * model.policy.learned, *["_prior"] * on_prior]:
            assert all(0 <= metrics[f"test/acc{who}{suffix}@{k}"] <= 1 for k in range(1, n_probes + 1))
    assert sorted(p.name for p in tmp_path.iterdir()) == ["run"]


@pytest.mark.parametrize("row, components", [
    ("gaussian_row", ["hg.nets.PCRN", "hg.policies.GaussianPolicy", "hg.policies.SidePickingScan", "hg.rl.FollowPrior",
                      "hg.nets.FCClassifier", "hg.nets.TouchSetClassifier"]),
    ("planner_copy_library_row", ["hg.nets.PCRN", "hg.policies.CandidateChoice", "hg.rl.ImitateTeacher",
                                  "hg.nets.FCClassifier", "hg.nets.TouchSetClassifier"]),
])
def test_print_config_shows_the_injected_components(row, components, capsys):
    with pytest.raises(SystemExit) as done:
        cli(["fit", *args_of(ROWS[row]), "--print_config"])
    assert done.value.code in (0, None)
    config = yaml.safe_load(capsys.readouterr().out)
    model = config["model"]
    paths = [model["encoder"]["class_path"], model["policy"]["class_path"], *(
        [model["policy"]["init_args"]["prior"]["class_path"]] if model["policy"]["init_args"].get("prior") else []),
        model["warmup"]["class_path"], *(h["class_path"] for h in model["heads"])]
    assert sorted(set(paths)) == sorted(components)
    assert model["loss"]["reward"] == "log_gain"
    assert config["trainer"]["max_steps"] == 4  # tiny.yaml, last, wins over long.yaml


class Schedules(pl.Callback):
    """The policy's std scale and the learning rates each training step used."""

    def __init__(self) -> None:
        self.std, self.lr = [], []

    def on_before_optimizer_step(self, trainer, module, optimizer) -> None:
        self.std.append(float(module.policy.std_scale))
        self.lr.append([group["lr"] for group in optimizer.param_groups])


def schedules(tmp_path, steps: int, warmup: int) -> Schedules:
    run = cli(args_of(ROWS["gaussian_row"], "--trainer.default_root_dir", str(tmp_path), "--trainer.max_steps",
                      str(steps), "--trainer.val_check_interval", str(steps), "--model.warmup.init_args.steps",
                      str(warmup), "--std_decay.final_scale", "0.1", "--lr_decay.final_scale", "0.05"), run=False)
    record = Schedules()
    run.trainer.callbacks.append(record)
    run.trainer.fit(run.model, datamodule=run.datamodule)
    path = tmp_path / "checkpoints" / "last.ckpt"
    assert HapticGlance.load_from_checkpoint(path).policy.std_scale.item() == pytest.approx(record.std[-1])
    return record


def test_std_and_lr_schedules_fall_from_the_policys_start_to_the_last_step(tmp_path):
    """The std stays 1 through the warm-up, then falls linearly; every learning rate falls along a half cosine
    from the first step, the policy's kept at policy_lr_scale (0.3, stable_rl.yaml) of the rest's; both travel with
    the checkpoint."""
    record = schedules(tmp_path, 6, 2)
    assert record.std[:3] == [1.0, 1.0, 1.0]  # the warm-up, then the first learning step at full std
    falls = np.diff(record.std[2:])
    assert (falls < 0).all() and np.allclose(falls, falls[0])
    rest, policy = np.array(record.lr).T
    np.testing.assert_allclose(policy, 0.3 * rest)
    factor = 0.05 + 0.95 * 0.5 * (1 + np.cos(np.pi * np.arange(6) / 5))
    np.testing.assert_allclose(rest, 1e-3 * factor)


def test_std_and_lr_schedules_reach_their_final_scale_at_the_last_step(tmp_path):
    record = schedules(tmp_path, 6, 2)
    assert record.std[-1] == pytest.approx(0.1)
    assert record.lr[-1][0] == pytest.approx(1e-3 * 0.05)


def test_schedules_need_an_end(tmp_path):
    with pytest.raises(ValueError, match="std_decay.final_scale needs trainer.max_steps"):
        cli(["fit", *args_of(ROWS["gaussian_row"], "--trainer.max_steps", "-1", "--trainer.max_epochs", "1",
                             "--trainer.default_root_dir", str(tmp_path))])
    with pytest.raises(ValueError, match="std_decay.final_scale=0"):
        cli(args_of(ROWS["gaussian_row"], "--std_decay.final_scale", "0"), run=False)
    with pytest.raises(ValueError, match="lr_decay.final_scale=2"):
        cli(args_of(ROWS["pcrn_fc"], "--lr_decay.final_scale", "2"), run=False)


def test_the_touch_reward_trains_through_a_warm_up_and_pays_the_contacts(tmp_path):
    """#57's diagnostic reward: the imitation warm-up (no policy term) and the hybrid rule after it both run, and
    the logged reward is the share of probes that touched."""
    fit = cli(["fit", *args_of(ROWS["planner_copy"], "--model.loss.reward", "touch", "--trainer.default_root_dir",
                               str(tmp_path))])
    assert fit.trainer.global_step == 4
    logged = fit.trainer.callback_metrics
    assert 0.0 <= float(logged["train/reward"]) <= 1.0 and torch.isfinite(logged["train/loss_policy"])


@pytest.mark.parametrize("row, args, message", [
    ("pcrn_fc", ["--model.warmup", "hg.rl.FollowPrior", "--model.warmup.init_args.steps", "2"],
     "model.warmup: FollowPrior probes with the policy's prior scan; GaussianPolicy has none"),
    ("pcrn_fc", ["--model.policy.init_args.anchor", "1.0"], "GaussianPolicy: anchor=1.0: .*needs a prior scan"),
    ("side_scan", ["--model.warmup", "hg.rl.FollowPrior", "--model.warmup.init_args.steps", "2"],
     r"model.warmup: a fixed policy \(SidePickingScan\) has nothing to warm up"),
    ("side_scan", ["--model.heads", json.dumps([{"class_path": "hg.nets.TouchSetClassifier",
                                                 "init_args": {"last_only": True}}])],
     "every head scores the last probe only"),
    ("side_scan", ["--model.heads", "[]"], "model.heads: give at least one classifier head"),
    ("choice_on_side_scan", ["--model.warmup.init_args.imitate", "false"],
     r"model.policy.init_args.prior: CandidateChoice starts on its prior scan only by copying it"),
    ("choice_on_side_scan", ["--model.warmup", "null"], r"model.policy.init_args.prior: CandidateChoice starts on"),
    ("side_scan", ["--model.compare_with", "hg.policies.LineScan"],
     r"model.compare_with: the policy \(SidePickingScan\) is a fixed one itself"),
    ("choice_on_side_scan", ["--model.compare_with", "hg.policies.LineScan"],
     r"model.compare_with: the policy is compared with its prior scan \(SidePickingScan"),
    ("gaussian_on_side_scan", ["--model.warmup", "hg.rl.ExploreAroundPrior"],
     r"model.warmup: ExploreAroundPrior draws its detours among the policy's candidates; GaussianPolicy has none"),
    ("exploring_choice_on_side_scan", ["--model.warmup.init_args.explore", "0"], r"warmup.explore=0.0: .* \(0, 1\]"),
    pytest.param("pcrn_fc", ["--config", str(CONFIGS / "parts" / "library_classifier.yaml"),
                             "--model.library_classifier.teacher", TEACHERS[0]], "model.library_classifier",
                 ),
])
def test_a_composition_that_cannot_work_is_refused_naming_the_field(row, args, message):
    try:
        cli(args_of(ROWS[row], *args), run=False)
    except ValueError as error:
        assert re.search(message, str(error)), str(error)
    else:
        raise AssertionError(f"{row} {args} was built")


def test_a_teacher_of_other_candidates_or_a_library_of_held_out_poses_is_refused(tmp_path):
    """The copy's candidates must be its teacher's; the library classifier's episodes must be training poses."""
    with pytest.raises(ValueError, match=r"model.warmup.teachers=.*is not one of the 35 candidates.*the policy's "
                                         "places, span and leans must be the teacher's"):
        cli(["fit", *args_of(ROWS["planner_copy"], "--model.policy.init_args.places", "5",
                             "--trainer.default_root_dir", str(tmp_path))])
    with np.load(TEACHERS[0]) as f:
        episodes = dict(f)
    episodes["meta"] = np.array(json.dumps({**json.loads(str(episodes["meta"])), "library_split": "val"}))
    leaking = tmp_path / "leaking.npz"
    np.savez(leaking, **episodes)
    with pytest.raises(ValueError, match=f"model.library_classifier: {leaking}: meta library_split='val', this "
                                         "model needs 'train'"):
        cli(["validate", *args_of(ROWS["planner_copy_library_row"], "--model.library_classifier.teacher",
                                  str(leaking), "--trainer.default_root_dir", str(tmp_path))])


# -- the module in process: what each loss term trains, warm-ups, heads ---------------------------------------------
@pytest.fixture(scope="module")
def data():
    return ProbeDataModule(mode="ideal", batch_size=8, eval_batch_size=8, val_episodes=8, test_episodes=8, n_probes=4)


def make_model(data, policy=None, heads=None, **kwargs) -> HapticGlance:
    torch.manual_seed(0)
    model = HapticGlance(PCRN(width=16, out_dim=32), policy or (lambda dims: GaussianPolicy(dims, hidden=32)),
                         heads or [lambda dims: FCClassifier(dims, hidden=32)], n_probes=data.n_probes,
                         n_classes=data.n_classes, **kwargs)
    model.attach(data.make_simulator())
    return model


def first_batch(data):
    return next(iter(data.train_dataloader()))


def reaches(model, loss) -> dict[str, bool]:
    model.zero_grad()
    loss.backward(retain_graph=True)
    return {name: any(p.grad is not None and p.grad.abs().sum() > 0 for p in part.parameters())
            for name, part in (("encoder", model.encoder), ("heads", model.heads),
                               ("location", model.policy.location), ("baseline", model.policy.baseline))}


def test_each_term_of_the_hybrid_rule_trains_what_it_should(data):
    model = make_model(data, heads=[lambda d: FCClassifier(d, hidden=32), lambda d: TouchSetClassifier(d)])
    batch = first_batch(data)
    rollout = model.roll(batch["labels"], batch["poses"], int(batch["seed"]))
    terms, _ = model.evaluate(rollout, batch["labels"], "reinforce", int(batch["seed"]))
    assert reaches(model, terms["loss_policy"]) == {"encoder": True, "heads": False, "location": True,
                                                    "baseline": False}
    assert reaches(model, terms["loss_ce"]) == {"encoder": True, "heads": True, "location": False, "baseline": False}
    assert reaches(model, terms["loss_baseline"]) == {"encoder": False, "heads": False, "location": False,
                                                      "baseline": True}
    # a fixed policy's, or a warm-up's
    classify, _ = model.evaluate(rollout, batch["labels"], "classify", int(batch["seed"]))
    assert "loss_policy" not in classify and torch.equal(classify["loss"], classify["loss_ce"])
    imitate, _ = model.evaluate(rollout, batch["labels"], "imitate", int(batch["seed"]))
    assert "loss_policy" not in imitate
    torch.testing.assert_close(imitate["loss"], imitate["loss_ce"] + imitate["loss_imitation"])
    model.sim.close()


def test_warmup_trains_the_classifiers_behind_the_prior_scan_and_leaves_the_policy_alone(data):
    """FollowPrior(2): the first 2 training steps probe with the untrained prior scan and train the heads only; the
    policy learns by REINFORCE from the third on."""
    model = make_model(data, policy=lambda dims: GaussianPolicy(dims, hidden=32, prior=LineScan),
                       warmup=FollowPrior(2))
    rolled, roll = [], model.roll
    model.roll = lambda *args, **kwargs: rolled.append(roll(*args, **kwargs)) or rolled[-1]  # kept, not replaced
    states = []

    class Keep(pl.Callback):
        def on_train_batch_end(self, trainer, module, *args):
            states.append(copy.deepcopy(module.state_dict()))

    before = copy.deepcopy(model.state_dict())
    trainer = pl.Trainer(max_steps=3, logger=False, enable_checkpointing=False, enable_progress_bar=False,
                         enable_model_summary=False, limit_val_batches=0, accelerator="cpu", callbacks=[Keep()])
    trainer.fit(model, datamodule=data)
    scan = torch.stack([torch.linspace(-1, 1, 4), torch.zeros(4), torch.zeros(4), torch.ones(4)], -1)
    assert len(rolled) == 3
    for warming in rolled[:2]:
        torch.testing.assert_close(warming.requests, scan.expand_as(warming.requests))
    assert not torch.allclose(rolled[2].requests, scan.expand_as(rolled[2].requests))  # the policy's own draws

    def moved(a, b, prefix):
        return any(not torch.equal(a[k], b[k]) for k in a if k.startswith(prefix))

    for earlier, later in zip([before, *states[:1]], states[:2]):
        assert moved(earlier, later, "heads.") and not moved(earlier, later, "policy.location.")
    assert moved(states[1], states[2], "policy.location.")


def test_an_exploring_copy_probes_off_the_scan_and_copies_what_the_scan_would_ask(data):
    """ExploreAroundPrior: some probes are candidates the scan did not ask for, never one probed already; the choice
    learns to ask for the scan's request after what was really probed, except where that request was probed already
    (a choice never probes twice)."""
    warmup = ExploreAroundPrior(2, explore=0.5)
    scan = lambda dims: SidePickingScan(dims, span=0.5, lean=0.6, first_lean=1.0)  # noqa: E731
    model = make_model(data, policy=lambda dims: CandidateChoice(dims, places=None, leans=(0.6, 1.0), hidden=32,
                                                                 prior=scan), warmup=warmup)
    batch = first_batch(data)
    rollout = model.roll(batch["labels"], batch["poses"], int(batch["seed"]), policy=warmup.prober(model.policy))
    wanted = model.policy.prior.requests(rollout.points)
    index = model.policy.location.index_of(rollout.actions)  # every request is a candidate (or this refuses)
    detour = (rollout.actions - wanted).abs().amax(-1) > 1e-6
    assert 0 < detour.sum() < detour.numel()
    earlier = torch.ones(4, 4, dtype=torch.bool).tril(-1)
    probed_before = ((index[:, :, None] == index[:, None, :]) & earlier).any(-1)
    assert not probed_before[detour].any()
    # the targets are the scan's requests after the rollout's points; one the rollout sent earlier is left out
    rollout.actions[:, 0] = wanted[:, 2]  # what the scan asks for third, sent first: its third is not copied
    imitation = warmup.targets(model, rollout, batch["labels"], int(batch["seed"]))
    valid = imitation.valid
    assert torch.equal(imitation.requests, wanted) and not valid[:, 2].any() and valid[:, 0].all()
    # the copy's cross-entropy: the scan's requests in the states the detours led to
    terms, _ = model.evaluate(rollout, batch["labels"], "imitate", int(batch["seed"]))
    rep = model.encoder(rollout.requests, rollout.points)
    log_pi = model.policy.evaluate(rep, rollout.actions, rollout.points, chosen=wanted).log_pi
    torch.testing.assert_close(terms["loss_imitation"], -log_pi[valid].mean())
    assert torch.isfinite(terms["loss"]) and reaches(model, terms["loss_imitation"])["location"]
    assert all(torch.isfinite(p.grad).all() for p in model.policy.location.parameters())  # -inf left out, no NaN
    # a choice even over the candidates it may take pays log(how many) at each copied probe
    sent = model.policy.location.index_of(rollout.actions).tolist()  # of 4 places x (straight, 2 leans each way)
    last = model.policy.location.net[-1]
    with torch.no_grad():
        last.weight.zero_(), last.bias.zero_()
    terms, _ = model.evaluate(rollout, batch["labels"], "imitate", int(batch["seed"]))
    choices = torch.tensor([[float(20 - len(set(row[:k]))) for k in range(4)] for row in sent])
    torch.testing.assert_close(terms["loss_imitation"], choices.log()[valid].mean())
    model.sim.close()


def test_the_best_probe_warmup_teaches_the_candidate_the_heads_read_best_at_one_probe(data):
    """ImitateBestProbe: at one probe k per step (any of them, by the seed) the target is, of the sent request and
    the candidates not probed before, the one after which the heads read log p(true class) highest, read after the
    rollout's probes 1..k as the whole rollout reads its row k; the choice's cross-entropy there is its imitation
    term, which reaches the location network; and the rollout that follows is untouched by its probes."""
    warmup = ImitateBestProbe(2, samples=100)  # more than the candidates (20): every one is compared
    heads = [lambda dims: FCClassifier(dims, hidden=32),  # and one that reads whole episodes only
             lambda dims: TouchSetClassifier(dims, shared=(16, 32), hidden=32, last_only=True)]
    model = make_model(data, policy=lambda dims: CandidateChoice(dims, places=None, leans=(0.6, 1.0), hidden=32),
                       heads=heads, warmup=warmup)
    location, candidates = model.policy.location, model.policy.candidates
    batch = first_batch(data)
    labels, poses, seed = batch["labels"], batch["poses"], int(batch["seed"])
    rollout = model.roll(labels, poses, seed, policy=warmup.prober(model.policy))
    with torch.no_grad():
        whole = model.predict(rollout)[0].log_softmax(-1).gather(-1, labels[:, None, None].expand(-1, 4, 1))[..., 0]

    def read_after(k, requests):  # log p(true class) after probes 1..k and these requests (B, 4)
        actions = torch.cat([rollout.actions[:, :k], requests[:, None]], 1)
        points = torch.stack([probe_points(model.sim, actions[:, j], model.hparams.point_scale)[0]
                              for j in range(k + 1)], 1)
        with torch.no_grad():
            logits = model.predict(Rollout(actions, actions, points, torch.ones(8, k + 1, dtype=torch.bool)))[0]
        return logits[:, k].log_softmax(-1).gather(1, labels[:, None]).squeeze(1)

    seen = set()
    for draw in range(12):
        imitation = warmup.targets(model, rollout, labels, draw)
        k = int(imitation.valid[0].nonzero())
        seen.add(k)
        assert imitation.valid.sum(1).eq(1).all() and imitation.valid[:, k].all()
        index, probed = location.index_of(imitation.requests[:, k]), location.index_of(rollout.actions[:, :k])
        assert not (probed == index[:, None]).any()  # never a candidate probed before
        torch.testing.assert_close(read_after(k, rollout.actions[:, k]), whole[:, k])  # a branch reads as the whole
        readings = torch.stack([read_after(k, candidate.expand(8, 4)) for candidate in candidates], 1)
        readings[torch.arange(8)[:, None], probed] = -float("inf")  # the ones it may not ask for
        torch.testing.assert_close(read_after(k, imitation.requests[:, k]), readings.max(1).values)
        assert imitation.among[:, k].sum(1).eq(len(candidates) - k).all()  # the sent one and all not probed before
        assert not imitation.among[torch.arange(8)[:, None], k, probed].any()
    assert seen == {0, 1, 2, 3}  # the last probe too, where the head of whole episodes reads
    repeat = warmup.targets(model, rollout, labels, draw)  # the same seed, the same draws
    assert torch.equal(repeat.requests, imitation.requests) and torch.equal(repeat.valid, imitation.valid)
    again = model.roll(labels, poses, seed, policy=warmup.prober(model.policy))
    assert torch.equal(again.points, rollout.points) and torch.equal(again.actions, rollout.actions)
    terms, _ = model.evaluate(again, labels, "imitate", draw)
    rep = model.encoder(again.requests, again.points)
    log_pi = model.policy.evaluate(rep, again.actions, again.points, chosen=imitation.requests).log_pi
    torch.testing.assert_close(terms["loss_imitation"], -log_pi[:, k].mean())
    assert reaches(model, terms["loss_imitation"])["location"]
    # comparing 2 drawn candidates with the sent one, the choice is copied among those 3
    few = ImitateBestProbe(2, samples=2).targets(model, again, labels, draw)
    sent = location.index_of(again.actions[:, k])
    assert few.among[:, k].sum(1).eq(3).all() and few.among[torch.arange(8), k, sent].all()
    assert few.among[:, :k].all() and few.among[:, k + 1:].all()  # the probes not copied are not restricted
    model.warmup = ImitateBestProbe(2, samples=2)
    terms, _ = model.evaluate(again, labels, "imitate", draw)
    full = model.policy.evaluate(rep, again.actions, again.points, chosen=few.requests).log_pi[:, k]
    each = torch.stack([model.policy.evaluate(rep, again.actions, again.points, chosen=c.expand(8, 4, 4)).log_pi[:, k]
                        for c in candidates], 1)  # every candidate's log pi at probe k, in the same state
    restricted = full - each.masked_fill(~few.among[:, k], -torch.inf).logsumexp(1)
    torch.testing.assert_close(terms["loss_imitation"], -restricted.mean())
    model.sim.reset(((labels + 1) % data.n_classes).numpy(), poses.numpy())
    with pytest.raises(RuntimeError, match="model.sim no longer holds the rollout's episodes"):
        warmup.targets(model, again, labels, draw)
    with pytest.raises(ValueError, match="warmup.samples=0"):
        ImitateBestProbe(2, samples=0)
    with pytest.raises(ValueError, match="ImitateBestProbe compares the policy's candidates; GaussianPolicy"):
        make_model(data, warmup=ImitateBestProbe(2))
    gaussian = make_model(data)
    with pytest.raises(ValueError, match="`among` restricts a choice among candidates; a Gaussian has none"):
        gaussian.policy.evaluate(rep, again.actions, again.points, among=few.among)
    gaussian.sim.close()
    model.sim.close()


class TouchCount(nn.Module):
    """A head whose prediction follows what the probes found (how many touched, modulo the classes), untrained: the
    accuracy it gives differs between two policies' probes, unlike an untrained network's, which names one class."""

    last_only = False

    def __init__(self, dims) -> None:
        super().__init__()
        self.n_classes = dims.n_classes

    def forward(self, rep, points):
        return F.one_hot(points[..., 3].cumsum(1).long() % self.n_classes, self.n_classes).float()


def test_a_policy_on_a_prior_scan_is_also_scored_behind_the_scan(data):
    """Validation scores a learned policy started on a prior scan twice with the same heads: behind its own probes
    (acc) and behind the scan's (acc_prior), the comparison that says what its learned probes buy; a policy without
    a prior is scored behind its own probes only, unless given a scan to compare with (model.compare_with)."""
    trainer = pl.Trainer(logger=False, enable_checkpointing=False, enable_progress_bar=False,
                         enable_model_summary=False, accelerator="cpu")
    on_scan = make_model(data, policy=lambda dims: GaussianPolicy(dims, hidden=32, prior=LineScan), heads=[TouchCount])
    data.setup("validate")
    assert len(data.val_dataloader()) == 1  # one batch: the logged figures are this batch's
    batch = next(iter(data.val_dataloader()))
    labels, poses, seed = batch["labels"], batch["poses"], int(batch["seed"])

    def accuracy(rolled) -> list[float]:
        return (on_scan.predict(rolled)[0].argmax(-1) == labels[:, None]).float().mean(0).tolist()

    rolled = on_scan.roll(labels, poses, seed)
    own, behind_scan = accuracy(rolled), accuracy(on_scan.roll(labels, poses, seed, policy=on_scan.policy.prior))
    assert own != behind_scan
    handed = []

    class Outputs(pl.Callback):  # what callbacks such as ProbeMaps get: the policy's own rollouts, not the scan's
        def on_validation_batch_end(self, trainer, module, outputs, *args):
            handed.append(outputs)

    trainer.callbacks.append(Outputs())
    logged = trainer.validate(on_scan, datamodule=data, verbose=False)[0]
    assert [logged[f"val/acc@{k + 1}"] for k in range(4)] == pytest.approx(own)
    assert [logged[f"val/acc_prior@{k + 1}"] for k in range(4)] == pytest.approx(behind_scan)
    assert sorted(handed[0]) == [False, True]
    torch.testing.assert_close(handed[0][False][0].requests, rolled.requests)
    plain = trainer.validate(make_model(data), datamodule=data, verbose=False)[0]
    assert "val/acc@4" in plain and not any(k.startswith("val/acc_prior") for k in plain)
    # a policy from no scan is compared with the scan it is given (model.compare_with), the same way
    compared = make_model(data, heads=[TouchCount], compare_with=LineScan)
    assert compared.reference_scan is compared.compare_with and compared.policy.prior is None
    behind_given = (compared.predict(compared.roll(labels, poses, seed, policy=compared.compare_with))[0].argmax(-1)
                    == labels[:, None]).float().mean(0).tolist()
    assert behind_given == pytest.approx(behind_scan)  # the same scan and heads: the same reading
    logged = trainer.validate(compared, datamodule=data, verbose=False)[0]
    assert [logged[f"val/acc_prior@{k + 1}"] for k in range(4)] == pytest.approx(behind_given)


def test_a_curve_begun_by_code_that_scored_fewer_columns_is_continued(tmp_path):
    """A run resumed by newer code that scores more columns (acc_prior) keeps its learning curve: the earlier rows
    stay, blank in the new columns, and the new ones follow."""
    root = tmp_path / "run"
    root.mkdir()
    old = ["step", *(f"{label}@{k}" for label in ("stochastic", "mean_action") for k in range(1, 5))]
    (root / "val_curve.csv").write_text(",".join(old) + "\n" + ",".join(["1", *["0.5"] * 8]) + "\n")
    cli(["fit", *args_of(ROWS["gaussian_on_side_scan"], "--trainer.default_root_dir", str(root))])
    curve = list(csv.reader((root / "val_curve.csv").open()))
    assert curve[0] == [*old, *(f"prior@{k}" for k in range(1, 5))]
    assert [row[0] for row in curve[1:]] == ["1", "2", "4"]
    assert curve[1][1:] == ["0.5"] * 8 + [""] * 4 and all(v != "" for v in curve[2][1:])

def test_imitation_warmup_probes_the_teachers_episodes_and_copies_them(tmp_path):
    """ImitateTeacher(2): the first steps probe the teacher's episodes in turn with its requests, the policy learning
    to copy them; then the policy probes by itself."""
    run = cli(args_of(ROWS["planner_copy"], "--trainer.max_steps", "3", "--trainer.limit_val_batches", "0",
                      "--trainer.default_root_dir", str(tmp_path)), run=False)
    model, data = run.model, run.datamodule
    rolled, roll = [], model.roll
    model.roll = lambda *args, **kwargs: rolled.append((args, kwargs, roll(*args, **kwargs))) or rolled[-1][2]
    run.trainer.fit(model, datamodule=data)
    teacher = data.load_teacher(TEACHERS)
    assert torch.equal(model.warmup.teacher["requests"], teacher["requests"])  # loaded in setup
    size = data.hparams.batch_size
    for step, (args, kwargs, rollout) in enumerate(rolled[:2]):
        rows = torch.arange(step * size, (step + 1) * size)
        assert torch.equal(args[0], teacher["labels"][rows]) and torch.equal(args[1], teacher["poses"][rows])
        torch.testing.assert_close(rollout.requests, teacher["requests"][rows].clamp(-1, 1))
    _, kwargs, own = rolled[2]
    assert kwargs.get("requests") is None
    model.policy.location.index_of(own.requests)  # its own choices, among its candidates
    assert "train/loss_imitation" in run.trainer.callback_metrics


def test_a_non_finite_loss_stops_training_naming_its_step(data):
    model = make_model(data)
    with torch.no_grad():
        model.heads[0].net[-1].bias.fill_(float("nan"))
    trainer = pl.Trainer(max_steps=2, logger=False, enable_checkpointing=False, enable_progress_bar=False,
                         enable_model_summary=False, limit_val_batches=0, accelerator="cpu")
    with pytest.raises(FloatingPointError, match="non-finite loss nan at global step 0"):
        trainer.fit(model, datamodule=data)


def test_touch_sets_add_up_and_the_last_only_one_replaces_the_last_prediction(data):
    model = make_model(data, policy=LineScan, heads=[lambda d: FCClassifier(d, hidden=32),
                                                     lambda d: TouchSetClassifier(d, mirror=True),
                                                     lambda d: TouchSetClassifier(d, mirror=True, last_only=True)])
    batch = first_batch(data)
    rollout = model.roll(batch["labels"], batch["poses"], int(batch["seed"]))
    terms, logits = model.evaluate(rollout, batch["labels"], "classify", int(batch["seed"]))
    fc, every, last = model.heads
    rep = model.encoder(rollout.requests, rollout.points)
    shared = fc(rep, rollout.points) + every(rep, rollout.points)
    torch.testing.assert_close(logits[:, :-1], shared[:, :-1])
    torch.testing.assert_close(logits[:, -1:], last(rep, rollout.points))
    assert not torch.allclose(logits[:, -1], shared[:, -1])
    terms["loss"].backward()
    for head in model.heads:  # the cross-entropy trains every head, the last-only one on its one prediction
        assert any(p.grad is not None and p.grad.abs().sum() > 0 for p in head.parameters())
    model.sim.close()
    # the mirrors reflect about the model's own probe line (attach), in point units
    model.attach(ProbeSimulator("hg4", batch_size=2, scene=Scene(probe_x=0.1), mode="ideal"))
    assert every.line_x == last.line_x == pytest.approx(0.1 * model.hparams.point_scale)
    model.sim.close()


def test_eval_sets_are_fixed_and_disjoint_from_training():
    one = ProbeDataModule(mode="ideal", val_episodes=40, test_episodes=40, eval_batch_size=16, seed=1)
    two = ProbeDataModule(mode="ideal", val_episodes=40, test_episodes=40, eval_batch_size=16, seed=2)
    for a, b in zip(one.test_dataloader(), two.test_dataloader()):
        torch.testing.assert_close(a["poses"], b["poses"])  # the training seed never changes the test set
    train = next(iter(one.train_dataloader()))
    assert not torch.equal(train["poses"], next(iter(two.train_dataloader()))["poses"])
    assert (one.regions.split_of(train["poses"].numpy()) == 0).all()
    assert (one.regions.split_of(next(iter(one.test_dataloader()))["poses"].numpy()) == 2).all()
    assert (one.regions.split_of(next(iter(one.val_dataloader()))["poses"].numpy()) == 1).all()


# -- the `hg` executable end to end --------------------------------------------------------------------------------
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


def test_hg_fit_twice_then_test_with_wandb_offline(tmp_path, monkeypatch):
    """The paper's row by the `hg` executable: each run in its own wandb folder (a second fit in the same folder
    works too), the same seed the same weights, and a checkpoint tested again (here in this process) the same
    numbers."""
    tiny = ["--config", str(CONFIGS / "pcrn_fc.yaml"), "--config", str(CONFIGS / "parts" / "tiny.yaml"),
            "--trainer.enable_progress_bar", "false"]
    for _ in range(2):
        hg("fit", *tiny, "--seed_everything", "5", cwd=tmp_path)
    checkpoints = sorted(tmp_path.glob("runs/haptic-glance/*/checkpoints/last.ckpt"))
    runs = sorted(tmp_path.glob("runs/wandb/offline-run-*"))
    assert len(checkpoints) == len(runs) == 2
    for run in runs:
        assert (run / "files" / "config.yaml").is_file() and list(run.glob("*.wandb"))
        curve = list(csv.reader((run / "files" / "val_curve.csv").open()))  # one row per validation: steps 2, 4
        assert curve[0][:2] == ["step", "stochastic@1"] and len(curve[0]) == 1 + 2 * 4
        assert [row[0] for row in curve[1:]] == ["2", "4"] and all(0 <= float(v) <= 1 for v in curve[1][1:])
    states = [torch.load(p, weights_only=False)["state_dict"] for p in checkpoints]
    assert states[0].keys() == states[1].keys()
    for key in states[0]:
        torch.testing.assert_close(states[0][key], states[1][key])
    hg("test", *tiny, "--ckpt_path", str(checkpoints[0]), cwd=tmp_path)
    first = latest_csv(tmp_path)
    assert first[0] == ["probes", "stochastic", "mean_action"] and len(first) == 1 + 4
    monkeypatch.chdir(tmp_path)
    cli(["test", *tiny, "--ckpt_path", str(checkpoints[0]), "--trainer.logger", "false",
         "--trainer.default_root_dir", str(tmp_path / "again")])
    assert list(csv.reader((tmp_path / "again" / "per_probe_accuracy.csv").open())) == first


def test_scoring_a_checkpoint_trains_nothing_and_gives_what_its_run_gave(tmp_path, monkeypatch):
    """fit_and_test with a checkpoint (reproduce_table1's rows that score another row's runs): no training; the
    checkpoint's validation and test accuracy, as the run that trained it measured them."""
    from hg.lightning.experiment import fit_and_test

    monkeypatch.setenv("WANDB_MODE", "disabled")
    config, tiny = CONFIGS / "pcrn_fc.yaml", ["--config", str(CONFIGS / "parts" / "tiny.yaml")]
    kwargs = {"eval_seed": 0, "test_episodes": 32, "extra_args": tiny}
    trained = fit_and_test(config, 0, tmp_path / "trained", **kwargs)
    best = ROOT / trained["best_checkpoint"]  # (relative to the repository when inside it)
    scored = fit_and_test(config, 0, tmp_path / "scored", checkpoint=best, **kwargs)
    assert trained["train_wall_s"] > 0 and scored["train_wall_s"] == 0.0
    # how training ended on training poses, from the diagnostics' rows (one here: step 0, every 50 steps)
    assert 0 <= trained["train_last_quarter"]["acc"] <= 1 and scored["train_last_quarter"] is None
    # run again in its folder: it resumes from last.ckpt at its last step, trains nothing more, and still reports
    # the time its steps took (TrainingClock's total rides in the checkpoint), not the empty attempt's
    again = fit_and_test(config, 0, tmp_path / "trained", **kwargs)
    assert again["resumed_from_step"] == trained["max_steps"] and again["accuracy"] == trained["accuracy"]
    assert again["train_last_quarter"] == trained["train_last_quarter"]  # the diagnostics ride in the checkpoint
    saved = torch.load(tmp_path / "trained" / "checkpoints" / "last.ckpt", weights_only=False)["callbacks"]
    # (the checkpoint is written before the attempt ends, so it holds a little less than the attempt's total; how much
    # less depends on the machine's load, so only the order is asserted)
    assert 0 < saved["TrainingClock"]["seconds"] <= trained["train_wall_s"] + 0.05  # (train_wall_s is rounded to 0.1)
    assert again["train_wall_s"] >= saved["TrainingClock"]["seconds"] - 0.05
    # asked to resume it as another run (another discount here; another teacher or sensor alike): refused, untouched
    last = tmp_path / "trained" / "checkpoints" / "last.ckpt"
    before = last.read_bytes()
    with pytest.raises(ValueError, match=r"last.ckpt: trained with .*gamma.*Move .*trained away"):
        fit_and_test(config, 0, tmp_path / "trained", eval_seed=0, test_episodes=32,
                     extra_args=[*tiny, "--model.loss.gamma", "0.5"])
    assert last.read_bytes() == before
    assert not (tmp_path / "scored" / "checkpoints").exists()
    assert scored["accuracy"] == trained["accuracy"] and scored["best_val_acc"] == trained["best_val_acc"]
    assert scored["best_checkpoint"] == trained["best_checkpoint"]
    with pytest.raises(FileNotFoundError, match="nope.ckpt: the checkpoint to score is missing"):
        fit_and_test(config, 0, tmp_path / "none", checkpoint=tmp_path / "nope.ckpt", **kwargs)
    # stopped between saving a new best (which removes the old) and rewriting last.ckpt: the resumed state names a
    # removed file; the run tests the best checkpoint kept beside it
    best.rename(best.with_name("best-step999.ckpt"))
    stale = fit_and_test(config, 0, tmp_path / "trained", **kwargs)
    assert stale["best_checkpoint"].endswith("best-step999.ckpt") and stale["accuracy"] == trained["accuracy"]


def test_gradient_diagnostics_measure_what_the_policy_term_sends_into_the_encoder(tmp_path):
    """diagnostics.csv: every step here, the encoder gradient norms of the policy term and the cross-entropy; zero
    for the policy when REINFORCE is kept out of the encoder; a resumed run continues the file."""
    def fit(folder, steps, *extra):
        run = cli(args_of(ROWS["pcrn_fc"], "--trainer.default_root_dir", str(folder), "--trainer.max_steps",
                          str(steps), "--diagnostics.every_n_steps", "1", "--checkpoint.dirpath", str(folder / "ck"),
                          "--last_checkpoint.dirpath", str(folder / "ck"), "--last_checkpoint.every_n_train_steps",
                          "1", *extra), run=False)
        last = folder / "ck" / "last.ckpt"
        run.trainer.fit(run.model, datamodule=run.datamodule, ckpt_path=str(last) if last.is_file() else None)
        return list(csv.DictReader((folder / "diagnostics.csv").open()))

    rows = fit(tmp_path / "shared", 2)
    assert [float(r["step"]) for r in rows] == [0.0, 1.0]
    assert all(float(r["grad_policy"]) > 0 and float(r["grad_ce"]) > 0 for r in rows)
    assert float(rows[0]["grad_ratio"]) == pytest.approx(float(rows[0]["grad_policy"]) / float(rows[0]["grad_ce"]))
    assert {"clamp_share", "touch_rate@1", "advantage_std", "std_py"} <= set(rows[0])
    resumed = fit(tmp_path / "shared", 4)
    assert [float(r["step"]) for r in resumed] == [0.0, 1.0, 2.0, 3.0] and resumed[:2] == rows
    detached = fit(tmp_path / "detached", 2, "--model.policy.init_args.reads_detached", "true")
    assert all(float(r["grad_policy"]) == 0 and float(r["grad_ce"]) > 0 for r in detached)


def test_late_means_average_each_term_over_the_last_share_of_the_diagnostics_rows():
    """What a run's record keeps of how training ended (ablate.py: the second half; fit_and_test: the last quarter);
    a term logged on some rows only is averaged over those."""
    diagnostics = GradientDiagnostics()
    diagnostics.rows = [{"step": 0.0, "acc": 0.0}, {"step": 1.0, "acc": 0.5, "touch_rate": 1.0},
                        {"step": 2.0, "acc": 1.0}]
    assert diagnostics.late_means(0.5) == {"acc": 0.75, "touch_rate": 1.0}
    assert diagnostics.late_means(0.25) == {"acc": 1.0}
    diagnostics.rows = [{"step": float(k), "acc": float(k)} for k in range(5)]
    assert diagnostics.late_means(0.8) == {"acc": 2.5}  # 4 of 5 rows, though 5 x (1 - 0.8) is not quite 1 in floats
    with pytest.raises(ValueError, match=r"late_means: share=0: .* \(0, 1\]"):
        diagnostics.late_means(0)


class LossRecorder(pl.Callback):
    def __init__(self) -> None:
        self.losses: list[float] = []

    def on_train_batch_end(self, trainer, pl_module, outputs, batch, batch_idx) -> None:
        self.losses.append(float(outputs["loss"]))


@pytest.mark.parametrize("every, logged_steps", [(1, [0, 1, 2, 3]), (3, [2])])
def test_training_metrics_are_logged_on_the_steps_lightning_writes(every, logged_steps, tmp_path):
    """The step logs its terms only when Lightning writes them (every log_every_n_steps): each written row is that
    step's, none a stale one of an earlier step."""
    logger = ["--trainer.logger", json.dumps({"class_path": "pytorch_lightning.loggers.CSVLogger",
                                              "init_args": {"save_dir": str(tmp_path), "name": "csv"}})]
    run = cli([*args_of(ROWS["pcrn_fc"], "--trainer.default_root_dir", str(tmp_path / "run")), *logger,
               "--trainer.log_every_n_steps", str(every)], run=False)
    recorder = LossRecorder()
    run.trainer.callbacks.append(recorder)
    run.trainer.fit(run.model, datamodule=run.datamodule)
    rows = list(csv.DictReader(next(tmp_path.glob("csv/*/metrics.csv")).open()))
    written = [r for r in rows if r.get("train/loss")]
    assert [int(r["step"]) for r in written] == logged_steps
    assert [float(r["train/loss"]) for r in written] == pytest.approx([recorder.losses[s] for s in logged_steps])
    assert all(r["train/touch_rate@4"] and r["train/reach_rate"] and r["train/lr"] for r in written)
