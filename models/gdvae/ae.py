"""The point-cloud autoencoder (paper section 3, appendix "Autoencoder Details").

E_r maps a point cloud to a quaternion q; E_x maps it to a canonically oriented shape code x_c; the
decoder D maps x_c to a canonical point cloud P_c, which R(q) rotates onto the input. Two ways to
make x_c rotation-invariant:

- STD: the shape encoder sees the input under an extra random rotation (training only), and the
  cross-rotational consistency loss ties the codes of rotated copies together.
- FTL: the shape encoder produces a pose-aware code x~ of the rotated input; the rotational feature
  transform layer folds it into N_s 3-vectors and de-rotates them with R(q): x_c = U^-1(U(x~) R).
  The decoder reconstructs both x~ (the rotated input) and x_c (the canonical shape).

Rotation supervision: with aligned data (the sim's meshes are canonical), the geodesic loss d_R
trains E_r, the rotation predictor is pretrained first, and the true rotation replaces the
prediction in every other operation during training. Without alignment, a relative-rotation
consistency loss across the rotated copies trains E_r instead.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import nn

from .geometry import chamfer_and_hausdorff, geodesic_distance, quaternion_to_matrix, random_rotation_matrices, rotate
from .loss_parts import LossParts
from .nets import PointNet, mlp


@dataclass
class AEConfig:
    """Architecture and loss weights; defaults are the paper's (appendix, SMAL/SMPL)."""

    kind: str = "ftl"  # "ftl" or "std"
    supervised: bool = True
    points: int = 1600  # N_p
    latent: int = 999  # n = dim(x_c); a multiple of 3 for FTL (N_s = n / 3)
    rotation_hidden: tuple[int, ...] = (64, 128, 256, 512, 128)
    shape_hidden: tuple[int, ...] = (128, 256, 512, 836, 1024)
    decoder_width: int = 1250  # K: decoder hidden sizes (K, 2K, 4K); 1200 for STD in the paper
    full_rotations: bool = False  # SO(3) instead of rotations about the up axis
    alpha_chamfer: float = 200.0
    alpha_hausdorff: float = 1.0
    gamma_pose_aware: float = 100.0  # gamma~_P (FTL only)
    gamma_reconstruction: float = 20.0  # gamma_P: 20 (FTL), 250 (STD)
    gamma_consistency: float = 1.0  # gamma_c
    gamma_rotation: float = 10.0  # gamma_r
    gamma_weights: float = 2e-5  # gamma_w
    gamma_radius: float = 2e-5  # gamma_d
    copies: int = 3  # N_R
    # What E_r regresses. "quaternion": the paper's 4 numbers, normalised. "yaw" (rotations about
    # the up axis only): a direction (cos psi, sin psi) on the circle, turned into the quaternion
    # (cos psi/2, 0, 0, sin psi/2). A regressed quaternion needs a seam for yaw-only rotations (a
    # full turn maps q to -q); the circle has none, and the bundle still outputs q. (Issue 11.)
    rotation_head: str = "quaternion"
    # Not in the paper: E_p, a second shape encoder that reads the cloud turned back by R(q)^T (in
    # the frame the estimated heading gives it) and is trained on the sim's pose (pose.py), so that
    # the VAE's z_E reads a code that holds the pose. E_x of the STD kind must ignore the heading to
    # be rotation-invariant and carries little pose (models/EXPERIMENTS.md, "A pose encoder in the
    # estimated frame"). Its code x_p has x_c's size.
    pose_encoder: bool = False
    # E_p's per-point widths; None: E_x's (`shape_hidden`), and E_p starts from E_x's weights.
    # Narrower widths cost the node less encoder CPU; E_p then starts from random weights.
    pose_hidden: tuple[int, ...] | None = None
    # Not in the paper either: E_b, a third encoder in E_p's frame, trained on the sim's body-shape
    # parameters beta (pose.py), so that the VAE's z_I reads a code that holds the body and not the
    # pose: x_c, a reconstruction code, holds beta weakly (a ridge from x_c recovers R2 0.13-0.31 of it
    # on fresh subjects; models/EXPERIMENTS.md, "A body encoder for z_I"). Its code x_b has x_c's size.
    body_encoder: bool = False
    # E_b's per-point widths (from random weights).
    body_hidden: tuple[int, ...] = (32, 64, 128)

    def validate(self) -> None:
        if self.kind not in ("ftl", "std"):
            raise ValueError(f"AE kind must be 'ftl' or 'std', got {self.kind!r}")
        if self.rotation_head not in ("quaternion", "yaw"):
            raise ValueError(f"rotation_head must be 'quaternion' or 'yaw', got {self.rotation_head!r}")
        if self.rotation_head == "yaw" and self.full_rotations:
            raise ValueError("rotation_head = 'yaw' needs rotations about the up axis (full_rotations off)")
        if self.kind == "ftl" and self.latent % 3:
            raise ValueError(f"FTL latent size must be a multiple of 3, got {self.latent}")
        if self.points < 16 or self.latent < 3 or self.copies < 1:
            raise ValueError(f"points ({self.points}), latent ({self.latent}) and copies ({self.copies}) are too small")


