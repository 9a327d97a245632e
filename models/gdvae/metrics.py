"""The paper's metrics (sections 5.2-5.3, appendix "Evaluation Metric Details"), on held-out shapes.

- d_C: Chamfer distance between the AE reconstruction and a fresh uniform sample of the mesh,
  averaged over five randomly rotated copies of the test set.
- C_3D: Chamfer distance between the canonical reconstructions D(E(P_i)) of differently rotated
  copies of one shape (how well the AE undoes rotation in 3D).
- C_X: adjusted mutual information of k-means clusterings of x_c over rotated copies, with shape
  identity as the label, averaged over eight sample sizes from 20 to 1000 shapes (capped by the test
  set), two clusterings each.
- Coverage and fidelity (Achlioptas et al.): a generated set five times the test set, matched by
  minimum Chamfer distance; the mean of two runs.
- log P_lambda: mean exact log-likelihood of test spectra under the flow.
- Pose-aware retrieval: for each code rho in {x_c, z, z_E, z_I, z~_I}, the three nearest test
  shapes; E_beta (MSE of beta) and E_theta (mean d_q over joint rotations), each divided by the mean
  over all pairs (random retrieval = 1); s = 1 - E; s-hat = s(z_g) / s(x_c);
  S = s-hat_beta(z_I) + s-hat_theta(z_E) - s-hat_beta(z_E) - s-hat_theta(z_I). Computed within each
  family (beta and theta are family-specific) and averaged; `evaluate` also averages it over five
  draws of point samples and rotations, as one draw moves it by about 0.2 on 240 shapes.
- Heading error: median angle between the predicted and true rotation.
"""

from __future__ import annotations

import logging

import numpy as np
import torch
from sklearn.cluster import KMeans
from sklearn.metrics import adjusted_mutual_info_score

from .geometry import chamfer, geodesic_distance, quaternion_to_matrix, random_rotation_matrices, rotate

log = logging.getLogger(__name__)


# ---- retrieval -------------------------------------------------------------------------------

def axis_angle_to_quaternion(vectors: np.ndarray) -> np.ndarray:
    """[..., 3] axis-angle -> [..., 4] (w, x, y, z)."""
    angle = np.linalg.norm(vectors, axis=-1, keepdims=True)
    axis = np.where(angle > 1e-12, vectors / np.maximum(angle, 1e-12), 0.0)
    return np.concatenate([np.cos(angle / 2), axis * np.sin(angle / 2)], -1)


def pose_distance(theta_a: np.ndarray, theta_b: np.ndarray) -> np.ndarray:
    """Mean d_q = 1 - |q_a . q_b| over joints; theta is [..., 3 * joints] axis-angle."""
    qa = axis_angle_to_quaternion(theta_a.reshape(*theta_a.shape[:-1], -1, 3))
    qb = axis_angle_to_quaternion(theta_b.reshape(*theta_b.shape[:-1], -1, 3))
    return (1 - np.abs((qa * qb).sum(-1))).mean(-1)


def retrieval_errors(codes: np.ndarray, beta: np.ndarray, theta: np.ndarray, k: int = 3) -> tuple[float, float]:
    """(E_beta, E_theta): mean parameter errors of the k nearest codes, relative to random retrieval."""
    distance = ((codes[:, None, :] - codes[None, :, :]) ** 2).sum(-1)
    np.fill_diagonal(distance, np.inf)
    nearest = np.argsort(distance, axis=1)[:, :k]
    beta_pairs = ((beta[:, None, :] - beta[None, :, :]) ** 2).mean(-1)
    theta_pairs = pose_distance(theta[:, None, :], theta[None, :, :])
    off_diagonal = ~np.eye(len(codes), dtype=bool)
    e_beta = np.take_along_axis(beta_pairs, nearest, 1).mean() / beta_pairs[off_diagonal].mean()
    e_theta = np.take_along_axis(theta_pairs, nearest, 1).mean() / theta_pairs[off_diagonal].mean()
    return float(e_beta), float(e_theta)


def disentanglement(codes: dict[str, np.ndarray], beta: np.ndarray, theta: np.ndarray) -> dict:
    """Retrieval scores s_beta, s_theta per code, their normalisation by x_c, and S."""
    scores = {}
    for name, values in codes.items():
        e_beta, e_theta = retrieval_errors(values, beta, theta)
        scores[name] = {"E_beta": e_beta, "E_theta": e_theta, "s_beta": 1 - e_beta, "s_theta": 1 - e_theta}
    base = scores["x_c"]
    for name, row in scores.items():
        row["s_hat_beta"] = row["s_beta"] / base["s_beta"] if base["s_beta"] > 0 else float("nan")
        row["s_hat_theta"] = row["s_theta"] / base["s_theta"] if base["s_theta"] > 0 else float("nan")
    s = (scores["z_I"]["s_hat_beta"] + scores["z_E"]["s_hat_theta"]
         - scores["z_E"]["s_hat_beta"] - scores["z_I"]["s_hat_theta"])
    return {"codes": scores, "S": float(s)}


