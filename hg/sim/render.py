"""Pictures of one episode, without torch: TinyRenderer frames of the arm probing, the touched points over the mesh.

Frames come from the simulator's own world: slot 0 holds the arm and the only object bodies with visual shapes,
so an episode is replayed there. Rays and touch markers are visual-only bodies (no collision shape, so no probe
ever hits them; TinyRenderer does not draw debug lines in DIRECT mode). TinyRenderer ignores alpha, so the soil is
made see-through by compositing: a second render without the ground shows what lies under it, and a third with
only the markers shows the touches the object hides.
"""
from __future__ import annotations

import io
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Iterator, Sequence

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import trimesh  # noqa: E402
from matplotlib.collections import PolyCollection  # noqa: E402
from mpl_toolkits.mplot3d.art3d import Poly3DCollection  # noqa: E402
from PIL import Image, ImageDraw, ImageFont  # noqa: E402

from hg.sim.poses import rotation_matrices  # noqa: E402
from hg.sim.robot import tool_orientations  # noqa: E402
from hg.sim.scene import Scene  # noqa: E402
from hg.sim.simulator import ProbeSimulator  # noqa: E402

COLORMAP = "plasma"  # probe k's colour: dark (first probe) to bright (last), clear of the blue object
MISS_RGBA = (0.45, 0.45, 0.45, 1.0)
SOIL_ALPHA = 0.45  # how much of the soil's colour covers what lies beneath it
HIDDEN_ALPHA = 0.5  # how strongly a marker hidden behind the object or the arm shows through
FAR_AWAY = (0.0, 0.0, -1000.0)


@dataclass(frozen=True)
class EpisodeTrace:
    """One episode as the policy played it: a plain record that any rollout (torch or not) can fill in."""

    label: int
    pose: np.ndarray  # (6,) X, Y, Z, Rx, Ry, Rz (degrees) of the object
    requests: np.ndarray  # (N, 4) the executed requests, in [-1, 1]
    points: np.ndarray  # (N, 4) X, Y, Z (metres, episode frame, unscaled) and T; a miss gives the ray's end


@dataclass(frozen=True)
class Camera:
    """Where TinyRenderer looks from: by default from the -x side, slightly above the soil, so that the probe line
    runs across the picture, the arm stands behind it and the probes reach down to U_len below the soil."""

    width: int = 640
    height: int = 480
    target: tuple[float, float, float] = (0.2, 0.0, 0.25)
    distance: float = 2.7
    yaw: float = -65.0  # degrees about z; -90 looks along +x
    pitch: float = -15.0  # degrees; negative looks down
    fov: float = 40.0

    def matrices(self, client) -> tuple[list[float], list[float]]:
        view = client.computeViewMatrixFromYawPitchRoll(self.target, self.distance, self.yaw, self.pitch, 0.0, 2)
        projection = client.computeProjectionMatrixFOV(self.fov, self.width / self.height, 0.05, 20.0)
        return view, projection


def probe_colours(n: int) -> np.ndarray:
    """(n, 4) RGBA in [0, 1], one per probe index, shared by the frames and the figures."""
    return plt.get_cmap(COLORMAP)(np.linspace(0.0, 0.85, max(n, 1)))[:n]


def soil(sim: ProbeSimulator) -> list[int]:
    """The ground body, to hide it in the see-through render."""
    return [sim.ground]


