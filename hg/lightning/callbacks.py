"""Callbacks: per-probe accuracy files and plots, the run configuration saved where the run lives, a moving
average of the weights, a training clock that survives resuming, and a resumable checkpoint that knows the last
validation."""
from __future__ import annotations

import csv
import io
import time
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import pytorch_lightning as pl  # noqa: E402
import yaml  # noqa: E402
from matplotlib.ticker import MaxNLocator  # noqa: E402
from pytorch_lightning.callbacks import ModelCheckpoint, WeightAveraging  # noqa: E402
from pytorch_lightning.cli import SaveConfigCallback  # noqa: E402
from pytorch_lightning.loggers import WandbLogger  # noqa: E402
from pytorch_lightning.trainer.states import TrainerFn  # noqa: E402
from pytorch_lightning.utilities import rank_zero_only  # noqa: E402
from torch.optim.swa_utils import get_ema_multi_avg_fn  # noqa: E402

from hg.atomic import write_atomic  # noqa: E402


def run_dir(trainer: pl.Trainer) -> Path:
    """The run's own folder: the wandb run's files folder (synced with the run), else the trainer's log dir."""
    logger = trainer.logger
    if isinstance(logger, WandbLogger) and isinstance(getattr(logger.experiment, "dir", None), str):
        return Path(logger.experiment.dir)
    if logger is not None and getattr(logger, "log_dir", None):  # not trainer.log_dir: it broadcasts across ranks
        return Path(logger.log_dir)
    return Path(trainer.default_root_dir)


def per_probe_table(metrics: dict, stage: str, n_probes: int) -> dict[str, list[float]]:
    """Columns of accuracy after probe k = 1..N found in logged metrics: stochastic and mean-action rollouts, and
    a library namer alone on the stochastic rollout's probes (model.library_namer)."""
    columns = {}
    for label, suffix in (("stochastic", ""), ("mean_action", "_mean_action"), ("namer_alone", "_namer")):
        keys = [f"{stage}/acc{suffix}@{k}" for k in range(1, n_probes + 1)]
        if all(k in metrics for k in keys):
            columns[label] = [float(metrics[k]) for k in keys]
    return columns


class LatestCheckpoint(ModelCheckpoint):
    """The checkpoint a run resumes from (last.ckpt, and latest-step{N}). Lightning writes it at the end of a training
    step, before a validation at that step, and not again after it; so a run stopped right after a validation
    resumed without that validation's score in the best-by-val callback's state, and could test a worse checkpoint
    as its best. Written again after each validation here."""

    def on_validation_end(self, trainer: pl.Trainer, pl_module: pl.LightningModule) -> None:
        super().on_validation_end(trainer, pl_module)
        if (trainer.state.fn == TrainerFn.FITTING and not trainer.sanity_checking and not trainer.fast_dev_run
                and self._last_global_step_saved == trainer.global_step):  # saved at this step, before validating
            self._save_last_checkpoint(trainer, self._monitor_candidates(trainer))

    @property
    def state_key(self) -> str:
        """A plain ModelCheckpoint's key, so that checkpoints written before this class resume the same."""
        return super().state_key.replace(type(self).__qualname__, ModelCheckpoint.__qualname__, 1)


