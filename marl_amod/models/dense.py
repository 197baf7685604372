"""The small-graph path: the GNN layers of :mod:`marl_amod.models.gnn` as one matmul per layer.

For the city graphs here (10-400 regions) torch-geometric's scatter kernels spend far more time
on bookkeeping than on arithmetic. One layer is linear in the node features, so it is a fixed
(N, N) operator ``P`` of the graph applied to a batch (B, N, C) with one ``P @ x``:

* GCN (``GCNConv``, self-loops, symmetric normalisation): ``P = D^-1/2 (A + I) D^-1/2`` with
  ``A[i, j]`` the number of edges j -> i and D the in-degree counting the self-loop;
  out = P @ lin(x) + bias.
* SAGE with mean aggregation (``SAGEConv(aggr="mean")``): ``P = A / in-degree`` (rows of
  isolated regions stay zero); out = lin_l(P @ x) + lin_r(x).

The functions take the torch-geometric modules themselves, so a model trained on either path
runs on the other with the same parameters (outputs agree to float rounding, tested to 1e-5).
Give a model a :class:`DenseGraph` instead of ``edge_index`` and it takes this path; the
operators are built once per city and reused every forward pass.

:class:`PaddedGraphs` puts C cities of different sizes in one batch (C, B, N_max, C_in): each
city's operator sits in the top-left block of an (N_max, N_max) zero matrix, so messages never
cross cities and neither reach nor leave the padding; its ``mask`` tells the model which regions
are real (:class:`~marl_amod.models.recurrent.RecurrentGNN` reads it).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import TYPE_CHECKING, Literal

import numpy as np
import torch
from torch import nn
from torch_geometric.nn import GCNConv, SAGEConv

if TYPE_CHECKING:
    from marl_amod.scenario import City

ConvKind = Literal["gcn", "sage"]


def graph_operator(kind: ConvKind, edge_index: torch.Tensor, n: int, dtype: torch.dtype = torch.float32) -> torch.Tensor:
    """(N, N) dense propagation operator of a ``"gcn"`` or ``"sage"`` layer on the graph (2, E)."""
    edge_index = torch.as_tensor(edge_index, dtype=torch.long)
    src, dst = edge_index
    adj = torch.zeros(n, n, dtype=dtype, device=edge_index.device)
    adj.index_put_((dst, src), torch.ones(src.numel(), dtype=dtype, device=adj.device), accumulate=True)
    if kind == "gcn":
        adj.fill_diagonal_(1.0)  # add_remaining_self_loops: one self-loop of weight 1 per node
        d = adj.sum(1).rsqrt()  # >= 1 thanks to the self-loop
        return d[:, None] * adj * d[None, :]
    if kind == "sage":
        return adj / adj.sum(1, keepdim=True).clamp_min(1.0)
    raise ValueError(f"unknown conv {kind!r}; use 'gcn' or 'sage'")


def dense_conv(conv: nn.Module, x: torch.Tensor, op: torch.Tensor) -> torch.Tensor:
    """One GCNConv or mean-SAGEConv layer on x (..., N, C) with its own weights: (..., N, C_out)."""
    if isinstance(conv, GCNConv):
        out = op @ conv.lin(x)
        return out + conv.bias if conv.bias is not None else out
    if isinstance(conv, SAGEConv):
        if conv.aggr != "mean" or conv.project or conv.normalize or not conv.root_weight:
            raise ValueError("the dense path covers SAGEConv(aggr='mean') without project/normalize, with root weight")
        return conv.lin_l(op @ x) + conv.lin_r(x)
    raise TypeError(f"no dense form for {type(conv).__name__}")


class _Operators:
    """What both graph forms share: each conv kind's operator built on first use and reused every
    forward pass (``_build`` makes it), and a conv layer applied through it."""

    def __init__(self) -> None:
        self._ops: dict[str, torch.Tensor] = {}

    def _build(self, kind: ConvKind) -> torch.Tensor:
        raise NotImplementedError

    def operator(self, kind: ConvKind) -> torch.Tensor:
        """The operator of a ``"gcn"`` or ``"sage"`` layer on this graph (built once)."""
        if kind not in self._ops:
            # a normal tensor even when first asked for in inference mode (SAC's target side):
            # later passes that autograd records reuse it
            with torch.inference_mode(False):
                self._ops[kind] = self._build(kind)
        return self._ops[kind]

    def conv(self, conv: nn.Module, x: torch.Tensor) -> torch.Tensor:
        """``conv`` (GCNConv or mean SAGEConv) on x (..., N, C) through this graph's operator."""
        return dense_conv(conv, x, self.operator("gcn" if isinstance(conv, GCNConv) else "sage"))


class DenseGraph(_Operators):
    """One city graph for the dense path: pass it where a GNN model takes ``edge_index``.

    Holds the (N, N) operator of each conv kind, built on first use and reused every forward
    pass, so a batch (B, N, C) costs one ``P @ x`` per layer. The models of
    :mod:`marl_amod.models.gnn` accept either form and give the same outputs to float rounding.
    """

    def __init__(self, edge_index: torch.Tensor, n: int) -> None:
        super().__init__()
        self.edge_index = torch.as_tensor(edge_index, dtype=torch.long)
        self.n = int(n)

    def _build(self, kind: ConvKind) -> torch.Tensor:
        """The (N, N) operator of ``kind`` on this graph."""
        return graph_operator(kind, self.edge_index, self.n)


def city_graph(city: City) -> DenseGraph:
    """The city graph in the dense form of the batched path."""
    return DenseGraph(torch.tensor(np.array(city.edge_index), dtype=torch.long), city.n_regions)


class PaddedGraphs(_Operators):
    """C city graphs as one padded batch: pass it where :class:`DenseGraph` goes, with inputs
    (C, B, N_max, ...) (city, trial, region): one matmul per layer for every city at once.

    Why: the cities of a meta-training update differ in size; one after another they cost C
    forward passes of small tensors, padded together one. Region j of city c is real when
    ``mask[c, 0, j]``; the padding's rows and columns of the operator are zero, so a padded
    region's state never reaches a real one (a model must still mask its pools and outputs).
    """

    def __init__(self, graphs: Sequence[DenseGraph]) -> None:
        super().__init__()
        self.graphs = list(graphs)
        self.n = max(g.n for g in self.graphs)
        sizes = torch.tensor([g.n for g in self.graphs])
        self.mask = (torch.arange(self.n) < sizes[:, None]).unsqueeze(1)  # (C, 1, N_max): broadcasts over the trials

    def _build(self, kind: ConvKind) -> torch.Tensor:
        """(C, 1, N_max, N_max): each city's operator in its top-left block, zeros elsewhere."""
        block = torch.zeros(len(self.graphs), 1, self.n, self.n)
        for c, g in enumerate(self.graphs):
            block[c, 0, : g.n, : g.n] = g.operator(kind)
        return block
