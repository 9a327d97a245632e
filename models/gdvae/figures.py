"""Figures of a trained run (PNG, matplotlib): what the metrics summarise, made visible.

- `tsne_xc.png`: t-SNE of x_c for test shapes under several rotations, coloured by shape; tight
  clusters mean a rotation-invariant code.
- `interpolation_<family>.png`: a grid over z_E (columns) and z_I (rows) between two test shapes;
  the off-diagonal corners are pose transfers (pose of one, shape of the other).
- `retrieval_<family>.png`: query shapes and their nearest neighbours by z_E and by z_I.
- `generations.png`: random samples from the prior.
Point clouds are drawn from the side (x forward, z up) in the canonical frame.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from .data import MeshDataset
from .evaluate import encode_all
from .geometry import random_rotation_matrices
from .surface import PointSampler


def _draw(ax, cloud: np.ndarray, title: str = "") -> None:
    ax.scatter(cloud[:, 0], cloud[:, 2], s=1.5, c=cloud[:, 1], cmap="viridis")
    ax.set_aspect("equal")
    ax.set_xlim(-0.6, 0.6)
    ax.set_ylim(-0.6, 0.6)
    ax.set_xticks([])
    ax.set_yticks([])
    if title:
        ax.set_title(title, fontsize=7)


@torch.no_grad()
def make_figures(ae, vae, dataset: MeshDataset, spectra: np.ndarray, folder: str | Path, split: str = "test",
                 seed: int = 0) -> list[Path]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from sklearn.manifold import TSNE

    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    torch.manual_seed(seed)
    rng = np.random.default_rng(seed)
    indices = dataset.indices(split)
    sampler = PointSampler(dataset, indices, ae.config.points, seed)
    clouds = sampler.one_each()
    written = []

    # t-SNE of x_c under rotation.
    shapes = rng.choice(len(clouds), size=min(20, len(clouds)), replace=False)
    copies = 8
    batch = clouds[shapes].repeat(copies, 1, 1)
    codes = encode_all(ae, vae, batch, random_rotation_matrices(len(batch), full=ae.config.full_rotations), None)
    embedded = TSNE(perplexity=min(30, len(batch) - 1), random_state=seed).fit_transform(codes["x_c"].numpy())
    fig, ax = plt.subplots(figsize=(5, 5))
    ax.scatter(embedded[:, 0], embedded[:, 1], c=np.tile(np.arange(len(shapes)), copies), cmap="tab20", s=12)
    ax.set_title(f"t-SNE of x_c: {len(shapes)} test shapes x {copies} rotations (colour = shape)", fontsize=8)
    ax.set_xticks([])
    ax.set_yticks([])
    written.append(_save(fig, folder / "tsne_xc.png"))

    codes = encode_all(ae, vae, clouds, torch.eye(3).expand(len(clouds), 3, 3), torch.from_numpy(spectra[indices]).float())
    families = {}
    for row, index in enumerate(indices):
        truth = dataset.items[index].truth or {}
        families.setdefault(truth.get("family", "all"), []).append(row)

    def decode(z_e, z_i):
        _, x_c = vae.decode(codes["mu_R"][:1].expand(len(z_e), -1), z_e, z_i)
        return ae.decode(x_c).numpy()

    for family, rows in families.items():
        if len(rows) < 4:
            continue
        subjects = [dataset.items[indices[r]].subject for r in rows]
        a = rows[0]
        b = next((r for r, s in zip(rows, subjects) if s != subjects[0]), rows[-1])
        steps = 5
        t = torch.linspace(0, 1, steps)
        fig, axes = plt.subplots(steps, steps, figsize=(2 * steps, 2 * steps))
        for i, ti in enumerate(t):  # rows: z_I from a to b
            z_i = (1 - ti) * codes["mu_I"][a] + ti * codes["mu_I"][b]
            z_e = torch.stack([(1 - tj) * codes["mu_E"][a] + tj * codes["mu_E"][b] for tj in t])
            shapes_row = decode(z_e, z_i.expand(steps, -1))
            for j in range(steps):
                label = {(0, 0): "A", (steps - 1, steps - 1): "B", (0, steps - 1): "pose B, shape A",
                         (steps - 1, 0): "pose A, shape B"}.get((i, j), "")
                _draw(axes[i, j], shapes_row[j], label)
        fig.suptitle(f"{family}: z_E varies along columns, z_I along rows", fontsize=9)
        written.append(_save(fig, folder / f"interpolation_{family}.png"))

        queries = rows[:: max(1, len(rows) // 3)][:3]
        fig, axes = plt.subplots(2 * len(queries), 4, figsize=(8, 4 * len(queries)))
        for q, query in enumerate(queries):
            for g, key in enumerate(("mu_E", "mu_I")):
                members = np.array(rows)
                distance = ((codes[key][members] - codes[key][query]) ** 2).sum(-1).numpy()
                order = members[np.argsort(distance)]
                order = [m for m in order if m != query][:3]
                line = axes[2 * q + g]
                _draw(line[0], clouds[query].numpy(), f"query ({'z_E' if g == 0 else 'z_I'})")
                for k, match in enumerate(order):
                    _draw(line[k + 1], clouds[match].numpy(), dataset.items[indices[match]].subject)
        fig.suptitle(f"{family}: nearest by z_E (pose) and by z_I (shape)", fontsize=9)
        written.append(_save(fig, folder / f"retrieval_{family}.png"))

    c = vae.config
    z = [torch.randn(16, size) for size in (c.n_rotation, c.n_extrinsic, c.n_intrinsic)]
    _, x_gen = vae.decode(*z)
    generated = ae.decode(x_gen).numpy()
    fig, axes = plt.subplots(4, 4, figsize=(8, 8))
    for ax, cloud in zip(axes.ravel(), generated):
        _draw(ax, cloud)
    fig.suptitle("random samples from the prior (canonical frame)", fontsize=9)
    written.append(_save(fig, folder / "generations.png"))
    return written


def _save(fig, path: Path) -> Path:
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    import matplotlib.pyplot as plt

    plt.close(fig)
    return path
