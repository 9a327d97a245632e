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


def test_the_sims_binary_ply_is_read_directly_and_other_layouts_by_trimesh(tmp_path):
    from gdvae.data import read_mesh, read_simple_ply

    shape = trimesh.creation.icosphere(subdivisions=2)
    vertices = np.asarray(shape.vertices, np.float32)
    faces = np.asarray(shape.faces, np.int32)
    # The sim's layout (sim/src/ply.rs): float x y z, uchar-counted int triangles.
    header = (f"ply\nformat binary_little_endian 1.0\ncomment gdvae-sim test\nelement vertex {len(vertices)}\n"
              "property float x\nproperty float y\nproperty float z\n"
              f"element face {len(faces)}\nproperty list uchar int vertex_indices\nend_header\n").encode()
    records = np.zeros(len(faces), np.dtype([("n", "u1"), ("corners", "<i4", 3)]))
    records["n"], records["corners"] = 3, faces
    path = tmp_path / "sim.ply"
    path.write_bytes(header + vertices.astype("<f4").tobytes() + records.tobytes())
    direct = read_simple_ply(path)
    assert direct is not None
    np.testing.assert_array_equal(direct.vertices, vertices.astype(np.float64))
    np.testing.assert_array_equal(direct.faces, faces)
    parsed = trimesh.load(path, force="mesh", process=False)
    np.testing.assert_array_equal(direct.vertices, np.asarray(parsed.vertices, np.float64))
    # A quad among the triangles, an ASCII file and a truncated file are not the simple layout;
    # read_mesh hands them to trimesh (which reads the ASCII one and rejects the truncated one).
    quad = records.copy()
    quad["n"][0] = 4
    (tmp_path / "quad.ply").write_bytes(header + vertices.astype("<f4").tobytes() + quad.tobytes())
    assert read_simple_ply(tmp_path / "quad.ply") is None
    shape.export(tmp_path / "ascii.ply", encoding="ascii")
    assert read_simple_ply(tmp_path / "ascii.ply") is None
    assert len(read_mesh(tmp_path / "ascii.ply").faces) == len(faces)
    (tmp_path / "short.ply").write_bytes(path.read_bytes()[:-5])
    assert read_simple_ply(tmp_path / "short.ply") is None
