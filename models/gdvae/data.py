"""Mesh datasets: loading, the dataset-wide scale, and point sampling.

Follows the paper's data handling (appendix "Dataset Details"): one scale for the whole dataset
(largest bounding-box side -> 1; a per-shape scale would change each shape's spectrum
differently), centring, area-weighted surface sampling to N_p points, and random rotations about
the up axis (or all of SO(3) as an option). Any folder of PLY/OBJ/OFF meshes works; the sim's
`ground_truth.jsonl` and `splits.json` are used when present.

Bad meshes (empty, non-manifold, degenerate) are skipped with a logged reason and counted.
"""

from __future__ import annotations

import json
import logging
from collections import Counter
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path

import numpy as np

log = logging.getLogger(__name__)

MESH_SUFFIXES = (".ply", ".obj", ".off")


@dataclass
class Mesh:
    """A triangle mesh: vertices (V x 3, float64) and faces (F x 3, int64)."""

    vertices: np.ndarray
    faces: np.ndarray

    def face_areas(self) -> np.ndarray:
        return self._face_geometry[0]

    def face_normals(self) -> np.ndarray:
        """Unit normals by the faces' winding (outward for the sim's meshes)."""
        return self._face_geometry[1]

    @cached_property
    def _face_geometry(self) -> tuple[np.ndarray, np.ndarray]:
        # Computed once per mesh: samplers call these for every cloud (meshes are never mutated;
        # `normalize` makes a new one).
        a, b, c = (self.vertices[self.faces[:, i]] for i in range(3))
        cross = np.cross(b - a, c - a)
        norms = np.linalg.norm(cross, axis=1)
        return 0.5 * norms, cross / np.maximum(norms, 1e-300)[:, None]


class MeshRejected(ValueError):
    """A mesh that cannot be used, with the reason."""


def read_mesh(path: Path) -> Mesh:
    """Reads a PLY, OBJ or OFF triangle mesh (trimesh does the parsing; no processing/merging)."""
    import trimesh

    try:
        loaded = trimesh.load(path, force="mesh", process=False)
    except Exception as error:  # trimesh raises many types for corrupt files
        raise MeshRejected(f"cannot parse: {error}") from error
    vertices = np.asarray(loaded.vertices, dtype=np.float64)
    faces = np.asarray(loaded.faces, dtype=np.int64)
    return Mesh(vertices, faces)


def check_mesh(mesh: Mesh) -> None:
    """Raises MeshRejected unless the mesh is a non-empty, finite, non-degenerate, edge-manifold
    triangle mesh (what the cotangent Laplacian needs)."""
    if len(mesh.vertices) == 0 or len(mesh.faces) == 0:
        raise MeshRejected("empty mesh")
    if not np.isfinite(mesh.vertices).all():
        raise MeshRejected("non-finite vertex coordinates")
    if mesh.faces.ndim != 2 or mesh.faces.shape[1] != 3:
        raise MeshRejected(f"faces are not triangles (shape {mesh.faces.shape})")
    if mesh.faces.min() < 0 or mesh.faces.max() >= len(mesh.vertices):
        raise MeshRejected("face index out of range")
    areas = mesh.face_areas()
    if (areas <= 1e-14 * max(1.0, float(np.ptp(mesh.vertices)) ** 2)).any():
        raise MeshRejected(f"{int((areas <= 0).sum())} degenerate (zero-area) faces")
    edges = np.sort(np.concatenate([mesh.faces[:, [0, 1]], mesh.faces[:, [1, 2]], mesh.faces[:, [2, 0]]]), axis=1)
    _, counts = np.unique(edges, axis=0, return_counts=True)
    if (counts > 2).any():
        raise MeshRejected(f"{int((counts > 2).sum())} non-manifold edges (shared by more than two faces)")


@dataclass
class Item:
    """One mesh of a dataset with its optional ground truth."""

    path: Path
    subject: str
    split: str
    truth: dict | None = None


@dataclass
class MeshDataset:
    """A folder of meshes, scaled into model units, split by subject."""

    root: Path
    items: list[Item]
    meshes: list[Mesh]
    scale: float  # model units per input unit (metres for the sim)
    has_ground_truth: bool
    rejected: Counter = field(default_factory=Counter)

    def indices(self, split: str) -> list[int]:
        return [i for i, item in enumerate(self.items) if item.split == split]


