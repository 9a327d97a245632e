"""Data loading (including bad input) and Laplace-Beltrami spectra."""

import numpy as np
import pytest
import trimesh

from gdvae.data import Mesh, load_dataset, normalize, random_rotations, sample_surface
from gdvae.spectrum import (SpectrumCache, cotangent_laplacian, mesh_spectrum, mixed_voronoi_areas,
                            point_cloud_spectrum, spectral_distance)


def sphere(radius=1.0, subdivisions=4):
    s = trimesh.creation.icosphere(subdivisions=subdivisions, radius=radius)
    return Mesh(np.asarray(s.vertices, float), np.asarray(s.faces))


def test_cotangent_spectrum_of_a_sphere_matches_the_analytic_eigenvalues():
    # On a sphere of radius r the eigenvalues are l(l+1)/r^2 with multiplicity 2l+1.
    radius = 0.5
    values = mesh_spectrum(sphere(radius), 15)
    expected = np.repeat([2, 6, 12], [3, 5, 7]) / radius**2
    np.testing.assert_allclose(values, expected, rtol=0.01)


def test_mass_matrix_sums_to_the_surface_area_and_stiffness_rows_sum_to_zero():
    mesh = sphere()
    stiffness, mass = cotangent_laplacian(mesh)
    assert abs(mixed_voronoi_areas(mesh).sum() - mesh.face_areas().sum()) < 1e-9
    assert abs(mass.diagonal().sum() - mesh.face_areas().sum()) < 1e-9
    assert np.abs(np.asarray(stiffness.sum(axis=1))).max() < 1e-9


def test_point_cloud_spectrum_approximates_the_mesh_spectrum():
    points = sample_surface(sphere(), 3000, np.random.default_rng(0))
    values = point_cloud_spectrum(points, 8)
    np.testing.assert_allclose(values[:3], [2, 2, 2], rtol=0.1)


def test_spectral_distance_is_weyl_weighted():
    a = np.array([1.0, 2.0, 3.0])
    assert spectral_distance(a, a) == 0
    assert spectral_distance(a, a + [3, 0, 0]) == pytest.approx(1.0)  # |3| / 1 / 3
    assert spectral_distance(a, a + [0, 0, 3]) == pytest.approx(1 / 3)  # |3| / 3 / 3


def test_spectrum_cache_round_trip(tmp_path):
    cache = SpectrumCache(tmp_path)
    first = cache.mesh_spectrum(sphere(subdivisions=3), 5)
    assert len(list(tmp_path.iterdir())) == 1
    np.testing.assert_array_equal(first, cache.mesh_spectrum(sphere(subdivisions=3), 5))


def test_dataset_scale_splits_and_sampling(tiny_dataset):
    dataset = load_dataset(tiny_dataset)
    assert len(dataset.meshes) == 36 and dataset.has_ground_truth
    largest = max(np.ptp(normalize(m, dataset.scale).vertices, axis=0).max() for m in dataset.meshes)
    assert largest == pytest.approx(1.0)
    train, test = dataset.indices("train"), dataset.indices("test")
    assert {dataset.items[i].subject for i in train}.isdisjoint({dataset.items[i].subject for i in test})
    points = sample_surface(normalize(dataset.meshes[0], dataset.scale), 500, np.random.default_rng(1))
    assert points.shape == (500, 3) and np.isfinite(points).all()
    rotations = random_rotations(10, np.random.default_rng(2))
    np.testing.assert_allclose(rotations @ rotations.transpose(0, 2, 1), np.broadcast_to(np.eye(3), (10, 3, 3)), atol=1e-12)
    np.testing.assert_allclose(rotations[:, 2, 2], 1.0)  # about the up axis


def test_bad_meshes_are_skipped_with_a_reason_and_counted(tmp_path, caplog):
    good = trimesh.creation.icosphere(subdivisions=2)
    good.export(tmp_path / "good.ply")
    (tmp_path / "corrupt.ply").write_bytes(b"ply\nformat binary_little_endian 1.0\nelement vertex 99999999\n")
    trimesh.Trimesh(np.zeros((3, 3)), [[0, 1, 2]], process=False).export(tmp_path / "degenerate.obj")
    fan = trimesh.Trimesh([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1], [0, -1, 0]],
                          [[0, 1, 2], [0, 1, 3], [0, 1, 4]], process=False)
    fan.export(tmp_path / "nonmanifold.off")
    dataset = load_dataset(tmp_path)
    assert len(dataset.meshes) == 1 and not dataset.has_ground_truth
    assert sum(dataset.rejected.values()) == 3
    assert "non-manifold" in caplog.text and "degenerate" in caplog.text and "corrupt.ply" in caplog.text


def test_a_folder_without_usable_meshes_is_a_clear_error(tmp_path):
    with pytest.raises(ValueError, match="no usable meshes"):
        load_dataset(tmp_path)


def test_the_depth_camera_sees_only_the_nearest_surface_and_adds_depth_noise():
    from gdvae.data import DepthCamera

    def ball(centre, radius):
        s = trimesh.creation.icosphere(subdivisions=4, radius=radius)
        return np.asarray(s.vertices, float) + centre, np.asarray(s.faces)

    # A small ball hidden behind a large one, seen from 3 m along +x (model units = metres).
    (va, fa), (vb, fb) = ball([0.5, 0, 0], 0.3), ball([-0.5, 0, 0], 0.1)
    mesh = Mesh(np.vstack([va, vb]), np.vstack([fa, fb + len(va)]))
    towards = np.array([1.0, 0.0, 0.0])
    rng = np.random.default_rng(0)
    exact = DepthCamera(disparity_sigma=0.0, distance_m=(3.0, 3.0), dense=20000)
    seen = exact.view(sample_surface(mesh, exact.dense, rng), 400, rng, towards, scale=1.0)
    assert seen.shape == (400, 3) and seen.dtype == np.float32
    assert seen[:, 0].min() > 0.45  # the near half of the large ball only
    # Back-face culling alone (the kit's other partial views) keeps the hidden ball's front.
    assert sample_surface(mesh, 2000, rng, facing=towards)[:, 0].min() < -0.4
    radial = lambda p: np.linalg.norm(p - [0.5, 0, 0], axis=1) - 0.3
    assert np.abs(radial(seen)).max() < 0.01
    noisy = DepthCamera(distance_m=(3.0, 3.0)).view(sample_surface(mesh, 20000, rng), 400, rng, towards, scale=1.0)
    # sigma = z^2 * 0.1 / (441.25 * 0.075), about 0.02 m at 2.6 m.
    assert 0.01 < radial(noisy).std() < 0.03
