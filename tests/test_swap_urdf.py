"""Robot swap (scripts/swap_urdf.py, hg.sim.urdf_tools) on real yourdfpy and PyBullet, with small robots."""
import importlib.util
import json
import subprocess
import sys
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np
import pytest
import trimesh
import yourdfpy

from hg.sim.client import BulletClient
from hg.sim.kernels import tool_frames
from hg.sim.robot import (DEFAULT_URDF, TOOL_LINK, ProbeArm, ReachGrid, kinematic_chain, load_robot,
                          tool_orientations)
from hg.sim.scene import Scene
from hg.sim.urdf_tools import (BasePlacement, attach_probe, kinematic_copy, load_urdf, pick_tool_link, resolve_urdf,
                               search_base, set_base, swap_robot)

ROOT = Path(__file__).resolve().parents[1]
SCRIPT = ROOT / "scripts" / "swap_urdf.py"
COMMITTED = [ROOT / "urdf" / "kuka_iiwa_probe.urdf", ROOT / "urdf" / "franka_panda_probe.urdf", DEFAULT_URDF]
OUR_BASE = BasePlacement(0.45, 0.0, 0.25)  # where urdf/hg_probe_arm.urdf stands
ROBOTS = ROOT / "tests" / "data" / "robots"  # vendor-style structures, written by make_robots.py there


def load_script():
    spec = importlib.util.spec_from_file_location("swap_urdf", SCRIPT)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@pytest.fixture(autouse=True)
def fresh_reach_cache(tmp_path, monkeypatch):
    monkeypatch.setenv("HG_CACHE_DIR", str(tmp_path / "cache"))


