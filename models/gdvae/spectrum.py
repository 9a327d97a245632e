"""Laplace-Beltrami spectra: the intrinsic-shape signal GDVAE++ learns from.

- Mesh LBO: cotangent stiffness matrix with the mixed Voronoi mass matrix of Meyer et al. (2003);
  the generalized eigenproblem L phi = lambda M phi is solved by shift-invert Lanczos, and the
  first N_lambda non-zero eigenvalues are kept (the zero mode of a closed surface is dropped).
- Point-cloud LBO (the paper's PCLBO ablation): Sharp & Crane (2020), `robust_laplacian`.
- d_lambda: the paper's Weyl-weighted spectral distance, mean_n |lambda_n - lambda'_n| / n.

Spectra are cached on disk, keyed by a hash of the scaled geometry and the settings.
"""

from __future__ import annotations

import hashlib
from pathlib import Path

import numpy as np
import scipy.sparse as sparse
from scipy.sparse.linalg import eigsh

from .data import Mesh


def corner_cotangents(mesh: Mesh) -> list[np.ndarray]:
    """Per triangle, the cotangent of the angle at each corner (index i: corner i)."""
    corners = [mesh.vertices[mesh.faces[:, i]] for i in range(3)]
    cotangents = []
    for i in range(3):
        j, k = (i + 1) % 3, (i + 2) % 3
        e1, e2 = corners[j] - corners[i], corners[k] - corners[i]
        cotangents.append(np.einsum("ij,ij->i", e1, e2) / np.linalg.norm(np.cross(e1, e2), axis=1))
    return cotangents


def cotangent_laplacian(mesh: Mesh) -> tuple[sparse.csr_matrix, sparse.dia_matrix]:
    """(L, M): the positive semi-definite cotangent stiffness matrix and the mixed-Voronoi lumped
    mass matrix, so that L phi = lambda M phi has lambda >= 0."""
    f = mesh.faces
    n = len(mesh.vertices)
    cotangents = corner_cotangents(mesh)
    stiffness_rows, stiffness_cols, stiffness_vals = [], [], []
    for i in range(3):
        # The angle at corner i weights the opposite edge (j, k).
        j, k = (i + 1) % 3, (i + 2) % 3
        weight = 0.5 * cotangents[i]
        stiffness_rows += [f[:, j], f[:, k]]
        stiffness_cols += [f[:, k], f[:, j]]
        stiffness_vals += [-weight, -weight]
    off_diagonal = sparse.coo_matrix(
        (np.concatenate(stiffness_vals), (np.concatenate(stiffness_rows), np.concatenate(stiffness_cols))),
        shape=(n, n),
    ).tocsr()
    stiffness = off_diagonal - sparse.diags(np.asarray(off_diagonal.sum(axis=1)).ravel())
    mass = sparse.diags(mixed_voronoi_areas(mesh, cotangents))
    return stiffness.tocsr(), mass


def mixed_voronoi_areas(mesh: Mesh, cotangents: list[np.ndarray] | None = None) -> np.ndarray:
    """Per-vertex mixed Voronoi area (Meyer et al. 2003): Voronoi cells in non-obtuse triangles,
    half the triangle at an obtuse corner and a quarter at the others."""
    v, f = mesh.vertices, mesh.faces
    corners = [v[f[:, i]] for i in range(3)]
    area = 0.5 * np.linalg.norm(np.cross(corners[1] - corners[0], corners[2] - corners[0]), axis=1)
    if cotangents is None:
        cotangents = corner_cotangents(mesh)
    obtuse = np.stack([c < 0 for c in cotangents], axis=1)  # cot < 0 <=> angle > 90 degrees
    any_obtuse = obtuse.any(axis=1)
    per_corner = np.zeros((len(f), 3))
    for i in range(3):
        j, k = (i + 1) % 3, (i + 2) % 3
        # Voronoi area at corner i: (|ij|^2 cot(k) + |ik|^2 cot(j)) / 8.
        edge_ij = np.sum((corners[j] - corners[i]) ** 2, axis=1)
        edge_ik = np.sum((corners[k] - corners[i]) ** 2, axis=1)
        voronoi = (edge_ij * cotangents[k] + edge_ik * cotangents[j]) / 8.0
        per_corner[:, i] = np.where(any_obtuse, np.where(obtuse[:, i], area / 2.0, area / 4.0), voronoi)
    areas = np.zeros(len(v))
    for i in range(3):
        np.add.at(areas, f[:, i], per_corner[:, i])
    return areas


def generalized_eigenvalues(stiffness, mass, count: int) -> np.ndarray:
    """The `count` smallest non-zero eigenvalues of L phi = lambda M phi (one zero mode dropped)."""
    n = stiffness.shape[0]
    if n < count + 3:
        raise ValueError(f"{n} vertices cannot give {count} eigenvalues")
    # Shift-invert just below zero: L - sigma M is positive definite, and the smallest eigenvalues
    # converge first. A few more than wanted, from a fixed start vector: Lanczos can miss one
    # member of a repeated eigenvalue at the edge of what it was asked for (a sphere's 15th gave
    # the 16th's value now and then, as ARPACK's own random start vector moved with the calls made
    # before), and the answer must not depend on them.
    extra = min(4, n - count - 2)
    start = np.random.default_rng(0).standard_normal(n)
    values = eigsh(stiffness, k=count + 1 + extra, M=mass, sigma=-1e-6, which="LM", v0=start,
                   return_eigenvectors=False)
    values = np.sort(values)
    return values[1 : count + 1]


def mesh_spectrum(mesh: Mesh, count: int) -> np.ndarray:
    stiffness, mass = cotangent_laplacian(mesh)
    return generalized_eigenvalues(stiffness, mass, count)


def point_cloud_spectrum(points: np.ndarray, count: int) -> np.ndarray:
    """The PCLBO variant: robust point-cloud Laplacian (Sharp & Crane 2020)."""
    import robust_laplacian

    stiffness, mass = robust_laplacian.point_cloud_laplacian(np.asarray(points, dtype=np.float64))
    return generalized_eigenvalues(stiffness, mass, count)


def spectral_distance(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """The paper's d_lambda: mean over n of |a_n - b_n| / n (Weyl weighting), over the last axis."""
    a, b = np.asarray(a), np.asarray(b)
    weights = 1.0 / np.arange(1, a.shape[-1] + 1)
    return np.mean(np.abs(a - b) * weights, axis=-1)


class SpectrumCache:
    """Spectra on disk, one .npy per (geometry, scale, count, method)."""

    def __init__(self, folder: str | Path):
        self.folder = Path(folder)
        self.folder.mkdir(parents=True, exist_ok=True)

    def key(self, mesh: Mesh, count: int, method: str) -> str:
        digest = hashlib.sha256()
        digest.update(np.ascontiguousarray(mesh.vertices, dtype=np.float64).tobytes())
        digest.update(np.ascontiguousarray(mesh.faces, dtype=np.int64).tobytes())
        digest.update(f"{count}:{method}".encode())
        return digest.hexdigest()[:32]

    def mesh_spectrum(self, mesh: Mesh, count: int) -> np.ndarray:
        path = self.folder / f"{self.key(mesh, count, 'cotan')}.npy"
        if path.exists():
            return np.load(path)
        values = mesh_spectrum(mesh, count)
        np.save(path, values)
        return values


def spectral_distance_torch(a, b):
    """d_lambda on torch tensors (last axis), for losses."""
    import torch

    weights = 1.0 / torch.arange(1, a.shape[-1] + 1, dtype=a.dtype, device=a.device)
    return ((a - b).abs() * weights).mean(-1)
