"""The decentralised actor: each region runs the shared network on its own local observation.

A local observation holds the region's own features and up to K neighbours' features with a
mask. With mean aggregation (SAGE), one GNN layer at region i needs exactly that:

    h_i = relu(W_l mean_{j in N(i)} x_j + b + W_r x_i) + x_i

so :class:`LocalActor` *is* a :class:`GNNActor` with ``conv="sage"``: the same parameters run on
the global graph (centralised) or from one agent's observation alone (decentralised), and the two
agree exactly whenever K covers every neighbour (the env's default K is the largest in-degree).
The neighbour table is :func:`marl_amod.env.observations.neighbour_table`.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

from marl_amod.models.gnn import GNNActor, GNNValueCritic, concentration


def _mean_conv_local(conv, own: torch.Tensor, nbrs: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """One SAGE layer from local data: own (..., F), nbrs (..., K, F), mask (..., K) -> (..., F)."""
    agg = (nbrs * mask.unsqueeze(-1)).sum(-2) / mask.sum(-1, keepdim=True).clamp_min(1.0)  # (..., F)
    return F.relu(conv.lin_l(agg) + conv.lin_r(own)) + own


class LocalActor(GNNActor):
    """Shared-parameter actor; ``forward_local`` needs one agent's observation only."""

    def __init__(self, n_features: int = 13, hidden: int = 32) -> None:
        super().__init__(n_features, hidden, conv="sage")

    def forward_local(self, own: torch.Tensor, nbrs: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
        """own (..., F), nbrs (..., K, F), mask (..., K) -> concentration alpha_i (...)."""
        return concentration(self.head(_mean_conv_local(self.trunk.conv, own, nbrs, mask)).squeeze(-1))


class LocalValueCritic(GNNValueCritic):
    """Decentralised critic: V(s) ~ sum_i v(o_i), each term from one agent's local observation."""

    def __init__(self, n_features: int = 13, hidden: int = 32) -> None:
        super().__init__(n_features, hidden, conv="sage")

    def forward_local(self, own: torch.Tensor, nbrs: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
        """own (B, N, F), nbrs (B, N, K, F), mask (B, N, K) -> team value (B,)."""
        h = self.node(_mean_conv_local(self.trunk.conv, own, nbrs, mask))  # (B, N, H)
        return self.out(F.relu(h.sum(-2))).squeeze(-1)
