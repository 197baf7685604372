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

Two forms put C cities of different sizes in one batch, for meta-training's updates over several cities:

* :class:`PaddedGraphs` (C, B, N_max, C_in): each city's operator sits in the top-left block of an
  (N_max, N_max) zero matrix, so messages never cross cities and neither reach nor leave the
  padding; its ``mask`` tells the model which regions are real.
* :class:`PackedGraphs` (B, N_1 + ... + N_C, C_in): the cities' regions side by side, one graph that is
  their disjoint union (a block-diagonal operator), so no row is padding; its per-city sums and
  pools tell the model where each city's regions lie.

:class:`Cities` gives a model the per-city reductions (means, shares, pools) of any of the three
forms, one city included; :class:`~marl_amod.models.recurrent.RecurrentGNN` reads them.
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
Pool = Literal["mean", "max"]


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


class PackedGraphs(_Operators):
    """C city graphs as one graph, their disjoint union: inputs (B, N_1 + ... + N_C, ...) with each
    city's regions side by side (city 0's first), trial b of every city in row b.

    Why: padded to the largest city (:class:`PaddedGraphs`), an update of four cities of 12-23
    regions spends about a fifth of every per-region product on padding, and at 128 hidden units
    the update's time is those products; packed, every row is a region. The operator is
    block-diagonal, so messages never cross cities; the model's pools, shares and means run per
    city through :meth:`city_sum`, :meth:`city_pool` and :meth:`spread` (:class:`Cities`). :meth:`pack` and
    :meth:`unpack` convert from and to the padded layout (C, B, N_max, ...) the losses read.
    """

    def __init__(self, graphs: Sequence[DenseGraph]) -> None:
        super().__init__()
        self.graphs = list(graphs)
        self.sizes = [g.n for g in self.graphs]
        self.n, self.n_max = sum(self.sizes), max(self.sizes)
        self.starts = np.cumsum([0, *self.sizes[:-1]]).tolist()
        self.city = torch.repeat_interleave(torch.arange(len(self.sizes)), torch.tensor(self.sizes))  # (N,) each region's city
        self.city_regions = torch.tensor(self.sizes, dtype=torch.float32)  # (C,)
        self.regions = self.city_regions[self.city]  # (N,) each region's city's region count
        # position of each packed region in the padded (C x N_max) layout, city-major
        self._padded_at = torch.cat([c * self.n_max + torch.arange(n) for c, n in enumerate(self.sizes)])

    def _build(self, kind: ConvKind) -> torch.Tensor:
        """(N, N): the cities' operators on the diagonal, zeros elsewhere."""
        return torch.block_diag(*(g.operator(kind) for g in self.graphs))

    def city_sum(self, v: torch.Tensor) -> torch.Tensor:
        """(..., N) -> (..., C): each city's sum over its regions."""
        return torch.stack([v.narrow(-1, s, n).sum(-1) for s, n in zip(self.starts, self.sizes, strict=True)], dim=-1)

    def city_pool(self, e: torch.Tensor, kind: Pool) -> torch.Tensor:
        """(..., N, H) -> (..., C, H): each city's mean or max over its regions."""
        reduce = {"mean": torch.mean, "max": torch.amax}[kind]
        return torch.stack([reduce(e.narrow(-2, s, n), -2) for s, n in zip(self.starts, self.sizes, strict=True)], dim=-2)

    def spread(self, v: torch.Tensor, dim: int = -1) -> torch.Tensor:
        """(..., C, ...) -> (..., N, ...): each city's entry copied to its regions (along ``dim``)."""
        return v.index_select(dim, self.city)

    def pack(self, v: torch.Tensor, features: bool) -> torch.Tensor:
        """Padded (..., C, B, N_max[, F]) -> packed (..., B, N[, F]); ``features``: whether a last axis follows the regions'."""
        r = -2 if features else -1  # the region axis
        moved = v.movedim(r - 2, r - 1)  # (..., B, C, N_max[, F])
        return moved.flatten(r - 1, r).index_select(r, self._padded_at)

    def unpack(self, v: torch.Tensor) -> torch.Tensor:
        """Packed (..., B, N) -> padded (..., C, B, N_max), zeros in the padding."""
        out = v.new_zeros(*v.shape[:-1], len(self.sizes) * self.n_max).index_copy(-1, self._padded_at, v)
        return out.unflatten(-1, (len(self.sizes), self.n_max)).movedim(-2, -3)


class Cities:
    """Where each city's regions lie in a batch of N regions, and the per-city reductions a model
    takes over them: one city (a plain graph or :class:`DenseGraph`: all N regions), cities padded to
    one size (:class:`PaddedGraphs`: its mask), or side by side (:class:`PackedGraphs`: its segments).
    A per-city quantity is (...) for one city and padded cities (their lead axes hold the city) and
    (..., C) packed; ``regions`` broadcasts against (..., N): each region's city's region count."""

    def __init__(self, graph: object, n: int) -> None:
        self.n = n
        self.mask = graph.mask if isinstance(graph, PaddedGraphs) else None  # (C, 1, N): the real regions
        self.packed = graph if isinstance(graph, PackedGraphs) else None
        self.regions: int | torch.Tensor = n
        if self.packed is not None:
            self.regions = self.packed.regions  # (N,)
        elif self.mask is not None:
            self.regions = self.mask.sum(-1, keepdim=True)  # (C, 1, 1)

    def mean(self, v: torch.Tensor) -> torch.Tensor:
        """(..., N) -> each city's mean over its real regions."""
        if self.packed is not None:
            return self.packed.city_sum(v) / self.packed.city_regions
        if self.mask is None:
            return v.mean(-1)
        return v.masked_fill(~self.mask, 0.0).sum(-1) / self.regions.squeeze(-1)

    def per_region(self, v: torch.Tensor) -> torch.Tensor:
        """A per-city quantity as (..., N): each region gets its city's."""
        return self.packed.spread(v) if self.packed is not None else v.unsqueeze(-1).expand(*v.shape, self.n)

    def share(self, v: torch.Tensor) -> torch.Tensor:
        """(..., N) counts -> their distribution over each city's real regions; negatives count 0, all zero stays zero."""
        v = v.clamp_min(0) if self.mask is None else v.clamp_min(0).masked_fill(~self.mask, 0.0)
        total = self.packed.spread(self.packed.city_sum(v)) if self.packed is not None else v.sum(-1, keepdim=True)
        return v / total.clamp_min(1e-9)

    def pool(self, e: torch.Tensor, kind: Pool) -> torch.Tensor:
        """(..., N, H) -> each city's mean or max over its real regions: (..., 1, H), or (..., C, H) packed."""
        if self.packed is not None:
            return self.packed.city_pool(e, kind)
        if self.mask is None:
            return e.mean(-2, keepdim=True) if kind == "mean" else e.amax(-2, keepdim=True)
        m = self.mask.unsqueeze(-1)  # (C, 1, N, 1)
        if kind == "mean":
            return (e * m).sum(-2, keepdim=True) / m.sum(-2, keepdim=True)
        return e.masked_fill(~m, float("-inf")).amax(-2, keepdim=True)

    def to_regions(self, summary: torch.Tensor) -> torch.Tensor:
        """A :meth:`pool`'s output (..., 1 or C, P) in a form that adds to (..., N, P): each region its city's."""
        return self.packed.spread(summary, dim=-2) if self.packed is not None else summary
