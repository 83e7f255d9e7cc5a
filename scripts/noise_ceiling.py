"""Under sensor faults, what does our library namer lose to the faults themselves, and what to a policy they mislead?

On a split's table episodes (val by default: this measures, it chooses nothing), a checkpoint that chooses among the
planner's candidates probes with each reading corrupted with probability `rate` (a missed or a false contact, as
reproduce_noise.py tests ours), twice: its policy reading the faulty readings (as tested), and its policy reading
what a fault-free sensor reported (ProbeResult.clean_points) while the namer still gets the faulty ones. The probes
of each rollout are named by the library namer of the --namer teacher file (the sensor-aware likelihood of
hg.nets.library, as model.library_namer builds it) three ways:

  faulty          the readings as the sensor gave them: what "ours, its namer alone" reports
  faults_dropped  the corrupted readings left out: a namer told which readings the sensor corrupted
  clean           the fault-free readings of the same probes

So `policy_reads_clean` / `faults_dropped` is a ceiling for this policy's probe budget and library with a perfect
fault detector and a policy the faults do not mislead.

    .venv/bin/python scripts/noise_ceiling.py --namer data/planner/train_s10.npz --rates 0.1 0.3 \
        --ckpt runs/table1/pcrn_fc_candidates_readings_only_imitate_planner_final_mirror-seed0/checkpoints/best-step11500.ckpt

Last line: JSON {"<rate>": {"faults_per_episode": .., "policy_reads_faulty": {"faulty": [accuracy after each
probe], "faults_dropped": [..], "clean": [..]}, "policy_reads_clean": {...}}, ..., "ckpt", "split", "mode",
"episodes", "commit", "hardware"}.
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import time
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "scripts"))

from hg.lightning import HapticGlance  # noqa: E402
from hg.lightning.cli import datamodule_from_checkpoint  # noqa: E402
from hg.provenance import commit, hardware  # noqa: E402
from reproduce_noise import noise_args  # noqa: E402

READINGS = ("faulty", "faults_dropped", "clean")


class SensorTap:
    """The simulator with its readings tapped: what the faulty sensor and what a fault-free one reported are both
    kept, and the policy is shown one of them."""

    def __init__(self, sim, shown: str) -> None:
        self.sim, self.shown, self.faulty, self.clean = sim, shown, [], []

    def __getattr__(self, name: str):
        return getattr(self.sim, name)

    def probe(self, requests: np.ndarray, faults: np.ndarray | None = None):
        result = self.sim.probe(requests, faults)
        self.faulty.append(result.points)
        self.clean.append(result.clean_points)
        return result if self.shown == "faulty" else dataclasses.replace(result, points=result.clean_points)

    def taken(self, scale: float) -> tuple[torch.Tensor, torch.Tensor]:
        """(B, N, 4) the faulty and the clean points of the last rollout, scaled as the rollout scales them."""
        out = []
        for steps in (self.faulty, self.clean):
            points = torch.from_numpy(np.stack(steps, 1)).float()
            points[..., :3] *= scale
            out.append(points)
        self.faulty, self.clean = [], []
        return out[0], out[1]


def correct_after_each_probe(model: HapticGlance, namer, rollout, faulty: torch.Tensor, clean: torch.Tensor,
                             corrupted: torch.Tensor, labels: torch.Tensor) -> dict[str, np.ndarray]:
    """(B, N) bool, for each way of reading the rollout's probes: is the namer's class right after probe k+1.
    corrupted (B, N): the readings the sensor's faults flipped."""
    chosen, read = model.library_readings(rollout.actions, faulty)
    _, clean_read = model.library_readings(rollout.actions, clean)
    posteriors = {"faulty": namer(chosen, read), "faults_dropped": namer(chosen, read, corrupted),
                  "clean": namer(chosen, clean_read)}
    return {name: (p.argmax(-1) == labels[:, None]).numpy() for name, p in posteriors.items()}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--ckpt", type=Path, required=True)
    parser.add_argument("--namer", required=True, help="teacher file whose library names the probes")
    parser.add_argument("--rates", type=float, nargs="+", default=[0.1, 0.3])
    parser.add_argument("--split", choices=["val", "test"], default="val")
    parser.add_argument("--episodes", type=int, help="default: the table's (1024 for val, 2048 for test)")
    args = parser.parse_args()
    if not args.ckpt.is_file():
        parser.error(f"--ckpt {args.ckpt}: checkpoint not found")
    if not Path(args.namer).is_file():
        parser.error(f"--namer {args.namer}: teacher file not found (write one with planner_ceiling.py "
                     "--save-rollouts)")
    for rate in args.rates:
        if not 0 < rate <= 1:
            parser.error(f"--rates {rate}: a fault rate must be in (0, 1]")
    episodes = args.episodes or (2048 if args.split == "test" else 1024)
    if episodes < 1:
        parser.error(f"--episodes {episodes}: must be >= 1")
    torch.set_num_threads(1)
    code_commit = commit()
    model = HapticGlance.load_from_checkpoint(args.ckpt, map_location="cpu").eval()
    if model.hparams.location != "candidates":
        parser.error(f"--ckpt {args.ckpt}: the namer reads choices among the planner's candidates; this model's "
                     f"location network is {model.hparams.location!r}")
    results, namer = {}, None
    for rate in args.rates:
        start = time.time()
        data = datamodule_from_checkpoint(args.ckpt, args=[*noise_args(rate), "--data.eval_seed", "0",  # the tables'
                                                           f"--data.{args.split}_episodes", str(episodes)])
        try:
            namer = namer or model.build_library_namer(args.namer, data)
        except ValueError as exc:
            raise SystemExit(f"--namer: {exc}") from None
        namer.noise = data.noise  # the sensor-aware likelihood of this rate's faults
        data.setup("validate" if args.split == "val" else "test")
        batches = data.val_dataloader() if args.split == "val" else data.test_dataloader()
        correct = {shown: {name: [] for name in READINGS} for shown in ("faulty", "clean")}
        faults = 0
        sim = data.make_simulator()
        with torch.no_grad():
            for batch in batches:
                for shown in correct:
                    model.sim = tap = SensorTap(sim, shown)
                    rollout = model.rollout(batch["labels"], batch["poses"], int(batch["seed"]))
                    faulty, clean = tap.taken(model.hparams.point_scale)
                    corrupted = faulty[..., 3] != clean[..., 3]
                    faults += int(corrupted.sum()) if shown == "faulty" else 0
                    for name, right in correct_after_each_probe(model, namer, rollout, faulty, clean, corrupted,
                                                                batch["labels"]).items():
                        correct[shown][name].append(right)
        sim.close()
        results[str(rate)] = {"faults_per_episode": round(faults / episodes, 3)} | {
            f"policy_reads_{shown}": {name: [round(float(a), 4) for a in np.concatenate(c).mean(0)]
                                      for name, c in by_reading.items()}
            for shown, by_reading in correct.items()}
        print(f"rate {rate}: after {model.hparams.n_probes} probes "
              + ", ".join(f"{shown}: " + " / ".join(f"{name} {accuracy[-1]:.3f}" for name, accuracy in r.items())
                          for shown, r in results[str(rate)].items() if shown != "faults_per_episode")
              + f" ({time.time() - start:.0f} s)", flush=True)
    print(json.dumps(results | {"ckpt": str(args.ckpt), "split": args.split, "mode": data.hparams.mode,
                                "episodes": episodes, "commit": code_commit, "hardware": hardware()}))


if __name__ == "__main__":
    main()
