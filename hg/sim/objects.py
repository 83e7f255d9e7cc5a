"""Object sets: the default `hg4` (pipe, box, ball, tire) built with trimesh, or a folder of .obj/.stl files."""
from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import trimesh

MESH_SUFFIXES = (".obj", ".stl")
MAX_EXTENT_M = 5.0  # a mesh larger than this is in other units (millimetres, most often), not a buried object


@dataclass(frozen=True)
class ObjectSet:
    """Named, recentred meshes; the class index of an object is its position in `names`."""

    name: str
    names: tuple[str, ...]
    meshes: tuple[trimesh.Trimesh, ...]

    def __len__(self) -> int:
        return len(self.names)


def _recentred(mesh: trimesh.Trimesh, source: str) -> trimesh.Trimesh:
    """Centre the bounding box on the origin, so a pose's (X, Y, Z) is the object's centre."""
    if mesh.is_empty or len(mesh.faces) == 0:
        raise ValueError(f"{source}: mesh is empty (no faces)")
    if not np.isfinite(mesh.vertices).all():
        raise ValueError(f"{source}: mesh has non-finite vertex coordinates")
    if not mesh.is_watertight:
        open_edges = len(trimesh.grouping.group_rows(mesh.edges_sorted, require_count=1))
        raise ValueError(f"{source}: mesh is not watertight ({open_edges} open edges), so probes would pass through "
                         f"its holes; close it first (trimesh.repair.fill_holes, or a boolean union with manifold3d)")
    extent = float(mesh.extents.max())
    if extent > MAX_EXTENT_M:
        raise ValueError(f"{source}: mesh is {extent:g} units across, read as metres; objects here are tenths of a "
                         f"metre: if it is in millimetres, scale it by 0.001 (mesh.apply_scale(0.001)) first")
    mesh = mesh.copy()
    mesh.apply_translation(-mesh.bounds.mean(axis=0))
    return mesh


def hg4() -> ObjectSet:
    """The four objects of the paper's data set, with the sizes of the project's issue #2."""
    pipe = trimesh.creation.cylinder(radius=0.06, height=0.50, sections=48)
    pipe.apply_transform(trimesh.transformations.rotation_matrix(math.pi / 2, [0, 1, 0]))  # axis horizontal (x)
    meshes = {
        "pipe": pipe,
        "box": trimesh.creation.box(extents=(0.30, 0.20, 0.15)),
        "ball": trimesh.creation.icosphere(subdivisions=3, radius=0.12),
        "tire": trimesh.creation.torus(major_radius=0.15, minor_radius=0.05, major_sections=48, minor_sections=24),
    }
    return ObjectSet("hg4", tuple(meshes), tuple(_recentred(m, f"hg4/{n}") for n, m in meshes.items()))


def load_folder(folder: str | Path) -> ObjectSet:
    """One class per mesh file (class name = file stem), sorted by name for a stable class order."""
    folder = Path(folder)
    if not folder.is_dir():
        raise ValueError(f"objects={str(folder)!r}: not 'hg4' and not a folder of .obj/.stl meshes")
    files = sorted(p for p in folder.iterdir() if p.suffix.lower() in MESH_SUFFIXES)
    if not files:
        raise ValueError(f"{folder}: no .obj or .stl mesh files in this folder")
    names, meshes = [], []
    for path in files:
        try:
            mesh = trimesh.load(path, force="mesh")
        except Exception as exc:  # trimesh raises many types for unreadable files
            raise ValueError(f"{path}: cannot read mesh ({exc})") from exc
        if mesh.is_empty and path.stat().st_size > 0:
            raise ValueError(f"{path}: no mesh read from its {path.stat().st_size} bytes; is it really an "
                             f"{path.suffix.lower()[1:].upper()} file?")
        names.append(path.stem)
        meshes.append(_recentred(mesh, str(path)))
    return ObjectSet(folder.name, tuple(names), tuple(meshes))


def load_object_set(spec: str | Path) -> ObjectSet:
    """`hg4` or a path to a folder of meshes."""
    return hg4() if str(spec) == "hg4" else load_folder(spec)
