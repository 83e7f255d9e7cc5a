"""Callbacks: per-probe accuracy files and plots, the run configuration saved where the run lives, the schedules of
the policy's std and of the learning rate, a training clock that survives resuming, and resumable checkpoints that
know the last validation and survive a moved run folder."""
from __future__ import annotations

import csv
import io
import math
import os
import statistics
import time
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import pytorch_lightning as pl  # noqa: E402
import torch  # noqa: E402
import yaml  # noqa: E402
from matplotlib.ticker import MaxNLocator  # noqa: E402
from pytorch_lightning.callbacks import ModelCheckpoint  # noqa: E402
from pytorch_lightning.cli import SaveConfigCallback  # noqa: E402
from pytorch_lightning.loggers import WandbLogger  # noqa: E402
from pytorch_lightning.trainer.states import TrainerFn  # noqa: E402
from pytorch_lightning.utilities import rank_zero_only  # noqa: E402

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
    """Columns of accuracy after probe k = 1..N found in logged metrics: the learned heads on stochastic and
    mean-action rollouts and behind its reference scan (HapticGlance._eval_step) and, with a library classifier
    (model.library_classifier), it alone and mixed with them."""
    columns = {}
    for who in ("", "_library", "_mixed"):
        for rollout, suffix in (("stochastic", ""), ("mean_action", "_mean_action"), ("prior", "_prior")):
            keys = [f"{stage}/acc{who}{suffix}@{k}" for k in range(1, n_probes + 1)]
            if all(k in metrics for k in keys):
                columns[f"{rollout}{who}"] = [float(metrics[k]) for k in keys]
    return columns


class MovableCheckpoint(ModelCheckpoint):
    """A ModelCheckpoint that keeps its record (best score, best and last paths) when a run resumes in another folder
    than the one saved: moved to another clone, or a new logger's folder. Lightning drops it there, and the run chose
    its best among the later validations only (docs/findings.md, section 24). The saved paths are read as lying
    beside the checkpoint resumed from; where none of the files it names is there, Lightning's own handling stands."""

    PATHS = ("best_model_path", "kth_best_model_path", "last_model_path")
    _resumed_from: str | None = None

    def on_load_checkpoint(self, trainer: pl.Trainer, pl_module: pl.LightningModule, checkpoint: dict) -> None:
        self._resumed_from = trainer.ckpt_path  # Lightning loads this callback's state right after this hook

    def load_state_dict(self, state_dict: dict) -> None:
        saved, source = state_dict.get("dirpath"), self._resumed_from
        if all(p and "://" not in str(p) for p in (saved, source, self.dirpath)) and saved != self.dirpath:
            beside = os.path.dirname(os.path.realpath(source))
            if beside == os.path.realpath(self.dirpath):  # spelled as Lightning spells the folder it saves into
                beside = self.dirpath

            def there(path: str) -> str:
                return os.path.join(beside, os.path.basename(path)) if os.path.dirname(path) == saved else path

            moved = {k: there(state_dict[k]) for k in self.PATHS if state_dict.get(k)}
            if any(os.path.isfile(p) for p in moved.values()):  # the best, or the last.ckpt resumed from
                state_dict = {**state_dict, **moved, "dirpath": self.dirpath,
                              "best_k_models": {there(p): v for p, v in state_dict.get("best_k_models", {}).items()}}
        super().load_state_dict(state_dict)

    @property
    def state_key(self) -> str:
        """A plain ModelCheckpoint's key, so that checkpoints written before this class resume the same."""
        return super().state_key.replace(type(self).__qualname__, ModelCheckpoint.__qualname__, 1)


class LatestCheckpoint(MovableCheckpoint):
    """The checkpoint a run resumes from (last.ckpt, and latest-step{N}). Lightning writes it at the end of a training
    step, before a validation at that step, and not again after it; so a run stopped right after a validation
    resumed without that validation's score in the best-by-val callback's state, and could test a worse checkpoint
    as its best. Written again after each validation here."""

    def on_validation_end(self, trainer: pl.Trainer, pl_module: pl.LightningModule) -> None:
        super().on_validation_end(trainer, pl_module)
        if (trainer.state.fn == TrainerFn.FITTING and not trainer.sanity_checking and not trainer.fast_dev_run
                and self._last_global_step_saved == trainer.global_step):  # saved at this step, before validating
            self._save_last_checkpoint(trainer, self._monitor_candidates(trainer))


