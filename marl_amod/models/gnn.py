"""The paper's graph networks: a GNN actor with a Dirichlet head and GNN critics.

One message-passing layer with a residual connection, then a per-node MLP: the same weights
act on every region, so a trained model runs on any city's graph (size-agnostic) and relabelling
the regions relabels the outputs (permutation equivariance). That reach is one hop: region i's
output depends on its own and its neighbours' features only. ``readout`` (off by default, the
paper's model) appends a pooled summary of the whole fleet to every node before the head
(:class:`FleetReadout`), which keeps both properties; on the MPC-Forecast clone it moved the
GNN only slightly towards the MLP (docs/offline/bc_fidelity.md, "BC fidelity" 6). ``agent_ids`` (off
by default) appends a one-hot of the region index to every node's input (:class:`RegionIdentity`,
the agent-ID input of parameter-shared MARL policies): a region's output can then depend on
where it is, not only on what it sees, which gives up both properties (the model is tied to
one city's size and region order).

Shapes: B graphs in a batch, N regions, F node features, E directed edges, H hidden units.
Every model takes the graph as ``edge_index`` (torch-geometric's scatter kernels) or as a
:class:`~marl_amod.models.dense.DenseGraph` (one dense matmul per layer: much cheaper on the
10-400-region city graphs here, same outputs to float rounding). :class:`StackedTwinQ` is
:class:`TwinQ` for the dense path with both critics in one set of stacked weights.
"""

from __future__ import annotations

from typing import Literal, get_args

import torch
import torch.nn.functional as F
from torch import nn
from torch_geometric.nn import GCNConv, SAGEConv

from marl_amod.models.dense import Cities, ConvKind, DenseGraph
from marl_amod.models.distributions import CONCENTRATION_EPS

Graph = torch.Tensor | DenseGraph  # (2, E) edge_index for torch-geometric, or the dense small-graph form
Readout = Literal["none", "mean", "max", "mean-max"]
READOUTS: tuple[str, ...] = get_args(Readout)


def batch_edge_index(edge_index: torch.Tensor, batch: int, n: int) -> torch.Tensor:
    """Stack B copies of one (2, E) graph into (2, B*E) over B*N flattened nodes."""
    offsets = (torch.arange(batch, device=edge_index.device) * n).view(batch, 1, 1)  # (B, 1, 1)
    return (edge_index.unsqueeze(0) + offsets).permute(1, 0, 2).reshape(2, -1)


def make_conv(kind: ConvKind, channels: int) -> nn.Module:
    """GCN (the paper's, degree-normalised sum) or SAGE (mean of neighbours, computable locally)."""
    if kind == "gcn":
        return GCNConv(channels, channels)
    if kind == "sage":
        return SAGEConv(channels, channels, aggr="mean")
    raise ValueError(f"unknown conv {kind!r}; use 'gcn' or 'sage'")


class _GraphTrunk(nn.Module):
    """relu(conv(x)) + x over a batch of copies of one graph: (B, N, C) -> (B, N, C)."""

    def __init__(self, channels: int, conv: ConvKind) -> None:
        super().__init__()
        self.conv = make_conv(conv, channels)

    def forward(self, x: torch.Tensor, edge_index: Graph) -> torch.Tensor:
        if isinstance(edge_index, DenseGraph):  # one matmul per layer over the whole batch
            return F.relu(edge_index.conv(self.conv, x)) + x
        b, n, c = x.shape
        flat = x.reshape(b * n, c)  # (B*N, C)
        h = F.relu(self.conv(flat, batch_edge_index(edge_index, b, n)))  # (B*N, C)
        return (h + flat).view(b, n, c)


