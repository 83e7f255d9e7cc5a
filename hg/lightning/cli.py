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

from pytorch_lightning.cli import LightningArgumentParser, LightningCLI
from pytorch_lightning.utilities.exceptions import MisconfigurationException

from hg.lightning.callbacks import (CosineLR, FinalValidation, GradientDiagnostics, LatestCheckpoint, MovableCheckpoint,
                                   PerProbeAccuracy, RunDirSaveConfig, StdDecay, TrainingClock)
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


LIGHTNING_CKPT_NAMES = ("best", "last", "hpc", "registry")  # ckpt_path values Lightning resolves itself


def one_line(message: str, limit: int = 400) -> str:
    """A parser's message as one line: nested type errors span many lines and can run to pages."""
    line = " ".join(str(message).split())
    return line if len(line) <= limit else line[:limit - 3] + "..."


class OneLineParser(LightningArgumentParser):
    """Bad options or config files end in one `hg: error:` line, like every other bad input (exit code 2);
    jsonargparse's usage screen is what --help is for. HG_TRACEBACK=1 keeps its own report."""

    def error(self, message: str, ex: Exception | None = None):
        if os.environ.get("HG_TRACEBACK") or not self.exit_on_error:
            super().error(message, ex)
        sys.stderr.write(f"hg: error: {one_line(message)}\n")
        self.exit(2)


def read_checkpoint(ckpt_path: str | None) -> dict | None:
    """The checkpoint a subcommand was given, read as Lightning will read it (weights only), before anything else
    happens: a missing or unreadable file fails here with its name. None for no path or a name Lightning resolves."""
    if (ckpt_path is None or str(ckpt_path) in LIGHTNING_CKPT_NAMES or "://" in str(ckpt_path)
            or str(ckpt_path).lower().startswith("registry:")):
        return None
    path = Path(ckpt_path)
    if not path.is_file():
        raise FileNotFoundError(f"ckpt_path={ckpt_path}: checkpoint file not found")
    try:
        saved = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # pickle, zip and torch errors of many types: the file is not a checkpoint
        raise ValueError(f"ckpt_path={ckpt_path}: not a checkpoint PyTorch can read "
                         f"({type(exc).__name__}: {one_line(exc, 120)})") from exc
    if not isinstance(saved, dict) or "state_dict" not in saved:
        raise ValueError(f"ckpt_path={ckpt_path}: no state_dict inside; was it written by `hg fit`?")
    return saved


def check_fits(shapes: dict[str, tuple[int, ...]], ckpt_path: str, model: torch.nn.Module) -> None:
    """A checkpoint of another composition fails before the run starts, naming the first weight that differs
    (`shapes`: the checkpoint's state_dict shapes, by name)."""
    advice = "give the config it was trained with (config.yaml in its run directory)"
    mine = {name: tuple(tensor.shape) for name, tensor in model.state_dict().items()}
    for name, shape in mine.items():
        if name not in shapes:
            raise ValueError(f"ckpt_path={ckpt_path}: written for another model: it has no '{name}'; {advice}")
        if shapes[name] != shape:
            raise ValueError(f"ckpt_path={ckpt_path}: written for another model: '{name}' has shape "
                             f"{shapes[name]} there, {shape} here; {advice}")
    if extra := sorted(set(shapes) - set(mine)):
        raise ValueError(f"ckpt_path={ckpt_path}: written for another model: this one has no '{extra[0]}'"
                         f"{f' (and {len(extra) - 1} more)' if len(extra) > 1 else ''}; {advice}")


class HapticCLI(LightningCLI):
    """Every input is checked before the subcommand runs (the checkpoint file once parsed; the model, data and
    Trainer when they are built; the checkpoint's fit to the model in `before_<subcommand>`), so bad input never
    leaves a run directory, a wandb run or a checkpoint behind."""

    checkpoint_shapes: dict[str, tuple[int, ...]] | None = None  # of the given checkpoint's weights, by name

    def parse_arguments(self, parser: LightningArgumentParser, args) -> None:
        super().parse_arguments(parser, args)
        if self.config.get("subcommand"):  # Lightning reads the checkpoint's hyperparameters next
            saved = read_checkpoint(self.config[self.config.subcommand].get("ckpt_path"))
            if saved is not None:
                self.checkpoint_shapes = {k: tuple(v.shape) for k, v in saved["state_dict"].items()}

    def _check_ckpt_path(self) -> None:
        if self.checkpoint_shapes is not None:
            check_fits(self.checkpoint_shapes, self.config[self.subcommand].ckpt_path, self.model)

    before_fit = before_validate = before_test = before_predict = _check_ckpt_path

    def add_arguments_to_parser(self, parser: LightningArgumentParser) -> None:
        # best by val/acc; and, separately, the latest every N steps plus last.ckpt for resuming (Lightning only
        # refreshes last.ckpt when its callback saved, which a best-only callback does not do every time)
        parser.add_lightning_class_args(MovableCheckpoint, "checkpoint")
        parser.set_defaults({"checkpoint.monitor": "val/acc", "checkpoint.mode": "max",
                             "checkpoint.filename": "best-step{step}", "checkpoint.auto_insert_metric_name": False})
        parser.add_lightning_class_args(LatestCheckpoint, "last_checkpoint")
        parser.set_defaults({"last_checkpoint.save_last": True, "last_checkpoint.every_n_train_steps": 100,
                             "last_checkpoint.filename": "latest-step{step}",
                             "last_checkpoint.auto_insert_metric_name": False})
        parser.add_lightning_class_args(FinalValidation, "final_validation")  # the last step is validated too
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


def check_config_files(argv: list[str]) -> None:
    """A --config file that is not valid YAML, named with the line at fault (jsonargparse's own message names
    neither the file nor the option)."""
    pairs = [tuple(a.split("=", 1)) for a in argv if a.startswith("--config=")] + list(zip(argv, argv[1:]))
    for flag, value in pairs:
        path = Path(value)
        if flag in ("--config", "-c") and path.is_file():
            try:
                yaml.safe_load(path.read_text())
            except yaml.YAMLError as exc:
                raise ValueError(f"--config {value}: not valid YAML ({one_line(exc, 200)})") from exc


def cli(args: list[str] | None = None, run: bool = True) -> HapticCLI:
    """The CLI over `args`, or the command line when None. Given args are a script's own (main_job.py,
    reproduce_table1.py), not its command line: Lightning's warning about both is beside the point there."""
    os.environ.setdefault("WANDB_MODE", "offline")  # no internet here: runs are synced later with `wandb sync`
    check_config_files(list(sys.argv[1:] if args is None else args))
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message="LightningCLI's args parameter")
        return HapticCLI(HapticGlance, ProbeDataModule, seed_everything_default=0, trainer_defaults=TRAINER_DEFAULTS,
                         parser_class=OneLineParser,
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
    except (ValueError, FileNotFoundError, FloatingPointError, MisconfigurationException) as exc:
        if os.environ.get("HG_TRACEBACK"):
            raise
        where = "lightning: " if isinstance(exc, MisconfigurationException) else ""  # Lightning's own checks
        print(f"hg: error: {where}{one_line(exc, 1000)}", file=sys.stderr)
        sys.exit(2)


if __name__ == "__main__":
    main()
