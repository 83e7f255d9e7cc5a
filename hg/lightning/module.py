"""HapticGlance: rollouts in the simulator and the hybrid update rule (paper sec. 2.2 (d)) in Lightning."""
from __future__ import annotations

import math
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Literal, get_args

import pytorch_lightning as pl
import torch
import torch.nn.functional as F
from pytorch_lightning.utilities import rank_zero_info
from torch import Tensor

from hg.lightning.data import load_teacher, teacher_meta
from hg.nets import (PCRN, AlongLineClassifier, Baseline, CandidateLocationNetwork, FCClassifier, LibraryNamer,
                     LinearClassifier, LocationNetwork, LSTMEncoder, NClassClassifier, TouchSetClassifier, left_of_line,
                     reflect)
from hg.sim import ProbeSimulator, candidate_requests
from hg.sim.library import MISS, readings, teacher_library
from hg.sim.robot import achieved

COMPONENTS = ("py", "ux", "uy", "uz")
ScanOrder = Literal["sweep", "centre_out", "coarse_first"]  # model.scan_order: where a fixed scan puts probe k
SCAN_ORDERS = get_args(ScanOrder)


def discounted_returns(rewards: Tensor, gamma: float) -> Tensor:
    """G_k = sum_{j >= k} gamma^(j - k) r_j over the probe axis (B, N): the return of request k (eq. 3)."""
    returns = torch.zeros_like(rewards)
    running = torch.zeros_like(rewards[:, 0])
    for k in range(rewards.shape[1] - 1, -1, -1):
        running = rewards[:, k] + gamma * running
        returns[:, k] = running
    return returns


def relative_to_first_touch(points: Tensor) -> Tensor:
    """(B, N, 4) points with X, Y, Z taken relative to the episode's first touch for that touch and every later
    probe; probes before it keep their coordinates. Causal (probe k reads probes <= k), so a rollout may apply it
    to the prefix it has. Beyond the paper: the object's shape, not where it lies, is the class cue."""
    touched = points[..., 3] > 0.5
    seen = touched.cumsum(1) > 0  # (B, N): a touch at or before probe k
    first = touched.float().argmax(1)  # index of the first touch (0 when there is none; then seen is all False)
    reference = points[torch.arange(len(points)), first, :3]  # (B, 3)
    out = points.clone()
    out[..., :3] = points[..., :3] - seen[..., None] * reference[:, None]
    return out


def hybrid_loss(logits: Tensor, labels: Tensor, log_pi: Tensor | None, baseline: Tensor | None, gamma: float,
                beta: float, normalize_advantage: bool = False,
                reward: Literal["correct", "log_gain"] = "correct", sampled: Tensor | None = None,
                ce_prefixes: Literal["all", "last"] = "all") -> dict[str, Tensor]:
    """The hybrid update rule, eq. (6), as a loss to minimise; every term is returned for logging.

    logits (B, N, C): prediction after each probe; log_pi (B, N): log pi(a_k | s_k) of the detached requests;
    baseline (B, N): b_k from detached states. Without a policy to train (random, line scan) only the
    cross-entropy remains. sampled (B,) bool, beyond the paper: the episodes whose probes were drawn from the
    policy; only they train the policy and the baseline (the others were probed with its mean action, and
    REINFORCE needs sampled actions), while the cross-entropy takes every episode. ce_prefixes "last", beyond the
    paper: the cross-entropy scores only the prediction after the last probe (an ablation of scoring every prefix).
    """
    n_probes = logits.shape[1]
    correct = (logits.argmax(-1) == labels[:, None]).float()
    if reward == "correct":
        rewards = correct  # r_k = 1 when the prediction after probe k is right (the paper)
    else:  # "log_gain", beyond the paper: what probe k added to log p(true class); sums to log p_N - log(1/C)
        log_p = logits.detach().log_softmax(-1).gather(-1, labels[:, None, None].expand(-1, n_probes, 1)).squeeze(-1)
        rewards = torch.diff(log_p, dim=1, prepend=torch.full_like(log_p[:, :1], -math.log(logits.shape[-1])))
    # sum_o y_o log pi_c(o), on the prediction after every probe
    if ce_prefixes == "last":
        cross_entropy = F.cross_entropy(logits[:, -1], labels)
    else:
        cross_entropy = F.cross_entropy(logits.flatten(0, 1), labels.repeat_interleave(n_probes))
    terms = {"loss_ce": cross_entropy, "reward": rewards.mean(), "acc": correct[:, -1].mean()}
    if log_pi is None:
        terms["loss"] = cross_entropy
        return terms
    if sampled is not None:
        rewards, log_pi, baseline = rewards[sampled], log_pi[sampled], baseline[sampled]
    returns = discounted_returns(rewards, gamma)  # G_k, eq. (3); rewards carry no gradient
    advantage = (returns - baseline).detach()  # (G_k - b_k): the baseline reduces variance, never the gradient path
    if normalize_advantage:  # beyond the paper: unit-scale advantages per probe index keep eq. (3) well scaled
        advantage = advantage / (advantage.std(0, keepdim=True) + 1e-6)
    policy = -(log_pi * advantage).mean()  # autograd of log N(x; mu, sigma) gives xi_mu, xi_sigma of eq. (4), (5)
    baseline_mse = F.mse_loss(baseline, returns)  # b_k is fitted to the return
    terms.update(loss_policy=policy, loss_baseline=baseline_mse, loss=cross_entropy + beta * policy + baseline_mse)
    return terms


def scan_options_combine(lean: float, follow: float, cross: float, reach: float, side: float = 0.0) -> bool:
    """Whether these fixed-scan options (model.scan_lean, _follow, _cross, _reach, _side; 0: off) may be set
    together: a fanned scan may follow its touches, but the cross-checking, reaching and side-picking scans each
    stand alone."""
    return sum(map(bool, (lean or follow, cross, reach, side))) <= 1


@dataclass
class Rollout:
    """N probes of B episodes: what the policy asked for and what the sensor returned."""

    actions: Tensor  # (B, N, 4) raw Gaussian samples (the log-probability is taken of these)
    requests: Tensor  # (B, N, 4) the requests executed: actions clipped to [-1, 1]
    points: Tensor  # (B, N, 4) X, Y, Z scaled by point_scale, and T
    reached: Tensor  # (B, N) bool: the arm achieved the request within 5 mm and 3 degrees
    beliefs: Tensor | None = None  # (B, N, classes + 4) the library namer's belief after each probe, if a choice reads it
    named: Tensor | None = None  # (B, N, classes) the library namer's log posterior after each probe, weighed with them


def pick_view(views: Tensor, mirrored: Tensor) -> Tensor:
    """views (V, B, ...) of the episodes (HapticGlance.encoder_views) -> (B, ...): the last view (the mirrored one,
    if any) where mirrored (B, ...) is True, else the first."""
    return torch.where(mirrored.reshape(*mirrored.shape, *[1] * (views.dim() - 1 - mirrored.dim())), views[-1],
                       views[0])


