"""The paper's noise comparison: PointNet and DGCNN on 10 sparse, noisy surface points against our best model
after 10 probes under the simulator's missed / false-contact noise, at noise rates 0 to 50 %.

- PointNet and DGCNN (k = 9) are trained supervised at each rate on clouds of 10 points sampled from the whole
  object surface at fresh poses of the train region, a `rate` share of them replaced by points of the pose
  volume (hg.sim.pointclouds); the checkpoint best on val clouds is scored on the test clouds at the same rate.
  Their test clouds use the same test episodes (labels and poses) as docs/results/table1.md.
- Our model: the checkpoints of the best PCRN variant of docs/results/table1.json (chosen on val, trained
  without noise), tested on those episodes with SensorNoise(miss_prob = rate, false_contact_prob = rate): each
  probe's reading is corrupted with probability `rate`. A library namer in it (model.library_namer) weighs the
  readings with the sensor's fault rates (its likelihood is the sensor's model, hg.nets.library.log_likelihood),
  as PointNet and DGCNN are trained at the rate; its learned parts never saw noise.

- The greedy planner under faults (`--models planner`, beyond the paper, no learning): Table 1's planner row
  (scripts/plan.py over its library of training episodes, on the same test episodes in arm mode) with
  the sensor faulty at the rate; it weighs its library with the sensor's model, expects faulty readings when it
  picks a probe, and may probe a candidate again. At rate 0 it is the table's planner run. What probes placed
  under faults can say, for the policy copying the planner to aim at.
- Ours trained at the rate (`--models ours_trained`, beyond the paper; not in the default run, for its cost: one
  training per rate and seed): a table row's config (`--trained-row`, default the best PCRN variant) trained,
  validated and tested with the sensor noise at the rate, as the point-cloud baselines are. At rate 0 it is
  that row's own table run. Its checkpoints go to <runs-dir>; an interrupted training resumes there.

Each (model, rate, seed) leaves a JSON in <out>/noise_runs/ and is not recomputed (ours: per table row, and
again when that row's checkpoint changed); the merge writes noise.{md,json,png}, with ours from the row that
table1.json names best now. Last line printed: JSON of the mean accuracies per model and rate, and the commit.

    .venv/bin/python scripts/reproduce_noise.py                 # needs the table1 runs' checkpoints for 'ours'
    .venv/bin/python scripts/reproduce_noise.py --models pointnet dgcnn --seeds 0
    .venv/bin/python scripts/reproduce_noise.py --models ours_trained --rates 0.3 --seeds 0
    .venv/bin/python scripts/reproduce_noise.py --models planner --seeds 0 --rates 0.1 0.2 0.3 0.4 0.5
"""
from __future__ import annotations

import argparse
import copy
import io
import json
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "scripts"))

import matplotlib  # noqa: E402

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import torch  # noqa: E402
import torch.nn.functional as F  # noqa: E402

from hg.atomic import write_atomic  # noqa: E402
from hg.lightning.data import EvalEpisodes  # noqa: E402
from hg.nets import DGCNN, PointNet  # noqa: E402
from hg.provenance import commit, hardware, repo_path  # noqa: E402
from hg.sim import PoseRegions, Scene, load_object_set, sample_episodes  # noqa: E402
from hg.sim.pointclouds import noisy_point_clouds  # noqa: E402

RATES = (0.0, 0.1, 0.2, 0.3, 0.4, 0.5)
N_POINTS = 10
EVAL_SEED, VAL_EPISODES, TEST_EPISODES = 0, 1024, 2048  # as in reproduce_table1.py: the same test episodes
POINT_SCALE = 2.0  # as HapticGlance.point_scale: coordinates of order 1
NETS = {"pointnet": ("PointNet", lambda n_classes: PointNet(n_classes)),
        "dgcnn": ("DGCNN (k=9)", lambda n_classes: DGCNN(n_classes, k=9))}


