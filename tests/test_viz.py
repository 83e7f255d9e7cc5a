"""Pictures of what the robot does: renders show the arm, the object and the probes; figures are not blank; the
script runs end to end on a tiny checkpoint; ProbeMaps maps the very rollouts the test step scored."""
import io
import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import pytorch_lightning as pl
import torch
from PIL import Image

from hg.lightning import HapticGlance, ProbeDataModule
from hg.lightning.viz import (ProbeMaps, Rollouts, compare_models, confusion_counts, confusion_matrices,
                              probe_heatmaps, roll_out)
from hg.nets import PCRN, FCClassifier
from hg.policies import GaussianPolicy
from hg.sim import ProbeSimulator, Scene
from hg.sim.render import Camera, EpisodeTrace, episode_figure, render_episode, save_frames, save_gif, snapshot

ROOT = Path(__file__).resolve().parents[1]
SMALL = Camera(width=160, height=120)
FAR = (0.0, 0.0, -1000.0)


def image(data: bytes | Path) -> np.ndarray:
    raw = data.read_bytes() if isinstance(data, Path) else data
    return np.asarray(Image.open(io.BytesIO(raw)).convert("RGB"), dtype=np.float64)


def assert_not_blank(pixels: np.ndarray, floor: float = 50.0) -> None:
    assert pixels.var() > floor, f"image looks blank (pixel variance {pixels.var():.1f})"


def changed(a: np.ndarray, b: np.ndarray) -> float:
    """Fraction of pixels that differ between two frames."""
    return float((np.abs(a.astype(np.int16) - b.astype(np.int16)).sum(-1) > 30).mean())


@pytest.fixture(scope="module")
def arm_sim():
    with ProbeSimulator(batch_size=2, mode="arm", visuals=True) as sim:
        yield sim


@pytest.fixture(scope="module")
def box_trace(arm_sim):
    """Three probes at a box under the probe line (touches) and one far along the line (a miss)."""
    requests = np.array([[0.0, 0.0, 0.0, 1.0], [0.1, 0.3, -0.2, 0.5], [-0.15, -0.3, 0.2, 0.5], [0.95, 0.0, 0.0, 1.0]])
    pose = np.array([0.0, 0.0, -0.3, 0.0, 0.0, 20.0])
    label = arm_sim.classes.index("box")
    arm_sim.reset([label], pose[None])
    points = np.stack([arm_sim.probe(r[None]).points[0] for r in requests])
    assert points[:, 3].tolist() == [1.0, 1.0, 1.0, 0.0]
    return EpisodeTrace(label, pose, requests, points)


def test_frames_show_arm_object_and_probes(arm_sim, box_trace):
    bodies = arm_sim.client.getNumBodies()
    frames = render_episode(arm_sim, box_trace, SMALL)
    assert len(frames) == 4 and all(f.shape == (120, 160, 3) and f.dtype == np.uint8 for f in frames)
    assert arm_sim.client.getNumBodies() == bodies  # rays and markers are removed again
    assert_not_blank(frames[-1].astype(np.float64))
    buried_deep = EpisodeTrace(box_trace.label, box_trace.pose + [0, 0, -50, 0, 0, 0], box_trace.requests,
                               box_trace.points)
    assert changed(frames[-1], render_episode(arm_sim, buried_deep, SMALL)[-1]) > 0.005  # the object shows
    bare = snapshot(arm_sim, SMALL)  # same arm pose and object, no rays or markers
    assert changed(frames[-1], bare) > 0.003  # the probes show
    c, body = arm_sim.client, arm_sim.arm.body
    place = c.getBasePositionAndOrientation(body)
    c.resetBasePositionAndOrientation(body, FAR, (0, 0, 0, 1))
    try:
        armless = snapshot(arm_sim, SMALL)
    finally:
        c.resetBasePositionAndOrientation(body, *place)
    assert changed(bare, armless) > 0.01  # the arm shows
    assert changed(frames[0], frames[-1]) > 0.005  # and moves between probes


def test_frames_need_the_arm():
    with ProbeSimulator(batch_size=1, mode="ideal") as sim:
        trace = EpisodeTrace(0, np.array([0, 0, -0.3, 0, 0, 0.0]), np.zeros((2, 4)), np.zeros((2, 4)))
        with pytest.raises(ValueError, match="arm"):
            render_episode(sim, trace)


def test_frames_and_gif_files(tmp_path):
    rng = np.random.default_rng(0)
    frames = [rng.integers(0, 255, (30, 40, 3), dtype=np.uint8) for _ in range(5)]
    paths = save_frames(frames, tmp_path, "ball")
    assert [p.name for p in paths] == [f"ball_probe0{k}.png" for k in range(1, 6)]
    assert image(paths[0]).shape == (30, 40, 3)
    gif = Image.open(save_gif(frames, tmp_path / "ball.gif"))
    assert gif.n_frames == 5 and gif.size == (40, 30)


def test_points_over_mesh_figure(arm_sim, box_trace):
    pixels = image(episode_figure(box_trace, arm_sim.objects.meshes[box_trace.label], arm_sim.scene, "box"))
    assert pixels.shape[0] > 300 and pixels.shape[1] > 600
    assert_not_blank(pixels)


