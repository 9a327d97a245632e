"""The latent VAE on the autoencoder's codes (paper section 4, appendix "VAE Details").

Inputs are an AE encoding (q, x_c) and the shape's spectrum lambda. Encoders give diagonal
Gaussians over z_R (from q), z_E and z_I (from x_c); deterministic decoders give q^ = D_q(z_R) and
x_c^ = D_x(z_E, z_I); the spectral flow maps lambda to mu~_I = f_lambda(lambda), with a posterior
variance Sigma~_I(lambda) for training.

Two training regimes share architecture and inference, and differ only in the training pass:
- GDVAE++: reconstruct x_c from (z_E, z~_I), z~_I ~ N(f_lambda(lambda), Sigma~_I(lambda)); the
  disentanglement losses use mu~_I; mu_I(x_c) is pulled towards mu~_I with the gradient cut
  through mu~_I (so extrinsic information in mu_I cannot leak into the flow).
- GDVAE-FO ("flow only"): reconstruct from (z_E, z_I) with z_I from x_c; the spectrum enters only
  through the consistency losses and the flow likelihood.
A third regime, "paired" (not in the paper), is FO's pass plus two supervised terms from the sim's
ground truth, swap reconstruction and identity contrast (paired.py), on batches of paired meshes.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import nn

from .flow import SpectralFlow
from .geometry import normalize_quaternion, quaternion_distance
from .hfvae import hfvae_terms
from .loss_parts import LossParts
from .nets import mlp
from .paired import identity_contrast, swap_error
from .pose import family_head_error
from .spectrum import spectral_distance_torch


@dataclass
class VAEConfig:
    """Defaults: the paper's values for its mixed human-animal (HA) dataset, the closest to the
    sim's two families trained together (appendix Table "VAE hyper-parameters")."""

    regime: str = "gdvae++"  # or "fo", or "paired" (FO's pass + the paired terms)
    latent: int = 999  # n = dim(x_c), from the AE
    spectrum: int = 22  # N_lambda (= n_I)
    n_rotation: int = 3
    n_extrinsic: int = 10
    width_scale: float = 1.0  # multiplies every hidden width (CPU recipes shrink the networks)
    flow_layers: int = 9
    flow_hidden: int = 400
    beta_intra_tc: float = 1.0  # beta_1
    beta_dimension_kl: float = 20.0  # beta_2
    beta_mutual_information: float = 1.0  # beta_3
    beta_inter_tc: float = 80.0  # beta_4
    omega_reconstruction: float = 360.0  # omega_R
    omega_quaternion: float = 10.0  # omega_q
    omega_flow: float = 1.0  # omega_p
    omega_intrinsic: float = 450.0  # omega_I (FO: 0 for HA)
    omega_spectrum: float = 100.0  # omega_lambda (FO: 800)
    omega_covariance: float = 60.0  # omega_Sigma
    omega_jacobian: float = 200.0  # omega_J
    # Not in the paper: trains Sigma_I(x_c) as the Gaussian NLL of mu_I's error (gradients reach
    # only the variance network). In GDVAE++ nothing else trains it, and the node's shape fusion
    # weighs frames by it.
    omega_variance: float = 1.0
    # The paper divides L_R's relative error by n = dim(x_c). With our minibatch HFVAE estimates
    # that leaves the reconstruction gradient ~1/n of the KL terms' and the decoder collapses to
    # the mean code (relative error ~0.86 after 3000 iterations); False drops the 1/n.
    reconstruction_per_dimension: bool = True
    # Not in the paper: ramp the four HFVAE betas linearly from 0 over this many iterations, so
    # the decoder can learn to use z_E before its information costs anything (0: off).
    beta_warmup_iterations: int = 0
    # L_Sigma's form. "covariance": the paper's L1 norm of the raw cross-covariances between the
    # group means, whose sampling-noise floor grows with the means' scale (so it can push mu_E to a
    # constant); "correlation": the sum of squared cross-correlations, scale-free, with a floor of
    # about 1/batch per pair of dimensions; "off". (Issue 11, cause 3.)
    covariance_form: str = "covariance"
    # Not in the paper: weight of a view-consistency term. The code bank holds several views of
    # each training mesh, which share its spectrum; the term is the mean squared distance between
    # mu_I of two views of one mesh over twice the variance of mu_I across the batch (0 when the
    # views agree, about 1 when they are as far apart as two meshes), so z_I is pushed to name the
    # mesh, not the view. Batches are then drawn as pairs of views (`train_vae`). 0: off.
    omega_view: float = 0.0
    # The paired regime's terms (paired.py; 0: off). Swap: the relative error of the two swapped
    # decodings against the codes of the swapped meshes (as L_R's without 1/n). Contrast: InfoNCE
    # on mu_I, positives the same subject in another pose and view, negatives the family's other
    # subjects, at `contrast_temperature` times the batch's mean squared distance.
    omega_swap: float = 0.0
    omega_contrast: float = 0.0
    contrast_temperature: float = 0.1
    # Paired batches only (then drawn as quadruples, paired.PairedBatches): the same InfoNCE on
    # mu_E with the pose for the subject: positives the same shared pose on another subject seen
    # from another view, negatives the family's other poses in the batch. 0: off.
    omega_pose_contrast: float = 0.0
    # Paired batches only: L_R's target is the mesh's whole-surface code (the bank's target), not
    # the view's own code. The view's code also holds what the camera saw of the mesh; asked to
    # reproduce it, the decoder makes z_E carry the view, since z_I is held to the subject.
    reconstruct_canonical: bool = False
    # Not in the paper: mu_I taught the sim's body shape directly. A linear head per family (only
    # in training; not in the bundle) maps mu_I to the normalised beta of pose.BodyTargets, and its
    # mean squared error is added with this weight. 0: off. `body_heads` is the heads' output width
    # (beta parameters x families), set by `train` from the dataset.
    omega_body: float = 0.0
    body_heads: int = 0
    # With omega_body: no head; mu_I's first units (one per beta parameter, padded per family) are
    # regressed on the normalised beta directly, so that distances in mu_I are distances between
    # bodies, as omega_pose makes them between poses in mu_E.
    body_direct: bool = False
    # Not in the paper: mu_E taught the sim's pose directly, its mean squared error against the
    # mesh's theta on its family's top n_extrinsic principal axes (pose.PoseTargets, `whitened`
    # False: radians, so that distances in mu_E are distances between poses) added with this weight.
    # No head: a head would leave mu_E's own geometry free, and retrieval by mu_E reads that
    # geometry (models/EXPERIMENTS.md, "mu_E taught the pose"). 0: off.
    omega_pose: float = 0.0
    # Not in the paper: mu_I taught to tell subjects apart on the node's own clouds. The same
    # InfoNCE as omega_contrast, on batches of x_c the node computed on sim recordings (several
    # frames of each of many subjects; node_identity.py, `train --node-states`), added with this
    # weight to every step's objective on the code bank. 0: off.
    omega_node_identity: float = 0.0
    # Not in the paper: z_I's encoder, the spectral flow and the rotation branch keep the weights
    # the VAE starts with (another run's or an imported bundle's VAE, `train --init-from`); only
    # z_E's encoder and the shape decoder train. A live pose code is then added to a model whose
    # shape code, and so the node's identity, stays exactly what it was.
    keep_intrinsic: bool = False
    # The converse, not in the paper either: z_E's encoder and the rotation branch keep the starting
    # VAE's weights; z_I's encoder, the flow and the shape decoder train. A shape code taught on
    # another (larger) set of subjects replaces a model's z_I while its pose code stays exactly what
    # it was.
    keep_extrinsic: bool = False
    # Size of the pose code x_p that z_E's encoder reads beside x_c (the AE's pose encoder, pose.py;
    # 0: none, the paper's z_E from x_c alone).
    pose_input: int = 0
    # Size of the body code x_b that z_I's encoder reads beside x_c (the AE's body encoder, taught
    # the sim's beta, pose.py; 0: none, the paper's z_I from x_c alone).
    body_input: int = 0

    @property
    def paired(self) -> bool:
        """Whether training batches must be paired triples (paired.py)."""
        return self.omega_swap > 0 or self.omega_contrast > 0 or self.omega_pose_contrast > 0 or self.reconstruct_canonical

    @property
    def keeps_start(self) -> bool:
        """Whether part of the VAE keeps the starting VAE's weights (`keep_intrinsic`, `keep_extrinsic`)."""
        return self.keep_intrinsic or self.keep_extrinsic

    @property
    def n_intrinsic(self) -> int:
        return self.spectrum

    def validate(self) -> None:
        if self.regime not in ("gdvae++", "fo", "paired"):
            raise ValueError(f"regime must be 'gdvae++', 'fo' or 'paired', got {self.regime!r}")
        for name in ("omega_swap", "omega_contrast", "omega_pose_contrast", "omega_body", "omega_pose",
                     "omega_node_identity"):
            if not getattr(self, name) >= 0:
                raise ValueError(f"{name} must be >= 0 (0: off), got {getattr(self, name)}")
        if not self.contrast_temperature > 0:
            raise ValueError(f"contrast_temperature must be > 0, got {self.contrast_temperature}")
        if self.body_direct and not self.omega_body > 0:
            raise ValueError("body_direct says how omega_body teaches mu_I: it goes with omega_body > 0")
        for weight, kept, code in (("omega_pose", "keep_extrinsic", "mu_E"), ("omega_body", "keep_intrinsic", "mu_I"),
                                   ("omega_node_identity", "keep_intrinsic", "mu_I")):
            if getattr(self, weight) > 0 and getattr(self, kept):
                raise ValueError(f"{weight} teaches {code}, whose encoder {kept} holds fixed: use one or the other")
        if self.paired and self.regime == "gdvae++":
            raise ValueError("the paired terms decode z_I of x_c: use them with the 'paired' (or 'fo') regime")
        if self.pose_input < 0 or self.body_input < 0:
            raise ValueError(f"pose_input and body_input must be >= 0 (0: no such code), got {self.pose_input}, "
                             f"{self.body_input}")
        if min(self.latent, self.spectrum, self.n_rotation, self.n_extrinsic) < 1:
            raise ValueError("latent sizes must be positive")
        if self.covariance_form not in ("covariance", "correlation", "off"):
            raise ValueError(f"covariance_form must be 'covariance', 'correlation' or 'off', got {self.covariance_form!r}")
        if not self.omega_view >= 0:
            raise ValueError(f"omega_view must be >= 0 (0: off), got {self.omega_view}")
        if self.keep_intrinsic and self.keep_extrinsic:
            raise ValueError("keep_intrinsic and keep_extrinsic together would train the decoder alone")
        if self.keep_intrinsic and self.regime == "gdvae++":
            raise ValueError("keep_intrinsic holds z_I's encoder fixed, which GDVAE++ decodes only through the flow: "
                             "use it with the 'fo' or 'paired' regime")

    @classmethod
    def flow_only(cls, **overrides) -> "VAEConfig":
        """GDVAE-FO: the paper's FO weights for HA (omega_lambda = 800, omega_I = 0)."""
        return cls(**{"regime": "fo", "omega_spectrum": 800.0, "omega_intrinsic": 0.0, **overrides})

    @classmethod
    def paired_regime(cls, **overrides) -> "VAEConfig":
        """FO's weights, L_R as the relative error (the swap's scale: z_E must be worth decoding),
        squared cross-correlations for L_Sigma (scale-free, the screen's pick for a live z_E), and
        the two paired terms. models/README.md, "The paired regime", says how these were chosen."""
        return cls.flow_only(**{"regime": "paired", "reconstruction_per_dimension": False,
                                "covariance_form": "correlation", "omega_swap": 360.0, "omega_contrast": 100.0,
                                "reconstruct_canonical": True, **overrides})