class FinalValidation(pl.Callback):
    """Validate after the last training step even when max_steps is not a multiple of val_check_interval, so the
    best checkpoint and the validation curve see the final weights. Lightning validates when `should_stop` is set,
    on every rank alike under DDP (the step count is the same everywhere)."""

    def on_train_batch_end(self, trainer: pl.Trainer, pl_module: pl.LightningModule, outputs, batch,
                           batch_idx: int) -> None:
        interval = trainer.val_check_interval
        if (trainer.max_steps > 0 and trainer.global_step >= trainer.max_steps and isinstance(interval, int)
                and trainer.accumulate_grad_batches == 1 and trainer.global_step % interval):  # steps = batches
            trainer.should_stop = True


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
        # a resumed run continues its curve (dropping steps it validates again), also when newer code scores more
        # columns (blank in its earlier rows); another run's curve found there (runs without a logger share the root
        # folder) is replaced, never mixed in
        continued = len(rows) > 1 and header[:len(rows[0])] == rows[0] and int(rows[1][0]) < step
        blank = [""] * (len(header) - len(rows[0])) if continued else []
        rows = [header, *(r + blank for r in rows[1:] if int(r[0]) < step)] if continued else [header]
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
        policy = pl_module.policy

        def prober(label: str) -> str:  # the prior columns are the reference scan's probes
            return type(pl_module.reference_scan if label.startswith("prior") else policy).__name__

        write_atomic(plot_path, accuracy_plot({f"{prober(label)} ({label} rollout)": values
                                               for label, values in columns.items()}))
        if isinstance(trainer.logger, WandbLogger):
            trainer.logger.log_table("test/per_probe_accuracy", columns=["probes", *columns], data=rows)
            trainer.logger.log_image("test/per_probe_accuracy_plot", images=[str(plot_path)])
        header = "probes | " + " | ".join(f"{c:>11s}" for c in columns)
        print(f"\nTest accuracy after each probe (single rollout, {type(pl_module.policy).__name__} policy):\n{header}")
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


class GradientDiagnostics(pl.Callback):
    """Why a policy gradient may wreck the classifier it shares an encoder with: every `every_n_steps` training steps,
    the norms of the gradients the policy term (beta-weighted, as in the loss) and the cross-entropy send into the
    encoder, and their ratio, logged (train/grad_*) and written with the step's other training terms (advantage,
    stds, touch rate per probe, clamped share) to diagnostics.csv in the run directory. 0: off."""

    def __init__(self, every_n_steps: int = 50) -> None:
        if every_n_steps < 0:
            raise ValueError(f"diagnostics.every_n_steps={every_n_steps}: must be >= 0")
        self.every = every_n_steps
        self.rows: list[dict[str, float]] = []

    def on_before_backward(self, trainer: pl.Trainer, pl_module: pl.LightningModule, loss) -> None:
        terms = getattr(pl_module, "last_terms", None)
        if not self.every or trainer.global_step % self.every or terms is None:
            return
        params = [p for p in pl_module.encoder.parameters() if p.requires_grad]
        row = {"step": float(trainer.global_step)}
        parts = {"ce": terms["loss_ce"]}
        if "loss_policy" in terms:
            parts["policy"] = pl_module.loss.policy_weight(float(pl_module.policy.std_scale)) * terms["loss_policy"]
        for name, term in parts.items():
            grads = torch.autograd.grad(term, params, retain_graph=True, allow_unused=True)
            row[f"grad_{name}"] = float(torch.sqrt(sum((g.pow(2).sum() for g in grads if g is not None),
                                                       torch.zeros(()))))
        if "grad_policy" in row:
            row["grad_ratio"] = row["grad_policy"] / max(row["grad_ce"], 1e-12)
        pl_module.log_dict({f"train/{k}": v for k, v in row.items() if k != "step"})
        row |= {k: float(v.detach()) for k, v in terms.items()}
        path = run_dir(trainer) / "diagnostics.csv"
        if not self.rows and path.is_file():  # a resumed run continues its file, dropping steps it trains again
            self.rows = [{k: float(v) for k, v in r.items() if v != ""} for r in csv.DictReader(path.open())
                         if float(r["step"]) < trainer.global_step]
        self.rows.append(row)
        if trainer.is_global_zero:
            keys = list(dict.fromkeys(k for r in self.rows for k in r))
            text = io.StringIO()
            writer = csv.DictWriter(text, keys)
            writer.writeheader()
            writer.writerows(self.rows)
            write_atomic(path, text.getvalue())

    def state_dict(self) -> dict:
        """The rows so far ride in the checkpoint: a resumed run (even one that trains no further step) reads its
        whole training in late_means, whatever folder its new attempt logs to."""
        return {"rows": self.rows}

    def load_state_dict(self, state_dict: dict) -> None:
        self.rows = [dict(row) for row in state_dict["rows"]]

    def late_means(self, share: float) -> dict[str, float]:
        """The mean of each term over the last `share` of the rows (at least one): how training ended, on training
        poses (e.g. `acc`, the batch's accuracy after the last probe), for a run's record."""
        if not 0.0 < share <= 1.0:
            raise ValueError(f"late_means: share={share}: the share of the rows must be in (0, 1]")
        late = self.rows[len(self.rows) - math.ceil(len(self.rows) * share - 1e-9):]
        keys = dict.fromkeys(k for row in late for k in row if k != "step")
        return {k: statistics.fmean(row[k] for row in late if k in row) for k in keys}


