"""Swapping in another robot: attach our probe to any URDF arm, place its base beside the probe line, report reach.

The edited URDF keeps the conventions `ProbeArm` relies on: a root link `world`, a fixed joint `world_to_base`
placing the robot, and a tool link `probe_tip` (identity inertial frame, NOTES.md) whose +z is the probing
direction at the end of a 0.25 m rod. yourdfpy edits and writes the file; PyBullet checks and measures it, always
through `ProbeArm` (its reach map scores base candidates, its `reach` gives the reach fraction), so the figures
are the simulator's own. scripts/swap_urdf.py is the command line; docs/robots.md the how-to.
"""
from __future__ import annotations

import copy
import math
import os
import re
import shutil
import tempfile
import xml.etree.ElementTree as ET
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Iterable

import numpy as np
import pybullet_data
import trimesh
import yourdfpy
from lxml import etree

from hg.sim.client import BulletClient
from hg.sim.kernels import FIXED, tool_frames
from hg.sim.robot import (ANGLE_TOLERANCE_DEG, JOINT_KINDS, POSITION_TOLERANCE, TOOL_LINK, ProbeArm, ReachGrid,
                          achieved, load_robot, tool_orientations)
from hg.sim.scene import Scene

WORLD_LINK = "world"
BASE_JOINT = "world_to_base"
ROD_LINK, ROD_JOINT, TIP_JOINT = "probe_rod", "probe_mount", "probe_tip_joint"
ROD_LENGTH, ROD_RADIUS, ROD_MASS = 0.25, 0.008, 0.2
SEARCH_GRID = ReachGrid(n_y=5, n_dir=5)  # coarse: scores a base candidate in well under a second
VISUALS = ("copy", "collision")
LICENCE_NAMES = ("LICENSE", "LICENCE", "COPYING")


# -- reading ------------------------------------------------------------------------------------------
def resolve_urdf(path: str | Path) -> Path:
    """A URDF given as a path, or as a path inside the installed `pybullet_data` (e.g. kuka_iiwa/model.urdf)."""
    path = Path(path)
    if path.is_file():
        return path
    bundled = Path(pybullet_data.getDataPath()) / path
    if not path.is_absolute() and bundled.is_file():
        return bundled
    raise FileNotFoundError(f"robot URDF {path}: file not found (neither as a path nor inside pybullet_data)")


def load_urdf(path: str | Path) -> yourdfpy.URDF:
    """Parse a URDF strictly (yourdfpy alone silently recovers from broken XML) and check its tree."""
    path = resolve_urdf(path)
    try:
        root = ET.parse(path).getroot()
    except ET.ParseError as exc:
        raise ValueError(f"robot URDF {path}: malformed XML ({exc})") from exc
    if root.tag != "robot":
        raise ValueError(f"robot URDF {path}: the root element is <{root.tag}>, expected <robot>")
    if is_xacro(path, root):
        raise ValueError(f"robot URDF {path}: a xacro file, not a URDF (it has xacro macros or ${{...}} expressions); "
                         f"expand it first with ROS's `xacro {path.name} > robot.urdf`, or without ROS "
                         f"`pip install xacrodoc`, then swap robot.urdf")
    try:
        urdf = yourdfpy.URDF.load(str(path), build_scene_graph=False, load_meshes=False,
                                  filename_handler=yourdfpy.filename_handler_null)
    except (KeyError, ValueError, AttributeError) as exc:
        raise ValueError(f"robot URDF {path}: yourdfpy cannot read it ({exc!r})") from exc
    robot = urdf.robot
    links = [link.name for link in robot.links]
    duplicates = [name for name, n in Counter(links).items() if n > 1]
    if duplicates:
        raise ValueError(f"robot URDF {path}: duplicate link names {duplicates}")
    for joint in robot.joints:
        for end in (joint.parent, joint.child):
            if end not in links:
                raise ValueError(f"robot URDF {path}: joint '{joint.name}' refers to a missing link '{end}'")
    roots = [name for name in links if name not in {j.child for j in robot.joints}]
    if len(roots) != 1:
        raise ValueError(f"robot URDF {path}: expected one root link, found {len(roots)} ({', '.join(roots)})")
    adopt_world_root(robot, path)
    return urdf


XACRO_NAMESPACES = ("{http://www.ros.org/wiki/xacro}", "{http://ros.org/wiki/xacro}")


def is_xacro(path: Path, root: ET.Element) -> bool:
    """A xacro source (macros, properties, ${...}) rather than its expanded URDF: PyBullet cannot read it."""
    if path.name.endswith(".xacro"):
        return True
    return any(e.tag.startswith(XACRO_NAMESPACES) or any("${" in v or "$(" in v for v in e.attrib.values())
               for e in root.iter() if isinstance(e.tag, str))


def adopt_world_root(robot: yourdfpy.Robot, path: Path) -> None:
    """Many vendor URDFs (xArm, ROS descriptions) root the arm at a link `world` with one fixed joint: that joint
    becomes our `world_to_base`, which the base placement then sets. Any other use of `world` is refused."""
    names = {link.name for link in robot.links}
    if WORLD_LINK not in names or any(j.name == BASE_JOINT for j in robot.joints):
        return
    if root_link(robot) != WORLD_LINK:
        raise ValueError(f"robot URDF {path}: link '{WORLD_LINK}' is not the root, but hg roots the arm at its own "
                         f"'{WORLD_LINK}' link: rename that link")
    joints = [j for j in robot.joints if j.parent == WORLD_LINK]
    if len(joints) != 1 or joints[0].type != "fixed":
        held = ", ".join(f"'{j.child}' by a {j.type} joint '{j.name}'" for j in joints)
        raise ValueError(f"robot URDF {path}: root link '{WORLD_LINK}' holds {held}; hg mounts the arm with one "
                         f"fixed joint: remove the '{WORLD_LINK}' link and its joints, or make one joint fixed")
    joints[0].name = BASE_JOINT