class FleetReadout(nn.Module):
    """Every node's embedding with a summary of all nodes appended: (..., N, C) -> (..., N, C + k*H).

    The summary pools a learned per-node map relu(W h_j + b) (H units) over the regions by mean
    and/or max (k pools): pooling the raw embeddings would give the head only the fleet's
    averages, while a learned map before a symmetric pool can represent any function of the set
    (DeepSets). Mean and max do not grow with the region count, and a pool ignores the regions'
    order, so the model stays size-agnostic and permutation-equivariant; it is the same on the
    torch-geometric and dense paths (it acts after the convolution).
    """

    def __init__(self, channels: int, hidden: int, kind: Readout) -> None:
        super().__init__()
        if kind not in READOUTS or kind == "none":
            raise ValueError(f"unknown readout {kind!r}; use one of {', '.join(READOUTS[1:])} (or 'none': no readout)")
        self.pools = ("mean", "max") if kind == "mean-max" else (kind,)
        self.embed = nn.Sequential(nn.Linear(channels, hidden), nn.ReLU())
        self.out_dim = channels + len(self.pools) * hidden

    def forward(self, h: torch.Tensor) -> torch.Tensor:
        pooled = self.summary(h)  # (..., 1, kH)
        return torch.cat([h, pooled.expand(*h.shape[:-1], pooled.shape[-1])], dim=-1)

    def summary(self, h: torch.Tensor, cities: Cities | None = None) -> torch.Tensor:
        """(..., N, C) -> (..., 1, kH): the pools alone, once per graph (what ``forward`` appends to every node);
        ``cities`` (several cities in one batch, :class:`~marl_amod.models.dense.Cities`): each city's pools over
        its real regions ((..., C, kH) for cities side by side)."""
        e = self.embed(h)  # (..., N, H)
        cities = cities if cities is not None else Cities(None, h.shape[-2])
        return torch.cat([cities.pool(e, p) for p in self.pools], dim=-1)


class RegionIdentity(nn.Module):
    """Every node's input with a one-hot of its region index appended: (..., N, F) -> (..., N, F + N).

    A shared-weight GNN sees a corner and the centre of a grid alike unless their features
    differ, while a planner's move depends on place (where the demand wave is headed); this is
    the agent-ID input parameter-shared MARL policies take (EPyMARL's ``obs_agent_id``, MAPPO).
    The one-hot is rebuilt on each call (no buffer), so the state dict holds no extra entry.
    """

    def __init__(self, n_regions: int) -> None:
        super().__init__()
        if n_regions < 1:
            raise ValueError(f"a region identity needs the region count (got {n_regions})")
        self.n_regions = n_regions

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        n = x.shape[-2]
        if n != self.n_regions:
            raise ValueError(f"the model appends a {self.n_regions}-region identity; this graph has {n} regions")
        eye = torch.eye(n, dtype=x.dtype, device=x.device)
        return torch.cat([x, eye.expand(*x.shape[:-2], n, n)], dim=-1)

    def extra_repr(self) -> str:
        return f"n_regions={self.n_regions}"


def readout_layer(kind: Readout, channels: int, hidden: int) -> FleetReadout | None:
    """The readout of a model, or None for ``"none"`` (no module, so the paper's models keep
    their parameters and old checkpoints load unchanged)."""
    if kind == "none":
        return None
    return FleetReadout(channels, hidden, kind)


def mlp_head(in_dim: int, hidden: int, out_dim: int = 1) -> nn.Sequential:
    return nn.Sequential(nn.Linear(in_dim, hidden), nn.ReLU(), nn.Linear(hidden, hidden), nn.ReLU(), nn.Linear(hidden, out_dim))


def concentration(raw: torch.Tensor) -> torch.Tensor:
    """softplus + eps: positive Dirichlet concentrations, in float32 even when the network ran in
    bfloat16 (SAC's ``precision: bf16``): the Dirichlet's log-density is steep in them."""
    return F.softplus(raw.float()) + CONCENTRATION_EPS


def _batched(x: torch.Tensor) -> tuple[torch.Tensor, bool]:
    return (x.unsqueeze(0), True) if x.dim() == 2 else (x, False)


class _NodeEmbedding(nn.Module):
    """The part the actor and the value critic share: the optional region identity on the input
    (:class:`RegionIdentity`, ``agent_ids`` = N regions, 0: none), the graph trunk, then the
    optional fleet-wide readout (:class:`FleetReadout`); ``embed_dim`` is what their node MLP reads."""

    def __init__(self, n_features: int, hidden: int, conv: ConvKind, readout: Readout, agent_ids: int = 0) -> None:
        super().__init__()
        # None when off: no module, so the models without it print and load as before
        self.region_id = RegionIdentity(agent_ids) if agent_ids else None
        channels = n_features + agent_ids
        self.trunk = _GraphTrunk(channels, conv)
        self.readout = readout_layer(readout, channels, hidden)
        self.embed_dim = self.readout.out_dim if self.readout else channels

    def embed(self, x: torch.Tensor, edge_index: Graph) -> torch.Tensor:
        """(B, N, F) -> what the node MLP reads: (B, N, C), C = F (+ N with the region identity)
        (+ k*H with a readout)."""
        if self.region_id is not None:
            x = self.region_id(x)
        h = self.trunk(x, edge_index)
        return self.readout(h) if self.readout is not None else h


