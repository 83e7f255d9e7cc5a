"""How often probes touch the buried object: fixed scans, and the policies of trained checkpoints.

A classifier can only name an object it has touched, so the touches a scan collects, and how early, bound what
the line-scan baselines and the policies started from them (`model.prior: line_scan`) can reach. For each fixed
scan (`model.scan_span` x `model.scan_order` x `model.scan_lean` x `model.scan_follow` (x `_probes`) x
`model.scan_cross` x `model.scan_reach` x `model.scan_side` x `model.scan_side_first` x
`model.scan_side_pair_apart`, as in
`HapticGlance.scan_requests`) and for each checkpoint's mean-action policy (`--ckpt`), on the same episodes of a
pose split: mean touches per episode after all probes and after half of them, the share of episodes with at
least one touch, the mean tilt of the requests from vertical, and the share of the leaning probes that lean
towards the object's side.
For a checkpoint also its accuracy after all probes on those rollouts,
split by how many probes touched (a classifier can only be as good as what it touched) and by how far the
object lies off the probe line; for a learned policy started from a scan, also how far its requests moved from
that scan and its classifiers' accuracy when fed that scan instead (what the policy adds). Seconds on one core.

With `--fit EPISODES`, also how much a fixed scan's probes can say about the class: a PointNet (hg/nets, with
BatchNorm and dropout; or `--fit-net touch_set*`, one of the model's touch-set classifiers) trained supervised on the
scan's probes in EPISODES episodes of the training split (`--fit-split`), each probe as (X, Y, Z relative to the
mean of the touched points, T), and scored after its last epoch on the episodes above. It does not depend on the
policy being learned or on the classifier keeping up with it, so it tells whether a target is out of reach of a
kind of scan. Minutes per scan for 16384 episodes.
`--fit-net knn` trains nothing: each episode takes the vote of its `--fit-k` nearest fit episodes, probe by probe
where they are. With the fit episodes drawn from the scored split (`--fit-split val`) and a million or more of them
it approaches the best any classifier of the scan's probes can do (a ceiling to read a trained classifier against,
not a classifier: it has seen the held-out poses).

With `--aims`, also the scan aimed by an oracle that reads the object's pose: every probe leans across the line
towards the object's centre, by a fixed lean (a number, in request units as `model.scan_lean`) or by exactly the
lean that takes it under the centre (`exact`); or, for a side-picking scan (`side`), its own probes with the side
from the pose. Not a policy: a bound on what a policy that picks the side (and
the lean) of each probe from what it touched could reach with the same scan. `--fit-target side` (with
`--fit-probes K`) asks instead how well a scan's first K probes tell that side, on the episodes whose object lies
at least 5 cm off the line: fitted, and by the side-picking scan's rule without a fit (the side the first leaning
probe that touched leans to), so no split's base rates enter it.

    .venv/bin/python scripts/scan_coverage.py                        # 512 val episodes, ideal mode
    .venv/bin/python scripts/scan_coverage.py --mode arm --split test
    .venv/bin/python scripts/scan_coverage.py --spans 0.5 --leans 0 0.4 --episodes 2048   # the fanned scan
    .venv/bin/python scripts/scan_coverage.py --spans 0.5 --follows 0 0.05     # the scan following the touches
    .venv/bin/python scripts/scan_coverage.py --spans 0.5 --crosses 0 1     # cross-checking its first touch
    .venv/bin/python scripts/scan_coverage.py --spans 0.5 --reaches 0 1     # leaning while it touches nothing
    .venv/bin/python scripts/scan_coverage.py --spans 0.5 --sides 0 0.6     # leaning to the side it found
    .venv/bin/python scripts/scan_coverage.py --spans 0.5 --sides 0.6 --side-firsts 1   # ... found by a steeper pair
    .venv/bin/python scripts/scan_coverage.py --spans 0.5 --sides 0.6 --side-firsts 1 --side-pairs same apart  # pair apart
    .venv/bin/python scripts/scan_coverage.py --ckpt runs/table1/pcrn_fc_plus-seed0/checkpoints/best-step7500.ckpt
    .venv/bin/python scripts/scan_coverage.py --spans 0.5 --fit 16384 --episodes 4096   # what the scan can say
    .venv/bin/python scripts/scan_coverage.py --spans 0.5 --aims 0 0.6 exact --fit 16384   # ... aimed by an oracle
    .venv/bin/python scripts/scan_coverage.py --spans 0.5 --fit 1048576 --fit-net knn --fit-split val  # ... at best
    .venv/bin/python scripts/scan_coverage.py --spans 0.5 --sides 0.6 --side-firsts 1 --aims 0 side   # ... its side
    .venv/bin/python scripts/scan_coverage.py --spans 0.5 --sides 0.6 --fit 16384 --fit-target side --fit-probes 4

Last line: JSON {"<order>-span<span>[-lean<lean>][-follow<follow>][-cross<cross>][-reach<reach>][-side<side>]
[-first<first>][-apart][-aim<aim>]" or "<checkpoint>": {"touches": .., "touches_first_half": .., "any_touch": ..,
"tilt_deg": .., "towards_object": ..[, "fit_accuracy" or "fit_side_accuracy": ..][, "first_touch_side": {"share": ..,
"accuracy": ..}][, "accuracy": .., "by_touches": {"0-1": {"share": .., "accuracy": ..}, ...}, "by_offset_cm":
{"0-5": {...}, "5-10": .., "10+": ..}][, "prior_shift_rms": {"py": .., "ux": .., "uy": .., "uz": ..},
"accuracy_on_prior_scan": ..]}, ...}.
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from hg.lightning.module import COMPONENTS, SCAN_ORDERS, HapticGlance, scan_options_combine  # noqa: E402
from hg.nets.pointcloud import PointNet, TouchSetClassifier  # noqa: E402
from hg.provenance import repo_path  # noqa: E402
from hg.sim import PoseRegions, ProbeSimulator, sample_episodes  # noqa: E402


TOUCH_BINS = ((0, 1), (2, 3), (4, 5), (6, 10**6))  # touches per episode, inclusive
OFFSET_BINS = ((0.0, 0.05), (0.05, 0.10), (0.10, 10.0))  # |object X - probe line X| in metres, [low, high)
MIN_LEAN_DEG = 1.0  # a probe tilted more than this from straight down leans
SIDE_MIN_OFFSET = 0.05  # --fit-target side is scored where the object lies at least this far off the line (m)


def right_after_last_probe(model: HapticGlance, rollout, labels: torch.Tensor) -> np.ndarray:
    """(episodes,) whether the model's classifiers name each episode's object after the rollout's last probe."""
    with torch.no_grad():
        return (model.evaluate(rollout, labels, learn_policy=False)[1][:, -1].argmax(-1) == labels).numpy()