def root_link(robot: yourdfpy.Robot) -> str:
    """The link no joint points to (load_urdf checks there is exactly one)."""
    children = {j.child for j in robot.joints}
    return next(link.name for link in robot.links if link.name not in children)


def leaf_links(robot: yourdfpy.Robot) -> list[str]:
    """Links with no child: candidates for the tool link (fingers and frames count too)."""
    parents = {j.parent for j in robot.joints}
    return [link.name for link in robot.links if link.name not in parents]


def pick_tool_link(robot: yourdfpy.Robot, path: Path, tool_link: str | None = None) -> str:
    """The named tool link; else the tree's only leaf, or the last link all leaves share (a hand carrying fingers
    and frames) when a movable joint lies above it; an error lists the leaves otherwise."""
    names = [link.name for link in robot.links]
    if tool_link is not None:
        if tool_link not in names:
            raise ValueError(f"robot URDF {path}: no link named '{tool_link}' (links: {', '.join(names)})")
        return tool_link
    leaves = leaf_links(robot)
    if len(leaves) == 1:
        return leaves[0]
    paths = [[j.child for j in chain_joints(robot, leaf)] for leaf in leaves]
    shared = [at_depth[0] for at_depth in zip(*paths) if len(set(at_depth)) == 1]  # links every leaf hangs from
    if shared and any(j.type != "fixed" for j in chain_joints(robot, shared[-1])):
        return shared[-1]  # a gripper's base or a hand: the last link the fingers (or frames) share
    raise ValueError(f"robot URDF {path}: {len(leaves)} leaf links on separate branches, so the tool link is "
                     f"ambiguous; pass --tool-link with one of: {', '.join(leaves)} (or any other link)")


def check_chain(robot: yourdfpy.Robot, path: Path, tool_link: str) -> None:
    """The joints IK moves to place the tool must move on their own: PyBullet ignores <mimic>, and a floating or
    planar joint is not an arm's joint. Mimic joints elsewhere (a gripper's fingers) do no harm."""
    for joint in chain_joints(robot, tool_link):
        if joint.mimic is not None:
            raise ValueError(f"robot URDF {path}: joint '{joint.name}' between the root and the tool link "
                             f"'{tool_link}' mimics '{joint.mimic.joint}', which PyBullet's IK ignores (it would "
                             f"move the joint on its own); pass --tool-link '{joint.parent}' or a link above it")
        if joint.type in ("floating", "planar"):
            raise ValueError(f"robot URDF {path}: joint '{joint.name}' between the root and the tool link "
                             f"'{tool_link}' is {joint.type}; an arm's joints are revolute, continuous, prismatic "
                             f"or fixed: make it fixed or remove it")


def mesh_geometries(robot: yourdfpy.Robot) -> Iterable[yourdfpy.Mesh]:
    """Every <mesh> of every visual and collision, as the objects whose filename we rewrite."""
    for link in robot.links:
        for element in link.visuals + link.collisions:
            if element.geometry is not None and element.geometry.mesh is not None:
                yield element.geometry.mesh


def resolve_mesh(filename: str, urdf_path: Path) -> Path:
    """Where a mesh reference points, the way PyBullet resolves it (package:// relative to the URDF's folder)."""
    base = urdf_path.resolve().parent
    name = re.sub(r"^file://", "", filename)
    candidates = [Path(name)] if Path(name).is_absolute() else [base / name]
    if filename.startswith("package://"):
        rest = Path(filename[len("package://"):])
        candidates = [base / rest]
        if len(rest.parts) > 1:  # package://<package>/<path>: the package folder is the URDF's or a parent
            candidates += [folder / Path(*rest.parts[1:]) for folder in (base, *base.parents)
                           if folder.name == rest.parts[0]]
            candidates.append(base / Path(*rest.parts[1:]))
    for candidate in candidates:
        if candidate.is_file():
            return candidate
    raise FileNotFoundError(f"robot URDF {urdf_path}: mesh file '{filename}' not found (looked for {candidates[0]})")


def check_meshes(robot: yourdfpy.Robot, path: Path) -> dict[str, Path]:
    """Every mesh reference resolved to a file; the first missing one raises FileNotFoundError."""
    return {mesh.filename: resolve_mesh(mesh.filename, path) for mesh in mesh_geometries(robot)}


# -- editing ------------------------------------------------------------------------------------------
def _origin(xyz: Iterable[float] = (0.0, 0.0, 0.0)) -> np.ndarray:
    m = np.eye(4)
    m[:3, 3] = list(xyz)
    return m


def _inertial(mass: float, diagonal: tuple[float, float, float], z: float = 0.0) -> yourdfpy.Inertial:
    return yourdfpy.Inertial(origin=_origin((0.0, 0.0, z)), mass=mass, inertia=np.diag(diagonal))