# -- point-cloud baselines ---------------------------------------------------------------------------------
def cloud_tensor(clouds: np.ndarray) -> torch.Tensor:
    """Centred on the cloud's mean (the usual PointNet normalisation; the pose's position is not a class cue)."""
    return torch.from_numpy((clouds - clouds.mean(1, keepdims=True)) * POINT_SCALE).float()


def fixed_clouds(regions: PoseRegions, objects, split: str, n_episodes: int, rate: float) -> tuple[torch.Tensor, torch.Tensor]:
    """The split's fixed episodes (the ones the probing models meet) as clouds, seeded by split and rate only."""
    batches = EvalEpisodes(regions, split, n_episodes, 256, len(objects), EVAL_SEED).batches
    labels = np.concatenate([b["labels"].numpy() for b in batches])
    poses = np.concatenate([b["poses"].numpy() for b in batches])
    rng = np.random.default_rng([EVAL_SEED, split == "test", int(round(rate * 100))])
    clouds, _ = noisy_point_clouds(regions.scene, objects, labels, poses, N_POINTS, rate, rng)
    return cloud_tensor(clouds), torch.from_numpy(labels)


@torch.no_grad()
def accuracy(net: torch.nn.Module, clouds: torch.Tensor, labels: torch.Tensor) -> float:
    net.eval()
    return float((net(clouds).argmax(-1) == labels).float().mean())


def train_point_cloud_net(name: str, rate: float, seed: int, steps: int, batch_size: int) -> dict:
    """Supervised training on fresh train-region clouds; the state best on val is scored on test."""
    torch.manual_seed(seed)
    scene, objects = Scene(), load_object_set("hg4")
    regions = PoseRegions(scene, seed=EVAL_SEED)
    val, test = fixed_clouds(regions, objects, "val", VAL_EPISODES, rate), fixed_clouds(regions, objects, "test",
                                                                                         TEST_EPISODES, rate)
    net = NETS[name][1](len(objects))
    optimiser = torch.optim.Adam(net.parameters(), lr=1e-3)
    schedule = torch.optim.lr_scheduler.CosineAnnealingLR(optimiser, steps)
    rng = np.random.default_rng([seed, int(round(rate * 100))])
    best_val, best_state, start = -1.0, None, time.time()
    for step in range(1, steps + 1):
        labels, poses = sample_episodes(regions, "train", batch_size, len(objects), rng)
        clouds, _ = noisy_point_clouds(scene, objects, labels, poses, N_POINTS, rate, rng)
        net.train()
        loss = F.cross_entropy(net(cloud_tensor(clouds)), torch.from_numpy(labels))
        optimiser.zero_grad()
        loss.backward()
        optimiser.step()
        schedule.step()
        if step % 250 == 0 or step == steps:
            val_acc = accuracy(net, *val)
            if val_acc > best_val:
                best_val, best_state = val_acc, copy.deepcopy(net.state_dict())
    net.load_state_dict(best_state)
    return {"accuracy": round(accuracy(net, *test), 4), "best_val_acc": round(best_val, 4), "steps": steps,
            "batch_size": batch_size, "train_wall_s": round(time.time() - start, 1)}


# -- our model under sensor noise --------------------------------------------------------------------------
def table_row(results: Path, row: str | None = None) -> tuple[str, str, dict[int, dict], int]:
    """A row of table1.json (default: its best PCRN variant, `best_pcrn`, chosen on validation accuracy): its name,
    config, run records by training seed (checkpoints, accuracies) and the size of the test set the table used."""
    table_path = results / "table1.json"
    if not table_path.is_file():
        raise FileNotFoundError(f"{table_path}: run scripts/reproduce_table1.py first (our model's checkpoints)")
    saved = json.loads(table_path.read_text())
    row = row or saved.get("best_pcrn")
    if row is None:
        raise ValueError(f"{table_path}: no learned PCRN row (only {', '.join(saved['rows'])}); "
                         "train one with reproduce_table1.py")
    if row not in saved["rows"]:
        raise ValueError(f"{table_path}: no row {row!r} (rows: {', '.join(saved['rows'])})")
    runs = [json.loads(p.read_text()) for p in sorted((results / "runs").glob(f"{row}-seed*.json"))]
    return row, saved["rows"][row]["config"], {r["seed"]: r for r in runs}, saved["test_episodes"]