class GNNActor(_NodeEmbedding):
    """Node features (B, N, F) -> Dirichlet concentrations (B, N); unbatched (N, F) -> (N,).

    ``readout``: append a fleet-wide summary to every node before the head (:class:`FleetReadout`).
    ``agent_ids``: the region count N of the one city it runs on, to append a one-hot region
    identity to every node's input (:class:`RegionIdentity`); 0 (default): none.
    """

    def __init__(
        self, n_features: int = 13, hidden: int = 32, conv: ConvKind = "gcn", readout: Readout = "none", agent_ids: int = 0
    ) -> None:
        super().__init__(n_features, hidden, conv, readout, agent_ids)
        self.head = mlp_head(self.embed_dim, hidden)

    def forward(self, x: torch.Tensor, edge_index: Graph) -> torch.Tensor:
        x, squeeze = _batched(x)
        alpha = concentration(self.head(self.embed(x, edge_index)).squeeze(-1))  # (B, N)
        return alpha[0] if squeeze else alpha


class GNNValueCritic(_NodeEmbedding):
    """State value V(s): per-node embedding summed over regions -> (B,) (unbatched -> ()).

    ``readout`` and ``agent_ids`` as :class:`GNNActor`'s: each node's term also sees the
    fleet-wide summary, and its own region index.
    """

    def __init__(
        self, n_features: int = 13, hidden: int = 32, conv: ConvKind = "gcn", readout: Readout = "none", agent_ids: int = 0
    ) -> None:
        super().__init__(n_features, hidden, conv, readout, agent_ids)
        self.node = mlp_head(self.embed_dim, hidden, hidden)
        self.out = nn.Linear(hidden, 1)

    def forward(self, x: torch.Tensor, edge_index: Graph) -> torch.Tensor:
        x, squeeze = _batched(x)
        h = self.embed(x, edge_index)
        if isinstance(edge_index, DenseGraph):
            # the node MLP's last layer is linear, so it commutes with the sum over regions:
            # W sum_i h_i + N b, one (B, H) x (H, H) product instead of (B*N, H) x (H, H)
            *hidden, last = self.node
            pooled = last(nn.Sequential(*hidden)(h).sum(1)) + (h.shape[1] - 1) * last.bias
        else:
            pooled = self.node(h).sum(1)
        v = self.out(F.relu(pooled)).squeeze(-1)  # (B,)
        return v[0] if squeeze else v


class GNNQCritic(nn.Module):
    """Q(s, a) with the action (B, N) appended as one more node feature -> (B,)."""

    def __init__(self, n_features: int = 13, hidden: int = 256, conv: ConvKind = "gcn") -> None:
        super().__init__()
        self.value = GNNValueCritic(n_features + 1, hidden, conv)

    def forward(self, x: torch.Tensor, edge_index: Graph, action: torch.Tensor) -> torch.Tensor:
        return self.value(torch.cat([x, action.unsqueeze(-1)], dim=-1), edge_index)


