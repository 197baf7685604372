"""A recurrent graph policy for meta-RL through recurrence (RL², Duan et al. 2016).

Every region keeps a GRU memory that reads, each control step, the region's (scaled) features,
the share of the fleet the previous action asked of it, the previous reward *of that region*
(the profit of the trips that left it, minus its rebalancing cost) and the previous team reward.
The memory is *not* reset between the episodes of a trial on one city, so what it learned about
this city (how the fleet, demand and rewards respond, and where and when demand departs from the
forecast) carries into the next episode: adaptation without a gradient step. The per-region
reward is what lets a region's memory notice a local shock (a special event) that the team
reward only shows as a blur. Message passing between regions follows the memory, so each
region's action sees its neighbours' memories too. The same weights act on every region
(size-agnostic): one policy serves cities of 10 to 23 regions.

Shapes: B trials in lockstep (optional leading axes), N regions, F features, H hidden units.
The graph is ``edge_index`` (2, E) or a :class:`~marl_amod.models.dense.DenseGraph` (one matmul
per layer over the whole batch, what meta-training uses). Cities of different sizes go in one batch
two ways. Side by side, (B, N_1 + ... + N_C, F) with a :class:`~marl_amod.models.dense.PackedGraphs`
(their disjoint union; one team reward and one value per city): every row is a region, and the
per-city sums (:class:`~marl_amod.models.dense.Cities`) keep the cities apart; meta-training's opt-in ``pack_cities`` (1.15x an
update faster than padding at 128 hidden units in bf16). Or padded, (C, B, N_max, F) with a :class:`~marl_amod.models.dense.PaddedGraphs`:
the padded regions' memories run on whatever the padding holds but are never read (no messages,
masked pools and stay prior, left out of the value's mean); their concentration comes back 0.
(Running each per-region layer of the padded form on the real rows only, an index_select and
index_copy per layer, measured no faster: packing once per trial is what pays.) Nor did teacher-forced training gain from running the
encoder, messages and heads once over all steps with only the GRU stepped (the inputs are known in
advance): one update of ``configs/meta/bc_dagger_l1.yaml`` took 1.2x longer (the backward pass 1.4x),
the large tensors falling out of the cache; each step's batch is already large enough to pay.
"""

from __future__ import annotations

import math
from functools import partial

import torch
import torch.nn.functional as F
from torch import nn

from marl_amod.models.dense import Cities, DenseGraph, PackedGraphs, PaddedGraphs
from marl_amod.models.gnn import ConvKind, Graph, Readout, batch_edge_index, concentration, make_conv, mlp_head, readout_layer

N_FEEDBACK = 3  # previous action share, previous region reward, previous team reward
STAY_FLOOR = 0.1  # x 1/N: what a region without idle vehicles gets in the stay prior
STAY_CONCENTRATION = 20.0  # x N: total concentration of the untrained stay policy (samples near the mean)


