"""`hg`: Lightning's own CLI (fit, validate, test, predict) over HapticGlance and ProbeDataModule."""
from __future__ import annotations

import json
import os
import sys
import tempfile
import warnings
from dataclasses import asdict
from pathlib import Path

import torch
import yaml

from pytorch_lightning.callbacks import ModelCheckpoint
from pytorch_lightning.cli import LightningArgumentParser, LightningCLI

from hg.lightning.callbacks import CosineLR, GradientDiagnostics, LatestCheckpoint, PerProbeAccuracy, RunDirSaveConfig, StdDecay, TrainingClock
from hg.lightning.data import ProbeDataModule
from hg.lightning.module import HapticGlance
from hg.lightning.viz import ProbeMaps

TRAINER_DEFAULTS = {
    "logger": {"class_path": "pytorch_lightning.loggers.WandbLogger",
               "init_args": {"project": "haptic-glance", "offline": True, "save_dir": "runs"}},
    "max_steps": 8000,
    "val_check_interval": 500,
    "check_val_every_n_epoch": None,  # the training stream is endless: validate every val_check_interval steps
    "log_every_n_steps": 25,
    "num_sanity_val_steps": 0,
    "accelerator": "cpu",
    "deterministic": True,
}


class HapticCLI(LightningCLI):
    def add_arguments_to_parser(self, parser: LightningArgumentParser) -> None:
        # best by val/acc; and, separately, the latest every N steps plus last.ckpt for resuming (Lightning only
        # refreshes last.ckpt when its callback saved, which a best-only callback does not do every time)
        parser.add_lightning_class_args(ModelCheckpoint, "checkpoint")
        parser.set_defaults({"checkpoint.monitor": "val/acc", "checkpoint.mode": "max",
                             "checkpoint.filename": "best-step{step}", "checkpoint.auto_insert_metric_name": False})
        parser.add_lightning_class_args(LatestCheckpoint, "last_checkpoint")
        parser.set_defaults({"last_checkpoint.save_last": True, "last_checkpoint.every_n_train_steps": 100,
                             "last_checkpoint.filename": "latest-step{step}",
                             "last_checkpoint.auto_insert_metric_name": False})
        parser.add_lightning_class_args(PerProbeAccuracy, "per_probe_accuracy")
        parser.add_lightning_class_args(ProbeMaps, "probe_maps")  # heat maps and confusion matrices at test end
        parser.add_lightning_class_args(TrainingClock, "training_clock")  # training time over resumed attempts
        parser.add_lightning_class_args(StdDecay, "std_decay")  # schedules: off (final_scale 1) unless a config sets them
        parser.add_lightning_class_args(CosineLR, "lr_decay")
        parser.add_lightning_class_args(GradientDiagnostics, "diagnostics")
        parser.link_arguments("seed_everything", "data.seed")
        parser.link_arguments("data.n_probes", "model.n_probes")
        parser.link_arguments("data", "model.n_classes", compute_fn=lambda data: len(data.object_set),
                              apply_on="instantiate")


def cli(args: list[str] | None = None, run: bool = True) -> HapticCLI:
    """The CLI over `args`, or the command line when None. Given args are a script's own (main_job.py,
    reproduce_table1.py), not its command line: Lightning's warning about both is beside the point there."""
    os.environ.setdefault("WANDB_MODE", "offline")  # no internet here: runs are synced later with `wandb sync`
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message="LightningCLI's args parameter")
        return HapticCLI(HapticGlance, ProbeDataModule, seed_everything_default=0, trainer_defaults=TRAINER_DEFAULTS,
                         save_config_callback=RunDirSaveConfig, save_config_kwargs={"save_to_log_dir": False,
                                                                                     "overwrite": True},
                         args=args, run=run)


LINK_TARGETS = ("seed", "_instantiator")  # data.seed comes from seed_everything in the CLI


def datamodule_from_checkpoint(ckpt: str | Path, configs: list[str] = (), args: list[str] = ()) -> ProbeDataModule:
    """The checkpoint's ProbeDataModule, rebuilt by the CLI from its saved hyperparameters, then `configs` and
    CLI `args` (e.g. `["--data.noise.miss_prob", "0.1"]`) applied on top: the world a model was trained in. The
    model's saved parts go along, since the CLI parses a whole composition."""
    saved = torch.load(ckpt, map_location="cpu", weights_only=False)
    data = saved.get("datamodule_hyper_parameters")
    if data is None:
        raise ValueError(f"{ckpt}: no datamodule hyperparameters saved; was it written by `hg fit`?")
    model = {k: v for k, v in dict(saved.get("hyper_parameters", {})).items()
             if not k.startswith("_") and k not in ("n_probes", "n_classes")}  # linked from the data
    config = {"seed_everything": int(data.get("seed", 0)), "model": model,
              "data": {k: v for k, v in dict(data).items() if k not in LINK_TARGETS}}
    with tempfile.NamedTemporaryFile("w", suffix=".yaml", delete=False) as tmp:  # JSON first: Scene, tuples -> YAML
        yaml.safe_dump(json.loads(json.dumps(config, default=asdict)), tmp)
    argv = ["--config", tmp.name]
    for path in configs:
        argv += ["--config", str(path)]
    try:
        return cli([*argv, *args, "--trainer.logger", "false"], run=False).datamodule
    finally:
        Path(tmp.name).unlink()


def main() -> None:
    """Bad input ends in one line naming the field or file, and a non-zero exit (HG_TRACEBACK=1 for the wall)."""
    try:
        cli()
    except (ValueError, FileNotFoundError, FloatingPointError) as exc:
        if os.environ.get("HG_TRACEBACK"):
            raise
        print(f"hg: error: {exc}", file=sys.stderr)
        sys.exit(2)


if __name__ == "__main__":
    main()