class _Markers:
    """Visual-only bodies (rays, touches, misses) created for one render and removed afterwards."""

    def __init__(self, client) -> None:
        self.client, self.bodies = client, []

    def _add(self, visual: int, position, orientation=(0.0, 0.0, 0.0, 1.0)) -> None:
        self.bodies.append(self.client.createMultiBody(baseMass=0, baseCollisionShapeIndex=-1,
                                                       baseVisualShapeIndex=visual, basePosition=list(position),
                                                       baseOrientation=list(orientation)))

    def ray(self, start: np.ndarray, end: np.ndarray, rgba, radius: float = 0.005) -> None:
        length = float(np.linalg.norm(end - start))
        if length < 1e-6:
            return
        c = self.client
        visual = c.createVisualShape(c.GEOM_CYLINDER, radius=radius, length=length, rgbaColor=list(rgba))
        self._add(visual, (start + end) / 2, tool_orientations(((end - start) / length)[None])[0])

    def touch(self, position: np.ndarray, rgba, radius: float = 0.022) -> None:
        c = self.client
        self._add(c.createVisualShape(c.GEOM_SPHERE, radius=radius, rgbaColor=list(rgba)), position)

    def miss(self, position: np.ndarray, size: float = 0.05) -> None:
        """A grey 3D cross at the ray's end: three thin bars."""
        c = self.client
        for axis in np.eye(3):
            half = np.where(axis > 0, size / 2, size / 8)
            self._add(c.createVisualShape(c.GEOM_BOX, halfExtents=half.tolist(), rgbaColor=list(MISS_RGBA)), position)

    def probe_line(self, scene: Scene) -> None:
        """The line the probes enter on, in black, just above the soil."""
        lo, hi = scene.probe_y
        c = self.client
        visual = c.createVisualShape(c.GEOM_BOX, halfExtents=[0.006, (hi - lo) / 2, 0.003], rgbaColor=[0, 0, 0, 1])
        self._add(visual, (scene.probe_x, (lo + hi) / 2, 0.004))

    def remove(self) -> None:
        for body in self.bodies:
            self.client.removeBody(body)
        self.bodies = []


@contextmanager
def _moved_away(client, bodies: Sequence[int]) -> Iterator[None]:
    """Bodies out of the picture for a moment, then back where they were."""
    places = [client.getBasePositionAndOrientation(b) for b in bodies]
    for b in bodies:
        client.resetBasePositionAndOrientation(b, FAR_AWAY, (0, 0, 0, 1))
    try:
        yield
    finally:
        for b, (position, orientation) in zip(bodies, places):
            client.resetBasePositionAndOrientation(b, position, orientation)


def snapshot(sim: ProbeSimulator, camera: Camera = Camera(), markers: Sequence[int] = ()) -> np.ndarray:
    """One RGB frame (H, W, 3) uint8 of the world around slot 0: the soil see-through, and `markers` (body ids)
    shown faintly where the arm or the object hides them, so that no touch is lost behind the object."""
    c = sim.client
    view, projection = camera.matrices(c)

    def shot() -> tuple[np.ndarray, np.ndarray]:
        _, _, rgb, _, seg = c.getCameraImage(camera.width, camera.height, view, projection,
                                             renderer=c.ER_TINY_RENDERER)
        rgb = np.asarray(rgb, dtype=np.uint8).reshape(camera.height, camera.width, 4)[..., :3]
        return rgb.astype(np.float64), np.asarray(seg).reshape(camera.height, camera.width)

    ground = soil(sim)
    frame, seg = shot()
    with _moved_away(c, ground):
        beneath, beneath_seg = shot()
    frame = np.where(np.isin(seg, ground)[..., None], SOIL_ALPHA * frame + (1 - SOIL_ALPHA) * beneath, frame)
    if len(markers):
        solid = [b for b in (int(sim.active[0]), -1 if sim.arm is None else sim.arm.body) if b >= 0]
        with _moved_away(c, [*ground, *solid]):
            alone, alone_seg = shot()
        hidden = np.isin(alone_seg, markers) & ~np.isin(beneath_seg, markers)
        frame = np.where(hidden[..., None], HIDDEN_ALPHA * alone + (1 - HIDDEN_ALPHA) * frame, frame)
    return np.clip(np.rint(frame), 0, 255).astype(np.uint8)


