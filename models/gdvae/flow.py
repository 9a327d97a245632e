"""The spectral normalizing flow f_lambda: spectrum lambda <-> latent intrinsics (paper section 4.2,
appendix "VAE Network Architectures").

Nine layers, each an affine coupling (Dinh et al. 2016; one hidden layer of 400), an activation
normalization (Kingma & Dhariwal 2018) and a fixed random permutation; the last layer has neither
normalization nor permutation. It is written here rather than taken from nflows because the node
runs the flow through ONNX: a few plain layers export cleanly, while nflows' transforms carry
control flow and caching that complicate export.

A fixed first layer maps eigenvalues to standardized log-eigenvalues (log, then an affine map set
from training spectra). It is bijective with a known log-determinant, so log P_lambda(lambda) stays
exact in eigenvalue units, while the learned layers see well-scaled inputs.
"""

from __future__ import annotations

import math

import torch
from torch import nn


class AffineCoupling(nn.Module):
    """The second half of the features is scaled and shifted by functions of the first half."""

    def __init__(self, features: int, hidden: int):
        super().__init__()
        self.split = features // 2
        self.net = nn.Sequential(nn.Linear(self.split, hidden), nn.ReLU(), nn.Linear(hidden, 2 * (features - self.split)))
        # Near-identity start (small, not zero, so every weight gets a gradient from the first step).
        nn.init.normal_(self.net[-1].weight, std=1e-3)
        nn.init.zeros_(self.net[-1].bias)

    def _scale_shift(self, kept: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        raw_scale, shift = self.net(kept).chunk(2, dim=-1)
        return 2.0 * torch.tanh(raw_scale / 2.0), shift  # bounded log-scale, for stability

    def forward(self, x):
        kept, changed = x[..., : self.split], x[..., self.split :]
        log_scale, shift = self._scale_shift(kept)
        return torch.cat([kept, changed * torch.exp(log_scale) + shift], -1), log_scale.sum(-1)

    def inverse(self, y):
        kept, changed = y[..., : self.split], y[..., self.split :]
        log_scale, shift = self._scale_shift(kept)
        return torch.cat([kept, (changed - shift) * torch.exp(-log_scale)], -1)


class ActNorm(nn.Module):
    """Per-feature affine map, initialised from the first batch to zero mean and unit variance."""

    def __init__(self, features: int):
        super().__init__()
        self.bias = nn.Parameter(torch.zeros(features))
        self.log_scale = nn.Parameter(torch.zeros(features))
        self.register_buffer("initialized", torch.tensor(False))
        self.known_initialized = False  # read once from the buffer: reading it waits for the device

    def forward(self, x):
        if self.training and not self.known_initialized:
            if not bool(self.initialized):
                with torch.no_grad():
                    self.bias.copy_(-x.mean(0))
                    self.log_scale.copy_(-torch.log(x.std(0).clamp_min(1e-6)))
                    self.initialized.fill_(True)
            self.known_initialized = True
        return (x + self.bias) * torch.exp(self.log_scale), self.log_scale.sum().expand(x.shape[:-1])

    def inverse(self, y):
        return y * torch.exp(-self.log_scale) - self.bias


class Permutation(nn.Module):
    def __init__(self, features: int, generator: torch.Generator):
        super().__init__()
        order = torch.randperm(features, generator=generator)
        self.register_buffer("order", order)
        self.register_buffer("inverse_order", torch.argsort(order))

    def forward(self, x):
        return x[..., self.order], x.new_zeros(x.shape[:-1])

    def inverse(self, y):
        return y[..., self.inverse_order]


class LogStandardize(nn.Module):
    """lambda -> (log lambda - mean) / std, with fixed statistics of the training spectra."""

    def __init__(self, features: int):
        super().__init__()
        self.register_buffer("mean", torch.zeros(features))
        self.register_buffer("std", torch.ones(features))

    def fit(self, spectra: torch.Tensor) -> None:
        logs = torch.log(spectra.clamp_min(1e-12))
        self.mean.copy_(logs.mean(0))
        self.std.copy_(logs.std(0).clamp_min(1e-6))

    def forward(self, spectrum):
        logs = torch.log(spectrum.clamp_min(1e-12))
        # d/d lambda of (log lambda - m) / s = 1 / (lambda s)
        return (logs - self.mean) / self.std, -(logs + torch.log(self.std)).sum(-1)

    def inverse(self, y):
        return torch.exp(y * self.std + self.mean)


class SpectralFlow(nn.Module):
    """f_lambda (forward: spectrum -> latent, with log|det J|) and g_lambda = f_lambda^-1."""

    def __init__(self, features: int, layers: int = 9, hidden: int = 400, seed: int = 0):
        super().__init__()
        generator = torch.Generator().manual_seed(seed)
        self.input = LogStandardize(features)
        steps: list[nn.Module] = []
        for index in range(layers):
            steps.append(AffineCoupling(features, hidden))
            if index < layers - 1:
                steps += [ActNorm(features), Permutation(features, generator)]
        self.steps = nn.ModuleList(steps)

    def forward(self, spectrum: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        x, log_det = self.input(spectrum)
        for step in self.steps:
            x, step_log_det = step(x)
            log_det = log_det + step_log_det
        return x, log_det

    def inverse(self, latent: torch.Tensor) -> torch.Tensor:
        x = latent
        for step in reversed(self.steps):
            x = step.inverse(x)
        return self.input.inverse(x)

    def log_prob(self, spectrum: torch.Tensor) -> torch.Tensor:
        """log P_lambda(lambda) under a standard normal prior on the latent (paper eq. P_lambda)."""
        latent, log_det = self(spectrum)
        prior = -0.5 * (latent.pow(2).sum(-1) + latent.shape[-1] * math.log(2 * math.pi))
        return prior + log_det
