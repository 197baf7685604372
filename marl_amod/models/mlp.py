"""Ablation: an MLP on the flattened state (fixed to one city's size, no graph structure)."""

from __future__ import annotations

import torch
from torch import nn

from marl_amod.models.gnn import _batched, concentration


class MLPActor(nn.Module):
    """(B, N, F) -> flatten (B, N*F) -> 2 hidden layers -> (B, N) concentrations."""

    def __init__(self, n_features: int = 13, hidden: int = 32, n_regions: int = 16) -> None:
        super().__init__()
        self.n_regions = n_regions
        self.net = nn.Sequential(
            nn.Linear(n_features * n_regions, hidden), nn.ReLU(), nn.Linear(hidden, hidden), nn.ReLU(), nn.Linear(hidden, n_regions)
        )

    def forward(self, x: torch.Tensor, edge_index: torch.Tensor | None = None) -> torch.Tensor:
        x, squeeze = _batched(x)
        alpha = concentration(self.net(x.flatten(1)))  # (B, N)
        return alpha[0] if squeeze else alpha
