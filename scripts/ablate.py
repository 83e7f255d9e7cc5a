"""Single-factor ablations on validation: a base composition, then one named CLI override at a time, over seeds.

Each run trains the composition with the override for --steps steps, validates once at the end on the validation
split (never test), and writes its record (command, commit, host, validation accuracy after each probe, the mean
over the last half of training of the diagnostics: touch rate, clamped share, gradient ratio..., and their rows as
the run's diagnostics.csv held them, `train_curve`) atomically to --out/<factor>_s<seed>.json; a finished record is
reused. The last line printed is the summary table as JSON.

    .venv/bin/python scripts/ablate.py --base configs/pcrn_fc.yaml --steps 2000 --seeds 0 1 \\
        --factor none= --factor clip="--trainer.gradient_clip_val 1.0" --out docs/results/study
"""
from __future__ import annotations

import argparse
import json
import os
import shlex
import statistics
import sys
import tempfile
import time
from pathlib import Path

from hg.atomic import write_atomic
from hg.provenance import commit, hardware, repo_path

DIAGNOSTICS = ("touch_rate", "clamp_share", "grad_ratio", "grad_policy", "grad_ce", "std_py", "std_ux",
               "advantage_mean", "advantage_std", "loss_baseline")


def run(base: list[str], override: str, seed: int, steps: int, val_episodes: int, mode: str) -> dict:
    """Train, validate at the last step, and summarise the diagnostics of the second half of training."""
    import torch

    from hg.lightning.callbacks import GradientDiagnostics
    from hg.lightning.cli import cli

    start = time.time()
    with tempfile.TemporaryDirectory() as folder:
        args = [a for c in base for a in ("--config", c)] + shlex.split(override) + [
            "--seed_everything", str(seed), "--data.mode", mode, "--trainer.max_steps", str(steps),
            "--trainer.val_check_interval", str(steps), "--data.val_episodes", str(val_episodes),
            "--trainer.logger", "false", "--trainer.default_root_dir", folder, "--checkpoint.dirpath", folder,
            "--last_checkpoint.dirpath", folder, "--diagnostics.every_n_steps", str(max(1, steps // 40)),
            "--trainer.enable_progress_bar", "false"]
        torch.set_num_threads(1)
        trained = cli(args, run=False)
        trained.trainer.fit(trained.model, datamodule=trained.datamodule)
        metrics = trained.trainer.callback_metrics
    n = trained.model.hparams.n_probes
    diagnostics = next(c for c in trained.trainer.callbacks if isinstance(c, GradientDiagnostics))
    summary = {k: v for k, v in diagnostics.late_means(0.5).items() if k in DIAGNOSTICS}

    def column(name: str) -> list[float]:  # an optional column: empty where the run logs none
        return [round(float(metrics[f"val/{name}@{k}"]), 4) for k in range(1, n + 1) if f"val/{name}@{k}" in metrics]

    return {"val_accuracy": [round(float(metrics[f"val/acc@{k}"]), 4) for k in range(1, n + 1)],
            "val_accuracy_mean_action": column("acc_mean_action"),
            "val_accuracy_prior": column("acc_prior"),  # the same heads behind the policy's prior scan or compare_with
            "val_touch_rate": round(float(metrics["val/touch_rate"]), 4),
            "train_late": {k: round(v, 4) for k, v in summary.items()},
            "train_curve": [{k: round(v, 4) for k, v in row.items()} for row in diagnostics.rows],  # every logged row
            "wall_s": round(time.time() - start, 1)}


def halfway(accuracy: list[float]) -> float:
    """The accuracy after half the probes (after 5 of 10)."""
    return accuracy[len(accuracy) // 2 - 1]


def markdown(out: Path, factors: dict[str, str]) -> str:
    """The table of the factors' records in `out`: means over seeds, each seed's accuracy after 10 in brackets."""
    lines = ["| factor | override | seeds | val after half | val after all (per seed) | mean action after all | touch rate (val) "
             "| clamped share | policy / CE gradient on the encoder |", "|---|---|---|---:|---:|---:|---:|---:|---:|"]
    for name, override in factors.items():
        records = [r for r in (json.loads(p.read_text()) for p in sorted(out.glob(f"{name}_s*.json")))
                   if r["factor"] == name]
        if not records:
            continue
        def mean(key: str, index: int | None = None, late: bool = False) -> float:
            values = [r["train_late"].get(key, 0.0) if late else r[key] if index is None else r[key][index]
                      for r in records if late or index is None or r[key]]  # (a fixed policy has no mean action)
            return statistics.fmean(values) if values else float("nan")

        seeds = ", ".join(str(r["seed"]) for r in records)
        each = ", ".join(f"{r['val_accuracy'][-1]:.3f}" for r in records)
        lines.append(f"| {name} | `{override or '(the base)'}` | {seeds} | {mean('val_accuracy', len(records[0]['val_accuracy']) // 2 - 1):.3f} "
                     f"| {mean('val_accuracy', -1):.3f} ({each}) | {mean('val_accuracy_mean_action', -1):.3f} "
                     f"| {mean('val_touch_rate'):.3f} | {mean('clamp_share', late=True):.2f} "
                     f"| {mean('grad_ratio', late=True):.2f} |")
    return "\n".join(lines) + "\n"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--base", nargs="+", required=True, help="the composition's config files, in order")
    parser.add_argument("--factor", action="append", required=True, metavar="NAME=OVERRIDES",
                        help="a named CLI override ('none=' for the base itself); repeat")
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1])
    parser.add_argument("--steps", type=int, default=2000)
    parser.add_argument("--val-episodes", type=int, default=512)
    parser.add_argument("--mode", default="ideal", choices=["ideal", "arm"])
    parser.add_argument("--out", type=Path, required=True, help="folder of the run records")
    parser.add_argument("--markdown", type=Path, help="train nothing: write the records' table of these factors here")
    args = parser.parse_args()
    os.environ.setdefault("WANDB_MODE", "disabled")
    factors = dict(f.split("=", 1) for f in args.factor)
    if args.markdown:
        made_by = " ".join(["scripts/ablate.py", *(shlex.quote(a) for a in sys.argv[1:])])
        write_atomic(args.markdown, f"Made by `{made_by}` from the run records in {args.out}; each record holds the "
                                    f"command and commit of its run.\n\n" + markdown(args.out, factors))
        return
    code = commit()  # the code this process imported, whatever the work tree holds by the time a run ends
    table = {}
    for name, override in factors.items():
        for seed in args.seeds:
            path = args.out / f"{name}_s{seed}.json"
            if not path.is_file():
                record = {"factor": name, "override": override, "seed": seed, "base": [repo_path(c) for c in args.base],
                          "steps": args.steps, "mode": args.mode, "split": "val", "val_episodes": args.val_episodes,
                          "commit": code, "hardware": hardware(),
                          "command": f"scripts/ablate.py --base {' '.join(args.base)} --steps {args.steps} "
                                     f"--seeds {seed} --mode {args.mode} --val-episodes {args.val_episodes} "
                                     f"--factor {shlex.quote(f'{name}={override}')} --out {args.out}",
                          **run(args.base, override, seed, args.steps, args.val_episodes, args.mode)}
                path.parent.mkdir(parents=True, exist_ok=True)
                write_atomic(path, json.dumps(record, indent=1) + "\n")
            record = json.loads(path.read_text())
            asked = {"override": override, "base": [repo_path(c) for c in args.base], "steps": args.steps,
                     "mode": args.mode, "val_episodes": args.val_episodes}
            if (differ := [k for k, v in asked.items() if record.get(k) != v]):
                raise SystemExit(f"ablate.py: {path}: made with other {differ} than asked; move it away to run anew")
            table.setdefault(name, []).append(record)
            print(f"{name} seed {seed}: val after half / all probes {halfway(record['val_accuracy']):.3f} / "
                  f"{record['val_accuracy'][-1]:.3f}, touch {record['val_touch_rate']:.3f}", flush=True)
    print(json.dumps({name: {"seeds": [r["seed"] for r in rs],
                             "val_after_half": round(statistics.fmean(halfway(r["val_accuracy"]) for r in rs), 4),
                             "val_after_all": round(statistics.fmean(r["val_accuracy"][-1] for r in rs), 4),
                             **{k: round(statistics.fmean(r["train_late"].get(k, float("nan")) for r in rs), 4)
                                for k in ("touch_rate", "clamp_share", "grad_ratio")}}
                      for name, rs in table.items()}))


if __name__ == "__main__":
    main()
