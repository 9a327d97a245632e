"""The paired regime: the sim's ground truth as supervision for the latent VAE (issue 32).

The paper learns the split between pose (z_E) and shape (z_I) without labels, because scans of
people and animals come without them. This kit's data comes from its own simulator, which can pose
every subject of a family in the same poses (`sim dataset --shared-poses`: a subjects x poses grid
whose ground truth names each pose by `pose_id`). Two terms use that grid, on top of the FO
objective (which stays whole):

- swap reconstruction: for two subjects A and B of one family in poses p_A and p_B, decoding
  (z_E of A, z_I of B) must give the code of B's subject in p_A, and (z_E of B, z_I of A) the code of
  A's subject in p_B; both meshes are in the grid, so their codes are known exactly;
- identity contrast: mu_I of a subject in another pose, seen from another side, is pulled towards the
  anchor's, and pushed away from every other subject of the same family in the batch (InfoNCE over
  squared distances, scale-free).

Batches are triples of rows (`PairedBatches`): A, B (same family, another subject, another pose) and
C (A's subject in another pose), each a random copy (view) of its mesh in the code bank. The node
is unchanged: it runs the same frozen encoders on unlabelled clouds.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch


@dataclass
class Pairing:
    """Per training mesh (in the bank's order): family, subject and pose as small integers, its row
    (subject) and column (pose) in its family's grid, and the grids: grid[family, row, column] =
    mesh index, or -1 where that mesh is missing (rejected by the loader)."""

    family: np.ndarray
    subject: np.ndarray
    pose: np.ndarray
    subject_row: np.ndarray
    pose_column: np.ndarray
    grid: np.ndarray

    @classmethod
    def from_truths(cls, truths: list[dict | None], source: str = "the dataset") -> "Pairing":
        """From the meshes' ground-truth records; every one must name its family, subject and
        `pose_id` (a dataset written with `sim dataset --shared-poses`)."""
        missing = [k for k, t in enumerate(truths) if not t or not all(key in t for key in ("family", "subject", "pose_id"))]
        if missing:
            raise ValueError(f"{source}: {len(missing)} of {len(truths)} training meshes have no shared pose "
                             "(ground truth without 'pose_id'): the paired regime needs a dataset written by "
                             "`sim dataset --shared-poses`")
        families = sorted({t["family"] for t in truths})
        family = np.array([families.index(t["family"]) for t in truths])
        subjects = sorted({t["subject"] for t in truths})
        subject = np.array([subjects.index(t["subject"]) for t in truths])
        poses = sorted({t["pose_id"] for t in truths})
        pose = np.array([poses.index(t["pose_id"]) for t in truths])
        rows = {f: sorted({t["subject"] for t in truths if t["family"] == f}) for f in families}
        columns = {f: sorted({t["pose_id"] for t in truths if t["family"] == f}) for f in families}
        subject_row = np.array([rows[t["family"]].index(t["subject"]) for t in truths])
        pose_column = np.array([columns[t["family"]].index(t["pose_id"]) for t in truths])
        grid = np.full((len(families), max(map(len, rows.values())), max(map(len, columns.values()))), -1)
        grid[family, subject_row, pose_column] = np.arange(len(truths))
        pairing = cls(family, subject, pose, subject_row, pose_column, grid)
        if not pairing.usable().any():
            raise ValueError(f"{source}: no family has two subjects in two shared poses; nothing to pair")
        return pairing

    def usable(self) -> np.ndarray:
        """Meshes that can anchor a triple: their family has another subject and another pose."""
        subjects = (self.grid >= 0).any(axis=2).sum(axis=1)
        poses = (self.grid >= 0).any(axis=1).sum(axis=1)
        return (subjects[self.family] >= 2) & (poses[self.family] >= 2)


@dataclass
class PairedBatch:
    """Bank entries of the rows A, B, C (in that order, `rows` each; with pose pairs a fourth block
    D: B's subject in A's pose, another view) and the meshes whose codes the swaps must give: B's
    subject in A's pose, then A's subject in B's pose."""

    entries: np.ndarray
    swap_meshes: np.ndarray
    rows: int


class PairedBatches:
    """Triples drawn from a `Pairing` over a bank with `copies` entries per mesh (mesh-major).
    `pose_pairs`: quadruples instead, the fourth row D (B's subject in A's pose, a random view)
    giving z_E a positive of A's pose on another subject and view (`vae.omega_pose_contrast`)."""

    def __init__(self, pairing: Pairing, copies: int, seed: int, pose_pairs: bool = False):
        self.pairing, self.copies, self.pose_pairs = pairing, copies, pose_pairs
        self.anchors = np.flatnonzero(pairing.usable())
        self.rng = np.random.default_rng(seed)

    def draw(self, batch: int) -> PairedBatch:
        p, rng = self.pairing, self.rng
        rows = max(1, batch // (4 if self.pose_pairs else 3))
        _, subjects, poses = p.grid.shape
        a = self.anchors[rng.integers(0, len(self.anchors), rows)]
        f, sa, pa = p.family[a], p.subject_row[a], p.pose_column[a]
        sb, pb, pc = np.empty_like(sa), np.empty_like(pa), np.empty_like(pa)
        pending = np.arange(rows)
        for _ in range(100):  # a full grid needs one round; holes are redrawn
            n = len(pending)
            sb[pending] = rng.integers(0, subjects, n)
            pb[pending] = rng.integers(0, poses, n)
            pc[pending] = rng.integers(0, poses, n)
            ok = ((sb != sa) & (pb != pa) & (pc != pa) & (p.grid[f, sb, pb] >= 0) & (p.grid[f, sb, pa] >= 0)
                  & (p.grid[f, sa, pb] >= 0) & (p.grid[f, sa, pc] >= 0))
            pending = np.flatnonzero(~ok)
            if not len(pending):
                break
        keep = np.setdiff1d(np.arange(rows), pending)  # anchors with no partner after 100 draws
        a, f, sa, pa, sb, pb, pc = (x[keep] for x in (a, f, sa, pa, sb, pb, pc))
        blocks = [a, p.grid[f, sb, pb], p.grid[f, sa, pc]] + ([p.grid[f, sb, pa]] if self.pose_pairs else [])
        meshes = np.concatenate(blocks)
        entries = meshes * self.copies + rng.integers(0, self.copies, len(meshes))
        swaps = np.concatenate([p.grid[f, sb, pa], p.grid[f, sa, pb]])
        return PairedBatch(entries, swaps, len(keep))


def swap_error(decode_shape, z_e: torch.Tensor, z_i: torch.Tensor, targets: torch.Tensor,
               code_norm: torch.Tensor) -> torch.Tensor:
    """The swap reconstruction's relative error. Rows [0, r) of z are A's, [r, 2r) B's (r =
    len(targets) / 2); `targets` holds the codes of B's subject in A's pose, then A's subject in B's
    pose. Zero exactly when the decoder does both swaps."""
    r = len(targets) // 2
    swapped = decode_shape(torch.cat([torch.cat([z_e[:r], z_i[r:2 * r]], -1),
                                      torch.cat([z_e[r:2 * r], z_i[:r]], -1)], 0))
    return (swapped - targets).pow(2).sum(-1).mean() / code_norm


def contrast_masks(subject: torch.Tensor, family: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Per pair of batch rows (i, j), i != j: positive when both show one subject; negative when
    they show two subjects of one family. Rows of other families are neither."""
    same_subject = subject[:, None] == subject[None, :]
    same_family = family[:, None] == family[None, :]
    other = ~torch.eye(len(subject), dtype=torch.bool, device=subject.device)
    return same_subject & other, same_family & ~same_subject


def identity_contrast(mu_i: torch.Tensor, subject: torch.Tensor, family: torch.Tensor,
                      temperature: float) -> torch.Tensor:
    """InfoNCE on mu_I: for every row with a positive and a negative, minus the log share of its
    positives in softmax(-d / (temperature x mean d)) over its positives and negatives, d the
    squared distance (its batch mean detached, so the term does not reward shrinking mu_I)."""
    positive, negative = contrast_masks(subject, family)
    distance = (mu_i[:, None, :] - mu_i[None, :, :]).pow(2).sum(-1)
    considered = positive | negative
    scale = distance.detach()[considered].mean().clamp_min(1e-8)
    logits = (-distance / (temperature * scale)).masked_fill(~considered, float("-inf"))
    anchors = positive.any(1) & negative.any(1)
    if not anchors.any():
        return mu_i.new_zeros(())
    all_terms = torch.logsumexp(logits[anchors], 1)
    positives = torch.logsumexp(logits[anchors].masked_fill(~positive[anchors], float("-inf")), 1)
    return (all_terms - positives).mean()
