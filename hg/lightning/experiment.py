"""One training run of a composition of configs, scored on held-out episodes: the unit of work of the result scripts
(scripts/reproduce_table1.py, scripts/reproduce_noise.py). A run resumes from its folder's last checkpoint, so one
cut off at the end of a working session goes on where it stopped instead of starting again."""
from __future__ import annotations

import hashlib
import json
import os
import time
from collections.abc import Mapping, Sequence
from dataclasses import asdict, is_dataclass
from pathlib import Path

from hg.provenance import repo_path

# what a run may change without becoming another run: the test, and what is scored at validation and test but never
# trained (the library classifier, the scan the heads are compared behind)
EVALUATION_ONLY = ("test_episodes", "eval_batch_size", "library_classifier", "compare_with")


def run_args(configs: Sequence[str | Path], seed: int, *, eval_seed: int, test_episodes: int,
             extra_args: Sequence[str] = (), portable: bool = True) -> list[str]:
    """The CLI arguments of a run: its composition's config files in order (later ones override), its seed and test
    set, then CLI overrides. `portable`: config paths inside the repository relative to it, as records keep them."""
    args = [a for config in configs for a in ("--config", repo_path(config) if portable else str(config))]
    return [*args, "--seed_everything", str(seed), "--data.eval_seed", str(eval_seed),
            "--data.test_episodes", str(test_episodes), *extra_args]


# what a run's record keeps of how training ended: these terms over this last share of the diagnostics' rows
TRAINING_END_TERMS, TRAINING_END_SHARE = ("acc", "touch_rate"), 0.25