def schedule_end(trainer: pl.Trainer, name: str) -> int:
    """trainer.max_steps, where a schedule ends; refuses an endless run."""
    last = trainer.max_steps
    if last is None or last < 1:
        raise ValueError(f"{name}.final_scale needs trainer.max_steps (the schedule ends there), got {last}")
    return last


class StdDecay(pl.Callback):
    """Beyond the paper: the learned policy's std (a choice's temperature) falls linearly from 1 when the policy
    starts learning (after any warm-up) to `final_scale` of its learned value at the last step, so that the policy
    explores early and the classifier ends up trained behind the steady probes it is tested with. 1: no decay."""

    def __init__(self, final_scale: float = 1.0) -> None:
        if not 0.0 < final_scale <= 1.0:
            raise ValueError(f"std_decay.final_scale={final_scale}: must be in (0, 1]")
        self.final_scale = final_scale

    def scale(self, step: int, start: int, last: int) -> float:
        """The factor at training step `step` (0-based) of steps start..last: 1 at `start`, final at `last`, the last
        training step, with which the model is then tested. A run ending within the warm-up is at the final std."""
        progress = min(max((step - start) / (last - start), 0.0), 1.0) if last > start else 1.0
        return 1.0 + (self.final_scale - 1.0) * progress

    def on_train_batch_start(self, trainer: pl.Trainer, pl_module: pl.LightningModule, batch, batch_idx: int) -> None:
        if self.final_scale != 1.0 and pl_module.policy.learned:
            last = schedule_end(trainer, "std_decay") - 1  # the last training step
            pl_module.policy.std_scale.fill_(self.scale(trainer.global_step, pl_module.policy_start, last))


class CosineLR(pl.Callback):
    """Beyond the paper: every learning rate falls along a half cosine to `final_scale` of itself at the last step: a
    classifier fed fresh episodes every step keeps some of the noise of its last updates unless the steps shrink.
    1: a constant learning rate."""

    def __init__(self, final_scale: float = 1.0) -> None:
        if not 0.0 < final_scale <= 1.0:
            raise ValueError(f"lr_decay.final_scale={final_scale}: must be in (0, 1]")
        self.final_scale = final_scale

    def on_train_batch_start(self, trainer: pl.Trainer, pl_module: pl.LightningModule, batch, batch_idx: int) -> None:
        if self.final_scale == 1.0:
            return
        last = max(schedule_end(trainer, "lr_decay") - 1, 1)  # the last training step
        final = self.final_scale
        factor = final + (1.0 - final) * 0.5 * (1.0 + math.cos(math.pi * min(trainer.global_step / last, 1.0)))
        for group in trainer.optimizers[0].param_groups:  # each group's own rate (the policy's may be scaled)
            group["lr"] = group["initial_lr"] * factor