class HapticGlance(pl.LightningModule):
    """PCRN (or the LSTM baseline) with a location network, a baseline and a classifier, trained by eq. (6).

    The probe policy is `learned` (the paper), or `random` / `line_scan` with the same classifier: the
    ablations that show what the learned exploration buys.
    """

    def __init__(self, n_classes: int = 4, n_probes: int = 10, encoder: Literal["pcrn", "lstm"] = "pcrn",
                 classifier: Literal["fc", "nclass", "linear", "none"] = "fc",
                 policy: Literal["learned", "random", "line_scan"] = "learned", width: int = 128,
                 representation: int = 256, hidden: int = 256, std_floor: float = 0.05, std_max: float = 1.0,
                 gamma: float = 0.95, beta: float = 1.0, lr: float = 1e-3, point_scale: float = 2.0,
                 normalize_advantage: bool = False, policy_reads_detached: bool = False,
                 reward: Literal["correct", "log_gain"] = "correct", policy_lr_scale: float = 1.0,
                 prior: Literal["none", "line_scan"] = "none", prior_lean: float = 0.0, prior_exact: bool = False,
                 prior_anchor: float = 0.0, prior_anchor_free: tuple[Literal["py", "ux", "uy", "uz"], ...] = (),
                 mean_action_share: float = 0.0, scan_span: float = 1.0,
                 scan_order: ScanOrder = "sweep", scan_lean: float = 0.0, scan_follow: float = 0.0,
                 scan_cross: float = 0.0, scan_reach: float = 0.0, scan_side: float = 0.0,
                 scan_side_first: float = 0.0, scan_side_pair_apart: bool = False, scan_follow_probes: int = 0,
                 point_frame: Literal["episode", "first_touch"] = "episode",
                 touch_set: bool = False, touch_set_net: Literal["small", "wide"] = "small",
                 touch_set_prefix: bool = False, policy_reads_touch_set: bool = False,
                 policy_warmup_steps: int = 0, std_final_scale: float = 1.0, lr_final_scale: float = 1.0,
                 ce_prefixes: Literal["all", "last"] = "all", final_touch_set: bool = False,
                 touch_set_miss_frame: Literal["touches", "line"] = "touches", touch_set_mirror: bool = False,
                 mirror_encoder: bool = False, imitate: tuple[str, ...] = (),
                 location: Literal["gaussian", "candidates"] = "gaussian", candidate_places: int = 11,
                 candidate_span: float = 0.5, candidate_leans: tuple[float, ...] = (0.6, 1.0, 2.0),
                 choice_reads_probes: bool = False, choice_along_line: bool = False,
                 choice_reads_state: bool = True, random_probe_share: float = 0.0,
                 along_line_classifier: bool = False, library_namer: str | None = None,
                 library_namer_episodes: int | None = None, choice_repeats: bool = False,
                 choice_reads_belief: bool = False) -> None:
        super().__init__()
        if n_probes < 1:
            raise ValueError(f"model.n_probes={n_probes}: must be >= 1")
        if policy_warmup_steps < 0:
            raise ValueError(f"model.policy_warmup_steps={policy_warmup_steps}: must be >= 0")
        if not 0.0 < std_final_scale <= 1.0:
            raise ValueError(f"model.std_final_scale={std_final_scale}: must be in (0, 1] (the policy's std at the "
                             "last training step, as a share of its learned value)")
        if not 0.0 < lr_final_scale <= 1.0:
            raise ValueError(f"model.lr_final_scale={lr_final_scale}: must be in (0, 1] (the learning rate at the last "
                             "training step, as a share of model.lr)")
        if not 0.0 <= gamma <= 1.0:
            raise ValueError(f"model.gamma={gamma}: the discount must be in [0, 1]")
        if ce_prefixes not in ("all", "last"):
            raise ValueError(f"model.ce_prefixes={ce_prefixes!r}: expected 'all' or 'last'")
        if ce_prefixes == "last" and policy == "learned":
            raise ValueError("model.ce_prefixes='last' needs a fixed policy ('random' or 'line_scan'): a learned "
                             "policy's reward after every probe needs the predictions of every prefix trained")
        self.save_hyperparameters()
        if encoder == "pcrn":
            self.encoder = PCRN(width=width, out_dim=representation)
        elif encoder == "lstm":
            self.encoder = LSTMEncoder(hidden=representation)
        else:
            raise ValueError(f"model.encoder={encoder!r}: expected 'pcrn' or 'lstm'")
        dim = self.encoder.out_dim
        # "none", beyond the paper: no head on the encoder, the touch set's logits alone (an ablation of PCRN)
        classifiers = {"fc": lambda: FCClassifier(dim, n_classes, hidden),
                       "nclass": lambda: NClassClassifier(dim, n_classes, n_probes, hidden),
                       "linear": lambda: LinearClassifier(dim, n_classes), "none": lambda: None}
        if classifier not in classifiers:
            raise ValueError(f"model.classifier={classifier!r}: expected one of {sorted(classifiers)}")
        if policy not in ("learned", "random", "line_scan"):
            raise ValueError(f"model.policy={policy!r}: expected 'learned', 'random' or 'line_scan'")
        if classifier == "none" and not (touch_set and policy != "learned"):
            raise ValueError(f"model.classifier='none' (the touch set's logits alone) needs model.touch_set=true and "
                             f"a fixed policy ('random' or 'line_scan'), got touch_set={touch_set}, policy={policy!r}: "
                             "a learned policy reads the encoder, which only the classifier trains")
        self.classifier = classifiers[classifier]()
        # beyond the paper: the logits of a translation-invariant classifier of the touched points are added
        # touch_set_prefix: its head also reads which prefix it scores (one-hot)
        n_prefixes = n_probes if touch_set_prefix else 0
        # touch_set_miss_frame: where the wide nets place a miss; touch_set_mirror: every touch set reads an episode
        # and its mirror image across the line alike (TouchSetClassifier's miss_frame and mirror)
        touch_nets = {"small": lambda: TouchSetClassifier(n_classes, hidden=hidden, n_prefixes=n_prefixes,
                                                          mirror=touch_set_mirror),
                      "wide": lambda: TouchSetClassifier.wide(n_classes, n_prefixes, touch_set_miss_frame,
                                                              touch_set_mirror)}
        if touch_set_net not in touch_nets:
            raise ValueError(f"model.touch_set_net={touch_set_net!r}: expected one of {sorted(touch_nets)}")
        if touch_set_miss_frame not in ("touches", "line"):
            raise ValueError(f"model.touch_set_miss_frame={touch_set_miss_frame!r}: expected 'touches' or 'line'")
        if touch_set_miss_frame != "touches" and not (touch_set and touch_set_net == "wide" or final_touch_set):
            raise ValueError(f"model.touch_set_miss_frame={touch_set_miss_frame!r}: places the misses of a wide touch "
                             "set, so it needs model.touch_set_net: wide (with model.touch_set) or "
                             "model.final_touch_set")
        if touch_set_mirror and not (touch_set or final_touch_set):
            raise ValueError("model.touch_set_mirror=true mirrors the touch sets' episodes, so it needs model.touch_set "
                             "or model.final_touch_set")
        self.touch_set = touch_nets[touch_set_net]() if touch_set else None
        # beyond the paper: the answer after the last probe comes from a wide touch set of its own, which the
        # cross-entropy trains on whole episodes only; one classifier scoring every prefix reads a reordered scan's
        # full set of probes worse (model.ce_prefixes: last, docs/training.md)
        self.final_touch_set = TouchSetClassifier.wide(n_classes, miss_frame=touch_set_miss_frame,
                                                       mirror=touch_set_mirror) if final_touch_set else None
        if policy_reads_touch_set and not touch_set:
            raise ValueError("model.policy_reads_touch_set=true needs model.touch_set=true (the policy reads its "
                             "pooled features)")
        # beyond the paper: the policy may read the touch set's pooled features (detached) beside PCRN's summary
        policy_dim = dim + (self.touch_set.pooled_dim if policy_reads_touch_set else 0)
        if choice_reads_probes and (location != "candidates" or mirror_encoder):
            raise ValueError(f"model.choice_reads_probes=true reads the probes by candidate, so it needs "
                             f"model.location: candidates and model.mirror_encoder: false, got location={location!r}, "
                             f"mirror_encoder={mirror_encoder}")
        if not choice_reads_state and (not choice_reads_probes or choice_along_line):
            raise ValueError("model.choice_reads_state=false leaves the choice only the readings by candidate, so it "
                             "needs model.choice_reads_probes: true and model.choice_along_line: false")
        if choice_along_line and not choice_reads_probes:
            raise ValueError("model.choice_along_line=true convolves the readings by candidate along the line, so it "
                             "needs model.choice_reads_probes: true")
        # beyond the paper: under sensor faults a candidate probed again can outvote a corrupted first reading (the
        # planner under noise re-probes, scripts/planner_ceiling.py --noise); without faults it would read the same
        if choice_repeats and not choice_reads_probes:
            raise ValueError("model.choice_repeats=true lifts the choice's ban on a candidate probed already, which only "
                             "model.choice_reads_probes: true sets")
        # beyond the paper: `candidates`, a choice among fixed requests (the greedy planner's: candidate_places
        # along the middle candidate_span of the line, each straight or leaning to +-x by each of candidate_leans)
        if location == "gaussian":
            self.location = LocationNetwork(policy_dim, hidden=128, std_floor=std_floor, std_max=std_max,
                                            zero_mean=prior_exact)
        elif location == "candidates":
            if prior != "none":
                raise ValueError(f"model.location='candidates' chooses among fixed requests, so it takes no prior "
                                 f"(model.prior: none), got prior={prior!r}")
            try:
                candidates = candidate_requests(candidate_places, candidate_span, candidate_leans)
            except ValueError as error:
                raise ValueError(f"model.candidate_places / candidate_span / candidate_leans: {error}") from None
            # choice_reads_probes: beside PCRN's state, what each candidate read so far (CandidateLocationNetwork.
            # readings), and it never repeats a probe; the offline copy of the planner read this (0.962 after 10)
            readings = (3 * len(candidates) + n_probes) if choice_reads_probes else 0
            # choice_reads_belief: and, after the readings, the library namer's belief (LibraryNamer.belief)
            believed = n_classes + 4 if choice_reads_belief else 0
            policy_dim += readings + believed
            # choice_along_line: the choice is the same function of the readings around every place along the line
            # choice_reads_state=false: the choice reads the readings only, as the offline copy did
            self.location = CandidateLocationNetwork(policy_dim, torch.from_numpy(candidates), hidden=128,
                                                     along_line=(readings, candidate_places) if choice_along_line
                                                     else None,
                                                     reads_from=0 if choice_reads_state
                                                     else policy_dim - readings - believed)
        else:
            raise ValueError(f"model.location={location!r}: expected 'gaussian' or 'candidates'")
        if along_line_classifier and location != "candidates":
            raise ValueError(f"model.along_line_classifier=true reads the probes by candidate, so it needs "
                             f"model.location: candidates, got {location!r}")
        # beyond the paper: the logits of a classifier of the readings by candidate, the same along the line, are added
        # to every prediction (mirrored alike with model.touch_set_mirror)
        self.along_line_classifier = AlongLineClassifier(
            n_classes, candidate_places, len(candidates) // candidate_places,
            mirror=touch_set_mirror) if along_line_classifier else None
        if library_namer is not None and location != "candidates":
            raise ValueError(f"model.library_namer={library_namer!r} names the readings of the planner's candidates, so "
                             f"it needs model.location: candidates, got {location!r}")
        # beyond the paper: the choice reads what the namer believes of the probes so far (the class, where the object
        # lies along the line and across it), the summary of the library the planner it copies weighs its candidates
        # by; offline that closed half the copy's gap to its teacher after 5 probes (copy_planner.py --belief)
        if choice_reads_belief and (location != "candidates" or library_namer is None or choice_along_line
                                    or mirror_encoder):
            raise ValueError("model.choice_reads_belief=true reads the library namer's belief, so it needs "
                             "model.location: candidates, model.library_namer, model.choice_along_line: false and "
                             f"model.mirror_encoder: false, got location={location!r}, library_namer={library_namer!r}, "
                             f"choice_along_line={choice_along_line}, mirror_encoder={mirror_encoder}")
        if library_namer_episodes is not None and (library_namer is None or library_namer_episodes < 1):
            raise ValueError(f"model.library_namer_episodes={library_namer_episodes}: must be >= 1, and needs "
                             "model.library_namer")
        # beyond the paper: at validation and test, the planner's namer's log posterior over the class (a library of
        # training episodes read by nearest match) is added to every prediction; built in setup(). Its library is the
        # teacher file's, drawn as its planner drew it, or with library_namer_episodes that many training episodes
        # (drawn with its seed): more of them reach more of the held-out positions through the shifts
        self.library_namer: LibraryNamer | None = None
        self.baseline = Baseline(policy_dim)  # b_k reads the state s_k the policy reads
        self.line_x = 0.0  # where the probe line is (set with the sim)
        self.sim: ProbeSimulator | None = None
        if point_frame not in ("episode", "first_touch"):
            raise ValueError(f"model.point_frame={point_frame!r}: expected 'episode' or 'first_touch'")
        if mirror_encoder and point_frame != "episode":
            raise ValueError(f"model.mirror_encoder=true mirrors the episode frame across the probe line, so it needs "
                             f"model.point_frame: episode, got {point_frame!r}")
        if not 0.0 < scan_span <= 1.0:
            raise ValueError(f"model.scan_span={scan_span}: the scanned share of the probe line must be in (0, 1]")
        if not 0.0 <= scan_follow <= 1.0:
            raise ValueError(f"model.scan_follow={scan_follow}: must be in [0, 1] (a step along the probe line, "
                             "in request units; 0: no following)")
        for name, value, probes in (("scan_lean", scan_lean, "leaning probes"),
                                    ("scan_cross", scan_cross, "cross-check probes"),
                                    ("scan_reach", scan_reach, "reaching probes"),
                                    ("scan_side", scan_side, "side-picking scan's probes"),
                                    ("scan_side_first", scan_side_first, "side-picking scan's first two probes")):
            if not 0.0 <= value <= 2.0:
                raise ValueError(f"model.{name}={value}: must be in [0, 2] (1 - uz of the {probes}; 0: none)")
        if scan_side_first and not scan_side:
            raise ValueError(f"model.scan_side_first={scan_side_first}: sets the lean of the side-picking scan's first "
                             "two probes, so it needs model.scan_side > 0")
        if scan_side_pair_apart and not scan_side:
            raise ValueError("model.scan_side_pair_apart=True: places the side-picking scan's first two probes, so it "
                             "needs model.scan_side > 0")
        if scan_side and n_probes < 2:
            raise ValueError(f"model.scan_side={scan_side}: the side-picking scan needs model.n_probes >= 2, got "
                             f"{n_probes}")
        if not 0 <= scan_follow_probes < n_probes:
            raise ValueError(f"model.scan_follow_probes={scan_follow_probes}: must be in [0, n_probes - 1 = "
                             f"{n_probes - 1}] (how many probes after the first touch follow it; 0: all of them)")
        if scan_follow_probes and not scan_follow:
            raise ValueError(f"model.scan_follow_probes={scan_follow_probes}: limits the probes following the first "
                             "touch, so it needs model.scan_follow > 0")
        if not scan_options_combine(scan_lean, scan_follow, scan_cross, scan_reach, scan_side):
            raise ValueError(f"model.scan_lean={scan_lean}, model.scan_follow={scan_follow}, model.scan_cross="
                             f"{scan_cross}, model.scan_reach={scan_reach}, model.scan_side={scan_side}: choose one "
                             "way for the scan to adapt (only scan_follow and scan_lean combine)")
        if scan_order not in SCAN_ORDERS:
            raise ValueError(f"model.scan_order={scan_order!r}: expected one of {SCAN_ORDERS}")
        if prior not in ("none", "line_scan"):
            raise ValueError(f"model.prior={prior!r}: expected 'none' or 'line_scan'")
        if not 0.0 <= prior_lean <= 1.5:
            raise ValueError(f"model.prior_lean={prior_lean}: must be in [0, 1.5] (1 - uz of the prior's straight "
                             "probes; 0: uz = 1)")
        if prior_lean and prior != "line_scan":
            raise ValueError(f"model.prior_lean={prior_lean}: needs model.prior: line_scan (it shapes that prior)")
        if prior_exact and prior != "line_scan":
            raise ValueError("model.prior_exact=True: needs model.prior: line_scan (it starts the policy there)")
        if not 0.0 <= mean_action_share < 1.0:
            raise ValueError(f"model.mean_action_share={mean_action_share}: must be in [0, 1) (the share of each "
                             "training batch probed with the policy's mean action; the rest trains the policy)")
        if not 0.0 <= random_probe_share < 1.0 or mean_action_share + random_probe_share >= 1.0:
            raise ValueError(f"model.random_probe_share={random_probe_share}: must be in [0, 1) and leave, beside "
                             f"model.mean_action_share={mean_action_share}, some episodes to train the policy")
        if random_probe_share and location != "candidates":
            raise ValueError(f"model.random_probe_share={random_probe_share} probes with candidates drawn at random, "
                             f"so it needs model.location: candidates, got {location!r}")
        if prior_anchor < 0.0:
            raise ValueError(f"model.prior_anchor={prior_anchor}: must be >= 0 (the weight of the policy mean's squared "
                             "distance from its prior; 0: none)")
        if prior_anchor and prior != "line_scan":
            raise ValueError(f"model.prior_anchor={prior_anchor}: needs model.prior: line_scan (it holds the policy "
                             "near that prior)")
        if prior_anchor_free and not prior_anchor:
            raise ValueError(f"model.prior_anchor_free={list(prior_anchor_free)}: frees components of the anchor, so it "
                             "needs model.prior_anchor > 0")
        if imitate and not (policy == "learned" and policy_warmup_steps and prior == "none"):
            raise ValueError(f"model.imitate={list(imitate)}: a teacher replaces the fixed scan of the warm-up as the "
                             "policy's starting point, so it needs model.policy: learned, model.policy_warmup_steps > 0 "
                             f"and model.prior: none, got policy={policy!r}, policy_warmup_steps={policy_warmup_steps}, "
                             f"prior={prior!r}")
        self.teacher: dict[str, Tensor] | None = None  # its episodes, loaded in setup() (they must match the data)
        if unknown := set(prior_anchor_free) - set(COMPONENTS):
            raise ValueError(f"model.prior_anchor_free: {sorted(unknown)} not among the request's components "
                             f"{list(COMPONENTS)}")

    # -- simulator -----------------------------------------------------------------------------------
    @property
    def sim(self) -> ProbeSimulator | None:
        return self._sim

    @sim.setter
    def sim(self, sim: ProbeSimulator | None) -> None:
        self._sim = sim
        if sim is not None:  # the mirrors need to know where the line is
            self.line_x = sim.scene.probe_x * self.hparams.point_scale

    @property
    def line_x(self) -> float:
        """X of the probe line in point coordinates: what every mirror reflects about (the model's and its touch
        sets', which this keeps in step)."""
        return self._line_x

    @line_x.setter
    def line_x(self, line_x: float) -> None:
        self._line_x = line_x
        for net in (self.touch_set, self.final_touch_set):
            if net is not None:
                net.line_x = line_x

    def setup(self, stage: str) -> None:
        data = self.trainer.datamodule
        if self.sim is None:
            self.sim = data.make_simulator()
        if self.hparams.imitate and stage == "fit" and self.teacher is None:
            self.teacher = load_teacher(list(self.hparams.imitate), data.regions, data.object_set.name,
                                        self.hparams.n_probes, data.noise)
            if isinstance(self.location, CandidateLocationNetwork):  # a choice can copy only its own candidates
                try:
                    self.location.index_of(self.teacher["requests"])
                except ValueError as error:
                    raise ValueError(f"model.imitate={list(self.hparams.imitate)}: {error} (model.candidate_places, "
                                     "candidate_span, candidate_leans must be the teacher's)") from None
        if self.hparams.library_namer and self.library_namer is None:
            self.library_namer = self.build_library_namer(self.hparams.library_namer, data)
        if self.hparams.choice_reads_belief and self.teacher is not None and "beliefs" not in self.teacher:
            start = time.time()
            rank_zero_info(f"model.choice_reads_belief: the namer weighs its {self.library_namer.library.shape[1]} "
                           f"library episodes at every probe of the teacher's {len(self.teacher['labels'])} (once)")
            self.teacher["beliefs"] = self.teacher_beliefs(data)
            rank_zero_info(f"model.choice_reads_belief: the teacher's beliefs read in {time.time() - start:.0f} s")

    def teacher_beliefs(self, data) -> Tensor:
        """(E, N, classes + 4) the library namer's belief after each probe of the teacher's episodes, read in ideal
        mode as the teacher's planner read them: its copy learns each choice beside the belief the planner chose it
        from. Once, in setup (about as long as naming the episodes: the namer weighs its whole library at every
        probe, too slow for every training step)."""
        teacher = self.teacher
        if teacher["faults"] is not None:
            raise ValueError(f"model.choice_reads_belief: the teachers {list(self.hparams.imitate)} read under sensor "
                             "faults; their beliefs are read fault-free only")
        labels, poses = teacher["labels"].numpy(), teacher["poses"].numpy()
        chosen = self.location.index_of(teacher["requests"])
        with ProbeSimulator(data.object_set, 1024, data.scene, "ideal", seed=0) as sim:
            read = torch.from_numpy(readings(sim, labels, poses, self.location.candidates.cpu().numpy()))
        return self.library_namer.beliefs(chosen, read.gather(1, chosen)).cpu()

    def build_library_namer(self, path: str, data) -> LibraryNamer:
        """The namer of the teacher file `path`'s planner over its library, read here in ideal mode as the planner
        read it, naming readings of the data's sensor with its faults (data.noise) in its likelihood. Refuses a
        library of held-out poses, other objects or pose regions, or other candidates."""
        if not Path(path).is_file():
            raise FileNotFoundError(f"model.library_namer: {path}: teacher file not found (write one with "
                                    "scripts/planner_ceiling.py --save-rollouts)")
        meta = teacher_meta([path])
        h = self.hparams
        for field, have, want in (("library_split", meta.get("library_split"), "train"),
                                  ("objects", meta.get("objects"), data.object_set.name),
                                  ("eval_seed", meta.get("eval_seed"), data.regions.seed),
                                  ("places", meta.get("places"), h.candidate_places),
                                  ("span", meta.get("span"), h.candidate_span),
                                  ("leans", meta.get("leans"), list(h.candidate_leans)),
                                  ("along_leans", meta["along_leans"], [])):
            if have != want:
                raise ValueError(f"model.library_namer: {path}: meta {field}={have!r}, this model needs {want!r} "
                                 "(held-out poses must not enter the library; its candidates must be the model's)")
        with ProbeSimulator(data.object_set, 1024, data.scene, "ideal", seed=0) as sim:
            library, labels, positions = teacher_library(meta, sim, data.regions, data.n_classes,
                                                         h.library_namer_episodes)
        half_width = max(data.scene.object_y[1], data.scene.object_x[1])  # the belief's unit of position
        return LibraryNamer(torch.from_numpy(library), torch.from_numpy(labels).long(), data.n_classes,
                            meta["sigma"], meta["mismatch"], data.noise, data.scene.probe_length,
                            positions=torch.from_numpy(positions / half_width).float()).to(self.device)

    def library_readings(self, actions: Tensor, points: Tensor) -> tuple[Tensor, Tensor]:
        """(B, N) the candidates probed (actions (B, N, 4)) and what each read (points (B, N, 4), as a rollout
        holds them), as the planner read its candidates: how far from its requested entry point it touched (metres),
        MISS where nothing was touched."""
        chosen = self.location.index_of(actions)
        entries = torch.from_numpy(self.sim.scene.request_to_probe(self.location.candidates.cpu().numpy())[0])
        entries = entries.to(points)[chosen]
        distance = (points[..., :3] / self.hparams.point_scale - entries).norm(dim=-1)
        return chosen, torch.where(points[..., 3] > 0.5, distance, MISS)

    def library_log_posterior(self, rollout: Rollout) -> Tensor:
        """(B, N, classes) the library namer's log posterior after each probe (the rollout's, if it named them)."""
        if rollout.named is not None:
            return rollout.named
        return self.library_namer(*self.library_readings(rollout.actions, rollout.points))

    def teardown(self, stage: str) -> None:
        if self.sim is not None:
            self.sim.close()
            self.sim = None

    # -- rollout -------------------------------------------------------------------------------------
    def next_actions(self, k: int, points: Tensor, rep_sum: Tensor | None, deterministic: bool | Tensor,
                     generator: torch.Generator, follow_scan: bool = False, actions: Tensor | None = None,
                     beliefs: Tensor | None = None) -> Tensor:
        """Request k + 1 of every episode (k may be 0), given the points (B, N, 4) of the rollout so far and the
        actions (B, N, 4) that probed them (only [:, :k] are read; actions only by a choice reading the probes,
        beliefs (B, N, classes + 4) the namer's after each probe only by one reading them); a
        learned policy reads the sum of the representations after probes 1..k, which the rollout keeps running
        ((V, B, D), one per view of encoder_views()). follow_scan: the fixed scan, whatever the policy."""
        policy, batch = self.hparams.policy, len(points)
        if policy == "random":
            return torch.rand(batch, 4, generator=generator) * 2 - 1
        if policy == "line_scan" or follow_scan:
            return self.scan_requests(points)[:, k]
        extra = exclude = None
        if k > 0:  # what probes 1..k read, beside PCRN's state
            extra, exclude = self.policy_extra(None if actions is None else actions[:, :k], points[:, :k],
                                               last_only=True, beliefs=None if beliefs is None else beliefs[:, :k])
            extra, exclude = (None if t is None else t[:, -1] for t in (extra, exclude))
        mirrored = self.mirrored_states(points[:, :k + 1])[:, k].to(self.device)  # the policy acts in that view
        state = self.location.state(None if rep_sum is None else pick_view(rep_sum, mirrored), k, batch_size=batch,
                                    extra=extra)
        offsets = self.prior_offsets(points)
        offset = None if offsets is None else reflect(offsets[:, k].to(state.device), 1, where=mirrored)
        action = self.location.sample(state, deterministic=deterministic, generator=generator, offset=offset,
                                      exclude=exclude)[0]
        return reflect(action, 1, where=mirrored)

    def policy_extra(self, actions: Tensor | None, points: Tensor, last_only: bool = False,
                     pooled: Tensor | None = None, readings: tuple[Tensor, Tensor] | None = None,
                     beliefs: Tensor | None = None) -> tuple[Tensor | None, Tensor | None]:
        """Beyond the paper, what the policy reads beside PCRN's state: row j, after probes 1..j + 1 of the
        actions and points (B, K, 4) -> features (B, K, E) (the touch set's pooled ones, detached, and / or a
        choice's readings by candidate, then the namer's beliefs (B, K, classes + 4) after the same probes, which
        the rollout keeps) or None, and the candidates probed (B, K, C) the choice excludes, or None.
        last_only: row K - 1 only (K = 1 in the outputs), what a probe loop reads. pooled, readings: the touch set's
        features and the choice's readings (CandidateLocationNetwork.readings) of every row, if computed already."""
        h, features, exclude = self.hparams, [], None
        if h.policy_reads_touch_set:
            if pooled is None:
                pooled = self.touch_set.pooled(points.to(self.device), last_only=last_only)
            features.append(pooled.detach())
        if h.choice_reads_probes:
            if readings is None:
                readings = self.location.readings(actions.to(self.device), points.to(self.device), h.n_probes)
            readings, exclude = readings
            features.append(readings[:, -1:] if last_only else readings)
            exclude = None if h.choice_repeats else exclude[:, -1:] if last_only else exclude
        if h.choice_reads_belief:
            if beliefs is None:
                raise ValueError("model.choice_reads_belief: the rollout holds no beliefs of the library namer")
            features.append((beliefs[:, -1:] if last_only else beliefs).to(self.device))
        return (torch.cat(features, -1) if features else None), exclude

    def prior_offsets(self, points: Tensor) -> Tensor | None:
        """(B, N, 4) pre-tanh means of the learned policy's prior, or None without one. Beyond the paper: the
        policy may start from the fixed scan (`prior: line_scan`) and learn where to deviate from it.

        With `prior_lean`, the prior's straight probes (ux = 0) ask for uz = 1 - prior_lean instead of 1: the same
        probes, since a probe with ux = 0 goes straight down whatever uz, but ux now tilts them linearly (tan(tilt)
        = tan(max_tilt) |ux| prior_lean / 2). At uz = 1 the tilt is a product of ux and 1 - uz, whose gradient
        vanishes at straight down: a saddle the learned policies did not leave (their probes stayed within a degree).

        With `prior_exact`, the policy's mean starts at the scan's requests themselves, so that the probes do not
        move when the policy takes over from the scan the classifier learned behind during a warm-up: the mean
        head starts at zero (LocationNetwork zero_mean), and only requests beyond +-0.9 (uz = 1, the ends of a
        full-span scan) are pulled inside tanh's range, instead of every request shrinking by 0.9."""
        if self.hparams.prior != "line_scan":
            return None
        scan = self.scan_requests(points)
        if self.hparams.prior_lean:
            straight = scan[..., 1:3].abs().sum(-1) == 0
            scan = scan.clone()
            scan[..., 3] = torch.where(straight, 1.0 - self.hparams.prior_lean, scan[..., 3])
        return torch.atanh(scan.clamp(-0.9, 0.9) if self.hparams.prior_exact else 0.9 * scan)

    def scan_requests(self, points: Tensor) -> Tensor:
        """(B, N, 4): the fixed scan's requests, given the points (B, N, 4) its probes returned; request k reads
        only points[:, :k]. Without `scan_follow` it is line_scan_requests() in every episode. With it, the scan
        adapts: from the probe after an episode's first touch on, it probes around the mean y of the touches so
        far, `scan_follow` request units apart, alternating sides (+1, -1, +2, -2, ... steps), in the direction
        of the probe that touched first, because a scan that walks on past the object wastes its probes on bare
        soil. With `scan_follow_probes` K only the K probes after the first touch follow it (the local shape, early)
        and the scan then goes on where it stopped (its last K places are dropped), since touches packed into a few
        centimetres say less about the object than a profile spread over the scan. With `scan_cross`, the two
        probes after the first touch re-enter at its y leaning to +x and to -x,
        then the scan goes on where it stopped: how the surface falls away across the line tells a ball from a
        pipe crossing it, and a leaning probe reaches an object lying off the line. With `scan_reach`, the scan
        goes straight down for its first third; then, while nothing is touched, it leans to +x and -x in turn
        (it may lie off the line), and once something is, it keeps the direction of the probe that first touched.
        With `scan_side`, every probe leans across the line and the scan picks the side the object lies on from
        its first touches (side_picking)."""
        scan = self.line_scan_requests().to(points.device).expand(len(points), -1, -1).clone()
        h = self.hparams
        if not (h.scan_follow or h.scan_cross or h.scan_reach or h.scan_side):  # the plain scan, called at every
            return scan  # probe: no more work
        n = scan.shape[1]
        touched = (points[..., 3] > 0.5).float()
        first = torch.where(touched.any(1), touched.argmax(1), torch.full_like(touched[:, 0], n, dtype=torch.long))
        if h.scan_cross:
            return self.cross_checked(scan, first)
        if h.scan_reach:
            return self.reaching(scan, first)
        if h.scan_side:
            return self.side_picking(scan, points, first)
        step = h.scan_follow
        before = torch.cumsum(touched, 1) - touched  # touches among probes 1..k-1, for request k
        y_sum = torch.cumsum(touched * points[..., 1], 1) - touched * points[..., 1]
        mean_py = self.sim.scene.line_request(y_sum / before.clamp(min=1) / self.hparams.point_scale)
        k = torch.arange(n, device=points.device)
        j = k - first[:, None] - 1  # follow-up probe index, -1 at the first touch
        sides = torch.where(j % 2 == 0, j // 2 + 1, -(j // 2 + 1)).float()  # +1, -1, +2, -2, ...
        follow = (before > 0)[..., None]
        # a follow-up probe keeps the direction of the probe that first touched: if a leaning probe found the object
        # off the line, a straight one at the same y would miss it
        direction = scan.gather(1, first.clamp(max=n - 1)[:, None, None].expand(-1, n, 4))
        followed = torch.cat([(mean_py + step * sides).clamp(-1, 1)[..., None], direction[..., 1:]], -1)
        if h.scan_follow_probes:  # the K follow-ups, then request k is the scan's request k - K
            follow = follow & (j < h.scan_follow_probes)[..., None]
            resumed = torch.where(j >= h.scan_follow_probes, k - h.scan_follow_probes, k)
            scan = scan.gather(1, resumed[..., None].expand(-1, -1, 4))
        return torch.where(follow, followed, scan)

    def cross_checked(self, scan: Tensor, first: Tensor) -> Tensor:
        """(B, N, 4) scan with the cross-check probes inserted after each episode's first touch (index `first`,
        N if none): request first + 1 leans to +x and first + 2 to -x at the touching probe's py; request k >
        first + 2 is the scan's request k - 2."""
        n, lean = scan.shape[1], self.hparams.scan_cross
        k = torch.arange(n, device=scan.device).expand(len(first), n)
        offset = (k - first[:, None]).clamp(0, 3)  # 0: up to the touch, 1 and 2: the cross-checks, 3: after them
        shifted = scan.gather(1, torch.where(offset == 3, k - 2, k)[..., None].expand(-1, -1, 4))
        py = scan[..., 0].gather(1, first.clamp(max=n - 1)[:, None]).expand(-1, n)
        ux = torch.where(offset == 1, 1.0, -1.0)
        cross = torch.stack([py, ux, torch.zeros_like(py), torch.full_like(py, 1.0 - lean)], -1)
        return torch.where(((offset == 1) | (offset == 2))[..., None], cross, shifted)

    def reaching(self, scan: Tensor, first: Tensor) -> Tensor:
        """(B, N, 4) straight scan whose probes from N // 3 on lean to +x and -x in turn until a probe touches
        (index `first`, N if none); from then on they keep the touching probe's direction."""
        n, straight = scan.shape[1], scan.shape[1] // 3
        k = torch.arange(n, device=scan.device).expand(len(first), n)
        g = torch.minimum(k, first[:, None])  # the probe whose direction request k takes: itself until a touch
        leaning = g >= straight
        ux = torch.where(leaning, torch.where((g - straight) % 2 == 0, 1.0, -1.0), 0.0)
        uz = torch.where(leaning, 1.0 - self.hparams.scan_reach, 1.0)
        return torch.stack([scan[..., 0], ux, torch.zeros_like(ux), uz], -1)

    def side_picking(self, scan: Tensor, points: Tensor, first: Tensor) -> Tensor:
        """(B, N, 4): the scan with every probe leaning across the line (uz = 1 - scan_side), towards the side the
        object lies on once a touch tells it. Straight probes see only the slice of the object under the line, which
        for an object lying off it looks alike across classes; a probe leaning its way cuts it nearer the middle
        (scan_coverage.py --aims). The first two probes enter at the scan's first place leaning to +x, then -x;
        the later ones take the scan's places from its second on (its last is dropped). While nothing is touched
        the probes alternate +x and -x; after the first touch (index `first`, N if none) they all lean to its
        side, or, when both of the first two probes touched, to the side of the higher touch: a probe leaning
        towards the object meets its surface before one leaning away. With `scan_side_first` the first two lean by
        that instead, and only they pick the side: a steeper pair names it more often right when it touches
        (scan_coverage.py --fit-target side), and if neither touched the rest go straight down, because a probe
        leaning the wrong way misses what a straight one grazes. With `scan_side_pair_apart` the pair takes the
        scan's first two places instead of one (the scan keeps its last), so every place is probed; it names the side
        as well but reads worse (scan_coverage.py --side-pairs, docs/training.md): two probes entering at one place
        from both sides read the object's cross-section there."""
        n, lean = scan.shape[1], self.hparams.scan_side
        first_lean = self.hparams.scan_side_first or lean
        k = torch.arange(n, device=scan.device)
        alternate = torch.where(k % 2 == 0, 1.0, -1.0)
        touched, z = points[..., 3] > 0.5, points[..., 2]
        both = (first == 0) & touched[:, 1]
        found = torch.where(both, torch.where(z[:, 0] >= z[:, 1], 1.0, -1.0), alternate[first.clamp(max=n - 1)])
        decided = (first[:, None] < k) & (k >= 2)  # request k reads probes 1..k only: both first ones from k = 2
        ux = torch.where(decided, found[:, None], alternate)
        uz = torch.where(k < 2, 1.0 - first_lean, 1.0 - lean).expand_as(ux)
        if self.hparams.scan_side_first:  # the pair alone picks the side; if it touched nothing, straight down
            straight = (first[:, None] >= 2) & (k >= 2)
            ux, uz = torch.where(straight, 0.0, ux), torch.where(straight, 1.0, uz)
        py = scan[:, k if self.hparams.scan_side_pair_apart else (k - 1).clamp(min=0), 0]
        return torch.stack([py, ux, torch.zeros_like(ux), uz], -1)

    def line_scan_requests(self) -> Tensor:
        """(N, 4): probes evenly spaced over the middle `scan_span` of the probe line, swept from one end (the
        paper's kind of scan) or `centre_out` (nearest the centre first, alternating sides), which meets objects
        centred near the line's middle in the first probes instead of half-way through; or `coarse_first`: every
        second point of the same grid centre-out, then the points between, so that the first half of the probes
        already spans the whole scan (where the object ends) and the second half fills in its profile. Straight
        down, or with `scan_lean` fanned across the line (tan(tilt) = tan(max tilt) * scan_lean / 2: 11 degrees
        for 0.4)."""
        n, span, lean = self.hparams.n_probes, self.hparams.scan_span, self.hparams.scan_lean
        py = torch.linspace(-span, span, n) if n > 1 else torch.zeros(1)
        if self.hparams.scan_order != "sweep":
            rank = py.abs()
            if self.hparams.scan_order == "coarse_first":  # the pass holding the point nearest the centre goes first
                index = torch.arange(n)
                rank = rank + 2 * span * ((index - int(rank.argmin())) % 2)
            py = py[torch.argsort(rank, stable=True)]
        # scan_lean > 0 fans the scan across the line: of every three probes one goes straight down, one leans
        # towards +x and one towards -x, reaching objects lying off the line (ux = +-1, uz = 1 - scan_lean)
        ux = torch.tensor([0.0, 1.0, -1.0]).repeat(n)[:n] if lean > 0 else torch.zeros(n)
        uz = torch.where(ux == 0, torch.ones(n), torch.full((n,), 1.0 - lean))
        return torch.stack([py, ux, torch.zeros(n), uz], 1)

    @torch.no_grad()
    def rollout(self, labels: Tensor, poses: Tensor, seed: int, deterministic: bool | Tensor = False,
                follow_scan: bool = False, requests: Tensor | None = None, faults: Tensor | None = None,
                beliefs: Tensor | None = None) -> Rollout:
        """Probe B episodes N times with the current policy (or the fixed scan: follow_scan, or the given (B, N, 4)
        requests: a teacher's, or some episodes' with the others' rows NaN, left to the policy); the batch seed
        drives sampling and sensor noise, or the sensor's faults are the given (B, N, 2) uniforms (a teacher's,
        ProbeSimulator.probe). deterministic: the mean action, in every episode or in the (B,) True ones. A choice
        reading the namer's belief gets the given `beliefs` (B, N, classes + 4) (a teacher's, with all its requests),
        or the namer weighs its library after every probe as the rollout goes, and names the episodes on the way
        (Rollout.named, which library_log_posterior then need not weigh again)."""
        sim, n = self.sim, self.hparams.n_probes
        batch = len(labels)
        sim.reset(labels.cpu().numpy(), poses.cpu().numpy(), seed=seed)
        generator = torch.Generator().manual_seed(seed)
        actions, points = torch.zeros(batch, n, 4), torch.zeros(batch, n, 4)
        reached = torch.ones(batch, n, dtype=torch.bool)
        memory = rep_sum = None  # the encoder's memory of the probes so far, and the sum of its outputs
        requests = None if requests is None else requests.cpu()
        given = None if requests is None else torch.isfinite(requests).all(-1).all(-1)  # (B,) episodes given
        policy_probes = given is None or not given.all()
        log_w = named = None  # the library namer's log weights after the probes so far, if a choice reads its belief
        if self.hparams.choice_reads_belief and beliefs is None:
            n_classes = self.library_namer.one_hot.shape[1]
            beliefs, named = torch.zeros(batch, n, n_classes + 4), torch.zeros(batch, n, n_classes)
            log_w = torch.zeros(batch, self.library_namer.library.shape[1], device=self.library_namer.library.device)
        for k in range(n):
            action = requests[:, k] if requests is not None else None
            if policy_probes:
                chosen = self.next_actions(k, points, rep_sum, deterministic, generator, follow_scan, actions,
                                           beliefs).cpu()
                action = chosen if action is None else torch.where(given[:, None], action, chosen)
            if not torch.isfinite(action).all():
                raise FloatingPointError(f"non-finite probe request from the '{self.hparams.policy}' policy at probe "
                                         f"{k + 1}, global step {self.global_step}")
            actions[:, k] = action
            result = sim.probe(action.clamp(-1, 1).double().numpy(), None if faults is None else faults[:, k].numpy())
            points[:, k] = torch.from_numpy(result.points).float()
            points[:, k, :3] *= self.hparams.point_scale  # the policy must see what evaluate() will see
            if sim.arm is not None:
                reached[:, k] = torch.from_numpy(achieved(result.pose_error))
            if log_w is not None:
                probed, read = self.library_readings(action.clamp(-1, 1)[:, None], points[:, k:k + 1])
                self.library_namer.update(log_w, probed[:, 0].to(log_w.device), read[:, 0].to(log_w.device))
                beliefs[:, k] = self.library_namer.belief(log_w).cpu()
                named[:, k] = self.library_namer.log_posterior(log_w).cpu()
            if self.hparams.policy == "learned" and not follow_scan and policy_probes and k + 1 < n:  # once
                # (evaluate() redoes the whole sequence with gradients); the last one is never read by the policy
                views = self.encoder_views(action.clamp(-1, 1).to(self.device),
                                           self.encoder_points(points[:, :k + 1])[:, k].to(self.device))
                memory = memory or [None] * len(views)
                steps = [self.encoder.step(r, p, m) for (r, p), m in zip(views, memory)]
                rep, memory = torch.stack([r for r, _ in steps]), [m for _, m in steps]
                rep_sum = rep if rep_sum is None else rep_sum + rep
        device = self.device
        return Rollout(actions.to(device), actions.clamp(-1, 1).to(device), points.to(device), reached.to(device),
                       *(None if t is None else t.to(device) for t in (beliefs, named)))

    def encoder_points(self, points: Tensor) -> Tensor:
        """The points as the encoder reads them: in the episode frame (the paper) or relative to the first touch."""
        return relative_to_first_touch(points) if self.hparams.point_frame == "first_touch" else points

    def encoder_views(self, requests: Tensor, points: Tensor) -> list[tuple[Tensor, Tensor]]:
        """The (requests, points) the encoder reads, (..., 4) each: the episode, and with `mirror_encoder` also its
        mirror image across the probe line (X -> 2 line_x - X, Ux -> -Ux). Beyond the paper: the prefixes whose
        touches lie to -x are read in the second view (mirrored_prefixes), and the policy acts in it, so an object
        off the line to -x is probed and named as its mirror image to +x, which hg4's mirror-symmetric shapes allow."""
        views = [(requests, points)]
        if self.hparams.mirror_encoder:
            views.append((reflect(requests, 1), reflect(points, 0, self.line_x)))
        return views

    def mirrored_prefixes(self, points: Tensor) -> Tensor:
        """(B, N) bool: the prefixes (probes 1..k+1 for row k) read in the mirrored view; none without
        `mirror_encoder`."""
        if not self.hparams.mirror_encoder:
            return torch.zeros(points.shape[:2], dtype=torch.bool, device=points.device)
        return left_of_line(points, self.line_x)

    def mirrored_states(self, points: Tensor) -> Tensor:
        """(B, N) bool: the policy states s_k (reading probes 1..k) in the mirrored view: mirrored_prefixes one
        probe later (s_0 reads nothing)."""
        return F.pad(self.mirrored_prefixes(points)[:, :-1], (1, 0), value=False)

    def policy_states(self, rep: Tensor, mirrored: Tensor, extra: Tensor | None = None) -> Tensor:
        """(B, N, D'): every s_k of a rollout at once, from the encoder's views (V, B, N, D) of it (encode()) and
        the states read mirrored (B, N) (mirrored_states()): the state the rollout sampled request k + 1 from."""
        return pick_view(torch.stack([self.location.states(r, extra) for r in rep]), mirrored)

    def encode(self, rollout: Rollout) -> Tensor:
        """(V, B, N, D): the encoder's representation after each probe, in each view of encoder_views()."""
        views = self.encoder_views(rollout.requests, self.encoder_points(rollout.points))
        return torch.stack([self.encoder(r, p) for r, p in views])

    # -- loss ----------------------------------------------------------------------------------------
    def evaluate(self, rollout: Rollout, labels: Tensor, learn_policy: bool | Literal["imitate"] = True,
                 sampled: Tensor | None = None) -> tuple[dict[str, Tensor], Tensor]:
        """Forward pass over a finished rollout: the loss terms (without the policy's when not learn_policy) and
        the logits (B, N, C). sampled (B,) bool: the episodes that train the policy (default: all). "imitate": the
        rollout's requests are a teacher's, and the policy learns to copy them (its imitation_loss) instead of
        learning by REINFORCE."""
        logits = pooled = rep = None
        if self.classifier is not None:  # (else the policy is fixed and nothing reads the encoder)
            rep = self.encode(rollout)
            # each prefix is read whole in its view: a classifier pooling the probes so far (PCRN-FC) pools them all
            # in the same one
            logits = pick_view(torch.stack([self.classifier(r) for r in rep]), self.mirrored_prefixes(rollout.points))
        if self.touch_set is not None:
            pooled = self.touch_set.pooled(rollout.points)
            read = self.touch_set.read(pooled)
            logits = read if logits is None else logits + read
        if self.final_touch_set is not None:  # replaces the prediction after the last probe
            final = self.final_touch_set.read(self.final_touch_set.pooled(rollout.points, last_only=True))
            logits = torch.cat([logits[:, :-1], final], 1)
        readings = None
        if self.along_line_classifier is not None:  # (the choice reads the same readings, below)
            readings = self.location.readings(rollout.actions, rollout.points, self.hparams.n_probes)
            logits = logits + self.along_line_classifier(readings[0])
        log_pi = baseline = None
        if self.hparams.policy == "learned" and learn_policy:
            # s_k from which request k was drawn; beyond the paper, the policy may read it without training the encoder
            # and the touch set's pooled features, which learn from the cross-entropy only
            extra, exclude = self.policy_extra(rollout.actions, rollout.points, pooled=pooled, readings=readings,
                                               beliefs=rollout.beliefs)
            mirrored = self.mirrored_states(rollout.points)  # the policy drew each request in its state's view
            states = self.policy_states(rep.detach() if self.hparams.policy_reads_detached else rep, mirrored, extra)
            offsets = self.prior_offsets(rollout.points)
            offsets = None if offsets is None else reflect(offsets, 1, where=mirrored)
            actions = reflect(rollout.actions, 1, where=mirrored)  # in the view the policy drew them in
            if exclude is not None:  # state s_k excludes what probes 1..k probed (s_0 nothing)
                exclude = F.pad(exclude[:, :-1], (0, 0, 1, 0), value=False)
            log_pi, mu, sigma = self.location.log_prob_and_moments(states, actions, offsets, exclude)
            baseline = self.baseline(states.detach())
        h = self.hparams
        # the gradient of log N grows as 1 / std: a shrinking std must not let the policy term crowd the others
        # out of the clipped gradient
        beta = h.beta * float(self.location.std_scale)
        if learn_policy == "imitate":
            terms = hybrid_loss(logits, labels, None, None, h.gamma, beta, ce_prefixes=h.ce_prefixes)
            terms["loss_imitation"] = self.location.imitation_loss(log_pi, mu, actions)
            terms["loss"] = terms["loss"] + terms["loss_imitation"]
        else:
            terms = hybrid_loss(logits, labels, log_pi, baseline, h.gamma, beta, h.normalize_advantage, h.reward,
                                sampled, h.ce_prefixes)
        if log_pi is not None:
            sigma = sigma.detach().mean((0, 1))  # too large a std is the usual cause of poor accuracy: watch it
            terms.update({f"std_{c}": sigma[i] for i, c in enumerate(COMPONENTS)})
            if offsets is not None:
                # how far the mean policy has moved from its prior (request units, squared, summed over components);
                # beyond the paper, `prior_anchor` charges for it, so the policy leaves the scan its classifier
                # learned behind only where the reward pays for the move, except in the components
                # `prior_anchor_free` leaves to the policy (the lean, say, whose size the scan fixes by hand)
                shift = (mu - torch.tanh(offsets)).pow(2)
                terms["prior_shift"] = shift.detach().sum(-1).mean()
                if h.prior_anchor:
                    held = torch.tensor([c not in h.prior_anchor_free for c in COMPONENTS], device=shift.device)
                    terms["loss"] = terms["loss"] + h.prior_anchor * (shift * held).sum(-1).mean()
        return terms, logits

    def training_step(self, batch: dict[str, Tensor], batch_idx: int) -> Tensor:
        labels = batch["labels"]
        # beyond the paper: a learned policy may first leave the probing to the fixed scan (its prior), untrained,
        # so that the classifier learns on steady probes before the policy starts to move them
        warming_up = self.hparams.policy == "learned" and self.global_step < self.hparams.policy_warmup_steps
        self.location.std_scale.fill_(self.std_schedule())
        # beyond the paper: a share of the episodes is probed with the policy's mean action, the probes it is tested
        # with, so that the classifier does not learn only behind the exploration noise of the sampled ones
        mean_rows = None
        if self.hparams.policy == "learned" and not warming_up and self.hparams.mean_action_share:
            n_mean = min(round(self.hparams.mean_action_share * len(labels)), len(labels) - 1)  # >= 1 sampled
            mean_rows = torch.arange(len(labels)) < n_mean
        poses, requests, faults, beliefs, learn_policy = batch["poses"], None, None, None, not warming_up
        # beyond the paper: a share of the episodes probed with distinct candidates drawn at random trains the
        # classifiers only, so that they also read probes their policy rarely sends (as it may on held-out poses)
        random_rows = None
        if self.hparams.policy == "learned" and not warming_up and self.hparams.random_probe_share:
            n_random = max(1, round(self.hparams.random_probe_share * len(labels)))
            random_rows = torch.arange(len(labels)) >= len(labels) - n_random
            requests = self.random_candidates(random_rows, int(batch["seed"]))
        if warming_up and self.teacher is not None:  # the teacher's episodes in turn, with the requests it chose
            rows = (self.global_step * len(labels) + torch.arange(len(labels))) % len(self.teacher["labels"])
            labels, poses, requests = (self.teacher[k][rows].to(labels.device) for k in ("labels", "poses", "requests"))
            faults = None if self.teacher["faults"] is None else self.teacher["faults"][rows]  # what it read under noise
            beliefs = self.teacher["beliefs"][rows] if "beliefs" in self.teacher else None  # what the namer made of it
            learn_policy = "imitate"
        rollout = self.rollout(labels, poses, int(batch["seed"]), follow_scan=warming_up and requests is None,
                               deterministic=False if mean_rows is None else mean_rows, requests=requests,
                               faults=faults, beliefs=beliefs)
        held = [rows for rows in (mean_rows, random_rows) if rows is not None]  # episodes not training the policy
        terms, _ = self.evaluate(rollout, labels, learn_policy=learn_policy,
                                 sampled=~torch.stack(held).any(0).to(labels.device) if held else None)
        if not torch.isfinite(terms["loss"]):
            raise FloatingPointError(f"non-finite loss {terms['loss'].item()} at global step {self.global_step} "
                                     f"(terms: { {k: round(v.item(), 4) for k, v in terms.items()} })")
        size = len(labels)
        self.log_dict({f"train/{k}": v for k, v in terms.items()}, batch_size=size, prog_bar=False)
        self.log("train/touch_rate", rollout.points[..., 3].mean(), batch_size=size)
        self.log("train/reach_rate", rollout.reached.float().mean(), batch_size=size)
        self.log("train/lr", self.optimizers().param_groups[0]["lr"], batch_size=size)
        return terms["loss"]

    def random_candidates(self, rows: Tensor, seed: int) -> Tensor:
        """(B, N, 4) requests: in the True rows of rows (B,) N distinct candidates drawn at random (from the batch
        seed), NaN elsewhere (left to the policy)."""
        generator = torch.Generator().manual_seed(seed + 7919)  # not the rollout's own draws
        candidates = self.location.candidates.cpu()
        requests = torch.full((len(rows), self.hparams.n_probes, 4), torch.nan)
        for row in rows.nonzero()[:, 0]:
            requests[row] = candidates[torch.randperm(len(candidates), generator=generator)[:self.hparams.n_probes]]
        return requests

    def std_schedule(self) -> float:
        """The factor on the policy's std at this step. Beyond the paper: it falls linearly from 1 when the policy
        starts learning (after any warm-up) to `std_final_scale` at the last step, so that the policy explores
        early and the classifier ends up trained behind the steady probes it is tested with."""
        final = self.hparams.std_final_scale
        if final == 1.0:
            return 1.0
        last, start = self.trainer.max_steps, self.hparams.policy_warmup_steps
        if last is None or last < 0:
            raise ValueError(f"model.std_final_scale={final} needs trainer.max_steps (the schedule ends there), "
                             f"got trainer.max_steps={last}")
        # a run that ends within the warm-up never trains the policy: it is tested at the final std
        progress = min(max((self.global_step - start) / (last - start), 0.0), 1.0) if last > start else 1.0
        return 1.0 + (final - 1.0) * progress

    def on_load_checkpoint(self, checkpoint: dict) -> None:
        """Checkpoints written before the std schedule existed hold no std scale: theirs was 1."""
        checkpoint["state_dict"].setdefault("location.std_scale", torch.ones(()))

    def _eval_step(self, batch: dict[str, Tensor], stage: str) -> dict[bool, tuple[Rollout, Tensor]]:
        """Single-rollout accuracy after each probe: the stochastic policy, and for a learned policy also the
        mean-action policy, each labelled; never an average over several rollouts. Returns {deterministic:
        (rollout, logits)}, which callbacks (ProbeMaps) get as the step's outputs instead of rolling out again."""
        labels, seed, scored = batch["labels"], int(batch["seed"]), {}
        variants = [("", False)] + ([("_mean_action", True)] if self.hparams.policy == "learned" else [])
        for suffix, deterministic in variants:
            rollout = self.rollout(labels, batch["poses"], seed, deterministic=deterministic)
            _, logits = self.evaluate(rollout, labels)
            metrics = {}
            if self.library_namer is not None:
                named = self.library_log_posterior(rollout)
                if not deterministic:  # the namer alone on the same probes: what our classifier adds, or costs
                    alone = (named.argmax(-1) == labels[:, None]).float().mean(0)
                    metrics |= {f"{stage}/acc_namer@{k + 1}": alone[k] for k in range(len(alone))}
                logits = logits + named
            scored[deterministic] = (rollout, logits.detach())
            correct = (logits.argmax(-1) == labels[:, None]).float().mean(0)
            metrics |= {f"{stage}/acc{suffix}@{k + 1}": correct[k] for k in range(len(correct))}
            metrics[f"{stage}/acc{suffix}"] = correct[-1]
            metrics[f"{stage}/touch_rate{suffix}"] = rollout.points[..., 3].mean()
            self.log_dict(metrics, batch_size=len(labels), sync_dist=True)
        return scored

    def validation_step(self, batch: dict[str, Tensor], batch_idx: int) -> dict[bool, tuple[Rollout, Tensor]]:
        return self._eval_step(batch, "val")

    def test_step(self, batch: dict[str, Tensor], batch_idx: int) -> dict[bool, tuple[Rollout, Tensor]]:
        return self._eval_step(batch, "test")

    def configure_optimizers(self) -> torch.optim.Optimizer | dict:
        """Adam; beyond the paper, the location network may learn on a slower time scale than the classifier, and
        every learning rate may fall along a half cosine to `lr_final_scale` of itself at the last step: a classifier
        fed fresh episodes every step keeps some of the noise of its last updates unless the steps shrink."""
        location = list(self.location.parameters())  # a list, not a set: the order must survive a resume
        rest = [p for p in self.parameters() if all(p is not q for q in location)]
        optimizer = torch.optim.Adam([{"params": rest},
                                      {"params": location, "lr": self.hparams.lr * self.hparams.policy_lr_scale}],
                                     lr=self.hparams.lr)
        final = self.hparams.lr_final_scale
        if final == 1.0:
            return optimizer
        last = self.trainer.max_steps
        if last is None or last < 1:
            raise ValueError(f"model.lr_final_scale={final} needs trainer.max_steps (the schedule ends there), got "
                             f"trainer.max_steps={last}")

        def factor(step: int) -> float:
            return final + (1.0 - final) * 0.5 * (1.0 + math.cos(math.pi * min(step / last, 1.0)))

        return {"optimizer": optimizer,
                "lr_scheduler": {"scheduler": torch.optim.lr_scheduler.LambdaLR(optimizer, factor), "interval": "step"}}
