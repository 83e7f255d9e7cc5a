"""Simulator tests on real PyBullet ray casts and the real probe arm, at small sizes."""
import math

import numpy as np
import pytest
import trimesh

from hg.sim import PoseRegions, ProbeSimulator, Scene, SensorNoise, kernels, sample_episodes
from hg.sim.client import BulletClient, OBJECT_GROUP
from hg.sim.objects import hg4, load_folder
from hg.sim.poses import quaternions, rotation_matrices
from hg.sim.robot import ReachGrid, achieved, tool_orientations, z_axes

DOWN = np.array([[0.0, 0.0, 0.0, 1.0]])  # py=0 -> y=0, no lean, steepest: straight down at (0, 0, 0)


def at(x=0.0, y=0.0, z=-0.3, rz=0.0):
    return np.array([[x, y, z, 0.0, 0.0, rz]])


@pytest.fixture(scope="module")
def arm_sim():
    with ProbeSimulator(batch_size=8, mode="arm") as sim:
        yield sim


@pytest.mark.parametrize("mode", ["arm", "ideal"])
def test_ray_through_tire_hole_misses_and_rim_hits(mode, arm_sim):
    sim = arm_sim if mode == "arm" else ProbeSimulator(batch_size=8, mode="ideal")
    tire = sim.classes.index("tire")
    sim.reset([tire], at(z=-0.3))
    assert sim.probe(DOWN).points[0, 3] == 0.0
    rim = np.array([[0.15 / 0.4, 0.0, 0.0, 1.0]])  # y = 0.15: the tube's centre line
    point = sim.probe(rim).points[0]
    assert point[3] == 1.0 and point[2] == pytest.approx(-0.25, abs=1e-3)


def test_straight_down_on_box_hits_at_expected_depth(arm_sim):
    box = arm_sim.classes.index("box")
    arm_sim.reset([box], at(x=0.02, y=0.05, z=-0.31, rz=30.0))
    result = arm_sim.probe(np.array([[0.05 / 0.4, 0.0, 0.0, 1.0]]))
    x, y, z, t = result.points[0]
    assert t == 1.0
    assert abs(z - (-0.31 + 0.075)) <= 1e-3  # box is 0.15 tall
    assert abs(y - 0.05) <= 1e-3 and abs(x) <= 1e-3


def test_rays_never_report_arm_or_ground(arm_sim):
    arm_sim.reset([0], at(z=-5.0))  # object far out of reach: whatever is hit would be arm or ground
    rng = np.random.default_rng(1)
    for _ in range(5):
        result = arm_sim.probe(rng.uniform(-1, 1, (1, 4)))
        assert result.points[0, 3] == 0.0
        start = result.entry[0]  # achieved tip is within tolerance of P
        assert np.linalg.norm(result.points[0, :3] - start) == pytest.approx(arm_sim.scene.probe_length, abs=0.006)


def test_tool_orientation_points_the_tool_along_u():
    directions = Scene().request_to_probe(np.random.default_rng(3).uniform(-1, 1, (500, 4)))[1]
    np.testing.assert_allclose(z_axes(tool_orientations(directions)), directions, atol=1e-12)
    np.testing.assert_allclose(tool_orientations(np.array([[0.0, 0.0, -1.0]])), [[1.0, 0.0, 0.0, 0.0]])


def test_arm_reaches_random_requests(arm_sim):
    rng = np.random.default_rng(2)
    entry, direction = arm_sim.scene.request_to_probe(rng.uniform(-1, 1, (1000, 4)))
    tips, axes, errors = arm_sim.arm.reach(entry, direction)
    np.testing.assert_allclose(errors, arm_sim.arm.pose_error(entry, direction, tips, axes))
    assert achieved(errors).mean() >= 0.99


def test_episodes_are_independent_and_in_their_own_frame(arm_sim):
    labels = np.array([arm_sim.classes.index("box"), arm_sim.classes.index("tire")] * 4)
    arm_sim.reset(labels, np.repeat(at(z=-0.3), 8, axis=0))
    points = arm_sim.probe(np.repeat(DOWN, 8, axis=0)).points
    assert (points[0::2, 3] == 1).all() and (points[1::2, 3] == 0).all()
    np.testing.assert_allclose(points[0::2, 2], -0.225, atol=1e-3)