def mount_offset(urdf: yourdfpy.URDF, path: Path, tool_link: str) -> float:
    """Where the rod starts along the tool link's +z: the far face of its collision (or visual) geometry."""
    link = urdf.link_map[tool_link]
    top = 0.0
    for element in link.collisions or link.visuals:
        geometry, origin = element.geometry, np.eye(4) if element.origin is None else element.origin
        if geometry is None:
            continue
        if geometry.mesh is not None:
            mesh = trimesh.load(resolve_mesh(geometry.mesh.filename, path), force="mesh")
            if geometry.mesh.scale is not None:
                mesh.apply_scale(geometry.mesh.scale)
            points = mesh.vertices
        elif geometry.box is not None:
            points = trimesh.creation.box(geometry.box.size).vertices
        elif geometry.cylinder is not None:
            points = trimesh.creation.cylinder(geometry.cylinder.radius, geometry.cylinder.length).vertices
        elif geometry.sphere is not None:
            points = trimesh.creation.icosphere(radius=geometry.sphere.radius).vertices
        else:
            continue
        top = max(top, float(trimesh.transform_points(points, origin)[:, 2].max()))
    return round(top, 4)


def attach_probe(robot: yourdfpy.Robot, tool_link: str, offset: float, length: float = ROD_LENGTH,
                 radius: float = ROD_RADIUS) -> None:
    """Fix a rod (cylinder, explicit inertia) to the tool link's +z at `offset`, and `probe_tip` at its end."""
    taken = {link.name for link in robot.links} & {ROD_LINK, TOOL_LINK}
    if taken:
        raise ValueError(f"robot '{robot.name}' already has link(s) {sorted(taken)}: is the probe attached already?")
    side = ROD_MASS * (3 * radius ** 2 + length ** 2) / 12
    orange = yourdfpy.Material(name="probe_orange", color=yourdfpy.Color(np.array([0.95, 0.5, 0.1, 1.0])))
    geometry = yourdfpy.Geometry(cylinder=yourdfpy.Cylinder(radius=radius, length=length))
    rod = yourdfpy.Link(
        name=ROD_LINK, inertial=_inertial(ROD_MASS, (side, side, ROD_MASS * radius ** 2 / 2), length / 2),
        visuals=[yourdfpy.Visual(origin=_origin((0, 0, length / 2)), geometry=geometry, material=orange)],
        collisions=[yourdfpy.Collision(name=None, origin=_origin((0, 0, length / 2)), geometry=geometry)])
    tip = yourdfpy.Link(name=TOOL_LINK, inertial=_inertial(0.001, (1e-7, 1e-7, 1e-7)))
    robot.links += [rod, tip]
    robot.joints += [
        yourdfpy.Joint(name=ROD_JOINT, type="fixed", parent=tool_link, child=ROD_LINK, origin=_origin((0, 0, offset))),
        yourdfpy.Joint(name=TIP_JOINT, type="fixed", parent=ROD_LINK, child=TOOL_LINK, origin=_origin((0, 0, length))),
    ]


@dataclass(frozen=True)
class BasePlacement:
    """Where the robot's root stands: a position, a tilt of its z axis towards the probe line, a yaw about it."""

    x: float
    y: float
    z: float
    tilt_deg: float = 0.0  # 0 = upright; 90 = mounted on a wall facing the probe line
    yaw_deg: float = 0.0  # about the base's own z axis: where joint 1's dead zone points

    def matrix(self) -> np.ndarray:
        towards_line = -1.0 if self.x >= 0 else 1.0  # tilting about +y leans z towards +x
        m = np.eye(4)
        m[:3, :3] = _rot_y(towards_line * math.radians(self.tilt_deg)) @ _rot_z(math.radians(self.yaw_deg))
        m[:3, 3] = (self.x, self.y, self.z)
        return m

    def rpy_deg(self) -> list[float]:
        """The URDF origin's roll, pitch, yaw in degrees."""
        return [round(math.degrees(a), 3) + 0.0 for a in trimesh.transformations.euler_from_matrix(self.matrix())]

    def __str__(self) -> str:
        return (f"x={self.x:+.3f} y={self.y:+.3f} z={self.z:+.3f} m, tilt {self.tilt_deg:g} deg towards the "
                f"probe line, yaw {self.yaw_deg:g} deg")


