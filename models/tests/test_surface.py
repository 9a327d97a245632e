"""Training clouds made by tensor operations (gdvae.surface): area weighting against the NumPy
reference sampler, the depth camera's visibility and noise, camera-facing samples, and the
sampler's layout and seeding."""

import numpy as np
import pytest
import torch
import trimesh

from gdvae.data import DepthCamera, Mesh, sample_surface
from gdvae.surface import MeshCache, PointSampler, depth_camera_views, draw_seen, view_directions


def ball(centre, radius, subdivisions=4):
    s = trimesh.creation.icosphere(subdivisions=subdivisions, radius=radius)
    return np.asarray(s.vertices, float) + centre, np.asarray(s.faces)


def two_balls(large=0.3, small=0.1):
    """A large ball at x = +0.5 and a small one at x = -0.5 (model units = metres)."""
    (va, fa), (vb, fb) = ball([0.5, 0, 0], large), ball([-0.5, 0, 0], small)
    return Mesh(np.vstack([va, vb]), np.vstack([fa, fb + len(va)]))


def test_surface_points_are_area_weighted_as_the_numpy_reference_draws_them(monkeypatch):
    # Two balls of radii 0.3 and 0.1: 90 % of the area is the large one's. Two meshes in one
    # cache, so each mesh's face range and area shares are its own.
    mesh = two_balls()
    wide = Mesh(*ball([0, 0, 0], 1.0, subdivisions=2))
    cache = MeshCache([wide, mesh], scale=1.0)
    assert cache.shares is not None  # one row of shares per mesh
    generator = torch.Generator().manual_seed(0)
    points = cache.sample(torch.tensor([1, 1, 0]), 4000, generator)
    # Meshes of very different sizes share one sequence (rows would hold mostly padding); the same
    # draw either way.
    monkeypatch.setattr(MeshCache, "PADDING_LIMIT", 1.0)
    flat = MeshCache([wide, mesh], scale=1.0)
    assert flat.shares is None and flat.bytes() > 0
    flat_points = flat.sample(torch.tensor([1, 1, 0]), 4000, torch.Generator().manual_seed(0))
    assert abs((flat_points[:2, :, 0] > -0.1).float().mean().item() - 0.9) < 0.02
    assert ((flat_points[2].norm(dim=-1) - 1.0).abs() < 0.05).all()
    assert points.shape == (3, 4000, 3) and points.dtype == torch.float32
    # The cache centres each mesh on its bounding box: the balls sit at x = +0.4 and -0.6.
    on_large = (points[:2, :, 0] > -0.1).float().mean().item()
    reference = sample_surface(mesh, 8000, np.random.default_rng(0))
    assert abs(on_large - 0.9) < 0.02 and abs((reference[:, 0] > 0).mean() - 0.9) < 0.02
    radius = (points[:2] - torch.tensor([0.4, 0, 0])).norm(dim=-1)[points[:2, :, 0] > -0.1]
    assert (radius - 0.3).abs().max() < 0.01  # on the surface, not inside
    assert ((points[2].norm(dim=-1) - 1.0).abs() < 0.05).all()  # the other mesh's points are its own
    # Uniform over the large ball: the mean of the points' directions is near zero.
    assert (points[:2][points[:2, :, 0] > -0.1] - torch.tensor([0.4, 0, 0])).mean(0).norm() < 0.02


def dense_two_balls(views: int, seed: int):
    """`views` dense samples (20,000 points) of `two_balls`, the directions towards a camera on +x,
    the cache and the generator."""
    cache = MeshCache([two_balls()], scale=1.0)
    generator = torch.Generator().manual_seed(seed)
    dense = cache.sample(torch.zeros(views, dtype=torch.long), 20000, generator)
    return dense, torch.tensor([[1.0, 0.0, 0.0]]).expand(views, 3), cache, generator