def render_episode(sim: ProbeSimulator, trace: EpisodeTrace, camera: Camera = Camera()) -> list[np.ndarray]:
    """N frames: before frame k the arm is moved (IK) to the achieved pose of probe k; rays and touches of
    probes 1..k are drawn in their probe's colour, misses as grey crosses at the ray's end.

    Resets the simulator to this one episode (slot 0); it needs the arm, so a simulator in arm mode.
    """
    if sim.arm is None or not sim.visuals:
        raise ValueError("render_episode: frames need a simulator with the arm and the objects' looks "
                         "(mode='arm', visuals=True)")
    requests, points = np.asarray(trace.requests, dtype=np.float64), np.asarray(trace.points, dtype=np.float64)
    if requests.ndim != 2 or requests.shape[1] != 4 or points.shape != requests.shape:
        raise ValueError(f"trace: requests {requests.shape} and points {points.shape} must both be (N, 4)")
    sim.reset([trace.label], np.asarray(trace.pose, dtype=np.float64)[None])
    entry, direction = sim.scene.request_to_probe(requests)
    colours = probe_colours(len(requests))
    markers = _Markers(sim.client)
    frames = []
    try:
        markers.probe_line(sim.scene)
        for k in range(len(requests)):
            tip, axis, _ = sim.arm.reach(entry[k:k + 1], direction[k:k + 1])
            touched = points[k, 3] > 0.5
            end = points[k, :3] if touched else tip[0] + sim.scene.probe_length * axis[0]
            markers.ray(tip[0], end, colours[k])
            if touched:
                markers.touch(end, colours[k])
            else:
                markers.miss(end)
            frames.append(snapshot(sim, camera, markers.bodies))
    finally:
        markers.remove()
    return frames


