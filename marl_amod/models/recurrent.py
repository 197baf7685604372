"""A recurrent graph policy for meta-RL through recurrence (RL², Duan et al. 2016).

Every region keeps a GRU memory that reads, each control step, the region's (scaled) features,
the share of the fleet the previous action asked of it and the previous team reward. The memory
is *not* reset between the episodes of a trial on one city, so what it learned about this city
(how the fleet, demand and rewards respond) carries into the next episode: adaptation without a
gradient step. Message passing between regions follows the memory, so each region's action sees
its neighbours' memories too. The same weights act on every region (size-agnostic): one policy
serves cities of 10 to 23 regions.

Shapes: N regions, F features, H hidden units, E directed edges.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from marl_amod.models.gnn import ConvKind, concentration, make_conv, mlp_head


class RecurrentGNN(nn.Module):
    """(features, previous action, previous reward, memory) -> (concentrations, value, memory).

    Actor and critic share the memory and the message passing (one trunk, two heads): the value
    of a state depends on what the memory has inferred about the city as much as the action does.
    """

    def __init__(self, n_features: int, hidden: int = 64, conv: ConvKind = "sage") -> None:
        super().__init__()
        self.hidden = hidden
        self.encode = nn.Sequential(nn.Linear(n_features + 2, hidden), nn.ReLU())
        self.memory = nn.GRUCell(hidden, hidden)
        self.conv = make_conv(conv, hidden)
        self.actor = mlp_head(2 * hidden, hidden)
        self.critic = mlp_head(2 * hidden, hidden)

    def initial_memory(self, n_regions: int) -> torch.Tensor:
        """(N, H) zeros: the memory at the start of a trial (a new city)."""
        return torch.zeros(n_regions, self.hidden)

    def forward(
        self, x: torch.Tensor, prev_action: torch.Tensor, prev_reward: torch.Tensor, memory: torch.Tensor, edge_index: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """x (N, F), prev_action (N,), prev_reward () , memory (N, H) -> alpha (N,), value (), memory (N, H)."""
        n = x.shape[0]
        inputs = torch.cat([x, prev_action.view(n, 1), prev_reward.view(1, 1).expand(n, 1)], dim=1)  # (N, F + 2)
        memory = self.memory(self.encode(inputs), memory)  # (N, H)
        mixed = F.relu(self.conv(memory, edge_index))  # (N, H) neighbours' memories
        z = torch.cat([memory, mixed], dim=1)  # (N, 2H)
        alpha = concentration(self.actor(z).squeeze(-1))  # (N,)
        value = self.critic(z).mean()  # () mean over regions: rewards are per-city scaled, so N-free
        return alpha, value, memory
