"""The paper's noise comparison: PointNet and DGCNN on 10 sparse, noisy surface points against our best model
after 10 probes under the simulator's missed / false-contact noise, at noise rates 0 to 50 %.

- PointNet and DGCNN (k = 9) are trained supervised at each rate on clouds of 10 points sampled from the whole
  object surface at fresh poses of the train region, a `rate` share of them replaced by points of the pose
  volume (hg.sim.pointclouds); the checkpoint best on val clouds is scored on the test clouds at the same rate.
  Their test clouds use the same test episodes (labels and poses) as docs/results/table1.md (hg.lightning.clouds).
- Ours: Table 1's best variant, row planner_copy_mixed of scripts/reproduce_table1.py: planner_copy's checkpoints
  (trained without noise), its heads and its library classifier summed (`acc_mixed`), tested on those episodes with
  SensorNoise(miss_prob = rate, false_contact_prob = rate): each probe's reading is corrupted with probability
  `rate`. The library classifier weighs the readings with the sensor's fault rates (its likelihood is the sensor's
  model, hg.planner.log_likelihood), as PointNet and DGCNN are trained at the rate; the learned parts never saw
  noise. The same rollouts named by the library classifier alone (`acc_library`) are reported beside it.

- The greedy planner under faults (`--models planner`, beyond the paper, no learning): Table 1's planner row
  (scripts/plan.py over its library of training episodes, on the same test episodes in arm mode) with the sensor
  faulty at the rate; it weighs its library with the sensor's model, expects faulty readings when it picks a probe,
  and may probe a candidate again. At rate 0 it is the table's planner run. What probes placed under faults can
  say, for the policy copying the planner to aim at.
- Ours trained at the rate (`--models ours_trained`, beyond the paper; not in the default run, for its cost: one
  training per rate and seed): a table row's composition (`--trained-row`, default the best variant) trained,
  validated and tested with the sensor noise at the rate, as the point-cloud baselines are. At rate 0 it is that
  row's own table run. Its checkpoints go to <runs-dir>; an interrupted training resumes there.

Our model's runs read the records of Table 1 (<out>/table1_runs/, written by scripts/reproduce_table1.py): their
compositions, seeds and checkpoints. Each (model, rate, seed) leaves a JSON in <out>/noise_runs/ and is not
recomputed (ours: again when its table run's checkpoint changed); the merge writes noise.{md,json,png} from the
point-cloud baselines' records and the records made from Table 1's current rows (the hg4 research's records stay
in noise_runs/, out of the merge). Last line printed: JSON of the mean accuracies per model and rate, and the commit.

    .venv/bin/python scripts/reproduce_noise.py                 # needs Table 1's planner_copy_mixed runs for 'ours'
    .venv/bin/python scripts/reproduce_noise.py --models pointnet dgcnn --seeds 0
    .venv/bin/python scripts/reproduce_noise.py --models ours_trained --rates 0.3 --seeds 0
    .venv/bin/python scripts/reproduce_noise.py --models planner --seeds 0 --rates 0.1 0.2 0.3 0.4 0.5
"""
from __future__ import annotations

import argparse
import io
import json
import subprocess
import sys
import time
from pathlib import Path

import matplotlib
import numpy as np

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import yaml  # noqa: E402

from hg.atomic import write_atomic  # noqa: E402
from hg.lightning.clouds import N_POINTS, NETS, train_cloud_classifier  # noqa: E402
from hg.provenance import commit, hardware, repo_path  # noqa: E402
from hg.sim import Scene, load_object_set  # noqa: E402
from hg.sim.heldout import make_regions  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
RATES = (0.0, 0.1, 0.2, 0.3, 0.4, 0.5)
EVAL_SEED, VAL_EPISODES, TEST_EPISODES = 0, 1024, 2048  # as in reproduce_table1.py: the same test episodes
TABLE_RUNS = "table1_runs"  # reproduce_table1.py's records, <out>/TABLE_RUNS/<row>-seed<N>.json
OURS = "planner_copy_mixed"  # Table 1's best variant: planner_copy's heads and its library classifier summed
PLANNER = "planner65k"  # Table 1's greedy planner row
COLUMN = {"learned": "", "library": "_library", "mixed": "_mixed"}  # a prediction's suffix in the logged metrics
# -- our model under sensor noise --------------------------------------------------------------------------
def table_runs(out: Path, row: str) -> dict[int, tuple[Path, dict]]:
    """Table 1's records of `row` by training seed (and where each is), as scripts/reproduce_table1.py wrote them."""
    runs = {}
    for path in sorted((out / TABLE_RUNS).glob(f"{row}-seed*.json")):
        record = json.loads(path.read_text())
        runs[record["seed"]] = (path, record)
    if not runs:
        raise FileNotFoundError(f"{out / TABLE_RUNS}: no run of Table 1's row {row}; run it first with "
                                f"scripts/reproduce_table1.py --rows {row} (after the row it scores, if any)")
    return runs


