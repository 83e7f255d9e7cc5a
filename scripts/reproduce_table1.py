"""Reproduce the paper's Table 1 side by side: every row trained with the paper protocol, several seeds, all scored
once on the same held-out test episodes, merged into docs/results/table1.{md,json,png}.

A row is a named composition: config files combined in order (as several `hg fit --config` flags) and optional CLI
overrides, or scripts/plan.py's arguments for a row that plans instead of learning. Each row says what makes its
prediction (the learned heads, the library classifier, or both summed: "learned", "library", "mixed") and what
chooses its probes ("learned" policy, "fixed" scan, "random" probes, the greedy "planner").

Each (row, seed) is one run in a child process (this script with `--one`, its log in its run folder), started by a
Ray task (hg.sweep): on a local Ray instance that trains `--jobs` runs at once, or on a Ray cluster given by
`--address` or RAY_ADDRESS (README, "Running the table on a cluster"); a row that scores another row's checkpoints
runs after that row's run of the same seed. A finished run leaves its record, a small JSON in `<out>/table1_runs/`
(its composition, its command, the accuracy after each probe, commit, hardware); it is never recomputed, so rows can
be run separately (even on other machines) and merged, and an interrupted run resumes from its last checkpoint in
`<runs-dir>`. SIGTERM or Ctrl-C cancels the runs not started and stops the running children (Lightning ends a fit at
the next step; the run resumes next time). Each record is one read of the test split; the table counts them per row.

    .venv/bin/python scripts/reproduce_table1.py --jobs 2                     # every row, seeds 0 1 2
    .venv/bin/python scripts/reproduce_table1.py --rows random --seeds 0      # one run; finished runs are reused
    RAY_ADDRESS=head:6379 .venv/bin/python scripts/reproduce_table1.py --threads 4   # on a Ray cluster
    .venv/bin/python scripts/reproduce_table1.py --merge-only                 # table1.* and docs/ablations.md
    .venv/bin/python scripts/reproduce_table1.py --ablations                  # docs/ablations.md alone
    .venv/bin/python scripts/reproduce_table1.py --objects data/objects/pyb10 --rows side_scan line_scan
                                                              # another set: table1_pyb10.*, from table1_runs_pyb10/

Every table file says its `objects`, the `commit` it was merged at and `heldout_min_distance_m`: the smallest
distance from a test pose to a training pose after the objects' symmetries and the library's augmentations
(hg.sim.heldout; 0.0 if any test pose is an image of a training pose).

Training never rewrites the table: `--merge-only` does, from the records of the rows defined here. The records of
the hg4 research (`<out>/runs/`, made by rows whose configs were deleted at 42a3851) are listed in the ablations page
(`--ablations`: docs/ablations.md, beside --out), never merged into the table.

The last line printed is JSON: for each row its mean accuracy after each probe, and the commit.
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np
import yaml

from hg.atomic import write_atomic
from hg.provenance import commit, hardware, repo_path
from hg.sweep import Job, Stopped, run_jobs

ROOT = Path(__file__).resolve().parents[1]
TEST_EPISODES = 2048  # the fixed held-out test set every row is scored on (data.eval_seed 0)
CLOUD_STEPS, CLOUD_BATCH = 1000, 64  # the point-cloud baselines' training, as the noise study's (reproduce_noise.py)
EVAL_SEED = 0
SEEDS = (0, 1, 2)  # training seeds of every row (the protocol)
RUNS = "table1_runs"  # <out>/RUNS: the records of the rows defined here
OLD_RUNS = "runs"  # <out>/OLD_RUNS: the records of the hg4 research, made by rows whose configs are deleted
LAST_OLD_CONFIGS = "743bddf"  # the last commit with those 77 configs (and the script that ran them)
SHOWN = (2, 5, 10)  # probe counts of the one-line summaries

Prediction = Literal["learned", "library", "mixed"]
Probes = Literal["learned", "fixed", "random", "planner"]
COLUMN = {"learned": "", "library": "_library", "mixed": "_mixed"}  # a prediction's suffix in the logged metrics


@dataclass(frozen=True)
class Row:
    """A row of the table: a composition of configs (+ CLI overrides) trained and tested, scripts/plan.py run with
    `plan` (a planner row; `probes` says which of its results: "planner", or probes placed by no one, "fixed" or
    "random", named by the same library classifier), or a point-cloud baseline `cloud` (hg.lightning.clouds.NETS)
    trained supervised on clean surface points, no probing."""

    label: str
    prediction: Prediction
    probes: Probes
    configs: tuple[str, ...] = ()  # relative to the repository, combined in order (later ones override)
    overrides: tuple[str, ...] = ()  # CLI overrides after the configs
    plan: tuple[str, ...] = ()  # a planner row: scripts/plan.py's library and prober arguments
    cloud: str | None = None  # a point-cloud baseline: PointNet or DGCNN on 10 clean surface points
    scores: str | None = None  # a row that trains nothing: it scores that row's best checkpoints (same seed) as its
    # composition reads them (e.g. with the library classifier), so it runs after that row
    paper: str | None = None  # the paper's column this row reproduces
    was: str | None = None  # the row of the hg4 records (<out>/runs) this one replaces

    def definition(self) -> dict:
        """What makes the row's numbers: a record made otherwise is another row's."""
        return {"prediction": self.prediction, "probes": self.probes, "configs": list(self.configs),
                "overrides": list(self.overrides), "plan": list(self.plan), "scores": self.scores,
                **({"cloud": self.cloud} if self.cloud else {})}  # (rows recorded before clouds have no such key)


TOUCH_SETS, LONG, STABLE_RL = "configs/parts/touch_sets.yaml", "configs/parts/long.yaml", "configs/parts/stable_rl.yaml"
REPAIRED = ("configs/parts/centred_points.yaml", "configs/parts/new_touch.yaml")  # the paper's method, repaired (#57)
LIBRARY = "configs/parts/library_classifier.yaml"  # planner_copy's library classifier: its first teacher file's library
PLANNER_COPY = ("configs/planner_copy.yaml", STABLE_RL, TOUCH_SETS, LONG)
# the greedy planner's library: 65536 training episodes, with their moves along the line and mirror images
PLANNER_LIBRARY = ("--library-split", "train", "--library", "65536", "--shifts", "5", "--mirror")
# the library of planner_copy's library classifier (the recipe of its first teacher file), without the planner
CLASSIFIER_LIBRARY = (*PLANNER_LIBRARY, "--library-seed", "10", "--no-planner")
COPY_65K = "pcrn_fc_candidates_readings_only_imitate_planner65k_final_mirror"  # its hg4 row
ROWS = {
    "pcrn_fc_as_written": Row("PCRN-FC, the paper's hybrid rule as written", "learned", "learned",
                              ("configs/pcrn_fc.yaml",), paper="PCRN-FC", was="pcrn_fc"),
    "pcrn_nclass_as_written": Row("PCRN-N-class, the paper's hybrid rule as written", "learned", "learned",
                                  ("configs/pcrn_nclass.yaml",), paper="PCRN-N-class", was="pcrn_nclass"),
    "lstm_as_written": Row("LSTM, the paper's hybrid rule as written", "learned", "learned", ("configs/lstm.yaml",),
                           paper="LSTM", was="lstm"),
    "pcrn_fc": Row("PCRN-FC and the paper's Gaussian location network from no scan, repaired: points read around "
                   "their touches' centre, REINFORCE out of the encoder, the probe count, a new-touch reward",
                   "learned", "learned", ("configs/pcrn_fc.yaml", *REPAIRED), paper="PCRN-FC"),
    "pcrn_nclass": Row("PCRN-N-class and the paper's Gaussian location network from no scan, repaired as pcrn_fc",
                       "learned", "learned", ("configs/pcrn_nclass.yaml", *REPAIRED), paper="PCRN-N-class"),
    "lstm": Row("LSTM and the paper's Gaussian location network from no scan, repaired as pcrn_fc but for the centring "
                "(its encoder is no PCRN)", "learned", "learned", ("configs/lstm.yaml", REPAIRED[1]), paper="LSTM"),
    "random": Row("random probes + PCRN-FC", "learned", "random", ("configs/random.yaml",), was="random"),
    "line_scan": Row("line scan + PCRN-FC", "learned", "fixed", ("configs/line_scan.yaml",), was="line_scan"),
    "side_scan": Row("side-picking scan + mirrored touch-set classifiers (fixed probes)", "learned", "fixed",
                     ("configs/side_scan.yaml", TOUCH_SETS, LONG),
                     was="side_scan_touchset_wide_final_mirror_long_lr_decay"),
    "gaussian_on_side_scan": Row(
        "learned Gaussian policy started on the side-picking scan + mirrored touch sets", "learned", "learned",
        ("configs/gaussian_on_side_scan.yaml", STABLE_RL, TOUCH_SETS, LONG),
        was="pcrn_fc_side_touchset_warmup_wide_std_decay_long_exact_anchor_lr_decay_final_mirror"),
    "choice_on_side_scan": Row(
        "a choice among candidates started on the side-picking scan (copying it for the first half), then the hybrid "
        "rule + mirrored touch sets", "learned", "learned",
        ("configs/side_scan.yaml", "configs/parts/choice_on_scan.yaml", STABLE_RL, TOUCH_SETS, LONG),
        overrides=("--model.warmup.init_args.steps", "8000")),
    "best_probe_choice": Row(
        "a choice among candidates from no scan that learns to ask for whichever of 9 probed candidates its heads read "
        "best (privileged targets from the simulator, no REINFORCE) + mirrored touch sets", "learned", "learned",
        ("configs/side_scan.yaml", "configs/parts/choice_on_scan.yaml", "configs/parts/best_probe.yaml", STABLE_RL,
         TOUCH_SETS, LONG)),
    "planner_copy": Row("a choice among the greedy planner's candidates, copying it, then the hybrid rule: its learned "
                        "heads", "learned", "learned", PLANNER_COPY, was=COPY_65K),
    "planner_copy_library": Row("planner_copy's probes, named by the library classifier alone", "library", "learned",
                                (*PLANNER_COPY, LIBRARY), scores="planner_copy", was=f"{COPY_65K}_library_namer"),
    "planner_copy_mixed": Row("planner_copy's probes, its heads and the library classifier summed", "mixed",
                              "learned", (*PLANNER_COPY, LIBRARY), scores="planner_copy",
                              was=f"{COPY_65K}_library_namer"),
    "planner65k": Row("greedy information-gain planner over 65536 training poses, named by its library classifier (no "
                      "learning)", "library", "planner", plan=PLANNER_LIBRARY, was="planner65k"),
    "candidate_scan_library": Row("straight centre-out scan of the planner's candidate places, named by planner_copy's "
                                  "library classifier (no learning)", "library", "fixed",
                                  plan=(*CLASSIFIER_LIBRARY, "--fixed"), was="candidate_scan_namer65k"),
    "pointnet": Row("PointNet on 10 clean surface points (uniform over the whole surface; after k: the same net "
                    "reading the first k)", "learned", "random", cloud="pointnet"),
    "dgcnn": Row("DGCNN (k=9) on 10 clean surface points (uniform over the whole surface; after k: the same net "
                 "reading the first k)", "learned", "random", cloud="dgcnn"),
    "random_candidates_library": Row("random candidates of the planner, named by planner_copy's library classifier "
                                     "(no learning)", "library", "random", plan=(*CLASSIFIER_LIBRARY, "--random"),
                                     was="random_candidates_namer65k"),
}

# Table 1 of Riou et al. (ICASSP 2021): accuracy after k probes, 4 objects, held-out poses (no entry for k=1).
PAPER = {
    "LSTM": {2: 0.308, 3: 0.304, 4: 0.289, 5: 0.298, 6: 0.331, 7: 0.526, 8: 0.577, 9: 0.703, 10: 0.723},
    "PCRN-N-class": {2: 0.205, 3: 0.112, 4: 0.222, 5: 0.286, 6: 0.345, 7: 0.429, 8: 0.506, 9: 0.695, 10: 0.843},
    "PCRN-FC": {2: 0.416, 3: 0.505, 4: 0.576, 5: 0.615, 6: 0.649, 7: 0.670, 8: 0.687, 9: 0.710, 10: 0.796},
}


def teacher_files(objects: str) -> list[tuple[int, str]]:
    """The planner copy's teacher files for an object set, by seed, planned on the new protocol as
    data/planner/across_line/README.md says (hg4's are the ones its configs name)."""
    return [(seed, f"data/planner/across_line/{set_name(objects)}_train65k_s{seed}.npz") for seed in (10, 20)]


def on_set(spec: Row, objects: str, composition: list[str]) -> tuple[tuple[str, ...], tuple[str, ...]]:
    """A row's plan arguments and CLI overrides on an object set: on another set than hg4, that set and, for a
    composition with the planner copy or its library classifier, the set's own teacher files (refused when missing,
    with the command that writes them); a planner's library without mirror images when the set has chiral objects
    (hg.sim.symmetry)."""
    if objects == "hg4":
        return spec.plan, spec.overrides
    from hg.sim import load_object_set
    from hg.sim.symmetry import all_mirror_symmetric

    mirror = all_mirror_symmetric(load_object_set(objects))
    def on_this_set(args: tuple[str, ...]) -> tuple[str, ...]:
        return args if mirror else tuple(a for a in args if a != "--mirror")

    plan = on_this_set(spec.plan)
    overrides = (*spec.overrides, "--data.objects", objects)
    copies, names = PLANNER_COPY[0] in composition, LIBRARY in composition
    if copies or names:
        teachers = teacher_files(objects)
        library = on_this_set(PLANNER_LIBRARY)
        for seed, path in teachers:
            if not (ROOT / path).is_file():
                raise FileNotFoundError(
                    f"{path}: no teacher file for {objects}; write it with scripts/plan.py --objects {objects} "
                    f"{' '.join(library)} --split train --episodes 3072 --seed {seed} --save-rollouts {path}")
        if copies:
            overrides += ("--model.warmup.init_args.teachers", json.dumps([path for _, path in teachers]))
        if names:
            overrides += ("--model.library_classifier.teacher", teachers[0][1])
    return plan, overrides


def run_name(row: str, seed: int) -> str:
    return f"{row}-seed{seed}"


def set_name(objects: str) -> str:
    """hg4, or the folder name of another object set (--objects)."""
    return "hg4" if objects == "hg4" else Path(objects).name


def set_suffix(objects: str) -> str:
    """'' for hg4, the paper's set; '_<folder name>' for another (--objects): its records and table sit beside."""
    return "" if objects == "hg4" else f"_{set_name(objects)}"


def records_folder(out: Path, objects: str = "hg4") -> Path:
    return out / f"{RUNS}{set_suffix(objects)}"


def recorded_objects(objects: str) -> str:
    """The object set as a record names it: hg4, or the folder relative to the repository (portable)."""
    return objects if objects == "hg4" else repo_path(objects)


def record_path(out: Path, row: str, seed: int, objects: str = "hg4") -> Path:
    return records_folder(out, objects) / f"{run_name(row, seed)}.json"


def run_folder(runs_dir: Path, row: str, seed: int, objects: str = "hg4") -> Path:
    """Where a run's checkpoints, wandb run and log live."""
    return runs_dir / f"{run_name(row, seed)}{set_suffix(objects)}"


def encoder_of(row: str) -> str | None:
    """The class_path of the row's encoder, as its composition sets it (None for a planner row)."""
    found = None
    for config in ROWS[row].configs:
        model = (yaml.safe_load((ROOT / config).read_text()) or {}).get("model") or {}
        found = (model.get("encoder") or {}).get("class_path", found)
    return found


# -- one run (child process) -------------------------------------------------------------------------------
def train_and_test(row: str, seed: int, runs_dir: Path, out: Path, jobs: int, test_episodes: int = TEST_EPISODES,
                   add_configs: tuple[str, ...] = (), objects: str = "hg4") -> None:
    """Train one (row, seed) with the paper protocol, resuming from its last checkpoint; score the checkpoint that
    was best on val on the test set (a scoring row: the best checkpoint of the row it scores; a planner row: plan on
    the test episodes); write the run's record atomically (its presence marks the run done). `add_configs` come
    after the row's composition (smoke tests: configs/parts/tiny.yaml); `objects` another object set than hg4."""
    from hg.lightning.experiment import fit_and_test

    spec = ROWS[row]
    code_commit = commit()  # the code this run trains with, read before it starts
    composition = [*spec.configs, *add_configs]
    plan, overrides = on_set(spec, objects, composition)
    if spec.cloud:
        facts = cloud_and_test(spec.cloud, seed, test_episodes, objects)
    elif plan:
        facts = plan_and_test(plan, seed, test_episodes, spec.probes, objects)
    else:
        checkpoint = None
        if spec.scores:
            source = record_path(out, spec.scores, seed, objects)
            if not source.is_file():
                raise FileNotFoundError(f"{source}: row {row} scores the checkpoints of row {spec.scores}; run its "
                                        f"seed {seed} first")
            scored = read_record(source)
            check_definition(source, scored)
            checkpoint = ROOT / scored["best_checkpoint"]
        trained = fit_and_test([ROOT / c for c in composition], seed,
                               run_folder(runs_dir, row, seed, objects), eval_seed=EVAL_SEED,
                               test_episodes=test_episodes, extra_args=overrides, checkpoint=checkpoint)
        verb = "fit" if checkpoint is None else f"test --ckpt_path {trained['best_checkpoint']}"
        columns, suffix = trained.pop("columns"), COLUMN[spec.prediction]
        if f"stochastic{suffix}" not in columns:
            raise ValueError(f"row {row}: predicts by '{spec.prediction}', its composition logs only "
                             f"{sorted(columns)} (a library or mixed prediction needs {LIBRARY})")
        val = trained.pop("val").get(f"stochastic{suffix}")
        facts = {"composition": [repo_path(ROOT / c) for c in composition], "overrides": list(spec.overrides),
                 "command": f"hg {verb} {' '.join(trained.pop('cli_args'))}", **trained,
                 "accuracy": columns[f"stochastic{suffix}"],
                 "accuracy_mean_action": columns.get(f"mean_action{suffix}"),
                 "best_val_acc": val, "test_columns": columns}
        if spec.scores:
            facts["scores_checkpoint_of"] = spec.scores
    result = {"row": row, "label": spec.label, "prediction": spec.prediction, "probes": spec.probes,
              "definition": spec.definition(), "objects": recorded_objects(objects),
              "split": "test", "seed": seed, **facts,
              "parallel_jobs": jobs,
              "commit": code_commit, "hardware": hardware()}
    write_atomic(record_path(out, row, seed, objects), json.dumps(result, indent=1) + "\n")


def plan_and_test(plan: tuple[str, ...], seed: int, test_episodes: int, probes: Probes, objects: str = "hg4") -> dict:
    """A planner row's run: scripts/plan.py with its library and prober arguments `plan` (drawn with `seed`) on the
    test episodes every row meets, in arm mode; the facts a trained run's record holds for its result `probes`
    ("planner", "fixed" or "random"), with the script's wall time (library and planning) as the training time.
    Nothing is learned, so there is no checkpoint and no validation score."""
    from hg.lightning.data import ProbeDataModule
    from hg.lightning.experiment import test_fingerprint

    args = [*plan, "--objects", objects, "--split", "test", "--episodes", str(test_episodes), "--table-episodes",
            "--mode", "arm", "--seed", str(seed)]
    start = time.time()
    proc = subprocess.run([sys.executable, str(ROOT / "scripts" / "plan.py"), *args], capture_output=True, text=True,
                          cwd=ROOT)
    if proc.returncode:
        raise RuntimeError(f"scripts/plan.py {' '.join(args)} failed (exit {proc.returncode}): {proc.stderr[-2000:]}")
    result = json.loads(proc.stdout.strip().splitlines()[-1])[probes]
    data = ProbeDataModule(objects=objects, test_episodes=test_episodes, eval_seed=EVAL_SEED)
    return {"plan_args": args, "command": f"scripts/plan.py {' '.join(args)}", "max_steps": 0, "resumed_from_step": 0,
            "accuracy": result["accuracy"], "accuracy_mean_action": None, "best_val_acc": None,
            "best_checkpoint": None, "train_wall_s": round(time.time() - start, 1), "test_wall_s": 0.0,
            "test_episodes": test_episodes, "test_fingerprint": test_fingerprint(data), "torch_threads": 1}


def cloud_and_test(name: str, seed: int, test_episodes: int, objects: str = "hg4") -> dict:
    """A point-cloud baseline's run: NETS[name] trained supervised on clouds of 10 clean surface points of fresh
    training poses (hg.lightning.clouds, the noise study's baseline at rate 0), the state best on the validation
    episodes' clouds scored on the test episodes' clouds, read whole and by their first k points (the accuracy after
    k, for the table's columns; the net was trained on 10)."""
    import torch

    from hg.lightning.clouds import train_cloud_classifier
    from hg.lightning.data import ProbeDataModule
    from hg.lightning.experiment import test_fingerprint

    data, steps = ProbeDataModule(objects=objects, test_episodes=test_episodes, eval_seed=EVAL_SEED), CLOUD_STEPS
    result = train_cloud_classifier(name, data.object_set, data.regions, 0.0, seed, steps, CLOUD_BATCH,
                                    data.hparams.val_episodes, test_episodes, EVAL_SEED, first_k=True,
                                    eval_batch_size=data.hparams.eval_batch_size)  # the fingerprint's episodes
    return {"command": f"hg.lightning.clouds.train_cloud_classifier({name!r}, rate=0, seed={seed}, steps={steps}, "
                       f"batch_size={CLOUD_BATCH})", "max_steps": steps, "resumed_from_step": 0,
            "accuracy": result["accuracy_first_k"], "accuracy_mean_action": None,
            "best_val_acc": result["best_val_acc"], "best_checkpoint": None, "train_wall_s": result["train_wall_s"],
            "test_wall_s": 0.0, "test_episodes": test_episodes, "test_fingerprint": test_fingerprint(data),
            "torch_threads": torch.get_num_threads()}


# -- records ------------------------------------------------------------------------------------------------
def read_record(path: Path) -> dict:
    try:
        record = json.loads(path.read_text())
    except json.JSONDecodeError as exc:
        raise ValueError(f"{path}: not a run record of this script ({exc})") from exc
    if not isinstance(record, dict) or "row" not in record or "seed" not in record:
        raise ValueError(f"{path}: not a run record of this script (no row or seed)")
    return record


def check_definition(path: Path, record: dict, composition: list[str] | None = None) -> None:
    """Refuses a record the row's current definition (and, when given, the composition this run asks) would not
    make: taking it for this row's run would put another model's numbers under its name."""
    spec = ROWS[record["row"]]
    if record.get("definition") != spec.definition():
        raise ValueError(f"{path}: made by another definition of row {record['row']} ({record.get('definition')}; now "
                         f"{spec.definition()}); move it away to run this one")
    if composition is not None and not spec.plan and not spec.cloud and record.get("composition") != composition:
        raise ValueError(f"{path}: made with {record.get('composition')}, this run asks {composition}; move it away "
                         "(or --out elsewhere) to run this one")


def load_runs(out: Path, objects: str = "hg4") -> dict[str, list[dict]]:
    """The records of the rows defined here on the object set, by row in ROWS' order and by seed; every one must have
    met the same test episodes and match its row's definition."""
    runs: dict[str, list[dict]] = {}
    folder = records_folder(out, objects)
    for path in sorted(folder.glob("*.json")):
        record = read_record(path)
        if record["row"] not in ROWS:
            raise ValueError(f"{path}: row {record['row']!r} is not defined in scripts/reproduce_table1.py")
        check_definition(path, record)
        made_on = record.get("objects", "hg4")  # records from before --objects are hg4's
        if made_on != recorded_objects(objects):
            raise ValueError(f"{path}: a run on objects {made_on}, not {objects}")
        if record.get("split") != "test":
            raise ValueError(f"{path}: scored the {record.get('split')} split; the table holds test scores only")
        runs.setdefault(record["row"], []).append(record)
    fingerprints = {(r["test_episodes"], r["test_fingerprint"]) for rs in runs.values() for r in rs}
    if len(fingerprints) > 1:
        raise ValueError(f"{folder}: runs were scored on different test episodes ({sorted(fingerprints)})")
    return {row: sorted(runs[row], key=lambda r: r["seed"]) for row in ROWS if row in runs}


def mean_std(values: list[list[float]]) -> tuple[list[float], list[float]]:
    """Mean and std (over seeds, ddof=1; 0 for one seed) of the accuracy after each probe."""
    array = np.array(values)
    std = array.std(0, ddof=1) if len(values) > 1 else np.zeros(array.shape[1])
    return array.mean(0).round(4).tolist(), std.round(4).tolist()


def summarise(runs: dict[str, list[dict]]) -> dict[str, dict]:
    """Per row: what it is, its seeds, the mean and std of its accuracy after each probe, and how many times its runs
    read the test split (`test_reads`: its records that scored test, one read each)."""
    table = {}
    for row, rs in runs.items():
        spec = ROWS[row]
        entry = {"label": spec.label, "prediction": spec.prediction, "probes": spec.probes,
                 "composition": list(spec.configs) or None, "overrides": list(spec.overrides),
                 "command": rs[0]["command"], "seeds": [r["seed"] for r in rs],
                 "test_reads": sum(r.get("split") == "test" for r in rs)}
        for key in ("accuracy", "accuracy_mean_action"):
            if all(r.get(key) is not None for r in rs):
                entry[key], entry[f"{key}_std"] = mean_std([r[key] for r in rs])
        prior = [r.get("test_columns", {}).get(f"prior{COLUMN[spec.prediction]}") for r in rs]
        if all(p is not None for p in prior):  # its heads also read behind its prior scan or model.compare_with
            entry["accuracy_prior"], entry["accuracy_prior_std"] = mean_std(prior)
            for rollout in ("", "_mean_action"):  # the sampled policy's probes, and its mean action's
                if all(r.get(f"accuracy{rollout}") is not None for r in rs):
                    gain = np.subtract([r[f"accuracy{rollout}"] for r in rs], prior)
                    entry[f"gain{rollout}_over_prior"], entry[f"gain{rollout}_over_prior_std"] = mean_std(gain.tolist())
                    entry[f"seeds{rollout}_above_prior"] = (gain > 0).sum(0).tolist()
        if all(r.get("best_val_acc") is not None for r in rs):
            entry["best_val_acc"] = round(float(np.mean([r["best_val_acc"] for r in rs])), 4)
        entry["train_wall_s"] = [r["train_wall_s"] for r in rs]
        entry["parallel_jobs"] = sorted({r["parallel_jobs"] for r in rs})
        entry["commits"] = sorted({r["commit"] for r in rs})
        entry["hardware"] = sorted({r["hardware"] for r in rs})
        table[row] = entry
    return table


def best_variant(table: dict[str, dict], prediction: Prediction | None = None,
                 encoder: str | None = "hg.nets.PCRN") -> str | None:
    """The row with a learned policy (of that prediction and encoder, if given; PCRN's by default) with the highest
    mean validation accuracy after the last probe: chosen on val, never on the test episodes the table reports, and
    among the rows that have all their seeds when any has (one lucky seed must not outrank a mean over three)."""
    rows = [row for row in table if ROWS[row].probes == "learned"
            and (encoder is None or encoder_of(row) == encoder)
            and (prediction is None or ROWS[row].prediction == prediction)]
    complete = [row for row in rows if len(table[row]["seeds"]) >= len(SEEDS)]
    return max(complete or rows, key=lambda row: table[row].get("best_val_acc", -1.0)) if rows else None


def targets(table: dict[str, dict]) -> list[str]:
    """The issue's targets, each as a line saying met / not met and by how much."""
    best = best_variant(table)
    if best is None:
        return ["- No PCRN row with a learned policy yet: no target read."]
    acc, n = table[best]["accuracy"], len(table[best]["accuracy"])
    among = f" among the rows with all {len(SEEDS)} seeds" if len(table[best]["seeds"]) >= len(SEEDS) else ""
    lines = [f"- Best PCRN variant (highest mean validation accuracy after {n} probes{among}, "
             f"{table[best].get('best_val_acc', float('nan')):.3f}): {table[best]['label']} (predicted by "
             f"{table[best]['prediction']})."]
    for k, goal in ((10, 0.95), (5, 0.85)):
        if k <= n:
            lines.append(f"- After {k} probes >= {goal}: {'met' if acc[k - 1] >= goal else 'not met'} "
                         f"({acc[k - 1]:.3f}, {acc[k - 1] - goal:+.3f}).")
    paper_best = {k: max(col[k] for col in PAPER.values()) for k in range(2, n + 1) if k <= 10}
    short = {k: acc[k - 1] - paper_best[k] for k in paper_best if acc[k - 1] < paper_best[k]}
    lines.append("- At every probe count at least the paper's best entry: " + (
        "met." if not short else "not met at " + ", ".join(f"{k} probes ({d:+.3f})" for k, d in short.items()) + "."))
    placed_by_no_one = (row for row in table if ROWS[row].probes in ("fixed", "random") and not ROWS[row].cloud)
    for other in placed_by_no_one:
        prediction = ROWS[other].prediction
        mine = best_variant(table, prediction)
        label = table[other]["label"]
        if mine is None or len(table[mine]["accuracy"]) != len(table[other]["accuracy"]):
            lines.append(f"- Beats {label} by >= 0.15 after its last probe: not compared (no learned policy's row "
                         f"predicted by '{prediction}' over as many probes).")
            continue
        gap = table[mine]["accuracy"][-1] - table[other]["accuracy"][-1]
        read_by = ("both predicted by learned heads (the two rows' heads may differ)" if prediction == "learned"
                   else f"the same classifier ('{prediction}') reading both")
        lines.append(f"- Beats {label} by >= 0.15 after its last probe, {read_by}: "
                     f"{'met' if gap >= 0.15 else 'not met'} ({gap:+.3f}, {table[mine]['label']}).")
    if "lstm" in table and len(table["lstm"]["accuracy"]) == n:
        lost = [k for k in range(3, n + 1) if acc[k - 1] <= table["lstm"]["accuracy"][k - 1]]
        lines.append("- Beats the LSTM at every probe count from 3 on: " + ("met." if not lost else f"not met at {lost}."))
    return lines


def second_set_targets(table: dict[str, dict]) -> list[str]:
    """#56's targets on an object set other than hg4, after the last probe: the learned policy with a learned
    prediction that reads best on validation above every fixed scan by >= 0.05, and within 0.03 of the planner."""
    best = best_variant(table, "learned", encoder=None)
    if best is None:
        return ["- No learned policy with a learned prediction yet: no target read."]
    mine, n, seeds = table[best]["accuracy"][-1], len(table[best]["accuracy"]), len(table[best]["seeds"])
    lines = [f"- Best learned policy with a learned prediction (highest mean validation accuracy after {n} probes"
             f"{' among the rows with all seeds' if seeds >= len(SEEDS) else ''}): {table[best]['label']}, "
             f"{seeds} seeds, {mine:.3f}."]
    for probes, goal, says in (("fixed", 0.05, "Above every fixed scan by >= 0.05"),
                               ("planner", -0.03, "Within 0.03 of the planner")):
        others = [row for row in table if ROWS[row].probes == probes and not ROWS[row].cloud]
        if not others:
            lines.append(f"- {says} after {n} probes: not compared (no such row yet).")
            continue
        other = max(others, key=lambda row: table[row]["accuracy"][-1])
        gap = mine - table[other]["accuracy"][-1]
        lines.append(f"- {says} after {n} probes: {'met' if gap >= goal else 'not met'} ({gap:+.3f} against "
                     f"{table[other]['label']}).")
    return lines


def gains_over_reference_scan(table: dict[str, dict]) -> list[str]:
    """#57's "above the best fixed scan with the same classifiers": a policy against its own heads behind its reference
    scan (its prior scan, or from no scan model.compare_with; only the probes differ), met when above in every seed
    after 5 and 10 probes (a mean is not enough); the sampled policy's probes (the row's accuracy), then its mean
    action's."""
    rows = [row for row in table if len(table[row].get("gain_over_prior", ())) >= 5]
    if not rows:
        return ["- No learned policy's runs scored their heads behind their reference scan: not compared."]
    lines = []
    for row in rows:
        entry, shown = table[row], [k for k in (5, 10) if k <= len(table[row]["gain_over_prior"])]
        for rollout, who in (("", ""), ("_mean_action", " by its mean action")):
            if f"gain{rollout}_over_prior" not in entry:
                continue
            above = entry[f"seeds{rollout}_above_prior"]
            every = all(above[k - 1] == len(entry["seeds"]) for k in shown)
            lines.append(
                f"- {entry['label']}{who} above its reference scan in every seed, the same heads behind both, after "
                f"{' and '.join(map(str, shown))} probes: {'met' if every else 'not met'} (" + "; ".join(
                    f"after {k}: {entry[f'accuracy{rollout}'][k - 1]:.3f} against "
                    f"{entry['accuracy_prior'][k - 1]:.3f}, "
                    f"{entry[f'gain{rollout}_over_prior'][k - 1]:+.3f} +- "
                    f"{entry[f'gain{rollout}_over_prior_std'][k - 1]:.3f}, above in {above[k - 1]} of "
                    f"{len(entry['seeds'])} seeds" for k in shown) + ").")
    return lines


def cell(entry: dict, key: str, k: int) -> str:
    """Mean +- std after probe k over the seeds (the mean alone for one seed); empty where not measured."""
    if key not in entry or k > len(entry[key]):
        return ""
    mean, std = entry[key][k - 1], entry[f"{key}_std"][k - 1]
    return f"{mean:.3f}" if len(entry["seeds"]) == 1 else f"{mean:.3f} +- {std:.3f}"


def markdown(table: dict[str, dict], merged_at: str, test_episodes: int, objects: str, heldout_m: float) -> str:
    rows = list(table)
    n = max(len(t["accuracy"]) for t in table.values())
    paper = {r: PAPER[ROWS[r].paper][10] for r in rows if ROWS[r].paper}
    lines = ["# Table 1, reproduced and compared",
             "",
             f"Objects: {objects}. Accuracy after each probe on the same {test_episodes} held-out test episodes of "
             "the new protocol (`--data.regions across_line`, docs/benchmark.md: a band across the probe line that no "
             "training pose, library or teacher episode reaches under any symmetry or augmentation; "
             + (f"every test pose at least {heldout_m} m from a training pose" if heldout_m > 0 else
                "**but a test pose of this set lies within reach of a training pose**")
             + "), single stochastic rollout, mean +- std over training seeds; each learned model is the "
             "checkpoint best on the validation episodes (a third, separate pose region). Each row says what predicts "
             "the class (`learned` heads, the `library` classifier, or both summed: `mixed`) and what chooses the "
             "probes (a `learned` policy, a `fixed` scan, `random` probes, the greedy `planner`). The paper's figures "
             "(Riou et al., ICASSP 2021, Table 1) come from the authors' own simulator: a yardstick, not the same "
             "experiment.",
             "",
             "Produced by `.venv/bin/python scripts/reproduce_table1.py --merge-only"
             + ("" if objects == "hg4" else f" --objects {objects}") + "` (paper protocol: 8000 steps, batch 64, "
             "10 probes, arm mode; each row's composition is named below). Merged at commit "
             f"`{merged_at}`; each row's runs were made at the commits listed with it. `test reads`: how many times "
             "the row's runs read the test split (each run once). The hg4 research's table, on the old regions, is "
             "archived with its caveats in `docs/archive/table1_hg4_research.md`; its rows are in "
             "`docs/ablations.md`.",
             "",
             "| row | predicts | probes | seeds | " + " | ".join(f"after {k}" for k in SHOWN) +
             " | mean action, after 10 | validation, after the last | paper, after 10 | test reads |",
             "|---|---|---|---|" + "---:|" * (len(SHOWN) + 4)]
    for r, entry in table.items():
        val = entry.get("best_val_acc")
        lines.append(f"| {entry['label']} | {entry['prediction']} | {entry['probes']} | {len(entry['seeds'])} | "
                     + " | ".join(cell(entry, "accuracy", k) for k in SHOWN)
                     + f" | {cell(entry, 'accuracy_mean_action', 10)} | {'' if val is None else f'{val:.3f}'} | "
                       f"{paper.get(r, '')} | {entry['test_reads']} |")
    lines += ["", "## After each probe", "",
              "| probes | " + " | ".join(table[r]["label"] for r in rows) + " | " + " | ".join(
                  f"paper {c}" for c in PAPER) + " |",
              "|---:|" + "---:|" * (len(rows) + len(PAPER))]
    for k in range(1, n + 1):
        lines.append(f"| {k} | " + " | ".join([cell(table[r], "accuracy", k) for r in rows] + [
            f"{PAPER[c][k]:.3f}" if k in PAPER[c] else "" for c in PAPER]) + " |")
    mean_action = [r for r in rows if "accuracy_mean_action" in table[r]]
    lines += ["", "![accuracy after each probe](table1.png)", ""]
    if mean_action:
        lines += ["Learned policies, mean-action rollout (the policy's most likely request instead of a sample), same "
                  "episodes:", "",
                  "| probes | " + " | ".join(table[r]["label"] for r in mean_action) + " |",
                  "|---:|" + "---:|" * len(mean_action)]
        for k in range(1, n + 1):
            lines.append(f"| {k} | " + " | ".join(cell(table[r], "accuracy_mean_action", k) for r in mean_action)
                         + " |")
        lines.append("")
    lines += ["## Runs", "",
              "| row | composition or command | seeds | training wall time per seed (s) | jobs in parallel | commits | "
              "hardware | test reads |", "|---|---|---|---|---|---|---|---:|"]
    for r in rows:
        entry = table[r]
        made = (" + ".join(f"`{c}`" for c in entry["composition"]) + "".join(f" `{o}`" for o in entry["overrides"])
                if entry["composition"] else f"`{entry['command']}`")
        lines.append(f"| {entry['label']} | {made} | {entry['seeds']} | "
                     f"{', '.join(f'{s:.0f}' for s in entry['train_wall_s'])} | {entry['parallel_jobs']} | "
                     f"{', '.join(f'`{c}`' for c in entry['commits'])} | {'; '.join(entry['hardware'])} | "
                     f"{entry['test_reads']} |")
    lines += ["", "With two jobs in parallel each trains on one torch thread. A run resumed after an interruption "
              "counts every attempt's training time up to its last checkpoint (`hg.lightning.callbacks.TrainingClock`).",
              "", "## Targets (issue #4)", "", *targets(table), ""]
    if objects != "hg4":
        lines += ["## Targets on this second object set (issue #56)", "", *second_set_targets(table), ""]
    lines += ["## Learned probes against their reference scan, the same heads (issue #57)", "",
              "Each seed's heads read the test episodes twice, behind the policy's probes and behind its reference "
              "scan's (`test/acc_prior`): the prior scan it started on, or from no scan the scan given as "
              "`model.compare_with`; the gain is their difference, mean +- std over the seeds.", "",
              *gains_over_reference_scan(table), ""]
    return "\n".join(lines)


def heldout_min_distance_m(objects: str, test_episodes: int) -> float:
    """The smallest distance (m) from a test episode's pose to a training pose after the objects' turns, the
    library's shifts along the line and the mirror across it (hg.sim.heldout.nearest_training_distance)."""
    from hg.lightning.data import ProbeDataModule
    from hg.sim.heldout import nearest_training_distance
    from hg.sim.symmetry import object_symmetries

    data = ProbeDataModule(objects=objects, mode="ideal", test_episodes=test_episodes, eval_seed=EVAL_SEED)
    batches = data.test_dataloader().dataset.batches
    labels = np.concatenate([b["labels"].numpy() for b in batches])
    poses = np.concatenate([b["poses"].numpy() for b in batches])
    gap = nearest_training_distance(poses, labels, data.regions, object_symmetries(data.object_set))
    return 0.0 if gap.reached.any() else round(float(gap.position_m.min()), 4)


def merge(out: Path, write: bool = True, objects: str = "hg4") -> dict:
    """The table of the rows defined here on the object set from their records: written to
    <out>/table1[_<set>].{json,md,png} when `write` and there is any record (else the files are left as they are).
    Returns each row's mean accuracy."""
    runs = load_runs(out, objects)
    merged_at = commit(paths=())
    if not runs:
        return {"commit": merged_at}
    table = summarise(runs)
    if write:
        from hg.lightning.callbacks import accuracy_plot

        first, name = next(iter(runs.values()))[0], f"table1{set_suffix(objects)}"
        heldout_m = heldout_min_distance_m(objects, first["test_episodes"])
        write_atomic(out / f"{name}.json", json.dumps({
            "objects": objects, "commit": merged_at, "heldout_min_distance_m": heldout_m,
            "test_episodes": first["test_episodes"], "test_fingerprint": first["test_fingerprint"],
            "best_variant": best_variant(table), "rows": table, "paper": PAPER}, indent=1) + "\n")
        write_atomic(out / f"{name}.md", markdown(table, merged_at, first["test_episodes"], objects, heldout_m))
        write_atomic(out / f"{name}.png", accuracy_plot(
            {f"{t['label']} (n={len(t['seeds'])})": t["accuracy"] for t in table.values()},
            reference={f"paper {c}": col for c, col in PAPER.items()}))
    return {"commit": merged_at, **{row: t["accuracy"] for row, t in table.items()}}


# -- the hg4 rows: docs/ablations.md ------------------------------------------------------------------------
def predicted_by(record: dict) -> str:
    """What predicted an hg4 record's `accuracy`: the planner's Bayes classifier for a planner row, the learned heads
    and the library classifier (then "library namer") summed for a row that had one (its name says so, and its later
    records also hold the namer alone), else the learned heads."""
    if str(record.get("config", "")).startswith("scripts/"):
        return "library"
    return "mixed" if "accuracy_namer_alone" in record or "library_namer" in record["row"] else "learned"


def ablations(out: Path) -> str:
    """The ablations page: every row of the hg4 records (<out>/runs) that no row defined here replaces, with its
    accuracy after 2, 5 and 10 probes as recorded, its config and how to run it again. A pure function of the
    records and ROWS (no date, no commit of its own), so that writing it twice gives the same file."""
    runs: dict[str, list[dict]] = {}
    for path in sorted((out / OLD_RUNS).glob("*.json")):
        record = read_record(path)
        runs.setdefault(record["row"], []).append(record)
    replaced = {spec.was: name for name, spec in ROWS.items() if spec.was}
    reads = sum(len(rs) for rs in runs.values())

    def recorded(rs: list[dict]) -> list[str]:
        entry = {"seeds": [r["seed"] for r in rs]}
        entry["accuracy"], entry["accuracy_std"] = mean_std([r["accuracy"] for r in rs])
        return [cell(entry, "accuracy", k) for k in SHOWN]

    lines = ["# Ablations of the hg4 research", "",
             "Generated by `.venv/bin/python scripts/reproduce_table1.py --ablations` (also written by `--merge-only`) "
             f"from the run records in `{repo_path(out / OLD_RUNS)}/`; do not edit it by hand.", "",
             "These rows were trained and scored on the old protocol, before the components refactor (42a3851), on "
             "Table 1's 2048 test episodes of hg4. The project's audit found that those figures are no clean held-out "
             "estimate (the \"unseen heading\" cells copy training poses, the planner's library reaches the test "
             "cells, the test split steered the design, the best variant's last points come from the library "
             "classifier): read the caveats in [archive/README.md](archive/README.md) before quoting any, and "
             "[findings.md](findings.md) for what each line of work established. Their records read the test split "
             f"{reads} times in all, one read per record.", "",
             f"Their configs were deleted at 42a3851; `{LAST_OLD_CONFIGS}` is the last commit with them. To run a row "
             f"again: `git checkout {LAST_OLD_CONFIGS} && .venv/bin/python scripts/reproduce_table1.py --rows <old row> "
             "--seeds N --out /tmp/hg4` (another `--out`: in `docs/results` the committed records would count as "
             "done; a row that scores another row's checkpoints needs that row's run first, in the same `--out`).", "",
             "`predicts`: what made the recorded figure, as Table 1 now names it (`learned` heads, the `library` "
             "classifier, or both summed: `mixed`, the old `acc` of a row with a library namer). Accuracy: mean +- std "
             "over the seeds, single stochastic rollout, as recorded.", "",
             "| old row | what it is | predicts | seeds | after 2 | after 5 | after 10 | config (as recorded) | made at "
             "| run again (at " + f"`{LAST_OLD_CONFIGS}`) |", "|---|---|---|---|---:|---:|---:|---|---|---|"]
    for row in sorted(r for r in runs if r not in replaced):
        rs = sorted(runs[row], key=lambda r: r["seed"])
        seeds = [r["seed"] for r in rs]
        config = rs[0].get("command") or rs[0]["config"]
        source = rs[0].get("scores_checkpoint_of")
        again = f"`--rows {row} --seeds {' '.join(map(str, seeds))}`" + (f" (after `{source}`)" if source else "")
        lines.append(f"| `{row}` | {rs[0]['label']} | {predicted_by(rs[0])} | {', '.join(map(str, seeds))} | "
                     + " | ".join(recorded(rs))
                     + f" | `{config}` | {', '.join(f'`{c}`' for c in sorted({r['commit'] for r in rs}))} | {again} |")
    lines += ["", "## The hg4 rows that Table 1's rows replace", "",
              "Run again under their new names by `scripts/reproduce_table1.py --rows <row>` at the current commit; "
              "`tests/test_golden.py` checks that four of the compositions give the numbers their old configs gave. "
              "Their recorded figures (old protocol, as above) are those of the archived table, "
              "`docs/archive/table1_hg4_research.md`.", "",
              "| old row | predicts | seeds | after 2 | after 5 | after 10 | row now | composition or command now |",
              "|---|---|---|---:|---:|---:|---|---|"]
    for old in sorted(r for r in runs if r in replaced):
        rs = sorted(runs[old], key=lambda r: r["seed"])
        spec = ROWS[replaced[old]]
        now = sorted(name for name, s in ROWS.items() if s.was == old)  # one old row, two predictions now
        made = " + ".join(f"`{c}`" for c in spec.configs) or f"`scripts/plan.py {' '.join(spec.plan)}`"
        lines.append(f"| `{old}` | {predicted_by(rs[0])} | {', '.join(str(r['seed']) for r in rs)} | "
                     + " | ".join(recorded(rs)) + f" | {', '.join(f'`{o}`' for o in now)} | {made} |")
    return "\n".join(lines) + "\n"


# -- driver -----------------------------------------------------------------------------------------------
def run_children(todo: list[tuple[str, int]], args: argparse.Namespace) -> int:
    """Each (row, seed) of `todo` as one Ray task running this script's `--one` child (hg.sweep.run_jobs), a row
    that scores another row's checkpoints after that row's run of the same seed. SIGTERM or Ctrl-C stops the running
    children and starts no more. Returns how many runs did not write their record."""
    threads = args.threads or max(1, (os.cpu_count() or 1) // args.jobs)
    env = {"OMP_NUM_THREADS": str(threads), "WANDB_MODE": os.environ.get("WANDB_MODE", "offline")}
    names = {run_name(*job) for job in todo}
    jobs = []
    for row, seed in sorted(todo, key=lambda job: bool(ROWS[job[0]].scores)):  # a scored run's job comes first
        command = (sys.executable, __file__, "--one", row, str(seed), "--out", str(args.out), "--runs-dir",
                   str(args.runs_dir), "--jobs", str(args.jobs), "--test-episodes", str(args.test_episodes),
                   "--objects", args.objects, *(a for c in args.add_config for a in ("--add-config", c)))
        scored = run_name(ROWS[row].scores, seed) if ROWS[row].scores else None
        log = run_folder(args.runs_dir, row, seed, args.objects) / "log.txt"
        jobs.append(Job(run_name(row, seed), command, log, record_path(args.out, row, seed, args.objects), env,
                        after=(scored,) if scored in names else ()))
    try:
        return run_jobs(jobs, threads, args.jobs, ROOT, args.address)
    except Stopped as stop:
        raise SystemExit(f"reproduce_table1: stopped by {stop.signal_name}; {stop.unfinished} runs unfinished (they "
                         "resume next time)") from None


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--rows", nargs="+", default=list(ROWS), choices=list(ROWS))
    parser.add_argument("--seeds", nargs="+", type=int, default=list(SEEDS))
    parser.add_argument("--jobs", type=int, default=1, help="runs trained at once on this machine (on a Ray cluster "
                        "its CPUs decide)")
    parser.add_argument("--address", default=None, help="the Ray cluster to run on (ray start's address; default: "
                        "RAY_ADDRESS, else a local Ray instance of jobs x threads CPUs)")
    parser.add_argument("--threads", type=int, default=None,
                        help="torch threads per run, the CPUs its Ray task asks for (default: this machine's cores / "
                             "jobs); beside other work on the machine use 1, since a run on 2 threads sharing a core "
                             "with another process crawls (0.25 steps/s against 5.8 on 1 thread, measured)")
    parser.add_argument("--add-config", action="append", default=[], metavar="FILE",
                        help="a config added after each trained row's composition (smoke tests: "
                             "configs/parts/tiny.yaml); recorded in the run's composition")
    parser.add_argument("--test-episodes", type=int, default=TEST_EPISODES, help="test set size (smoke tests only)")
    parser.add_argument("--objects", default="hg4", help="object set: hg4, or a folder of meshes (data/objects/pyb10): "
                        "its records and table sit beside hg4's as table1_runs_<name>/ and table1_<name>.*")
    parser.add_argument("--out", type=Path, default=ROOT / "docs" / "results")
    parser.add_argument("--runs-dir", type=Path, default=ROOT / "runs" / "table1", help="checkpoints and wandb runs")
    parser.add_argument("--merge-only", action="store_true",
                        help="train nothing: write table1.* from the records (when there are any) and the ablations "
                             "page")
    parser.add_argument("--ablations", action="store_true", help="write only the ablations page (docs/ablations.md, "
                                                                 "beside --out) from the hg4 records in <out>/runs")
    parser.add_argument("--one", nargs=2, metavar=("ROW", "SEED"), help=argparse.SUPPRESS)  # the child's job
    args = parser.parse_args()
    if args.threads is not None and args.threads < 1:
        parser.error(f"--threads {args.threads}: must be >= 1")
    if args.jobs < 1:
        parser.error(f"--jobs {args.jobs}: must be >= 1")
    for config in args.add_config:
        if not Path(config).is_file():
            parser.error(f"--add-config {config}: file not found")
    add_configs = tuple(repo_path(c) for c in args.add_config)
    if args.one:
        train_and_test(args.one[0], int(args.one[1]), args.runs_dir, args.out, args.jobs, args.test_episodes,
                       add_configs, args.objects)
        return
    if args.ablations or args.merge_only:
        write_atomic(args.out.parent / "ablations.md", ablations(args.out))
        print(f"written: {args.out.parent / 'ablations.md'}", flush=True)
        if args.ablations:
            return
    else:
        todo = []
        for seed in args.seeds:  # seed-major: every row gets a seed early
            for row in args.rows:
                path = record_path(args.out, row, seed, args.objects)
                if path.is_file():  # done, if by this very row and composition
                    check_definition(path, read_record(path), None if ROWS[row].plan else [
                        *ROWS[row].configs, *add_configs])
                else:
                    todo.append((row, seed))
        print(f"{len(todo)} runs to train: {', '.join(run_name(*t) for t in todo) or 'none'}", flush=True)
        failed = run_children(todo, args)
        print(f"{failed} runs failed; " if failed else "", "table1.* are written by --merge-only", sep="", flush=True)
    summary = merge(args.out, write=args.merge_only, objects=args.objects)
    if args.merge_only and len(summary) == 1:
        print(f"{records_folder(args.out, args.objects)}: no record of the rows defined here yet; the table is "
              "left as it is", flush=True)
    print(json.dumps(summary))
    if not args.merge_only and failed:
        sys.exit(1)


if __name__ == "__main__":
    try:
        main()
    except (ValueError, FileNotFoundError) as exc:  # bad inputs end in one line naming the file
        sys.exit(f"reproduce_table1: error: {exc}")