def yaw_quaternion(direction: torch.Tensor) -> torch.Tensor:
    """[B, 2] (cos psi, sin psi), up to scale -> [B, 4] the rotation by psi about z, (w, x, y, z)
    with w >= 0: normalise (1 + cos psi, 0, 0, sin psi), which is cos(psi/2) (cos psi/2, 0, 0,
    sin psi/2). Its rotation matrix is [[c, -s, 0], [s, c, 0], [0, 0, 1]] for every direction (the
    q / -q flip at psi = pi is the double cover, not a seam in the rotation); only elementary ops,
    so it exports to ONNX as it is."""
    c, s = (direction / direction.norm(dim=-1, keepdim=True).clamp_min(1e-8)).unbind(-1)
    zero = torch.zeros_like(c)
    q = torch.stack([1 + c, zero, zero, s], -1)
    return q / q.norm(dim=-1, keepdim=True).clamp_min(1e-8)


@dataclass
class AEOutput:
    q: torch.Tensor  # [B, 4] predicted quaternion
    rotation: torch.Tensor  # [B, 3, 3] the rotation used (predicted, or true when substituted)
    x_c: torch.Tensor  # [B, n] canonical shape code
    canonical: torch.Tensor  # [B, N, 3] P_c = D(x_c)
    reconstruction: torch.Tensor  # [B, N, 3] P^ = P_c rotated by `rotation`
    pose_aware: torch.Tensor | None = None  # FTL: D(x~), the rotated input's reconstruction