def test_more_than_16384_rays_in_one_batch():
    with BulletClient() as client:
        shape = client.createCollisionShape(client.GEOM_BOX, halfExtents=[1, 1, 0.1])
        body = client.createMultiBody(0, shape, -1, [0, 0, -1])
        client.setCollisionFilterGroupMask(body, -1, OBJECT_GROUP, OBJECT_GROUP)
        n = 20000
        starts = np.column_stack([np.linspace(-2, 2, n), np.zeros(n), np.zeros(n)])
        hit, position = client.cast_rays(starts, starts - [0, 0, 2])
    assert len(hit) == n
    np.testing.assert_array_equal(hit, np.abs(starts[:, 0]) < 1)
    np.testing.assert_allclose(position[hit, 2], -0.9, atol=1e-5)


def test_same_seed_same_probes():
    noise = SensorNoise(position_std=0.002, miss_prob=0.2, false_contact_prob=0.2)
    runs = []
    for seed in (3, 3, 4):
        with ProbeSimulator(batch_size=16, mode="ideal", noise=noise, seed=seed) as sim:
            rng = np.random.default_rng(seed)
            sim.reset(*sample_episodes(PoseRegions(sim.scene), "train", 16, 4, rng))
            runs.append(np.stack([sim.probe(rng.uniform(-1, 1, (16, 4))).points for _ in range(5)]))
    np.testing.assert_array_equal(runs[0], runs[1])
    assert not np.array_equal(runs[0], runs[2])


def test_noise_flips_contacts():
    sim = ProbeSimulator(batch_size=64, mode="ideal", noise=SensorNoise(miss_prob=1.0))
    sim.reset(np.full(64, 1), np.repeat(at(), 64, axis=0))
    result = sim.probe(np.repeat(DOWN, 64, axis=0))
    assert (result.points[:, 3] == 0).all() and (result.clean_points[:, 3] == 1).all()  # what it did touch is kept
    sim.noise = SensorNoise(false_contact_prob=1.0)
    sim.reset(np.full(64, 3), np.repeat(at(), 64, axis=0))  # tire: straight down misses
    result = sim.probe(np.repeat(DOWN, 64, axis=0))
    points = result.points
    assert (points[:, 3] == 1).all() and (points[:, 2] < 0).all() and (points[:, 2] > -0.6).all()
    assert (result.clean_points[:, 3] == 0).all()
    sim.noise = SensorNoise()
    sim.reset(np.full(64, 3), np.repeat(at(), 64, axis=0))
    result = sim.probe(np.repeat(DOWN, 64, axis=0))
    np.testing.assert_array_equal(result.clean_points, result.points)  # no faults: the sensor is the clean one
    # given faults replace the sensor's draws: the same uniforms, the same faults, whatever its random state
    sim.noise = SensorNoise(miss_prob=0.5, false_contact_prob=0.5)
    faults = np.column_stack([np.linspace(0, 0.99, 64), np.full(64, 0.25)])
    sim.reset(np.full(64, 3), np.repeat(at(), 64, axis=0), seed=1)  # misses: false touches where column 0 < 0.5
    first = sim.probe(np.repeat(DOWN, 64, axis=0), faults).points
    sim.reset(np.full(64, 3), np.repeat(at(), 64, axis=0), seed=2)
    np.testing.assert_array_equal(sim.probe(np.repeat(DOWN, 64, axis=0), faults).points, first)
    assert (first[:, 3] == (faults[:, 0] < 0.5)).all()
    np.testing.assert_allclose(first[first[:, 3] == 1, 2], -0.25 * sim.scene.probe_length, atol=1e-9)
    sim.reset(np.full(64, 1), np.repeat(at(), 64, axis=0))  # touches: missed where column 0 < 0.5
    assert (sim.probe(np.repeat(DOWN, 64, axis=0), faults).points[:, 3] == (faults[:, 0] >= 0.5)).all()
    with pytest.raises(ValueError, match=r"faults: expected shape \(64, 2\) with values in \[0, 1\)"):
        sim.probe(np.repeat(DOWN, 64, axis=0), np.ones((64, 2)))


def test_folder_object_set(tmp_path):
    trimesh.creation.box(extents=(0.2, 0.2, 0.1)).export(tmp_path / "slab.stl")
    trimesh.creation.icosphere(radius=0.1).apply_translation([3, 3, 3]).export(tmp_path / "orb.obj")
    objects = load_folder(tmp_path)
    assert objects.names == ("orb", "slab")
    np.testing.assert_allclose(objects.meshes[0].bounds.mean(0), 0, atol=1e-9)  # recentred
    with ProbeSimulator(objects=tmp_path, batch_size=2, mode="ideal") as sim:
        sim.reset([0, 1], np.repeat(at(z=-0.3), 2, axis=0))
        np.testing.assert_allclose(sim.probe(np.repeat(DOWN, 2, axis=0)).points[:, 2], [-0.2, -0.25], atol=1e-3)