def _w(size: int, scale: float) -> int:
    return max(8, int(round(size * scale)))


class GaussianEncoder(nn.Module):
    """mu and log-variance networks, each a fully connected stack."""

    def __init__(self, inputs: int, outputs: int, mean_hidden, variance_hidden):
        super().__init__()
        self.mean = mlp(inputs, mean_hidden, outputs)
        self.log_variance = mlp(inputs, variance_hidden, outputs)

    def forward(self, x):
        return self.mean(x), self.log_variance(x).clamp(-12.0, 6.0)


class RotationEncoder(nn.Module):
    """mu_R and Sigma_R from q: a shared stack (256, 128) into 64, then one linear layer each."""

    def __init__(self, outputs: int, scale: float):
        super().__init__()
        self.shared = nn.Sequential(mlp(4, (_w(256, scale), _w(128, scale)), _w(64, scale)), nn.ReLU())
        self.mean = nn.Linear(_w(64, scale), outputs)
        self.log_variance = nn.Linear(_w(64, scale), outputs)

    def forward(self, q):
        h = self.shared(q)
        return self.mean(h), self.log_variance(h).clamp(-12.0, 6.0)


class LatentVAE(nn.Module):
    def __init__(self, config: VAEConfig):
        super().__init__()
        config.validate()
        self.config = config
        s = config.width_scale
        n, n_e, n_i = config.latent, config.n_extrinsic, config.n_intrinsic
        self.rotation = RotationEncoder(config.n_rotation, s)
        self.extrinsic = GaussianEncoder(n + config.pose_input, n_e, tuple(_w(h, s) for h in (2000, 1600, 1200, 400)),
                                         tuple(_w(h, s) for h in (2000, 1200, 400)))
        self.intrinsic = GaussianEncoder(n + config.body_input, n_i, tuple(_w(h, s) for h in (2000, 1600, 1200, 400)),
                                         tuple(_w(h, s) for h in (2000, 1200, 400)))
        # Sigma~_I(lambda): only the GDVAE++ training pass samples z~_I, so only it has one.
        self.spectral_variance = mlp(config.spectrum, (2 * n_i, 2 * n_i), n_i) if config.regime == "gdvae++" else None
        self.flow = SpectralFlow(config.spectrum, config.flow_layers, _w(config.flow_hidden, s))
        self.decode_rotation = mlp(config.n_rotation, tuple(_w(h, s) for h in (64, 128, 256)), 4)
        self.decode_shape = mlp(n_e + n_i, tuple(_w(h, s) for h in (600, 1200, 1600, 2000)), n)
        self.body_heads = nn.Linear(n_i, config.body_heads) if config.omega_body > 0 and config.body_heads else None
        # E[||x_c||^2] over the training codes, for the normalized reconstruction error.
        self.register_buffer("code_norm", torch.ones(()))
        if config.keep_intrinsic:
            for fixed in (self.rotation, self.intrinsic, self.flow, self.decode_rotation):
                fixed.requires_grad_(False)
        if config.keep_extrinsic:
            for fixed in (self.rotation, self.extrinsic, self.decode_rotation):
                fixed.requires_grad_(False)

    def trained_parameters(self) -> list[nn.Parameter]:
        """The parameters training updates (all but the fixed branches of `keep_intrinsic` or
        `keep_extrinsic`)."""
        return [p for p in self.parameters() if p.requires_grad]

    def encode(self, q, x_c, x_p=None, x_b=None):
        """Posterior means and log-variances: ((mu_R, lv_R), (mu_E, lv_E), (mu_I, lv_I)). `x_p`: the
        pose code, which z_E's encoder reads beside x_c when `pose_input` > 0; `x_b`: the body code,
        which z_I's encoder reads beside x_c when `body_input` > 0."""
        for code, size, name, latent in ((x_p, self.config.pose_input, "pose", "z_E"),
                                         (x_b, self.config.body_input, "body", "z_I")):
            if (code is None) != (size == 0):
                raise ValueError(f"this VAE's {latent} reads a {name} code of {size} numbers; got "
                                 f"{'none' if code is None else code.shape[-1]}")
        return self.rotation(q), self.extrinsic(with_code(x_c, x_p)), self.intrinsic(with_code(x_c, x_b))

    def decode(self, z_r, z_e, z_i):
        return normalize_quaternion(self.decode_rotation(z_r)), self.decode_shape(torch.cat([z_e, z_i], -1))