def test_the_depth_camera_sees_only_the_nearest_surface_and_adds_depth_noise():
    # The small ball hides behind the large one, seen from 3 m along +x.
    dense, towards, cache, generator = dense_two_balls(4, seed=0)
    exact = DepthCamera(disparity_sigma=0.0, distance_m=(3.0, 3.0))
    seen = depth_camera_views(exact, dense, towards, 400, 1.0, generator)
    assert seen.shape == (4, 400, 3) and seen.dtype == torch.float32
    centre = torch.tensor([0.4, 0.0, 0.0])  # the large ball, with the mesh centred on its box
    radial = lambda p: (p - centre).norm(dim=-1) - 0.3
    assert seen[..., 0].min() > 0.35  # the near half of the large ball only
    assert radial(seen).abs().max() < 0.01
    for view in seen:  # drawn without repetition
        assert len(torch.unique(view, dim=0)) == 400
    # Back-face culling alone (the kit's other partial views) keeps the hidden ball's front.
    facing = cache.sample_facing(torch.zeros(4, dtype=torch.long), 2000, towards, generator)
    assert facing[..., 0].min() < -0.5
    noisy = depth_camera_views(DepthCamera(distance_m=(3.0, 3.0)), dense, towards, 400, 1.0, generator)
    # sigma = z^2 * 0.1 / (441.25 * 0.075), about 0.02 m at 2.6 m.
    assert 0.01 < radial(noisy).std() < 0.03
    # Seen from the other side, the small ball is in front.
    behind = depth_camera_views(exact, dense, -towards, 400, 1.0, generator)
    assert (behind[..., 0] < -0.45).float().mean() > 0.05 and behind[..., 0].max() < 0.45


def test_the_depth_edge_dropout_thins_a_thin_leg_and_spares_a_wall_but_its_rim():
    # A wall 1 m square facing the camera at 3 m, and in front of it a post 5 cm wide: the sim's
    # camera drops the pixels whose neighbours lie more than 4 % of their depth away (or nowhere).
    rng = np.random.default_rng(0)
    wall = np.c_[rng.uniform(0.0, 0.002, 60000), rng.uniform(-0.5, 0.5, (60000, 2))]
    post = np.c_[rng.uniform(0.2, 0.25, 6000), rng.uniform(-0.025, 0.025, 6000), rng.uniform(-0.5, 0.5, 6000)]
    dense = torch.tensor(np.concatenate([wall, post])[rng.permutation(66000)], dtype=torch.float32)[None]
    towards = torch.tensor([[1.0, 0.0, 0.0]])
    seen = {}
    for threshold in (0.0, 0.04):
        camera = DepthCamera(disparity_sigma=0.0, distance_m=(3.0, 3.0), dense=66000, edge_threshold=threshold)
        view = depth_camera_views(camera, dense, towards, 12000, 1.0, torch.Generator().manual_seed(1))[0]
        seen[threshold] = torch.unique(view, dim=0)
    on_post = lambda v: (v[:, 0] > 0.1).sum().item()  # noqa: E731
    on_wall = lambda v: (v[:, 0] < 0.1).sum().item()  # noqa: E731
    # The post is about 3.7 pixels wide (at decimation 2): its two edge columns go, and so do the
    # wall's pixels beside it and round its rim; the wall's middle stays.
    assert on_post(seen[0.04]) < 0.6 * on_post(seen[0.0]) and on_post(seen[0.04]) > 0
    assert 0.8 * on_wall(seen[0.0]) < on_wall(seen[0.04]) < on_wall(seen[0.0])


def test_a_view_with_fewer_points_than_asked_repeats_seen_points_only():
    dense, towards, _, generator = dense_two_balls(2, seed=1)
    # About 2,700 of the 20,000 are seen: 6,000 asked are repeats of them.
    seen = depth_camera_views(DepthCamera(disparity_sigma=0.0), dense, towards, 6000, 1.0, generator)
    assert seen.shape == (2, 6000, 3)
    assert seen[..., 0].min() > 0.35  # never the hidden side
    assert 1000 < len(torch.unique(seen[0], dim=0)) < 4000


