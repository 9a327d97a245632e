"""Rotations and point-set distances in torch (the losses' building blocks).

Conventions: quaternions are (w, x, y, z); `quaternion_to_matrix(q)` acts on column vectors; point
sets are rows, so rotating a set by R is `points @ R.transpose(-1, -2)` (see `rotate`). A model's
q is the rotation that carries its canonical shape to the observed one.
"""

from __future__ import annotations

import math

import torch


def normalize_quaternion(q: torch.Tensor, eps: float = 1e-8) -> torch.Tensor:
    return q / q.norm(dim=-1, keepdim=True).clamp_min(eps)


def quaternion_to_matrix(q: torch.Tensor) -> torch.Tensor:
    w, x, y, z = normalize_quaternion(q).unbind(-1)
    return torch.stack(
        [
            torch.stack([1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)], -1),
            torch.stack([2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)], -1),
            torch.stack([2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)], -1),
        ],
        -2,
    )


def matrix_to_quaternion(matrix: torch.Tensor) -> torch.Tensor:
    """Rotation matrices -> unit quaternions with w >= 0 (Shepperd's method, batched)."""
    m = matrix
    trace = m[..., 0, 0] + m[..., 1, 1] + m[..., 2, 2]
    candidates = torch.stack(
        [
            torch.stack([1 + trace, m[..., 2, 1] - m[..., 1, 2], m[..., 0, 2] - m[..., 2, 0], m[..., 1, 0] - m[..., 0, 1]], -1),
            torch.stack([m[..., 2, 1] - m[..., 1, 2], 1 + m[..., 0, 0] - m[..., 1, 1] - m[..., 2, 2], m[..., 1, 0] + m[..., 0, 1], m[..., 0, 2] + m[..., 2, 0]], -1),
            torch.stack([m[..., 0, 2] - m[..., 2, 0], m[..., 1, 0] + m[..., 0, 1], 1 - m[..., 0, 0] + m[..., 1, 1] - m[..., 2, 2], m[..., 2, 1] + m[..., 1, 2]], -1),
            torch.stack([m[..., 1, 0] - m[..., 0, 1], m[..., 0, 2] + m[..., 2, 0], m[..., 2, 1] + m[..., 1, 2], 1 - m[..., 0, 0] - m[..., 1, 1] + m[..., 2, 2]], -1),
        ],
        -2,
    )
    diagonal = torch.stack([trace, m[..., 0, 0], m[..., 1, 1], m[..., 2, 2]], -1)
    best = diagonal.argmax(-1)
    q = torch.gather(candidates, -2, best[..., None, None].expand(*best.shape, 1, 4)).squeeze(-2)
    q = normalize_quaternion(q)
    return torch.where(q[..., :1] < 0, -q, q)


def rotate(points: torch.Tensor, rotation: torch.Tensor) -> torch.Tensor:
    """Applies rotation matrices [B, 3, 3] to point sets [B, N, 3]."""
    return points @ rotation.transpose(-1, -2)


def geodesic_distance(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """d_R of the paper: the angle of a b^T divided by pi, in [0, 1]."""
    trace = (a * b).sum(dim=(-1, -2))  # tr(a b^T)
    cosine = ((trace - 1) / 2).clamp(-1 + 1e-6, 1 - 1e-6)
    return torch.acos(cosine) / math.pi


def quaternion_distance(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """d_q of the paper: 1 - |a . b| for unit quaternions (sign-invariant)."""
    return 1 - (normalize_quaternion(a) * normalize_quaternion(b)).sum(-1).abs()


def squared_distances(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Pairwise squared distances between point sets [B, N, 3] and [B, M, 3] -> [B, N, M], as
    |a|^2 + |b|^2 - 2 a.b (one batched matrix product instead of an [B, N, M, 3] difference)."""
    cross = a @ b.transpose(-1, -2)
    return (a.pow(2).sum(-1).unsqueeze(-1) + b.pow(2).sum(-1).unsqueeze(-2) - 2 * cross).clamp_min(0.0)


def chamfer(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """d_C: mean squared distance to the nearest point, both ways, per batch item."""
    d = squared_distances(a, b)
    return d.min(dim=-1).values.mean(-1) + d.min(dim=-2).values.mean(-1)


def chamfer_and_hausdorff(a: torch.Tensor, b: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(d_C, d_H) per batch item, from one distance matrix. d_H is the approximate Hausdorff
    distance: the largest squared nearest-point distance, either way."""
    d = squared_distances(a, b)
    a_to_b, b_to_a = d.min(dim=-1).values, d.min(dim=-2).values
    return a_to_b.mean(-1) + b_to_a.mean(-1), torch.maximum(a_to_b.max(-1).values, b_to_a.max(-1).values)


def random_rotation_matrices(count: int, generator: torch.Generator | None = None, full: bool = False,
                             device=None) -> torch.Tensor:
    """Uniform rotations about +z (the sim's up axis), or uniform on SO(3) when `full`."""
    if full:
        q = torch.randn(count, 4, generator=generator, device=device)
        return quaternion_to_matrix(q)
    angle = (torch.rand(count, generator=generator, device=device) * 2 - 1) * math.pi
    c, s = torch.cos(angle), torch.sin(angle)
    zero, one = torch.zeros_like(c), torch.ones_like(c)
    return torch.stack([torch.stack([c, -s, zero], -1), torch.stack([s, c, zero], -1),
                        torch.stack([zero, zero, one], -1)], -2)
