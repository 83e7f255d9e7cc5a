"""Build an object set from meshes that ship with pybullet_data, by a written rule, with a README of how.

The sources: pybullet_data's single household objects (HOUSEHOLD: bunny, duck, teddy, mug, soccer ball, cube; the
V-HACD collision mesh where the object's URDF uses one), leaving out the boxes under other names (lego's and jenga's
collision shapes, domino, stone) and the second sphere (sphere_smooth); then its random_urdfs blobs in numeric order.
The rule, for every source mesh:
1. Solid: if every connected piece of the file is closed (the V-HACD collision meshes, the blobs), their boolean
   union (manifold3d); else the same once faces saved apart are joined at shared vertices (cube, soccer ball); else
   the convex hull.
2. Upright: the file's up axis turned to +Z (Y for the duck and teddy files, Z for the others).
3. Scaled uniformly so the bounding-box diagonal is --diagonal metres, or less where needed so the object's top stays
   --clearance metres below the ground Z=0 at its highest allowed pose (the scene's highest centre and any tilt);
   bounding box centred on the origin (hg.sim.objects does the same on loading).
4. Kept unless it is a near-duplicate of an object kept before it: a symmetric Chamfer distance under --duplicate
   times the diagonal after the best turn about the vertical (every --turn-step degrees) or mirror image.
5. Blobs are taken in numeric order, only if chiral with no turn symmetry (hg.sim.symmetry), until --blobs are kept.
6. Written as OBJ (vertices and faces), simplified (manifold3d) within the smallest tolerance of SIMPLIFY_M that brings
   the file under 200 KB, if it is not already, and that reads back closed.
Then every kept object's symmetries are printed and written to the README with its source and scale factor, and the
set is checked against the scene (hg.sim.poses.check_below_ground) by loading it as training will.

    .venv/bin/python scripts/make_object_set.py --out data/objects/pyb10
"""
from __future__ import annotations

import argparse
import math
from dataclasses import dataclass
from importlib.metadata import version
from pathlib import Path

import manifold3d
import numpy as np
import pybullet_data
import trimesh
from scipy.spatial import cKDTree

from hg.sim import Scene, load_object_set
from hg.sim.poses import check_below_ground, rotation_matrices
from hg.sim.symmetry import TOLERANCE, find_symmetry, mirror_matrix, object_symmetries, turn_matrix

ROOT = Path(__file__).resolve().parents[1]

DATA = Path(pybullet_data.getDataPath())
HOUSEHOLD = (  # class, file under pybullet_data, the file's up axis
    ("bunny", "bunny.obj", "z"),
    ("duck", "duck_vhacd.obj", "y"),
    ("teddy", "teddy2_VHACD_CHs.obj", "y"),
    ("mug", "objects/mug_col.obj", "z"),
    ("soccer_ball", "soccerball.obj", "z"),
    ("cube", "cube.obj", "z"),
)
UP = {"z": np.eye(3), "y": np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])}  # file's +Y -> +Z
MAX_FILE_BYTES = 200_000
SIMPLIFY_M = (1e-4, 2e-4, 5e-4, 1e-3, 2e-3)  # simplification tolerances tried, smallest first (m)


@dataclass
class Built:
    """One kept object: its class name, where it came from and what the rule did to it."""

    name: str
    source: str
    solid: str
    up: str
    scale: float
    mesh: trimesh.Trimesh


def solid(mesh: trimesh.Trimesh) -> tuple[trimesh.Trimesh, str]:
    """One closed mesh (rule 1): the union of the file's pieces if all are closed, else of the pieces its faces make
    once vertices at the same place are merged whatever their normals and texture coordinates (faces saved apart,
    as in the cube and soccer ball files), else the convex hull."""
    for merged in (False, True):
        candidate = mesh.copy()
        if merged:
            candidate.merge_vertices(merge_tex=True, merge_norm=True)
        pieces = candidate.split(only_watertight=False)
        if all(piece.is_volume for piece in pieces):
            joined = pieces[0] if len(pieces) == 1 else trimesh.boolean.union(pieces, engine="manifold")
            how = f"union of {len(pieces)} closed pieces" if len(pieces) > 1 else "closed as it is"
            return joined, how + (" once its faces are joined" if merged else "")
    return mesh.convex_hull, f"convex hull ({len(pieces)} open pieces)"


def top_per_metre(mesh: trimesh.Trimesh, scene: Scene, grid: int = 21) -> float:
    """Height of the mesh's highest point above its centre per unit scale, over a fine grid of the allowed tilts."""
    rx, ry = np.meshgrid(np.linspace(*scene.rot_x_deg, grid), np.linspace(*scene.rot_y_deg, grid))
    rot = rotation_matrices(np.column_stack([rx.ravel(), ry.ravel(), np.zeros(rx.size)]))
    return float((rot[:, 2, :] @ mesh.vertices.T).max())