def policy_probes(model: HapticGlance, sim: ProbeSimulator, labels: np.ndarray, poses: np.ndarray, seed: int = 0
                  ) -> tuple[torch.Tensor, np.ndarray, np.ndarray, dict[str, float] | None]:
    """(episodes, probes, 4) points and (episodes, probes, 3) unit probe directions of the model's policy (mean
    action for a learned one) on these episodes, (episodes,) whether its prediction after the last probe is
    right (meaningful for a trained checkpoint only), and, for a learned policy with a prior, how far its requests
    lie from the prior's: the root mean square per request component (py, ux, uy, uz), in request units."""
    model.sim = sim
    labels_t = torch.from_numpy(labels)
    rollout = model.rollout(labels_t, torch.from_numpy(poses), seed=seed, deterministic=True)
    correct = right_after_last_probe(model, rollout, labels_t)
    shift = None
    if model.hparams.policy == "learned" and model.hparams.prior != "none":
        prior = torch.tanh(model.prior_offsets(rollout.points))  # the requests of the mean policy it started from
        rms = (rollout.requests - prior).pow(2).mean((0, 1)).sqrt()
        shift = {c: round(float(v), 4) for c, v in zip(COMPONENTS, rms)}
    requests = rollout.requests.double().numpy()
    directions = sim.scene.request_to_probe(requests.reshape(-1, 4))[1]
    return rollout.points, directions.reshape(*requests.shape[:2], 3), correct, shift