def noise_args(rate: float) -> list[str]:
    """CLI overrides that corrupt each probe's reading with probability `rate` (a missed or a false contact)."""
    return ["--data.noise.miss_prob", str(rate), "--data.noise.false_contact_prob", str(rate)]


def scored(columns: dict[str, list[float]], prediction: str) -> dict:
    """A test's accuracy after each probe by the row's prediction, and by its library classifier alone if it has one."""
    mine = columns[f"stochastic{COLUMN[prediction]}"]
    return {"accuracy": mine[-1], "accuracy_per_probe": mine,
            **({"accuracy_library_per_probe": columns["stochastic_library"]} if "stochastic_library" in columns
               and prediction != "library" else {})}


def table_result(path: Path, record: dict) -> dict:
    """Rate 0: the table's own test of the row (where and when it ran, with its facts)."""
    columns = record.get("test_columns") or {f"stochastic{COLUMN[record['prediction']]}": record["accuracy"]}
    return {**scored(columns, record["prediction"]), "checkpoint": record["best_checkpoint"],
            "best_val_acc": record["best_val_acc"], "train_wall_s": record["train_wall_s"],
            "table_record": repo_path(path), "commit": record["commit"], "hardware": record["hardware"]}


def test_under_noise(path: Path, record: dict, rate: float, runs_dir: Path) -> dict:
    """The table run's best checkpoint, tested as its composition reads it on its test episodes with each reading
    corrupted with probability rate (nothing trained, no validation)."""
    from hg.lightning.experiment import fit_and_test

    checkpoint = ROOT / record["best_checkpoint"]
    if not checkpoint.is_file():
        raise FileNotFoundError(f"{checkpoint}: checkpoint of the table run {repo_path(path)} not found (runs/ is not "
                                "committed; rerun that row with scripts/reproduce_table1.py)")
    folder = runs_dir / f"ours-{record['row']}-rate{round(rate * 100):02d}-seed{record['seed']}"
    facts = fit_and_test([ROOT / c for c in record["composition"]], record["seed"], folder, eval_seed=EVAL_SEED,
                         test_episodes=record["test_episodes"], extra_args=[*record["overrides"], *noise_args(rate)],
                         checkpoint=checkpoint, validate=False)
    return {**scored(facts["columns"], record["prediction"]), "checkpoint": record["best_checkpoint"],
            "test_wall_s": facts["test_wall_s"], "table_record": repo_path(path)}


def plan_under_noise(path: Path, record: dict, rate: float) -> dict:
    """Table 1's planner run (its plan.py arguments: library, seed, test episodes) with the sensor faulty at the rate;
    at rate 0 the table's own run."""
    from hg.lightning.data import ProbeDataModule
    from hg.lightning.experiment import test_fingerprint

    if rate == 0:
        return {"accuracy": record["accuracy"][-1], "accuracy_per_probe": record["accuracy"],
                "table_record": repo_path(path), **{k: record[k] for k in (
                    "command", "train_wall_s", "test_fingerprint", "commit", "hardware")}}  # where and when it ran
    args = [*record["plan_args"], "--noise", str(rate)]
    start = time.time()
    proc = subprocess.run([sys.executable, str(ROOT / "scripts" / "plan.py"), *args], capture_output=True, text=True,
                          cwd=ROOT)
    if proc.returncode:
        raise RuntimeError(f"scripts/plan.py {' '.join(args)} failed (exit {proc.returncode}): {proc.stderr[-2000:]}")
    accuracy = json.loads(proc.stdout.strip().splitlines()[-1])[record["probes"]]["accuracy"]
    data = ProbeDataModule(test_episodes=record["test_episodes"], eval_seed=EVAL_SEED)
    return {"accuracy": accuracy[-1], "accuracy_per_probe": accuracy, "command": f"scripts/plan.py {' '.join(args)}",
            "train_wall_s": round(time.time() - start, 1), "test_fingerprint": test_fingerprint(data),
            "table_record": repo_path(path)}