def noise_args(rate: float) -> list[str]:
    """CLI overrides that corrupt each probe's reading with probability `rate` (a missed or a false contact)."""
    return ["--data.noise.miss_prob", str(rate), "--data.noise.false_contact_prob", str(rate)]


def test_under_noise(checkpoint: Path, rate: float, test_episodes: int = TEST_EPISODES, config: str | None = None
                     ) -> dict:
    """Accuracy after each probe on the table's test episodes with each reading corrupted with probability rate;
    the model as the row's `config` reads it (its model section over the checkpoint's: a row scoring another row's
    checkpoints adds to what they name, e.g. model.library_namer)."""
    import pytorch_lightning as pl
    import yaml

    from hg.lightning.callbacks import per_probe_table
    from hg.lightning.cli import datamodule_from_checkpoint
    from hg.lightning.module import HapticGlance

    if not checkpoint.is_file():
        raise FileNotFoundError(f"{checkpoint}: checkpoint of the table1 run not found (runs/ is not committed; "
                                "rerun that row with scripts/reproduce_table1.py)")
    data = datamodule_from_checkpoint(checkpoint, args=[
        *noise_args(rate), "--data.eval_seed", str(EVAL_SEED), "--data.test_episodes", str(test_episodes)])
    model_args = (yaml.safe_load((ROOT / config).read_text()).get("model") or {}) if config else {}
    model = HapticGlance.load_from_checkpoint(checkpoint, map_location="cpu", **model_args)
    trainer = pl.Trainer(accelerator="cpu", logger=False, enable_checkpointing=False, enable_progress_bar=False,
                         enable_model_summary=False, deterministic=True)
    start = time.time()
    trainer.test(model, datamodule=data, verbose=False)
    columns = per_probe_table(trainer.callback_metrics, "test", model.hparams.n_probes)
    return {"accuracy": round(columns["stochastic"][-1], 4),
            "accuracy_per_probe": [round(v, 4) for v in columns["stochastic"]],
            **({"accuracy_namer_alone_per_probe": [round(v, 4) for v in columns["namer_alone"]]}
               if "namer_alone" in columns else {}),
            "checkpoint": repo_path(checkpoint), "test_wall_s": round(time.time() - start, 1)}


def plan_under_noise(seed: int, rate: float, test_episodes: int, out: Path, library: tuple[str, ...] | None = None
                     ) -> dict:
    """Table 1's planner row on its test episodes with the sensor faulty at the rate (plan.py --noise;
    `library`: its library arguments, default the row's); at rate 0 the table's own planner run."""
    from reproduce_table1 import PLANNER_LIBRARY, plan_and_test

    if rate == 0:
        path = out / "runs" / f"planner-seed{seed}.json"
        if not path.is_file():
            raise FileNotFoundError(f"{path}: no table run of the planner with seed {seed} (rate 0 is the table's own "
                                    "run; run it with reproduce_table1.py --one planner SEED)")
        run = json.loads(path.read_text())
        return {k: run[k] for k in ("command", "train_wall_s", "test_fingerprint", "commit", "hardware")} | {
            "accuracy_per_probe": run["accuracy"], "accuracy": run["accuracy"][-1]}  # where and when it ran
    facts = plan_and_test(library or PLANNER_LIBRARY, seed, test_episodes, ("--noise", str(rate)))
    return {"accuracy": facts["accuracy"][-1], "accuracy_per_probe": facts["accuracy"],
            **{k: facts[k] for k in ("command", "train_wall_s", "test_fingerprint")}}


