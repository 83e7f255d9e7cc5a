"""The README's main job (`make run`): the quickstart, a short training on the default objects, then the held-out
test, printing the accuracy after each probe.

The quickstart is the composition QUICKSTART (the Gaussian policy started on the side-picking scan, cut to 2000
steps). Extra arguments go to the CLI, e.g. `--trainer.max_steps 300`; with `--config` files of its own the
quickstart's are not used (`--config configs/pcrn_fc.yaml` runs the paper protocol)."""
from __future__ import annotations

import sys
from pathlib import Path

from hg.lightning.cli import cli

ROOT = Path(__file__).resolve().parents[1]
QUICKSTART = ("configs/gaussian_on_side_scan.yaml", "configs/parts/stable_rl.yaml", "configs/parts/touch_sets.yaml",
              "configs/parts/quickstart.yaml")


def main(argv: list[str]) -> None:
    configs = [] if "--config" in argv else [a for c in QUICKSTART for a in ("--config", str(ROOT / c))]
    run = cli([*configs, *argv], run=False)
    run.trainer.fit(run.model, datamodule=run.datamodule)
    run.trainer.test(run.model, datamodule=run.datamodule, ckpt_path="best")  # prints the accuracy after each probe


if __name__ == "__main__":
    main(sys.argv[1:])
