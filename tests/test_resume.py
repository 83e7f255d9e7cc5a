"""A fit killed mid-run resumes from last.ckpt at the right step and ends where an uninterrupted run ends."""
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch

CONFIGS = Path(__file__).resolve().parents[1] / "configs"
STEPS, VALIDATE = 160, 40
ARGS = ["--config", str(CONFIGS / "pcrn_fc.yaml"), "--config", str(CONFIGS / "parts" / "tiny.yaml"),
        "--trainer.max_steps", str(STEPS), "--trainer.val_check_interval", str(VALIDATE),
        "--last_checkpoint.every_n_train_steps", "10", "--trainer.logger", "false",
        # the schedules' places (the learning rate's, the policy's std) must survive the kill too
        "--lr_decay.final_scale", "0.5", "--std_decay.final_scale", "0.5"]
ENV = {**os.environ, "WANDB_MODE": "disabled"}


def fit(cwd, *extra, background=False):
    command = [sys.executable, "-m", "hg.lightning.cli", "fit", *ARGS, "--trainer.default_root_dir", str(cwd), *extra]
    if background:
        log = open(Path(cwd) / "fit.log", "w")  # not a pipe: an unread pipe fills up and blocks the run
        return subprocess.Popen(command, cwd=cwd, env=ENV, stdout=log, stderr=subprocess.STDOUT)
    proc = subprocess.run(command, cwd=cwd, env=ENV, capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-3000:]


def last_checkpoint(folder):
    found = list(Path(folder).rglob("last.ckpt"))
    return found[0] if found else None


def final_state(folder):
    checkpoint = torch.load(last_checkpoint(folder), weights_only=False)
    return checkpoint["global_step"], checkpoint["state_dict"]


@pytest.fixture(scope="module")
def reference(tmp_path_factory):
    folder = tmp_path_factory.mktemp("uninterrupted")
    fit(folder)
    return (*final_state(folder), (folder / "val_curve.csv").read_text())


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGKILL])
def test_killed_fit_resumes_to_the_same_result(tmp_path, reference, sig):
    proc = fit(tmp_path, background=True)
    deadline = time.time() + 300
    while time.time() < deadline:  # wait for a checkpoint past the first validation, then kill mid-run
        ckpt = last_checkpoint(tmp_path)
        if ckpt is not None and torch.load(ckpt, weights_only=False)["global_step"] > VALIDATE:
            break
        time.sleep(0.05)
    proc.send_signal(sig)
    proc.wait(timeout=120)
    killed_at = torch.load(last_checkpoint(tmp_path), weights_only=False)["global_step"]
    assert VALIDATE < killed_at < STEPS, "the run must be killed mid-way"
    fit(tmp_path, "--ckpt_path", str(last_checkpoint(tmp_path)))
    step, state = final_state(tmp_path)
    assert step == reference[0] == STEPS
    for key, value in reference[1].items():
        torch.testing.assert_close(state[key], value, msg=f"{key} differs after resume")
    # the learning curve continues across the kill: the same rows, every validation once
    assert (tmp_path / "val_curve.csv").read_text() == reference[2]
    assert reference[2].count("\n") == 1 + STEPS // VALIDATE


def test_a_run_stopped_right_after_a_validation_resumes_knowing_its_score(tmp_path):
    """last.ckpt is written at the end of step 20, before the validation at step 20: it must be written again
    after it, or a resume forgets that score and may test a worse checkpoint as the best."""
    fit(tmp_path, "--trainer.max_steps", "20", "--trainer.val_check_interval", "10",
        "--last_checkpoint.every_n_train_steps", "10", "--data.regions", "cells")  # where step 20 scores best
    checkpoint = torch.load(last_checkpoint(tmp_path), weights_only=False)
    assert checkpoint["global_step"] == 20
    best = [state for key, state in checkpoint["callbacks"].items() if "'monitor': 'val/acc'" in key]
    assert len(best) == 1 and best[0]["best_model_score"] is not None
    assert best[0]["best_model_path"].endswith("best-step20.ckpt")
    # the resumable callback keeps a plain ModelCheckpoint's state key, as checkpoints from before it have
    latest = [key for key in checkpoint["callbacks"] if "'every_n_train_steps': 10" in key]
    assert len(latest) == 1 and latest[0].startswith("ModelCheckpoint{"), list(checkpoint["callbacks"])


def test_a_run_folder_moved_between_attempts_resumes_from_its_last_step_with_its_best_score(tmp_path):
    """Lightning drops the checkpoint callbacks' state when the folder saved in it is not the current one: the moved
    run wrote last-v1.ckpt beside the last.ckpt it resumed from (the next attempt went back to the older one) and
    chose its best among the later validations only."""
    here, there = tmp_path / "here", tmp_path / "there"
    here.mkdir()
    fit(here, "--trainer.max_steps", "20", "--trainer.val_check_interval", "10", "--data.regions", "cells")
    before = torch.load(last_checkpoint(here), weights_only=False)
    best_before = next(s for k, s in before["callbacks"].items() if "'monitor': 'val/acc'" in k)
    here.rename(there)
    fit(there, "--trainer.max_steps", "30", "--trainer.val_check_interval", "10", "--data.regions", "cells",
        "--ckpt_path", str(there / "checkpoints" / "last.ckpt"))
    assert sorted(p.name for p in (there / "checkpoints").glob("last*")) == ["last.ckpt"]
    after = torch.load(there / "checkpoints" / "last.ckpt", weights_only=False)
    assert after["global_step"] == 30
    best = next(s for k, s in after["callbacks"].items() if "'monitor': 'val/acc'" in k)
    assert best["dirpath"] == str(there / "checkpoints") and Path(best["best_model_path"]).parent == there / "checkpoints"
    assert best["best_model_score"] >= best_before["best_model_score"]  # the scores before the move still count
    assert len(list((there / "checkpoints").glob("best-step*.ckpt"))) == 1  # the older best removed when beaten
