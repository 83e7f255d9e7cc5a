"""HapticGlance: an encoder, a policy and classifier heads composed in Lightning, trained by the hybrid update rule
(paper sec. 2.2 (d)). Every part is injected from YAML (`class_path` / `init_args`); this file only wires them."""
from __future__ import annotations

from collections.abc import Callable
from typing import Literal

import pytorch_lightning as pl
import torch
from torch import Tensor, nn

from hg.nets import TouchSetClassifier
from hg.nets.dims import Dims
from hg.policies import Imitation, LearnedPolicy, Policy, Scan
from hg.rl import HybridLoss, Rollout, rollout
from hg.rl.warmup import FollowPrior, ImitateTeacher, Warmup
from hg.sim import ProbeSimulator
from hg.sim.symmetry import all_mirror_symmetric, require_mirror
from hg.lightning.library import LibrarySource

Regime = Literal["classify", "reinforce", "imitate"]  # what a training step's loss trains


class HapticGlance(pl.LightningModule):
    """PCRN (or the LSTM baseline) with a policy and classifier heads, trained by eq. (6).

    encoder: the probes so far -> a representation after each probe (hg.nets.PCRN, LSTMEncoder). policy: what request
    next (hg.policies). heads: classifiers whose logits are summed (a head with `last_only` replaces the prediction
    after the last probe). library_classifier: beyond the paper, a non-learned Bayes classifier over a library of
    simulated training episodes, scored alone and mixed with the heads at validation and test, never trained
    (hg.planner). warmup: beyond the paper, what probes before the policy learns (itself untrained, its prior scan,
    or a teacher to copy). loss: eq. (6)'s settings. compare_with: beyond the paper, a fixed scan the heads also read
    behind at validation and test, for a learned policy with no prior scan of its own (one with a prior is compared
    with its prior): what the learned probes buy over the scan, the classifiers held equal.
    """

    def __init__(self, encoder: nn.Module, policy: Callable[[Dims], Policy], heads: list[Callable[[Dims], nn.Module]],
                 loss: HybridLoss = HybridLoss(), warmup: Warmup | None = None,
                 library_classifier: LibrarySource | None = None, compare_with: Callable[[Dims], Scan] | None = None,
                 lr: float = 1e-3, policy_lr_scale: float = 1.0, point_scale: float = 2.0, n_probes: int = 10,
                 n_classes: int = 4) -> None:
        super().__init__()
        if n_probes < 1:
            raise ValueError(f"model.n_probes={n_probes}: must be >= 1")
        if not heads:
            raise ValueError("model.heads: give at least one classifier head")
        self.save_hyperparameters()
        self.encoder = encoder
        dims = Dims(encoder.out_dim, n_probes, n_classes)
        self.policy = policy(dims)
        self.heads = nn.ModuleList(head(dims) for head in heads)
        if all(head.last_only for head in self.heads):
            raise ValueError("model.heads: every head scores the last probe only; one must score every probe")
        self.loss, self.warmup, self.library_source = loss, warmup, library_classifier
        if warmup is not None and not self.policy.learned:
            raise ValueError(f"model.warmup: a fixed policy ({type(self.policy).__name__}) has nothing to warm up")
        if warmup is not None:
            warmup.prober(self.policy)  # refuses a warm-up that cannot probe with this policy
        if self.policy.copies_prior and self.policy.prior is not None and not (
                isinstance(warmup, FollowPrior) and warmup.imitate):
            raise ValueError(f"model.policy.init_args.prior: {type(self.policy).__name__} starts on its prior scan only "
                             "by copying it; set model.warmup to hg.rl.FollowPrior with imitate: true")
        if library_classifier is not None and getattr(self.policy, "grid", None) is None:
            raise ValueError(f"model.library_classifier names the planner's candidate probes; "
                             f"{type(self.policy).__name__} does not choose among them (CandidateChoice does)")
        self.compare_with = compare_with(dims) if compare_with is not None else None
        if self.compare_with is not None and not self.policy.learned:
            raise ValueError(f"model.compare_with: the policy ({type(self.policy).__name__}) is a fixed one itself; "
                             "compare two fixed policies as two runs")
        if self.compare_with is not None and self.policy.prior is not None:
            raise ValueError(f"model.compare_with: the policy is compared with its prior scan "
                             f"({type(self.policy.prior).__name__}, model.policy.init_args.prior); give one of the two")
        self.library = None  # the library classifier, built in setup() from its source (it needs the simulator)
        self.sim: ProbeSimulator | None = None

    @property
    def reference_scan(self) -> Policy | None:
        """The scan the heads also read behind at validation and test (`acc_prior`): the policy's prior, or
        compare_with."""
        prior = getattr(self.policy, "prior", None)  # a fixed policy has none
        return prior if prior is not None else self.compare_with

    # -- world ---------------------------------------------------------------------------------------
    def setup(self, stage: str) -> None:
        data = self.trainer.datamodule
        self.attach(data.make_simulator() if self.sim is None else self.sim)
        if isinstance(self.warmup, ImitateTeacher) and stage == "fit" and self.warmup.teacher is None:
            self.warmup.teacher = data.load_teacher(self.warmup.teachers)
            if hasattr(self.policy, "candidates"):  # a choice can copy only its own candidates
                try:
                    self.policy.location.index_of(self.warmup.teacher["requests"])
                except ValueError as error:
                    raise ValueError(f"model.warmup.teachers={self.warmup.teachers}: {error} (the policy's places, "
                                     "span and leans must be the teacher's)") from None
        if self.library_source is not None and self.library is None:
            self.library = self.library_source.build(data, getattr(self.policy, "grid", None)).to(self.device)

    def attach(self, sim: ProbeSimulator) -> None:
        """Probe in `sim`; the mirrors of the touch sets reflect about its probe line, and only for an object set
        whose objects are their own mirror images (`mirror: auto` mirrors there and nowhere else)."""
        self.sim = sim
        for module in self.modules():
            if isinstance(module, TouchSetClassifier):
                module.line_x = sim.scene.probe_x * self.hparams.point_scale
                if module.mirror == "auto":
                    module.mirror = all_mirror_symmetric(sim.objects)
                elif module.mirror:
                    require_mirror(sim.objects, "model.heads: TouchSetClassifier(mirror=true)")

    def teardown(self, stage: str) -> None:
        if self.sim is not None:
            self.sim.close()
            self.sim = None

    # -- rollout and prediction ----------------------------------------------------------------------
    def roll(self, labels: Tensor, poses: Tensor, seed: int, deterministic: bool = False, policy: Policy | None = None,
             requests: Tensor | None = None, faults: Tensor | None = None) -> Rollout:
        """hg.rl.rollout with this model's simulator, policy (or the given one) and encoder."""
        return rollout(self.sim, policy or self.policy, labels, poses, seed, self.hparams.n_probes,
                       self.hparams.point_scale, self.encoder, deterministic, requests, faults)

    def predict(self, rollout: Rollout) -> tuple[Tensor, Tensor]:
        """The heads' summed logits (B, N, C) after each probe, and the encoder's representation (B, N, D). Heads of
        the whole episode (`last_only`) read only whole episodes (n_probes probes): a shorter rollout is a prefix."""
        rep = self.encoder(rollout.requests, rollout.points)
        every = [head(rep, rollout.points) for head in self.heads if not head.last_only]
        whole = rollout.points.shape[1] == self.hparams.n_probes
        last = [head(rep, rollout.points) for head in self.heads if head.last_only and whole]
        logits = sum(every)
        if last:  # heads of the whole episode replace the prediction after the last probe
            logits = torch.cat([logits[:, :-1], sum(last)], 1)
        return logits, rep

    # -- loss ----------------------------------------------------------------------------------------
    def evaluate(self, rollout: Rollout, labels: Tensor, regime: Regime, seed: int) -> tuple[dict[str, Tensor], Tensor]:
        """The loss terms of a finished rollout (the last the simulator made, drawn with `seed`) and the logits (B, N,
        C). Eq. (6) is self.loss; the terms beyond the paper (the imitation of a teacher, the policy's own, e.g. its
        anchor) are named and added here, and only here."""
        logits, rep = self.predict(rollout)
        evaluated = imitation = None
        if regime == "imitate":  # what the warm-up would ask for in these states; by default what it sent
            imitation = self.warmup.targets(self, rollout, labels, seed) if self.warmup else Imitation(rollout.actions)
        if regime != "classify" and isinstance(self.policy, LearnedPolicy):
            evaluated = self.policy.evaluate(rep, rollout.actions, rollout.points,
                                             chosen=None if imitation is None else imitation.requests,
                                             among=None if imitation is None else imitation.among)
        if regime == "reinforce" and evaluated is not None:
            terms = self.loss(logits, labels, evaluated.log_pi, evaluated.baseline, float(self.policy.std_scale),
                              points=rollout.points)
        else:  # the reward is logged at every step, whoever pays it
            terms = self.loss(logits, labels, points=rollout.points)
        if evaluated is not None:
            extra = dict(evaluated.losses)
            if imitation is not None:
                extra["loss_imitation"] = self.policy.imitation_loss(evaluated, imitation)
            terms |= evaluated.stats | extra
            terms["loss"] = terms["loss"] + sum(extra.values())
        return terms, logits

    @property
    def policy_start(self) -> int:
        """The training step from which the policy learns by REINFORCE (after any warm-up)."""
        return self.warmup.steps if self.warmup is not None else 0

    def training_step(self, batch: dict[str, Tensor], batch_idx: int) -> Tensor:
        labels, poses, seed = batch["labels"], batch["poses"], int(batch["seed"])
        if self.global_step < self.policy_start:
            labels, poses, requests, faults = self.warmup.episodes(labels, poses, self.global_step)
            probe_with = self.warmup.prober(self.policy) if requests is None else None
            rollout = self.roll(labels, poses, seed, policy=probe_with, requests=requests, faults=faults)
            regime: Regime = "imitate" if self.warmup.imitate else "classify"
        else:
            rollout = self.roll(labels, poses, seed)
            regime = "reinforce" if self.policy.learned else "classify"
        terms, _ = self.evaluate(rollout, labels, regime, seed)
        if not torch.isfinite(terms["loss"]):
            raise FloatingPointError(f"non-finite loss {terms['loss'].item()} at global step {self.global_step} "
                                     f"(terms: { {k: round(v.item(), 4) for k, v in terms.items()} })")
        touches = rollout.points[..., 3].mean(0)
        terms |= {"touch_rate": touches.mean(), **{f"touch_rate@{k + 1}": t for k, t in enumerate(touches)},
                  "clamp_share": (rollout.actions.abs() > 1).float().mean()}  # requests executed other than drawn
        self.last_terms = terms  # for the gradient diagnostics (hg.lightning.callbacks.GradientDiagnostics)
        # Lightning writes training metrics every log_every_n_steps only; a self.log call costs about as much as the
        # step's loss pass, so the step logs only when they will be written (Lightning's own test, same step count)
        if self.trainer._logger_connector.should_update_logs:
            size = len(labels)
            self.log_dict({f"train/{k}": v for k, v in terms.items()}
                          | {"train/reach_rate": rollout.reached.float().mean(),
                             "train/lr": self.optimizers().param_groups[0]["lr"]}, batch_size=size)
        return terms["loss"]

    # -- evaluation ----------------------------------------------------------------------------------
    def _eval_step(self, batch: dict[str, Tensor], stage: str) -> dict[bool, tuple[Rollout, Tensor]]:
        """Single-rollout accuracy after each probe: the stochastic policy, and for a learned policy also the
        mean-action policy, each labelled; never an average over several rollouts. A learned policy is also scored
        by the same heads behind its reference scan (`acc_prior`: its prior, or compare_with): what its learned
        probes buy over the scan's, with the classifiers held equal. With a library classifier, its accuracy alone
        (`acc_library`) and mixed with the heads (`acc_mixed`) too, under their own names. Returns {deterministic:
        (rollout, logits)} of the policy's own rollouts, which callbacks (ProbeMaps) get as the step's outputs."""
        labels, seed, scored = batch["labels"], int(batch["seed"]), {}
        variants = [("", False, None)]  # (metric suffix, deterministic, the policy probing instead of the model's)
        if self.policy.learned:
            variants.append(("_mean_action", True, None))
            if self.reference_scan is not None:
                variants.append(("_prior", False, self.reference_scan))
        for suffix, deterministic, probe_with in variants:
            rollout = self.roll(labels, batch["poses"], seed, deterministic=deterministic, policy=probe_with)
            logits, _ = self.predict(rollout)
            if probe_with is None:
                scored[deterministic] = (rollout, logits.detach())
            predictions = {"": logits}
            if self.library is not None:
                named = self.library.name(rollout, self.hparams.point_scale)
                predictions |= {"_library": named, "_mixed": logits + named}
            metrics = {f"{stage}/touch_rate{suffix}": rollout.points[..., 3].mean()}
            for who, predicted in predictions.items():
                correct = (predicted.argmax(-1) == labels[:, None]).float().mean(0)
                metrics |= {f"{stage}/acc{who}{suffix}@{k + 1}": correct[k] for k in range(len(correct))}
                metrics[f"{stage}/acc{who}{suffix}"] = correct[-1]
            self.log_dict(metrics, batch_size=len(labels), sync_dist=True)
        return scored

    def validation_step(self, batch: dict[str, Tensor], batch_idx: int) -> dict[bool, tuple[Rollout, Tensor]]:
        return self._eval_step(batch, "val")

    def test_step(self, batch: dict[str, Tensor], batch_idx: int) -> dict[bool, tuple[Rollout, Tensor]]:
        return self._eval_step(batch, "test")

    def configure_optimizers(self) -> torch.optim.Optimizer:
        """Adam; beyond the paper, the policy may learn on a slower time scale than the classifier
        (policy_lr_scale). Learning-rate schedules are callbacks (hg.lightning.callbacks.CosineLR)."""
        # the location network's (not the baseline's); a list, not a set: the order must survive a resume
        policy = list(self.policy.location.parameters()) if isinstance(self.policy, LearnedPolicy) else []
        rest = [p for p in self.parameters() if all(p is not q for q in policy)]
        lr, slow = self.hparams.lr, self.hparams.lr * self.hparams.policy_lr_scale
        # initial_lr: each group's own rate, which a schedule scales; it rides in the optimizer's state on resume
        groups = [{"params": rest, "initial_lr": lr}, {"params": policy, "lr": slow, "initial_lr": slow}]
        return torch.optim.Adam(groups, lr=lr, foreach=True)  # one call per step for all tensors: torch's default on CPU loops