def fake_rollouts(n_episodes=40, n_probes=6, n_classes=4):
    rng = np.random.default_rng(1)
    labels = rng.integers(n_classes, size=n_episodes)
    predictions = np.where(rng.random((n_episodes, n_probes)) < 0.7, labels[:, None],
                           rng.integers(n_classes, size=(n_episodes, n_probes)))
    return Rollouts(labels, np.zeros((n_episodes, 6)), rng.uniform(-1, 1, (n_episodes, n_probes, 4)),
                    np.zeros((n_episodes, n_probes, 4)), predictions)


def test_test_set_figures():
    rollouts, names = fake_rollouts(), ("pipe", "box", "ball", "tire")
    for png in (probe_heatmaps(rollouts, names, Scene()), confusion_matrices(rollouts, names),
                compare_models({"pcrn": [0.4, 0.6, 0.8], "lstm": [0.3, 0.5, 0.6]})):
        pixels = image(png)
        assert pixels.shape[0] > 250 and pixels.shape[1] > 500
        assert_not_blank(pixels)
    counts = confusion_counts(np.array([0, 0, 1, 2]), np.array([0, 1, 1, 2]), 3)
    np.testing.assert_array_equal(counts, [[1, 1, 0], [0, 1, 0], [0, 0, 1]])


def test_probe_maps_callback_maps_the_scored_rollouts(tmp_path):
    data = ProbeDataModule(mode="ideal", batch_size=8, eval_batch_size=12, test_episodes=12, n_probes=3)
    torch.manual_seed(0)
    model = HapticGlance(PCRN(width=16, out_dim=32), lambda dims: GaussianPolicy(dims, hidden=32),
                         [lambda dims: FCClassifier(dims, hidden=32)], n_classes=data.n_classes, n_probes=3)
    maps = ProbeMaps(render_episodes=True, frame_width=160, frame_height=120)
    trainer = pl.Trainer(logger=False, callbacks=[maps], default_root_dir=tmp_path, accelerator="cpu",
                         enable_progress_bar=False, enable_model_summary=False)
    rollouts_made = []
    roll = model.roll
    model.roll = lambda *args, **kwargs: rollouts_made.append(kwargs.get("deterministic")) or roll(*args, **kwargs)
    trainer.test(model, datamodule=data, verbose=False)
    assert rollouts_made == [False, True]  # one batch: the stochastic and the mean-action rollout, none made again
    rollouts = Rollouts.concat(maps.parts)
    scored = [trainer.callback_metrics[f"test/acc@{k}"].item() for k in (1, 2, 3)]
    np.testing.assert_allclose(rollouts.accuracy(), scored, atol=1e-6)
    # a rollout the test step did not make (here the mean action's, with its outputs withheld) is made again from the
    # batch's seed: the very rollout the test step scored
    model.attach(data.make_simulator())
    batch = data.test_dataloader().dataset[0]
    again = roll_out(model, batch, deterministic=True)
    scored = [trainer.callback_metrics[f"test/acc_mean_action@{k}"].item() for k in (1, 2, 3)]
    np.testing.assert_allclose(again.accuracy(), scored, atol=1e-6)
    assert again.kind == "single mean-action rollout"
    model.sim.close()
    for name in ("probe_heatmaps.png", "confusion_matrices.png"):
        assert_not_blank(image(tmp_path / name))
    gifs = sorted((tmp_path / "episodes").glob("*.gif"))
    assert gifs and all(Image.open(g).n_frames == 3 for g in gifs)


def test_render_script_end_to_end(tmp_path):
    env = {**os.environ, "WANDB_MODE": "disabled"}
    fit = [sys.executable, "-m", "hg.lightning.cli", "fit", "--config", str(ROOT / "configs" / "pcrn_fc.yaml"),
           "--config", str(ROOT / "configs" / "parts" / "tiny.yaml"),
           "--trainer.logger", "false", "--trainer.default_root_dir", str(tmp_path),
           "--trainer.enable_progress_bar", "false"]
    subprocess.run(fit, cwd=tmp_path, env=env, check=True, capture_output=True)
    ckpt = tmp_path / "checkpoints" / "last.ckpt"
    out = tmp_path / "renders"
    run = subprocess.run([sys.executable, str(ROOT / "scripts" / "render_episode.py"), "--ckpt", str(ckpt),
                          "--out", str(out), "--mode", "arm", "--maps", "--size", "160", "120"],
                         cwd=tmp_path, env=env, check=True, capture_output=True, text=True)
    report = json.loads(run.stdout.strip().splitlines()[-1])
    files = [Path(f) for f in report["files"]]
    assert report["mode"] == "arm" and report["rollout"] == "single stochastic rollout"
    n_probes, classes = 4, [e["class"] for e in report["episodes"]]  # tiny.yaml: 4 probes
    assert len(classes) >= 2 and len(files) == len(classes) * (n_probes + 2) + 2
    assert all(f.is_file() for f in files)
    for name in classes:
        assert image(out / f"{name}_probe01.png").shape == (120, 160, 3)
        assert Image.open(out / f"{name}.gif").n_frames == n_probes
        assert_not_blank(image(out / f"{name}_points.png"))
    assert_not_blank(image(out / "probe_heatmaps.png"))
