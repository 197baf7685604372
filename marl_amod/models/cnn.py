"""Ablation: a CNN over grid cities, regions laid out as pixels (rows x cols), same Dirichlet head."""

from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from marl_amod.errors import ConfigError
from marl_amod.models.gnn import _batched, concentration


def grid_layout(positions: np.ndarray) -> tuple[int, int, np.ndarray]:
    """(rows, cols, (N,) flat cell index) of a grid city, from its drawing positions (x=col, y=-row)."""
    pos = np.asarray(positions, dtype=float)
    cols_v, rows_v = np.unique(np.round(pos[:, 0], 6)), np.unique(np.round(-pos[:, 1], 6))
    col = np.searchsorted(cols_v, np.round(pos[:, 0], 6))
    row = np.searchsorted(rows_v, np.round(-pos[:, 1], 6))
    cell = row * len(cols_v) + col
    if len(np.unique(cell)) != len(pos):
        raise ConfigError("the CNN actor needs a grid city (distinct row/col per region), e.g. the synthetic scenarios")
    return len(rows_v), len(cols_v), cell


class CNNActor(nn.Module):
    """(B, N, F) -> image (B, F, R, C) -> three 3x3 convs -> (B, N) concentrations."""

    def __init__(self, n_features: int = 13, hidden: int = 32, rows: int = 4, cols: int = 4, cells: list[int] | None = None) -> None:
        super().__init__()
        self.rows, self.cols = rows, cols
        self.register_buffer("cells", torch.as_tensor(cells if cells is not None else range(rows * cols), dtype=torch.long))
        self.c1 = nn.Conv2d(n_features, hidden, 3, padding=1)
        self.c2 = nn.Conv2d(hidden, hidden, 3, padding=1)
        self.c3 = nn.Conv2d(hidden, 1, 1)

    def forward(self, x: torch.Tensor, edge_index: torch.Tensor | None = None) -> torch.Tensor:
        x, squeeze = _batched(x)
        b, n, f = x.shape
        img = x.new_zeros(b, self.rows * self.cols, f)
        img[:, self.cells] = x
        img = img.permute(0, 2, 1).reshape(b, f, self.rows, self.cols)  # (B, F, R, C)
        out = self.c3(F.relu(self.c2(F.relu(self.c1(img))))).reshape(b, -1)[:, self.cells]  # (B, N)
        alpha = concentration(out)
        return alpha[0] if squeeze else alpha
