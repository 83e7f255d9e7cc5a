"""Bad input from the CLI ends in one clear line naming the field or file, and a non-zero exit code."""
import os
import subprocess
import sys
from pathlib import Path

import pytest

TINY = str(Path(__file__).resolve().parents[1] / "configs" / "tiny.yaml")


@pytest.mark.parametrize("args, field", [
    (["--data.n_probes", "0"], "data.n_probes=0"),
    (["--data.scene.probe_length", "0"], "probe_length"),
    (["--data.scene.object_x", "[0.1, -0.1]"], "object_x"),
    (["--data.objects", "hg5"], "objects='hg5'"),
    (["--data.robot", "missing.urdf"], "missing.urdf"),
    (["--model.policy", "greedy"], "model.policy"),
    (["--ckpt_path", "missing.ckpt"], "missing.ckpt"),
])
def test_bad_input_gives_one_line(tmp_path, args, field):
    env = {**os.environ, "WANDB_MODE": "disabled"}
    env.pop("HG_TRACEBACK", None)
    proc = subprocess.run([sys.executable, "-m", "hg.lightning.cli", "fit", "--config", TINY, *args], cwd=tmp_path,
                          env=env, capture_output=True, text=True, timeout=300)
    assert proc.returncode != 0
    assert "Traceback" not in proc.stderr
    assert "args parameter" not in proc.stderr  # the command line is read once, so Lightning has nothing to warn of
    errors = [line for line in proc.stderr.splitlines() if "error" in line.lower() and field in line]
    assert errors, proc.stderr[-2000:]


CONFIGS = sorted((Path(__file__).resolve().parents[1] / "configs").glob("*.yaml"))


def test_every_shipped_config_builds(monkeypatch):
    """A typo in a Table 1 config must fail here, not half an hour into its run."""
    from hg.lightning.cli import cli

    monkeypatch.setenv("WANDB_MODE", "disabled")
    assert len(CONFIGS) >= 10
    for path in CONFIGS:
        built = cli(["--config", str(path), "--trainer.logger", "false"], run=False)
        assert built.model.hparams.n_probes == built.datamodule.n_probes, path.name