def accuracy_on_prior_scan(model: HapticGlance, sim: ProbeSimulator, labels: np.ndarray, poses: np.ndarray,
                           seed: int = 0) -> float:
    """Accuracy after the last probe of a learned checkpoint's classifiers fed the fixed scan its policy started from
    (`model.prior: line_scan`) instead of its policy's probes: what the policy's own probes add over that scan."""
    model.sim = sim
    labels_t = torch.from_numpy(labels)
    rollout = model.rollout(labels_t, torch.from_numpy(poses), seed=seed, follow_scan=True)
    return float(right_after_last_probe(model, rollout, labels_t).mean())


class OracleAimedScan(HapticGlance):
    """The fixed scan with every probe leaning across the line (x) towards the object's centre, read from the
    pose: by `aim` request units (the side from the oracle), or, with aim "exact", by the lean whose probe passes
    under the line at the centre's (X, Z), so the probes profile the object through its middle wherever it lies."""

    def __init__(self, aim: str, **scan) -> None:
        super().__init__(**scan)
        self.aim = aim

    def rollout(self, labels: torch.Tensor, poses: torch.Tensor, seed: int, deterministic: bool = False,
                follow_scan: bool = False):
        scene = self.sim.scene
        off, depth = poses[:, 0].double() - scene.probe_x, -poses[:, 2].double()
        if self.aim == "exact":  # tan(tilt) = tan(max_tilt) |ux| when uy = 0, uz = -1 (request_to_probe)
            ux, uz = (off / depth / np.tan(np.radians(scene.max_tilt_deg))).clamp(-1, 1).float(), -1.0
        else:  # as model.scan_lean: ux the lean, uz 0 (half the tilt range)
            ux, uz = float(self.aim) * torch.sign(off).float(), 0.0
        self.direction = torch.stack([ux, torch.zeros_like(ux), torch.full_like(ux, uz)], -1)  # (ux, uy, uz)
        return super().rollout(labels, poses, seed, deterministic, follow_scan)

    def next_actions(self, *args, **kwargs) -> torch.Tensor:
        action = super().next_actions(*args, **kwargs).clone()
        action[:, 1:] = self.direction
        return action


class OracleSidedScan(HapticGlance):
    """A side-picking scan (model.scan_side) that keeps its first pair and its leans, but whose later probes all lean
    to the side read from the pose: what the pair costs, apart from the sides it gets wrong."""

    def rollout(self, labels: torch.Tensor, poses: torch.Tensor, seed: int, deterministic: bool = False,
                follow_scan: bool = False):
        self.side = torch.sign(poses[:, 0].double() - self.sim.scene.probe_x).float()
        return super().rollout(labels, poses, seed, deterministic, follow_scan)

    def side_picking(self, scan: torch.Tensor, points: torch.Tensor, first: torch.Tensor) -> torch.Tensor:
        requests = super().side_picking(scan, points, first)
        requests[:, 2:, 1] = self.side[:, None]
        requests[:, 2:, 3] = 1.0 - self.hparams.scan_side
        return requests


def touch_frame(points: torch.Tensor, scale: float = 5.0, centred: bool = True) -> torch.Tensor:
    """(B, N, 4) probes -> (B, N, 4): X, Y, Z relative to the mean of the episode's touched points (x scale, to
    about unit size), and T. Where the object lies is no class cue; misses stay in, as where it is not. Not
    centred: where the object lies is the question (--fit-target side)."""
    touched = points[..., 3:]
    centre = (points[..., :3] * touched).sum(1, keepdim=True) / touched.sum(1, keepdim=True).clamp(min=1)
    return torch.cat([(points[..., :3] - centre * centred) * scale, touched], -1)


