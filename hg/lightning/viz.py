"""What the policy does: episode renders, test-set maps of where it probes, confusion matrices, model comparison.

Rollouts are re-run here from each batch's seed: a batch's rollout depends on that batch alone (data.py), so
this reproduces exactly the single rollout the test step scored, without any hook in the module.
"""
from __future__ import annotations

import csv
import io
from dataclasses import dataclass
from pathlib import Path
from typing import Iterable, Sequence

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import pytorch_lightning as pl  # noqa: E402
import torch  # noqa: E402
from pytorch_lightning.loggers import WandbLogger  # noqa: E402
from pytorch_lightning.utilities import rank_zero_only  # noqa: E402

from hg.atomic import write_atomic  # noqa: E402
from hg.lightning.callbacks import accuracy_plot, run_dir  # noqa: E402
from hg.sim import ProbeSimulator, Scene  # noqa: E402
from hg.sim.render import (Camera, EpisodeTrace, caption, episode_figure, render_episode, save_frames,  # noqa: E402
                           save_gif)


def rollout_kind(deterministic: bool) -> str:
    return "single mean-action rollout" if deterministic else "single stochastic rollout"


@dataclass(frozen=True)
class Rollouts:
    """Single rollouts of E episodes as numpy arrays, N probes each; `kind` says which policy played them."""

    labels: np.ndarray  # (E,)
    poses: np.ndarray  # (E, 6)
    requests: np.ndarray  # (E, N, 4) executed requests in [-1, 1]
    points: np.ndarray  # (E, N, 4) X, Y, Z in metres (episode frame, point_scale undone) and T
    predictions: np.ndarray  # (E, N) class predicted after each probe
    kind: str = rollout_kind(False)

    def __len__(self) -> int:
        return len(self.labels)

    def trace(self, i: int) -> EpisodeTrace:
        return EpisodeTrace(int(self.labels[i]), self.poses[i], self.requests[i], self.points[i])

    def accuracy(self) -> np.ndarray:
        """(N,) accuracy after each probe."""
        return (self.predictions == self.labels[:, None]).mean(0)

    @staticmethod
    def concat(parts: Sequence["Rollouts"]) -> "Rollouts":
        if not parts:
            raise ValueError("Rollouts.concat: no rollouts to join")
        fields = ("labels", "poses", "requests", "points", "predictions")
        return Rollouts(*(np.concatenate([getattr(p, f) for p in parts]) for f in fields), kind=parts[0].kind)


@torch.no_grad()
def roll_out(module: pl.LightningModule, batch: dict[str, torch.Tensor], deterministic: bool = False,
             done: tuple | None = None) -> Rollouts:
    """The rollout the eval step makes of this batch (same seed, same policy), and the prediction after each probe;
    `done` = (rollout, logits) of that eval step, when it has already been made."""
    labels = batch["labels"].to(module.device)
    if done is None:
        rollout = module.roll(labels, batch["poses"], int(batch["seed"]), deterministic=deterministic)
        logits, _ = module.predict(rollout)
    else:
        rollout, logits = done
    points = rollout.points.detach().cpu().double().numpy().copy()
    points[..., :3] /= module.hparams.point_scale
    return Rollouts(labels.cpu().numpy(), batch["poses"].cpu().double().numpy(),
                    rollout.requests.cpu().double().numpy(), points, logits.argmax(-1).cpu().numpy(),
                    rollout_kind(deterministic))


def one_per_class(rollouts: Rollouts, n_classes: int) -> list[int]:
    """Index of the first episode of each class, in class order; classes absent from the rollouts are skipped."""
    return [int(np.flatnonzero(rollouts.labels == c)[0]) for c in range(n_classes) if (rollouts.labels == c).any()]


def arm_simulator(datamodule: pl.LightningDataModule) -> ProbeSimulator:
    """A one-slot arm-mode simulator of the datamodule's world: frames need the arm even for ideal-mode rollouts."""
    h = datamodule.hparams
    return ProbeSimulator(datamodule.object_set, 1, datamodule.scene, "arm", h.robot, seed=h.seed, visuals=True)


def _figure_png(fig: plt.Figure) -> bytes:
    buffer = io.BytesIO()
    fig.savefig(buffer, format="png")
    plt.close(fig)
    return buffer.getvalue()