class PerProbeAccuracy(pl.Callback):
    """At test end: per_probe_accuracy.csv and .png in the run directory, the same logged to wandb, and the
    table printed. Accuracy after probe k is logged during evaluation as `val/acc@k` and `test/acc@k`.

    After every validation, a row of val_curve.csv in the run directory (global step, then accuracy after each
    probe): the learning curve, readable while a run goes on and without a wandb reader for offline runs."""

    @rank_zero_only
    def on_validation_end(self, trainer: pl.Trainer, pl_module: pl.LightningModule) -> None:
        if trainer.sanity_checking:
            return
        n_probes = pl_module.hparams.n_probes
        columns = per_probe_table(trainer.callback_metrics, "val", n_probes)
        if not columns:
            return
        header = ["step", *(f"{label}@{k}" for label in columns for k in range(1, n_probes + 1))]
        path = run_dir(trainer) / "val_curve.csv"
        step = trainer.global_step
        rows = list(csv.reader(path.open())) if path.is_file() else []
        # a resumed run continues its curve (dropping steps it validates again); another run's curve found there
        # (runs without a logger share the root folder) is replaced, never mixed in
        continued = len(rows) > 1 and rows[0] == header and int(rows[1][0]) < step
        rows = [header, *(r for r in rows[1:] if int(r[0]) < step)] if continued else [header]
        rows.append([str(step), *(f"{v:.4f}" for values in columns.values() for v in values)])
        text = io.StringIO()
        csv.writer(text).writerows(rows)
        write_atomic(path, text.getvalue())

    @rank_zero_only
    def on_test_end(self, trainer: pl.Trainer, pl_module: pl.LightningModule) -> None:
        n_probes = pl_module.hparams.n_probes
        columns = per_probe_table(trainer.callback_metrics, "test", n_probes)
        if not columns:
            return
        folder = run_dir(trainer)
        text = io.StringIO()
        writer = csv.writer(text)
        writer.writerow(["probes", *columns])
        rows = [[k + 1, *(round(v[k], 4) for v in columns.values())] for k in range(n_probes)]
        writer.writerows(rows)
        write_atomic(folder / "per_probe_accuracy.csv", text.getvalue())
        plot_path = folder / "per_probe_accuracy.png"
        write_atomic(plot_path, accuracy_plot({f"{pl_module.hparams.policy} ({label} rollout)": values
                                               for label, values in columns.items()}))
        if isinstance(trainer.logger, WandbLogger):
            trainer.logger.log_table("test/per_probe_accuracy", columns=["probes", *columns], data=rows)
            trainer.logger.log_image("test/per_probe_accuracy_plot", images=[str(plot_path)])
        header = "probes | " + " | ".join(f"{c:>11s}" for c in columns)
        print(f"\nTest accuracy after each probe (single rollout, {pl_module.hparams.policy} policy):\n{header}")
        for row in rows:
            print(f"{row[0]:6d} | " + " | ".join(f"{v:11.3f}" for v in row[1:]))
        print(f"written: {folder / 'per_probe_accuracy.csv'}, {plot_path}")


def accuracy_plot(curves: dict[str, list[float]], title: str = "Accuracy after each probe (held-out test poses)",
                  reference: dict[str, dict[int, float]] | None = None) -> bytes:
    """PNG bytes of accuracy-vs-probes curves; `reference` curves ({probe: accuracy}, e.g. the paper's) dashed."""
    fig, ax = plt.subplots(figsize=(6, 4), dpi=110)
    colours, markers = plt.get_cmap("tab20").colors, "os^Dv"  # a dozen rows must not share a colour
    for i, (name, values) in enumerate(curves.items()):
        ax.plot(range(1, len(values) + 1), values, marker=markers[i % len(markers)], color=colours[i % 20], label=name)
    for i, (name, points) in enumerate((reference or {}).items(), start=len(curves)):
        ax.plot(list(points), list(points.values()), "--", color=colours[i % 20], label=name)
    ax.set(xlabel="probes", ylabel="accuracy", ylim=(0, 1.02), title=title)
    ax.xaxis.set_major_locator(MaxNLocator(integer=True))  # probe counts are whole numbers
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8, loc="upper left", bbox_to_anchor=(1.01, 1))  # beside the axes: never over a curve
    buffer = io.BytesIO()
    fig.savefig(buffer, format="png", bbox_inches="tight")
    plt.close(fig)
    return buffer.getvalue()


