"""Point clouds of the PointNet / DGCNN baselines: on the posed surface, noise points where they belong."""
import numpy as np
import pytest
import trimesh

from hg.sim import PoseRegions, Scene, load_object_set, sample_episodes
from hg.sim.pointclouds import noisy_point_clouds, pose_volume
from hg.sim.poses import rotation_matrices

OBJECTS = load_object_set("hg4")
SCENE = Scene()


def episodes(n: int, seed: int = 0):
    return sample_episodes(PoseRegions(SCENE), "train", n, len(OBJECTS), np.random.default_rng(seed))


def posed(label: int, pose: np.ndarray) -> trimesh.Trimesh:
    transform = np.eye(4)
    transform[:3, :3] = rotation_matrices(pose[None, 3:])[0]
    transform[:3, 3] = pose[:3]
    return OBJECTS.meshes[label].copy().apply_transform(transform)


def test_clean_points_lie_on_the_posed_surface_of_every_class():
    labels, poses = episodes(24)
    clouds, mask = noisy_point_clouds(SCENE, OBJECTS, labels, poses, 10, 0.0, np.random.default_rng(1))
    assert clouds.shape == (24, 10, 3) and not mask.any()
    assert set(labels.tolist()) == set(range(len(OBJECTS)))
    for i in range(len(labels)):
        distance = np.abs(trimesh.proximity.signed_distance(posed(labels[i], poses[i]), clouds[i]))
        assert distance.max() < 1e-6, (OBJECTS.names[labels[i]], distance.max())


@pytest.mark.parametrize("rate, expected", [(0.1, 1), (0.3, 3), (0.5, 5), (1.0, 10)])
def test_noise_rate_replaces_that_share_of_points_with_pose_volume_points(rate, expected):
    labels, poses = episodes(32)
    clouds, mask = noisy_point_clouds(SCENE, OBJECTS, labels, poses, 10, rate, np.random.default_rng(2))
    assert (mask.sum(1) == expected).all()
    low, high = pose_volume(SCENE, OBJECTS)
    assert ((clouds[mask] >= low) & (clouds[mask] <= high)).all()
    if expected < 10:  # noise takes different places in different clouds
        assert len(np.unique(np.argmax(mask, axis=1))) > 1
    on_surface = [np.abs(trimesh.proximity.signed_distance(posed(labels[i], poses[i]), clouds[i][mask[i]])).min()
                  for i in range(8) if mask[i].any()]
    assert min(on_surface) > 1e-4  # noise points are off the object


def test_pose_volume_holds_every_object_at_extreme_poses():
    low, high = pose_volume(SCENE, OBJECTS)
    corners = np.array([[x, y, z, rx, ry, rz] for x in SCENE.object_x for y in SCENE.object_y for z in SCENE.object_z
                        for rx in SCENE.rot_x_deg for ry in SCENE.rot_y_deg for rz in (0.0, 45.0, 90.0)])
    for label in range(len(OBJECTS)):
        for pose in corners:
            vertices = posed(label, pose).vertices
            assert (vertices >= low - 1e-9).all() and (vertices <= high + 1e-9).all()
    assert high[2] <= 0.0


def test_same_seed_same_clouds_and_bad_rate_is_named():
    labels, poses = episodes(8)
    a = noisy_point_clouds(SCENE, OBJECTS, labels, poses, 10, 0.2, np.random.default_rng(5))[0]
    b = noisy_point_clouds(SCENE, OBJECTS, labels, poses, 10, 0.2, np.random.default_rng(5))[0]
    c = noisy_point_clouds(SCENE, OBJECTS, labels, poses, 10, 0.2, np.random.default_rng(6))[0]
    assert np.array_equal(a, b) and not np.array_equal(a, c)
    with pytest.raises(ValueError, match="noise_rate=1.5"):
        noisy_point_clouds(SCENE, OBJECTS, labels, poses, 10, 1.5, np.random.default_rng(0))
