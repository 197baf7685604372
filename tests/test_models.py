"""Models: shapes, permutation equivariance, local == global, Dirichlet vs Gamma, learning."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from marl_amod.env.features import node_features
from marl_amod.env.observations import local_observations, split_local
from marl_amod.errors import ConfigError
from marl_amod.models import (
    CNNActor,
    GNNActor,
    GNNValueCritic,
    LocalActor,
    LocalValueCritic,
    MLPActor,
    TwinQ,
    build_actor,
    dirichlet,
    dirichlet_log_prob_from_gammas,
    gamma,
    gamma_log_prob,
)
from marl_amod.system import FleetSystem


def _features(city, seed=0, steps=2):
    system = FleetSystem(city)
    system.reset(seed)
    for _ in range(steps):
        system.step(system.targets_from_weights(np.ones(city.n_regions)))
    return system, torch.as_tensor(node_features(system))


@pytest.mark.parametrize("conv", ["gcn", "sage"])
def test_gnn_actor_and_critics_shapes(tiny_city, conv):
    ei = torch.as_tensor(tiny_city.edge_index)
    x = torch.rand(4, 9, 13)
    actor = GNNActor(13, 16, conv)
    alpha = actor(x, ei)
    assert alpha.shape == (4, 9) and bool((alpha > 0).all())
    assert actor(x[0], ei).shape == (9,)
    torch.testing.assert_close(actor(x[1], ei), alpha[1])  # batching does not mix graphs
    assert GNNValueCritic(13, 16, conv)(x, ei).shape == (4,)
    q1, q2 = TwinQ(13, 16, conv)(x, ei, torch.rand(4, 9))
    assert q1.shape == q2.shape == (4,) and not torch.allclose(q1, q2)


@pytest.mark.parametrize("conv", ["gcn", "sage"])
def test_gnn_is_permutation_equivariant_and_critic_invariant(tiny_city, conv):
    torch.manual_seed(0)
    ei = torch.as_tensor(tiny_city.edge_index)
    x = torch.rand(2, 9, 13)
    perm = torch.randperm(9)  # new node k is old node perm[k]
    inv = torch.argsort(perm)
    ei_p = inv[ei]  # relabel edges to the new numbering
    actor, critic = GNNActor(13, 16, conv), GNNValueCritic(13, 16, conv)
    torch.testing.assert_close(actor(x[:, perm], ei_p), actor(x, ei)[:, perm])
    torch.testing.assert_close(critic(x[:, perm], ei_p), critic(x, ei))


def test_gnn_is_size_agnostic(tiny_city, small_city):
    actor = GNNActor(13, 16)
    _, x9 = _features(tiny_city)
    _, x16 = _features(small_city)
    assert actor(x9, torch.as_tensor(tiny_city.edge_index)).shape == (9,)
    assert actor(x16, torch.as_tensor(small_city.edge_index)).shape == (16,)


def test_local_actor_from_local_observations_equals_global_gnn(small_city):
    """Decentralised execution computes exactly the centralised SAGE GNN, one agent at a time."""
    torch.manual_seed(1)
    system, x = _features(small_city, steps=3)
    actor = LocalActor(13, 16)
    own, _ctx, nbrs, mask = split_local(torch.as_tensor(local_observations(system)))
    per_agent = torch.stack([actor.forward_local(own[i], nbrs[i], mask[i]) for i in range(16)])  # one obs each
    torch.testing.assert_close(per_agent, actor(x, torch.as_tensor(small_city.edge_index)))
    critic = LocalValueCritic(13, 16)
    assert critic.forward_local(own[None], nbrs[None], mask[None]).shape == (1,)


def test_dirichlet_log_prob_equals_normalised_gamma_change_of_variables():
    torch.manual_seed(0)
    alpha = torch.tensor([[0.5, 1.0, 2.0, 7.0], [3.0, 0.2, 1.5, 1.0]], dtype=torch.float64)
    g = gamma(alpha).sample((5,))  # (5, 2, 4)
    y = g / g.sum(-1, keepdim=True)
    torch.testing.assert_close(dirichlet_log_prob_from_gammas(g, alpha), dirichlet(alpha).log_prob(y))
    # the Gamma joint is a proper, different density of the unnormalised weights
    assert not torch.allclose(gamma_log_prob(g, alpha), dirichlet(alpha).log_prob(y))


def test_normalised_gamma_draws_have_dirichlet_moments():
    torch.manual_seed(0)
    alpha = torch.tensor([0.5, 1.0, 2.0, 4.5])
    g = gamma(alpha).sample((40_000,))
    y = g / g.sum(-1, keepdim=True)
    a0 = alpha.sum()
    torch.testing.assert_close(y.mean(0), alpha / a0, atol=5e-3, rtol=0)
    torch.testing.assert_close(y.var(0), alpha * (a0 - alpha) / (a0**2 * (a0 + 1)), atol=2e-3, rtol=0)


def test_mlp_and_cnn_ablations_share_the_head(tiny_city):
    x = torch.rand(3, 9, 13)
    for kind, cls in (("mlp", MLPActor), ("cnn", CNNActor)):
        actor = build_actor(kind, tiny_city, 13, 16)
        assert isinstance(actor, cls)
        alpha = actor(x, None)
        assert alpha.shape == (3, 9) and bool((alpha > 0).all())


def test_cnn_rejects_a_non_grid_city(tiny_city):
    import dataclasses

    city = dataclasses.replace(tiny_city, positions=np.zeros((9, 2)))
    with pytest.raises(ConfigError, match="grid"):
        build_actor("cnn", city)


def test_gradient_steps_change_parameters_and_reduce_loss(tiny_city):
    """Maximising the Dirichlet likelihood of a target distribution moves the actor toward it."""
    torch.manual_seed(0)
    _, x = _features(tiny_city)
    ei = torch.as_tensor(tiny_city.edge_index)
    target = torch.full((9,), 0.02)
    target[4] = 1 - 0.02 * 8  # send the fleet to the centre
    actor = GNNActor(13, 16)
    before = [p.detach().clone() for p in actor.parameters()]
    opt = torch.optim.Adam(actor.parameters(), lr=1e-2)
    losses = []
    for _ in range(30):
        loss = -dirichlet(actor(x, ei)).log_prob(target)
        opt.zero_grad()
        loss.backward()
        opt.step()
        losses.append(loss.item())
    assert losses[-1] < losses[0] - 1.0
    assert any(not torch.equal(b, p) for b, p in zip(before, actor.parameters(), strict=True))
    alpha = actor(x, ei).detach()
    assert int(torch.argmax(alpha / alpha.sum())) == 4
