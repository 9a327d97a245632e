"""The taught stages: the AE's pose encoder E_p taught the sim's pose, so that z_E has a pose to
read, and its body encoder E_b taught the sim's body shape (beta), so that z_I has one.

Not in the paper, which has no labels. The STD shape encoder E_x must give the same code under any
heading, and a cloud whose front and back the encoder cannot tell apart says little about which leg
is forward: probes of x_c find almost none of the pose on fresh animals (models/EXPERIMENTS.md).
E_p reads the cloud turned back by the AE's own rotation estimate, so it sees every animal facing
the same way, and is trained to predict the top principal components of the sim's joint angles
(theta) of each family through a linear head per family. The heads exist only here; the bundle
keeps E_p, and the VAE's z_E encoder reads its code x_p beside x_c (vae.py, `pose_input`). The
node still runs the frozen encoders on unlabelled clouds.

E_b is E_p's twin for z_I (not in the paper either): it reads the cloud in the same frame and is
trained to predict each family's body-shape parameters beta (each mapped to [0, 1] by its family's
range, then in units of its spread), and z_I's encoder reads its code x_b beside x_c (`body_input`).
x_c, a reconstruction code, holds beta weakly; without labels the paper has only the spectrum for it.

Each runs between the AE stage and the code bank (the pose stage first), with the AE frozen;
resumable like the others.
"""

from __future__ import annotations

import logging
import time

import numpy as np
import torch
from torch import nn

from .evaluate import normalised_beta
from .geometry import quaternion_to_matrix, random_rotation_matrices, rotate

log = logging.getLogger(__name__)


class PoseTargets:
    """Per family, theta's mean and its top `components` principal axes over the training meshes,
    with each component's spread: a mesh's target is its theta on those axes, in units of the
    spread (so every component weighs the same and a constant prediction scores 1).

    `components` 0: every joint angle instead, each in units of its own spread (families with
    fewer angles padded, `mask` marking each family's own columns): the whole pose, not its
    main modes, for pose data whose bends are not a few (the prior's random poses).

    `whitened` False (what `vae.omega_pose` teaches mu_E, which has no head): the components keep
    their relative sizes (radians on the principal axes), one scale per family making their total
    variance `components`, so that distances between targets stay proportional to distances between
    poses (what retrieval by the code reads) and their spread suits the prior."""

    def __init__(self, truths: list[dict], components: int, whitened: bool = True):
        if not truths or any("theta" not in t or "family" not in t for t in truths):
            raise ValueError("the pose stage needs the sim's ground truth (theta and family) of every training mesh")
        if components < 0 or (components == 0 and not whitened):
            raise ValueError(f"pose components {components}: must be >= 0 (0: every joint angle, whitened only)")
        self.families = sorted({t["family"] for t in truths})
        self.family = np.array([self.families.index(t["family"]) for t in truths])
        width = components or max(len(t["theta"]) for t in truths)
        self.components = width
        rows = np.zeros((len(truths), width), np.float32)
        mask = np.zeros_like(rows) if components == 0 else np.ones_like(rows)
        self.explained = {}
        for f, name in enumerate(self.families):
            members = np.nonzero(self.family == f)[0]
            theta = np.array([truths[i]["theta"] for i in members], np.float64)
            if len(members) <= max(components, 1):
                raise ValueError(f"the pose stage needs more than {max(components, 1)} training meshes of family "
                                 f"{name!r} (got {len(members)})")
            centred = theta - theta.mean(0)
            if components == 0:
                spread = centred.std(0)
                rows[members, :theta.shape[1]] = np.where(spread > 0, centred / np.maximum(spread, 1e-12), 0.0)
                mask[members, :theta.shape[1]] = spread > 0
                self.explained[name] = 1.0
                continue
            _, values, axes = np.linalg.svd(centred, full_matrices=False)
            projected = centred @ axes[:components].T
            if whitened:
                rows[members] = projected / (projected.std(0) + 1e-9)
            else:
                rows[members] = projected * np.sqrt(components / max((projected ** 2).sum(1).mean(), 1e-12))
            self.explained[name] = float((values[:components] ** 2).sum() / (values ** 2).sum())
        self.rows = torch.from_numpy(rows)
        self.mask = torch.from_numpy(mask)


class BodyTargets:
    """Per family, each body-shape parameter of beta mapped to [0, 1] by the family's range (the
    dataset's `ranges`, as `evaluate` maps it for E_beta; the observed range where it has none),
    then centred and in units of its spread over the training meshes. Families with fewer
    parameters are padded, and `mask` says which columns are a family's own."""

    def __init__(self, truths: list[dict], ranges: dict):
        if not truths or any("beta" not in t or "family" not in t for t in truths):
            raise ValueError("the body stage needs the sim's ground truth (beta and family) of every training mesh")
        self.families = sorted({t["family"] for t in truths})
        self.family = np.array([self.families.index(t["family"]) for t in truths])
        self.components = max(len(t["beta"]) for t in truths)
        rows = np.zeros((len(truths), self.components), np.float32)
        mask = np.zeros_like(rows)
        for f, name in enumerate(self.families):
            members = np.nonzero(self.family == f)[0]
            beta = np.array([truths[i]["beta"] for i in members], np.float64)
            scaled = normalised_beta(beta, name, ranges)
            spread = scaled.std(0)
            if len(members) < 2 or not (spread > 0).any():
                raise ValueError(f"the body stage needs training meshes of family {name!r} whose beta differs "
                                 f"(got {len(members)})")
            width = beta.shape[1]
            rows[members, :width] = np.where(spread > 0, (scaled - scaled.mean(0)) / np.maximum(spread, 1e-12), 0.0)
            mask[members, :width] = spread > 0
        self.rows, self.mask = torch.from_numpy(rows), torch.from_numpy(mask)