def caption(frame: np.ndarray, text: str) -> np.ndarray:
    """The frame with `text` in a white band along its top edge."""
    image = Image.fromarray(frame)
    draw = ImageDraw.Draw(image)
    font = ImageFont.load_default(size=max(10, frame.shape[0] // 28))
    box = draw.textbbox((6, 4), text, font=font)
    draw.rectangle((0, 0, frame.shape[1], box[3] + 4), fill=(255, 255, 255))
    draw.text((6, 4), text, fill=(0, 0, 0), font=font)
    return np.asarray(image)


def _png(image: Image.Image, **kwargs) -> bytes:
    buffer = io.BytesIO()
    image.save(buffer, format=kwargs.pop("format", "PNG"), **kwargs)
    return buffer.getvalue()


def save_frames(frames: list[np.ndarray], folder: str | Path, stem: str) -> list[Path]:
    """`stem_probeKK.png` per frame (K from 01)."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    paths = []
    for k, frame in enumerate(frames, 1):
        path = folder / f"{stem}_probe{k:02d}.png"
        path.write_bytes(_png(Image.fromarray(frame)))
        paths.append(path)
    return paths


def save_gif(frames: list[np.ndarray], path: str | Path, frame_ms: int = 800) -> Path:
    """An animated GIF, one frame per probe, looping; the last frame is held three times as long."""
    if not frames:
        raise ValueError(f"{path}: no frames to write")
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    images = [Image.fromarray(f) for f in frames]
    durations = [frame_ms] * (len(images) - 1) + [3 * frame_ms]
    path.write_bytes(_png(images[0], format="GIF", save_all=True, append_images=images[1:], duration=durations,
                          loop=0))
    return path


def posed_mesh(mesh: trimesh.Trimesh, pose: np.ndarray) -> trimesh.Trimesh:
    """The centred mesh moved to pose (X, Y, Z, Rx, Ry, Rz in degrees), as the simulator places it."""
    transform = np.eye(4)
    transform[:3, :3] = rotation_matrices(np.asarray(pose, dtype=np.float64)[None, 3:])[0]
    transform[:3, 3] = pose[:3]
    return mesh.copy().apply_transform(transform)


def episode_figure(trace: EpisodeTrace, mesh: trimesh.Trimesh, scene: Scene, title: str = "") -> bytes:
    """PNG: the touched points over the object at its pose, in 3D and seen along x (the probe plane y-z).

    Rays run from the requested entry point to the reported point; touches are dots, misses crosses at the
    ray's end, both coloured by probe index.
    """
    requests, points = np.asarray(trace.requests, dtype=np.float64), np.asarray(trace.points, dtype=np.float64)
    n = len(requests)
    entry, _ = scene.request_to_probe(requests)
    colours = probe_colours(n)
    touched = points[:, 3] > 0.5
    body = posed_mesh(mesh, trace.pose)
    triangles = body.vertices[body.faces]
    fig = plt.figure(figsize=(10, 4.6), dpi=110)
    ax = fig.add_subplot(1, 2, 1, projection="3d")
    ax.add_collection3d(Poly3DCollection(triangles, facecolor=(0.2, 0.45, 0.8, 0.18),
                                         edgecolor=(0.2, 0.45, 0.8, 0.05), linewidth=0.2))
    side = fig.add_subplot(1, 2, 2)
    side.add_collection(PolyCollection(triangles[:, :, 1:], facecolor=(0.2, 0.45, 0.8, 0.04), edgecolor="none"))
    lo, hi = scene.probe_y
    ax.plot([scene.probe_x] * 2, [lo, hi], [0, 0], color="black", linewidth=2.5, label="probe line")
    side.plot([lo, hi], [0, 0], color="black", linewidth=2.5, label="probe line (ground)")
    for k in range(n):
        start, end = entry[k], points[k, :3]
        ax.plot(*np.stack([start, end]).T, color=colours[k], linewidth=1.0, alpha=0.8)
        side.plot([start[1], end[1]], [start[2], end[2]], color=colours[k], linewidth=1.0, alpha=0.8)
        marker = dict(marker="o", s=36, edgecolors="black", linewidths=0.5) if touched[k] else dict(marker="x", s=40)
        ax.scatter(*end, color=colours[k], **marker)
        side.scatter(end[1], end[2], color=colours[k], zorder=3, **marker)
        side.annotate(str(k + 1), (end[1], end[2]), textcoords="offset points", xytext=(4, 3), fontsize=7)
    everything = np.concatenate([body.vertices, entry, points[:, :3]])
    centre = (everything.max(0) + everything.min(0)) / 2
    half = (everything.max(0) - everything.min(0)).max() / 2 + 0.02
    ax.set(xlim=(centre[0] - half, centre[0] + half), ylim=(centre[1] - half, centre[1] + half),
           zlim=(centre[2] - half, centre[2] + half), xlabel="x (m)", ylabel="y (m)", zlabel="z (m)")
    ax.set_box_aspect((1, 1, 1))
    ax.view_init(elev=22, azim=-50)
    side.set(xlabel="y (m)", ylabel="z (m)", title="seen along x (probe plane)")
    side.set_aspect("equal")
    side.autoscale_view()
    side.grid(alpha=0.3)
    handles = [plt.Line2D([], [], marker="o", linestyle="", color="grey", markeredgecolor="black", label="touch"),
               plt.Line2D([], [], marker="x", linestyle="", color="grey", label="miss (ray end)")]
    side.legend(handles=handles, fontsize=8, loc="lower right")
    mappable = plt.cm.ScalarMappable(cmap=matplotlib.colors.ListedColormap(colours),
                                     norm=matplotlib.colors.Normalize(0.5, n + 0.5))
    bar = fig.colorbar(mappable, ax=side, ticks=range(1, n + 1), fraction=0.05, pad=0.02)
    bar.set_label("probe")
    fig.suptitle(title or f"{n} probes: {int(touched.sum())} touches")
    fig.tight_layout()
    data = io.BytesIO()
    fig.savefig(data, format="png")
    plt.close(fig)
    return data.getvalue()
