"""The README's main job: a short training on the default objects, then the held-out test, printing the
accuracy after each probe. Extra arguments go to the CLI, e.g. `--trainer.max_steps 300`; with a `--config`
of its own the quickstart config is not used (`--config configs/pcrn_fc.yaml` runs the paper protocol)."""
from __future__ import annotations

import sys
from pathlib import Path

from hg.lightning.cli import cli

CONFIG = Path(__file__).resolve().parents[1] / "configs" / "quickstart.yaml"


def main(argv: list[str]) -> None:
    run = cli(argv if "--config" in argv else ["--config", str(CONFIG), *argv], run=False)
    run.trainer.fit(run.model, datamodule=run.datamodule)
    run.trainer.test(run.model, datamodule=run.datamodule, ckpt_path="best")


if __name__ == "__main__":
    main(sys.argv[1:])
