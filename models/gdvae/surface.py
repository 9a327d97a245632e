"""Training clouds made where the model trains (issue 31): the dataset's meshes held once on the
training device as flat tensors, and whole-surface samples, camera-facing samples and depth-camera
views drawn for a whole batch at once by tensor operations, with no per-cloud Python loop. The same
code runs on the CPU.

Why: the AE's batches used to be drawn one cloud at a time in NumPy, in loader processes; on a lent
H200 those processes fed the model 5,400 clouds/s and were the limit. Here a batch of views is a
handful of kernels: area-weighted face choice by `searchsorted` on each mesh's cumulative areas,
a depth buffer per view by `scatter_reduce`, its 3x3 minimum by two passes of `minimum`, and the
seen points drawn by one cumulative sum. The camera's dense samples are kept coordinate-major
([V, 3, D]), so that its rotation is one batched 3x3 product over contiguous rows.

The sampling is the per-cloud NumPy sampler's it replaced (`data.sample_surface` stays, and the
tests compare its area weighting with this one's): area-weighted surface points in model units
(dataset scale, centred on the bounding box), random view directions from above, and
`data.DepthCamera`'s nearest-point-per-pixel visibility and stereo depth noise. The NumPy camera
rendered every view of a mesh from one dense sample drawn once; here the views of a batch redraw a
share of theirs (`PointSampler.dense_refresh`).
"""

from __future__ import annotations

import math

import numpy as np
import torch

from .data import DepthCamera, Mesh, MeshDataset


