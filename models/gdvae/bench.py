"""Throughput of the training path (issue 31): how many clouds per second the batch maker gives,
and how many iterations per second the AE and VAE steps run, for a recipe on a device. A GPU
recipe is only as fast as its slowest part; this says which part that is, with the command that
reproduces it. Figures, not a test: `python -m gdvae bench DATASET [--recipe R] [--device D]`.
"""

from __future__ import annotations

import time

import torch

from .ae import Autoencoder, ae_loss
from .data import DepthCamera, MeshDataset
from .surface import PointSampler
from .train import Recipe, fused_adam
from .vae import LatentVAE, vae_loss


def timed(step, seconds: float, device: torch.device) -> tuple[int, float]:
    """Runs `step` once to warm up, then for about `seconds`: (steps, wall seconds)."""
    step()
    synchronize(device)
    started, steps = time.perf_counter(), 0
    while time.perf_counter() - started < seconds:
        step()
        steps += 1
    synchronize(device)
    return steps, time.perf_counter() - started


def operator_calls(step) -> int:
    """Operators one call of `step` sends to the device's kernels (what reaches the backend after
    composite operators are taken apart; views included): on a GPU each costs the host a few
    microseconds whatever its size, so a step of small tensors with thousands of them is bound by
    the host, not the device."""
    from torch.utils._python_dispatch import TorchDispatchMode

    class Count(TorchDispatchMode):
        calls = 0

        def __torch_dispatch__(self, func, types, args=(), kwargs=None):
            Count.calls += 1
            return func(*args, **(kwargs or {}))

    with Count():
        step()
    return Count.calls


