"""Lightning DDP on CPU (gloo): two ranks, each with its own simulator and episode seeds."""
import os
import subprocess
import sys
from pathlib import Path

import torch

from hg.lightning.data import TrainEpisodes
from hg.sim import PoseRegions, Scene

CONFIGS = Path(__file__).resolve().parents[1] / "configs"


def test_ranks_draw_different_training_episodes():
    regions = PoseRegions(Scene())
    rank0, rank1 = (next(iter(TrainEpisodes(regions, 4, 8, seed=0, rank=r, start=0))) for r in (0, 1))
    assert not torch.equal(rank0["poses"], rank1["poses"])
    again = next(iter(TrainEpisodes(regions, 4, 8, seed=0, rank=0, start=0)))
    torch.testing.assert_close(rank0["poses"], again["poses"])


def test_fit_under_ddp_with_two_cpu_processes(tmp_path):
    env = {**os.environ, "WANDB_MODE": "disabled"}
    proc = subprocess.run(
        [sys.executable, "-m", "hg.lightning.cli", "fit", "--config", str(CONFIGS / "pcrn_fc.yaml"), "--config",
         str(CONFIGS / "parts" / "tiny.yaml"), "--trainer.strategy", "ddp",
         "--trainer.devices", "2", "--trainer.accelerator", "cpu", "--trainer.logger", "false",
         "--trainer.default_root_dir", str(tmp_path), "--trainer.max_steps", "5"],
        cwd=tmp_path, env=env, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-3000:]
    checkpoint = torch.load(next(tmp_path.rglob("last.ckpt")), weights_only=False)
    assert checkpoint["global_step"] == 5  # max_steps, between two validations (every 2): the final step is saved
    curve = (tmp_path / "val_curve.csv").read_text().splitlines()
    assert [row.split(",")[0] for row in curve[1:]] == ["2", "4", "5"]  # and validated
    scores = [state.get("best_model_score") for state in checkpoint["callbacks"].values() if "best_model_score" in state]
    assert scores and scores[0] is not None  # val/acc was reduced across ranks and monitored