def noise_teachers(patterns: list[str] | None, config_teachers: list[str], rate: float) -> list[str]:
    """The teacher files planned at `rate` for a row that copies a planner (model.imitate): `patterns` with {pct}
    the rate in percent, by default each of the config's teachers as <stem>_noise{pct}.npz beside it. Refuses a
    missing one, naming the command that writes it: a teacher planned without faults chose for readings the copy
    would not see (hg.lightning.data.load_teacher)."""
    pct = f"{round(rate * 100):02d}"
    patterns = patterns or [str(Path(t).with_name(f"{Path(t).stem}_noise{{pct}}.npz")) for t in config_teachers]
    teachers = [pattern.replace("{pct}", pct) for pattern in patterns]
    for teacher in teachers:
        if not (ROOT / teacher).is_file():
            raise FileNotFoundError(
                f"{teacher}: no teacher planned at rate {rate}; write one with scripts/plan.py, the "
                f"arguments of the noise-free teacher it stands for (its meta: library, shifts, mirror, episodes, seed) "
                f"and --noise {rate} --save-rollouts {teacher}")
    return teachers


def noise_training_setup(row: str, config: str, rate: float,
                         teachers: list[str] | None) -> tuple[str | None, str, list[str]]:
    """How train_under_noise trains `row` at `rate` > 0: the row it trains when `row` scores another's checkpoints
    (else None), the config it trains, and the CLI overrides (the sensor's faults; for a row copying a planner, the
    teachers planned at the rate and model.choice_repeats)."""
    import yaml

    from reproduce_table1 import ROWS, config_of

    source = ROWS[row].scores if row in ROWS else None
    trained = config_of(source) if source else config
    model = yaml.safe_load((ROOT / trained).read_text()).get("model") or {}
    extra = noise_args(rate)
    if model.get("imitate"):
        extra += ["--model.imitate", json.dumps(noise_teachers(teachers, model["imitate"], rate))]
        if model.get("choice_reads_probes"):
            extra += ["--model.choice_repeats", "true"]
    return source, trained, extra


def train_under_noise(row: str, config: str, seed: int, rate: float, table_runs: dict[int, dict], runs_dir: Path,
                      test_episodes: int, steps: int | None, teachers: list[str] | None = None) -> dict:
    """Our model trained at the rate it is tested at, as the point-cloud baselines are: the row's config with the
    sensor noise on in training, validation and test. At rate 0 that is the table's own run of the row. A row that
    scores another's checkpoints (e.g. with model.library_namer) trains that row's config and scores its best
    checkpoint as its own config reads it. A row that copies a planner copies one planned at the rate (its fault
    draws replayed, noise_teachers(teachers)), and its choice may probe a candidate again (model.choice_repeats),
    as that planner does (noise_training_setup)."""
    if rate == 0:
        if seed not in table_runs:
            raise FileNotFoundError(f"docs/results/runs/{row}-seed{seed}.json: no table run of {row} with seed {seed} "
                                    "(rate 0 is the table's own run; train it with reproduce_table1.py)")
        run = table_runs[seed]
        return {"accuracy": run["accuracy"][-1], "accuracy_per_probe": run["accuracy"], "checkpoint":
                run["best_checkpoint"], "best_val_acc": run["best_val_acc"], "train_wall_s": run["train_wall_s"],
                **({"accuracy_namer_alone_per_probe": run["accuracy_namer_alone"]} if "accuracy_namer_alone" in run
                   else {})}
    from hg.lightning.experiment import fit_and_test

    source, trained, extra = noise_training_setup(row, config, rate, teachers)
    folder = runs_dir / f"ours_trained-{source or row}-rate{round(rate * 100):02d}-seed{seed}"
    facts = fit_and_test(ROOT / trained, seed, folder, eval_seed=EVAL_SEED, test_episodes=test_episodes, steps=steps,
                         extra_args=extra)
    train_facts = {k: facts[k] for k in ("best_val_acc", "train_wall_s", "max_steps", "resumed_from_step")}
    if source:
        facts = fit_and_test(ROOT / config, seed, folder.with_name(f"{folder.name}-scored"), eval_seed=EVAL_SEED,
                             test_episodes=test_episodes, extra_args=extra, checkpoint=ROOT / facts["best_checkpoint"])
    return {"accuracy": facts["accuracy"][-1], "accuracy_per_probe": facts["accuracy"],
            "checkpoint": facts["best_checkpoint"], **train_facts, "test_wall_s": facts["test_wall_s"],
            "command_args": extra,
            **({"accuracy_namer_alone_per_probe": facts["accuracy_namer_alone"]} if "accuracy_namer_alone" in facts
               else {})}