def synchronize(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def bench(dataset: MeshDataset, chosen: Recipe, device: torch.device, seconds: float = 10.0,
          seed: int = 0) -> dict:
    """clouds/s of the batch maker on `device` (one AE batch: its canonical clouds and every
    copy's view), it/s and clouds/s of the AE step on ready batches and with its batches made as
    training makes them (in the training process, on the device), it/s of the VAE step on a code
    bank of the recipe's sizes (random codes: the step's cost does not depend on their values)."""
    torch.manual_seed(seed)
    indices = dataset.indices("train") or list(range(len(dataset.meshes)))
    camera = DepthCamera() if chosen.depth_camera_views else None
    started = time.perf_counter()
    sampler = PointSampler(dataset, indices, chosen.ae.points, seed, camera, device)
    synchronize(device)
    cache_seconds = time.perf_counter() - started
    copies, batch = chosen.ae.copies, chosen.ae_batch
    partial = chosen.partial_views

    made: list = []

    def make_batch():
        chosen_meshes, clouds = sampler.batch(batch)
        return clouds, sampler.views(chosen_meshes, copies, partial) if partial > 0 else None

    def make():
        made.append(make_batch())
        del made[:-4]  # keep a few ready batches for the AE step

    steps, wall = timed(make, seconds, device)
    clouds_per_batch = batch * (1 + (copies if partial > 0 else 0))
    maker = {"batches_per_s": steps / wall, "clouds_per_s": steps * clouds_per_batch / wall,
             "clouds_per_batch": clouds_per_batch, "cache_seconds": cache_seconds,
             "cache_mb": sampler.cache.bytes() / 1e6, "operators": operator_calls(make)}

    ae = Autoencoder(chosen.ae).to(device).train()
    optimizer = torch.optim.Adam(ae.parameters(), lr=chosen.ae_learning_rate, fused=fused_adam(device))

    def ae_step(clouds, views):
        losses, _ = ae_loss(ae, clouds, views=views)
        optimizer.zero_grad(set_to_none=True)
        losses.total.backward()
        optimizer.step()

    counter = iter(range(1 << 62))
    steps, wall = timed(lambda: ae_step(*made[next(counter) % len(made)]), seconds, device)
    ae_figures = {"it_per_s": steps / wall, "clouds_per_s": steps * batch / wall, "batch": batch,
                  "operators": operator_calls(lambda: ae_step(*made[0]))}
    steps, wall = timed(lambda: ae_step(*make_batch()), seconds, device)
    ae_figures.update(with_batches_it_per_s=steps / wall, with_batches_clouds_per_s=steps * batch / wall)

    vae = LatentVAE(chosen.vae).to(device).train()
    vae_optimizer = torch.optim.Adam(vae.parameters(), lr=chosen.vae_learning_rate, fused=fused_adam(device))
    size, vae_batch = 4096, chosen.vae_batch
    q = torch.nn.functional.normalize(torch.randn(size, 4, device=device), dim=-1)
    x_c = torch.randn(size, chosen.vae.latent, device=device)
    spectra = (torch.rand(size, chosen.vae.spectrum, device=device).cumsum(-1) + 1.0)
    vae.flow.input.fit(spectra)
    generator = torch.Generator(device="cpu").manual_seed(seed)

    def vae_step():
        rows = torch.randint(0, size, (vae_batch,), generator=generator).to(device)
        losses = vae_loss(vae, q[rows], x_c[rows], spectra[rows], dataset_size=size)
        vae_optimizer.zero_grad(set_to_none=True)
        losses.total.backward()
        torch.nn.utils.clip_grad_norm_(vae.parameters(), 100.0)  # as train_vae does
        vae_optimizer.step()

    steps, wall = timed(vae_step, seconds, device)
    vae_figures = {"it_per_s": steps / wall, "clouds_per_s": steps * vae_batch / wall, "batch": vae_batch,
                   "operators": operator_calls(vae_step)}
    return {"recipe": chosen.name, "device": str(device), "threads": torch.get_num_threads(),
            "depth_camera_views": chosen.depth_camera_views, "partial_views": partial,
            "meshes": len(indices), "points": chosen.ae.points, "copies": copies,
            "batch_maker": maker, "ae_step": ae_figures, "vae_step": vae_figures,
            "seconds_per_part": seconds}


def report(figures: dict) -> str:
    m, a, v = figures["batch_maker"], figures["ae_step"], figures["vae_step"]
    share = a["with_batches_it_per_s"] / m["batches_per_s"]  # a batch's making time over a stage step's
    return "\n".join([
        f"recipe {figures['recipe']} on {figures['device']} ({figures['threads']} threads), "
        f"{figures['meshes']} meshes, {figures['points']} points, {figures['copies']} copies, "
        f"partial views {figures['partial_views']}"
        f"{' (depth camera)' if figures['depth_camera_views'] else ''}",
        *([f"  dataset:     {figures['dataset']['meshes']} meshes read and checked in "
           f"{figures['dataset']['load_seconds']:.1f} s"] if "dataset" in figures else []),
        f"  meshes:      {m['cache_mb']:.0f} MB on {figures['device']} in {m['cache_seconds']:.1f} s",
        f"  batch maker: {m['batches_per_s']:.2f} AE batches/s, {m['clouds_per_s']:.0f} clouds/s "
        f"({m['clouds_per_batch']} clouds a batch, on {figures['device']}); {m['operators']} operators a batch",
        f"  AE step:     {a['it_per_s']:.2f} it/s at batch {a['batch']} ({a['clouds_per_s']:.0f} clouds/s) on ready batches, "
        f"{a['with_batches_it_per_s']:.2f} it/s making its batches as training does; {a['operators']} operators a step",
        f"  VAE step:    {v['it_per_s']:.2f} it/s at batch {v['batch']} ({v['clouds_per_s']:.0f} codes/s); "
        f"{v['operators']} operators a step",
        f"  making the batches takes about {min(share, 1.0):.0%} of the AE stage's time",
        *([f"  memory:      {figures['peak_resident_mb'] / 1024:.1f} GB at the process's peak (resident)"]
          if "peak_resident_mb" in figures else []),
    ])