# what --fit-net trains; the touch sets as the model builds them (model.touch_set_net, model.touch_set_miss_frame)
FIT_NETS = {"pointnet": lambda n: PointNet(n, in_dim=4), "touch_set": TouchSetClassifier,
            "touch_set_wide": TouchSetClassifier.wide,
            "touch_set_wide_line": lambda n: TouchSetClassifier.wide(n, miss_frame="line"),
            "touch_set_wide_mirror": lambda n: TouchSetClassifier.wide(n, mirror=True)}


class FitNet(torch.nn.Module):
    """The classifier `--fit` trains on the probes of an episode: a PointNet on touch_frame(points), or the model's
    own touch-set classifier (model.touch_set; its logits after the last probe), to compare them on the same
    probes. For the side target a PointNet reads the points where they are (scaled as touch_frame's): the side
    is where the object lies."""

    def __init__(self, kind: str, n_classes: int, centred: bool = True) -> None:
        super().__init__()
        self.kind, self.centred = kind, centred
        self.net = FIT_NETS[kind](n_classes)

    def forward(self, points: torch.Tensor) -> torch.Tensor:
        if self.kind != "pointnet":
            return self.net(points)[:, -1]
        return self.net(touch_frame(points, centred=self.centred))


def fit_labels(target: str, labels: np.ndarray, poses: np.ndarray, scene) -> np.ndarray:
    """What --fit learns to tell: the class, or the side of the probe line the object lies on (1: +x)."""
    return labels if target == "class" else (poses[:, 0] > scene.probe_x).astype(np.int64)


def knn_predict(library: torch.Tensor, library_labels: torch.Tensor, queries: torch.Tensor, k: int,
                n_classes: int, chunk: int = 65536) -> torch.Tensor:
    """(Q,) class of each query episode (Q, N, 4 probes) by a vote of its k nearest library episodes (L, N, 4), the
    probes compared in order and where they are (X, Y, Z x 5, and T). No training and no translation invariance:
    with a library drawn from the same poses as the queries, and as it grows, this approaches the best any
    classifier of these probes can do, so it separates what a scan cannot tell from what a classifier misses. Ties
    go to the class of the nearer neighbours."""
    if not 1 <= k <= len(library):
        raise ValueError(f"--fit-k {k}: must be in [1, {len(library)}] (the fit episodes)")

    def features(points: torch.Tensor) -> torch.Tensor:
        return torch.cat([points[..., :3] * 5.0, points[..., 3:]], -1).flatten(1)

    queries, best_d = features(queries), torch.full((len(queries), k), float("inf"))
    best_i = torch.zeros((len(queries), k), dtype=torch.long)
    for start in range(0, len(library), chunk):  # the running k nearest: the whole distance matrix would not fit
        d = torch.cdist(queries, features(library[start:start + chunk]))
        index = torch.arange(start, start + d.shape[1]).expand(len(queries), -1)
        best_d, order = torch.cat([best_d, d], 1).topk(k, largest=False)
        best_i = torch.cat([best_i, index], 1).gather(1, order)
    nearness = 1.0 + torch.linspace(1, 0, k) / (2 * k)  # nearest first; all of it adds < 1: it only breaks ties
    votes = torch.zeros(len(queries), n_classes).scatter_add_(1, library_labels[best_i], nearness.expand_as(best_d))
    return votes.argmax(1)