def with_code(x_c, code):
    """x_c, with a taught code (x_p or x_b) beside it when there is one."""
    return x_c if code is None else torch.cat([x_c, code], -1)


def sample(mean, log_variance):
    return mean + torch.exp(0.5 * log_variance) * torch.randn_like(mean)


def covariance_penalty(groups: list[torch.Tensor]) -> torch.Tensor:
    """L_Sigma: sum of |empirical cross-covariance| between the means of different groups."""
    total = groups[0].new_zeros(())
    for a in range(len(groups)):
        for b in range(len(groups)):
            if a != b:
                x = groups[a] - groups[a].mean(0)
                y = groups[b] - groups[b].mean(0)
                total = total + (x.T @ y / (len(x) - 1)).abs().sum()
    return total


def correlation_penalty(groups: list[torch.Tensor]) -> torch.Tensor:
    """L_Sigma as squared correlations: the sum over pairs of different groups of every squared
    Pearson correlation between a dimension of one and a dimension of the other. Scale-free: it
    cannot be lowered by shrinking a group's means, only by making the groups independent."""
    standardised = []
    for g in groups:
        x = g - g.mean(0)
        standardised.append(x / (x.pow(2).sum(0).sqrt() + 1e-8))
    total = groups[0].new_zeros(())
    for a in range(len(groups)):
        for b in range(a + 1, len(groups)):
            total = total + (standardised[a].T @ standardised[b]).pow(2).sum()
    return 2 * total


