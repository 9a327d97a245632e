"""Does a change to the kit's depth camera (models/gdvae/surface.py) still draw the same views? The
camera is rewritten for speed from time to time (issue 31); a faster camera that drew other views
would change what every autoencoder learns, and a short training run is too noisy to tell (its
heading median moves by 10 degrees from seed to seed). This draws camera views of a dataset's
training meshes with the current kit and with a reference copy of `surface.py` (any commit's:
`git show REV:models/gdvae/surface.py > /tmp/reference.py`), each with two seeds, and prints the
mean of a few per-view figures with its standard error: the three spreads of a view (eigenvalues
of its points' covariance), its height, its mean distance from the centre, and the spacing of its
points (mean nearest-neighbour distance: a draw that clumped points would show there).

    .venv/bin/python bench/camera_views.py DATASET --reference /tmp/reference.py [--limit 200]
"""
import argparse
import importlib.util
import sys
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT / "models"))

from gdvae.data import DepthCamera, load_dataset  # noqa: E402
from gdvae import surface  # noqa: E402

FIGURES = ("spread 1", "spread 2", "spread 3", "height", "radius", "spacing")


def reference_module(path: str):
    spec = importlib.util.spec_from_file_location("gdvae.surface_reference", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def view_figures(module, dataset, indices, seed: int, batches: int, batch: int) -> torch.Tensor:
    """[batches * batch, len(FIGURES)]: the figures of camera views drawn by `module`'s sampler."""
    sampler = module.PointSampler(dataset, indices, 256, seed, DepthCamera(), "cpu")
    meshes = torch.Generator().manual_seed(seed + 100)
    rows = []
    for _ in range(batches):
        chosen = torch.randint(0, len(sampler), (batch,), generator=meshes)
        views = sampler.views(chosen, 1, 1.0)  # every copy a camera view
        centred = views - views.mean(1, keepdim=True)
        spreads = torch.linalg.eigvalsh(centred.transpose(1, 2) @ centred / views.shape[1])
        distances = torch.cdist(views, views)
        distances.diagonal(dim1=1, dim2=2).fill_(float("inf"))
        rows.append(torch.stack([*spreads.unbind(-1), views[..., 2].amax(1) - views[..., 2].amin(1),
                                 views.norm(dim=-1).mean(1), distances.amin(-1).mean(-1)], -1))
    return torch.cat(rows)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("dataset")
    parser.add_argument("--reference", required=True, help="another kit's surface.py")
    parser.add_argument("--limit", type=int, default=200, help="meshes to load (default 200)")
    parser.add_argument("--batches", type=int, default=60, help="batches of 64 views per seed (default 60)")
    args = parser.parse_args()
    dataset = load_dataset(args.dataset, limit=args.limit)
    indices = dataset.indices("train") or list(range(len(dataset.meshes)))
    kits = {"reference": reference_module(args.reference), "this kit": surface}
    drawn = {(name, seed): view_figures(module, dataset, indices, seed, args.batches, 64)
             for name, module in kits.items() for seed in (1, 2)}
    views = len(next(iter(drawn.values())))
    print(f"{views} camera views per kit and seed, {len(indices)} meshes of {args.dataset}")
    print(f"{'':10s} {'reference (seeds 1, 2)':>24s} {'this kit (seeds 1, 2)':>24s} {'standard error':>15s}")
    for k, name in enumerate(FIGURES):
        reference = [drawn["reference", seed][:, k].mean().item() for seed in (1, 2)]
        current = [drawn["this kit", seed][:, k].mean().item() for seed in (1, 2)]
        error = drawn["reference", 1][:, k].std().item() / views ** 0.5
        print(f"{name:10s} {reference[0]:11.5f} {reference[1]:11.5f}  {current[0]:11.5f} {current[1]:11.5f}  "
              f"{error:14.5f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