def _rot_y(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def _rot_z(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def set_base(robot: yourdfpy.Robot, base: BasePlacement) -> None:
    """Root the robot at a link `world` with the fixed joint `world_to_base`, replacing an existing one."""
    joints = [j for j in robot.joints if j.name == BASE_JOINT]
    if not joints:
        if root_link(robot) == WORLD_LINK:
            raise ValueError(f"robot '{robot.name}': its root link is already '{WORLD_LINK}' without a "
                             f"'{BASE_JOINT}' joint; rename the root or remove it")
        joints = [yourdfpy.Joint(name=BASE_JOINT, type="fixed", parent=WORLD_LINK, child=root_link(robot))]
        robot.links.insert(0, yourdfpy.Link(name=WORLD_LINK, inertial=_inertial(0.001, (1e-6, 1e-6, 1e-6))))
        robot.joints.insert(0, joints[0])
    joints[0].origin = base.matrix()


def kinematic_copy(robot: yourdfpy.Robot) -> yourdfpy.Robot:
    """The same joints and inertials without any geometry: fast to load for scoring base candidates."""
    links = [yourdfpy.Link(name=link.name, inertial=copy.deepcopy(link.inertial)) for link in robot.links]
    return yourdfpy.Robot(name=robot.name, links=links, joints=copy.deepcopy(robot.joints))


def _obj_companions(mesh: Path) -> list[Path]:
    """Material and texture files an OBJ mesh refers to (mtllib, map_*), when they exist."""
    if mesh.suffix.lower() != ".obj":
        return []
    found = []
    for line in mesh.read_text(errors="replace").splitlines():
        if line.startswith("mtllib"):
            mtl = mesh.parent / line.split(maxsplit=1)[1].strip()
            if mtl.is_file():
                found.append(mtl)
                for entry in mtl.read_text(errors="replace").splitlines():
                    words = entry.split()
                    if words and words[0].startswith("map_") and (mtl.parent / words[-1]).is_file():
                        found.append(mtl.parent / words[-1])
    return found


def use_collision_visuals(robot: yourdfpy.Robot) -> None:
    """Draw each link with its collision geometry: robot visual meshes are often megabytes each."""
    for link in robot.links:
        if not any(v.geometry is not None and v.geometry.mesh is not None for v in link.visuals):
            continue
        material = next((v.material for v in link.visuals if v.material is not None), None)
        link.visuals = [yourdfpy.Visual(origin=copy.deepcopy(c.origin), geometry=copy.deepcopy(c.geometry),
                                        material=material) for c in link.collisions]


def copy_meshes(robot: yourdfpy.Robot, source: Path, out: Path) -> int:
    """Copy every referenced mesh (with its OBJ materials, and the licence files beside the source URDF) into
    meshes/<out stem>/ beside `out` and point the URDF there with relative paths; returns the bytes copied.
    The folder is replaced, so no stale files stay."""
    resolved = check_meshes(robot, source)
    if not resolved:
        return 0
    files = set(resolved.values())
    files |= {c for f in resolved.values() for c in _obj_companions(f)}
    licences = [f for f in source.resolve().parent.iterdir()
                if f.is_file() and f.name.upper().startswith(LICENCE_NAMES)]
    common = Path(os.path.commonpath([str(f.parent) for f in files]))
    folder = Path("meshes") / out.stem
    target = out.parent / folder
    if any(target.resolve() in f.resolve().parents for f in files):
        raise ValueError(f"robot URDF {source}: its meshes lie in {target}, which the copy would replace; "
                         f"choose another output name")
    if target.exists():
        shutil.rmtree(target)
    for f in files:
        destination = target / f.relative_to(common)
        destination.parent.mkdir(parents=True, exist_ok=True)
        shutil.copyfile(f, destination)
    for f in licences:  # the meshes' licence travels with them
        shutil.copyfile(f, target / f.name)
    for mesh in mesh_geometries(robot):
        mesh.filename = (folder / resolved[mesh.filename].relative_to(common)).as_posix()
    return sum(f.stat().st_size for f in [*files, *licences])


def source_notices(path: Path) -> list[str]:
    """The comments before <robot> in a URDF: where vendors keep the licence that must travel with the file."""
    root = etree.parse(str(path)).getroot()
    return [c.text for c in reversed(list(root.itersiblings(preceding=True))) if isinstance(c, etree._Comment)]


def write_urdf(robot: yourdfpy.Robot, out: Path, comments: Iterable[str] = ()) -> None:
    """Write with yourdfpy, after leading comments (how the file was made, the source's licence notices)."""
    xml = yourdfpy.URDF(robot=robot, build_scene_graph=False, load_meshes=False,
                        filename_handler=yourdfpy.filename_handler_null).write_xml()  # else paths get rewritten
    written = {e.get("name"): e for e in xml.getroot().iter("joint")}
    for joint in (j for j in robot.joints if j.mimic is not None):  # yourdfpy's writer drops <mimic>
        if written[joint.name].find("mimic") is None:
            etree.SubElement(written[joint.name], "mimic", joint=joint.mimic.joint,
                             multiplier=str(joint.mimic.multiplier), offset=str(joint.mimic.offset))
    body = etree.tostring(xml, pretty_print=True, encoding="unicode")
    notes = "".join(f"<!--{c if c.startswith(' ') else ' ' + c}{'' if c.endswith(' ') else ' '}-->\n"
                    for c in (c.replace("--", "- -") for c in comments))  # '--' may not appear in a comment
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(f"<?xml version='1.0' encoding='utf-8'?>\n{notes}{body}")


# -- reach ------------------------------------------------------------------------------------------
def chain_joints(robot: yourdfpy.Robot, link: str) -> list[yourdfpy.Joint]:
    """Joints from the root down to `link`, in order."""
    by_child = {j.child: j for j in robot.joints}
    chain = []
    while link in by_child:
        chain.append(by_child[link])
        link = by_child[link].parent
    return chain[::-1]


def movable_joints(robot: yourdfpy.Robot, link: str) -> int:
    """How many joints between the root and `link` move (what IK has to place it with)."""
    return sum(JOINT_KINDS.get(j.type, FIXED) != FIXED for j in chain_joints(robot, link))


def reach_bound(robot: yourdfpy.Robot, link: str = TOOL_LINK) -> tuple[str, float]:
    """The first movable joint on the way to `link` and an upper bound on how far `link` gets from it:
    the sum of the joint offsets after it (plus prismatic travel). A target farther away is out of reach."""
    chain = chain_joints(robot, link)
    first = next((i for i, j in enumerate(chain) if j.type != "fixed"), None)
    if first is None:
        raise ValueError(f"robot '{robot.name}': no movable joint between the root and '{link}'")
    bound = 0.0
    for joint in chain[first + 1:]:
        bound += float(np.linalg.norm(joint.origin[:3, 3])) if joint.origin is not None else 0.0
        if joint.type == "prismatic" and joint.limit is not None:
            bound += max(abs(joint.limit.lower or 0.0), abs(joint.limit.upper or 0.0))
    return chain[first].name, bound


def span_fraction(robot: yourdfpy.Robot, base: BasePlacement, scene: Scene, n: int, seed: int = 0) -> float:
    """Share of random requests whose entry point lies within the arm's span (`reach_bound`) from its first
    movable joint: an upper bound on the reach fraction that needs no IK."""
    name, bound = reach_bound(robot)
    pivot = base.matrix()
    for joint in chain_joints(robot, TOOL_LINK):
        if joint.name != BASE_JOINT:  # its origin is what `base` replaces
            pivot = pivot @ (np.eye(4) if joint.origin is None else joint.origin)
        if joint.name == name:
            break
    points, _ = scene.request_to_probe(np.random.default_rng(seed).uniform(-1.0, 1.0, (n, 4)))
    return float((np.linalg.norm(points - pivot[:3, 3], axis=1) <= bound).mean())


@dataclass
class ReachResult:
    """Random requests sent through `ProbeArm.reach` as the simulator does, with a reason for every miss."""

    points: np.ndarray  # (n, 3) requested entry points P
    dirs: np.ndarray  # (n, 3) requested directions u
    error: np.ndarray  # (n, 2) position (m) and angle (deg) errors
    map_error: np.ndarray  # (entries, 2) the reach map's own errors
    reasons: list[str] = field(default_factory=list)  # one per miss, in order

    @property
    def ok(self) -> np.ndarray:
        return achieved(self.error)

    @property
    def fraction(self) -> float:
        return float(self.ok.mean())


def _wrap_into_limits(q: np.ndarray, lower: np.ndarray, upper: np.ndarray) -> np.ndarray:
    """Shift joints by a full turn where that brings them inside their limits (same pose for a revolute joint)."""
    q = q.copy()
    for turn in (-2 * math.pi, 2 * math.pi):
        shift = ((q < lower) | (q > upper)) & (q + turn >= lower) & (q + turn <= upper)
        q[shift] += turn
    return q


def _solve(arm: ProbeArm, point: np.ndarray, orientation: list[float] | None, start: np.ndarray,
           clip: bool) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A thorough IK call (200 iterations), optionally without orientation or without clipping to the limits;
    returns the joints (turned by full turns into their limits where possible), tip position and tip axis."""
    extra = {"targetOrientation": orientation} if orientation is not None else {}
    q = arm.client.calculateInverseKinematics(arm.body, arm.tool, point.tolist(), currentPositions=start.tolist(),
                                              jointDamping=arm.damping, maxNumIterations=200,
                                              residualThreshold=1e-6, **extra)
    q = _wrap_into_limits(np.asarray(q[:len(arm.joints)]), arm.lower, arm.upper)
    if clip:
        q = np.clip(q, arm.lower, arm.upper)
    arm.set_joints(q)
    tips, axes = tool_frames(q[None], *arm.chain)  # the pose the simulator computes, not PyBullet's float32 one
    return q, tips[0], axes[0]


def diagnose_miss(arm: ProbeArm, point: np.ndarray, direction: np.ndarray, pivot: tuple[str, np.ndarray, float],
                  rng: np.random.Generator, starts: int = 8) -> str:
    """Why a request was missed, from IK runs with and without joint limits and without the orientation:
    beyond the arm's reach distance, a joint limit in the way (naming the joint), or the probe direction."""
    name, position, bound = pivot
    distance = float(np.linalg.norm(point - position))
    if distance > bound:
        return f"beyond the arm's span ({distance:.2f} m from {name}, it spans {bound:.2f} m)"
    orientation = tool_orientations(direction[None])[0].tolist()
    grid_points, grid_dirs = arm.grid_targets
    nearest = np.argsort(np.abs(grid_points[:, 1] - point[1]) + np.abs(grid_dirs - direction).sum(1))[:starts // 2]
    low, high = np.maximum(arm.lower, -math.pi), np.minimum(arm.upper, math.pi)
    start_qs = [arm.map_q[e] for e in nearest] + [rng.uniform(low, high) for _ in range(starts - len(nearest))]

    def hits(tip: np.ndarray, axis: np.ndarray, with_axis: bool = True) -> bool:
        err = arm.pose_error(point[None], direction[None], tip[None], axis[None])[0]
        return err[0] <= POSITION_TOLERANCE and (not with_axis or err[1] <= ANGLE_TOLERANCE_DEG)

    needs = []
    for start in start_qs:
        q, tip, axis = _solve(arm, point, orientation, start, clip=False)
        if hits(tip, axis):
            outside = [arm.joint_names[k] for k in range(len(q)) if not arm.lower[k] <= q[k] <= arm.upper[k]]
            if not outside:
                return "IK missed a solution inside the joint limits"
            needs.append(outside)
    if needs:
        return f"needs {' and '.join(min(needs, key=len))} beyond its limit"
    if not any(hits(*_solve(arm, point, None, start, clip=False)[1:], with_axis=False) for start in start_qs):
        return f"tip position out of reach ({distance:.2f} m from {name})"
    at_limit = Counter()
    for start in start_qs:
        q = _solve(arm, point, orientation, start, clip=True)[0]
        at_limit.update(arm.joint_names[k] for k in range(len(q))
                        if min(q[k] - arm.lower[k], arm.upper[k] - q[k]) < 1e-3)
    limit = f": the IK solution hits the limit of {at_limit.most_common(1)[0][0]}" if at_limit else ""
    return f"tip reachable, not along this direction{limit}"


def measure_reach(urdf: str | Path, scene: Scene, n: int, seed: int = 0, diagnose: bool = True) -> ReachResult:
    """Reach fraction over `n` random requests in [-1, 1]^4 through ProbeArm.reach, exactly the simulator's path."""
    requests = np.random.default_rng(seed).uniform(-1.0, 1.0, (n, 4))
    points, dirs = scene.request_to_probe(requests)
    with BulletClient() as client:
        arm = ProbeArm(client, urdf, scene, TOOL_LINK, seed=seed)
        _, _, errors = arm.reach(points, dirs)
        result = ReachResult(points, dirs, errors, arm.map_error)
        if diagnose and not result.ok.all():
            robot = load_urdf(urdf).robot
            name, bound = reach_bound(robot)
            index = next(j for j in range(client.getNumJoints(arm.body))
                         if client.getJointInfo(arm.body, j)[1].decode() == name)
            pivot = (name, np.array(client.getLinkState(arm.body, index)[4]), bound)  # the joint's own frame
            rng = np.random.default_rng(seed)
            result.reasons = [diagnose_miss(arm, points[i], dirs[i], pivot, rng) for i in np.flatnonzero(~result.ok)]
    return result


# -- the report ------------------------------------------------------------------------------------
def tilt_bands(scene: Scene) -> list[tuple[float, float]]:
    """Thirds of the tilt range: the first is 'steep', where the lean direction hardly matters."""
    t = scene.max_tilt_deg
    return [(0.0, t / 3), (t / 3, 2 * t / 3), (2 * t / 3, t)]


LEAN_AXES = ("+x", "-x", "+y", "-y")


def lean_names(scene: Scene) -> list[str]:
    """Every probe-direction label, in report order: steep first, then each lean axis per tilt band."""
    (_, steep), *bands = tilt_bands(scene)
    return [f"steep (<{steep:g} deg)"] + [f"lean {a} {lo:g}-{hi:g} deg" for lo, hi in bands for a in LEAN_AXES]


def lean_labels(dirs: np.ndarray, scene: Scene) -> np.ndarray:
    """Which way each probe leans: 'steep' in the first tilt band, else the nearest axis and the tilt band."""
    names = lean_names(scene)
    tilt = np.degrees(np.arccos(np.clip(-dirs[:, 2], -1.0, 1.0)))
    band = np.clip(np.searchsorted([hi for _, hi in tilt_bands(scene)], tilt, side="right"), 0, 2)
    quadrant = np.rint(np.degrees(np.arctan2(dirs[:, 1], dirs[:, 0])) / 90.0).astype(int) % 4  # +x, +y, -x, -y
    axis = np.array([0, 2, 1, 3])[quadrant]  # as in LEAN_AXES
    return np.array([names[0] if b == 0 else names[1 + (b - 1) * len(LEAN_AXES) + a] for b, a in zip(band, axis)])


def reach_report(result: ReachResult, scene: Scene, title: str, base: BasePlacement, n_y: int = 4,
                 max_rows: int = 12) -> str:
    """Human-readable: overall reach, reach by entry y and by lean direction, and where and why it fails."""
    ok, n = result.ok, len(result.ok)
    edges = np.linspace(*scene.probe_y, n_y + 1)
    ybin = np.clip(np.searchsorted(edges, result.points[:, 1], side="right") - 1, 0, n_y - 1)
    yname = [f"y in [{edges[k]:+.2f}, {edges[k + 1]:+.2f}]" for k in range(n_y)]
    leans = lean_labels(result.dirs, scene)
    map_ok = achieved(result.map_error)
    tolerance = f"within {POSITION_TOLERANCE * 1e3:g} mm and {ANGLE_TOLERANCE_DEG:g} deg"
    lines = [
        title,
        f"  base: {base}",
        f"  reach map: {int(map_ok.sum())}/{len(map_ok)} grid entries {tolerance}",
        f"  random requests: {int(ok.sum())}/{n} achieved {tolerance} = {ok.mean():.4f}",
        "  by entry point: " + ", ".join(f"{yname[k]} {ok[ybin == k].mean():.3f}" for k in range(n_y)
                                         if (ybin == k).any()),
        "  by probe direction (lean +x: the probe points down towards +x):",
    ]
    for label in (name for name in lean_names(scene) if (leans == name).any()):
        count = int((leans == label).sum())
        lines.append(f"    {label}: {ok[leans == label].mean():.3f} of {count} request{'s' * (count != 1)}")
    misses = np.flatnonzero(~ok)
    if not len(misses):
        lines.append("  every request was achieved")
        return "\n".join(lines)
    regions: dict[tuple[int, str], Counter] = {}
    for i, reason in zip(misses, result.reasons or ["not diagnosed"] * len(misses)):
        regions.setdefault((int(ybin[i]), str(leans[i])), Counter())[reason] += 1
    lines.append(f"  where it fails ({len(misses)} of {n} requests), and why:")
    ranked = sorted(regions.items(), key=lambda item: -sum(item[1].values()))
    for (k, lean), reasons in ranked[:max_rows]:
        total = int(((ybin == k) & (leans == lean)).sum())
        why = "; ".join(f"{reason} ({count})" for reason, count in reasons.most_common())
        lines.append(f"    {yname[k]}, {lean}: {sum(reasons.values())} of {total} missed - {why}")
    if len(ranked) > max_rows:
        lines.append(f"    ... and {len(ranked) - max_rows} more regions")
    return "\n".join(lines)


# -- base placement -------------------------------------------------------------------------------
def default_candidates() -> list[BasePlacement]:
    """Coarse grid of bases beside the probe line (x > 0 covers both sides: the request space is symmetric
    under a half turn about the line's vertical). Tilted mounts are included: an upright 7-DOF arm cannot cover
    both the steep probes near its base and the outward-leaning ones at the line's ends (joint limits)."""
    return [BasePlacement(x, 0.0, z, tilt, yaw) for x in (0.2, 0.3, 0.4, 0.5, 0.6) for z in (0.2, 0.4, 0.6, 0.8)
            for tilt in (0.0, 30.0, 60.0, 90.0) for yaw in (0.0, 180.0)]


def neighbours(base: BasePlacement) -> list[BasePlacement]:
    """Half-steps of the coarse grid around a candidate, one coordinate at a time."""
    steps = {"x": 0.05, "z": 0.1, "tilt_deg": 15.0, "yaw_deg": 45.0}
    found = []
    for name, step in steps.items():
        for sign in (-1, 1):
            value = getattr(base, name) + sign * step
            if name == "tilt_deg" and not 0.0 <= value <= 90.0:
                continue
            found.append(BasePlacement(**{**base.__dict__, name: round(value, 4)}))
    return found


@dataclass
class Candidate:
    """A base placement with its coarse reach-map score and, once verified, its reach over random requests."""

    base: BasePlacement
    map_score: float
    verified: float | None = None


def _with_base(robot: yourdfpy.Robot, base: BasePlacement, path: Path) -> Path:
    placed = copy.deepcopy(robot)
    set_base(placed, base)
    write_urdf(placed, path)
    return path


def score_bases(robot: yourdfpy.Robot, bases: list[BasePlacement], scene: Scene, workdir: Path,
                seed: int = 0) -> list[Candidate]:
    """Share of a coarse reach map's grid entries each base achieves (ProbeArm's own map builder)."""
    scored = []
    for base in bases:
        path = _with_base(robot, base, workdir / "candidate.urdf")
        with BulletClient() as client:
            arm = ProbeArm(client, path, scene, TOOL_LINK, grid=SEARCH_GRID, seed=seed)
            scored.append(Candidate(base, float(achieved(arm.map_error).mean())))
    return scored


def _by_map(candidate: Candidate) -> tuple:
    return (-candidate.map_score, candidate.base.tilt_deg, candidate.base.z)


def _by_reach(candidate: Candidate) -> tuple:
    """Best verified reach first; on a tie the least tilted mount, then the better map."""
    return (-(candidate.verified if candidate.verified is not None else -1.0), candidate.base.tilt_deg,
            -candidate.map_score, candidate.base.z)


def search_base(robot: yourdfpy.Robot, scene: Scene, candidates: list[BasePlacement] | None = None,
                n_check: int = 500, verify_top: int = 4, refine: bool = True, seed: int = 0,
                log: Callable[[str], None] = lambda _: None) -> list[Candidate]:
    """Coarse search scored by reach maps, a local refinement around the best, then the top few (and the best
    upright base) verified with random requests through ProbeArm.reach. Returns candidates, best first.
    `robot` should be a kinematic copy (fast to load)."""
    bases = candidates if candidates is not None else default_candidates()
    with tempfile.TemporaryDirectory(prefix="hg-swap-") as tmp:
        workdir = Path(tmp)
        scored = sorted(score_bases(robot, bases, scene, workdir, seed), key=_by_map)
        log(f"scored {len(scored)} base candidates on a {SEARCH_GRID.n_y}x{SEARCH_GRID.n_dir}x{SEARCH_GRID.n_dir} "
            f"reach map; best map score {scored[0].map_score:.3f}")
        if refine and len(scored) > 1:
            seen = {c.base for c in scored}
            extra = list(dict.fromkeys(b for c in scored[:3] for b in neighbours(c.base) if b not in seen))
            scored = sorted(scored + score_bases(robot, extra, scene, workdir, seed), key=_by_map)
            log(f"refined with {len(extra)} neighbours; best map score {scored[0].map_score:.3f}")
        upright = [c for c in scored if c.base.tilt_deg == 0.0][:1]
        for candidate in scored[:verify_top] + [c for c in upright if c not in scored[:verify_top]]:
            path = _with_base(robot, candidate.base, workdir / "verify.urdf")
            candidate.verified = measure_reach(path, scene, n_check, seed + 1, diagnose=False).fraction
            log(f"  verified {candidate.base}: map {candidate.map_score:.3f}, "
                f"{n_check} random requests {candidate.verified:.4f}")
    return sorted(scored, key=_by_reach)


# -- the whole swap ---------------------------------------------------------------------------------
def fk_gap(urdf: str | Path, n_random: int = 3, seed: int = 0, link: str = TOOL_LINK) -> float:
    """Largest distance between yourdfpy's and PyBullet's world position of `link`, at the zero configuration and
    at `n_random` random ones within the joint limits: both must read the file the same way."""
    model = yourdfpy.URDF.load(str(urdf), build_scene_graph=True, load_meshes=False,
                               filename_handler=yourdfpy.filename_handler_null)
    rng = np.random.default_rng(seed)
    gap = 0.0
    with BulletClient() as client:
        body, index = load_robot(client, urdf, link)
        joints = {client.getJointInfo(body, j)[1].decode(): client.getJointInfo(body, j) for j in
                  range(client.getNumJoints(body))}
        names = model.actuated_joint_names
        for k in range(n_random + 1):
            q = [0.0 if k == 0 else rng.uniform(*((joints[n][8], joints[n][9]) if joints[n][8] < joints[n][9]
                                                  else (-math.pi, math.pi))) for n in names]
            for name, value in zip(names, q):
                client.resetJointState(body, joints[name][0], value)
            model.update_cfg(np.array(q))
            expected = model.get_transform(link, model.base_link)[:3, 3]
            actual = np.array(client.getLinkState(body, index, computeForwardKinematics=True)[4])
            gap = max(gap, float(np.linalg.norm(actual - expected)))
    return gap


@dataclass
class SwapResult:
    """What a swap produced: the file, where its base stands, how well it reaches, and the report to print."""

    out: Path
    tool_link: str
    joints: int  # movable joints between the root and the tool link
    base: BasePlacement
    reach: ReachResult
    mesh_bytes: int
    report: str

    def summary(self) -> dict:
        """The script's last line: what a caller needs to use or check the new robot."""
        return {"reach_fraction": round(self.reach.fraction, 4), "n_requests": len(self.reach.ok),
                "base_position": [round(v, 4) + 0.0 for v in (self.base.x, self.base.y, self.base.z)],
                "base_rpy_deg": self.base.rpy_deg(), "tool_link": self.tool_link, "joints": self.joints,
                "out": str(self.out)}


def swap_robot(source: str | Path, out: str | Path, tool_link: str | None = None, base: BasePlacement | None = None,
               candidates: list[BasePlacement] | None = None, scene: Scene = Scene(), visuals: str = "copy",
               mount: float | None = None, n_verify: int = 2000, n_check: int = 500, min_reach: float = 0.5,
               seed: int = 0, generator: str = "hg.sim.urdf_tools.swap_robot",
               log: Callable[[str], None] = lambda _: None) -> SwapResult:
    """Attach the probe, place the base (given, or the best of a search), write `out` with its meshes, check that
    it loads, and measure its reach. Raises ValueError / FileNotFoundError naming the file and the fault."""
    if visuals not in VISUALS:
        raise ValueError(f"visuals={visuals!r}: expected one of {VISUALS}")
    path, out = resolve_urdf(source), Path(out)
    urdf = load_urdf(path)
    robot = urdf.robot
    tool = pick_tool_link(robot, path, tool_link)
    check_chain(robot, path, tool)
    check_meshes(robot, path)
    offset = mount_offset(urdf, path, tool) if mount is None else mount
    attach_probe(robot, tool, offset)
    log(f"{path}: tool link {tool}, probe rod mounted {offset:.4f} m along its +z")

    bases = [base] if base is not None else candidates if candidates is not None else default_candidates()
    spans = [span_fraction(robot, b, scene, n_check, seed + 1) for b in bases]
    if max(spans) < min_reach:  # certain without any IK: requests beyond the arm's span are never reached
        name, bound = reach_bound(robot)
        raise ValueError(f"robot URDF {path}: the arm cannot reach the probe line: at most {max(spans):.3f} of "
                         f"{n_check} random requests lie within its span ({bound:.2f} m from {name}), below "
                         f"--min-reach {min_reach}")
    if base is None:
        ranked = search_base(kinematic_copy(robot), scene, [b for b, f in zip(bases, spans) if f >= min_reach],
                             n_check, seed=seed, log=log)
        base = ranked[0].base
        if ranked[0].verified < min_reach:
            raise ValueError(f"robot URDF {path}: the arm cannot reach the probe line: the best base ({base}) "
                             f"achieves {ranked[0].verified:.3f} of {n_check} random requests, below --min-reach "
                             f"{min_reach}")

    if visuals == "collision":
        use_collision_visuals(robot)
    set_base(robot, base)
    mesh_bytes = copy_meshes(robot, path, out)
    made = (f"generated by {generator} from {source}: {tool} carries a {ROD_LENGTH} m probe rod ending in "
            f"{TOOL_LINK}; base at {base}. The notices below come from the source file.")
    write_urdf(robot, out, [made, *source_notices(path)])
    gap = fk_gap(out)
    if gap > 1e-4:
        raise ValueError(f"robot URDF {out}: yourdfpy and PyBullet disagree on {TOOL_LINK} by {gap:.2e} m")
    log(f"wrote {out} ({out.stat().st_size / 1e3:.1f} kB, meshes {mesh_bytes / 1e6:.2f} MB in "
        f"{out.parent / 'meshes' / out.stem}); PyBullet loads it")

    reach = measure_reach(out, scene, n_verify, seed + 2)
    title = f"Reach report for {out} ({tool} + {ROD_LENGTH} m probe rod), {n_verify} random requests:"
    joints = movable_joints(robot, tool)
    result = SwapResult(out, tool, joints, base, reach, mesh_bytes, reach_report(reach, scene, title, base))
    if reach.fraction < min_reach:
        log(result.report)
        out.unlink()
        shutil.rmtree(out.parent / "meshes" / out.stem, ignore_errors=True)
        raise ValueError(f"robot URDF {path}: the arm cannot reach the probe line: with the base at {base} it "
                         f"achieves {reach.fraction:.3f} of {n_verify} random requests, below --min-reach {min_reach}")
    return result
