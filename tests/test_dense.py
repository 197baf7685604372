"""The dense small-graph path gives the torch-geometric layers' outputs with the same weights."""

from __future__ import annotations

import pytest
import torch

from marl_amod.models import GNNActor, GNNValueCritic, LocalActor, TwinQ
from marl_amod.models.dense import actor_forward, dense_conv, graph_operator, q_forward, value_forward
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
    op = graph_operator(kind, edge_index, n)
    x = torch.rand(7, n, 13) * 3
    action = torch.rand(7, n)
    actor = GNNActor(13, 32, kind) if kind == "gcn" else LocalActor(13, 32)
    critic, twin = GNNValueCritic(13, 32, kind), TwinQ(13, 64, kind)
    torch.testing.assert_close(actor_forward(actor, x, op), actor(x, edge_index), atol=1e-5, rtol=1e-5)
    torch.testing.assert_close(value_forward(critic, x, op), critic(x, edge_index), atol=1e-5, rtol=1e-5)
    q1, q2 = twin(x, edge_index, action)
    torch.testing.assert_close(q_forward(twin.q1, x, op, action), q1, atol=1e-5, rtol=1e-5)
    torch.testing.assert_close(q_forward(twin.q2, x, op, action), q2, atol=1e-5, rtol=1e-5)
    # gradients flow to the same parameters
    actor_forward(actor, x, op).sum().backward()
    assert all(p.grad is not None and p.grad.abs().sum() > 0 for p in actor.parameters())


def test_graph_operator_rejects_unknown_kind() -> None:
    with pytest.raises(ValueError, match="unknown conv"):
        graph_operator("gat", torch.zeros(2, 0, dtype=torch.long), 3)  # type: ignore[arg-type]