def fit_accuracy(model: HapticGlance, sim: ProbeSimulator, regions: PoseRegions, n_train: int, val_points: torch.Tensor,
                 val_labels: np.ndarray, epochs: int, seed: int, kind: str = "pointnet", target: str = "class",
                 probes: int | None = None, val_mask: np.ndarray | None = None, split: str = "train",
                 k: int = 16) -> float:
    """Validation accuracy (over val_mask, default all) of a classifier (FitNet, or knn_predict with k neighbours)
    trained supervised on the first `probes` (default all) of the fixed scan's probes in n_train episodes of the
    split (rolled out in batches of the simulator's size): what this scan's probes can say about the class, or the
    side (target)."""
    rng, batches = np.random.default_rng(seed + 1), []
    for i in range(max(1, n_train // sim.batch_size)):
        labels, poses = sample_episodes(regions, split, sim.batch_size, len(sim.classes), rng)
        batches.append((policy_probes(model, sim, labels, poses, seed=seed + 1 + i)[0][:, :probes],
                        torch.from_numpy(fit_labels(target, labels, poses, sim.scene))))
    points, labels = torch.cat([b[0] for b in batches]), torch.cat([b[1] for b in batches])
    n_out = len(sim.classes) if target == "class" else 2
    if kind == "knn":
        predicted = knn_predict(points, labels, val_points[:, :probes], k, n_out)
    else:
        net = train_fit_net(kind, n_out, target == "class", points, labels, epochs, seed)
        with torch.no_grad():
            predicted = net(val_points[:, :probes]).argmax(-1)
    right = predicted.numpy() == val_labels
    return float(right[val_mask].mean() if val_mask is not None else right.mean())


def train_fit_net(kind: str, n_out: int, centred: bool, points: torch.Tensor, labels: torch.Tensor, epochs: int,
                  seed: int) -> FitNet:
    """A FitNet seeded, built and trained with Adam on (points, labels) for `epochs` passes of batches of 256,
    returned in eval mode."""
    torch.manual_seed(seed)
    net = FitNet(kind, n_out, centred=centred)
    optimiser = torch.optim.Adam(net.parameters(), lr=1e-3)
    for _ in range(epochs):
        net.train()
        for idx in torch.randperm(len(points)).split(256):
            loss = torch.nn.functional.cross_entropy(net(points[idx]), labels[idx])
            optimiser.zero_grad()
            loss.backward()
            optimiser.step()
    return net.eval()


def accuracy_by_touches(touches: np.ndarray, correct: np.ndarray, offsets: np.ndarray) -> dict:
    """Accuracy after all probes, overall, per bin of touches per episode, and per bin of the object's distance
    from the probe line across it (straight probes miss what lies far off the line); None for an empty bin."""
    counts = touches.sum(1)

    def split(inside: np.ndarray) -> dict:
        return {"share": round(float(inside.mean()), 3),
                "accuracy": round(float(correct[inside].mean()), 3) if inside.any() else None}

    return {"accuracy": round(float(correct.mean()), 3),
            "by_touches": {f"{lo}-{hi}" if hi < 10**6 else f"{lo}+": split((counts >= lo) & (counts <= hi))
                           for lo, hi in TOUCH_BINS},
            "by_offset_cm": {f"{100 * lo:g}-{100 * hi:g}" if hi < 10 else f"{100 * lo:g}+":
                             split((offsets >= lo) & (offsets < hi)) for lo, hi in OFFSET_BINS}}


def tilt_deg(directions: np.ndarray) -> np.ndarray:
    """(..., 3) unit probe directions -> (...) their tilt from straight down, in degrees."""
    return np.degrees(np.arccos(np.clip(-directions[..., 2], -1, 1)))


def coverage(touches: np.ndarray, directions: np.ndarray, offsets: np.ndarray) -> dict[str, float | None]:
    """Touches, tilt, and the share of the probes tilted by more than a degree that lean towards the side of the
    line the object lies on (offsets: object X - probe line X per episode; None when no probe leans)."""
    half = touches.shape[1] // 2
    tilt = tilt_deg(directions)
    leaning = tilt > MIN_LEAN_DEG
    towards = np.sign(directions[..., 0]) == np.sign(offsets)[:, None]
    return {"touches": round(float(touches.sum(1).mean()), 3),
            "touches_first_half": round(float(touches[:, :half].sum(1).mean()), 3),
            "any_touch": round(float((touches.sum(1) > 0).mean()), 3),
            "tilt_deg": round(float(tilt.mean()), 1),
            "towards_object": round(float(towards[leaning].mean()), 3) if leaning.any() else None}


def first_touch_side(touches: np.ndarray, directions: np.ndarray, offsets: np.ndarray, probes: int | None = None
                     ) -> dict:
    """The side-picking scan's rule, scored without a fit: the object lies on the side the first leaning probe (of
    the first `probes`) that touched leans to (the scan itself, when both of its first two probes touch, takes the
    higher touch's side instead). Over the episodes whose object lies at least 5 cm off the line: the share with
    such a touch, and how often its side is the object's (None if none has one)."""
    far = np.abs(offsets) >= SIDE_MIN_OFFSET
    lean = np.sign(directions[:, :probes, 0]) * (tilt_deg(directions[:, :probes]) > MIN_LEAN_DEG)
    hit = (touches[:, :probes] > 0.5) & (lean != 0)
    told = hit.any(1) & far
    side = lean[np.arange(len(lean)), hit.argmax(1)]
    return {"share": round(float(told.sum() / max(far.sum(), 1)), 3),
            "accuracy": round(float((side[told] == np.sign(offsets[told])).mean()), 3) if told.any() else None}


def _is_number(text: str) -> bool:
    try:
        return float(text) == float(text)
    except ValueError:
        return False


def scan_model(aim: str, **scan) -> HapticGlance:
    """The fixed scan of these options, aimed by the oracle unless aim is "0" (told only its side if "side")."""
    if aim == "side":
        return OracleSidedScan(**scan)
    return HapticGlance(**scan) if aim == "0" else OracleAimedScan(aim, **scan)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--episodes", type=int, default=512)
    parser.add_argument("--n-probes", type=int, default=10)
    parser.add_argument("--mode", choices=["ideal", "arm"], default="ideal")
    parser.add_argument("--split", choices=["train", "val", "test"], default="val")
    parser.add_argument("--orders", nargs="+", choices=SCAN_ORDERS, default=["sweep", "centre_out"])
    parser.add_argument("--spans", type=float, nargs="+", default=[1.0, 0.75, 0.5])
    parser.add_argument("--leans", type=float, nargs="+", default=[0.0],
                        help="model.scan_lean values (0: straight down)")
    parser.add_argument("--follows", type=float, nargs="+", default=[0.0],
                        help="model.scan_follow values (0: the scan ignores its touches)")
    parser.add_argument("--follow-probes", type=int, nargs="+", default=[0],
                        help="model.scan_follow_probes values: how many probes after the first touch follow it (0: "
                             "all; only with --follows > 0)")
    parser.add_argument("--crosses", type=float, nargs="+", default=[0.0],
                        help="model.scan_cross values (0: no leaning probes after the first touch)")
    parser.add_argument("--reaches", type=float, nargs="+", default=[0.0],
                        help="model.scan_reach values (0: no leaning probes while nothing is touched)")
    parser.add_argument("--sides", type=float, nargs="+", default=[0.0],
                        help="model.scan_side values (0: no side-picking)")
    parser.add_argument("--side-firsts", type=float, nargs="+", default=[0.0],
                        help="model.scan_side_first values: the side-picking scan's first two probes' lean (0: as "
                             "the rest)")
    parser.add_argument("--side-pairs", choices=["same", "apart"], nargs="+", default=["same"],
                        help="where the side-picking scan's first two probes enter: both at its first place, or at "
                             "its first two (model.scan_side_pair_apart)")
    parser.add_argument("--aims", nargs="+", default=["0"],
                        help="oracle leans towards the object's centre: request units, or 'exact'; or 'side': a "
                             "side-picking scan (--sides) whose later probes lean to the side read from the pose "
                             "(0: no oracle)")
    parser.add_argument("--ckpt", type=Path, nargs="*", default=[], help="checkpoints whose policies to measure too")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--fit", type=int, default=0, metavar="EPISODES",
                        help="also fit a classifier (--fit-net) to each fixed scan's probes in this many episodes "
                             "of --fit-split")
    parser.add_argument("--fit-epochs", type=int, default=25)
    parser.add_argument("--fit-net", choices=[*FIT_NETS, "knn"], default="pointnet",
                        help="the classifier --fit trains: a PointNet, one of the model's touch-set classifiers "
                             "(small, wide, wide with its misses in the line's frame, wide mirrored to the line's "
                             "+x side), or the k nearest fit episodes (--fit-k; with --fit-split as --split, near "
                             "the best possible)")
    parser.add_argument("--fit-k", type=int, default=16, help="neighbours that vote with --fit-net knn")
    parser.add_argument("--fit-split", choices=["train", "val", "test"], default="train",
                        help="the pose split --fit draws its episodes from")
    parser.add_argument("--fit-target", choices=["class", "side"], default="class",
                        help="what --fit learns: the class, or the side of the line the object lies on (scored on "
                             "the episodes whose object lies at least 5 cm off the line, where the side matters)")
    parser.add_argument("--fit-probes", type=int, default=None, metavar="K",
                        help="--fit reads only each episode's first K probes (default: all)")
    args = parser.parse_args()
    if args.fit_target == "side" and args.fit_net.startswith("touch_set"):
        parser.error("--fit-target side: needs --fit-net pointnet or knn")
    if args.fit_net == "knn" and not 1 <= args.fit_k <= args.fit:
        parser.error(f"--fit-k {args.fit_k}: must be in [1, --fit {args.fit}] (the episodes that vote)")
    if args.fit_probes is not None and not 1 <= args.fit_probes <= args.n_probes:
        parser.error(f"--fit-probes {args.fit_probes}: must be in [1, --n-probes {args.n_probes}]")
    for aim in args.aims:
        if aim not in ("exact", "side") and not _is_number(aim):
            parser.error(f"--aims: {aim!r} is neither a number nor 'exact' or 'side'")
    torch.set_num_threads(1)

    scans = {f"{order}-span{span:g}" + (f"-lean{lean:g}" if lean else "") + (f"-follow{follow:g}" if follow else "")
             + (f"x{follow_probes}" if follow_probes else "")
             + (f"-cross{cross:g}" if cross else "") + (f"-reach{reach:g}" if reach else "")
             + (f"-side{side:g}" if side else "") + (f"-first{first:g}" if first else "")
             + ("-apart" if pair == "apart" else "")
             + (f"-aim{aim}" if aim != "0" else ""):
             scan_model(aim, n_probes=args.n_probes, policy="line_scan", scan_span=span, scan_order=order,
                        scan_lean=lean, scan_follow=follow, scan_follow_probes=follow_probes, scan_cross=cross,
                        scan_reach=reach, scan_side=side, scan_side_first=first, scan_side_pair_apart=pair == "apart")
             for order in args.orders for span in args.spans for lean in args.leans for follow in args.follows
             for follow_probes in args.follow_probes for cross in args.crosses for reach in args.reaches
             for side in args.sides for first in args.side_firsts for pair in args.side_pairs for aim in args.aims
             if scan_options_combine(lean, follow, cross, reach, side) and (side or not (first or pair == "apart"))
             and (follow or not follow_probes)
             and (aim == "0" or (bool(side) == (aim == "side") and not (lean or cross or reach)))}
    models = dict(scans)
    for path in args.ckpt:
        if not path.is_file():
            sys.exit(f"scan_coverage: error: {path}: checkpoint not found")
        models[repo_path(path)] = HapticGlance.load_from_checkpoint(path, map_location="cpu").eval()
    sim = ProbeSimulator("hg4", batch_size=args.episodes, mode=args.mode, seed=args.seed)
    regions = PoseRegions(sim.scene)
    labels, poses = sample_episodes(regions, args.split, args.episodes, len(sim.classes),
                                    np.random.default_rng(args.seed))
    half = args.n_probes // 2
    offsets = poses[:, 0] - sim.scene.probe_x
    far = np.abs(offsets) >= SIDE_MIN_OFFSET
    print(f"{args.episodes} {args.split} episodes, {args.mode} mode, {args.n_probes} probes")
    if args.fit_target == "side":  # what naming one side every time would score
        print(f"{far.mean():.3f} of them lie at least {100 * SIDE_MIN_OFFSET:g} cm off the line, "
              f"{(offsets[far] > 0).mean():.3f} of those to +x")
    print(f"{'touches':>8} {f'after {half}':>9} {'any touch':>10} {'tilt (deg)':>11} {'towards':>8}"
          + (f" {'fit acc' if args.fit_target == 'class' else 'fit side':>8}" if args.fit else "")
          + "  scan or checkpoint")
    results = {}
    for name, model in models.items():
        if model.hparams.n_probes != args.n_probes:
            sys.exit(f"scan_coverage: error: {name}: trained for {model.hparams.n_probes} probes, not {args.n_probes}")
        points, directions, correct, shift = policy_probes(model, sim, labels, poses)
        touches = points[..., 3].numpy()
        r = results[name] = coverage(touches, directions, offsets)
        if shift is not None:
            r["prior_shift_rms"] = shift
            r["accuracy_on_prior_scan"] = round(accuracy_on_prior_scan(model, sim, labels, poses), 4)
        if args.fit_target == "side":
            r["first_touch_side"] = first_touch_side(touches, directions, offsets, args.fit_probes)
        if args.fit and name in scans:
            key = "fit_accuracy" if args.fit_target == "class" else "fit_side_accuracy"
            r[key] = round(fit_accuracy(model, sim, regions, args.fit, points,
                                        fit_labels(args.fit_target, labels, poses, sim.scene), args.fit_epochs,
                                        args.seed, args.fit_net, args.fit_target, args.fit_probes,
                                        None if args.fit_target == "class" else far, args.fit_split,
                                        args.fit_k), 3)
        towards = "-" if r["towards_object"] is None else f"{r['towards_object']:.2f}"
        print(f"{r['touches']:8.2f} {r['touches_first_half']:9.2f} {r['any_touch']:10.2f} {r['tilt_deg']:11.1f}"
              f" {towards:>8}"
              + "".join(f" {r[k]:8.3f}" for k in ("fit_accuracy", "fit_side_accuracy") if k in r) + f"  {name}",
              flush=True)
        if name not in scans:  # a fixed scan built here has an untrained classifier: no accuracy
            r.update(accuracy_by_touches(touches, correct, np.abs(offsets)))
    for name in (name for name in results if name not in scans):
        r = results[name]
        for key, unit in (("by_touches", "touches"), ("by_offset_cm", "cm off the line")):
            split = ", ".join(f"{b} {unit}: {v['share']:.2f} of episodes, accuracy "
                              + ("-" if v["accuracy"] is None else f"{v['accuracy']:.3f}") for b, v in r[key].items())
            print(f"{name}: accuracy after {args.n_probes} probes {r['accuracy']:.3f} ({split})")
        if "prior_shift_rms" in r:
            print(f"{name}: mean requests off the prior's, rms per component: "
                  + ", ".join(f"{c} {v:.3f}" for c, v in r["prior_shift_rms"].items())
                  + f"; its classifiers fed the prior's scan instead: accuracy after {args.n_probes} probes "
                  f"{r['accuracy_on_prior_scan']:.3f}")
    for name, r in results.items():
        if "first_touch_side" in r:
            side = r["first_touch_side"]
            print(f"{name}: in {side['share']:.3f} of the episodes {100 * SIDE_MIN_OFFSET:g}+ cm off the line a "
                  "leaning probe touched, and the first such probe's lean names their side "
                  + ("-" if side["accuracy"] is None else f"{side['accuracy']:.3f}") + " of the time")
    sim.close()
    print(json.dumps(results))


if __name__ == "__main__":
    main()