def family_head_error(outputs: torch.Tensor, rows: torch.Tensor, mask: torch.Tensor,
                      family: torch.Tensor) -> torch.Tensor:
    """The mean squared error of linear heads per family ([B, families x columns] outputs) against
    each row's targets, read from the row's own family's head, over the columns `mask` marks."""
    chosen = outputs.view(len(outputs), -1, rows.shape[-1])[torch.arange(len(outputs), device=outputs.device), family]
    return ((chosen - rows).pow(2) * mask).sum() / mask.sum().clamp_min(1.0)


def train_pose(ae, sampler, truths: list[dict], chosen, state: dict, save, progress, device, stages) -> None:
    """Trains `ae.pose_encoder` (from E_x's weights when it has E_x's widths, else from random
    weights) on views of the training meshes as the code bank draws them (`chosen.bank_view_share()`
    camera views), each turned by a random yaw and turned back by E_r's estimate."""
    targets = PoseTargets(truths, chosen.pose_components)
    if chosen.pose_components:
        log.info("pose: theta's top %d components per family hold %s of its variance", targets.components,
                 ", ".join(f"{100 * share:.0f}% ({name})" for name, share in targets.explained.items()))
    else:
        log.info("pose: every joint angle of theta (%s)", ", ".join(
            f"{name} {int(targets.mask[targets.family == f][0].sum())}" for f, name in enumerate(targets.families)))
    if state["iteration"] == 0 and "pose_heads" not in state and ae.config.pose_hidden in (None, ae.config.shape_hidden):
        ae.pose_encoder.load_state_dict(ae.shape_encoder.state_dict())
    teach(ae, "pose", ae.pose_encoder, ae.encode_pose, targets, sampler, chosen.pose_iterations, chosen.pose_batch,
          chosen.pose_learning_rate, chosen, state, save, progress, device, stages)


def train_body(ae, sampler, truths: list[dict], ranges: dict, chosen, state: dict, save, progress, device,
               stages) -> None:
    """Trains `ae.body_encoder` (from random weights) as `train_pose` trains E_p, on beta."""
    targets = BodyTargets(truths, ranges)
    log.info("body: %d beta parameters per family (%s)", targets.components,
             ", ".join(f"{name} {int(targets.mask[targets.family == f][0].sum())}"
                       for f, name in enumerate(targets.families)))
    teach(ae, "body", ae.body_encoder, ae.encode_body, targets, sampler, chosen.body_iterations, chosen.pose_batch,
          chosen.body_learning_rate, chosen, state, save, progress, device, stages)


def teach(ae, stage: str, encoder, encode, targets, sampler, total: int, batch: int, learning_rate: float, chosen,
          state: dict, save, progress, device, stages) -> None:
    """One taught stage: `encoder` (read through `encode`) and a linear head per family trained to
    predict `targets.rows` (mean squared error over each family's own columns, `targets.mask`)."""
    heads_key = f"{stage}_heads"
    heads = nn.Linear(ae.config.latent, targets.components * len(targets.families)).to(device)
    start = state["iteration"]
    optimizer = torch.optim.Adam([*encoder.parameters(), *heads.parameters()], lr=learning_rate)
    if heads_key in state:
        heads.load_state_dict(state[heads_key])
        optimizer.load_state_dict(state["optimizer"])
    ae.eval()
    encoder.train()
    rows, mask = targets.rows.to(device), targets.mask.to(device)
    family = torch.from_numpy(targets.family).to(device)
    generator = torch.Generator(device).manual_seed(chosen.seed + 2 + start)
    sampler.reseed(chosen.seed + 3 + start)
    partial = chosen.bank_view_share()
    started, last_save = time.monotonic(), time.monotonic()
    for iteration in range(start, total):
        meshes = torch.randint(0, len(sampler), (batch,), generator=generator, device=device)
        with torch.no_grad():
            clouds = rotate(sampler.views(meshes, 1, partial),
                            random_rotation_matrices(len(meshes), generator, ae.config.full_rotations, device))
            rotation = quaternion_to_matrix(ae.encode_rotation(clouds))
        loss = family_head_error(heads(encode(clouds, rotation)), rows[meshes], mask[meshes], family[meshes])
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        optimizer.step()
        progress.update(iteration + 1, lambda: {stage: loss.item()}, force=iteration + 1 == total)
        if time.monotonic() - last_save > chosen.checkpoint_seconds and iteration + 1 < total:
            encoder.eval()
            save({"stage": stage, "iteration": iteration + 1, heads_key: heads.state_dict(),
                  "optimizer": optimizer.state_dict()})
            encoder.train()
            last_save = time.monotonic()
    encoder.eval()
    stages.finish(stage, total, total, time.monotonic() - started, False)
