"""The dense small-graph path gives the torch-geometric layers' outputs with the same weights."""

from __future__ import annotations

import pytest
import torch

from marl_amod.models import GNNActor, GNNValueCritic, LocalActor, TwinQ
from marl_amod.models.dense import DenseGraph, dense_conv, graph_operator
from marl_amod.models.gnn import make_conv
from marl_amod.scenario import grid_city


def _graphs() -> list[tuple[torch.Tensor, int]]:
    """A city graph and a random directed one with an isolated node, a one-way edge and no symmetry."""
    city = grid_city(3, 4, seed=0)
    g = torch.Generator().manual_seed(0)
    src = torch.randint(0, 9, (30,), generator=g)
    dst = torch.randint(0, 9, (30,), generator=g)
    keep = src != dst
    edges = torch.unique(torch.stack([src[keep], dst[keep]]), dim=1)
    edges = edges[:, (edges != 9).all(0)]  # node 9 of 10 has no edge at all
    return [(torch.as_tensor(city.edge_index), city.n_regions), (edges, 10)]


@pytest.mark.parametrize("kind", ["gcn", "sage"])
@pytest.mark.parametrize("graph", [0, 1])
def test_dense_conv_equals_torch_geometric_layer(kind: str, graph: int) -> None:
    edge_index, n = _graphs()[graph]
    torch.manual_seed(1)
    conv = make_conv(kind, 13)
    torch.nn.init.normal_(conv.bias if kind == "gcn" else conv.lin_l.bias)  # non-zero biases
    x = torch.randn(5, n, 13)
    sparse = torch.stack([conv(x[b], edge_index) for b in range(5)])
    dense = dense_conv(conv, x, graph_operator(kind, edge_index, n))
    torch.testing.assert_close(dense, sparse, atol=1e-5, rtol=1e-5)


@pytest.mark.parametrize("kind", ["gcn", "sage"])
def test_dense_models_equal_the_graph_models_with_the_same_weights(kind: str) -> None:
    edge_index, n = _graphs()[1]
    torch.manual_seed(2)
    dense = DenseGraph(edge_index, n)
    x = torch.rand(7, n, 13) * 3
    action = torch.rand(7, n)
    actor = GNNActor(13, 32, kind) if kind == "gcn" else LocalActor(13, 32)
    critic, twin = GNNValueCritic(13, 32, kind), TwinQ(13, 64, kind)
    torch.testing.assert_close(actor(x, dense), actor(x, edge_index), atol=1e-5, rtol=1e-5)
    torch.testing.assert_close(actor(x[0], dense), actor(x[0], edge_index), atol=1e-5, rtol=1e-5)  # unbatched
    torch.testing.assert_close(critic(x, dense), critic(x, edge_index), atol=1e-5, rtol=1e-5)
    for q_dense, q_sparse in zip(twin(x, dense, action), twin(x, edge_index, action), strict=True):
        torch.testing.assert_close(q_dense, q_sparse, atol=1e-5, rtol=1e-5)
    # gradients flow to the same parameters
    actor(x, dense).sum().backward()
    assert all(p.grad is not None and p.grad.abs().sum() > 0 for p in actor.parameters())


@pytest.mark.parametrize("agent_id", [False, True])
@pytest.mark.parametrize("readout", ["none", "mean", "max", "mean-max"])
@pytest.mark.parametrize("kind", ["gcn", "sage"])
def test_gnn_options_give_the_same_outputs_on_both_paths(kind: str, readout: str, agent_id: bool) -> None:
    """The fleet readout and the region identity act around the graph layer, so every option
    combination of the actor and the value critic agrees across the paths, gradients included."""
    edge_index, n = _graphs()[1]
    torch.manual_seed(2)
    dense = DenseGraph(edge_index, n)
    x = torch.rand(5, n, 13) * 3
    ids = n if agent_id else 0
    actor, critic = GNNActor(13, 32, kind, readout, ids), GNNValueCritic(13, 32, kind, readout, ids)  # type: ignore[arg-type]
    torch.testing.assert_close(actor(x, dense), actor(x, edge_index), atol=1e-5, rtol=1e-5)
    torch.testing.assert_close(actor(x[0], dense), actor(x[0], edge_index), atol=1e-5, rtol=1e-5)  # unbatched
    torch.testing.assert_close(critic(x, dense), critic(x, edge_index), atol=1e-5, rtol=1e-5)
    actor(x, dense).sum().backward()
    assert all(p.grad is not None and p.grad.abs().sum() > 0 for p in actor.parameters())


def test_graph_operator_rejects_unknown_kind() -> None:
    with pytest.raises(ValueError, match="unknown conv"):
        graph_operator("gat", torch.zeros(2, 0, dtype=torch.long), 3)  # type: ignore[arg-type]


def _nonzero_biases(module: torch.nn.Module) -> None:
    for name, p in module.named_parameters():
        if name.endswith("bias"):
            torch.nn.init.normal_(p)  # torch-geometric starts some biases at zero; zeros hide misplaced ones


@pytest.mark.parametrize("kind", ["gcn", "sage"])
def test_stacked_twin_critics_equal_the_two_critics_in_values_and_gradients(kind: str) -> None:
    """StackedTwinQ (one batched matmul per layer) computes TwinQ's two functions: the same Q values,
    action gradients (the policy loss) and weight gradients, each critic in its own slice."""
    from marl_amod.models.gnn import StackedTwinQ

    edge_index, n = _graphs()[1]
    torch.manual_seed(3)
    twin = TwinQ(16, 24, kind)
    _nonzero_biases(twin)
    stacked = StackedTwinQ(twin)
    dense = DenseGraph(edge_index, n)
    x = torch.rand(6, n, 16) * 3
    action = torch.rand(6, n)
    a1, a2 = action.clone().requires_grad_(True), action.clone().requires_grad_(True)
    q_twin, q_stacked = twin(x, edge_index, a1), stacked(x, dense, a2)
    for q, s in zip(q_twin, q_stacked, strict=True):
        torch.testing.assert_close(s, q, atol=1e-5, rtol=1e-5)
    loss = lambda q: (q[0] ** 2).sum() + 3 * torch.min(*q).sum()  # noqa: E731 - mixes both critics unevenly
    loss(q_twin).backward()
    loss(q_stacked).backward()
    torch.testing.assert_close(a2.grad, a1.grad, atol=1e-4, rtol=1e-4)
    for (name, p), (_, p1), (_, p2) in zip(stacked.named_parameters(), _pairs(twin, stacked, 0), _pairs(twin, stacked, 1), strict=True):
        torch.testing.assert_close(p.grad[0], p1.grad, atol=1e-4, rtol=1e-4, msg=name)
        torch.testing.assert_close(p.grad[1], p2.grad, atol=1e-4, rtol=1e-4, msg=name)


def _pairs(twin: TwinQ, stacked: torch.nn.Module, which: int) -> list[tuple[str, torch.nn.Parameter]]:
    """Critic ``which``'s parameters in StackedTwinQ's order (found by value: stacked was built from twin)."""
    critic = (twin.q1, twin.q2)[which]
    out = []
    for name, p in stacked.named_parameters():
        match = [q for q in critic.parameters() if q.shape == p.shape[1:] and torch.equal(q.detach(), p.detach()[which])]
        assert len(match) == 1, name
        out.append((name, match[0]))
    return out
