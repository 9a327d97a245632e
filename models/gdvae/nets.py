"""Network building blocks of the paper's appendix: PointNet encoders (no spatial transformer) and
fully connected stacks of linear -> LayerNorm -> ReLU."""

from __future__ import annotations

import torch
from torch import nn


class PointNet(nn.Module):
    """Per-point shared layers (1x1 convolutions with batch norm and ReLU) at the given hidden
    widths, a max-pool over points, then a linear map to `out_features`. Any number of points."""

    def __init__(self, hidden: tuple[int, ...], out_features: int):
        super().__init__()
        layers, width = [], 3
        for size in hidden:
            layers += [nn.Conv1d(width, size, 1), nn.BatchNorm1d(size), nn.ReLU()]
            width = size
        self.shared = nn.Sequential(*layers)
        self.head = nn.Linear(width, out_features)

    def forward(self, points: torch.Tensor) -> torch.Tensor:  # [B, N, 3] -> [B, out]
        features = self.shared(points.transpose(1, 2))
        return self.head(features.max(dim=2).values)


def mlp(in_features: int, hidden: tuple[int, ...], out_features: int) -> nn.Sequential:
    """linear -> LayerNorm -> ReLU per hidden layer, then a final linear layer."""
    layers, width = [], in_features
    for size in hidden:
        layers += [nn.Linear(width, size), nn.LayerNorm(size), nn.ReLU()]
        width = size
    layers.append(nn.Linear(width, out_features))
    return nn.Sequential(*layers)