def load_dataset(root: str | Path, limit: int | None = None) -> MeshDataset:
    """Loads every mesh under `root` (recursively), checks it, and computes the dataset scale.

    Splits come from `splits.json` (subject ids per split) and subjects from `ground_truth.jsonl`
    when present; otherwise every mesh is its own subject and all go to "train".
    """
    root = Path(root)
    truths: dict[str, dict] = {}
    truth_file = root / "ground_truth.jsonl"
    if truth_file.exists():
        for number, line in enumerate(truth_file.read_text().splitlines(), 1):
            if line.strip():
                try:
                    record = json.loads(line)
                    truths[record["file"]] = record
                except (json.JSONDecodeError, KeyError) as error:
                    log.warning("%s:%d: ignoring a bad ground-truth line (%s)", truth_file, number, error)
    else:
        log.info("%s has no ground_truth.jsonl: metrics that need ground truth will be skipped", root)
    split_of: dict[str, str] = {}
    splits_file = root / "splits.json"
    if splits_file.exists():
        for split, subjects in json.loads(splits_file.read_text()).items():
            for subject in subjects:
                split_of[subject] = split

    paths = sorted(p for p in root.rglob("*") if p.suffix.lower() in MESH_SUFFIXES)
    if limit is not None:
        paths = paths[:limit]
    items, meshes, rejected = [], [], Counter()
    for path in paths:
        relative = path.relative_to(root).as_posix()
        try:
            mesh = read_mesh(path)
            check_mesh(mesh)
        except MeshRejected as reason:
            log.warning("skipping %s: %s", path, reason)
            rejected[str(reason).split(":")[0]] += 1
            continue
        truth = truths.get(relative)
        subject = truth["subject"] if truth else relative
        split = truth.get("split") if truth and "split" in truth else split_of.get(subject, "train")
        items.append(Item(path, subject, split, truth))
        meshes.append(mesh)
    if not meshes:
        raise ValueError(f"{root}: no usable meshes ({sum(rejected.values())} rejected: {dict(rejected)})")
    if rejected:
        log.warning("%s: %d meshes skipped: %s", root, sum(rejected.values()), dict(rejected))
    extent = max(float(np.ptp(mesh.vertices, axis=0).max()) for mesh in meshes)
    return MeshDataset(root, items, meshes, 1.0 / extent, bool(truths), rejected)


def normalize(mesh: Mesh, scale: float) -> Mesh:
    """Centres a mesh on its bounding-box centre and applies the dataset scale."""
    centre = 0.5 * (mesh.vertices.min(axis=0) + mesh.vertices.max(axis=0))
    return Mesh((mesh.vertices - centre) * scale, mesh.faces)


def sample_surface(mesh: Mesh, count: int, rng: np.random.Generator, facing: np.ndarray | None = None) -> np.ndarray:
    """`count` points uniformly distributed over the surface (area-weighted), float32.

    `facing`: a unit vector from the object towards a distant viewer; only the faces turned
    towards it are sampled, which is what a depth camera sees (self-occlusion is ignored)."""
    areas = mesh.face_areas()
    if facing is not None:
        visible = areas * (mesh.face_normals() @ facing > 0.0)
        areas = visible if visible.sum() > 0 else areas
    faces = rng.choice(len(mesh.faces), size=count, p=areas / areas.sum())
    u, v = rng.random(count), rng.random(count)
    flip = u + v > 1.0
    u[flip], v[flip] = 1.0 - u[flip], 1.0 - v[flip]
    a, b, c = (mesh.vertices[mesh.faces[faces, i]] for i in range(3))
    return (a + u[:, None] * (b - a) + v[:, None] * (c - a)).astype(np.float32)