# ---- rotation invariance ---------------------------------------------------------------------

def clustering_consistency(encode, clouds: torch.Tensor, rng: np.random.Generator, copies: int = 5,
                           sizes: int = 8, full_rotations: bool = False, views: torch.Tensor | None = None) -> float:
    """C_X: mean AMI of k-means on x_c of rotated copies, identity as label (appendix C.1).

    `encode(inputs, rotations)` gets the rotated clouds and the rotations applied (for an oracle
    that may use them). `views` ([copies, shapes, points, 3]): other samples of each shape, e.g.
    the sides a camera sees, used as its copies instead of the same cloud."""
    total = len(clouds)
    if views is not None:
        copies = len(views)
    if total < 4:
        raise ValueError(f"C_X needs at least 4 test shapes, got {total}")
    grid = np.unique(np.linspace(min(20, total), min(1000, total), sizes).astype(int))
    amis = []
    for size in grid:
        runs = []
        for _ in range(2):
            chosen = rng.choice(total, size=size, replace=False)
            if views is None:
                batch = clouds[chosen].repeat(copies, 1, 1)
            else:
                batch = views[:, chosen].reshape(copies * size, *clouds.shape[1:])
            rotations = random_rotation_matrices(len(batch), full=full_rotations)
            codes = encode(rotate(batch, rotations), rotations).numpy()
            labels = np.tile(np.arange(size), copies)
            predicted = KMeans(n_clusters=size, n_init=3, random_state=int(rng.integers(1 << 31))).fit_predict(codes)
            runs.append(adjusted_mutual_info_score(labels, predicted))
        amis.append(float(np.mean(runs)))
    return float(np.mean(amis))


# ---- generative quality ----------------------------------------------------------------------

def pairwise_chamfer(a: torch.Tensor, b: torch.Tensor, chunk: int = 64) -> torch.Tensor:
    """[len(a), len(b)] Chamfer distances."""
    rows = []
    for start in range(0, len(a), chunk):
        block = a[start : start + chunk]
        row = []
        for j in range(len(b)):
            row.append(chamfer(block, b[j : j + 1].expand(len(block), -1, -1)))
        rows.append(torch.stack(row, 1))
    return torch.cat(rows, 0)


def coverage_and_fidelity(generated: torch.Tensor, real: torch.Tensor) -> tuple[float, float]:
    """Coverage: fraction of real clouds that are some generated cloud's nearest real cloud.
    Fidelity (minimum matching distance): mean over real clouds of the nearest generated distance."""
    distance = pairwise_chamfer(generated, real)
    coverage = len(set(distance.argmin(1).tolist())) / len(real)
    fidelity = float(distance.min(0).values.mean())
    return coverage, fidelity


def heading_errors(predicted_q: torch.Tensor, true_rotation: torch.Tensor) -> np.ndarray:
    """Angles (degrees) between predicted and true rotations."""
    return (geodesic_distance(quaternion_to_matrix(predicted_q), true_rotation) * 180.0).numpy()


def variance_calibration(means: np.ndarray, log_variances: np.ndarray, groups) -> dict:
    """How far codes of one group (a subject) spread, against the variance the encoder reports for
    them: per dimension, the mean within-group variance of the means over the mean reported
    variance. `z_I_variance_scale` is the median over dimensions: 1 when the encoder's variances
    are right, < 1 when they are wider than the spread."""
    groups = np.asarray(groups)
    members = [means[groups == g] for g in np.unique(groups) if (groups == g).sum() >= 2]
    if not members:
        raise ValueError("variance calibration needs a group with two or more codes")
    spread = [codes.var(0) for codes in members]
    ratio = np.mean(spread, 0) / np.exp(log_variances).mean(0)
    # The unit of the node's z_I distances ([track.objects]): how far a group's codes lie from
    # their mean (root mean square), the median over groups.
    wander = [np.sqrt(((codes - codes.mean(0)) ** 2).sum(1).mean()) for codes in members]
    return {"z_I_variance_scale": float(np.median(ratio)), "ratio_p10": float(np.quantile(ratio, 0.1)),
            "ratio_p90": float(np.quantile(ratio, 0.9)), "z_I_spread": float(np.median(wander)),
            "groups": len(spread), "codes": int(len(means))}