class RecurrentGNN(nn.Module):
    """(features, previous action, previous rewards, memory) -> (concentrations, value, memory).

    Actor and critic share the memory and the message passing (one trunk, two heads): the value
    of a state depends on what the memory has inferred about the city as much as the action does.

    ``stay_prior``: the actor's output is a log-ratio to the distribution of the idle vehicles now
    (feature column 0, mixed with ``STAY_FLOOR`` / N of uniform): alpha_i = c N (idle share_i) exp(a_i),
    c = ``STAY_CONCENTRATION``: concentrated enough that sampled actions (adaptation episodes, RL²)
    stay near the mean an imitation fitted (the cross-entropy fits the mean, not the spread).
    The untrained policy then asks for what is there (no move, no cost) instead of a random
    distribution, and a demonstrator that mostly keeps vehicles where they are and moves a few
    (MPC-Forecast) differs from it by small log-ratios instead of an exact copy of the idle counts.

    ``readout`` (:class:`~marl_amod.models.gnn.FleetReadout`, after the message passing): both heads
    also see a pool over all regions (mean and/or max of a learned map of (memory, neighbours)):
    MPC-Forecast plans for the whole fleet, one hop of messages shows a region only its neighbours.

    ``demand_prior`` (a share g, with ``stay_prior``): the prior mixes in the regions' share of the
    requests, the sum of the feature columns ``demand_columns`` (the requests just served and left
    unserved, and those expected next step): alpha_i = c N ((1 - f - g) idle share_i + g demand
    share_i + f / N) exp(a_i). Why: the idle share alone reads a region emptied by its own demand (a
    dominant hotspot, a surge) as "few vehicles wanted", so filling it takes a log-ratio that grows
    without bound as its idle vehicles run out, on states imitation rarely showed (docs/meta/log.md,
    "Where the held-out gap is now"); with demand in the prior an emptied busy region keeps weight.

    ``centred`` (with ``stay_prior``): the actor's outputs minus their mean over the city's regions
    before the clamp. Why: the Dirichlet mean reads only their differences, so imitation never
    trains their common level; it drifts (-2.9 to +2.3 across nine good seeds of the recipes, so their
    adaptation episodes sample with concentrations 180x apart) and, past the clamp at +10, passes
    no gradient: one seed's actor sat there from update 200 on as the stay prior itself
    (docs/meta/log.md, "Why seed 7 stalled"). Centred, the level is 0 by construction and the
    concentration is the prior's ``STAY_CONCENTRATION`` as designed.
    """

    def __init__(
        self, n_features: int, hidden: int = 64, conv: ConvKind = "sage", stay_prior: bool = False, readout: Readout = "none",
        demand_prior: float = 0.0, demand_columns: tuple[int, ...] = (), end_cut: bool = False, centred: bool = False,
    ) -> None:
        super().__init__()
        if centred and not stay_prior:
            raise ValueError("centred takes the actor's log-ratios to the stay prior: set stay_prior too")
        if demand_prior and (not stay_prior or not demand_columns or demand_prior + STAY_FLOOR > 1 or max(demand_columns) >= n_features):
            raise ValueError(f"demand_prior {demand_prior} needs stay_prior, demand columns among the {n_features} features and a share <= {1 - STAY_FLOOR}")
        self.hidden, self.stay_prior, self.n_features, self.readout_kind = hidden, stay_prior, n_features, readout
        self.demand_prior, self.demand_columns = float(demand_prior), tuple(demand_columns)
        self.centred = centred  # how its outputs are read, not a weight (docstring)
        self.end_cut = end_cut  # what its inputs are, not a weight: the task features cut at the episode's end (meta.cut_at_end)
        self.encode = nn.Sequential(nn.Linear(n_features + N_FEEDBACK, hidden), nn.ReLU())
        self.memory = nn.GRUCell(hidden, hidden)
        self.conv = make_conv(conv, hidden)
        self.readout = readout_layer(readout, 2 * hidden, hidden)  # None for "none": old files load unchanged
        head_in = self.readout.out_dim if self.readout is not None else 2 * hidden
        self.actor = mlp_head(head_in, hidden)
        self.critic = mlp_head(head_in, hidden)

    def initial_memory(self, n_regions: int, *lead: int) -> torch.Tensor:
        """(*lead, N, H) zeros: the memory at the start of a trial (a new city)."""
        return torch.zeros(*lead, n_regions, self.hidden)

    def forward(
        self, x: torch.Tensor, prev_action: torch.Tensor, prev_region_reward: torch.Tensor, prev_reward: torch.Tensor,
        memory: torch.Tensor, graph: Graph | PaddedGraphs | PackedGraphs,
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """x (..., N, F), prev_action (..., N), prev_region_reward (..., N), prev_reward (...),
        memory (..., N, H) -> alpha (..., N), value (...), memory (..., N, H). With
        :class:`PaddedGraphs` whatever the padding holds is ignored; its alpha comes back 0. With
        :class:`PackedGraphs` (N the cities' regions side by side) prev_reward and value are (..., C): one per city."""
        *lead, n, _ = x.shape
        cities = Cities(graph, n)
        team = cities.per_region(prev_reward if cities.packed is not None else prev_reward.reshape(lead)).unsqueeze(-1)  # (..., N, 1)
        inputs = torch.cat([x, prev_action.unsqueeze(-1), prev_region_reward.unsqueeze(-1), team], dim=-1)  # (..., N, F + 3)
        flat = self.encode(inputs).reshape(-1, self.hidden)
        # float32 out of the GRU and the heads (no-ops in float32): under bf16 autocast only the products are bf16,
        # the memory carried across a trial's steps and what the prior and losses read keep float32's precision
        memory = self.memory(flat, memory.reshape(-1, self.hidden)).float().reshape(*lead, n, self.hidden)  # (..., N, H)
        read = _for_products(memory)  # what the layers after the GRU read
        if isinstance(graph, DenseGraph | PaddedGraphs | PackedGraphs):
            mixed = graph.conv(self.conv, read)
        else:  # torch-geometric: the batch as one graph of B copies
            edges = batch_edge_index(graph, math.prod(lead), n) if lead else graph
            mixed = self.conv(read.reshape(-1, self.hidden), edges).reshape(*lead, n, self.hidden)
        z = torch.cat([read, F.relu(mixed)], dim=-1)  # (..., N, 2H): own memory, neighbours' memories
        fleet = self.readout.summary(z, cities) if self.readout is not None else None  # (..., 1 or C, kH)
        actor, per_region = (out.squeeze(-1).float() for out in _heads(z, fleet, (self.actor, self.critic), cities))  # (..., N)
        if self.stay_prior:
            idle = x[..., 0]  # (..., N) idle vehicles per region, in per-city units
            stay = (1 - STAY_FLOOR - self.demand_prior) * cities.share(idle) + STAY_FLOOR / cities.regions
            if self.demand_prior:
                demand = x[..., list(self.demand_columns)].sum(-1)  # (..., N) requests, in per-city units
                stay = stay + self.demand_prior * cities.share(demand)
            if self.centred:
                actor = actor - cities.per_region(cities.mean(actor))
            alpha = STAY_CONCENTRATION * cities.regions * stay * torch.exp(actor.clamp(-10, 10))  # (..., N)
        else:
            alpha = concentration(actor)  # (..., N)
        if cities.mask is not None:
            alpha = alpha.masked_fill(~cities.mask, 0.0)
        return alpha, cities.mean(per_region), memory  # the value: a mean over regions (rewards are per-city scaled, so N-free)


def _heads(
    z: torch.Tensor, fleet: torch.Tensor | None, heads: tuple[nn.Sequential, ...], cities: Cities | None = None
) -> list[torch.Tensor]:
    """Each :func:`~marl_amod.models.gnn.mlp_head` of ``heads`` on every region's (z, fleet summary),
    z (..., N, C), fleet (..., 1, P) or None (cities side by side: (..., C, P), one per city; ``cities``
    says where each city's regions lie), without building that (..., N, C + P) concatenation:
    the first layers' weights split into the columns that read z and those that read the summary,
    which run once per graph instead of once per region, and all heads' first layers run as one
    matmul. The same function as the heads on :meth:`FleetReadout.forward`'s output, to float
    rounding (tested); a meta-imitation update ran 1.18x faster alone, 1.12x with two runs side by
    side (``benchmarks/meta_update.py``): with the mean-max readout the summary is half of what the first layers read."""
    firsts = [head[0] for head in heads]
    weight, bias = torch.cat([f.weight for f in firsts]), torch.cat([f.bias for f in firsts])  # (sum of outs, C + P), (sum of outs,)
    c = z.shape[-1]
    pre = F.linear(z, weight[:, :c], bias)
    if fleet is not None:
        summary = F.linear(fleet, weight[:, c:])  # (..., 1 or C, outs)
        pre = pre + (cities.to_regions(summary) if cities is not None else summary)  # each region its city's
    hidden = F.relu(pre).split([f.out_features for f in firsts], dim=-1)
    return [head[2:](h) for head, h in zip(heads, hidden, strict=True)]  # the rest of each head: Linear, ReLU, Linear


def _for_products(memory: torch.Tensor) -> torch.Tensor:
    """The memory as the layers after the GRU read it: under CPU autocast cast to its dtype once, else itself.

    Why: every reader is a product, which autocast would cast the float32 memory for again, and the
    concatenation the readout and heads read would be promoted to float32 and cast back for each; cast
    once, the products see the same bf16 values (the losses bit for bit the same) and a 128-unit bf16
    update runs about 1.06x faster (``benchmarks/meta_update.py``). The memory carried to the next step stays float32.
    """
    return memory.to(_cpu_autocast_dtype()) if _cpu_autocast_enabled() else memory


# CPU autocast's state through the installed torch's API, chosen once at import (the device-type forms came in 2.4;
# the package supports 2.2, whose forms 2.4 deprecates)
if hasattr(torch, "get_autocast_dtype"):
    _cpu_autocast_enabled, _cpu_autocast_dtype = partial(torch.is_autocast_enabled, "cpu"), partial(torch.get_autocast_dtype, "cpu")
else:  # torch 2.2-2.3
    _cpu_autocast_enabled, _cpu_autocast_dtype = torch.is_autocast_cpu_enabled, torch.get_autocast_cpu_dtype


def concatenated_heads(
    z: torch.Tensor, fleet: torch.Tensor | None, heads: tuple[nn.Sequential, ...], cities: Cities | None = None
) -> list[torch.Tensor]:
    """The plain form of :func:`_heads`: the summary copied to every region, each head on the
    concatenation. The reference the tests and ``benchmarks/meta_update.py`` compare it with."""
    if fleet is not None and cities is not None:
        fleet = cities.to_regions(fleet)
    full = z if fleet is None else torch.cat([z, fleet.expand(*z.shape[:-1], fleet.shape[-1])], dim=-1)
    return [head(full) for head in heads]
