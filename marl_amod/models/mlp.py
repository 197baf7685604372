"""Ablation: an MLP on the flattened state (fixed to one city's size, no graph structure)."""

from __future__ import annotations

import torch
from torch import nn

from marl_amod.models.gnn import _batched, concentration

INPUT_STD_FLOOR = 1e-3  # an input that never varies in the data (a region never idle) stays as it is, not blown up


class MLPActor(nn.Module):
    """(B, N, F) -> flatten (B, N*F) -> 2 hidden layers -> (B, N) concentrations.

    ``standardise``: every input dimension is shifted and scaled by statistics the file carries
    (buffers ``input_mean``, ``input_std``; set from an offline dataset by :meth:`fit_inputs`):
    the node features mix vehicle counts times 0.01 (about 0.1-1) with demand values (up to ~40),
    and an unscaled first layer resolves the small ones poorly (CORL's BC/IQL/CQL standardise
    states the same way). Off: no buffers, so every earlier MLP policy file loads unchanged.
    """

    def __init__(self, n_features: int = 13, hidden: int = 32, n_regions: int = 16, standardise: bool = False) -> None:
        super().__init__()
        self.n_regions = n_regions
        self.net = nn.Sequential(
            nn.Linear(n_features * n_regions, hidden), nn.ReLU(), nn.Linear(hidden, hidden), nn.ReLU(), nn.Linear(hidden, n_regions)
        )
        self.standardise = standardise
        if standardise:
            self.register_buffer("input_mean", torch.zeros(n_features * n_regions))
            self.register_buffer("input_std", torch.ones(n_features * n_regions))

    @torch.no_grad()
    def fit_inputs(self, x: torch.Tensor) -> None:
        """Set the standardisation from inputs (T, N, F): each flattened dimension's mean and std."""
        if not self.standardise:
            raise ValueError("this MLP actor was built without standardise")
        flat = x.flatten(1).float()
        self.input_mean.copy_(flat.mean(0))
        self.input_std.copy_(flat.std(0).clamp_min(INPUT_STD_FLOOR))

    def forward(self, x: torch.Tensor, edge_index: torch.Tensor | None = None) -> torch.Tensor:
        x, squeeze = _batched(x)
        h = x.flatten(1)
        if self.standardise:
            h = (h - self.input_mean) / self.input_std
        alpha = concentration(self.net(h))  # (B, N)
        return alpha[0] if squeeze else alpha
