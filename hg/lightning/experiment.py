"""One training run of a config, scored on held-out episodes: the unit of work of the result scripts
(scripts/reproduce_table1.py, scripts/reproduce_noise.py). A run resumes from its folder's last checkpoint, so one
cut off at the end of a working session goes on where it stopped instead of starting again."""
from __future__ import annotations

import hashlib
import json
import time
from collections.abc import Mapping, Sequence
from dataclasses import asdict, is_dataclass
from pathlib import Path

from hg.provenance import repo_path


def fit_and_test(config: Path, seed: int, folder: Path, *, eval_seed: int, test_episodes: int,
                 steps: int | None = None, extra_args: Sequence[str] = (), checkpoint: Path | None = None) -> dict:
    """Train `config` with `seed` (checkpoints and the wandb run in `folder`), then test the checkpoint best on val;
    or, given `checkpoint` (another run's best), train nothing: score that checkpoint on val and test as `config`
    reads it (a config that adds to what the model names, e.g. model.library_namer).

    `extra_args` are CLI overrides applied after the config (e.g. the sensor noise); `steps` overrides max_steps
    (smoke tests). Returns the accuracy after each probe (stochastic and, for a learned policy, mean action), the
    best checkpoint and the run's facts; the caller adds what it is for and writes it."""
    import wandb

    from hg.lightning.callbacks import TrainingClock, per_probe_table
    from hg.lightning.cli import cli

    checkpoints = folder / "checkpoints"
    args = ["--config", str(config), "--seed_everything", str(seed),
            "--data.eval_seed", str(eval_seed), "--data.test_episodes", str(test_episodes),
            "--trainer.logger.init_args.save_dir", str(folder), "--trainer.logger.init_args.name", folder.name,
            "--checkpoint.dirpath", str(checkpoints), "--last_checkpoint.dirpath", str(checkpoints), *extra_args]
    if steps is not None:
        args += ["--trainer.max_steps", str(steps), "--trainer.val_check_interval", str(max(1, min(500, steps // 4)))]
    run = cli(args, run=False)
    if checkpoint is not None:
        if not checkpoint.is_file():
            raise FileNotFoundError(f"{checkpoint}: the checkpoint to score is missing")
        resumed_from = 0
        val = run.trainer.validate(run.model, datamodule=run.datamodule, ckpt_path=str(checkpoint))[0]["val/acc"]
        train_s, best_path, best_score = 0.0, str(checkpoint), val
    else:
        last = checkpoints / "last.ckpt"
        resumed_from = 0
        if last.is_file():
            import torch

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
    start = time.time()
    run.trainer.test(run.model, datamodule=run.datamodule, ckpt_path=best_path)
    test_s = time.time() - start
    columns = per_probe_table(run.trainer.callback_metrics, "test", run.model.hparams.n_probes)
    wandb.finish()  # close the run here: a caller that goes on (another run, a merge) must not print into its logs
    return {
        "max_steps": run.trainer.max_steps, "resumed_from_step": resumed_from,
        "accuracy": [round(v, 4) for v in columns["stochastic"]],
        "accuracy_mean_action": [round(v, 4) for v in columns["mean_action"]] if "mean_action" in columns else None,
        **({"accuracy_namer_alone": [round(v, 4) for v in columns["namer_alone"]]} if "namer_alone" in columns else {}),
        "best_val_acc": round(float(best_score), 4) if best_score is not None else None,
        "best_checkpoint": repo_path(best_path),
        "train_wall_s": round(train_s, 1), "test_wall_s": round(test_s, 1),
        "test_episodes": test_episodes, "test_fingerprint": test_fingerprint(run.datamodule),
        "torch_threads": __import__("torch").get_num_threads(),
    }


EVALUATION_ONLY = ("test_episodes", "eval_batch_size")  # what a resumed run may change: the test, not the training


def changed_hyperparameters(saved: dict, model_hparams: Mapping, data_hparams: Mapping) -> list[str]:
    """'model.X=<saved> (now <asked>)' for every hyperparameter a checkpoint was trained with that this run sets
    otherwise (e.g. another teacher in model.imitate, another data.noise): resuming would train the rest of the
    steps as another run and record it under this one's name. Keys one side lacks (added to the code since) are
    skipped: their defaults keep the older behaviour."""
    def plain(value):
        return json.loads(json.dumps(value, default=lambda o: asdict(o) if is_dataclass(o) else str(o)))

    differ = []
    for prefix, key, asked in (("model", "hyper_parameters", model_hparams),
                               ("data", "datamodule_hyper_parameters", data_hparams)):
        before = saved.get(key) or {}
        for name in sorted(set(before) & set(asked)):
            if name not in EVALUATION_ONLY and not name.startswith("_") and plain(before[name]) != plain(asked[name]):
                differ.append(f"{prefix}.{name}={plain(before[name])} (now {plain(asked[name])})")
    return differ


def test_fingerprint(datamodule) -> str:
    """SHA-256 of the test episodes (labels and poses): a merge checks that every run met the same ones."""
    digest = hashlib.sha256()
    for batch in datamodule.test_dataloader().dataset.batches:
        digest.update(batch["labels"].numpy().tobytes())
        digest.update(batch["poses"].numpy().tobytes())
    return digest.hexdigest()[:16]
