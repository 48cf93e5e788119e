"""The on-disk cache of a mesh's stable resting poses: same arrays as trimesh computes, robust to a bad cache."""

import numpy as np
import pytest
import trimesh

from ddsgen.scene.stable_poses import stable_poses


@pytest.fixture()
def cache(tmp_path, monkeypatch):
    monkeypatch.setenv("DDSGEN_CACHE_DIR", str(tmp_path))
    return tmp_path / "stable_poses"


def _brick():
    return trimesh.creation.box(extents=(0.10, 0.06, 0.03))


def test_cached_poses_are_trimesh_poses_bit_for_bit(cache):
    mesh = _brick()
    expected_rotations, expected_probabilities = trimesh.poses.compute_stable_poses(mesh, center_mass=mesh.center_mass)
    first = stable_poses(mesh, mesh.center_mass)
    assert len(list(cache.glob("*.npz"))) == 1
    second = stable_poses(mesh, mesh.center_mass)  # read back from the file
    for rotations, probabilities in (first, second):
        np.testing.assert_array_equal(rotations, expected_rotations)
        np.testing.assert_array_equal(probabilities, expected_probabilities)
    # physics: a brick rests most often on its largest faces (the 0.10 x 0.06 ones, thickness 0.03 upright)
    upright = np.abs(second[0][np.argmax(second[1])][:3, :3] @ [0.0, 0.0, 1.0])
    assert np.isclose(upright[2], 1.0, atol=1e-6)


def test_a_different_centre_of_mass_is_another_entry(cache):
    mesh = _brick()
    stable_poses(mesh, mesh.center_mass)
    _, probabilities = stable_poses(mesh, mesh.center_mass + [0.04, 0.0, 0.0])
    assert len(list(cache.glob("*.npz"))) == 2
    _, centred = stable_poses(mesh, mesh.center_mass)
    assert not np.array_equal(np.sort(probabilities), np.sort(centred))


def test_a_corrupt_cache_file_is_recomputed_and_replaced(cache):
    mesh = _brick()
    expected = stable_poses(mesh, mesh.center_mass)
    (path,) = cache.glob("*.npz")
    path.write_bytes(b"not an npz file")
    rotations, probabilities = stable_poses(mesh, mesh.center_mass)
    np.testing.assert_array_equal(rotations, expected[0])
    np.testing.assert_array_equal(probabilities, expected[1])
    with np.load(path) as stored:  # rewritten
        np.testing.assert_array_equal(stored["probabilities"], expected[1])


def test_an_unwritable_cache_still_gives_the_poses(cache):
    cache.parent.mkdir(parents=True, exist_ok=True)
    cache.write_text("a file where the cache folder should be")  # writing under it fails with an OSError
    mesh = _brick()
    rotations, probabilities = stable_poses(mesh, mesh.center_mass)
    assert rotations.shape[1:] == (4, 4) and len(rotations) >= 3
    assert np.isclose(probabilities.sum(), 1.0)