class TwinQ(nn.Module):
    """SAC's two independent Q critics; min of the two curbs over-estimation."""

    def __init__(self, n_features: int = 13, hidden: int = 256, conv: ConvKind = "gcn") -> None:
        super().__init__()
        self.q1 = GNNQCritic(n_features, hidden, conv)
        self.q2 = GNNQCritic(n_features, hidden, conv)

    def forward(self, x: torch.Tensor, edge_index: Graph, action: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        return self.q1(x, edge_index, action), self.q2(x, edge_index, action)


class StackedLinear(nn.Module):
    """Two linear layers of one shape as one: weight (2, out, in), bias (2, out) or None.

    x (M, in) shared by both layers, or (2, M, in) one per layer -> (2, M, out): one batched
    matmul where two ``nn.Linear`` calls would each pay PyTorch's per-op overhead.
    """

    def __init__(self, weights: tuple[torch.Tensor, torch.Tensor], biases: tuple[torch.Tensor, torch.Tensor] | None) -> None:
        super().__init__()
        self.weight = nn.Parameter(torch.stack([w.detach() for w in weights]).clone())
        self.bias = None if biases is None else nn.Parameter(torch.stack([b.detach() for b in biases]).clone())

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if self.bias is None:
            return torch.matmul(x, self.weight.mT)
        if x.dim() == 3:
            return torch.baddbmm(self.bias.unsqueeze(1), x, self.weight.mT)
        return torch.matmul(x, self.weight.mT) + self.bias.unsqueeze(1)


class StackedTwinQ(nn.Module):
    """:class:`TwinQ` on the dense path with the two critics' weights stacked on a leading axis.

    Same functions as ``TwinQ`` (built from one, so the same initial weights; outputs equal to
    float rounding): each layer of both critics is one batched matmul, and the graph operator
    meets the input (state + action) once for both, since the conv layer is linear
    (``P (z W) = (P z) W``). On the small city graphs SAC's update is dominated by per-op
    overhead, which this halves. Takes a :class:`DenseGraph` and batches (B, N, F), (B, N).
    """

    def __init__(self, twin: TwinQ) -> None:
        super().__init__()
        v1, v2 = twin.q1.value, twin.q2.value
        c1, c2 = v1.trunk.conv, v2.trunk.conv
        self.kind: ConvKind = "gcn" if isinstance(c1, GCNConv) else "sage"
        if self.kind == "gcn":  # out = P z W + b
            self.conv = StackedLinear((c1.lin.weight, c2.lin.weight), (c1.bias, c2.bias))
            self.root: StackedLinear | None = None
        else:  # mean SAGE: out = lin_l(P z) + lin_r(z)
            if c1.aggr != "mean" or c1.project or c1.normalize or not c1.root_weight:
                raise ValueError("the dense path covers SAGEConv(aggr='mean') without project/normalize, with root weight")
            self.conv = StackedLinear((c1.lin_l.weight, c2.lin_l.weight), (c1.lin_l.bias, c2.lin_l.bias))
            self.root = StackedLinear((c1.lin_r.weight, c2.lin_r.weight), None)
        linears = [(a, b) for a, b in zip(v1.node, v2.node, strict=True) if isinstance(a, nn.Linear)]
        self.node = nn.ModuleList(StackedLinear((a.weight, b.weight), (a.bias, b.bias)) for a, b in linears)
        self.out = StackedLinear((v1.out.weight, v2.out.weight), (v1.out.bias, v2.out.bias))

    def forward(self, x: torch.Tensor, graph: DenseGraph, action: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        z = torch.cat([x, action.unsqueeze(-1)], dim=-1)  # (B, N, F)
        b, n, f = z.shape
        flat = z.reshape(b * n, f)
        h = self.conv((graph.operator(self.kind) @ z).reshape(b * n, f))  # (2, B*N, F)
        if self.root is not None:
            h = h + self.root(flat)
        h = F.relu(h, inplace=True) + flat  # residual, as _GraphTrunk
        first, hidden, last = self.node
        # ReLU in place where it can be (a linear layer's output is not needed for its backward):
        # these are the update's largest tensors, and their memory traffic is much of its cost.
        # The last ReLU acts on the per-graph view, so its backward takes the pooled gradient as
        # a broadcast and no (2, B, N, H) copy is made for the view.
        h = F.relu(hidden(F.relu(first(h), inplace=True)).view(2, b, n, -1))  # (2, B, N, H)
        # the last node layer is linear, so it commutes with the sum over regions (as GNNValueCritic);
        # the pooled head has B rows, so it runs in float32 under a bfloat16 autocast: Q's scale
        # (returns in the hundreds) needs float32's mantissa
        pooled = h.sum(2).float()  # (2, B, H)
        with torch.autocast(h.device.type, enabled=False):
            pooled = last(pooled) + (n - 1) * last.bias.unsqueeze(1)
            q = self.out(F.relu(pooled)).squeeze(-1)  # (2, B)
        return q[0], q[1]