def noise_teachers(patterns: list[str] | None, config_teachers: list[str], rate: float) -> list[str]:
    """The teacher files planned at `rate` for a row that copies a planner (model.warmup: hg.rl.ImitateTeacher):
    `patterns` with {pct} the rate in percent, by default each of the composition's teachers as
    <stem>_noise{pct}.npz beside it. Refuses a missing one, naming the command that writes it: a teacher planned
    without faults chose for readings the copy would not see (hg.planner.load_teacher)."""
    pct = f"{round(rate * 100):02d}"
    patterns = patterns or [str(Path(t).with_name(f"{Path(t).stem}_noise{{pct}}.npz")) for t in config_teachers]
    teachers = [pattern.replace("{pct}", pct) for pattern in patterns]
    for teacher in teachers:
        if not (ROOT / teacher).is_file():
            raise FileNotFoundError(
                f"{teacher}: no teacher planned at rate {rate}; write one with scripts/plan.py, the arguments of the "
                f"noise-free teacher it stands for (its meta: library, shifts, mirror, episodes, seed) and --noise "
                f"{rate} --save-rollouts {teacher}")
    return teachers


def teachers_of(composition: list[str]) -> list[str]:
    """The teacher files a composition's warm-up copies (the last config that names them), or none."""
    teachers: list[str] = []
    for config in composition:
        warmup = ((yaml.safe_load((ROOT / config).read_text()) or {}).get("model") or {}).get("warmup") or {}
        teachers = (warmup.get("init_args") or {}).get("teachers", teachers)
    return teachers


def noise_training_args(composition: list[str], rate: float, teachers: list[str] | None) -> list[str]:
    """The CLI overrides that train a composition at `rate`: the sensor's faults and, for a row copying a planner,
    the teachers planned at the rate (their fault draws replayed)."""
    copied = teachers_of(composition)
    extra = noise_args(rate)
    if copied:
        extra += ["--model.warmup.init_args.teachers", json.dumps(noise_teachers(teachers, copied, rate))]
    return extra


def train_under_noise(out: Path, row: str, seed: int, rate: float, runs_dir: Path, teachers: list[str] | None,
                      steps: int | None = None) -> dict:
    """Our model trained at the rate it is tested at, as the point-cloud baselines are: the row's composition with
    the sensor noise on in training, validation and test. At rate 0 that is the table's own run of the row. A row that
    scores another's checkpoints (e.g. with the library classifier) trains that row's composition and scores its best
    checkpoint as its own composition reads it. A row that copies a planner copies one planned at the rate
    (noise_teachers). `steps` overrides max_steps (smoke tests)."""
    runs = table_runs(out, row)
    if seed not in runs:
        raise FileNotFoundError(f"{out / TABLE_RUNS}/{row}-seed{seed}.json: no table run of {row} with seed {seed} "
                                "(rate 0 is the table's own run, and the others train its composition; run it with "
                                "reproduce_table1.py)")
    path, record = runs[seed]
    if rate == 0:
        return table_result(path, record)
    from hg.lightning.experiment import fit_and_test

    source = record.get("scores_checkpoint_of")
    trained = table_runs(out, source)[seed][1] if source else record
    if trained.get("plan_args"):
        raise ValueError(f"--trained-row {row}: a planner row learns nothing (--models planner plans under faults)")
    extra = noise_training_args(trained["composition"], rate, teachers)
    folder = runs_dir / f"ours_trained-{source or row}-rate{round(rate * 100):02d}-seed{seed}"
    facts = fit_and_test([ROOT / c for c in trained["composition"]], seed, folder, eval_seed=EVAL_SEED,
                         test_episodes=record["test_episodes"], steps=steps, extra_args=[*trained["overrides"], *extra])
    train_facts = {k: facts[k] for k in ("best_val_acc", "train_wall_s", "max_steps", "resumed_from_step")}
    if source:
        facts = fit_and_test([ROOT / c for c in record["composition"]], seed, folder.with_name(f"{folder.name}-scored"),
                             eval_seed=EVAL_SEED, test_episodes=record["test_episodes"],
                             extra_args=[*record["overrides"], *extra], checkpoint=ROOT / facts["best_checkpoint"],
                             validate=False)
    return {**scored(facts["columns"], record["prediction"]), "checkpoint": facts["best_checkpoint"], **train_facts,
            "test_wall_s": facts["test_wall_s"], "command_args": extra, "table_record": repo_path(path)}


