"""Bad input of every kind ends before any side effect: one `hg: error:` line naming the field or file, exit code 2,
no traceback, no run directory, wandb run or checkpoint left behind. The cases also write docs/bad_inputs.md:
`HG_WRITE_DOCS=1 pytest tests/test_bad_input.py` after changing a message; the last test fails while it is stale."""
import os
import sys
from pathlib import Path

import pytest
import torch
import trimesh

from hg.lightning.cli import main

ROOT = Path(__file__).resolve().parents[1]
DOC = ROOT / "docs" / "bad_inputs.md"
TINY = ["--config", str(ROOT / "configs" / "pcrn_fc.yaml"), "--config", str(ROOT / "configs" / "parts" / "tiny.yaml")]
ARM = ["--data.mode", "arm"]


def meshes(*made: tuple[str, trimesh.Trimesh]) -> None:
    Path("objects").mkdir()
    for name, mesh in made:
        mesh.export(f"objects/{name}")


def open_box() -> trimesh.Trimesh:
    box = trimesh.creation.box((0.3, 0.2, 0.1))
    box.update_faces([True] * (len(box.faces) - 1) + [False])
    return box


def urdf_without_tip() -> None:
    Path("arm.urdf").write_text(
        (ROOT / "urdf" / "hg_probe_arm.urdf").read_text().replace('"probe_tip"', '"flange_tip"'))


def urdf_with_missing_mesh() -> None:
    Path("arm.urdf").write_text((ROOT / "urdf" / "hg_probe_arm.urdf").read_text().replace(
        '<cylinder radius="0.07" length="0.2"/>', '<mesh filename="meshes/shoulder.stl"/>'))