# -- merge ------------------------------------------------------------------------------------------------
def merge(out: Path) -> dict:
    table_path = out / "table1.json"
    best = json.loads(table_path.read_text()).get("best_pcrn") if table_path.is_file() else None
    runs: dict[str, dict[float, list[dict]]] = {}
    for path in sorted((out / "noise_runs").glob("*.json")):
        run = json.loads(path.read_text())
        if run["model"] == "ours" and run["row"] != best:  # a row that is no longer the table's best
            continue
        key = f"ours_trained-{run['row']}" if run["model"] == "ours_trained" else run["model"]
        runs.setdefault(key, {}).setdefault(run["rate"], []).append(run)
        if "accuracy_namer_alone_per_probe" in run:  # the same rollouts named by the row's library namer alone
            alone, what = (("ours_namer_alone", "ours") if run["model"] == "ours" else
                           (f"{key}-namer_alone", "ours trained at the rate"))
            runs.setdefault(alone, {}).setdefault(run["rate"], []).append(
                run | {"accuracy": run["accuracy_namer_alone_per_probe"][-1],
                       "label": f"{what}, its namer alone: {run['row']} after 10 probes"})
    if not runs:
        raise SystemExit(f"{out / 'noise_runs'}: no finished runs to merge")
    summary = {}
    for model, by_rate in runs.items():
        rates = sorted(by_rate)
        values = [[r["accuracy"] for r in by_rate[rate]] for rate in rates]
        summary[model] = {"label": by_rate[rates[0]][0]["label"], "rates": rates,
                          "accuracy": [round(float(np.mean(v)), 4) for v in values],
                          "std": [round(float(np.std(v, ddof=1)) if len(v) > 1 else 0.0, 4) for v in values],
                          "seeds": [sorted(r["seed"] for r in by_rate[rate]) for rate in rates],
                          "commits": sorted({r["commit"] for rs in by_rate.values() for r in rs}),
                          "hardware": sorted({r["hardware"] for rs in by_rate.values() for r in rs})}
    merged_at = commit(paths=())
    write_atomic(out / "noise.json", json.dumps({"commit": merged_at, "test_episodes": TEST_EPISODES,
                                                 "n_points": N_POINTS, "models": summary}, indent=1) + "\n")
    write_atomic(out / "noise.png", noise_plot(summary))
    write_atomic(out / "noise.md", noise_markdown(summary, merged_at))
    return {"commit": merged_at, **{m: s["accuracy"] for m, s in summary.items()}}


def noise_plot(summary: dict) -> bytes:
    fig, ax = plt.subplots(figsize=(6, 4), dpi=110)
    for entry in summary.values():
        ax.errorbar([100 * r for r in entry["rates"]], entry["accuracy"], yerr=entry["std"], marker="o",
                    capsize=3, label=entry["label"])
    ax.set(xlabel="noise rate (%)", ylabel="accuracy (10 points / 10 probes)", ylim=(0, 1.02),
           title="Accuracy under noise (held-out test poses)")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    buffer = io.BytesIO()
    fig.savefig(buffer, format="png")
    plt.close(fig)
    return buffer.getvalue()


