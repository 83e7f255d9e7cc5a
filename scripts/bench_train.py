"""Times real training steps (Trainer.fit) of a composition of configs on this machine and projects its full protocol.

The step time is split into simulator (reset + probes), forward (policy rollout forwards, the loss pass and
Lightning's bookkeeping) and backward (backward + optimizer step). Validation is timed once and counted
max_steps / val_check_interval times in the projection. The network's arithmetic alone is timed too, on the same
model: the rollout's policy and encoder steps, the loss pass, backward and Adam's step, with a recorded rollout
replayed in place of the simulator and no Lightning (`network_ms`); `sim_fraction_ceiling` is the simulator's share
if everything else in a step cost nothing beyond that arithmetic. That arithmetic's matrix products are counted
(`network_gflop_per_step` and by part, torch's FlopCounterMode) and this machine's rate on one large product is timed
in the same run at the run's threads (`matmul_gflop_per_s`): `sim_fraction_at_peak` is the simulator's share if the
step's products ran at that rate and nothing else cost anything; `..._no_rollout` the same without the rollout's
forward passes, which the loss pass computes again. Last line: JSON with
steps_per_s, sim_fraction, projected_paper_minutes, the split, network_ms, the counts and bounds, and the host.

    .venv/bin/python scripts/bench_train.py --config configs/side_scan.yaml --config configs/parts/touch_sets.yaml
"""
from __future__ import annotations

import argparse
import contextlib
import json
import tempfile
import time

import numpy as np
import pytorch_lightning as pl
import torch
from torch.utils.flop_counter import FlopCounterMode

from hg.lightning.cli import cli
from hg.provenance import hardware
from hg.rl import rollout
from hg.sim.simulator import ProbeResult


class StepTimer(pl.Callback):
    """Wall time per training step and the parts of it spent in the simulator and in backward."""

    def __init__(self, warmup: int) -> None:
        self.warmup, self.step_time, self.sim_time, self.backward_time, self.steps = warmup, 0.0, 0.0, 0.0, 0
        self._sim_acc = 0.0

    def on_train_start(self, trainer, pl_module) -> None:
        sim = pl_module.sim
        for name in ("reset", "probe"):
            original = getattr(sim, name)

            def timed(*args, _original=original, **kwargs):
                start = time.perf_counter()
                try:
                    return _original(*args, **kwargs)
                finally:
                    self._sim_acc += time.perf_counter() - start
            setattr(sim, name, timed)

    def on_train_batch_start(self, trainer, pl_module, batch, batch_idx) -> None:
        self._sim_acc, self._backward, self._start = 0.0, 0.0, time.perf_counter()

    def on_before_backward(self, trainer, pl_module, loss) -> None:
        self._backward_start = time.perf_counter()

    def on_before_optimizer_step(self, trainer, pl_module, optimizer) -> None:
        self._backward = time.perf_counter() - self._backward_start

    def on_train_batch_end(self, trainer, pl_module, outputs, batch, batch_idx) -> None:
        if trainer.global_step > self.warmup:
            self.step_time += time.perf_counter() - self._start
            self.sim_time += self._sim_acc
            self.backward_time += self._backward
            self.steps += 1


class Replay:
    """Stands in for the simulator when timing the network alone: every probe returns the recorded rollout's reading."""

    arm = None  # no pose errors to read

    def __init__(self, points: torch.Tensor, point_scale: float) -> None:
        self.points = points.clone()
        self.points[..., :3] /= point_scale  # rollout() scales them again
        self.points, self.k = self.points.double().numpy(), 0

    def reset(self, labels, poses, seed=None) -> None:
        self.k = 0

    def probe(self, requests, faults=None) -> ProbeResult:
        points, self.k = self.points[:, self.k], self.k + 1
        return ProbeResult(points, None, None, None, points)


def network_ms(model: pl.LightningModule, batch: dict, repeats: int) -> dict[str, float]:
    """Median ms of one training step's arithmetic, by part: a rollout replayed (the policy's and encoder's steps),
    the loss pass, backward with an Adam step; on one batch of real episodes."""
    labels, poses, seed = batch["labels"], batch["poses"], int(batch["seed"])
    replay = Replay(model.roll(labels, poses, seed).points, model.hparams.point_scale)
    regime = "reinforce" if model.policy.learned else "classify"
    optimizer = model.configure_optimizers()

    def step(gflop: list[float] | None = None) -> tuple[float, float, float]:
        """One step's parts timed; with `gflop`, their matrix products counted into it instead (a slower pass)."""
        counters = [FlopCounterMode(display=False) if gflop is not None else contextlib.nullcontext()
                    for _ in range(3)]
        t0 = time.perf_counter()
        with counters[0]:
            replayed = rollout(replay, model.policy, labels, poses, seed, model.hparams.n_probes,
                               model.hparams.point_scale, model.encoder)
        t1 = time.perf_counter()
        with counters[1]:
            terms, _ = model.evaluate(replayed, labels, regime, seed)
        t2 = time.perf_counter()
        with counters[2]:
            optimizer.zero_grad()
            terms["loss"].backward()
            optimizer.step()
        if gflop is not None:
            gflop += [counter.get_total_flops() / 1e9 for counter in counters]
        return t1 - t0, t2 - t1, time.perf_counter() - t2

    times = [step() for _ in range(repeats + 2)]  # the first two untimed
    parts = 1000 * np.median(np.array(times[2:]), axis=0)
    gflop: list[float] = []
    step(gflop)
    return {"network_ms": float(parts.sum()), "rollout_network_ms": float(parts[0]), "loss_pass_ms": float(parts[1]),
            "backward_adam_ms": float(parts[2]), "network_gflop_per_step": sum(gflop), "rollout_gflop": gflop[0],
            "loss_pass_gflop": gflop[1], "backward_gflop": gflop[2]}