def truncated_checkpoint() -> None:
    torch.save({"state_dict": {"encoder.weight": torch.zeros(64, 64)}}, "whole.ckpt")
    data = Path("whole.ckpt").read_bytes()
    Path("half.ckpt").write_bytes(data[:len(data) // 2])


SPHERE = trimesh.creation.icosphere(radius=0.1)
# (case, what is wrong, subcommand and arguments, setup in the run's folder, fragment the message must contain)
CASES = [
    ("cli: Trainer option", "`--trainer.max_steps=-5`", ["fit", "--trainer.max_steps=-5"], None,
     "lightning: `max_steps`"),
    ("cli: unknown option", "`--model.foo 1`", ["fit", "--model.foo", "1"], None,
     "unrecognized arguments: --model.foo"),
    ("cli: wrong type", "`--data.n_probes ten`", ["fit", "--data.n_probes", "ten"], None, "data.n_probes"),
    ("cli: out of range", "`--data.n_probes 0`", ["fit", "--data.n_probes", "0"], None, "data.n_probes=0"),
    ("config: missing file", "`--config missing.yaml`", ["fit", "--config", "missing.yaml"], None, "missing.yaml"),
    ("config: not YAML", "a config with an unclosed list", ["fit", "--config", "bad.yaml"],
     lambda: Path("bad.yaml").write_text("model: [1, 2\n"), "--config bad.yaml: not valid YAML"),
    ("config: unknown class", "`--model.policy greedy`", ["fit", "--model.policy", "greedy"], None, "model.policy"),
    ("config: scene field", "`--data.scene.probe_length 0`", ["fit", "--data.scene.probe_length", "0"], None,
     "scene.probe_length=0"),
    ("config: objects above ground", "`--data.scene.object_z [-0.1,-0.05]`",
     ["fit", "--data.scene.object_z", "[-0.1, -0.05]"], None, "above ground"),
    ("checkpoint: missing", "`hg test --ckpt_path missing.ckpt`", ["test", "--ckpt_path", "missing.ckpt"], None,
     "ckpt_path=missing.ckpt: checkpoint file not found"),
    ("checkpoint: not a checkpoint", "a text file as `--ckpt_path`", ["test", "--ckpt_path", "notes.ckpt"],
     lambda: Path("notes.ckpt").write_text("hello\n"), "ckpt_path=notes.ckpt: not a checkpoint PyTorch can read"),
    ("checkpoint: half-written", "the first half of a checkpoint", ["test", "--ckpt_path", "half.ckpt"],
     truncated_checkpoint, "ckpt_path=half.ckpt: not a checkpoint PyTorch can read"),
    ("checkpoint: another model", "a checkpoint whose weights do not fit", ["test", "--ckpt_path", "whole.ckpt"],
     truncated_checkpoint, "ckpt_path=whole.ckpt: written for another model"),
    ("objects: unknown set", "`--data.objects hg5`", ["fit", "--data.objects", "hg5"], None, "objects='hg5'"),
    ("objects: empty folder", "a folder with no meshes", ["fit", "--data.objects", "objects"],
     lambda: Path("objects").mkdir(), "objects: no .obj or .stl mesh files"),
    ("mesh: empty", "an empty .obj file", ["fit", "--data.objects", "objects"],
     lambda: (meshes(("ball.stl", SPHERE)), Path("objects/empty.obj").write_text("")),
     "objects/empty.obj: mesh is empty"),
    ("mesh: unreadable", "random bytes as .stl", ["fit", "--data.objects", "objects"],
     lambda: (meshes(("ball.stl", SPHERE)), Path("objects/noise.stl").write_bytes(bytes(range(256)) * 2)),
     "objects/noise.stl: no mesh read from its 512 bytes"),
    ("mesh: not watertight", "a box with a face missing", ["fit", "--data.objects", "objects"],
     lambda: meshes(("ball.stl", SPHERE), ("open.stl", open_box())), "objects/open.stl: mesh is not watertight"),
    ("mesh: millimetres", "a box 300 x 200 x 100 (mm)", ["fit", "--data.objects", "objects"],
     lambda: meshes(("ball.stl", SPHERE), ("box.stl", trimesh.creation.box((300, 200, 100)))),
     "objects/box.stl: mesh is 300 units across"),
    ("urdf: missing", "`--data.robot missing.urdf`", ["fit", "--data.robot", "missing.urdf", *ARM], None,
     "data.robot=missing.urdf: URDF file not found"),
    ("urdf: not XML", "an unclosed tag", ["fit", "--data.robot", "arm.urdf", *ARM],
     lambda: Path("arm.urdf").write_text('<robot name="x"><link'), "robot URDF arm.urdf: malformed XML"),
    ("urdf: no probe tip", "a URDF without `probe_tip`", ["fit", "--data.robot", "arm.urdf", *ARM], urdf_without_tip,
     "robot URDF arm.urdf: no link named 'probe_tip'"),
    ("urdf: missing mesh", "a URDF naming a mesh file that is not there", ["fit", "--data.robot", "arm.urdf", *ARM],
     urdf_with_missing_mesh, "robot URDF arm.urdf: mesh file 'meshes/shoulder.stl' not found"),
]
MESSAGES: dict[str, str] = {}


@pytest.mark.parametrize("case, wrong, args, setup, fragment", CASES, ids=[c[0] for c in CASES])
def test_bad_input_fails_first_in_one_line(case, wrong, args, setup, fragment, tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    monkeypatch.delenv("HG_TRACEBACK", raising=False)
    monkeypatch.setenv("WANDB_MODE", "offline")  # a wandb run would leave its folder behind: there must be none
    if setup is not None:
        setup()
    before = set(tmp_path.rglob("*"))
    subcommand, *rest = args
    monkeypatch.setattr(sys, "argv", ["hg", subcommand, *TINY, *rest])
    with pytest.raises(SystemExit) as exit_:
        main()
    assert exit_.value.code == 2
    err = capsys.readouterr().err
    errors = [line for line in err.splitlines() if line.startswith("hg: error: ")]
    assert len(errors) == 1 and "Traceback" not in err, err[-3000:]
    assert not [line for line in err.splitlines() if "error" in line.lower() and line not in errors], err[-3000:]
    assert fragment in errors[0], errors[0]
    assert set(tmp_path.rglob("*")) == before  # no run directory, wandb run, checkpoint or config written
    MESSAGES[case] = errors[0].replace(str(ROOT), "<repo>").replace(str(tmp_path), ".")


def table() -> str:
    rows = [f"| {case} | {wrong} | `hg {args[0]} ... {' '.join(args[1:])}` | "
            f"{MESSAGES[case].replace('<', '&lt;').replace('|', '&#124;')} |" for case, wrong, args, _, _ in CASES]
    return "\n".join([
        "# Bad input and what `hg` says",
        "",
        "Written by `HG_WRITE_DOCS=1 pytest tests/test_bad_input.py` (each case runs `hg` with the tiny config,",
        "`configs/pcrn_fc.yaml configs/parts/tiny.yaml`, in an empty folder). Every case exits with code 2 after",
        "printing one line, before any run directory, wandb run or checkpoint exists; `HG_TRACEBACK=1` shows the",
        "traceback instead. The URDF cases add `--data.mode arm` (ideal mode loads no robot).",
        "",
        "| case | input | command | message |",
        "|---|---|---|---|",
        *rows,
        "",
    ])


def test_docs_table_lists_every_case_with_its_message():
    if len(MESSAGES) < len(CASES):
        pytest.skip("runs after every case above (the whole file)")
    if os.environ.get("HG_WRITE_DOCS"):
        DOC.write_text(table())
    assert DOC.read_text() == table(), "docs/bad_inputs.md is stale: HG_WRITE_DOCS=1 pytest tests/test_bad_input.py"