def fitted(mesh: trimesh.Trimesh, up: str, diagonal: float, clearance: float, scene: Scene
           ) -> tuple[trimesh.Trimesh, float]:
    """Upright, centred and scaled by rule 2-3; returns the mesh and its scale factor from the file's units."""
    mesh = mesh.copy()
    transform = np.eye(4)
    transform[:3, :3] = UP[up]
    mesh.apply_transform(transform)
    mesh.apply_translation(-mesh.bounds.mean(axis=0))
    scale = diagonal / float(np.linalg.norm(mesh.extents))
    room = -clearance - scene.object_z[1]  # how high above its centre an object may reach
    scale = min(scale, room / top_per_metre(mesh, scene))
    mesh.apply_scale(scale)
    return mesh, scale


def shape_distance(a: trimesh.Trimesh, b: trimesh.Trimesh, turn_step: float, points: int = 1500) -> float:
    """Symmetric Chamfer distance between two centred surfaces after the best turn about the vertical or mirror
    image of b, over a's bounding-box diagonal (rule 4)."""
    pa, _ = trimesh.sample.sample_surface(a, points, seed=0)
    pb, _ = trimesh.sample.sample_surface(b, points, seed=1)
    tree_a, tree_b = cKDTree(pa), cKDTree(pb)
    best = math.inf
    for flip in (np.eye(3), mirror_matrix(0.0)):
        for angle in np.arange(0.0, 360.0, turn_step):
            move = turn_matrix(angle) @ flip  # orthogonal: its inverse is its transpose
            there, _ = tree_a.query(pb @ move.T)
            back, _ = tree_b.query(pa @ move)
            best = min(best, 0.5 * float(there.mean() + back.mean()))
    return best / float(np.linalg.norm(a.extents))


def obj_text(mesh: trimesh.Trimesh) -> str:
    """The mesh as OBJ text: vertices and faces only, to 0.1 nm (a boolean union leaves edges of nanometres,
    which fewer digits would fold, opening the mesh)."""
    return trimesh.exchange.obj.export_obj(mesh, include_normals=False, include_color=False, include_texture=False,
                                           digits=10, header=None)


def small(mesh: trimesh.Trimesh) -> tuple[trimesh.Trimesh, float]:
    """The mesh as it is, or simplified (manifold3d) within the smallest tolerance of SIMPLIFY_M, whichever first
    has an OBJ text under MAX_FILE_BYTES that reads back closed. Returns it and the tolerance (0: as it is)."""
    solid = manifold3d.Manifold(manifold3d.Mesh(vert_properties=np.asarray(mesh.vertices, np.float32),
                                                tri_verts=np.asarray(mesh.faces, np.uint32)))
    for tolerance in (0.0, *SIMPLIFY_M):
        if tolerance:
            out = solid.simplify(tolerance).to_mesh()
            mesh = trimesh.Trimesh(out.vert_properties[:, :3], out.tri_verts)
        text = obj_text(mesh)
        back = trimesh.load(trimesh.util.wrap_as_stream(text), file_type="obj", force="mesh")
        if len(text.encode()) <= MAX_FILE_BYTES and back.is_watertight:
            return back, tolerance
    raise ValueError(f"mesh of {len(mesh.faces)} faces: no tolerance of {SIMPLIFY_M} m gives a closed OBJ under "
                     f"{MAX_FILE_BYTES} bytes")


def build(args: argparse.Namespace) -> list[Built]:
    """Apply the rule to the household meshes, then to the blobs until --blobs chiral ones are kept."""
    scene = Scene()
    kept: list[Built] = []

    def consider(name: str, source: str, up: str, want_chiral: bool) -> bool:
        closed, how = solid(trimesh.load(DATA / source, force="mesh"))
        mesh, scale = fitted(closed, up, args.diagonal, args.clearance, scene)
        mesh, simplified = small(mesh)
        if simplified:
            how += f", simplified within {simplified * 1000:g} mm"
        if want_chiral and ((symmetry := find_symmetry(mesh)).mirror or symmetry.turn_order != 1):
            print(f"  skip {source}: {symmetry.describe()}")
            return False
        for other in kept:
            if (d := shape_distance(other.mesh, mesh, args.turn_step)) < args.duplicate:
                print(f"  skip {source}: near-duplicate of {other.name} (Chamfer {d:.4f} of the diagonal)")
                return False
        kept.append(Built(name, source, how, up, scale, mesh))
        return True

    for name, source, up in HOUSEHOLD:
        consider(name, source, up, want_chiral=False)
    blobs = 0
    for number in range(1000):
        if blobs == args.blobs:
            break
        blobs += consider(f"blob_{number:03d}", f"random_urdfs/{number:03d}/{number:03d}.obj", "z", want_chiral=True)
    if blobs < args.blobs:
        raise SystemExit(f"only {blobs} chiral blobs with no turn symmetry in random_urdfs, --blobs={args.blobs}")
    return kept