def test_request_mapping_stays_inside_limits():
    scene = Scene()
    requests = np.random.default_rng(0).uniform(-1.5, 1.5, (5000, 4))
    entry, direction = scene.request_to_probe(requests)
    assert (entry[:, 0] == scene.probe_x).all() and (entry[:, 2] == 0).all()
    assert entry[:, 1].min() >= -0.4 and entry[:, 1].max() <= 0.4
    np.testing.assert_allclose(np.linalg.norm(direction, axis=1), 1)
    tilt = np.degrees(np.arccos(-direction[:, 2]))
    assert (direction[:, 2] < 0).all() and tilt.max() <= 45 + 1e-9 and tilt.max() > 44
    np.testing.assert_allclose(scene.line_request(entry[:, 1]), np.clip(requests[:, 0], -1, 1))  # the inverse


def test_compiled_probe_arithmetic_equals_the_numpy_it_replaced():
    """hg.sim.kernels does numpy's float64 operations in numpy's order: the same to the bit (the angle error to its
    last bit: numpy's arccos is its own SIMD routine)."""
    rng, scene = np.random.default_rng(4), Scene()
    requests = rng.uniform(-1.5, 1.5, (300, 4))
    entry, u = scene.request_to_probe(requests)
    py, ux, uy, uz = np.clip(requests, -1.0, 1.0).T
    scale = math.tan(math.radians(scene.max_tilt_deg)) * 0.5 * (1.0 - uz) / np.maximum(1.0, np.hypot(ux, uy))
    expected = np.column_stack([ux * scale, uy * scale, -np.ones(len(ux))])
    np.testing.assert_array_equal(u, expected / np.sqrt((expected * expected).sum(axis=1))[:, None])
    np.testing.assert_array_equal(entry[:, 1], -0.4 + (py + 1.0) * (0.5 * 0.8))
    q = np.column_stack([1.0 - u[:, 2], np.zeros(len(u)), u[:, 0], -u[:, 1]])
    np.testing.assert_array_equal(tool_orientations(u), q / np.sqrt((q * q).sum(axis=1))[:, None])
    quats = rng.normal(size=(300, 4))
    x, y, z, w = quats.T
    np.testing.assert_array_equal(z_axes(quats), np.column_stack([2 * (x * z + w * y), 2 * (y * z - w * x),
                                                                  1 - 2 * (x * x + y * y)]))
    tips, axes = entry + rng.normal(0, 0.01, entry.shape), u + rng.normal(0, 0.01, u.shape)
    errors = kernels.pose_errors(entry, u, tips, axes)
    np.testing.assert_array_equal(errors[:, 0], np.sqrt(((tips - entry) ** 2).sum(-1)))
    np.testing.assert_allclose(errors[:, 1], np.degrees(np.arccos(np.clip((axes * u).sum(-1), -1, 1))), rtol=1e-14)
    grid = ReachGrid()
    origin, step, top, strides = grid._frame(scene)
    coords = np.column_stack([entry[:, 1], u[:, :2]])
    np.testing.assert_array_equal(grid.nearest(scene, entry, u),
                                  np.clip(np.rint((coords - origin) / step), 0, top).astype(np.int64) @ strides)
    hit, offsets = rng.random(300) < 0.5, rng.normal(size=(300, 3))
    ends, ray_from, ray_to = kernels.ray_segments(entry, u, 0.6, offsets)
    np.testing.assert_array_equal(ends, entry + 0.6 * u)
    np.testing.assert_array_equal(ray_to, ends + offsets)
    points = kernels.episode_points(hit, ray_from, offsets, ends)
    np.testing.assert_array_equal(points, np.column_stack([np.where(hit[:, None], ray_from - offsets, ends), hit]))


def test_pose_regions_are_disjoint_and_deterministic():
    regions = PoseRegions(Scene(), seed=5)
    rng = np.random.default_rng(0)
    samples = {split: regions.sample(split, 3000, rng) for split in ("train", "val", "test")}
    for index, (split, poses) in enumerate(samples.items()):
        assert (regions.split_of(poses) == index).all(), split
        assert (poses >= Scene().pose_low).all() and (poses <= Scene().pose_high).all()
    train_cells = set(zip(*regions.cell_of(samples["train"])[:2]))
    test_cells = set(zip(*regions.cell_of(samples["test"])[:2]))
    assert test_cells - train_cells, "test must hold object positions never used in training"
    np.testing.assert_array_equal(PoseRegions(Scene(), seed=5).table, regions.table)
    assert not np.array_equal(PoseRegions(Scene(), seed=6).table, regions.table)


