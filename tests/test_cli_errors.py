"""Bad input from the CLI ends in one clear line naming the field or file, and a non-zero exit code."""
import os
import subprocess
import sys
from pathlib import Path

import pytest

from hg.lightning.cli import main

CONFIGS = Path(__file__).resolve().parents[1] / "configs"
TINY = ["--config", str(CONFIGS / "pcrn_fc.yaml"), "--config", str(CONFIGS / "parts" / "tiny.yaml")]


def one_error_line(stderr: str, field: str) -> None:
    assert "Traceback" not in stderr
    errors = [line for line in stderr.splitlines() if "error" in line.lower() and field in line]
    assert errors, stderr[-2000:]


@pytest.mark.parametrize("args, field", [
    (["--data.n_probes", "0"], "data.n_probes=0"),
    (["--data.scene.probe_length", "0"], "probe_length"),
    (["--data.scene.object_x", "[0.1, -0.1]"], "object_x"),
    (["--data.objects", "hg5"], "objects='hg5'"),
    (["--model.policy", "greedy"], "model.policy"),
    (["--model.policy.init_args.anchor", "1.0"], "anchor=1.0"),
    (["--model.warmup", "hg.rl.FollowPrior", "--model.warmup.init_args.steps", "2"], "model.warmup"),
    (["--ckpt_path", "missing.ckpt"], "missing.ckpt"),
])
def test_bad_input_gives_one_line(tmp_path, monkeypatch, capsys, args, field):
    monkeypatch.chdir(tmp_path)
    monkeypatch.delenv("HG_TRACEBACK", raising=False)
    monkeypatch.setattr(sys, "argv", ["hg", "fit", *TINY, "--trainer.logger", "false", *args])
    with pytest.raises(SystemExit) as exit_:
        main()
    assert exit_.value.code not in (0, None)
    one_error_line(capsys.readouterr().err, field)


def test_bad_input_in_a_fresh_process_gives_one_line(tmp_path):
    env = {**os.environ, "WANDB_MODE": "disabled"}
    env.pop("HG_TRACEBACK", None)
    proc = subprocess.run([sys.executable, "-m", "hg.lightning.cli", "fit", *TINY, "--data.robot", "missing.urdf"],
                          cwd=tmp_path, env=env, capture_output=True, text=True, timeout=300)
    assert proc.returncode != 0
    assert "args parameter" not in proc.stderr  # the command line is read once, so Lightning has nothing to warn of
    one_error_line(proc.stderr, "missing.urdf")