def disentanglement_penalty(form: str, groups: list[torch.Tensor]) -> torch.Tensor:
    """L_Sigma in the configured form (see VAEConfig.covariance_form)."""
    if form == "correlation":
        return correlation_penalty(groups)
    if form == "off":
        return groups[0].new_zeros(())
    return covariance_penalty(groups)


def jacobian_penalty(model: LatentVAE, mu_e: torch.Tensor, mu_i: torch.Tensor,
                     x_p: torch.Tensor | None = None, x_b: torch.Tensor | None = None) -> torch.Tensor:
    """L_J: ||d mu^_E / d mu_I||_F^2 + ||d mu^_I / d mu_E||_F^2 through a decode/re-encode cycle,
    estimated without building Jacobians: E_v ||J v||^2 = ||J||_F^2 for v ~ N(0, I). The taught
    codes x_p and x_b (read from the points, not from x_c) are held at the batch's own."""

    def reencode_extrinsic(z_i):
        return model.extrinsic.mean(with_code(model.decode_shape(torch.cat([mu_e, z_i], -1)), x_p))

    def reencode_intrinsic(z_e):
        return model.intrinsic.mean(with_code(model.decode_shape(torch.cat([z_e, mu_i], -1)), x_b))

    _, e_by_i = torch.func.jvp(reencode_extrinsic, (mu_i,), (torch.randn_like(mu_i),))
    _, i_by_e = torch.func.jvp(reencode_intrinsic, (mu_e,), (torch.randn_like(mu_e),))
    return e_by_i.pow(2).sum(-1).mean() + i_by_e.pow(2).sum(-1).mean()


