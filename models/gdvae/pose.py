"""The pose stage: the AE's pose encoder E_p taught the sim's pose, so that z_E has a pose to read.

Not in the paper, which has no labels. The STD shape encoder E_x must give the same code under any
heading, and a cloud whose front and back the encoder cannot tell apart says little about which leg
is forward: probes of x_c find almost none of the pose on fresh animals (models/EXPERIMENTS.md).
E_p reads the cloud turned back by the AE's own rotation estimate, so it sees every animal facing
the same way, and is trained to predict the top principal components of the sim's joint angles
(theta) of each family through a linear head per family. The heads exist only here; the bundle
keeps E_p, and the VAE's z_E encoder reads its code x_p beside x_c (vae.py, `pose_input`). The
node still runs the frozen encoders on unlabelled clouds.

Runs between the AE stage and the code bank, with the AE frozen; resumable like the others.
"""

from __future__ import annotations

import logging
import time

import numpy as np
import torch
from torch import nn

from .geometry import quaternion_to_matrix, random_rotation_matrices, rotate

log = logging.getLogger(__name__)


class PoseTargets:
    """Per family, theta's mean and its top `components` principal axes over the training meshes,
    with each component's spread: a mesh's target is its theta on those axes, in units of the
    spread (so every component weighs the same and a constant prediction scores 1)."""

    def __init__(self, truths: list[dict], components: int):
        if not truths or any("theta" not in t or "family" not in t for t in truths):
            raise ValueError("the pose stage needs the sim's ground truth (theta and family) of every training mesh")
        self.families = sorted({t["family"] for t in truths})
        self.family = np.array([self.families.index(t["family"]) for t in truths])
        self.components = components
        rows = np.zeros((len(truths), components), np.float32)
        self.explained = {}
        for f, name in enumerate(self.families):
            members = np.nonzero(self.family == f)[0]
            theta = np.array([truths[i]["theta"] for i in members], np.float64)
            if len(members) <= components:
                raise ValueError(f"the pose stage needs more than {components} training meshes of family {name!r} "
                                 f"(got {len(members)})")
            centred = theta - theta.mean(0)
            _, values, axes = np.linalg.svd(centred, full_matrices=False)
            projected = centred @ axes[:components].T
            rows[members] = projected / (projected.std(0) + 1e-9)
            self.explained[name] = float((values[:components] ** 2).sum() / (values ** 2).sum())
        self.rows = torch.from_numpy(rows)


def train_pose(ae, sampler, truths: list[dict], chosen, state: dict, save, progress, device, stages) -> None:
    """Trains `ae.pose_encoder` (from E_x's weights when it has E_x's widths, else from random
    weights) on views of the training meshes
    as the code bank draws them (`chosen.bank_view_share()` camera views), each turned by a random
    yaw and turned back by E_r's estimate."""
    targets = PoseTargets(truths, chosen.pose_components)
    log.info("pose: theta's top %d components per family hold %s of its variance", targets.components,
             ", ".join(f"{100 * share:.0f}% ({name})" for name, share in targets.explained.items()))
    heads = nn.Linear(ae.config.latent, targets.components * len(targets.families)).to(device)
    start = state["iteration"]
    if start == 0 and "pose_heads" not in state and ae.config.pose_hidden in (None, ae.config.shape_hidden):
        ae.pose_encoder.load_state_dict(ae.shape_encoder.state_dict())
    optimizer = torch.optim.Adam([*ae.pose_encoder.parameters(), *heads.parameters()], lr=chosen.pose_learning_rate)
    if "pose_heads" in state:
        heads.load_state_dict(state["pose_heads"])
        optimizer.load_state_dict(state["optimizer"])
    ae.eval()
    ae.pose_encoder.train()
    rows, family = targets.rows.to(device), torch.from_numpy(targets.family).to(device)
    generator = torch.Generator(device).manual_seed(chosen.seed + 2 + start)
    sampler.reseed(chosen.seed + 3 + start)
    partial = chosen.bank_view_share()
    total, started, last_save = chosen.pose_iterations, time.monotonic(), time.monotonic()
    for iteration in range(start, total):
        meshes = torch.randint(0, len(sampler), (chosen.pose_batch,), generator=generator, device=device)
        with torch.no_grad():
            clouds = rotate(sampler.views(meshes, 1, partial),
                            random_rotation_matrices(len(meshes), generator, ae.config.full_rotations, device))
            rotation = quaternion_to_matrix(ae.encode_rotation(clouds))
        predicted = heads(ae.encode_pose(clouds, rotation)).view(len(meshes), len(targets.families), -1)
        predicted = predicted[torch.arange(len(meshes), device=device), family[meshes]]
        loss = (predicted - rows[meshes]).pow(2).mean()
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        optimizer.step()
        progress.update(iteration + 1, lambda: {"pose": loss.item()}, force=iteration + 1 == total)
        if time.monotonic() - last_save > chosen.checkpoint_seconds and iteration + 1 < total:
            ae.pose_encoder.eval()
            save({"stage": "pose", "iteration": iteration + 1, "pose_heads": heads.state_dict(),
                  "optimizer": optimizer.state_dict()})
            ae.pose_encoder.train()
            last_save = time.monotonic()
    ae.pose_encoder.eval()
    stages.finish("pose", total, total, time.monotonic() - started, False)