@dataclass(frozen=True)
class DepthCamera:
    """The sim's stereo depth camera (sim/src/camera.rs: OAK-D at 640x400, fx 441.25 px, 7.5 cm
    baseline, 0.1 px disparity noise), as the node's benchmark records it (every 2nd pixel), at
    `distance_m` from the subject. Lengths in metres; `view` converts to model units."""

    fx: float = 441.25
    baseline_m: float = 0.075
    disparity_sigma: float = 0.1
    decimation: int = 2
    distance_m: tuple[float, float] = (2.4, 3.6)
    dense: int = 8000

    def view(self, surface: np.ndarray, count: int, rng: np.random.Generator, direction: np.ndarray,
             scale: float) -> np.ndarray:
        """`count` points (float32, drawn from `see`'s, repeated when fewer) of what the camera
        sees of a dense `surface` sample (`sample_surface(mesh, self.dense)`) from `direction`
        (unit vector from its box centre towards the camera) at a random distance in
        `distance_m`; `scale`: model units per metre."""
        centre = 0.5 * (surface.min(axis=0) + surface.max(axis=0))
        points = self.see(surface, centre + direction * rng.uniform(*self.distance_m) * scale, rng, scale)
        return points[rng.choice(len(points), size=count, replace=len(points) < count)].astype(np.float32)

    def see(self, surface: np.ndarray, camera: np.ndarray, rng: np.random.Generator, scale: float) -> np.ndarray:
        """Every point of a dense `surface` sample that the camera at `camera` (same units),
        looking at the sample's box centre, sees: the nearest visible point per pixel
        (self-occlusion), each moved along its ray by the stereo depth error (sigma = z^2 *
        disparity sigma / (fx * baseline), in metres)."""
        centre = 0.5 * (surface.min(axis=0) + surface.max(axis=0))
        forward = (centre - camera) / np.linalg.norm(centre - camera)
        right = np.cross(forward, [0.0, 0.0, 1.0]) if abs(forward[2]) < 0.99 else np.cross(forward, [1.0, 0.0, 0.0])
        right /= np.linalg.norm(right)
        up = np.cross(right, forward)
        rays = surface.astype(np.float64) - camera
        depth = rays @ forward
        focal = self.fx / self.decimation
        pixel = np.floor(focal * np.stack([rays @ right, rays @ up], axis=1) / depth[:, None]).astype(np.int64)
        # Depth buffer and its minimum over each pixel's 3x3 neighbourhood, so that a pixel no
        # near-side sample fell in does not show the far side (tolerance: six pixels' footprint).
        pixel -= pixel.min(axis=0)
        buffer = np.full(pixel.max(axis=0) + 3, np.inf)
        np.minimum.at(buffer, (pixel[:, 0] + 1, pixel[:, 1] + 1), depth)
        near = buffer.copy()
        for dx in (-1, 0, 1):
            for dy in (-1, 0, 1):
                near[1:-1, 1:-1] = np.minimum(near[1:-1, 1:-1], buffer[1 + dx:buffer.shape[0] - 1 + dx,
                                                                      1 + dy:buffer.shape[1] - 1 + dy])
        # Per pixel the nearest point, unless something well in front of it is nearby.
        cell = (pixel[:, 0] + 1, pixel[:, 1] + 1)
        seen = np.flatnonzero((depth == buffer[cell]) & (depth <= near[cell] + 6.0 * depth / focal))
        depth_m = depth[seen] / scale
        sigma_m = depth_m ** 2 * self.disparity_sigma / (self.fx * self.baseline_m)
        stretch = (depth_m + sigma_m * rng.standard_normal(len(seen))) / depth_m
        return camera + rays[seen] * stretch[:, None]


def random_view_directions(count: int, rng: np.random.Generator, up_axis: int = 2,
                           elevation_degrees: tuple[float, float] = (5.0, 40.0)) -> np.ndarray:
    """Unit vectors towards a camera: any azimuth about the up axis, looking down by an elevation
    in the given range (a robot's camera above the ground)."""
    azimuth = rng.uniform(-np.pi, np.pi, size=count)
    elevation = np.radians(rng.uniform(*elevation_degrees, size=count))
    horizontal = [a for a in range(3) if a != up_axis]
    directions = np.zeros((count, 3))
    directions[:, horizontal[0]] = np.cos(elevation) * np.cos(azimuth)
    directions[:, horizontal[1]] = np.cos(elevation) * np.sin(azimuth)
    directions[:, up_axis] = np.sin(elevation)
    return directions


def random_rotations(count: int, rng: np.random.Generator, full: bool = False, up_axis: int = 2) -> np.ndarray:
    """`count` rotation matrices: uniform about the up axis, or uniform on SO(3) when `full`."""
    if full:
        q = rng.normal(size=(count, 4))
        q /= np.linalg.norm(q, axis=1, keepdims=True)
        return quaternion_to_matrix_np(q)
    angles = rng.uniform(-np.pi, np.pi, size=count)
    c, s = np.cos(angles), np.sin(angles)
    rotations = np.zeros((count, 3, 3))
    axes = [a for a in range(3) if a != up_axis]
    rotations[:, up_axis, up_axis] = 1.0
    rotations[:, axes[0], axes[0]] = c
    rotations[:, axes[0], axes[1]] = -s
    rotations[:, axes[1], axes[0]] = s
    rotations[:, axes[1], axes[1]] = c
    return rotations


def quaternion_to_matrix_np(q: np.ndarray) -> np.ndarray:
    """(w, x, y, z) unit quaternions -> rotation matrices acting on column vectors."""
    w, x, y, z = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    return np.stack(
        [
            np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)], -1),
            np.stack([2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)], -1),
            np.stack([2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)], -1),
        ],
        -2,
    )