def seeds_cell(entry: dict) -> str:
    """The seeds behind a row: one list when every rate has the same ones, else the list of each rate, so that a
    rate with fewer runs is not hidden behind the first rate's."""
    if all(seeds == entry["seeds"][0] for seeds in entry["seeds"]):
        return str(entry["seeds"][0])
    return "; ".join(f"{100 * rate:.0f} %: {seeds}" for rate, seeds in zip(entry["rates"], entry["seeds"]))


def noise_markdown(summary: dict, merged_at: str) -> str:
    rates = sorted({r for s in summary.values() for r in s["rates"]})
    lines = ["# Accuracy under noise: PointNet and DGCNN on 10 noisy points, our model after 10 noisy probes", "",
             f"Same {TEST_EPISODES} held-out test episodes as `table1.md`, mean +- std over seeds. Produced by "
             f"`.venv/bin/python scripts/reproduce_noise.py`, merged at commit `{merged_at}` (runs at the commits "
             "listed below).", "",
             "- PointNet / DGCNN: trained and tested at each rate; 10 points sampled uniformly from the whole "
             "object surface, that share of them replaced by uniform points of the pose volume. They see the whole "
             "surface, top and bottom, without having to find the object first.",
             "- Ours: the best PCRN variant of `table1.md` (chosen on validation accuracy), trained without noise, "
             "tested with each probe's reading corrupted with probability = rate (a touch reported as a miss at the "
             "ray's end, or a miss as a touch at a random point of the ray). A library namer in it weighs the readings "
             "with the sensor's fault rates (its likelihood is the sensor's model), as PointNet and DGCNN are "
             "trained at the rate; its learned parts never saw noise.",
             *(["- Ours, its namer alone: the same rollouts as ours, named by its library namer without our "
                "classifier's logits (our classifier never saw sensor faults; the namer's likelihood models them)."]
               if "ours_namer_alone" in summary else []),
             *(["- Ours trained at the rate: that table row's config trained, validated and tested with the noise "
                "at the rate, as PointNet and DGCNN are; at 0 % it is the row's own table run. A row copying the "
                "greedy planner copies one planned at the rate (its faults replayed, each run's teachers in its "
                "record's `command_args`), free to probe a candidate again as that planner is."]
               if any(m.startswith("ours_trained-") for m in summary) else []),
             *(["- Greedy planner under faults (beyond the paper, no learning): Table 1's planner row on the same "
                "episodes with the faulty sensor; it weighs its library of training episodes with the sensor's model, "
                "expects faulty readings when it picks a probe, and may probe a candidate again (one seed: the "
                "library's draw and the faults'). At 0 % it is the table's planner run. What probes placed under "
                "faults can say: the reference for a policy copying it."] if "planner" in summary else []), "",
             "| model | " + " | ".join(f"{100 * r:.0f} %" for r in rates) + " | seeds | commits | hardware |",
             "|---|" + "---:|" * len(rates) + "---|---|---|"]
    for entry in summary.values():
        cells = [f"{entry['accuracy'][entry['rates'].index(r)]:.3f} +- {entry['std'][entry['rates'].index(r)]:.3f}"
                 if r in entry["rates"] else "" for r in rates]
        lines.append(f"| {entry['label']} | " + " | ".join(cells) +
                     f" | {seeds_cell(entry)} | {', '.join(f'`{c}`' for c in entry['commits'])} | "
                     f"{'; '.join(entry['hardware'])} |")
    lines += ["", "![accuracy vs noise](noise.png)", ""]
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--models", nargs="+", default=["pointnet", "dgcnn", "ours"],
                        choices=["pointnet", "dgcnn", "ours", "ours_trained", "planner"])
    parser.add_argument("--trained-row", default=None,
                        help="table row that ours_trained trains at each rate (default: the best PCRN variant)")
    parser.add_argument("--ours-steps", type=int, default=None, help="override ours_trained's max_steps (smoke tests)")
    parser.add_argument("--noise-teachers", nargs="+", default=None,
                        help="ours_trained of a row copying a planner: its teacher files planned at each rate, {pct} "
                             "the rate in percent (default: each of the row's teachers as <stem>_noise{pct}.npz)")
    parser.add_argument("--runs-dir", type=Path, default=ROOT / "runs" / "noise", help="ours_trained's checkpoints")
    parser.add_argument("--rates", nargs="+", type=float, default=list(RATES))
    parser.add_argument("--seeds", nargs="+", type=int, default=[0, 1, 2],
                        help="training seeds of the baselines and ours_trained; ours: which of the table row's runs")
    parser.add_argument("--steps", type=int, default=1000, help="training steps of the baselines")
    parser.add_argument("--batch-size", type=int, default=64)
    parser.add_argument("--out", type=Path, default=ROOT / "docs" / "results")
    parser.add_argument("--merge-only", action="store_true")
    args = parser.parse_args()
    if not args.merge_only:
        jobs = [(m, r, s) for s in args.seeds for m in args.models if m in NETS for r in args.rates]  # seed-major
        if "ours" in args.models:
            row, config, table_runs, test_episodes = table_row(args.out)
            checkpoints = {seed: ROOT / run["best_checkpoint"] for seed, run in table_runs.items()}
            jobs += [("ours", r, seed) for seed in sorted(checkpoints) if seed in args.seeds for r in args.rates]
        if "ours_trained" in args.models:
            trained_row, trained_config, trained_runs, test_episodes = table_row(args.out, args.trained_row)
            jobs += [("ours_trained", r, seed) for seed in args.seeds for r in args.rates]
        if "planner" in args.models:
            jobs += [("planner", r, seed) for seed in args.seeds for r in args.rates]
        for model, rate, seed in jobs:
            name = model  # ours and ours_trained: per table row
            if model == "ours":
                name = f"ours-{row}"
            elif model == "ours_trained":
                name = f"ours_trained-{trained_row}"
            path = args.out / "noise_runs" / f"{name}-rate{round(rate * 100):02d}-seed{seed}.json"
            made = json.loads(path.read_text()) if path.is_file() else None
            if made and (model != "ours" or made["checkpoint"] == repo_path(checkpoints[seed])):
                if model == "ours_trained" and rate > 0:  # made as this run would make it (e.g. the same teachers)?
                    asked = noise_training_setup(trained_row, trained_config, rate, args.noise_teachers)[2]
                    if made.get("command_args") != asked:
                        raise ValueError(f"{path}: made with {made.get('command_args')}, this run asks {asked}; move "
                                         f"it and its runs in {repo_path(args.runs_dir)} away to make this one")
                continue
            code_commit = commit()
            if model == "ours":
                result = test_under_noise(checkpoints[seed], rate, test_episodes, config)
                result["label"], result["row"] = f"ours: {row} after 10 probes", row
            elif model == "ours_trained":
                result = train_under_noise(trained_row, trained_config, seed, rate, trained_runs, args.runs_dir,
                                           test_episodes, args.ours_steps, args.noise_teachers)
                result["label"] = f"ours trained at the rate: {trained_row} after 10 probes"
                result["row"] = trained_row
            elif model == "planner":
                result = plan_under_noise(seed, rate, TEST_EPISODES, args.out)
                result["label"] = "greedy planner under faults, fault-aware, may re-probe (beyond the paper, no learning)"
            else:
                result = train_point_cloud_net(model, rate, seed, args.steps, args.batch_size)
                result["label"] = NETS[model][0]
            result = {"commit": code_commit, "hardware": hardware()} | result  # a reused table run keeps its own
            result.update(model=model, rate=rate, seed=seed)
            write_atomic(path, json.dumps(result, indent=1) + "\n")
            print(f"{path.stem}: accuracy {result['accuracy']:.3f}", flush=True)
    print(json.dumps(merge(args.out)))


if __name__ == "__main__":
    try:
        main()
    except (ValueError, FileNotFoundError) as exc:  # bad inputs end in one line naming the file
        sys.exit(f"reproduce_noise: error: {exc}")