def test_a_view_with_points_at_the_camera_is_refused():
    # One point 0.1 mm in front of a camera 3 m away on +x, off its axis: its pixel lies about
    # 200,000 pixels out, and a depth buffer that large is refused, not allocated.
    dense = torch.zeros(1, 500, 3)
    dense[0, 0] = torch.tensor([3.0 - 1e-4, 0.1, 0.1])
    with pytest.raises(ValueError, match="at or behind the camera"):
        depth_camera_views(DepthCamera(distance_m=(3.0, 3.0)), dense, torch.tensor([[1.0, 0.0, 0.0]]), 100, 1.0,
                           torch.Generator().manual_seed(0), torch.zeros(1, 3))


def test_seen_points_are_drawn_evenly_and_without_repetition():
    # Row 0 sees one run of 300 points, row 1 every 7th of 1,000 (143): each seen point must be
    # drawn as often as any other, whatever lies before it.
    generator = torch.Generator().manual_seed(0)
    seen = torch.zeros(2, 1000, dtype=torch.bool)
    seen[0, :300] = True
    seen[1, ::7] = True
    drawn = torch.zeros(2, 1000)
    rounds = 2000
    for _ in range(rounds):
        chosen = draw_seen(seen, 100, generator)
        assert chosen.shape == (2, 100) and bool(seen.gather(1, chosen).all())
        assert all(len(row.unique()) == 100 for row in chosen)
        drawn.scatter_add_(1, chosen, torch.ones(chosen.shape))
    for row in range(2):
        share = drawn[row][seen[row]] / rounds  # each seen point's chance: 100 / visible
        assert (share / (100 / int(seen[row].sum())) - 1).abs().max() < 0.2


def test_camera_facing_samples_show_the_viewers_side():
    sphere = Mesh(*ball([0, 0, 0], 1.0, subdivisions=3))
    cache = MeshCache([sphere], scale=1.0)
    generator = torch.Generator().manual_seed(0)
    directions = view_directions(50, generator, cache.device)
    assert torch.allclose(directions.norm(dim=-1), torch.ones(50))
    elevation = torch.rad2deg(torch.asin(directions[:, 2]))
    assert elevation.min() >= 5.0 and elevation.max() <= 40.0
    seen = cache.sample_facing(torch.zeros(5, dtype=torch.long), 500, directions[:5], generator)
    along = (seen * directions[:5, None]).sum(-1)
    # Front faces of a unit icosphere, up to the faces straddling the silhouette.
    assert (along > -0.1).all() and (along.mean(1) > 0.4).all()  # a hemisphere's mean is 0.5
    whole = cache.sample(torch.zeros(1, dtype=torch.long), 2000, generator)[0]
    assert (whole @ directions[0]).mean().abs() < 0.05


def test_the_sampler_lays_copies_out_copy_major_and_repeats_with_its_seed(tiny_dataset):
    from gdvae.data import load_dataset

    dataset = load_dataset(tiny_dataset)
    indices = dataset.indices("train")
    make = lambda seed: PointSampler(dataset, indices, 64, seed, DepthCamera())
    sampler = make(3)
    chosen, clouds = sampler.batch(5)
    assert clouds.shape == (5, 64, 3) and chosen.shape == (5,)
    assert int(chosen.min()) >= 0 and int(chosen.max()) < len(indices)
    # Copy k of mesh i is row k * len(chosen) + i: each copy of a mesh is a cloud of that mesh,
    # whose extent differs from mesh to mesh.
    meshes = torch.tensor([0, len(indices) - 1])
    views = sampler.views(meshes, 3, 0.5)
    assert views.shape == (6, 64, 3)
    wholes = sampler.clouds(meshes.repeat_interleave(50)).view(2, 50, 64, 3)
    own = [wholes[m].reshape(-1, 3).norm(dim=-1).max() for m in range(2)]
    for row in range(6):
        assert views[row].norm(dim=-1).max() <= own[row % 2] + 0.05  # noise along the rays
    # One generator: the same seed draws the same batch, another seed another.
    again, other = make(3), make(4)
    assert torch.equal(again.batch(5)[1], clouds)
    assert not torch.equal(other.batch(5)[1], clouds)
    assert sampler.one_each().shape == (len(indices), 64, 3)
