"""A fit killed mid-run resumes from last.ckpt at the right step and ends where an uninterrupted run ends."""
import os
import shutil
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


def best_state(checkpoint: Path) -> dict:
    state = torch.load(checkpoint, weights_only=False)
    return next(s for k, s in state["callbacks"].items() if "'monitor': 'val/acc'" in k) | {"step": state["global_step"]}


@pytest.mark.parametrize("moved", [True, False])
def test_a_run_resumed_in_another_folder_keeps_its_last_step_and_its_best_score(tmp_path, moved):
    """Lightning drops the checkpoint callbacks' record when the run's folder is not the one saved: a run moved to
    another clone wrote last-v1.ckpt beside the last.ckpt it resumed from (the next attempt went back to the older
    one), and a run resumed into a new folder (a new logger's) chose its best among the later validations only."""
    first, second = tmp_path / "first", tmp_path / "second"
    first.mkdir()
    fit(first, "--trainer.max_steps", "20", "--trainer.val_check_interval", "10", "--data.regions", "cells")
    before = best_state(first / "checkpoints" / "last.ckpt")
    kept = sorted(p.name for p in (first / "checkpoints").iterdir())
    if moved:
        first.rename(second)
    else:
        second.mkdir()
    source = (second if moved else first) / "checkpoints" / "last.ckpt"
    # no validation after the resume: the record the second attempt writes is the one it restored
    fit(second, "--trainer.max_steps", "30", "--trainer.limit_val_batches", "0", "--data.regions", "cells",
        "--ckpt_path", str(source))
    assert sorted(p.name for p in (second / "checkpoints").glob("last*")) == ["last.ckpt"]
    after = best_state(second / "checkpoints" / "last.ckpt")
    assert after["step"] == 30 and after["best_model_score"] == before["best_model_score"] is not None
    best = Path(after["best_model_path"])
    assert best.is_file() and best == source.parent / Path(before["best_model_path"]).name
    if not moved:  # nothing of the first folder is removed
        assert sorted(p.name for p in (first / "checkpoints").iterdir()) == kept


def test_a_checkpoint_copied_without_its_best_resumes_as_lightning_would(tmp_path):
    """A last.ckpt alone in a new folder: its record names a best that is not beside it, so Lightning's own handling
    stands (the best is chosen among the new validations) rather than a best that cannot be tested."""
    first, second = tmp_path / "first", tmp_path / "second"
    first.mkdir(), second.mkdir()
    fit(first, "--trainer.max_steps", "20", "--trainer.val_check_interval", "10", "--data.regions", "cells")
    (second / "copied").mkdir()
    copied = second / "copied" / "last.ckpt"
    copied.write_bytes((first / "checkpoints" / "last.ckpt").read_bytes())
    shutil.rmtree(first)
    fit(second, "--trainer.max_steps", "30", "--trainer.val_check_interval", "10", "--data.regions", "cells",
        "--ckpt_path", str(copied))
    after = best_state(second / "checkpoints" / "last.ckpt")
    assert after["step"] == 30 and Path(after["best_model_path"]).is_file()