def fit_and_test(configs: str | Path | Sequence[str | Path], seed: int, folder: Path, *, eval_seed: int,
                 test_episodes: int, steps: int | None = None, extra_args: Sequence[str] = (),
                 checkpoint: Path | None = None, validate: bool = True) -> dict:
    """Train the composition `configs` with `seed` (checkpoints and the wandb run in `folder`), then test the
    checkpoint best on val; or, given `checkpoint` (another run's best), train nothing: score that checkpoint (on val
    unless `validate` is False, and on test) as the composition reads it (e.g. with a library classifier added).

    `extra_args` are CLI overrides applied after the configs (e.g. the sensor noise); `steps` overrides max_steps
    (smoke tests). Returns the accuracy after each probe of every prediction the model logs (`columns`, named as
    hg.lightning.callbacks.per_probe_table names them; `accuracy` and `accuracy_mean_action` are the learned heads'),
    the validation accuracy after the last probe (`val`, same names), the training batches' accuracy after the last
    probe and touch rate over the last quarter of the diagnostics' rows (`train_last_quarter`: how well it fits
    training poses, beside how well it generalises; None when nothing trained), the best checkpoint, the CLI
    arguments (`cli_args`, without the folder's) and the run's facts; the caller adds what it is for and writes it."""
    import torch

    from hg.lightning.callbacks import GradientDiagnostics, TrainingClock, per_probe_table
    from hg.lightning.cli import cli

    configs = [configs] if isinstance(configs, (str, Path)) else list(configs)
    extra = [*extra_args, *(["--trainer.max_steps", str(steps), "--trainer.val_check_interval",
                             str(max(1, min(500, steps // 4)))] if steps is not None else [])]
    given = {"eval_seed": eval_seed, "test_episodes": test_episodes, "extra_args": extra}
    checkpoints = folder / "checkpoints"
    versioned = sorted(p.name for p in checkpoints.glob("last-v*.ckpt"))
    if checkpoint is None and versioned:  # written beside last.ckpt by a resume in a moved folder before c34c920
        raise ValueError(f"{checkpoints}: {', '.join(versioned)} beside last.ckpt; the newest state may not be "
                         "last.ckpt, which a resume reads. Keep the newest of them as last.ckpt, remove the others")
    # WANDB_MODE=disabled (the tests): no logger at all, the run's files in its folder (a wandb logger asked for
    # offline runs makes one whatever the variable says)
    wandb_run = os.environ.get("WANDB_MODE") != "disabled"
    logger = (["--trainer.logger.init_args.save_dir", str(folder), "--trainer.logger.init_args.name", folder.name]
              if wandb_run else ["--trainer.logger", "false", "--trainer.default_root_dir", str(folder)])
    run = cli([*run_args(configs, seed, portable=False, **given), *logger, "--checkpoint.dirpath", str(checkpoints),
               "--last_checkpoint.dirpath", str(checkpoints)], run=False)
    n_probes = run.model.hparams.n_probes
    resumed_from, val, late = 0, {}, None
    if checkpoint is not None:
        if not checkpoint.is_file():
            raise FileNotFoundError(f"{checkpoint}: the checkpoint to score is missing")
        saved = torch.load(checkpoint, map_location="cpu", weights_only=False)
        differ = changed_hyperparameters(saved, run.model.hparams)  # the world may differ (a test with noise)
        if differ:
            raise ValueError(f"{checkpoint}: trained with {'; '.join(differ)}; scoring it under this composition would "
                             "record another model than the one tested")
        if validate:
            run.trainer.validate(run.model, datamodule=run.datamodule, ckpt_path=str(checkpoint))
            val = {k: v[-1] for k, v in per_probe_table(run.trainer.callback_metrics, "val", n_probes).items()}
        train_s, best_path = 0.0, str(checkpoint)
        best_score = val.get("stochastic")
    else:
        last = checkpoints / "last.ckpt"
        if last.is_file():
            saved = torch.load(last, map_location="cpu", weights_only=False)
            differ = changed_hyperparameters(saved, run.model.hparams, run.datamodule.hparams)
            if differ:
                raise ValueError(f"{last}: trained with {'; '.join(differ)}; resuming would finish it as another run. "
                                 f"Move {folder} away to train this one anew")
            resumed_from = int(saved["global_step"])
        run.trainer.fit(run.model, datamodule=run.datamodule, ckpt_path=str(last) if last.is_file() else None)
        train_s = next(c for c in run.trainer.callbacks if isinstance(c, TrainingClock)).seconds  # every attempt's
        best = next(c for c in run.trainer.checkpoint_callbacks if getattr(c, "monitor", None) == "val/acc")
        best_path, best_score = best.best_model_path, best.best_model_score
        if best_path and not Path(best_path).is_file():
            # stopped between saving a new best (which removes the old one) and rewriting last.ckpt: the state
            # resumed names the removed file, and the one best checkpoint kept (save_top_k 1) is the newer best
            kept = sorted(Path(best_path).parent.glob("best-step*.ckpt"), key=lambda p: p.stat().st_mtime)
            if not kept:
                raise FileNotFoundError(f"{best_path}: the best checkpoint is gone and no other is kept beside it")
            best_path, best_score = str(kept[-1]), None
        if best_score is not None:
            val = {"stochastic": float(best_score)}
        diagnostics = next((c for c in run.trainer.callbacks if isinstance(c, GradientDiagnostics)), None)
        if diagnostics is not None and diagnostics.rows:  # how training ended, on training poses
            late = {k: round(v, 4) for k, v in diagnostics.late_means(TRAINING_END_SHARE).items()
                    if k in TRAINING_END_TERMS}
    start = time.time()
    run.trainer.test(run.model, datamodule=run.datamodule, ckpt_path=best_path)
    test_s = time.time() - start
    columns = {k: [round(v, 4) for v in vs] for k, vs in
               per_probe_table(run.trainer.callback_metrics, "test", n_probes).items()}
    if wandb_run:
        import wandb

        wandb.finish()  # close the run here: a caller that goes on (another run, a merge) must not print into its logs
    return {
        "cli_args": run_args(configs, seed, **given), "max_steps": run.trainer.max_steps, "resumed_from_step": resumed_from,
        "columns": columns, "accuracy": columns["stochastic"], "accuracy_mean_action": columns.get("mean_action"),
        "val": {k: round(v, 4) for k, v in val.items()}, "train_last_quarter": late,
        "best_val_acc": round(float(best_score), 4) if best_score is not None else None,
        "best_checkpoint": repo_path(best_path),
        "train_wall_s": round(train_s, 1), "test_wall_s": round(test_s, 1),
        "test_episodes": run.datamodule.hparams.test_episodes, "test_fingerprint": test_fingerprint(run.datamodule),
        "torch_threads": torch.get_num_threads(),
    }


def changed_hyperparameters(saved: dict, model_hparams: Mapping, data_hparams: Mapping | None = None) -> list[str]:
    """'model.X.Y=<saved> (now <asked>)' for every hyperparameter a checkpoint was trained with that this run sets
    otherwise (e.g. model.warmup.init_args.teachers, data.noise.miss_prob): resuming would train the rest of the steps
    as another run and record it under this one's name. Injected parts are compared field by field down their
    class_path / init_args; a part of another class is one difference (its class_path). Keys one side lacks (added to
    the code since) are skipped: their defaults keep the older behaviour. data_hparams None: the model only."""
    def plain(value):
        return json.loads(json.dumps(value, default=lambda o: asdict(o) if is_dataclass(o) else str(o)))

    def compare(path: str, before, asked) -> None:
        if isinstance(before, dict) and isinstance(asked, dict):
            if "class_path" in before and "class_path" in asked and before["class_path"] != asked["class_path"]:
                differ.append(f"{path}.class_path={before['class_path']} (now {asked['class_path']})")
                return
            for key in sorted(set(before) & set(asked)):
                compare(f"{path}.{key}", before[key], asked[key])
        elif isinstance(before, list) and isinstance(asked, list) and len(before) == len(asked):
            for i, (old, new) in enumerate(zip(before, asked)):
                compare(f"{path}.{i}", old, new)
        elif before != asked and not same_contents(before, asked):
            differ.append(f"{path}={json.dumps(before)} (now {json.dumps(asked)})")

    differ: list[str] = []
    for prefix, key, asked in (("model", "hyper_parameters", model_hparams),
                               ("data", "datamodule_hyper_parameters", data_hparams)):
        if asked is None:
            continue
        before, asked = plain(dict(saved.get(key) or {})), plain(dict(asked))
        for name in sorted(set(before) & set(asked)):
            if name not in EVALUATION_ONLY and not name.startswith("_"):
                compare(f"{prefix}.{name}", before[name], asked[name])
    return differ


def same_contents(before: object, asked: object) -> bool:
    """Two paths to files of the same bytes, as they are now, are the same setting: a run folder copied to another
    clone of the repository resumes there, although its checkpoint names the URDF in the first clone (which must
    still be there). Only files: a folder (data.objects) named elsewhere stays another setting."""
    if not (isinstance(before, str) and isinstance(asked, str)):
        return False
    try:
        paths = Path(before), Path(asked)
        return all(p.is_file() for p in paths) and paths[0].read_bytes() == paths[1].read_bytes()
    except OSError:  # not a path at all (a name too long for one)
        return False


def test_fingerprint(datamodule) -> str:
    """SHA-256 of the test episodes (labels and poses): a merge checks that every run met the same ones."""
    digest = hashlib.sha256()
    for batch in datamodule.test_dataloader().dataset.batches:
        digest.update(batch["labels"].numpy().tobytes())
        digest.update(batch["poses"].numpy().tobytes())
    return digest.hexdigest()[:16]