@dataclass
class VAELosses:
    total: torch.Tensor
    parts: LossParts


def view_consistency(mu_i: torch.Tensor) -> torch.Tensor:
    """The batch's first half and second half are two views of the same meshes, row by row: their
    mean squared mu_I distance over twice mu_I's variance across the whole batch (scale-free)."""
    half = len(mu_i) // 2
    apart = (mu_i[:half] - mu_i[half:2 * half]).pow(2).sum(-1).mean()
    spread = (mu_i - mu_i.mean(0)).pow(2).sum(-1).mean()
    return apart / (2 * spread + 1e-8)


def vae_loss(model: LatentVAE, q: torch.Tensor, x_c: torch.Tensor, spectrum: torch.Tensor,
             dataset_size: int, with_jacobian: bool = True, beta_scale: float = 1.0,
             paired: dict | None = None, x_p: torch.Tensor | None = None,
             x_b: torch.Tensor | None = None, taught: dict | None = None) -> VAELosses:
    """The full objective L_HF + L_lambda + L_F + L_D on a batch, in the configured regime.
    `beta_scale` multiplies the four HFVAE betas (the warm-up). With `omega_view` > 0 the batch
    must be pairs of views (`view_consistency`). With the paired terms on, the batch is paired
    triples and `paired` holds the swaps' target codes and each row's subject and family
    (train.py, `paired_inputs`). With `omega_body` (`omega_pose`) > 0, `taught["body"]`
    (`taught["pose"]`) holds each row's targets (`rows`, `mask`: pose.BodyTargets' or PoseTargets')
    and `family` (its index there)."""
    c = model.config
    if c.paired and paired is None:
        raise ValueError("the paired regime's terms are on but the batch is not paired (train.py, paired_inputs)")
    (mu_r, lv_r), (mu_e, lv_e), (mu_i, lv_i) = model.encode(q, x_c, x_p, x_b)
    flow_mean, log_det = model.flow(spectrum)
    if c.regime == "gdvae++":
        mean_i, log_var_i = flow_mean, model.spectral_variance(spectrum).clamp(-12.0, 6.0)
    else:
        mean_i, log_var_i = mu_i, lv_i
    z_r, z_e, z_i = sample(mu_r, lv_r), sample(mu_e, lv_e), sample(mean_i, log_var_i)
    q_hat, x_hat = model.decode(z_r, z_e, z_i)

    dimensions = c.latent if c.reconstruction_per_dimension else 1
    target_code = paired["own_targets"] if c.reconstruct_canonical else x_c
    reconstruction = (target_code - x_hat).pow(2).sum(-1).mean() / (dimensions * model.code_norm)
    rotation = quaternion_distance(q, q_hat).mean()
    terms = hfvae_terms(
        torch.cat([z_r, z_e, z_i], -1),
        torch.cat([mu_r, mu_e, mean_i], -1),
        torch.cat([lv_r, lv_e, log_var_i], -1),
        [c.n_rotation, c.n_extrinsic, c.n_intrinsic],
        dataset_size,
    )
    hf = (c.omega_reconstruction * (reconstruction + c.omega_quaternion * rotation)
          + beta_scale * (c.beta_intra_tc * terms["intra_group_tc"] + c.beta_dimension_kl * terms["dimension_kl"]
                          + c.beta_mutual_information * terms["mutual_information"]
                          + c.beta_inter_tc * terms["inter_group_tc"]))

    prior = -0.5 * (flow_mean.pow(2).sum(-1) + c.n_intrinsic * torch.log(torch.tensor(2 * torch.pi)))
    log_likelihood = (prior + log_det).mean()
    flow = -c.omega_flow * log_likelihood

    target = flow_mean.detach() if c.regime == "gdvae++" else flow_mean
    intrinsic = (mu_i - target).pow(2).sum(-1).mean()
    spectrum_error = spectral_distance_torch(spectrum, model.flow.inverse(mu_i)).mean()
    consistency = c.omega_intrinsic * intrinsic + c.omega_spectrum * spectrum_error

    # Calibrate Sigma_I(x_c) to the error of mu_I against the spectral target (see VAEConfig).
    error = (mu_i.detach() - flow_mean.detach()).pow(2)
    variance = 0.5 * (error * torch.exp(-lv_i) + lv_i).sum(-1).mean()
    consistency = consistency + c.omega_variance * variance
    views = view_consistency(mu_i) if c.omega_view > 0 else mu_i.new_zeros(())
    consistency = consistency + c.omega_view * views

    swap = contrast = pose_contrast = mu_i.new_zeros(())
    if c.paired:
        if c.omega_swap > 0:
            swap = swap_error(model.decode_shape, z_e, z_i, paired["targets"], model.code_norm)
        if c.omega_contrast > 0:
            contrast = identity_contrast(mu_i, paired["subject"], paired["family"], c.contrast_temperature)
        if c.omega_pose_contrast > 0:
            # The same contrast with the shared pose as the label: a pose is one family's.
            pose_contrast = identity_contrast(mu_e, paired["pose"], paired["family"], c.contrast_temperature)
    supervised = c.omega_swap * swap + c.omega_contrast * contrast + c.omega_pose_contrast * pose_contrast
    head_errors = {}  # through a head per family (body), or on the code's first units (pose; body_direct)
    for name, weight, code in (("body", c.omega_body, mu_i), ("pose", c.omega_pose, mu_e)):
        head_errors[name] = mu_i.new_zeros(())
        if weight > 0:
            targets = (taught or {}).get(name)
            through_heads = name == "body" and not c.body_direct
            if targets is None or (through_heads and model.body_heads is None):
                raise ValueError(f"omega_{name} is on but the batch has no {name} targets (train.py, train_vae)")
            if through_heads:
                outputs, family = model.body_heads(code), targets["family"]
            else:  # one shared layout: the code's first units, as many as the targets' columns
                outputs, family = code[:, :targets["rows"].shape[-1]], torch.zeros_like(targets["family"])
            head_errors[name] = family_head_error(outputs, targets["rows"], targets["mask"], family)
            supervised = supervised + weight * head_errors[name]

    covariance = disentanglement_penalty(c.covariance_form, [mu_r, mu_e, mean_i])
    # omega_J = 0 turns L_J off, and its cost (most of a step) with it.
    with_jacobian = with_jacobian and c.omega_jacobian != 0
    jacobian = jacobian_penalty(model, mu_e, mean_i, x_p, x_b) if with_jacobian else mu_e.new_zeros(())
    disentangle = c.omega_covariance * covariance + c.omega_jacobian * jacobian

    total = hf + flow + consistency + disentangle + supervised
    parts = {
        "total": total, "reconstruction": reconstruction, "quaternion": rotation,
        **terms, "log_p_lambda": log_likelihood, "intrinsic_consistency": intrinsic,
        "spectrum_error": spectrum_error, "variance_nll": variance, "view_consistency": views, "covariance": covariance, "jacobian": jacobian,
        "swap": swap, "identity_contrast": contrast, "pose_contrast": pose_contrast, **head_errors,
    }
    return VAELosses(total, LossParts(parts))