def probe_heatmaps(rollouts: Rollouts, class_names: Sequence[str], scene: Scene,
                   bins: tuple[int, int] = (16, 9)) -> bytes:
    """PNG: where the policy probes, as entry y on the probe line vs tilt from vertical, one row per class and
    one column per probe index (and all probes); each panel is the fraction of that class's episodes per cell."""
    n_episodes, n_probes = rollouts.requests.shape[:2]
    entry, direction = scene.request_to_probe(rollouts.requests.reshape(-1, 4))
    y = entry[:, 1].reshape(n_episodes, n_probes)
    tilt = np.degrees(np.arccos(np.clip(-direction[:, 2], -1.0, 1.0))).reshape(n_episodes, n_probes)
    edges = (np.linspace(*scene.probe_y, bins[0] + 1), np.linspace(0.0, scene.max_tilt_deg, bins[1] + 1))
    columns = [*(f"probe {k + 1}" for k in range(n_probes)), "all probes"]
    maps = np.zeros((len(class_names), len(columns), bins[0], bins[1]))
    for c in range(len(class_names)):
        mine = rollouts.labels == c
        for k in range(len(columns)):
            probes = slice(k, k + 1) if k < n_probes else slice(None)
            counts, *_ = np.histogram2d(y[mine, probes].ravel(), tilt[mine, probes].ravel(), bins=edges)
            maps[c, k] = counts / max(counts.sum(), 1)
    fig, axes = plt.subplots(len(class_names), len(columns), squeeze=False, sharex=True, sharey=True,
                             figsize=(1.25 * len(columns) + 1.2, 1.15 * len(class_names) + 1.0), dpi=100)
    vmax = max(maps.max(), 1e-9)
    extent = (*scene.probe_y, 0.0, scene.max_tilt_deg)
    for c, row in enumerate(axes):
        for k, ax in enumerate(row):
            image = ax.imshow(maps[c, k].T, origin="lower", extent=extent, aspect="auto", cmap="magma", vmin=0,
                              vmax=vmax)
            if c == 0:
                ax.set_title(columns[k], fontsize=8)
            if k == 0:
                ax.set_ylabel(f"{class_names[c]}\ntilt (deg)", fontsize=8)
            if c == len(class_names) - 1:
                ax.set_xlabel("entry y (m)", fontsize=8)
            ax.tick_params(labelsize=6)
    fig.colorbar(image, ax=axes, fraction=0.02, pad=0.01).set_label("fraction of episodes", fontsize=8)
    fig.suptitle(f"Where the policy probes (held-out episodes, {rollouts.kind})", fontsize=10)
    return _figure_png(fig)


def confusion_counts(labels: np.ndarray, predictions: np.ndarray, n_classes: int) -> np.ndarray:
    """(C, C) episode counts, rows true class, columns predicted class."""
    counts = np.zeros((n_classes, n_classes), dtype=np.int64)
    np.add.at(counts, (labels, predictions), 1)
    return counts


def confusion_matrices(rollouts: Rollouts, class_names: Sequence[str], after: Iterable[int] = (1, 5, -1)) -> bytes:
    """PNG: row-normalised confusion matrices of the prediction after the given probe counts (-1: the last)."""
    n_probes, n_classes = rollouts.predictions.shape[1], len(class_names)
    probes = sorted({n_probes if k == -1 else k for k in after if k == -1 or 1 <= k <= n_probes})
    fig, axes = plt.subplots(1, len(probes), squeeze=False, figsize=(3.3 * len(probes) + 0.8, 3.4), dpi=110)
    for ax, k in zip(axes[0], probes):
        counts = confusion_counts(rollouts.labels, rollouts.predictions[:, k - 1], n_classes)
        rates = counts / np.maximum(counts.sum(1, keepdims=True), 1)
        ax.imshow(rates, cmap="Blues", vmin=0, vmax=1)
        for (i, j), n in np.ndenumerate(counts):
            ax.text(j, i, f"{rates[i, j]:.2f}\n({n})", ha="center", va="center", fontsize=7,
                    color="white" if rates[i, j] > 0.6 else "black")
        accuracy = np.trace(counts) / max(counts.sum(), 1)
        ax.set_title(f"after {k} probe{'s' if k > 1 else ''}: accuracy {accuracy:.2f}", fontsize=9)
        ax.set_xticks(range(n_classes), class_names, rotation=45, fontsize=8)
        ax.set_yticks(range(n_classes), class_names, fontsize=8)
        ax.set_xlabel("predicted", fontsize=8)
        ax.set_ylabel("true", fontsize=8)
    fig.suptitle(f"Confusion on held-out episodes ({rollouts.kind}; rows sum to 1, counts in brackets)",
                 fontsize=9)
    fig.tight_layout()
    return _figure_png(fig)


def compare_models(accuracies: dict[str, Sequence[float]],
                   reference: dict[str, dict[int, float]] | None = None) -> bytes:
    """PNG: accuracy after each probe of every model in one figure, best final accuracy first in the legend."""
    if not accuracies:
        raise ValueError("compare_models: no models given")
    ranked = dict(sorted(accuracies.items(), key=lambda item: -item[1][-1]))
    return accuracy_plot({name: [float(v) for v in values] for name, values in ranked.items()},
                         title="Accuracy after each probe, every model (held-out test poses)", reference=reference)