class Autoencoder(nn.Module):
    def __init__(self, config: AEConfig):
        super().__init__()
        config.validate()
        self.config = config
        self.rotation_encoder = PointNet(config.rotation_hidden, 2 if config.rotation_head == "yaw" else 4)
        self.shape_encoder = PointNet(config.shape_hidden, config.latent)
        self.pose_encoder = (PointNet(config.pose_hidden or config.shape_hidden, config.latent)
                             if config.pose_encoder else None)
        self.body_encoder = PointNet(config.body_hidden, config.latent) if config.body_encoder else None
        k = config.decoder_width
        self.decoder = mlp(config.latent, (k, 2 * k, 4 * k), 3 * config.points)

    def encode_rotation(self, points: torch.Tensor) -> torch.Tensor:
        out = self.rotation_encoder(points)
        if self.config.rotation_head == "yaw":
            return yaw_quaternion(out)
        return out / out.norm(dim=-1, keepdim=True).clamp_min(1e-8)

    def encode_shape(self, points: torch.Tensor, rotation: torch.Tensor, generator=None) -> tuple[torch.Tensor, torch.Tensor | None]:
        """(x_c, x~): the canonical code, and for FTL the pose-aware code it was derotated from."""
        if self.config.kind == "ftl":
            pose_aware = self.shape_encoder(points)
            folded = pose_aware.view(points.shape[0], -1, 3)
            # Rows times R apply R^T to each 3-vector: the inverse of the rotation carrying the
            # canonical shape onto the input.
            return (folded @ rotation).reshape(points.shape[0], -1), pose_aware
        if self.training:
            scramble = random_rotation_matrices(len(points), generator, self.config.full_rotations, points.device)
            points = rotate(points, scramble)
        return self.shape_encoder(points), None

    def encode_pose(self, points: torch.Tensor, rotation: torch.Tensor) -> torch.Tensor | None:
        """x_p: E_p's code of the points turned back by `rotation` (None without a pose encoder)."""
        if self.pose_encoder is None:
            return None
        return self.pose_encoder(rotate(points, rotation.transpose(-1, -2)))

    def encode_body(self, points: torch.Tensor, rotation: torch.Tensor) -> torch.Tensor | None:
        """x_b: E_b's code of the points turned back by `rotation` (None without a body encoder)."""
        if self.body_encoder is None:
            return None
        return self.body_encoder(rotate(points, rotation.transpose(-1, -2)))

    def taught_codes(self, points: torch.Tensor, rotation: torch.Tensor) -> dict:
        """The codes of the encoders taught the sim's truth, as the VAE's encode takes them:
        {"x_p": E_p's or None, "x_b": E_b's or None}."""
        return {"x_p": self.encode_pose(points, rotation), "x_b": self.encode_body(points, rotation)}

    def decode(self, x_c: torch.Tensor) -> torch.Tensor:
        return self.decoder(x_c).view(x_c.shape[0], -1, 3)

    def forward(self, points: torch.Tensor, true_rotation: torch.Tensor | None = None, generator=None) -> AEOutput:
        q = self.encode_rotation(points)
        rotation = quaternion_to_matrix(q)
        if true_rotation is not None:
            rotation = true_rotation
        x_c, pose_aware = self.encode_shape(points, rotation, generator)
        canonical = self.decode(x_c)
        return AEOutput(
            q=q,
            rotation=rotation,
            x_c=x_c,
            canonical=canonical,
            reconstruction=rotate(canonical, rotation),
            pose_aware=None if pose_aware is None else self.decode(pose_aware),
        )


@dataclass
class AELosses:
    total: torch.Tensor
    parts: LossParts