def matmul_gflop_per_s(size: int = 1024, repeats: int = 20) -> float:
    """This machine's float32 rate on one large matrix product, at the run's thread count: near its peak, an upper
    bound for the small products of the network."""
    a, b = torch.randn(size, size), torch.randn(size, size)
    torch.mm(a, b)
    timed = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        torch.mm(a, b)
        timed.append(time.perf_counter() - t0)
    return 2 * size**3 / min(timed) / 1e9


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--config", action="append", default=[],
                        help="config files combined in order, as `hg fit --config` (default: configs/pcrn_fc.yaml)")
    parser.add_argument("--steps", type=int, default=100)
    parser.add_argument("--warmup", type=int, default=10)
    parser.add_argument("--network-repeats", type=int, default=20, help="timings of the network alone (median)")
    args, overrides = parser.parse_known_args()
    configs = args.config or ["configs/pcrn_fc.yaml"]
    composition = [a for c in configs for a in ("--config", c)]
    with tempfile.TemporaryDirectory() as tmp:
        protocol = cli([*composition, *overrides], run=False)
        paper_steps = protocol.trainer.max_steps
        val_every = protocol.trainer.val_check_interval
        timer = StepTimer(args.warmup)
        run = cli([*composition, *overrides, "--trainer.logger", "false",
                   "--trainer.max_steps", str(args.steps + args.warmup), "--trainer.limit_val_batches", "0",
                   "--trainer.enable_progress_bar", "false", "--trainer.default_root_dir", tmp,
                   "--checkpoint.dirpath", tmp, "--checkpoint.monitor", "null", "--checkpoint.save_last", "false"],
                  run=False)
        run.trainer.callbacks.append(timer)
        run.trainer.fit(run.model, datamodule=run.datamodule)
        start = time.perf_counter()
        validate = cli([*composition, *overrides, "--trainer.logger", "false",
                        "--trainer.enable_progress_bar", "false", "--trainer.default_root_dir", tmp], run=False)
        validate.trainer.validate(run.model, datamodule=validate.datamodule, verbose=False)
        val_seconds = time.perf_counter() - start
        data = run.datamodule
        run.model.attach(data.make_simulator())
        network = network_ms(run.model, next(iter(data.train_dataloader())), args.network_repeats)
        run.model.sim.close()
    peak = matmul_gflop_per_s()
    step = timer.step_time / timer.steps
    sim_ms = 1000 * timer.sim_time / timer.steps
    figures = {
        "configs": configs,
        "steps_timed": timer.steps,
        "steps_per_s": round(1 / step, 2),
        "step_ms": round(1000 * step, 1),
        "sim_fraction": round(timer.sim_time / timer.step_time, 3),
        "forward_fraction": round(1 - (timer.sim_time + timer.backward_time) / timer.step_time, 3),
        "backward_fraction": round(timer.backward_time / timer.step_time, 3),
        **{k: round(v, 2 if "gflop" in k else 1) for k, v in network.items()},
        "sim_fraction_ceiling": round(sim_ms / (sim_ms + network["network_ms"]), 3),
        "network_gflop_per_s": round(network["network_gflop_per_step"] / network["network_ms"] * 1000, 1),
        "matmul_gflop_per_s": round(peak, 1),
        "sim_fraction_at_peak": round(sim_ms / (sim_ms + 1000 * network["network_gflop_per_step"] / peak), 3),
        # the rollout's forward passes, which the loss pass computes again on the same probes, left out
        "sim_fraction_at_peak_no_rollout": round(sim_ms / (sim_ms + 1000 * (
            network["network_gflop_per_step"] - network["rollout_gflop"]) / peak), 3),
        "validation_s": round(val_seconds, 1),
        "projected_paper_minutes": round((paper_steps * step + paper_steps // val_every * val_seconds) / 60, 1),
        "threads": torch.get_num_threads(),
        "host": hardware(),
    }
    print(f"{figures['step_ms']} ms per step: simulator {figures['sim_fraction']:.0%}, forward "
          f"{figures['forward_fraction']:.0%}, backward {figures['backward_fraction']:.0%}; one validation "
          f"{val_seconds:.1f} s; {paper_steps} steps projected at {figures['projected_paper_minutes']} min on "
          f"{figures['host']}; the network's arithmetic alone {network['network_ms']:.1f} ms per step (simulator share at most "
          f"{figures['sim_fraction_ceiling']:.0%}); its matrix products {network['network_gflop_per_step']:.2f} GFLOP at "
          f"{figures['network_gflop_per_s']} GFLOP/s, this machine's large product {figures['matmul_gflop_per_s']} "
          f"GFLOP/s on {figures['threads']} thread(s) (simulator share at most {figures['sim_fraction_at_peak']:.0%} at "
          f"that rate, {figures['sim_fraction_at_peak_no_rollout']:.0%} with the rollout's forward not done twice)")
    print(json.dumps(figures))


if __name__ == "__main__":
    main()