class MeshCache:
    """Meshes as flat tensors on one device: vertices [V, 3] float32 (model units, each mesh centred
    on its bounding box), faces [F, 3] int32 (indices into all vertices), and the cumulative
    shares of each mesh's area over its faces, in which `searchsorted` draws area-weighted faces:
    one row per mesh [meshes, most faces] (float32, padded with 2: a search stays within one
    mesh's row), or, when meshes differ so much in size that the rows would hold mostly padding,
    one sorted sequence of mesh number + share (float64)."""

    PADDING_LIMIT = 3.0  # rows while they take at most this many times the faces' own shares

    def __init__(self, meshes: list[Mesh], scale: float, device: torch.device | str = "cpu"):
        if not meshes:
            raise ValueError("no meshes to sample")
        self.device = torch.device(device)
        vertex_counts = np.array([len(m.vertices) for m in meshes])
        face_counts = np.array([len(m.faces) for m in meshes])
        vertex_start = np.concatenate([[0], np.cumsum(vertex_counts)[:-1]])
        face_start = np.concatenate([[0], np.cumsum(face_counts)[:-1]])
        total_faces, max_faces = int(face_counts.sum()), int(face_counts.max())
        # Filled one mesh at a time: whole-dataset float64 temporaries cost about 1 MB a mesh at
        # their peak (14,400 meshes ran out of 24 GB), these arrays a quarter of that.
        vertices = np.empty((int(vertex_counts.sum()), 3), np.float32)
        faces = np.empty((total_faces, 3), np.int32)
        as_rows = len(meshes) * max_faces <= self.PADDING_LIMIT * total_faces
        shares = np.full((len(meshes), max_faces), 2.0, np.float32) if as_rows else None
        keys = None if as_rows else np.empty(total_faces, np.float64)
        for number, (mesh, v0, f0) in enumerate(zip(meshes, vertex_start, face_start)):
            centre = 0.5 * (mesh.vertices.min(axis=0) + mesh.vertices.max(axis=0))
            vertices[v0:v0 + len(mesh.vertices)] = (mesh.vertices - centre) * scale
            faces[f0:f0 + len(mesh.faces)] = mesh.faces + v0
            areas = mesh.face_areas()
            share = np.cumsum(areas) / areas.sum()
            share[-1] = 1.0  # each mesh's last face ends its range exactly
            if as_rows:
                shares[number, :len(share)] = share
            else:
                keys[f0:f0 + len(share)] = number + share
        self.shares = None if shares is None else torch.from_numpy(shares).to(self.device)
        self.keys = None if keys is None else torch.from_numpy(keys).to(self.device)
        self.vertices = torch.from_numpy(vertices).to(self.device)
        self.faces = torch.from_numpy(faces).to(self.device)
        self.face_start = torch.from_numpy(face_start).to(self.device)
        self.face_count = torch.from_numpy(face_counts).to(self.device)
        self.max_faces = int(face_counts.max())

    def __len__(self) -> int:
        return len(self.face_start)

    def bytes(self) -> int:
        return sum(t.numel() * t.element_size() for t in (self.vertices, self.faces, self.shares, self.keys)
                   if t is not None)

    def corners(self, faces: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """The three corners [..., 3] of each face index in `faces`."""
        # index_select: several times faster than advanced indexing on a CPU
        corner = torch.index_select(self.faces, 0, faces.reshape(-1)).long().reshape(-1)
        points = torch.index_select(self.vertices, 0, corner).view(*faces.shape, 3, 3)
        return points[..., 0, :], points[..., 1, :], points[..., 2, :]

    def points_on(self, faces: torch.Tensor, generator: torch.Generator | None) -> torch.Tensor:
        """One uniform point on each face in `faces` [...] -> [..., 3]."""
        a, b, c = self.corners(faces)
        u = torch.rand(faces.shape, generator=generator, device=self.device)
        v = torch.rand(faces.shape, generator=generator, device=self.device)
        flip = u + v > 1.0
        u, v = torch.where(flip, 1.0 - u, u), torch.where(flip, 1.0 - v, v)
        return a + u[..., None] * (b - a) + v[..., None] * (c - a)

    def sample(self, meshes: torch.Tensor, count: int, generator: torch.Generator | None) -> torch.Tensor:
        """[len(meshes), count, 3]: `count` area-weighted surface points of each mesh."""
        if self.shares is not None:
            u = torch.rand(len(meshes), count, generator=generator, device=self.device)
            slot = torch.searchsorted(torch.index_select(self.shares, 0, meshes), u)
        else:
            u = torch.rand(len(meshes), count, generator=generator, device=self.device, dtype=torch.float64)
            slot = torch.searchsorted(self.keys, meshes[:, None] + u) - self.face_start[meshes][:, None]
        slot = torch.minimum(slot, self.face_count[meshes][:, None] - 1)
        return self.points_on(self.face_start[meshes][:, None] + slot, generator)

    def sample_facing(self, meshes: torch.Tensor, count: int, directions: torch.Tensor,
                      generator: torch.Generator | None) -> torch.Tensor:
        """Like `sample`, from the faces turned towards `directions` [len(meshes), 3] (unit vectors
        from the object towards a distant viewer; self-occlusion ignored); a mesh with no face
        turned that way gives its whole surface, as `data.sample_surface` does."""
        slots = torch.arange(self.max_faces, device=self.device)
        valid = slots[None] < self.face_count[meshes][:, None]
        faces = torch.where(valid, self.face_start[meshes][:, None] + slots[None], 0)
        a, b, c = self.corners(faces)
        cross = torch.linalg.cross(b - a, c - a)
        area = 0.5 * cross.norm(dim=-1) * valid
        facing = (cross * directions[:, None]).sum(-1) > 0
        visible = area * facing
        weights = torch.where(visible.sum(1, keepdim=True) > 0, visible, area).double().cumsum(1)
        u = torch.rand(len(meshes), count, generator=generator, device=self.device, dtype=torch.float64)
        slot = torch.searchsorted(weights, u * weights[:, -1:])
        slot = torch.minimum(slot, self.face_count[meshes][:, None] - 1)
        return self.points_on(torch.gather(faces, 1, slot), generator)


def view_directions(count: int, generator: torch.Generator | None, device: torch.device,
                    elevation_degrees: tuple[float, float] = (5.0, 40.0)) -> torch.Tensor:
    """[count, 3] unit vectors towards a camera: any azimuth about +z, looking down by an elevation
    in the given range (`data.random_view_directions`)."""
    azimuth = (torch.rand(count, generator=generator, device=device) * 2 - 1) * math.pi
    low, high = (math.radians(d) for d in elevation_degrees)
    elevation = low + torch.rand(count, generator=generator, device=device) * (high - low)
    return torch.stack([elevation.cos() * azimuth.cos(), elevation.cos() * azimuth.sin(), elevation.sin()], -1)


def depth_camera_views(camera: DepthCamera, surfaces: torch.Tensor, directions: torch.Tensor, count: int,
                       scale: float, generator: torch.Generator | None,
                       centres: torch.Tensor | None = None) -> torch.Tensor:
    """[V, count, 3]: what `camera` sees of each dense surface sample [V, D, 3] from its direction
    [V, 3] (unit vectors from the object's centre towards the camera) at a random distance in
    `camera.distance_m`: the nearest point per pixel (unless something well in front of it lies in
    a neighbouring pixel), each moved along its ray by the stereo depth error, `count` of them
    drawn without repetition (with, when fewer are seen). The dense sample's points must be
    independent draws in random order (as `MeshCache.sample` gives them): the draw takes a run of
    consecutive seen points. `centres` [V, 3]: where the camera looks (default: each sample's
    bounding-box centre). `scale`: model units per metre."""
    return render_views(camera, surfaces.transpose(1, 2), directions, count, scale, generator, centres)


def render_views(camera: DepthCamera, surfaces: torch.Tensor, directions: torch.Tensor, count: int,
                 scale: float, generator: torch.Generator | None,
                 centres: torch.Tensor | None = None) -> torch.Tensor:
    """`depth_camera_views` on dense samples laid out coordinate-major, [V, 3, D]: each coordinate
    of a view's points is one contiguous row, which the camera's rotation (one batched 3x3 product)
    and every per-point step after it read several times faster than rows of [x, y, z]."""
    views, _, dense = surfaces.shape
    device = surfaces.device
    if centres is None:
        centres = 0.5 * (surfaces.amin(2) + surfaces.amax(2))
    low, high = camera.distance_m
    distance = (low + torch.rand(views, generator=generator, device=device) * (high - low)) * scale
    position = centres + directions * distance[:, None]
    forward = -directions
    up_axis = torch.tensor([0.0, 0.0, 1.0], device=device).expand_as(forward)
    side_axis = torch.tensor([1.0, 0.0, 0.0], device=device).expand_as(forward)
    right = torch.linalg.cross(forward, torch.where(forward[:, 2:].abs() < 0.99, up_axis, side_axis))
    right = right / right.norm(dim=-1, keepdim=True)
    up = torch.linalg.cross(right, forward)
    axes = torch.stack([right, up, forward], 1)  # rows: the camera's right, up and viewing axes
    image = torch.baddbmm(-torch.bmm(axes, position[:, :, None]), axes, surfaces)  # [V, (right, up, depth), D]
    depth = image[:, 2]
    focal = camera.fx / camera.decimation
    inverse = focal / depth
    column, row = torch.floor(image[:, 0] * inverse), torch.floor(image[:, 1] * inverse)
    column -= column.amin(1, keepdim=True)
    row -= row.amin(1, keepdim=True)
    width, height = (int(extent) + 3 for extent in torch.stack([column.max(), row.max()]).tolist())
    if width * height >= 1 << 24:
        raise ValueError(f"a camera view spans {width - 2} x {height - 2} pixels: some surface points lie "
                         f"at or behind the camera (distance_m {camera.distance_m} against the sample's size)")
    # A pixel's cell in one depth buffer [V, width, height] with an empty border (whole numbers in
    # float32 are exact below 2^24, which the check above keeps one view's buffer below).
    cell = (((column + 1) * height + row + 1).long()
            + torch.arange(0, views * width * height, width * height, device=device)[:, None])
    buffer = torch.full((views, width, height), math.inf, device=device)
    flat, depth = cell.view(-1), depth.contiguous()
    buffer.view(-1).scatter_reduce_(0, flat, depth.view(-1), reduce="amin")
    near = neighbourhood_minimum(buffer)
    nearest = torch.index_select(buffer.view(-1), 0, flat).view(views, dense)
    around = torch.index_select(near.view(-1), 0, flat).view(views, dense)
    seen = (depth == nearest) & (depth <= around + depth * (6.0 / focal))
    if camera.edge_threshold > 0:
        seen &= ~torch.index_select(depth_edges(buffer, near, camera.edge_threshold).view(-1), 0, flat).view(views, dense)
    chosen = draw_seen(seen, count, generator)
    points = torch.gather(surfaces, 2, chosen[:, None].expand(-1, 3, -1)).transpose(1, 2)
    rays = points - position[:, None]
    depth_m = torch.gather(depth, 1, chosen) / scale
    sigma_m = depth_m.pow(2) * camera.disparity_sigma / (camera.fx * camera.baseline_m)
    noise = torch.randn(depth_m.shape, generator=generator, device=device)
    return position[:, None] + rays * ((depth_m + sigma_m * noise) / depth_m)[..., None]


def depth_edges(buffer: torch.Tensor, near: torch.Tensor, threshold: float) -> torch.Tensor:
    """[V, W, H]: the cells of a depth buffer (empty: infinite) at a depth edge as the sim's camera
    finds them (sim/src/camera.rs `at_depth_edge`): a neighbour in the 3x3 neighbourhood nearer or
    further than `threshold` times the cell's depth, or empty. `near`: the buffer's
    `neighbourhood_minimum`."""
    far = -neighbourhood_minimum(-buffer)
    return (far > buffer * (1 + threshold)) | (near < buffer * (1 - threshold))


def neighbourhood_minimum(buffer: torch.Tensor) -> torch.Tensor:
    """The minimum over each cell's 3x3 neighbourhood of a depth buffer [V, W, H] whose border is
    empty (infinite), one axis at a time, written in place into two buffers (fresh tensors and
    slice assignments cost four times as much on a CPU); the border stays empty."""
    across = torch.empty_like(buffer)
    across[:, 0], across[:, -1] = math.inf, math.inf
    inner = across[:, 1:-1]
    torch.minimum(buffer[:, :-2], buffer[:, 1:-1], out=inner)
    torch.minimum(inner, buffer[:, 2:], out=inner)
    near = torch.empty_like(buffer)
    near[:, :, 0], near[:, :, -1] = math.inf, math.inf
    inner = near[:, :, 1:-1]
    torch.minimum(across[:, :, :-2], across[:, :, 1:-1], out=inner)
    torch.minimum(inner, across[:, :, 2:], out=inner)
    return near


def draw_seen(seen: torch.Tensor, count: int, generator: torch.Generator | None) -> torch.Tensor:
    """[V, count] indices of points with `seen` [V, D] true: without repetition, `count` seen points
    in a row from a random one of them (wrapping round; each seen point is drawn with the same
    chance, and the draw is uniform among subsets when the points are independent draws in random
    order) at the cost of one cumulative sum (random keys and a top-k over all D points cost four
    times as much); with repetition, uniform draws among the seen points, where fewer than `count`
    are seen."""
    views, dense = seen.shape
    device = seen.device
    running = seen.to(torch.int32).cumsum(1, dtype=torch.int32)  # seen points up to and including each
    visible = running[:, -1:]
    if bool((visible >= count).all()):
        first = (torch.rand(views, 1, generator=generator, device=device) * visible).to(torch.int32)
        first = torch.minimum(first, visible - 1)  # a draw that rounds up to `visible`
        rank = running - 1 - first  # among the seen points, counted from the first drawn
        rank = torch.where(rank < 0, rank + visible, rank)
        return (seen & (rank < count)).nonzero()[:, 1].view(views, count)
    keys = torch.where(seen, torch.rand(seen.shape, generator=generator, device=device), -1.0)
    order = keys.argsort(dim=1, descending=True)  # seen points first, in random order
    slots = torch.arange(count, device=device)[None].expand(views, count).clamp(max=dense - 1)
    drawn = (torch.rand(views, count, generator=generator, device=device) * visible).long()
    return torch.gather(order, 1, torch.where(visible >= count, slots, drawn))


class PointSampler:
    """Clouds of a dataset's meshes (those at `indices`) in model units, made on `device`: whole
    surfaces, and partial views as `camera` sees them (None: the faces turned towards the viewer).

    The camera renders each view from a dense sample of its mesh's surface (`camera.dense`
    points); every mesh keeps one, and the views of a batch redraw a share `dense_refresh` of the
    dense samples of the meshes they show, so that the views of a mesh do not repeat one point
    pattern while the cost of drawing a dense sample is paid for a few of them per batch."""

    def __init__(self, dataset: MeshDataset, indices: list[int], points: int, seed: int,
                 camera: DepthCamera | None = None, device: torch.device | str = "cpu",
                 dense_refresh: float = 0.1):
        self.cache = MeshCache([dataset.meshes[i] for i in indices], dataset.scale, device)
        self.device, self.scale, self.camera, self.points = self.cache.device, dataset.scale, camera, points
        self.dense_refresh = dense_refresh
        self.generator = torch.Generator(self.cache.device).manual_seed(seed)
        self.dense: torch.Tensor | None = None  # [meshes, 3, camera.dense] (`render_views`), drawn on first use

    def __len__(self) -> int:
        return len(self.cache)

    def reseed(self, seed: int) -> None:
        self.generator = torch.Generator(self.device).manual_seed(seed)

    def batch(self, size: int) -> tuple[torch.Tensor, torch.Tensor]:
        """`size` meshes drawn at random, and one whole-surface cloud of each [size, points, 3]."""
        chosen = torch.randint(0, len(self), (size,), generator=self.generator, device=self.device)
        return chosen, self.cache.sample(chosen, self.points, self.generator)

    def views(self, chosen, copies: int, partial: float) -> torch.Tensor:
        """[copies * len(chosen), points, 3], copy-major as `ae_loss` lays copies out: each copy of
        each chosen mesh is, with probability `partial`, the side a camera sees from a random
        direction, else its whole surface."""
        meshes = torch.as_tensor(chosen, device=self.device).long().repeat(copies)
        if partial <= 0:
            return self.cache.sample(meshes, self.points, self.generator)
        viewed = torch.rand(len(meshes), generator=self.generator, device=self.device) < partial
        clouds = torch.empty(len(meshes), self.points, 3, device=self.device)
        whole, rows = (~viewed).nonzero().squeeze(1), viewed.nonzero().squeeze(1)
        if len(whole):
            clouds[whole] = self.cache.sample(meshes[whole], self.points, self.generator)
        if len(rows):
            directions = view_directions(len(rows), self.generator, self.device)
            clouds[rows] = self.partial_views(meshes[rows], directions)
        return clouds

    def partial_views(self, meshes: torch.Tensor, directions: torch.Tensor) -> torch.Tensor:
        if self.camera is None:
            return self.cache.sample_facing(meshes, self.points, directions, self.generator)
        if self.dense is None:
            self.dense = torch.cat([self.cache.sample(part, self.camera.dense, self.generator).transpose(1, 2)
                                    for part in torch.arange(len(self), device=self.device).split(256)])
        renew = meshes[torch.rand(len(meshes), generator=self.generator, device=self.device) < self.dense_refresh]
        if len(renew):
            renew = renew.unique()
            self.dense[renew] = self.cache.sample(renew, self.camera.dense, self.generator).transpose(1, 2)
        centres = torch.zeros(len(meshes), 3, device=self.device)  # meshes are centred on their box
        return render_views(self.camera, torch.index_select(self.dense, 0, meshes), directions, self.points,
                            self.scale, self.generator, centres)

    def clouds(self, meshes) -> torch.Tensor:
        """[len(meshes), points, 3]: a fresh whole-surface cloud of each mesh index in `meshes`."""
        return self.cache.sample(torch.as_tensor(meshes, device=self.device).long(), self.points, self.generator)

    def one_each(self) -> torch.Tensor:
        """[meshes, points, 3]: one fresh whole-surface cloud of every mesh, in order."""
        return self.clouds(torch.arange(len(self)))