def test_vectorised_rotations_match_pybullet():
    import pybullet
    angles = np.random.default_rng(0).uniform(-180, 180, (20, 3))
    expected = np.array([pybullet.getQuaternionFromEuler(np.radians(a).tolist()) for a in angles])
    np.testing.assert_allclose(quaternions(angles), expected, atol=1e-12)
    expected_m = np.array([pybullet.getMatrixFromQuaternion(q) for q in expected]).reshape(-1, 3, 3)
    np.testing.assert_allclose(rotation_matrices(angles), expected_m, atol=1e-12)


def test_sampled_objects_lie_below_ground():
    regions = PoseRegions(Scene())
    poses = regions.sample("train", 500, np.random.default_rng(0))
    rot = rotation_matrices(poses[:, 3:])
    for mesh in hg4().meshes:
        top = (np.einsum("njk,vk->nvj", rot, mesh.vertices)[..., 2] + poses[:, None, 2]).max()
        assert top < 0


# -- bad input --------------------------------------------------------------------------------------
def test_missing_urdf():
    with pytest.raises(FileNotFoundError, match="nope.urdf"):
        ProbeSimulator(robot="nope.urdf", batch_size=1)


def test_urdf_without_probe_tip(tmp_path):
    urdf = tmp_path / "stick.urdf"
    urdf.write_text('<robot name="s"><link name="a"><inertial><mass value="1"/>'
                    '<inertia ixx="1" ixy="0" ixz="0" iyy="1" iyz="0" izz="1"/></inertial></link></robot>')
    with pytest.raises(ValueError, match=r"stick.urdf.*no link named 'probe_tip'"):
        ProbeSimulator(robot=urdf, batch_size=1)


def test_malformed_urdf(tmp_path):
    urdf = tmp_path / "broken.urdf"
    urdf.write_text("<robot><link name='a'>")
    with pytest.raises(ValueError, match="broken.urdf: malformed XML"):
        ProbeSimulator(robot=urdf, batch_size=1)


def test_folder_without_meshes(tmp_path):
    (tmp_path / "readme.txt").write_text("no meshes")
    with pytest.raises(ValueError, match="no .obj or .stl"):
        load_folder(tmp_path)


def test_unknown_object_set():
    with pytest.raises(ValueError, match="objects='hg5'"):
        ProbeSimulator(objects="hg5", batch_size=1, mode="ideal")


def test_empty_and_open_meshes(tmp_path):
    (tmp_path / "empty.obj").write_text("# nothing\n")
    with pytest.raises(ValueError, match="empty.obj"):
        load_folder(tmp_path)
    (tmp_path / "empty.obj").unlink()
    box = trimesh.creation.box()
    box.update_faces(np.arange(len(box.faces)) != 0)
    box.export(tmp_path / "open.stl")
    with pytest.raises(ValueError, match=r"open.stl: mesh is not watertight \(\d+ open edges\)"):
        load_folder(tmp_path)
    (tmp_path / "open.stl").unlink()
    trimesh.creation.box((300.0, 200.0, 150.0)).export(tmp_path / "millimetres.stl")
    with pytest.raises(ValueError, match=r"millimetres.stl: mesh is 300 units across.*scale it by 0.001"):
        load_folder(tmp_path)


def test_ranges_that_put_objects_above_ground():
    with pytest.raises(ValueError, match=r"object_z.*'pipe'.*above ground"):
        ProbeSimulator(scene=Scene(object_z=(-0.3, -0.05)), batch_size=1, mode="ideal")
    with pytest.raises(ValueError, match="object_z"):
        Scene(object_z=(-0.3, 0.1))
    with pytest.raises(ValueError, match="probe_length"):
        Scene(probe_length=0)


def test_non_finite_requests():
    with ProbeSimulator(batch_size=2, mode="ideal") as sim:
        sim.reset([0, 1], np.repeat(at(), 2, axis=0))
        with pytest.raises(ValueError, match="non-finite.*episode 1, component 2"):
            sim.probe(np.array([[0, 0, 0, 1], [0, 0, math.nan, 1]]))