README = """# {name}: {count} objects from the meshes that ship with pybullet_data

Built by `scripts/make_object_set.py` (its docstring states the rule) from pybullet {pybullet}'s `pybullet_data`;
nobody in this project drew these shapes. Rebuild (needs manifold3d) with

    .venv/bin/python scripts/make_object_set.py --out {out} --diagonal {diagonal} --clearance {clearance} \\
        --duplicate {duplicate} --turn-step {turn_step} --blobs {blobs}

Train on it with `--data.objects {out}`. Each class is one OBJ (class name = file stem): one closed mesh
(pieces that only touch, as the blobs' boxes do, stay separate closed bodies in it), upright, its bounding box
centred on the origin, its diagonal {diagonal} m unless the scene's depth limits it (every allowed pose keeps it
at least {clearance} m below the ground). Scale is from the file's units to metres.

Symmetries as `hg.sim.symmetry.object_symmetries` finds them on this folder: a map is a symmetry when the mean
symmetric Chamfer distance between the surface and its image is at most {tolerance} of the bounding-box diagonal
(the errors below; the mirror's is that of the best vertical plane, its normal given in degrees from x). Turns are
about the vertical axis. A chiral object has no mirror plane: a mirror image of its episode shows no pose of it,
so mirror augmentations must be off for it. {close}

| class | source (pybullet_data/) | made solid | up axis | scale | extents (m) | faces | bodies | turns | turn error | mirror | mirror error |
|---|---|---|---|---|---|---|---|---|---|---|---|
{rows}
"""


def write(kept: list[Built], args: argparse.Namespace) -> None:
    """The OBJ files, then the README with the symmetries of the set as training loads it."""
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    for stale in out.glob("*.obj"):
        stale.unlink()
    for b in kept:
        (out / f"{b.name}.obj").write_text(obj_text(b.mesh))
    loaded = load_object_set(out)  # refuses a mesh that is not watertight
    check_below_ground(Scene(), loaded)
    symmetries = dict(zip(loaded.names, object_symmetries(loaded)))
    rows = []
    for b in kept:
        s = symmetries[b.name]
        turns = "any angle" if s.turn_order is None else ("none" if s.turn_order == 1 else f"{s.turn_deg:g} deg")
        mirror = f"yes (normal {s.mirror_deg:g} deg)" if s.mirror else "no (chiral)"
        rows.append(f"| {b.name} | {b.source} | {b.solid} | {b.up.upper()} | {b.scale:.5g} | "
                    f"{' x '.join(f'{e:.3f}' for e in b.mesh.extents)} | {len(b.mesh.faces)} | "
                    f"{len(b.mesh.split(only_watertight=False))} | {turns} | "
                    f"{s.turn_error:.4f} | {mirror} | {s.mirror_error:.4f} |")
        print(f"{b.name:12s} {b.source:28s} scale {b.scale:.4f}  extents {np.round(b.mesh.extents, 3)}  "
              f"{s.describe()}")
    near = [f"{name} ({kind} {error:.4f})" for name, sym in symmetries.items()
            for kind, error in (("turn", sym.turn_error), ("mirror", sym.mirror_error))
            if 0.5 < error / TOLERANCE < 1.5]
    close = (f"Verdicts within a factor 1.5 of the tolerance are\njudgements, not facts: {', '.join(near)}."
             if near else "No verdict lies within a factor 1.5 of the tolerance.")
    try:
        shown = out.resolve().relative_to(ROOT)
    except ValueError:
        shown = out
    (out / "README.md").write_text(README.format(
        name=out.name, count=len(kept), pybullet=version("pybullet"), out=shown, diagonal=args.diagonal,
        clearance=args.clearance, duplicate=args.duplicate, turn_step=args.turn_step, blobs=args.blobs,
        tolerance=TOLERANCE, close=close, rows="\n".join(rows)))
    print(f"wrote {len(kept)} objects to {out}")


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", required=True, help="folder to write (its .obj files are replaced)")
    parser.add_argument("--diagonal", type=float, default=0.45, help="bounding-box diagonal of each object (m)")
    parser.add_argument("--clearance", type=float, default=0.01, help="least depth of an object's top (m)")
    parser.add_argument("--duplicate", type=float, default=0.03,
                        help="near-duplicate below this Chamfer distance (share of the diagonal)")
    parser.add_argument("--turn-step", type=float, default=5.0, help="turns tried in the duplicate test (deg)")
    parser.add_argument("--blobs", type=int, default=4, help="chiral random_urdfs blobs to add")
    args = parser.parse_args(argv)
    write(build(args), args)


if __name__ == "__main__":
    main()
