"""The hierarchically factorized VAE objective (Esmaeili et al. 2018), as the paper uses it.

With groups g (here z_R, z_E, z_I), the KL term of the ELBO splits into four parts:
  I[x; z]                   mutual information between data and code        (beta_3)
  TC[z] = KL(q(z) || prod_g q(z_g))               inter-group total correlation (beta_4)
  sum_g KL(q(z_g) || prod_d q(z_g,d))             intra-group total correlation (beta_1)
  sum_g,d KL(q(z_g,d) || p(z_g,d))                dimension-wise KL to the prior (beta_2)
The aggregate posterior q(z) and its marginals are estimated on the minibatch with minibatch
weighted sampling (Chen et al. 2018, as ProbTorch does): log q(z_i) ~ logsumexp_j log q(z_i|x_j)
- log(N M) for a batch of M out of N training items. With all betas 1 the four terms add up to
the usual KL(q(z|x) || p(z)) in expectation.
"""

from __future__ import annotations

import math

import torch


def gaussian_log_density(z: torch.Tensor, mean: torch.Tensor, log_variance: torch.Tensor) -> torch.Tensor:
    return -0.5 * (math.log(2 * math.pi) + log_variance + (z - mean).pow(2) * torch.exp(-log_variance))


def hfvae_terms(z: torch.Tensor, mean: torch.Tensor, log_variance: torch.Tensor, groups: list[int],
                dataset_size: int) -> dict[str, torch.Tensor]:
    """The four HFVAE terms, averaged over the batch. `z`, `mean`, `log_variance` are [M, D] with
    the groups laid out consecutively; `groups` gives each group's size."""
    batch, _ = z.shape
    # log q(z_i,d | x_j) for every pair: [M (i), M (j), D]
    pairwise = gaussian_log_density(z[:, None, :], mean[None, :, :], log_variance[None, :, :])
    log_norm = math.log(dataset_size * batch)
    log_q_z_given_x = gaussian_log_density(z, mean, log_variance).sum(-1)
    log_q_z = torch.logsumexp(pairwise.sum(-1), dim=1) - log_norm
    log_q_dims = torch.logsumexp(pairwise, dim=1) - log_norm  # [M, D]
    log_prior_dims = -0.5 * (math.log(2 * math.pi) + z.pow(2))
    log_q_groups, intra = [], z.new_zeros(batch)
    start = 0
    for size in groups:
        block = slice(start, start + size)
        log_q_group = torch.logsumexp(pairwise[:, :, block].sum(-1), dim=1) - log_norm
        log_q_groups.append(log_q_group)
        intra = intra + log_q_group - log_q_dims[:, block].sum(-1)
        start += size
    return {
        "mutual_information": (log_q_z_given_x - log_q_z).mean(),
        "inter_group_tc": (log_q_z - torch.stack(log_q_groups, -1).sum(-1)).mean(),
        "intra_group_tc": intra.mean(),
        "dimension_kl": (log_q_dims - log_prior_dims).sum(-1).mean(),
    }