class TrainingClock(pl.Callback):
    """Training wall time summed over a run's attempts. Its total rides in every checkpoint, so a run resumed after
    an interruption reports what its steps took, not only its last attempt (the time an interruption lost after the
    last checkpoint is not counted: those steps were trained again)."""

    def __init__(self) -> None:
        self.seconds = 0.0  # earlier attempts, and this one once it has ended
        self._start: float | None = None

    @property
    def elapsed(self) -> float:
        return self.seconds + (time.time() - self._start if self._start is not None else 0.0)

    def setup(self, trainer: pl.Trainer, pl_module: pl.LightningModule, stage: str) -> None:
        if stage == "fit":  # before a checkpoint's state is restored, which sets the earlier attempts' seconds
            self.seconds, self._start = 0.0, time.time()

    def teardown(self, trainer: pl.Trainer, pl_module: pl.LightningModule, stage: str) -> None:
        if stage == "fit" and self._start is not None:
            self.seconds, self._start = self.elapsed, None

    def state_dict(self) -> dict:
        return {"seconds": self.elapsed}

    def load_state_dict(self, state_dict: dict) -> None:
        self.seconds = float(state_dict["seconds"])


class RunDirSaveConfig(SaveConfigCallback):
    """Saves the full config into the run directory and into the logger's hyperparameters.

    Lightning's default writes config.yaml into trainer.log_dir, which for WandbLogger is the shared save_dir,
    so a second `fit` there aborts; every run has its own folder instead.
    """

    def save_config(self, trainer: pl.Trainer, pl_module: pl.LightningModule, stage: str) -> None:
        if trainer.is_global_zero:
            config = self.parser.dump(self.config, skip_none=False)
            write_atomic(run_dir(trainer) / self.config_filename, config)
            if trainer.logger is not None:
                trainer.logger.log_hyperparams({"config": yaml.safe_load(config)})


class WeightEMA(WeightAveraging):
    """Beyond the paper: validate, test and checkpoint an exponential moving average of the weights (`decay` per
    step), Lightning's WeightAveraging. Why: fed fresh episodes at a constant learning rate, the model keeps
    moving, its validation accuracy swings from one check to the next, and the best checkpoint is picked on those
    swings. A checkpoint's state_dict holds the average (the live weights ride along for resuming), so `hg test`
    and the scripts score the average. Buffers are not averaged but copied: the policy's std scale must be the
    schedule's current one. Add it to a config's `trainer.callbacks`."""

    def __init__(self, decay: float = 0.999) -> None:
        if not 0.0 < decay < 1.0:
            raise ValueError(f"WeightEMA decay={decay}: must be in (0, 1) (the share of the average kept per step)")
        super().__init__(use_buffers=False, multi_avg_fn=get_ema_multi_avg_fn(decay))

    def on_train_batch_end(self, trainer: pl.Trainer, pl_module: pl.LightningModule, outputs, batch,
                           batch_idx: int) -> None:
        super().on_train_batch_end(trainer, pl_module, outputs, batch, batch_idx)
        for average, current in zip(self._average_model.module.buffers(), pl_module.buffers()):
            average.copy_(current)

    # Lightning's callback also swaps and reloads outside fitting: a `trainer.test(ckpt_path=...)` after `fit` (as
    # hg/lightning/experiment.py does) would load the checkpoint's live weights over its average, and a validate
    # would swap in the average left from training. Outside fitting the module keeps what the checkpoint holds.
    def _fitting(self, trainer: pl.Trainer) -> bool:
        return trainer.state.fn == TrainerFn.FITTING

    def on_validation_epoch_start(self, trainer: pl.Trainer, pl_module: pl.LightningModule) -> None:
        if self._fitting(trainer):
            super().on_validation_epoch_start(trainer, pl_module)

    def on_validation_epoch_end(self, trainer: pl.Trainer, pl_module: pl.LightningModule) -> None:
        if self._fitting(trainer):
            super().on_validation_epoch_end(trainer, pl_module)

    def on_load_checkpoint(self, trainer: pl.Trainer, pl_module: pl.LightningModule, checkpoint: dict) -> None:
        if self._fitting(trainer):  # resuming: the live weights and the average both come back
            super().on_load_checkpoint(trainer, pl_module, checkpoint)