def read_per_probe_csv(path: str | Path, column: str = "stochastic") -> list[float]:
    """One column of a run's per_probe_accuracy.csv (written by PerProbeAccuracy), for `compare_models`."""
    with open(path, newline="") as f:
        rows = list(csv.DictReader(f))
    if not rows or column not in rows[0]:
        raise ValueError(f"{path}: no column '{column}' (columns: {', '.join(rows[0]) if rows else 'none'})")
    return [float(row[column]) for row in rows]


def write_test_maps(rollouts: Rollouts, class_names: Sequence[str], scene: Scene, folder: str | Path) -> list[Path]:
    """probe_heatmaps.png and confusion_matrices.png in `folder`."""
    folder = Path(folder)
    files = {folder / "probe_heatmaps.png": probe_heatmaps(rollouts, class_names, scene),
             folder / "confusion_matrices.png": confusion_matrices(rollouts, class_names)}
    for path, data in files.items():
        write_atomic(path, data)
    return list(files)


def render_episodes(rollouts: Rollouts, indices: Sequence[int], sim: ProbeSimulator, class_names: Sequence[str],
                    folder: str | Path, camera: Camera = Camera()) -> list[Path]:
    """Per episode, named by its class: one captioned PNG per probe, a GIF of them and the points-over-mesh figure.

    `sim` must be in arm mode; it is reset to each episode in turn.
    """
    folder = Path(folder)
    written = []
    for i in indices:
        trace, truth = rollouts.trace(i), class_names[int(rollouts.labels[i])]
        predictions = [class_names[int(p)] for p in rollouts.predictions[i]]
        n = len(predictions)
        frames = [caption(frame, f"{truth} | probe {k + 1}/{n}: {'touch' if trace.points[k, 3] > 0.5 else 'miss'}"
                                 f" | predicts {predictions[k]}")
                  for k, frame in enumerate(render_episode(sim, trace, camera))]
        written += save_frames(frames, folder, truth)
        written.append(save_gif(frames, folder / f"{truth}.gif"))
        title = (f"{truth}, test episode {i}: predicted {predictions[-1]} after {n} probes "
                 f"(touches: {int((trace.points[:, 3] > 0.5).sum())}; {rollouts.kind})")
        figure = folder / f"{truth}_points.png"
        write_atomic(figure, episode_figure(trace, sim.objects.meshes[trace.label], sim.scene, title))
        written.append(figure)
    return written


class ProbeMaps(pl.Callback):
    """At test end: probe_heatmaps.png and confusion_matrices.png in the run directory (and as wandb images), and
    optionally episode renders (one test episode per class) in its `episodes/` folder.

    It maps the rollouts the test step scored (its outputs), or rolls a batch out again from its seed, which
    reproduces them, when the test step made none of this kind. Only this process's share of the test
    set is mapped (the whole set on one device).
    """

    def __init__(self, mean_action: bool = False, render_episodes: bool = False, frame_width: int = 480,
                 frame_height: int = 360) -> None:
        self.mean_action, self.render = mean_action, render_episodes
        self.camera = Camera(width=frame_width, height=frame_height)
        self.parts: list[Rollouts] = []

    def on_test_epoch_start(self, trainer: pl.Trainer, pl_module: pl.LightningModule) -> None:
        self.parts = []

    def on_test_batch_end(self, trainer: pl.Trainer, pl_module: pl.LightningModule, outputs, batch: dict,
                          batch_idx: int, dataloader_idx: int = 0) -> None:
        done = outputs.get(self.mean_action) if isinstance(outputs, dict) else None
        self.parts.append(roll_out(pl_module, batch, deterministic=self.mean_action, done=done))

    @rank_zero_only
    def on_test_end(self, trainer: pl.Trainer, pl_module: pl.LightningModule) -> None:
        if not self.parts:
            return
        rollouts, datamodule = Rollouts.concat(self.parts), trainer.datamodule
        folder = run_dir(trainer)
        maps = write_test_maps(rollouts, datamodule.class_names, datamodule.scene, folder)
        if isinstance(trainer.logger, WandbLogger):
            for path in maps:
                trainer.logger.log_image(f"test/{path.stem}", images=[str(path)])
        print(f"written: {', '.join(map(str, maps))}")
        if self.render:
            own = pl_module.sim is None or pl_module.sim.arm is None
            sim = arm_simulator(datamodule) if own else pl_module.sim
            try:
                episodes = render_episodes(rollouts, one_per_class(rollouts, datamodule.n_classes), sim,
                                           datamodule.class_names, folder / "episodes", self.camera)
            finally:
                if own:
                    sim.close()
            print(f"written: {len(episodes)} episode renders in {folder / 'episodes'}")
