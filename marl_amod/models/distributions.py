"""The paper's Dirichlet policy, centralised or split into per-agent Gamma draws.

If every region i draws g_i ~ Gamma(alpha_i, 1) independently, the normalised vector
g / sum(g) is exactly Dirichlet(alpha). So a decentralised fleet whose agents only sample their
own Gamma weight (the env normalises the weights) follows the same joint law as the
centralised Dirichlet policy; its deterministic action alpha_i equals the Dirichlet mean after
normalisation. The change of variables links the two densities:

    log Dir(y; alpha) = sum_i log Gamma(g_i; alpha_i) - log Gamma(S; sum alpha) + (N - 1) log S,
    with S = sum_i g_i and y = g / S.
"""

from __future__ import annotations

import torch
from torch.distributions import Dirichlet, Gamma

CONCENTRATION_EPS = 1e-3  # keeps alpha > 0 so log-probs stay finite


def dirichlet(concentration: torch.Tensor) -> Dirichlet:
    """Dirichlet over the last axis; concentration (..., N) > 0."""
    return Dirichlet(concentration)


def gamma(concentration: torch.Tensor) -> Gamma:
    """Independent per-agent Gamma(alpha_i, 1) weights; concentration (..., N) > 0."""
    return Gamma(concentration, torch.ones_like(concentration))


def dirichlet_mean(concentration: torch.Tensor) -> torch.Tensor:
    """The deterministic action: alpha / sum(alpha) over the last axis."""
    return concentration / concentration.sum(-1, keepdim=True)


def gamma_log_prob(weights: torch.Tensor, concentration: torch.Tensor) -> torch.Tensor:
    """Joint log-density of the agents' unnormalised weights (..., N) -> (...)."""
    return gamma(concentration).log_prob(weights.clamp_min(1e-30)).sum(-1)


def dirichlet_log_prob_from_gammas(weights: torch.Tensor, concentration: torch.Tensor) -> torch.Tensor:
    """log Dir(weights / sum; alpha) computed from the Gamma draws (change of variables) -> (...)."""
    s = weights.sum(-1)  # (...)
    total = Gamma(concentration.sum(-1), torch.ones_like(s))
    n = weights.shape[-1]
    return gamma_log_prob(weights, concentration) - total.log_prob(s) + (n - 1) * torch.log(s)