def bare_arm(path: Path, mesh: bool = False) -> Path:
    """Our 6-DOF arm without its world mount and probe: a robot as a vendor would ship it (leaf: flange_link)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    root = ET.parse(DEFAULT_URDF).getroot()
    for element in list(root):
        if element.get("name") in {"world", "world_to_base", "probe_rod", "probe_mount", TOOL_LINK, "probe_tip_joint"}:
            root.remove(element)
    if mesh:
        (path.parent / "parts").mkdir(exist_ok=True)
        trimesh.creation.box((0.1, 0.1, 0.1)).export(path.parent / "parts" / "cover.stl")
        visual = root.find("link[@name='shoulder_link']/visual/geometry")
        visual.remove(visual[0])
        ET.SubElement(visual, "mesh", filename="parts/cover.stl")
    ET.ElementTree(root).write(path)
    return path


def tiny_arm(path: Path, branches: int = 1) -> Path:
    """Two joints, 0.1 m links: it cannot reach a probe line 0.8 m long. With two branches, two such arms share
    the root link (a two-armed robot: no tool link to guess)."""
    inertial = ('<inertial><mass value="0.1"/><inertia ixx="1e-4" ixy="0" ixz="0" iyy="1e-4" iyz="0" izz="1e-4"/>'
                '</inertial>')
    names = ["l0"] + [f"l{i}{b}" for b in "ab"[:branches] for i in (1, 2)]
    links = "".join(f'<link name="{name}">{inertial}</link>' for name in names)
    joints = "".join(f'<joint name="j{child}" type="revolute"><parent link="{parent}"/><child link="{child}"/>'
                     f'<origin xyz="0 0 0.1"/><axis xyz="0 1 0"/><limit lower="-1" upper="1" effort="1" velocity="1"/>'
                     f'</joint>' for b in "ab"[:branches] for parent, child in (("l0", f"l1{b}"), (f"l1{b}", f"l2{b}")))
    path.write_text(f'<robot name="tiny">{links}{joints}</robot>')
    return path


# -- the committed robots ---------------------------------------------------------------------------
@pytest.mark.parametrize("urdf", COMMITTED, ids=lambda p: p.stem)
def test_probe_tip_fk_agrees_between_yourdfpy_and_pybullet(urdf):
    model = yourdfpy.URDF.load(str(urdf), build_scene_graph=True, load_meshes=False)
    rng = np.random.default_rng(0)
    with BulletClient() as client:
        body, tip = load_robot(client, urdf)
        index = {client.getJointInfo(body, j)[1].decode(): j for j in range(client.getNumJoints(body))}
        for _ in range(5):
            q = {}
            for name in model.actuated_joint_names:
                info = client.getJointInfo(body, index[name])
                low, high = (info[8], info[9]) if info[8] < info[9] else (-np.pi, np.pi)
                q[name] = float(rng.uniform(low, high))
                client.resetJointState(body, index[name], q[name])
            model.update_cfg(np.array([q[name] for name in model.actuated_joint_names]))
            expected = model.get_transform(TOOL_LINK, model.base_link)
            state = client.getLinkState(body, tip, computeForwardKinematics=True)
            axis = np.array(client.getMatrixFromQuaternion(state[5])).reshape(3, 3)[:, 2]
            assert np.linalg.norm(np.array(state[4]) - expected[:3, 3]) <= 1e-4
            assert np.linalg.norm(axis - expected[:3, 2]) <= 1e-4
            # the simulator's own chain (ProbeArm.place reads achieved poses from it): PyBullet's to 1e-6
            movable = [n for n, j in index.items() if client.getJointInfo(body, j)[2] in (0, 1)]  # revolute, prismatic
            chain = kinematic_chain(urdf, TOOL_LINK, sorted(movable, key=index.get))
            tips, axes = tool_frames(np.array([[q[n] for n in sorted(movable, key=index.get)]]), *chain)
            assert np.abs(tips[0] - state[4]).max() <= 1e-6 and np.abs(axes[0] - axis).max() <= 1e-6


def test_a_tool_link_behind_a_joint_an_arm_cannot_have_is_refused(tmp_path):
    path = tmp_path / "planar.urdf"
    link = ('<link name="{}"><inertial><mass value="1"/><inertia ixx="1" ixy="0" ixz="0" iyy="1" iyz="0" izz="1"/>'
            '</inertial></link>')
    path.write_text(f'<robot name="p">{link.format("base")}{link.format(TOOL_LINK)}<joint name="slide" type="planar">'
                    f'<parent link="base"/><child link="{TOOL_LINK}"/><axis xyz="0 0 1"/></joint></robot>')
    with pytest.raises(ValueError, match=r"planar.urdf: the chain to 'probe_tip' has joints an arm cannot have: 'sl"):
        kinematic_chain(path, TOOL_LINK, [])


@pytest.mark.parametrize("urdf", COMMITTED[:2], ids=lambda p: p.stem)
def test_committed_urdf_follows_our_conventions(urdf):
    robot = load_urdf(urdf).robot
    joints = {j.name: j for j in robot.joints}
    assert joints["world_to_base"].parent == "world" and joints["world_to_base"].type == "fixed"
    tip = next(link for link in robot.links if link.name == TOOL_LINK)
    assert np.allclose(tip.inertial.origin, np.eye(4))  # rays from the tip frame need no inertial offset
    meshes = [e.geometry.mesh.filename for link in robot.links for e in link.visuals + link.collisions
              if e.geometry.mesh is not None]
    assert meshes and all(not Path(m).is_absolute() and (urdf.parent / m).is_file() for m in meshes)
    assert sum((urdf.parent / m).stat().st_size for m in set(meshes)) < 1_500_000  # small enough to commit
    licence = {"kuka_iiwa_probe": "Copyright (c) 2015, Robert Krug", "franka_panda_probe": "Apache License"}[urdf.stem]
    notices = urdf.read_text() + "".join(f.read_text() for f in (urdf.parent / "meshes" / urdf.stem).glob("LICENSE*"))
    assert licence in notices  # the vendor's licence travels with its meshes


# -- swapping ---------------------------------------------------------------------------------------
def test_swap_small_robot_writes_a_loadable_urdf_with_probe_tip_and_copied_meshes(tmp_path):
    source = bare_arm(tmp_path / "vendor" / "arm.urdf", mesh=True)
    out = tmp_path / "urdf" / "small_probe.urdf"
    result = swap_robot(source, out, base=OUR_BASE, n_check=100, n_verify=300)
    assert result.tool_link == "flange_link"  # the only leaf
    assert (out.parent / "meshes" / "small_probe" / "cover.stl").is_file()
    assert 'filename="meshes/small_probe/cover.stl"' in out.read_text()
    with BulletClient() as client:
        body, tip = load_robot(client, out)
        assert client.getJointInfo(body, tip)[12].decode() == TOOL_LINK
    summary = json.loads(json.dumps(result.summary()))
    assert summary["base_position"] == [0.45, 0.0, 0.25] and summary["out"] == str(out)
    assert summary["reach_fraction"] >= 0.97  # the same arm as urdf/hg_probe_arm.urdf


@pytest.mark.parametrize("source, tool", [("ros_arm/urdf/ros_arm.urdf", "tool0"), ("gripper_arm.urdf", "hand")])
def test_vendor_structures_swap_with_no_options_and_reach(tmp_path, source, tool):
    """ros_arm: xacro output rooted at `world`, package:// meshes, continuous and in-chain fixed joints;
    gripper_arm: root `base`, mimic fingers and a grasp frame as leaves, no link called a tool."""
    out = tmp_path / "arm_probe.urdf"
    result = swap_robot(ROBOTS / source, out, base=OUR_BASE, n_check=100, n_verify=200)
    assert result.tool_link == tool and result.joints == 6
    assert result.reach.fraction >= 0.95  # the same kinematics as urdf/hg_probe_arm.urdf
    robot = load_urdf(out).robot
    base = [j for j in robot.joints if j.parent == "world"]
    assert len(base) == 1 and base[0].name == "world_to_base" and base[0].type == "fixed"
    assert [link.name for link in robot.links].count("world") == 1
    types = {j.name: j.type for j in robot.joints}
    if source.startswith("ros_arm"):
        assert types["joint_4"] == types["joint_6"] == "continuous" and types["forearm_fixed"] == "fixed"
        assert 'filename="meshes/arm_probe/shoulder.stl"' in out.read_text()
        assert (tmp_path / "meshes" / "arm_probe" / "shoulder.stl").is_file()
    else:
        assert next(j for j in robot.joints if j.name == "finger_right_joint").mimic.joint == "finger_left_joint"


@pytest.mark.parametrize("source, tool, root", [("xarm/xarm6_robot.urdf", "link6", "link_base"),
                                                ("xarm/xarm6_with_gripper.urdf", "xarm_gripper_base_link", "link_base"),
                                                ("franka_panda/panda.urdf", "panda_hand", "panda_link0")])
def test_pybullet_data_arms_get_a_tool_link_and_a_base_joint(source, tool, root):
    """xArm roots itself at `world` (its joint becomes ours); grippers leave several leaves (their hand is taken)."""
    path = resolve_urdf(source)
    robot = load_urdf(path).robot
    assert pick_tool_link(robot, path) == tool
    set_base(robot, OUR_BASE)
    base = [j for j in robot.joints if j.name == "world_to_base"]
    assert len(base) == 1 and base[0].parent == "world" and base[0].child == root
    assert np.allclose(base[0].origin, OUR_BASE.matrix())


def test_search_picks_the_base_that_reaches(tmp_path):
    robot = load_urdf(bare_arm(tmp_path / "arm.urdf")).robot
    attach_probe(robot, "flange_link", 0.02)
    far = BasePlacement(1.6, 0.0, 0.25)
    ranked = search_base(kinematic_copy(robot), Scene(), [far, OUR_BASE], n_check=100, verify_top=1, refine=False)
    assert ranked[0].base == OUR_BASE and ranked[0].verified >= 0.95
    assert ranked[1].base == far and ranked[1].map_score < ranked[0].map_score


def test_cli_prints_report_and_json_last(tmp_path, capsys):
    source = bare_arm(tmp_path / "arm.urdf")
    out = tmp_path / "arm_probe.urdf"
    code = load_script().main([str(source), "--out", str(out), "--base", "0.45", "0", "0.25", "--n-verify", "200"])
    lines = capsys.readouterr().out.strip().splitlines()
    assert code == 0
    assert any(line.startswith("Reach report") for line in lines) and any("by entry point" in line for line in lines)
    last = json.loads(lines[-1])
    assert set(last) >= {"reach_fraction", "base_position", "out"} and last["out"] == str(out)


def test_arm_below_min_reach_fails_with_its_fraction_and_reports_where_and_why(tmp_path):
    log = []
    fault = r"cannot reach the probe line: .* achieves 0\.\d{3} of 150 random requests, below --min-reach 0\.9"
    with pytest.raises(ValueError, match=fault):
        swap_robot(bare_arm(tmp_path / "arm.urdf"), tmp_path / "far_probe.urdf", base=BasePlacement(0.85, 0.0, 0.25),
                   n_verify=150, min_reach=0.9, log=log.append)
    assert not (tmp_path / "far_probe.urdf").exists() and not (tmp_path / "meshes" / "far_probe").exists()
    failing = [line for line in "\n".join(log).splitlines() if " missed - " in line]
    assert failing and all(line.strip().startswith("y in [") for line in failing)  # which part of the line
    assert any("lean +x" in line for line in failing)  # which tilt directions: leaning away from the base
    reasons = ("limit of joint_", "beyond", "out of reach", "not along this direction")
    assert all(any(reason in line for reason in reasons) for line in failing)  # why


# -- errors -----------------------------------------------------------------------------------------
def error_case(kind: str, tmp_path: Path) -> tuple[list[str], type, list[str]]:
    """(command-line arguments, exception type, fragments the message must contain) for each fault."""
    out = ["--out", str(tmp_path / "out_probe.urdf"), "--n-check", "100", "--n-verify", "100"]
    if kind == "malformed":
        bad = tmp_path / "broken.urdf"
        bad.write_text("<robot name='x'><link name='a'>")
        return [str(bad)] + out, ValueError, [str(bad), "malformed XML"]
    if kind == "missing_tool":
        return ["kuka_iiwa/model.urdf", "--tool-link", "nope"] + out, ValueError, ["model.urdf", "no link named 'nope'"]
    if kind == "ambiguous":
        source = tiny_arm(tmp_path / "two_arms.urdf", branches=2)
        return [str(source)] + out, ValueError, [str(source), "separate branches", "l2a, l2b"]
    if kind == "mimic_in_chain":
        return [str(ROBOTS / "mimic_wrist.urdf")] + out, ValueError, [
            "mimic_wrist.urdf", "joint 'joint_6'", "mimics 'joint_4'", "--tool-link 'wrist_link'"]
    if kind == "floating_world":
        return [str(ROBOTS / "floating_world.urdf")] + out, ValueError, [
            "floating_world.urdf", "floating joint 'world_joint'", "make one joint fixed"]
    if kind == "xacro":
        return [str(ROBOTS / "xacro_arm.urdf.xacro")] + out, ValueError, ["xacro_arm.urdf.xacro", "xacro file",
                                                                          "xacrodoc"]
    if kind == "xacro_named_urdf":  # found by its xacro elements and ${...}, not by its name
        source = tmp_path / "arm.urdf"
        source.write_text((ROBOTS / "xacro_arm.urdf.xacro").read_text())
        return [str(source)] + out, ValueError, [str(source), "xacro file", "xacrodoc"]
    if kind == "missing_mesh":
        source = bare_arm(tmp_path / "arm.urdf", mesh=True)
        (tmp_path / "parts" / "cover.stl").unlink()
        return [str(source)] + out, FileNotFoundError, [str(source), "parts/cover.stl", "not found"]
    if kind == "unreachable":
        source = tiny_arm(tmp_path / "tiny.urdf")
        return [str(source), "--base", "0.3", "0", "0.2"] + out, ValueError, [str(source), "cannot reach", "0.000",
                                                                                  "--min-reach 0.5"]
    raise AssertionError(kind)


KINDS = ["malformed", "missing_tool", "ambiguous", "missing_mesh", "unreachable", "mimic_in_chain", "floating_world",
         "xacro", "xacro_named_urdf"]


@pytest.mark.parametrize("kind", KINDS)
def test_errors_name_the_file_and_the_fault(kind, tmp_path):
    args, error, fragments = error_case(kind, tmp_path)
    script = load_script()
    with pytest.raises(error) as info:
        script.run(script.parse_args(args))
    message = str(info.value)
    assert all(fragment in message for fragment in fragments), message
    assert "\n" not in message
    assert not (tmp_path / "out_probe.urdf").exists()


@pytest.mark.parametrize("kind", KINDS)
def test_cli_errors_are_one_line_and_exit_non_zero(kind, tmp_path, capsys):
    args, _, fragments = error_case(kind, tmp_path)
    assert load_script().main(args) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("swap_urdf.py: error: ") and len(err.splitlines()) == 1 and fragments[-1] in err


def test_cli_error_in_a_fresh_process_has_no_traceback(tmp_path):
    args, _, fragments = error_case("malformed", tmp_path)
    done = subprocess.run([sys.executable, str(SCRIPT), *args], capture_output=True, text=True, timeout=60)
    assert done.returncode == 2
    assert "Traceback" not in done.stderr and fragments[-1] in done.stderr


def test_a_joint_that_turns_without_limit_is_wrapped_not_clipped(tmp_path):
    """An IK solution a turn or more away on a continuous joint is the same pose: the arm must keep it, not clip it."""
    root = ET.parse(DEFAULT_URDF).getroot()
    joint = root.find("joint[@name='joint_4']")
    joint.set("type", "continuous")
    for bound in ("lower", "upper"):  # a continuous joint has none
        joint.find("limit").attrib.pop(bound)
    urdf = tmp_path / "continuous.urdf"
    ET.ElementTree(root).write(urdf)
    with BulletClient() as client:
        arm = ProbeArm(client, urdf, Scene(), grid=ReachGrid(n_y=5, n_dir=5))
        column = arm.joint_names.index("joint_4")
        assert arm.wraps.tolist() == [name == "joint_4" for name in arm.joint_names]
        points, dirs = arm.grid_targets
        orients = tool_orientations(dirs)
        starts = arm.map_q.copy()
        q, tips, axes = arm.place(points, orients, starts, arm.ik_iterations)
        starts[:, column] += 4 * np.pi  # two turns on: IK stays near its start, beyond the +-2 pi bounds
        raw = client.calculateInverseKinematics(arm.body, arm.tool, points[0].tolist(), orients[0].tolist(),
                                                currentPositions=starts[0].tolist(), jointDamping=arm.damping,
                                                maxNumIterations=arm.ik_iterations)
        assert abs(raw[column]) > 2 * np.pi  # what clipping would have cut
        q_far, tips_far, axes_far = arm.place(points, orients, starts, arm.ik_iterations)
    assert np.abs(q_far[:, column]).max() <= np.pi
    assert np.abs(tips_far - tips).max() <= 1e-4 and np.abs(axes_far - axes).max() <= 1e-4