def reconstruction_distance(config: AEConfig, a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """D_P = alpha_C d_C + alpha_H d_H, averaged over the batch."""
    chamfer, hausdorff = chamfer_and_hausdorff(a, b)
    return (config.alpha_chamfer * chamfer + config.alpha_hausdorff * hausdorff).mean()


def pairwise_mean(values: torch.Tensor, copies: int, distance) -> torch.Tensor:
    """Mean of distance(values[i], values[j]) over pairs of rotated copies i < j of each shape;
    `values` is laid out copy-major: [copies * B, ...]."""
    grouped = values.view(copies, -1, *values.shape[1:])
    terms = [distance(grouped[i], grouped[j]) for i in range(copies) for j in range(i + 1, copies)]
    return torch.stack(terms).mean() if terms else values.new_zeros(())


def ae_loss(model: Autoencoder, canonical_points: torch.Tensor, generator=None,
            rotation_only: bool = False, views: torch.Tensor | None = None) -> tuple[AELosses, AEOutput]:
    """One training step's loss on a batch of canonical point clouds [B, N, 3].

    Each shape is copied N_R times under independent random rotations (copy-major layout).
    `rotation_only` trains E_r alone (the supervised pretraining phase). `views` [N_R * B, N, 3]:
    what each copy shows the encoder instead of the whole cloud (e.g. partial views, canonical
    frame); the reconstruction target stays the whole cloud. Supervised AEs only.
    """
    config = model.config
    copies = config.copies
    batch = len(canonical_points)
    rotations = random_rotation_matrices(copies * batch, generator, config.full_rotations, canonical_points.device)
    targets = canonical_points.repeat(copies, 1, 1)
    observed = rotate(targets, rotations)
    if views is None:
        inputs = observed
    elif not config.supervised:
        raise ValueError("partial views need the supervised AE (its target is the whole canonical cloud)")
    elif views.shape[0] != copies * batch:
        raise ValueError(f"views has {views.shape[0]} clouds for {copies} copies of {batch} shapes")
    else:
        inputs = rotate(views, rotations)

    q = model.encode_rotation(inputs)
    predicted = quaternion_to_matrix(q)
    if config.supervised:
        rotation_loss = config.gamma_rotation * geodesic_distance(predicted, rotations).mean()
    else:
        relative = rotations.transpose(-1, -2) @ predicted
        rotation_loss = config.gamma_rotation * pairwise_mean(relative, copies, lambda a, b: geodesic_distance(a, b).mean())
    parts: dict[str, torch.Tensor] = {"rotation": rotation_loss}
    if rotation_only:
        return AELosses(rotation_loss, LossParts(parts)), None

    used = rotations if config.supervised else predicted
    x_c, pose_aware_code = model.encode_shape(inputs, used, generator)
    canonical = model.decode(x_c)
    if config.supervised:
        reconstruction = config.gamma_reconstruction * reconstruction_distance(config, targets, canonical)
    else:
        reconstruction = config.gamma_reconstruction * reconstruction_distance(config, inputs, rotate(canonical, used))
    parts["reconstruction"] = reconstruction
    total = rotation_loss + reconstruction
    if pose_aware_code is not None:
        pose_aware = config.gamma_pose_aware * reconstruction_distance(config, observed, model.decode(pose_aware_code))
        parts["pose_aware"] = pose_aware
        total = total + pose_aware
    consistency = config.gamma_consistency * pairwise_mean(x_c, copies, lambda a, b: (a - b).pow(2).sum(-1).mean())
    radius = config.gamma_radius * x_c.pow(2).sum(-1).mean()
    weights = config.gamma_weights * sum(p.pow(2).sum() for name, p in model.named_parameters() if p.dim() > 1)
    parts.update(consistency=consistency, radius=radius, weight_decay=weights)
    total = total + consistency + radius + weights
    parts["total"] = total
    output = AEOutput(q=q, rotation=used, x_c=x_c, canonical=canonical, reconstruction=rotate(canonical, used))
    return AELosses(total, LossParts(parts)), output


@torch.no_grad()
def restore_batch_norms(ae: Autoencoder, clouds: torch.Tensor) -> None:
    """Each PointNet batch norm set to its input's mean and spread over `clouds` [B, N, 3] (inputs
    like the training ones), so that training mode normalises as before the export's folding (an
    autoencoder imported from a bundle, `import_bundle.py`, has them as identities)."""
    norms = [m for m in ae.modules() if isinstance(m, torch.nn.BatchNorm1d)]
    seen: dict[torch.nn.Module, tuple[torch.Tensor, torch.Tensor]] = {}

    def record(module, inputs, _output):
        x = inputs[0].transpose(0, 1).reshape(inputs[0].shape[1], -1)  # [C, B * N]
        seen[module] = (x.mean(1), x.var(1, unbiased=False))

    hooks = [m.register_forward_hook(record) for m in norms]
    was_training = ae.training
    ae.eval()
    try:
        turned = rotate(clouds, random_rotation_matrices(len(clouds), None, ae.config.full_rotations, clouds.device))
        ae.encode_rotation(turned)
        ae.shape_encoder(turned)
    finally:
        for hook in hooks:
            hook.remove()
        ae.train(was_training)
    for module in norms:
        mean, variance = seen[module]
        variance = variance.clamp_min(2 * module.eps)
        module.weight.copy_(variance.sqrt())
        module.bias.copy_(mean)
        module.running_mean.copy_(mean)
        module.running_var.copy_(variance - module.eps)
