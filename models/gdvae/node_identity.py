"""z_I taught to tell subjects apart on the node's own clouds.

The kit's training views are not the node's clouds: a stereo camera's shadows and depth edges cut
pieces off, and prepare crops and clusters what is left (docs/tracking.md, "Legs cut off by the
sensor"). Every z_I trained on the kit's views alone told the node's subjects apart worse than the
one it replaced. x_c, which z_I's encoder reads, is what the node computes and records: `gdvae-node
evaluate SIM-RECORDINGS --states FILE` writes every frame's x_c beside the sim's truth (the subject
and its family). This module turns such files into batches of several frames of each of many
subjects, and the VAE stage adds an identity contrast on them (`vae.omega_node_identity`, the same
InfoNCE as the paired regime's `omega_contrast`: positives another frame of the subject, negatives
the family's other subjects in the batch) to its objective on the code bank.

The states must hold x_c of the autoencoder the run trains on: write them with a bundle exported
from the run given to `train --init-from` (or from this run's AE), on recordings of subjects kept
apart from the sets the node is measured on.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from .identity import read_states

FAMILY_MINIMUM = 2  # subjects per family: a contrast needs another subject of the family
FRAMES_PER_SUBJECT = 4  # frames of each subject drawn into a batch (its positives)


@dataclass
class NodeIdentityData:
    """x_c of the node's frames [frames, width] (float32), with each frame's subject number and
    family number, and where the data came from (for the run's records)."""

    x_c: torch.Tensor
    subject: torch.Tensor
    family: torch.Tensor
    families: list[str]
    files: list[str]

    @classmethod
    def from_states(cls, paths: list[str], width: int) -> "NodeIdentityData":
        """Reads `gdvae-node evaluate --states` files. Refused, naming the reason: no frame with
        truth, x_c of another width than the AE's (`width`), a family with fewer than two
        subjects, or a subject with a single frame."""
        if not paths:
            raise ValueError("no node states files given")
        by_subject, unmatched = read_states(paths)
        if not by_subject:
            raise ValueError(f"{', '.join(paths)}: no frame with the sim's truth ({unmatched} without): write the "
                             "states with `gdvae-node evaluate SIM-RECORDINGS --states FILE`")
        widths = {len(codes[0]) for codes in by_subject.values()}
        if widths != {width}:
            raise ValueError(f"{', '.join(paths)}: x_c has {sorted(widths)} numbers, this run's AE {width}: write the "
                             "states with a bundle exported from this run's autoencoder")
        for (family, subject), codes in by_subject.items():
            if len(codes) < 2:
                raise ValueError(f"{', '.join(paths)}: subject {subject!r} ({family}) has one frame; the contrast "
                                 "needs two or more of each subject")
        families = sorted({family for family, _ in by_subject})
        for family in families:
            count = sum(1 for f, _ in by_subject if f == family)
            if count < FAMILY_MINIMUM:
                raise ValueError(f"{', '.join(paths)}: family {family!r} has {count} subject; the contrast needs "
                                 f"{FAMILY_MINIMUM} or more of each family")
        x_c, subject, family = [], [], []
        for number, ((name, _), codes) in enumerate(sorted(by_subject.items())):
            x_c.append(np.stack(codes))
            subject += [number] * len(codes)
            family += [families.index(name)] * len(codes)
        return cls(torch.from_numpy(np.concatenate(x_c).astype(np.float32)), torch.tensor(subject),
                   torch.tensor(family), families, list(paths))

    def summary(self) -> dict:
        """What the run records of its node data (dataset.json, the model card)."""
        subjects = {name: len(set(self.subject[self.family == k].tolist())) for k, name in enumerate(self.families)}
        return {"states": self.files, "frames": len(self.x_c), "subjects": subjects}

    def to(self, device) -> "NodeIdentityData":
        return NodeIdentityData(self.x_c.to(device), self.subject.to(device), self.family.to(device),
                                self.families, self.files)


class NodeIdentityBatches:
    """Endless batches of `size // FRAMES_PER_SUBJECT` subjects drawn without repetition (all of
    them when fewer), `FRAMES_PER_SUBJECT` frames of each drawn with repetition: (x_c, subject,
    family) rows, so that every row has a positive and, within its family, negatives."""

    def __init__(self, data: NodeIdentityData, size: int, seed: int):
        self.data = data
        self.generator = torch.Generator().manual_seed(seed)
        subject = data.subject.cpu()
        order = torch.argsort(subject, stable=True)
        counts = torch.bincount(subject)
        self.start = torch.cumsum(counts, 0) - counts
        self.order, self.counts = order, counts
        self.subjects = max(2, min(len(counts), size // FRAMES_PER_SUBJECT))

    def __next__(self) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        chosen = torch.randperm(len(self.counts), generator=self.generator)[: self.subjects]
        chosen = chosen.repeat_interleave(FRAMES_PER_SUBJECT)
        offsets = (torch.rand(len(chosen), generator=self.generator) * self.counts[chosen]).long()
        rows = self.order[self.start[chosen] + offsets].to(self.data.x_c.device)
        return self.data.x_c[rows], self.data.subject[rows], self.data.family[rows]