# -- merge ------------------------------------------------------------------------------------------------
def merge(out: Path) -> dict:
    """noise.{json,md,png} from the point-cloud baselines' records and the records made from Table 1's current rows
    (those with a `table_record`; ours: of its best variant only). Without any of the latter the files are left as
    they are: the hg4 research's noise table stays until our model has runs to set against the baselines."""
    runs: dict[str, dict[float, list[dict]]] = {}
    for path in sorted((out / "noise_runs").glob("*.json")):
        run = json.loads(path.read_text())
        if run["model"] not in NETS and ("table_record" not in run or run["model"] == "ours" and run["row"] != OURS):
            continue  # made from a row that is not (or no longer) Table 1's
        key = f"ours_trained-{run['row']}" if run["model"] == "ours_trained" else run["model"]
        runs.setdefault(key, {}).setdefault(run["rate"], []).append(run)
        if "accuracy_library_per_probe" in run:  # the same rollouts named by the library classifier alone
            alone, what = ("ours_library", "ours") if run["model"] == "ours" else (f"{key}-library",
                                                                                  "ours trained at the rate")
            n = len(run["accuracy_library_per_probe"])
            runs.setdefault(alone, {}).setdefault(run["rate"], []).append(
                run | {"accuracy": run["accuracy_library_per_probe"][-1],
                       "label": f"{what}, its library classifier alone: {run['row']} after {n} probes"})
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
    if all(model in NETS for model in summary):
        print(f"{out / 'noise_runs'}: no run made from Table 1's rows yet; noise.* left as they are", flush=True)
        return {"commit": merged_at, **{m: s["accuracy"] for m, s in summary.items()}}
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
             "- Ours: Table 1's best variant (`planner_copy_mixed`: planner_copy's checkpoints, its learned heads "
             "and its library classifier summed), trained without noise, tested with each probe's reading corrupted "
             "with probability = rate (a touch reported as a miss at the ray's end, or a miss as a touch at a random "
             "point of the ray). The library classifier weighs the readings with the sensor's fault rates (its "
             "likelihood is the sensor's model), as PointNet and DGCNN are trained at the rate; the learned parts "
             "never saw noise.",
             *(["- Ours, its library classifier alone: the same rollouts, named by the library classifier without the "
                "learned heads' logits (they never saw sensor faults; the classifier's likelihood models them)."]
               if "ours_library" in summary else []),
             *(["- Ours trained at the rate: that table row's composition trained, validated and tested with the noise "
                "at the rate, as PointNet and DGCNN are; at 0 % it is the row's own table run. A row copying the "
                "greedy planner copies one planned at the rate (its faults replayed, each run's teachers in its "
                "record's `command_args`)."]
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
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--models", nargs="+", default=["pointnet", "dgcnn", "ours"],
                        choices=["pointnet", "dgcnn", "ours", "ours_trained", "planner"])
    parser.add_argument("--trained-row", default=OURS,
                        help=f"Table 1's row that ours_trained trains at each rate (default: the best variant, {OURS})")
    parser.add_argument("--ours-steps", type=int, default=None, help="override ours_trained's max_steps (smoke tests)")
    parser.add_argument("--noise-teachers", nargs="+", default=None,
                        help="ours_trained of a row copying a planner: its teacher files planned at each rate, {pct} "
                             "the rate in percent (default: each of the row's teachers as <stem>_noise{pct}.npz)")
    parser.add_argument("--runs-dir", type=Path, default=ROOT / "runs" / "noise",
                        help="ours' and ours_trained's runs (checkpoints, logs)")
    parser.add_argument("--rates", nargs="+", type=float, default=list(RATES))
    parser.add_argument("--seeds", nargs="+", type=int, default=[0, 1, 2],
                        help="training seeds of the baselines and ours_trained; ours, planner: which of the table "
                             "row's runs")
    parser.add_argument("--steps", type=int, default=1000, help="training steps of the baselines")
    parser.add_argument("--batch-size", type=int, default=64)
    parser.add_argument("--out", type=Path, default=ROOT / "docs" / "results")
    parser.add_argument("--merge-only", action="store_true")
    args = parser.parse_args()
    if not args.merge_only:
        jobs = [(m, r, s) for s in args.seeds for m in args.models if m in NETS for r in args.rates]  # seed-major
        table = {}
        for model, row in (("ours", OURS), ("planner", PLANNER)):
            if model in args.models:
                table[model] = table_runs(args.out, row)
                jobs += [(model, r, seed) for seed in sorted(table[model]) if seed in args.seeds for r in args.rates]
        if "ours_trained" in args.models:
            jobs += [("ours_trained", r, seed) for seed in args.seeds for r in args.rates]
        for model, rate, seed in jobs:
            row = {"ours": OURS, "ours_trained": args.trained_row, "planner": PLANNER}.get(model)
            name = f"{model}-{row}" if row else model  # ours, ours_trained and planner: per table row
            path = args.out / "noise_runs" / f"{name}-rate{round(rate * 100):02d}-seed{seed}.json"
            made = json.loads(path.read_text()) if path.is_file() else None
            if made and model in NETS and made.get("regions") != "across_line":  # the hg4 research's, in cells
                raise ValueError(f"{path}: a point-cloud baseline trained in the old regions (cells); the table's "
                                 "are across_line: move it away to train this one")
            if made and (model != "ours" or made["checkpoint"] == table["ours"][seed][1]["best_checkpoint"]):
                if model == "ours_trained" and rate > 0:  # made as this run would make it (e.g. the same teachers)?
                    runs = table_runs(args.out, args.trained_row)
                    source = runs[seed][1].get("scores_checkpoint_of") if seed in runs else None
                    trained = table_runs(args.out, source)[seed][1] if source else runs[seed][1]
                    asked = noise_training_args(trained["composition"], rate, args.noise_teachers)
                    if made.get("command_args") != asked:
                        raise ValueError(f"{path}: made with {made.get('command_args')}, this run asks {asked}; move "
                                         f"it and its runs in {repo_path(args.runs_dir)} away to make this one")
                continue
            code_commit = commit()
            if model == "ours":
                table_path, record = table["ours"][seed]
                result = (table_result(table_path, record) if rate == 0 else
                          test_under_noise(table_path, record, rate, args.runs_dir))
                result["label"] = f"ours: {OURS} after {len(result['accuracy_per_probe'])} probes"
            elif model == "ours_trained":
                result = train_under_noise(args.out, args.trained_row, seed, rate, args.runs_dir, args.noise_teachers,
                                           args.ours_steps)
                result["label"] = (f"ours trained at the rate: {args.trained_row} after "
                                   f"{len(result['accuracy_per_probe'])} probes")
            elif model == "planner":
                result = plan_under_noise(*table["planner"][seed], rate)
                result["label"] = "greedy planner under faults, fault-aware, may re-probe (beyond the paper, no learning)"
            else:
                # the table's regions (the data module's default), whose test episodes every model here meets
                result = train_cloud_classifier(model, load_object_set("hg4"), make_regions("across_line", Scene(),
                                                EVAL_SEED), rate, seed, args.steps, args.batch_size, VAL_EPISODES,
                                                TEST_EPISODES, EVAL_SEED)
                result["label"], result["regions"] = NETS[model][0], "across_line"
            result = {"commit": code_commit, "hardware": hardware()} | result  # a reused table run keeps its own
            result.update(model=model, rate=rate, seed=seed, **({"row": row} if row else {}))
            write_atomic(path, json.dumps(result, indent=1) + "\n")
            print(f"{path.stem}: accuracy {result['accuracy']:.3f}", flush=True)
    print(json.dumps(merge(args.out)))


if __name__ == "__main__":
    try:
        main()
    except (ValueError, FileNotFoundError) as exc:  # bad inputs end in one line naming the file
        sys.exit(f"reproduce_noise: error: {exc}")
