"""Meta-RL through recurrence: per-city units, the recurrent GNN, trials, adaptation, transfer strategies."""

from __future__ import annotations

import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch

from marl_amod.algos import meta
from marl_amod.algos.registry import ALGOS
from marl_amod.errors import ConfigError
from marl_amod.evaluation import evaluate
from marl_amod.metrics import normalised_score, score_points
from marl_amod.models.recurrent import RecurrentGNN
from marl_amod.scenario import grid_city, load_city
from marl_amod.system import FleetSystem
from marl_amod.transfer import STRATEGIES, run_strategy
from tests.conftest import needs_data


def _city_yaml(tmp_path, name, **keys):
    text = f"name: {name}\nsource: synthetic\nhorizon: 6\n" + "".join(f"{k}: {v}\n" for k, v in keys.items())
    (tmp_path / f"{name}.yaml").write_text(text)
    return str(tmp_path / f"{name}.yaml")


def test_city_scale_makes_a_tenfold_city_look_alike():
    """Ten times the fleet and the demand: the same scaled request features, rewards scaled 10x."""
    small = grid_city(rows=3, cols=3, vehicles_per_region=12, requests_per_region=3.0)
    big = grid_city(rows=3, cols=3, vehicles_per_region=120, requests_per_region=30.0)
    s_small, s_big = meta.CityScale.of(small), meta.CityScale.of(big)
    assert s_big.reward == pytest.approx(10 * s_small.reward) and s_big.vehicles == 10 * s_small.vehicles
    feats = []
    for city, scale in ((small, s_small), (big, s_big)):
        system = FleetSystem(city)
        system.reset(np.random.SeedSequence(0))
        feats.append(meta.task_features(system, scale, lookahead=3))
    assert feats[0].shape == (9, meta.n_task_features(3))
    np.testing.assert_allclose(feats[0][:, 4:7], feats[1][:, 4:7], rtol=1e-5)  # request values
    np.testing.assert_allclose(feats[0][:, -1], feats[1][:, -1])  # t / horizon
    # idle vehicles and served requests after the first dispatch: in units of fleet / N, about the same
    for col in (0, 7):
        assert abs(feats[0][:, col].mean() - feats[1][:, col].mean()) < 0.3


def test_task_features_show_the_served_and_unserved_requests_of_the_step():
    city = grid_city(rows=2, cols=2, vehicles_per_region=1, requests_per_region=6.0)
    system = FleetSystem(city)
    system.reset(np.random.SeedSequence(3))
    feats, scale = meta.task_features(system, meta.CityScale.of(city), lookahead=2), meta.CityScale.of(city)
    sim = system.sim
    np.testing.assert_allclose(feats[:, -3] * scale.vehicles, sim.last_dispatch.sum(-1), rtol=1e-6)
    np.testing.assert_allclose(feats[:, -2] * scale.vehicles, sim.requests().sum(-1), rtol=1e-6)
    assert feats[:, -2].sum() > 0  # more requests than vehicles: some go unserved


def test_structure_features_tell_where_trips_go_and_what_moves_cost():
    """The structure columns: expected requests into each region at t+1..t+T (vehicles per region),
    trip and rebalancing times in steps / T, the cost of driving / the mean fare; stored task
    features gain the same columns from their step column as the agent reads live."""
    city = load_city("synthetic")
    scale, lookahead = meta.CityScale.of(city), 3
    system = FleetSystem(city)
    system.reset(np.random.SeedSequence(2))
    for _ in range(2):
        system.step(system.sim.idle.copy())
    live = meta.task_features(system, scale, lookahead, structure=True)
    assert live.shape == (city.n_regions, meta.n_task_features(lookahead, structure=True))
    t = system.sim.t
    np.testing.assert_allclose(live[:, -6:-3] * scale.vehicles, city.forecast_rate[t + 1 : t + 4].sum(axis=1).T, rtol=1e-5)
    src, dst = city.edge_index
    i = int(src[0])
    np.testing.assert_allclose(live[i, -2] * lookahead, city.reb_time[i, dst[src == i]].mean(), rtol=1e-5)
    fare = (city.forecast_rate[: city.horizon] * city.price[: city.horizon]).sum() / city.forecast_rate[: city.horizon].sum()
    np.testing.assert_allclose(live[:, -1], city.beta * city.tstep / fare, rtol=1e-5)
    base = meta.task_features(system, scale, lookahead)[None, None]  # (E, T, N, F) as stored
    np.testing.assert_allclose(meta.with_structure(base, city, lookahead)[0, 0], live, rtol=1e-6)



def test_end_cut_shows_only_the_demand_mpc_plans_with_live_and_stored_alike():
    """With ``end_cut`` the value and inflow columns of steps past the episode's last step are zero
    (MPC-F's plan has no demand there: plan_data's live steps) and every other column is unchanged;
    stored task features cut at load equal the live ones at every step."""
    from marl_amod.baselines.mpc import plan_data

    city, lookahead = load_city("synthetic"), 3
    scale, t_total = meta.CityScale.of(city), city.horizon
    system = FleetSystem(city)
    system.reset(np.random.SeedSequence(4))
    value, inflow = slice(1 + lookahead, 1 + 2 * lookahead), slice(4 + 2 * lookahead, 4 + 3 * lookahead)
    seen_cut = 0
    while not system.done:
        t = system.sim.t
        full = meta.task_features(system, scale, lookahead, structure=True)
        cut = meta.task_features(system, scale, lookahead, structure=True, end_cut=True)
        live = t + np.arange(1, lookahead + 1) <= t_total - 1  # the look-ahead steps MPC-F gives demand
        planned = plan_data(city, t, system.sim.idle, system.sim.arrivals, np.ones((lookahead + 1, city.n_regions, city.n_regions)),
                            lookahead + 1).demand[1:].sum(axis=(1, 2)) > 0  # fmt: skip
        np.testing.assert_array_equal(live, planned)
        for cols in (value, inflow):
            np.testing.assert_array_equal(cut[:, cols][:, ~live], 0.0)
            np.testing.assert_array_equal(cut[:, cols][:, live], full[:, cols][:, live])
            assert (full[:, cols][:, ~live] > 0).any() or live.all()  # the city's tables do go on past the episode
        rest = np.ones(full.shape[1], dtype=bool)
        rest[value], rest[inflow] = False, False
        np.testing.assert_array_equal(cut[:, rest], full[:, rest])
        stored = meta.task_features(system, scale, lookahead)[None, None]  # (E, T, N, F) as a demonstration file keeps it
        np.testing.assert_allclose(meta.cut_at_end(meta.with_structure(stored, city, lookahead), city, lookahead)[0, 0], cut, rtol=1e-6)
        seen_cut += int((~live).any())
        system.step(system.sim.idle.copy())
    assert seen_cut == lookahead - 1  # the episode's last T - 1 decisions (t + T > horizon - 1) look past its end, none before

def test_place_features_tell_where_a_region_lies_relative_to_its_city():
    """The place columns: mean rebalancing time to and from the other regions over the city's
    mean, the region's shares of the day's requests out and in and of the initial fleet (x N);
    stored task features gain them with the structure columns, as the agent reads them live."""
    city = load_city("synthetic")
    n, lookahead = city.n_regions, 2
    place = meta.place_table(city)
    assert place.shape == (n, meta.N_PLACE)
    np.testing.assert_allclose(place.mean(0), 1.0, rtol=1e-5)  # relative to the city: a typical region reads 1
    to = city.reb_time.sum(1) / (n - 1)
    np.testing.assert_allclose(place[:, 0], to / to.mean(), rtol=1e-5)
    np.testing.assert_allclose(place[:, 1], city.reb_time.sum(0) / (n - 1) / to.mean(), rtol=1e-5)
    day = city.forecast_rate[: city.horizon].sum(0)
    np.testing.assert_allclose(place[:, 3], day.sum(0) * n / day.sum(), rtol=1e-5)
    np.testing.assert_allclose(place[:, 4], city.initial_vehicles * n / city.initial_vehicles.sum(), rtol=1e-5)
    system = FleetSystem(city)
    system.reset(np.random.SeedSequence(1))
    system.step(system.sim.idle.copy())
    live = meta.task_features(system, meta.CityScale.of(city), lookahead, structure=True, place=True)
    assert live.shape == (n, meta.n_task_features(lookahead, structure=True, place=True))
    np.testing.assert_allclose(live[:, -meta.N_PLACE :], place)
    base = meta.task_features(system, meta.CityScale.of(city), lookahead)[None, None]
    np.testing.assert_allclose(meta.with_structure(base, city, lookahead, place=True)[0, 0], live, rtol=1e-6)
    with pytest.raises(ConfigError, match="city_features"):
        meta.n_task_features(lookahead, place=True)


@pytest.mark.parametrize("place, readout", [(False, "none"), (True, "mean-max")])
def test_a_policy_extended_to_more_features_or_a_readout_starts_as_the_same_policy(place, readout):
    """Widening a warm start: the new input columns and the readout's columns of the heads start
    at zero weight, so the actions and values are the old model's until training uses them."""
    from marl_amod.errors import DataError
    from marl_amod.models.dense import DenseGraph

    torch.manual_seed(0)
    old = RecurrentGNN(meta.n_task_features(2), hidden=8, stay_prior=True)
    new = RecurrentGNN(meta.n_task_features(2, structure=True, place=place), hidden=8, stay_prior=True, readout=readout)
    new.load_state_dict(meta.widened(old, new))
    assert meta.features_read(new, 2) == (True, place) and meta.features_read(old, 2) == (False, False)
    graph = DenseGraph(torch.tensor([[0, 1, 1, 2], [1, 0, 2, 1]]), 3)
    x = torch.rand(2, 3, new.n_features)
    feedback = (torch.rand(2, 3), torch.rand(2, 3), torch.rand(2), torch.rand(2, 3, 8))
    for a, b in zip(old(x[..., : old.n_features], *feedback, graph), new(x, *feedback, graph), strict=True):
        torch.testing.assert_close(a, b)
    if readout != "none":  # the readout is there to be used: its columns get a gradient
        alpha, value, _ = new(x, *feedback, graph)
        (alpha.log().sum() + value.sum()).backward()
        assert new.actor[0].weight.grad[:, 16:].abs().sum() > 0 and new.critic[0].weight.grad[:, 16:].abs().sum() > 0
        with pytest.raises(DataError, match="cannot extend"):  # a readout is not dropped
            meta.widened(new, RecurrentGNN(new.n_features, hidden=8, stay_prior=True))
    with pytest.raises(DataError, match="cannot extend"):
        meta.widened(old, RecurrentGNN(meta.n_task_features(2, structure=True), hidden=4, stay_prior=True))


def test_recurrent_gnn_is_size_agnostic_batched_and_its_memory_changes_the_action():
    from marl_amod.models.dense import DenseGraph

    torch.manual_seed(0)
    model = RecurrentGNN(n_features=5, hidden=8)
    for city in (grid_city(rows=2, cols=3), grid_city(rows=4, cols=4)):
        n = city.n_regions
        edges = torch.as_tensor(np.array(city.edge_index), dtype=torch.long)
        x, a, rr, r = torch.rand(3, n, 5), torch.ones(3, n), torch.rand(3, n), torch.rand(3)
        alpha, v, mem = model(x, a, rr, r, model.initial_memory(n, 3), DenseGraph(edges, n))
        assert alpha.shape == (3, n) and (alpha > 0).all() and v.shape == (3,) and mem.shape == (3, n, 8)
        for b in range(3):  # each trial of the batch is the unbatched model on its own, on either graph form
            one, w, m = model(x[b], a[b], rr[b], r[b], model.initial_memory(n), edges)
            torch.testing.assert_close(one, alpha[b]), torch.testing.assert_close(w, v[b]), torch.testing.assert_close(m, mem[b])
        again, _, _ = model(x, a, rr, r, mem, edges)  # same input, what it remembers differs
        assert not torch.allclose(alpha, again)


@pytest.mark.parametrize("stay_prior, readout, centred", [(True, "mean-max", False), (False, "max", False), (True, "none", True)])
def test_recurrent_gnn_on_padded_cities_is_each_city_on_its_own(stay_prior, readout, centred):
    """Cities of 6 and 16 regions in one (C, B, N_max) batch: each city's concentrations, value and
    memory are those of the city alone, whatever the padding holds; the padding's alpha is 0."""
    from marl_amod.models.dense import DenseGraph, PaddedGraphs

    torch.manual_seed(0)
    model = RecurrentGNN(n_features=5, hidden=8, stay_prior=stay_prior, readout=readout, centred=centred)
    graphs = [DenseGraph(torch.as_tensor(np.array(c.edge_index)), c.n_regions) for c in (grid_city(rows=2, cols=3), grid_city(rows=4, cols=4))]
    padded = PaddedGraphs(graphs)
    x, a, rr, r, mem = torch.rand(2, 3, 16, 5), torch.rand(2, 3, 16), torch.rand(2, 3, 16), torch.rand(2, 3), torch.rand(2, 3, 16, 8)
    alpha, v, memory = model(x, a, rr, r, mem, padded)  # the padding holds random numbers, not zeros
    assert padded.n == 16 and (alpha[0, :, 6:] == 0).all()
    for c, g in enumerate(graphs):
        n = g.n
        one, w, m = model(x[c, :, :n], a[c, :, :n], rr[c, :, :n], r[c], mem[c, :, :n], g)
        torch.testing.assert_close(alpha[c, :, :n], one), torch.testing.assert_close(v[c], w), torch.testing.assert_close(memory[c, :, :n], m)


@pytest.mark.parametrize("stay_prior, readout, centred", [(True, "mean-max", False), (False, "max", False), (True, "none", True)])
def test_recurrent_gnn_on_packed_cities_is_each_city_on_its_own(stay_prior, readout, centred):
    """Cities of 6, 16 and 6 regions side by side (B, 28) with one team reward each (B, 3): each city's
    concentrations, value and memory are those of the city alone (no message, pool, prior or mean
    crosses a city's edge), and packing the padded batch gives the padded model's outputs."""
    from marl_amod.models.dense import DenseGraph, PackedGraphs, PaddedGraphs

    torch.manual_seed(0)
    model = RecurrentGNN(n_features=5, hidden=8, stay_prior=stay_prior, readout=readout, centred=centred)
    cities = (grid_city(rows=2, cols=3), grid_city(rows=4, cols=4), grid_city(rows=3, cols=2))
    graphs = [DenseGraph(torch.as_tensor(np.array(c.edge_index)), c.n_regions) for c in cities]
    packed = PackedGraphs(graphs)
    assert packed.n == 28 and packed.starts == [0, 6, 22] and packed.regions.tolist() == [6.0] * 6 + [16.0] * 16 + [6.0] * 6
    x, a, rr, r, mem = torch.rand(4, 28, 5), torch.rand(4, 28), torch.rand(4, 28), torch.rand(4, 3), torch.rand(4, 28, 8)  # 4 trials, 3 cities
    alpha, v, memory = model(x, a, rr, r, mem, packed)
    assert alpha.shape == (4, 28) and v.shape == (4, 3) and memory.shape == (4, 28, 8)
    for c, (g, s) in enumerate(zip(graphs, packed.starts, strict=True)):
        part = slice(s, s + g.n)
        one, w, m = model(x[:, part], a[:, part], rr[:, part], r[:, c], mem[:, part], g)
        torch.testing.assert_close(alpha[:, part], one), torch.testing.assert_close(v[:, c], w), torch.testing.assert_close(memory[:, part], m)
    # from and to the padded layout (C, B, N_max): the padded model on the same trials agrees
    pad_x, pad_mem = torch.rand(3, 4, 16, 5), torch.rand(3, 4, 16, 8)
    for c, (g, s) in enumerate(zip(graphs, packed.starts, strict=True)):
        pad_x[c, :, : g.n], pad_mem[c, :, : g.n] = x[:, s : s + g.n], mem[:, s : s + g.n]
    torch.testing.assert_close(packed.pack(pad_x, features=True), x), torch.testing.assert_close(packed.pack(pad_mem, features=True), mem)
    pad_a = packed.unpack(a)
    assert pad_a.shape == (3, 4, 16) and (pad_a[0, :, 6:] == 0).all() and torch.equal(packed.pack(pad_a, features=False), a)
    p_alpha, p_v, _ = model(pad_x, pad_a, packed.unpack(rr), r.T, pad_mem, PaddedGraphs(graphs))
    torch.testing.assert_close(p_alpha, packed.unpack(alpha)), torch.testing.assert_close(p_v, v.T)


@pytest.mark.parametrize("readout", ["none", "mean", "mean-max"])
def test_the_split_heads_are_the_heads_on_the_readouts_output(monkeypatch, readout):
    """The recurrent GNN runs its heads' first layers split between the regions' columns and the
    fleet summary's (once per graph): outputs and gradients are those of the heads applied to the
    readout's full (..., N, 2H + kH) output, on one city, on padded cities and on packed ones."""
    from marl_amod.models import recurrent
    from marl_amod.models.dense import DenseGraph, PackedGraphs, PaddedGraphs

    torch.manual_seed(0)
    model = RecurrentGNN(n_features=5, hidden=8, stay_prior=True, readout=readout)
    for p in model.parameters():  # non-zero everywhere, so a column read by the wrong weight shows
        torch.nn.init.normal_(p, std=0.5)
    graphs = [DenseGraph(torch.as_tensor(np.array(c.edge_index)), c.n_regions) for c in (grid_city(rows=2, cols=3), grid_city(rows=4, cols=4))]
    x, a, rr, r, mem = torch.rand(2, 3, 16, 5), torch.rand(2, 3, 16), torch.rand(2, 3, 16), torch.rand(2, 3), torch.rand(2, 3, 16, 8)
    packed = PackedGraphs(graphs)
    packed_args = (packed.pack(x, True), packed.pack(a, False), packed.pack(rr, False), r.T, packed.pack(mem, True))
    for graph, args in ((graphs[1], (x[1], a[1], rr[1], r[1], mem[1])), (PaddedGraphs(graphs), (x, a, rr, r, mem)), (packed, packed_args)):
        runs = []
        for heads in (recurrent._heads, recurrent.concatenated_heads):
            monkeypatch.setattr(recurrent, "_heads", heads)
            model.zero_grad()
            alpha, value, _ = model(*args, graph)
            (alpha.log1p().sum() + value.sum()).backward()
            runs.append((alpha, value, [p.grad.clone() for p in model.parameters()]))
        (alpha, value, grads), (ref_alpha, ref_value, ref_grads) = runs
        torch.testing.assert_close(alpha, ref_alpha), torch.testing.assert_close(value, ref_value)
        for g, ref in zip(grads, ref_grads, strict=True):
            torch.testing.assert_close(g, ref)


def test_the_stay_prior_starts_from_the_idle_vehicles_distribution():
    """With a zero actor output the stay-prior policy's mean is the idle share (mixed with the floor):
    played on a city, it asks for (nearly) what is there; the actor then scales it per region."""
    from marl_amod.models.recurrent import STAY_FLOOR

    city = grid_city(rows=2, cols=3)
    model = RecurrentGNN(meta.n_task_features(6), hidden=8, stay_prior=True)
    torch.nn.init.zeros_(model.actor[-1].weight), torch.nn.init.zeros_(model.actor[-1].bias)
    system = FleetSystem(city)
    system.reset(0)
    agent = meta.MetaAgent(model, city, 6)
    w = agent.act(system, sample=False)[0][0]
    idle = system.sim.idle
    np.testing.assert_allclose(w, (1 - STAY_FLOOR) * idle / idle.sum() + STAY_FLOOR / city.n_regions, rtol=1e-5)
    assert np.abs(system.targets_from_weights(w) - idle).sum() <= 0.25 * idle.sum()
    torch.nn.init.constant_(model.actor[-1].bias, 1.0)  # the same log-ratio everywhere: the same mean
    np.testing.assert_allclose(agent.act(system, sample=False)[0][0], w, rtol=1e-5)


def test_a_common_level_past_the_clamp_stalls_the_actor_unless_it_is_centred():
    """The stay prior's mean reads only the differences of the actor's log-ratios. Pushed to a common
    level past the clamp (+25, where seed 7 of the tables' recipe sat), the plain actor plays the
    stay prior and its imitation loss sends no gradient to the actor: it cannot come back. Centred,
    the same weights give the mean and concentration of level 0, and the gradient flows."""
    from marl_amod.models.dense import DenseGraph

    city = grid_city(rows=2, cols=3)
    graph = DenseGraph(torch.as_tensor(np.array(city.edge_index)), city.n_regions)
    torch.manual_seed(0)
    x, a, rr, r, mem = torch.rand(3, 6, 5), torch.rand(3, 6), torch.rand(3, 6), torch.rand(3), torch.rand(3, 6, 8)
    target = torch.softmax(torch.randn(3, 6), -1)
    out = {}
    for centred in (False, True):
        torch.manual_seed(1)
        model = RecurrentGNN(n_features=5, hidden=8, stay_prior=True, centred=centred)
        at_zero = model(x, a, rr, r, mem, graph)[0].detach()
        with torch.no_grad():
            model.actor[-1].bias += 25.0
        alpha = model(x, a, rr, r, mem, graph)[0]
        mean = alpha / alpha.sum(-1, keepdim=True)
        (mean - target).abs().sum(-1).mean().backward()
        grad = sum(float(p.grad.abs().sum()) for p in model.actor.parameters())
        model.actor[-1].bias.data.zero_()
        plain = model(x, a, rr, r, mem, graph)[0].detach()
        out[centred] = (at_zero, alpha.detach(), mean.detach(), grad, plain)
    at_zero, alpha, mean, grad, plain = out[False]
    stay = RecurrentGNN(n_features=5, hidden=8, stay_prior=True)
    torch.nn.init.zeros_(stay.actor[-1].weight), torch.nn.init.zeros_(stay.actor[-1].bias)
    stay_alpha = stay(x, a, rr, r, mem, graph)[0].detach()
    torch.testing.assert_close(mean, stay_alpha / stay_alpha.sum(-1, keepdim=True))  # the stay prior, whatever it was fitted to
    assert grad == 0.0
    at_zero, alpha, mean, grad, plain = out[True]
    torch.testing.assert_close(alpha, at_zero, rtol=1e-5, atol=1e-4)  # no level to drift (to the rounding of +25 - 25)
    assert grad > 0
    torch.testing.assert_close(mean, plain / plain.sum(-1, keepdim=True))  # centring changes no mean within the clamp
    with pytest.raises(ValueError, match="stay_prior"):
        RecurrentGNN(n_features=5, hidden=8, centred=True)


def test_the_demand_prior_gives_an_emptied_busy_region_weight():
    """With ``demand_prior`` g and a zero actor output the mean is (1 - f - g) idle share + g demand
    share + f / N: a region with no idle vehicles but the requests gets g of the fleet, where the
    stay prior alone gives it the floor; the padded and packed paths agree; bad settings are refused."""
    from marl_amod.models.dense import DenseGraph, PackedGraphs, PaddedGraphs
    from marl_amod.models.recurrent import STAY_FLOOR

    lookahead, n = 2, 4
    cols = meta.demand_columns(lookahead)
    model = RecurrentGNN(meta.n_task_features(lookahead), hidden=8, stay_prior=True, demand_prior=0.3, demand_columns=cols)
    torch.nn.init.zeros_(model.actor[-1].weight), torch.nn.init.zeros_(model.actor[-1].bias)
    x = torch.zeros(n, meta.n_task_features(lookahead))
    x[:, 0] = torch.tensor([0.0, 2.0, 1.0, 1.0])  # idle: region 0 emptied
    x[0, cols[1]], x[0, cols[2]], x[1, cols[0]] = 2.0, 1.0, 1.0  # region 0 served 2 and left 1 unserved; region 1 expects 1
    edges = torch.as_tensor(np.array(grid_city(rows=2, cols=2).edge_index))
    zeros = torch.zeros(n)
    alpha, _, _ = model(x, zeros, zeros, torch.zeros(()), model.initial_memory(n), edges)
    mean = alpha / alpha.sum()
    expect = (1 - STAY_FLOOR - 0.3) * torch.tensor([0.0, 0.5, 0.25, 0.25]) + 0.3 * torch.tensor([0.75, 0.25, 0, 0]) + STAY_FLOOR / n
    torch.testing.assert_close(mean, expect)
    assert mean[0] > 0.2 > STAY_FLOOR / n
    padded = PaddedGraphs([DenseGraph(edges, n), DenseGraph(torch.as_tensor(np.array(grid_city(rows=2, cols=3).edge_index)), 6)])
    xp = torch.rand(2, 1, 6, x.shape[-1]) * 5  # the padding holds noise
    xp[0, 0, :n] = x
    ap, _, _ = model(xp, torch.zeros(2, 1, 6), torch.zeros(2, 1, 6), torch.zeros(2, 1), torch.zeros(2, 1, 6, 8), padded)
    torch.testing.assert_close(ap[0, 0, :n], alpha), torch.testing.assert_close(ap[0, 0, n:], torch.zeros(2))
    packed = PackedGraphs(padded.graphs)  # and side by side: the second city's requests do not enter the first's share
    apk, _, _ = model(packed.pack(xp, True), torch.zeros(1, 10), torch.zeros(1, 10), torch.zeros(1, 2), torch.zeros(1, 10, 8), packed)
    torch.testing.assert_close(apk[0, :n], alpha), torch.testing.assert_close(packed.unpack(apk), ap)
    for bad in ({"stay_prior": False}, {"demand_prior": 0.95}, {"demand_columns": ()}):
        kwargs = {"stay_prior": True, "demand_prior": 0.3, "demand_columns": cols} | bad
        with pytest.raises(ValueError, match="demand_prior"):
            RecurrentGNN(meta.n_task_features(lookahead), hidden=8, **kwargs)


def test_each_regions_reward_reaches_the_memory():
    """The same team reward split differently over the regions: the policy must tell them apart
    (a special event shows as a local reward, not only as a blur in the team's)."""
    city = grid_city(rows=2, cols=2, horizon=4)
    torch.manual_seed(0)
    model = RecurrentGNN(meta.n_task_features(2), hidden=8)
    system = FleetSystem(city)
    system.reset(np.random.SeedSequence(0))
    alphas = []
    for split in ([4.0, 0.0, 0.0, 0.0], [1.0, 1.0, 1.0, 1.0]):
        agent = meta.MetaAgent(model, city, 2)
        team = agent.observe(np.array(split) * agent.scale.reward / 4)
        assert team == pytest.approx([1.0])
        alphas.append(agent.act(system, sample=False)[0])
    assert not np.allclose(alphas[0], alphas[1])


def test_random_shocks_change_the_draw_not_the_forecast():
    city = load_city("synthetic")
    rng = np.random.default_rng(0)
    for _ in range(20):
        shocked = meta.random_shock(city, rng)
        np.testing.assert_array_equal(meta.task_city(shocked.name).demand_rate, shocked.demand_rate)  # an event task: its name replays it
        np.testing.assert_array_equal(shocked.forecast_rate, city.forecast_rate)
        changed = np.flatnonzero((np.asarray(shocked.demand_rate) != np.asarray(city.demand_rate)).any(axis=(1, 2)))
        assert changed.size and changed.min() < city.horizon and 3 <= changed.size <= 10  # a window of 3-10 steps
        assert meta.CityScale.of(shocked) == meta.CityScale.of(city)  # units read the forecast


def test_a_hotspot_variant_is_another_city_its_name_rebuilds():
    """Requests out of one region x m against the others in the draw *and* the forecast (the
    features show it, unlike a shock), every step's total kept; fares and times unchanged; the
    name alone rebuilds it."""
    city = load_city("synthetic")
    hot = meta.hotspot(city, 2, 3.5)
    assert hot.name == "synthetic~hot2x3.5" and meta.base_city(hot.name) == "synthetic"
    for table in ("demand_rate", "forecast_rate"):
        new, old = np.asarray(getattr(hot, table)), np.asarray(getattr(city, table))
        np.testing.assert_allclose(new.sum(axis=(1, 2)), old.sum(axis=(1, 2)))  # the same demand in all
        ratio = new / np.where(old > 0, old, np.nan)  # per step: 3.5 c out of region 2, c out of the others
        others = np.nanmax(np.delete(ratio, 2, axis=1), axis=(1, 2))
        np.testing.assert_allclose(np.nanmin(np.delete(ratio, 2, axis=1), axis=(1, 2)), others)
        np.testing.assert_allclose(np.nanmax(ratio[:, 2], axis=1), 3.5 * others)
    np.testing.assert_array_equal(hot.price, city.price)
    assert meta.place_table(hot)[2, 2] > meta.place_table(city)[2, 2]  # its share of the day's requests out grew
    rebuilt = meta.task_city(hot.name)
    np.testing.assert_array_equal(rebuilt.forecast_rate, hot.forecast_rate)
    assert meta.task_city("synthetic").name == "synthetic"
    for bad in ("synthetic~hotAx2", "synthetic~hot99x2", "synthetic~hot1x0"):
        with pytest.raises(ConfigError, match="hotspot"):
            meta.task_city(bad)


@needs_data
def test_hotspot_tasks_are_drawn_per_city_by_seed():
    """``hotspot_tasks``: ``variants`` hotspot tasks of each city, the same for a seed, multipliers in range."""
    names = meta.hotspot_tasks(["synthetic", "porto"], 3, (2.0, 4.0), seed=0)
    assert names == meta.hotspot_tasks(["synthetic", "porto"], 3, (2.0, 4.0), seed=0) != meta.hotspot_tasks(["synthetic", "porto"], 3, (2.0, 4.0), seed=1)
    assert [meta.base_city(n) for n in names] == ["synthetic"] * 3 + ["porto"] * 3
    assert all(2.0 <= meta.task_city(n).meta["hotspot"]["multiplier"] <= 4.0 for n in names)


def test_an_event_task_carries_its_event_in_the_draw_not_the_forecast_and_its_name_rebuilds_it():
    """An event task multiplies the requests out of its surge regions (and its dropped ones) inside
    its window only, in the draw; the forecast the features read stays the city's; the name alone
    rebuilds it; a malformed name or an event outside the city is a ConfigError; event_tasks draws
    surges outside the two busiest regions, windows inside the horizon, as a function of the seed."""
    city = load_city("synthetic")
    ev = meta.event_task(city, [3, 7], 6.0, 4, 10, [0, 1], 0.5)
    assert ev.name == "synthetic~ev3+7x6@4-10dr0+1x0.5" and meta.base_city(ev.name) == "synthetic"
    np.testing.assert_array_equal(ev.forecast_rate, city.forecast_rate)
    old, new = np.asarray(city.demand_rate), np.asarray(ev.demand_rate)
    np.testing.assert_allclose(new[4:10, [3, 7]], 6.0 * old[4:10, [3, 7]])
    np.testing.assert_allclose(new[4:10, [0, 1]], 0.5 * old[4:10, [0, 1]])
    np.testing.assert_allclose(new[4:10, 2], old[4:10, 2])
    np.testing.assert_allclose(new[:4], old[:4]), np.testing.assert_allclose(new[10:], old[10:])
    rebuilt = meta.task_city(ev.name)
    np.testing.assert_array_equal(rebuilt.demand_rate, ev.demand_rate)
    assert rebuilt.meta["events"] == ev.meta["events"] and meta.task_city("synthetic~ev3x2@0-5").meta["events"][0]["regions"] == [3]
    for bad in ("synthetic~ev3+x2@0-5", "synthetic~ev3x2@5-5", "synthetic~ev99x2@0-5", "synthetic~ev3x2@0-5dr1x"):
        with pytest.raises(ConfigError, match="event"):
            meta.task_city(bad)
    with pytest.raises(ConfigError, match="event_multipliers"):
        meta.event_tasks(["synthetic"], 1, (0.5, 2.0), seed=0)


@needs_data
def test_event_tasks_surge_outside_the_busiest_regions_inside_the_horizon_by_seed():
    """``event_tasks``: surges outside the two busiest regions, windows inside the horizon, drops at
    the busiest, as a function of the seed, for each city."""
    names = meta.event_tasks(["synthetic", "porto"], 3, (3.0, 8.0), seed=0)
    assert names == meta.event_tasks(["synthetic", "porto"], 3, (3.0, 8.0), seed=0) != meta.event_tasks(["synthetic", "porto"], 3, (3.0, 8.0), seed=1)
    assert [meta.base_city(n) for n in names] == ["synthetic"] * 3 + ["porto"] * 3 and len(set(names)) == 6
    for name in names:
        task, base = meta.task_city(name), load_city(meta.base_city(name))
        busiest = set(np.argsort(-meta.place_table(base)[:, 2], kind="stable")[:2].tolist())
        surge, *drop = task.meta["events"]
        assert len(surge["regions"]) == 2 and not busiest & set(surge["regions"]) and 3.0 <= surge["multiplier"] <= 8.0
        assert 6 <= surge["end"] - surge["start"] <= 10 and surge["end"] <= base.horizon
        assert all(set(d["regions"]) == busiest and 0.3 <= d["multiplier"] <= 0.8 for d in drop)


def test_event_tasks_are_as_many_as_asked_or_refused(tmp_path):
    """A 4-region city of 2 control steps has 14 distinct event tasks at one multiplier: asking for
    more is an error, never fewer tasks than the card says; a multiplier range that rounds to x1
    (one decimal) is no surge and is refused."""
    tiny = tmp_path / "tiny.yaml"
    tiny.write_text("name: tiny\nsource: synthetic\nrows: 2\ncols: 2\nhorizon: 2\n")
    assert len(set(meta.event_tasks([str(tiny)], 14, (3.0, 3.0), seed=0))) == 14
    with pytest.raises(ConfigError, match="distinct event tasks"):
        meta.event_tasks([str(tiny)], 15, (3.0, 3.0), seed=0)
    with pytest.raises(ConfigError, match="event_multipliers"):
        meta.event_tasks(["synthetic"], 1, (1.01, 1.04), seed=0)


def test_an_event_task_refuses_a_bad_event_in_one_line_and_its_name_always_rebuilds_it():
    """A window or multiplier the event cannot have is a one-line ConfigError naming the task, from
    event_task itself too (not pydantic's report); any event it accepts, -0.0 included, gets a
    name task_city rebuilds."""
    city = load_city("synthetic")
    with pytest.raises(ConfigError, match=r"^event task of synthetic, its surge: .*end \(5\) must be after start \(5\)$"):
        meta.event_task(city, [3], 2.0, 5, 5)
    for bad in ("synthetic~ev3x2000@0-5", "synthetic~ev3+3x2@0-5", "synthetic~ev3x2@5-5", "synthetic~ev3x1.2.3@0-5"):
        with pytest.raises(ConfigError, match="synthetic") as err:
            meta.task_city(bad)
        assert "\n" not in str(err.value) and "pydantic" not in str(err.value)
    for m, dm in ((2.1234567, 0.0), (1000.0, -0.0), (0.0, 0.25)):
        ev = meta.event_task(city, [3, 7], m, 0, 6, [1], dm)
        np.testing.assert_array_equal(meta.task_city(ev.name).demand_rate, ev.demand_rate)


def test_the_deployed_policy_replays_the_trained_agent_exactly():
    """MetaPolicy (through evaluate, one episode on a FleetSystem) rebuilds the previous rewards from
    the booked money: its episode must be the batched trial's deterministic one from the same memory."""
    from marl_amod.batch_system import BatchFleetSystem

    city = grid_city(rows=3, cols=3, horizon=6)
    torch.manual_seed(1)
    model = RecurrentGNN(meta.n_task_features(6), hidden=8)
    policy = meta.adapt(model, city, episodes=2, lookahead=6)
    got = evaluate(policy, city, episodes=2, seed=0)["metrics"]["profit"]["mean"]
    agent = meta.MetaAgent(model, city, 6, num_trials=2)
    agent.memory = policy.adapted.expand(2, -1, -1).clone()
    trial = meta.run_trials(agent, BatchFleetSystem(city, 2), [[np.random.SeedSequence([0, k]) for k in range(2)]], sample=False)
    assert got == pytest.approx(trial.profits.mean(), rel=1e-9)


def test_adaptation_is_reproducible_by_seed_and_leaves_torch_rng_alone():
    """Adaptation samples its actions; the same seed must give the same memory whatever torch's
    global stream did before, a different seed a different one, and the caller's stream is untouched."""
    city = grid_city(rows=3, cols=3, horizon=6)
    torch.manual_seed(1)
    model = RecurrentGNN(meta.n_task_features(6), hidden=8)
    first = meta.adapt(model, city, episodes=2, lookahead=6, seed=3).adapted
    torch.manual_seed(12345)
    before = torch.get_rng_state()
    again = meta.adapt(model, city, episodes=2, lookahead=6, seed=3).adapted
    assert torch.equal(torch.get_rng_state(), before)
    assert torch.equal(first, again)
    other = meta.adapt(model, city, episodes=2, lookahead=6, seed=4).adapted
    assert not torch.equal(first, other)


def test_meta_training_resumes_exactly_and_ships_a_policy_that_adapts(tmp_path):
    tasks = [_city_yaml(tmp_path, "small", rows=2, cols=3, vehicles_per_region=5),
             _city_yaml(tmp_path, "large", rows=3, cols=3, vehicles_per_region=40, requests_per_region=20)]  # fmt: skip
    # 2 cities x 2 trials x 2 episodes = 8 episodes per update; half the draws shocked
    args = meta.Args(scenario="synthetic", cities=tasks, val_cities=tasks[:1], hidden=8, episodes=24, trial_episodes=2,
                     num_envs=2, cities_per_update=2, shock_prob=0.5, eval_every=8, eval_episodes=2, final_eval_episodes=2,
                     run_dir=str(tmp_path / "full"), policy_out=str(tmp_path / "full.pt"))  # fmt: skip
    assert "meta" in ALGOS
    summary = ALGOS["meta"].train(args)
    assert summary["card"]["algorithm"] == "meta" and summary["card"]["episodes_trained"] == 24
    half = args.model_copy(update={"run_dir": str(tmp_path / "half"), "policy_out": str(tmp_path / "resumed.pt")})
    ALGOS["meta"].train(half.model_copy(update={"episodes": 16}))
    ALGOS["meta"].train(half, resume=str(tmp_path / "half" / "state.pt"))
    full, resumed = (torch.load(tmp_path / f, weights_only=True)["state_dict"] for f in ("full.pt", "resumed.pt"))
    for key in full:
        torch.testing.assert_close(full[key], resumed[key], rtol=0, atol=0)
    shocked = [row for row in (tmp_path / "full" / "log.csv").read_text().splitlines() if "shocked" in row]
    assert {row.rsplit(",", 1)[1] for row in shocked} - {"0.0"}  # some draws did get a shock
    # the checkpoint evaluates like any policy file: it adapts (1 episode) to the city first
    result = evaluate(str(tmp_path / "full.pt"), "synthetic", episodes=1)
    assert result["policy"] == "full" and np.isfinite(result["metrics"]["profit"]["mean"])


def test_held_out_cities_cannot_be_training_tasks():
    with pytest.raises(ConfigError, match="held-out"):
        meta.train(meta.Args(cities=["chicago", "san_francisco"]))
    with pytest.raises(ConfigError, match="held-out"):
        meta.train(meta.Args(scenario="porto", cities=["porto", "rome"]))
    with pytest.raises(ConfigError, match="held-out"):  # nor a variant of one
        meta.train(meta.Args(cities=["chicago", "nyc_brooklyn~hot5x2"]))


@pytest.mark.parametrize("task", ["nyc_brooklyn_event", "nyc_brooklyn_event~hot5x2", "nyc_brooklyn_event~ev1+2x3@0-6", "nyc_brooklyn~ev1+2x3@0-6"])
def test_a_scenario_built_on_a_held_out_citys_data_is_held_out_too(task):
    """The event study's city (``extends: nyc_brooklyn`` with the Brooklyn event) is the held-out
    city's data with the very event the study tests: as a training task, a variant or an event task
    of one it would be demonstrated by MPC told that event (meta_imitation.expert_for)."""
    assert meta.held_out_among([task, "porto", "porto~ev1+2x3@0-6"]) == [meta.base_city(task)]
    with pytest.raises(ConfigError, match="held-out"):
        meta.check_tasks(meta.Args(cities=["chicago", task]))
    with pytest.raises(ConfigError, match="validation"):  # nor the city the best model is chosen on
        meta.check_tasks(meta.Args(cities=["chicago"], val_cities=["porto", task]))


def test_transfer_strategies_and_the_normalised_score(tmp_path):
    assert normalised_score(150.0, 100.0, 200.0) == 50.0 and normalised_score(100.0, 100.0, 200.0) == 0.0
    assert score_points(25.0, 100.0, 200.0) == 25.0 and np.isnan(score_points(25.0, 100.0, 100.0))  # a spread in score points
    with pytest.raises(ConfigError, match="unknown strategy"):
        run_strategy("wishful", "synthetic")
    with pytest.raises(ConfigError, match="needs --policy"):
        run_strategy("zero-shot", "synthetic")
    assert len(STRATEGIES) == 6
    ignored = {  # an option the strategy would not use is refused, not silently dropped
        ("mpc-forecast", "policies/a2c_gnn_synthetic.pt", None): "drop --policy",
        ("zero-shot", "policies/a2c_gnn_synthetic.pt", 3): "adapts nothing",
        ("fine-tune", "policies/a2c_gnn_synthetic.pt", 0): "at least one online episode",
        ("zero-shot", "policies/a2c_gnn_synthetic.pt", None): "single-city strategy",  # trained on the target itself
    }
    for (strategy, policy, k), message in ignored.items():
        with pytest.raises(ConfigError, match=message):
            run_strategy(strategy, "synthetic", policy=policy, adapt_episodes=k, episodes=1)
    rec = run_strategy("mpc-forecast", "synthetic", episodes=1)
    assert rec["transfer"]["target_episodes"] == 0


def test_fine_tuning_is_a2c_with_init_actor_for_k_episodes(monkeypatch):
    from marl_amod.algos import a2c
    from marl_amod.transfer import fine_tune

    real, seen, trained = a2c.train, [], []

    def spy(args, **kw):
        out = real(args, **kw)
        seen.append(args), trained.append(torch.load(out["policy"], weights_only=True)["state_dict"])
        return out

    monkeypatch.setattr(a2c, "train", spy)
    policy = fine_tune("policies/a2c_gnn_synthetic.pt", "synthetic", episodes=4, per_update=2)
    (args,) = seen
    assert args.init_actor == "policies/a2c_gnn_synthetic.pt" and args.episodes == 4 and args.scenario == "synthetic"
    for key, value in policy.actor.state_dict().items():  # the policy is what that A2C run kept
        torch.testing.assert_close(value, trained[0][key], rtol=0, atol=0)
    assert policy.name == "fine-tune(a2c_gnn_synthetic)"
    rec = run_strategy("fine-tune", "synthetic", policy="policies/a2c_gnn_synthetic.pt", adapt_episodes=2, episodes=1)
    assert rec["transfer"]["target_episodes"] == 2 and rec["transfer"]["validation_episodes"] == 4


def test_a_study_reruns_only_the_rows_asked_for(monkeypatch):
    from marl_amod import transfer

    monkeypatch.setitem(transfer.STUDIES, "toy", ("synthetic",))
    first = transfer.run_study("toy", episodes=1, strategies=("mpc-forecast", "mpc-oracle"))
    rows = first["targets"]["synthetic"]
    assert set(rows) == {"equal-distribution", "mpc-forecast", "mpc-oracle"}
    assert rows["equal-distribution"]["normalised_score"] == 0.0 and rows["mpc-oracle"]["normalised_score"] == 100.0
    again = transfer.run_study("toy", episodes=1, strategies=("mpc-forecast",), previous=first)
    assert again["targets"]["synthetic"]["mpc-oracle"] is rows["mpc-oracle"]  # kept, not rerun
    assert "# toy" not in transfer.study_markdown(again) and "| mpc-forecast |" in transfer.study_markdown(again)
    with pytest.raises(ConfigError, match="run with 1 episodes, seed 0"):  # rows of another seed: never mixed in, nor the saved ones dropped
        transfer.run_study("toy", episodes=1, seed=1, strategies=("mpc-forecast",), previous=first)


def test_a_hotspot_variant_with_any_multiplier_is_rebuilt_exactly_by_its_name():
    """The name is what demonstrations, DAgger rounds and cards keep: it must hold the multiplier
    exactly (``:g`` kept 6 digits: 2.1234567 was rebuilt as 2.12346), and plain values stay short."""
    city = load_city("synthetic")
    for m, text in ((2.1234567, "2.1234567"), (1234567.0, "1234567"), (3.0, "3"), (0.5, "0.5")):
        hot = meta.hotspot(city, 1, m)
        assert hot.name == f"synthetic~hot1x{text}"
        rebuilt = meta.task_city(hot.name)
        assert rebuilt.meta["hotspot"]["multiplier"] == m
        np.testing.assert_array_equal(rebuilt.demand_rate, hot.demand_rate)


def test_hotspot_tasks_are_distinct_and_refuse_ranges_they_cannot_draw_from():
    """A duplicate would be one task counted twice on the card (and in the transfer table's
    demonstrations); a multiplier range that rounds to 0 names no city."""
    n = load_city("synthetic").n_regions
    names = meta.hotspot_tasks(["synthetic"], n, (2.0, 2.0), seed=0)  # every region once: the only way
    assert len(set(names)) == n
    assert meta.hotspot_tasks(["synthetic"], 1, (2.0, 4.0), seed=0) == meta.hotspot_tasks(["synthetic"], 3, (2.0, 4.0), seed=0)[:1]
    with pytest.raises(ConfigError, match="distinct"):
        meta.hotspot_tasks(["synthetic"], n + 1, (2.0, 2.0), seed=0)
    for bad in ((0.0, 2.0), (0.01, 0.04), (3.0, 2.0), (2.0, float("inf"))):
        with pytest.raises(ConfigError, match="hotspot_multipliers"):
            meta.hotspot_tasks(["synthetic"], 1, bad, seed=0)


def test_hotspot_tasks_with_distinct_regions_move_the_hotspot():
    """With ``distinct_regions`` a city's variants sit on as many regions (without it the same
    region recurs at other multipliers), the first variant is the one without it (its
    demonstrations reused), and more variants than regions are refused."""
    n = load_city("synthetic").n_regions
    region = lambda name: meta.task_city(name).meta["hotspot"]["region"]  # noqa: E731
    plain = meta.hotspot_tasks(["synthetic"], n, (2.0, 4.0), seed=0)
    assert len({region(v) for v in plain}) < n  # the default repeats regions: the option changes something
    moved = meta.hotspot_tasks(["synthetic"], n, (2.0, 4.0), seed=0, distinct_regions=True)
    assert sorted(region(v) for v in moved) == list(range(n)) and moved[0] == plain[0]
    with pytest.raises(ConfigError, match="each region once"):
        meta.hotspot_tasks(["synthetic"], n + 1, (2.0, 4.0), seed=0, distinct_regions=True)


def test_trials_reads_a_dagger_trial_by_the_episodes_place_and_pairs_runs_on_the_same_days(tmp_path, capsys):
    """benchmarks/meta_diagnostics.py trials: an action that is MPC-F's label misplaces nothing, a sampled
    one half its L1 distance; the busiest region is the label's; coverage is the idle vehicles' spread
    there over the trial's episodes; runs pair only where their trials share a seed (the same days)."""
    import meta_diagnostics

    k, t, n, f = 4, 3, 2, 16
    share = np.tile(np.array([0.75, 0.25], dtype=np.float32), (k, t, 1))
    action = share.copy()
    action[:3] = [0.25, 0.75]  # the adaptation episodes ask the other way round: half the fleet misplaced
    x = np.zeros((k, t, n, f), np.float32)
    x[..., 0, 0] = np.arange(k)[:, None]  # idle at the busiest region: 0, 1, 2, 3 by episode
    x[..., 0, 14] = 1.0  # unserved there (column 2 + 2 x lookahead 6), every step
    for run, seed, gain in (("a", 1, 0.0), ("b", 1, 1.0), ("c", 2, 0.0)):
        folder = tmp_path / run / "dagger" / "round1"
        folder.mkdir(parents=True)
        np.savez(folder / "porto.npz", x=x, share=share, action=action, reward=np.full((k, t), 1.0 + gain, np.float32), seed=np.array(seed),
                 lookahead=np.array(6))
    seed, m = meta_diagnostics.trial_measures(tmp_path / "a" / "dagger" / "round1" / "porto.npz")
    assert seed == 1
    np.testing.assert_allclose(m["misplaced"], [0.5, 0.5, 0.5, 0.0])
    np.testing.assert_allclose(m["asked"], [0.25, 0.25, 0.25, 0.75])
    np.testing.assert_allclose(m["label"], 0.75)
    np.testing.assert_allclose(m["unserved"], 3.0)
    np.testing.assert_allclose(m["spread"], np.std([0, 1, 2, 3]))
    meta_diagnostics.trials([str(tmp_path / r) for r in "abc"])
    out = capsys.readouterr().out
    assert "b - a, return over 1 paired trials: ep 1 +3.000 (nan)" in out and "c: no trials on the same days as a" in out
    with pytest.raises(SystemExit, match="no DAgger trials"):
        meta_diagnostics.trials([str(tmp_path)])


def test_spread_measures_how_far_single_runs_lie_apart_and_the_rule_reads_differences_in_it(tmp_path, capsys):
    """benchmarks/meta_diagnostics.py spread: each rule set's mean for every single run and its sd over the
    runs, written once; the rule's table then divides each difference by it (its verdict unchanged)."""
    import json

    import meta_diagnostics as md

    folders = []
    for i, gain in enumerate((0.0, 2.0, 4.0)):  # three runs: profits 100, 102, 104 against MPC-F's 110
        folder = tmp_path / f"rule{i}"
        folder.mkdir()
        for name, (_, tasks_) in md.RULE_SETS.items():
            record = {"policy": f"run{i}.pt", "tasks": {t: {"policy": [100.0 + gain] * 2, "mpc-forecast": [110.0] * 2} for t in tasks_}}
            md.rule_file(folder, "candidate", name).write_text(json.dumps(record))
        folders.append(str(folder))
    out = tmp_path / "runs.json"
    summary = md.spread(folders, out)
    assert summary["runs"][folders[1]]["policy"] == "run1.pt"
    assert summary["sd"]["training-city events"] == pytest.approx(2.0)  # profits 100, 102, 104
    assert summary["sd"]["shaped set"] == pytest.approx(np.std([100 / 11, 80 / 11, 60 / 11], ddof=1))  # gaps 9.09, 7.27, 5.45%
    assert md.runs_spread(out) == summary["sd"] and md.runs_spread(tmp_path / "none.json") is None
    rows = [{"set": "training-city events", "what": "profit", "reference": 100.0, "candidate": 104.0, "diff": 4.0, "se": 0.1, "passes": True}]
    capsys.readouterr()
    assert md.print_rule_table(rows, "a", "b", summary["sd"])
    assert "| +4.000 (0.100) | yes | +2.0 |" in capsys.readouterr().out
    with pytest.raises(SystemExit, match="at least two"):
        md.spread(folders[:1], out)


def test_compare_reads_the_standard_error_of_its_mean_over_the_episodes(tmp_path, capsys):
    """benchmarks/meta_diagnostics.py compare: the tasks are fixed and episode k of every task is
    drawn from the same seed, so the standard error of the mean difference is over the episodes (each
    the tasks' mean), not the tasks x episodes pairs taken as independent: a task that gains a fixed
    amount on every episode leaves no doubt, an episode that moves every task is one draw, not T."""
    import json

    import meta_diagnostics

    fixed = np.array([[1.0, 1.0, 1.0], [3.0, 3.0, 3.0]])  # (tasks, episodes): each task's gain the same every episode
    assert meta_diagnostics.paired_se(fixed) == (pytest.approx(np.std([1, 1, 1, 3, 3, 3], ddof=1) / np.sqrt(6)), 0.0)
    shared = np.array([[0.0, 2.0, 4.0]] * 4)  # every task moved alike by the episode
    pooled, by_episode = meta_diagnostics.paired_se(shared)
    assert by_episode == pytest.approx(2.0 / np.sqrt(3)) and by_episode > pooled
    files = []
    for i, gain in enumerate((0.0, 100.0)):
        tasks = {f"porto~ev1+2x{m}@0-6": {"policy": [1000.0 + gain * m + e for e in range(3)], "mpc-forecast": [1100.0] * 3} for m in (2, 3)}
        files.append(tmp_path / f"{i}.json")
        files[-1].write_text(json.dumps({"policy": str(i), "seed": 1000, "episodes": 3, "tasks": tasks}))
    meta_diagnostics.compare([str(f) for f in files])
    out = capsys.readouterr().out
    assert "+250.000 profit" in out and "by episode 0.000" in out and "+24.98% of the first's mean" in out  # 250 / 1,001 (the non-inferiority rule reads it)
    for i, gap in enumerate((10.0, 5.0)):  # skew and sink variants: groups of their own, read as the gap to MPC-F
        tasks = {"porto~skew2.7": {"policy": [100.0 - gap] * 3, "mpc-forecast": [100.0] * 3},
                 "porto~sink2x6": {"policy": [100.0 - 2 * gap] * 3, "mpc-forecast": [100.0] * 3}}  # fmt: skip
        files[i].write_text(json.dumps({"policy": str(i), "seed": 1000, "episodes": 3, "tasks": tasks}))
    meta_diagnostics.compare([str(f) for f in files])
    out = capsys.readouterr().out
    assert "-5.000% gap to MPC-F" in out and "-10.000% gap to MPC-F" in out and "over 1 tasks x 3 episodes: 20.000" in out


def test_the_tasks_diagnostic_adapts_over_the_k_it_is_given(tmp_path, monkeypatch):
    """benchmarks/meta_diagnostics.py tasks --k: the adaptation episodes reach the policy and the
    file (compare pairs only files of one k)."""
    import json

    import meta_diagnostics

    adapted = []
    monkeypatch.setattr(meta_diagnostics.meta, "load_policy", lambda path, task, k, seed: adapted.append(k) or "equal-distribution")
    out = tmp_path / "tasks.json"
    monkeypatch.setattr(sys, "argv", ["meta_diagnostics.py", "tasks", "--cities", "synthetic", "--episodes", "1", "--k", "1", "--out", str(out)])
    meta_diagnostics.main()
    assert adapted == [1] and json.loads(out.read_text())["k"] == 1



def test_final_card_evaluation_runs_on_validation_streams_not_report_seeds(tmp_path):
    # the held-out city's profit on the card comes from the validation streams (eval_seed), and the
    # card says so: the report seeds 0..9 are scored once per shipped change, never by a training run
    args = meta.Args(scenario="synthetic", cities=["porto"], val_cities=["porto"], hidden=8, trial_episodes=2, eval_seed=1000,
                     final_eval_episodes=2, run_dir=str(tmp_path / "run"))  # fmt: skip
    torch.manual_seed(0)
    model = meta.make_model(args)
    card = meta.finish(args, model, 1.0, 0, None)["card"]
    assert card["eval_seed"] == 1000 and card["eval_streams"] == "validation"
    city = load_city("synthetic")
    on_validation = evaluate(meta.adapt(model, city, 1, args.lookahead, seed=1000), city, 2, 1000)["metrics"]["profit"]
    assert card["profit_mean"] == on_validation["mean"] and card["profit_std"] == on_validation["std"]
    with pytest.raises(ValueError, match="final_eval_seed is not read"):  # pydantic's; a config file gets a ConfigError
        meta.Args(scenario="synthetic", cities=["porto"], final_eval_seed=3)


def test_the_forecast_noise_page_names_the_command_that_makes_it():
    """benchmarks/mpc_forecast_noise.py: the page's first line is the command that regenerates it,
    the scenarios and noises included when they are not the defaults."""
    import mpc_forecast_noise

    row = {"equal-distribution": 0.0, "mpc-oracle": 100.0, "mpc-forecast": {"0": 90.0, "1": 80.0}}
    page = mpc_forecast_noise.table({"nyc_brooklyn": row}, [0.0, 1.0], 2, 7000)
    assert page.splitlines()[0] == "<!-- python benchmarks/mpc_forecast_noise.py --episodes 2 --seed 7000 --noises 0 1 --scenarios nyc_brooklyn -->"
    assert "| nyc_brooklyn | 10.0% (90) | 20.0% (80) | 1.2% |" in page
    rows = {name: {**row, "mpc-forecast": {f"{s:g}": 90.0 for s in mpc_forecast_noise.NOISES}} for name in mpc_forecast_noise.SCENARIOS}
    assert mpc_forecast_noise.table(rows, mpc_forecast_noise.NOISES, 10, 0).splitlines()[0] == (
        "<!-- python benchmarks/mpc_forecast_noise.py --episodes 10 --seed 0 -->"
    )


def test_first_distinct_keeps_the_first_n_new_names_skips_refused_draws_and_gives_up_after_1000_n():
    """The loop every task drawer shares: repeats and refused draws (None) are not kept, the order is the
    draws', and a stream with too few distinct names within 1000 n draws gives None (the drawer's error)."""
    assert meta.first_distinct(iter(["a", None, "a", "b", "c", "d"]), 3) == ["a", "b", "c"]
    assert meta.first_distinct(iter(["a", "a", None]), 2) is None  # the stream ends first
    late = iter(["a"] * 1999 + ["b"])  # the second name arrives at draw 2,000, the last one the budget allows
    assert meta.first_distinct(late, 2) == ["a", "b"]
    too_late = iter(["a"] * 2000 + ["b"])
    assert meta.first_distinct(too_late, 2) is None


def test_the_hold_diagnostic_holds_only_the_steps_it_names(monkeypatch):
    """benchmarks/meta_diagnostics.py hold: a step held keeps every region's idle vehicles (a policy
    held at every step is no rebalancing, to the dollar), and the unheld row is the policy itself."""
    import meta_diagnostics as md

    from marl_amod.policies import make_policy

    city = md.load_city("synthetic")
    ed = lambda: make_policy("equal-distribution")  # noqa: E731
    always = md.episode_profit(md.Override(ed(), lambda t: True), city, 0)
    assert always == md.episode_profit(make_policy("no-rebalancing"), city, 0)
    assert always != md.episode_profit(ed(), city, 0)  # equal distribution does move vehicles here
    monkeypatch.setattr(md.meta, "load_policy", lambda path, task, k, seed: ed())
    row = md.hold("unused.pt", ["synthetic"], last=2, episodes=1)["synthetic"]
    assert row["the policy"] == md.episode_profit(ed(), city, 0)
    assert {"first step held", "last 2 steps held", "both held", "MPC-Forecast"} <= set(row)


def test_the_steps_diagnostic_plays_the_other_policy_only_in_its_windows(monkeypatch):
    """benchmarks/meta_diagnostics.py steps: with the other player at every step the episode is the other's,
    to the dollar; in a window only, it differs from both; the shares logged on the other's path are both
    players' asks at the busiest region, and the own path's profit is the policy's."""
    import meta_diagnostics as md

    from marl_amod.policies import make_policy

    city = md.load_city("synthetic")
    ed, other = (lambda: make_policy("equal-distribution")), (lambda: make_policy("plus-one"))  # noqa: E731
    monkeypatch.setattr(md.meta, "load_policy", lambda path, task, k, seed: ed())
    monkeypatch.setattr(md, "MPCForecast", other)
    out = md.steps("unused.pt", ["synthetic"], md.windows_of("0-1,3"), episodes=1)["synthetic"]
    mine, theirs = md.episode_profit(ed(), city, 0), md.episode_profit(other(), city, 0)
    assert out["policy"] == mine and out["gains"]["every step"][0] == pytest.approx(theirs - mine)
    assert set(out["gains"]) == {"every step", "steps 0-1", "steps 3-3"}
    assert theirs - mine != out["gains"]["steps 0-1"][0] != 0
    by_step = out["by_step"]
    assert len(by_step["own path: policy asks"]) == city.horizon - 1
    np.testing.assert_allclose(by_step["own path: policy asks"][0], by_step["MPC-F's path: policy asks"][0])  # the same first state
    assert by_step["MPC-F's path: MPC-F asks"] != by_step["MPC-F's path: policy asks"]
    with pytest.raises(ValueError):
        md.windows_of("0-x")


def test_rule_judges_a_candidate_by_every_set_from_the_files_it_finds(tmp_path, capsys):
    """benchmarks/meta_diagnostics.py rule: each set's gap to MPC-F must fall (the events' profit must
    not), paired by episode; files already holding the same policy, tasks and episodes are read, not rerun."""
    import json

    import meta_diagnostics as md

    def write(label: str, policy: str, worse: str | None) -> None:
        for name, (what, names) in md.RULE_SETS.items():
            if what == "gap":  # the candidate 1% nearer MPC-F, except on the set it is worse
                own = 95.0 if label == "reference" else (93.0 if name == worse else 96.0)
            else:
                own = 95.0 if label == "reference" else 95.0 + (-1.0 if name == worse else 0.0)  # a tie passes
            tasks = {n: {"policy": [own + e for e in range(3)], "mpc-forecast": [100.0 + e for e in range(3)]} for n in names}
            record = {"policy": policy, "seed": 1000, "episodes": 3, "k": 3, "tasks": tasks}
            md.rule_file(tmp_path, label, name).write_text(json.dumps(record))

    write("reference", "ref.yaml", None)
    write("candidate", "cand.yaml", None)
    assert md.rule("cand.yaml", "ref.yaml", str(tmp_path), episodes=3) is True
    assert "yes" in capsys.readouterr().out
    for worse in ("skew variants 2.7", "training-city events", "hotspot events", "sink events"):
        write("candidate", "cand.yaml", worse)
        assert md.rule("cand.yaml", "ref.yaml", str(tmp_path), episodes=3) is False
        row = next(line for line in capsys.readouterr().out.splitlines() if line.startswith(f"| {worse}"))
        assert "| **no** |" in row  # (then the difference in runs' sd when docs/meta/rule/runs.json is there)
    rows = md.rule_rows(*({name: json.loads(md.rule_file(tmp_path, label, name).read_text()) for name in md.RULE_SETS}
                          for label in ("reference", "candidate")))  # fmt: skip
    skew = next(r for r in rows if r["set"] == "skew variants 2.7")
    assert skew["reference"] == pytest.approx(np.mean([100 * (1 - (95 + e) / (100 + e)) for e in range(3)]))
    assert skew["diff"] == pytest.approx(np.mean([-100 / (100 + e) for e in range(3)])) and skew["passes"]


def test_rule_reads_the_tables_records_for_its_reference_and_keeps_a_copy(tmp_path, monkeypatch, capsys):
    """benchmarks/meta_diagnostics.py rule: the reference's sets come from the shipped records
    (docs/meta/rule) when they hold the same policy, tasks and episodes, copied into the rule's folder
    (the candidate reads MPC-F's profits there); a record of another policy is not taken."""
    import json

    import meta_diagnostics as md

    shipped, out = tmp_path / "shipped", tmp_path / "rule"
    shipped.mkdir()
    out.mkdir()
    monkeypatch.setattr(md, "RULE_RECORDS", shipped)
    for name, (_, names) in md.RULE_SETS.items():
        for label, folder, policy, own in (("reference", shipped, "ref.yaml", 95.0), ("candidate", out, "cand.yaml", 96.0)):
            tasks = {n: {"policy": [own, own + 1], "mpc-forecast": [100.0, 101.0]} for n in names}
            md.rule_file(folder, label, name).write_text(json.dumps({"policy": policy, "seed": 1000, "episodes": 2, "k": 3, "tasks": tasks}))
    assert md.rule("cand.yaml", "ref.yaml", str(out), episodes=2) is True  # nearer MPC-F everywhere, nothing rerun
    assert all(md.rule_file(out, "reference", name).is_file() for name in md.RULE_SETS)
    capsys.readouterr()
    assert md.rule_record(out, "reference", "sink events", "other.yaml", 2) is None
    assert md.rule_record(shipped, "reference", "sink events", "ref.yaml", 3) is None


def test_the_rule_reference_averages_in_the_replicate_episode_by_episode(tmp_path, capsys):
    """benchmarks/meta_diagnostics.py rule: the tables' reference is both pairs of its recipe averaged per
    episode (MPC-F's profits unchanged), every pair's records shipped; records of other tasks are refused; ``recipes``
    reads two recipes' kept records, each averaged, and judges the second against the first."""
    import json

    import meta_diagnostics as md

    ref = {"policy": "ref.yaml", "episodes": 2, "tasks": {"a": {"policy": [10.0, 20.0], "mpc-forecast": [30.0, 31.0]}}}
    rep = {"policy": "rep.yaml", "episodes": 2, "tasks": {"a": {"policy": [14.0, 10.0], "mpc-forecast": [30.0, 31.0]}}}
    both = md.averaged([ref, rep])
    assert both["tasks"]["a"] == {"policy": [12.0, 15.0], "mpc-forecast": [30.0, 31.0]} and ref["tasks"]["a"]["policy"] == [10.0, 20.0]
    assert both["policy"] == "ref.yaml + rep.yaml"
    with pytest.raises(SystemExit, match="other tasks"):
        md.averaged([ref, {**rep, "tasks": {"b": rep["tasks"]["a"]}}])
    assert md.RULE_AVERAGED_WITH == md.META_POLICY
    for label in ("reference", "replicate", "cut01", "cut23"):  # the tables' recipe's two pairs, the earlier recipe's two
        assert all(md.rule_file(md.RULE_RECORDS, label, name).is_file() for name in md.RULE_SETS)
    (tmp_path / "shipped").mkdir()
    assert all(md.rule_record(tmp_path / "shipped", "reference", name, md.META_POLICY, 20) for name in md.RULE_SETS)  # read, not rerun

    for label, profit in (("a0", 80.0), ("a1", 90.0), ("b0", 70.0), ("b1", 99.0)):  # recipe b: 84.5 against a's 85 on average
        for name, (_, names) in md.RULE_SETS.items():
            tasks = {t: {"policy": [profit, profit], "mpc-forecast": [100.0, 100.0]} for t in names}
            md.rule_file(tmp_path, label, name).write_text(json.dumps({"policy": label, "seed": 1000, "episodes": 2, "k": 3, "tasks": tasks}))
    assert md.recipes([str(tmp_path / "a0"), str(tmp_path / "a1")], [str(tmp_path / "b0"), str(tmp_path / "b1")]) is False
    assert "| 15.000% | 15.500% | +0.500% (0.000) | **no** |" in capsys.readouterr().out
    assert md.recipes([str(tmp_path / "a0")], [str(tmp_path / "b0"), str(tmp_path / "b1")]) is True  # 84.5 against 80 alone
    assert md.recipes([str(tmp_path / "a1")], [str(tmp_path / "b0"), str(tmp_path / "b1")]) is False


def test_rule_tasks_measured_in_two_processes_are_those_measured_in_one(tmp_path):
    """benchmarks/meta_diagnostics.py --workers: each task's profits depend on its arguments only, so a
    rule split over spawned processes writes the numbers one process writes, in the order asked."""
    import meta_diagnostics as md

    args = meta.Args(scenario="synthetic", cities=["porto"], val_cities=["porto"], hidden=8, trial_episodes=2, final_eval_episodes=1,
                     run_dir=str(tmp_path / "run"), policy_out=str(tmp_path / "tiny.pt"))  # fmt: skip
    torch.manual_seed(0)
    meta.finish(args, meta.make_model(args), 1.0, 0, None)
    jobs = [(str(tmp_path / "tiny.pt"), "synthetic", 2, 1000 + i, 1, None) for i in range(3)]
    alone = list(md.in_workers(jobs, 1))
    assert list(md.in_workers(jobs, 2)) == alone
    assert alone[0] != alone[1] and all(len(r["policy"]) == len(r["mpc-forecast"]) == 2 for r in alone)


def test_misread_adapts_on_the_usual_day_without_the_event_and_refuses_a_task_without_one():
    """benchmarks/meta_diagnostics.py misread: the usual day of an evented task is the task's own
    variant with the draw back on its forecast (a hotspot stays, the event goes), so the memory adapts
    on the same city minus the shock; a task without an event has nothing to misread."""
    import meta_diagnostics as md

    evented, variant = meta.task_city("synthetic~hot1x2~ev3x2@0-5"), meta.task_city("synthetic~hot1x2")
    usual = md.usual_day(evented)
    assert evented.meta["events"] and "events" not in usual.meta and usual.meta["hotspot"] == variant.meta["hotspot"]
    np.testing.assert_array_equal(usual.demand_rate, variant.demand_rate)
    assert not np.array_equal(evented.demand_rate, variant.demand_rate)
    with pytest.raises(SystemExit, match="has no event"):
        md.misread("unused.pt", ["synthetic~hot1x2"], episodes=1)


def test_a_memory_frozen_at_every_step_adapts_to_nothing_and_unfreezes_after():
    """benchmarks/meta_diagnostics.py misread --freeze: with the memory held at every step of the
    adaptation episodes the adapted memory is the new trial's; held nowhere, it moves; outside the
    context the agent is itself again."""
    import meta_diagnostics as md

    city = load_city("synthetic")
    torch.manual_seed(0)
    model = meta.RecurrentGNN(meta.n_task_features(6), hidden=8, stay_prior=True)
    fresh = model.initial_memory(city.n_regions, 1)
    with md.memory_frozen(range(city.horizon)):
        held = meta.adapt(model, city, 2, 6, seed=0)
    torch.testing.assert_close(held.adapted, fresh)
    with md.memory_frozen(None):
        moved = meta.adapt(model, city, 2, 6, seed=0)
    assert not torch.equal(moved.adapted, fresh)
    torch.testing.assert_close(meta.adapt(model, city, 2, 6, seed=0).adapted, moved.adapted)  # unfrozen after


def test_the_pairs_figure_reads_every_pair_and_its_tables_row_is_the_tables(tmp_path):
    """benchmarks/meta_pairs_plot.py: docs/meta/pairs.csv holds four numbers and a verdict for every
    pair, its last chosen pair is the tables' meta-rl to the rounding (so the figure cannot drift from
    the tables), a bad row is refused, and the figure is written."""
    import json

    import meta_pairs_plot as mp

    rows = mp.load_pairs()
    tables = [r for r in rows if r["verdict"] == "yes"][-1]
    for city in mp.CITIES:
        rows_ = json.loads((mp.DOCS / "intercity.json").read_text())["targets"][city]
        gap = 100 * (1 - rows_["meta-rl"]["metrics"]["profit"]["mean"] / rows_["mpc-oracle"]["metrics"]["profit"]["mean"])
        assert float(tables[city]) == pytest.approx(gap, abs=0.005), city
    event = json.loads((mp.DOCS / "event.json").read_text())["targets"]["nyc_brooklyn_event"]["meta-rl"]["metrics"]["profit"]["mean"]
    assert float(tables["event"]) == pytest.approx(event, abs=0.5)
    bad = tmp_path / "pairs.csv"
    bad.write_text(mp.DOCS.joinpath("pairs.csv").read_text().replace(",yes\n", ",maybe\n", 1))
    with pytest.raises(SystemExit, match="verdict"):
        mp.load_pairs(bad)
    from marl_amod.plots import save_figure

    assert save_figure(mp.figure(rows, mp.event_references()), tmp_path / "pairs.png").stat().st_size > 10_000


def _rule_folder(folder: Path, profit_of: Callable[[str], float], episodes: int = 1) -> str:
    """A single run's ``rule`` folder as meta_diagnostics reads it: each set's candidate record, every task at
    ``profit_of(task)`` in each of ``episodes`` episodes against MPC-F's 110."""
    import json

    import meta_diagnostics as md

    folder.mkdir()
    for name, (_, tasks_) in md.RULE_SETS.items():
        record = {"policy": f"{folder.name}.pt", "tasks": {t: {"policy": [profit_of(t)] * episodes, "mpc-forecast": [110.0] * episodes} for t in tasks_}}
        md.rule_file(folder, "candidate", name).write_text(json.dumps(record))
    return str(folder)


def _heldout_folder(folder: Path, intercity: dict[str, float], event: dict[str, float]) -> str:
    """A ``transfer-table`` folder with only the meta-rl profits given (MPC-Oracle at 200 in every target)."""
    import json

    def rows(profits: dict[str, float]) -> dict[str, Any]:
        return {"targets": {city: {"meta-rl": {"metrics": {"profit": {"mean": p}}}, "mpc-oracle": {"metrics": {"profit": {"mean": 200.0}}}}
                            for city, p in profits.items()}}  # fmt: skip

    folder.mkdir()
    (folder / "intercity.json").write_text(json.dumps(rows(intercity)))
    (folder / "event.json").write_text(json.dumps(rows(event)))
    return str(folder)


def test_runs_reads_a_recipe_against_another_in_the_first_recipes_spread_between_runs(tmp_path, capsys):
    """benchmarks/meta_diagnostics.py runs: each set's mean over each recipe's single runs, the difference,
    and its SE sd_first x sqrt(1/n1 + 1/n2); fewer than two runs of the yardstick is refused."""
    import meta_diagnostics as md

    plain = [_rule_folder(tmp_path / f"p{i}", lambda t, p=p: p, episodes=2) for i, p in enumerate((100.0, 102.0, 104.0))]  # sd 2
    arm = [_rule_folder(tmp_path / f"a{i}", lambda t, p=p: p, episodes=2) for i, p in enumerate((105.0, 107.0))]
    rows = {r["set"]: r for r in md.arm_runs(plain, arm)}
    events = rows["training-city events"]
    assert (events["first"], events["second"], events["diff"]) == pytest.approx((102.0, 106.0, 4.0))
    assert events["se"] == pytest.approx(2.0 * np.sqrt(1 / 3 + 1 / 2)) and events["z"] == pytest.approx(4.0 / events["se"])
    shaped = rows["shaped set"]  # gaps: 100 * (1 - profit / 110)
    assert shaped["diff"] == pytest.approx(100 * (102.0 - 106.0) / 110) and shaped["second_runs"] == pytest.approx([100 * (1 - p / 110) for p in (105, 107)])
    assert events["welch_se"] == pytest.approx(np.sqrt(4 / 3 + 2 / 2))  # sds 2 and sqrt(2)
    assert "| training-city events | 102 | 106 | 105 / 107 | +4.000 (1.826) | +2.2 | +2.6 |" in capsys.readouterr().out
    assert np.isnan(md.arm_runs(plain, arm[:1])[0]["welch_se"])  # one run of the second: no spread of its own
    with pytest.raises(SystemExit, match="at least two"):
        md.arm_runs(plain[:1], arm)


def test_track_ranks_runs_by_each_rule_set_against_the_held_out_cities(tmp_path, capsys):
    """benchmarks/meta_diagnostics.py track: per rule set and held-out measure, Spearman's rank correlation over
    runs, signed so +1 agrees (a lower gap or a higher profit better on both); mismatched inputs are refused."""
    import meta_diagnostics as md

    # rule sets: profits rise with i, so run 3 is best on every set; held out, city a: the runs' order (best last),
    # city b: the reverse, the event: the runs' order
    rules = [_rule_folder(tmp_path / f"rule{i}", lambda t, p=p: p) for i, p in enumerate((100.0, 101.0, 103.0, 106.0))]
    held = [_heldout_folder(tmp_path / f"ho{i}", {"a": 150.0 + i, "b": 160.0 - i}, {"a_event": 50.0 + i}) for i in range(4)]
    table = md.track(rules, held)
    for name in md.RULE_SETS:
        assert table[name]["a"][0] == pytest.approx(1.0) and table[name]["b"][0] == pytest.approx(-1.0)
        assert table[name]["a_event"][0] == pytest.approx(1.0)
    assert "| shaped set | +1.00" in capsys.readouterr().out
    with pytest.raises(SystemExit, match="one held-out folder per rule folder"):
        md.track(rules, held[:3])


def test_track_reads_each_rule_set_on_the_cities_asked_only(tmp_path, capsys):
    """track --cities: each set's mean over those cities' tasks only (the cities a recipe never trained on), so runs
    ranked one way on porto and the other way elsewhere correlate +1 or -1 by the cities read; none there: refused."""
    import meta_diagnostics as md

    # porto's tasks: profits rise with i (run 3 best); every other city's fall, and outweigh porto's
    rules = [_rule_folder(tmp_path / f"rule{i}", lambda t, i=i: 100.0 + i if t.startswith("porto~") else 100.0 - 3 * i) for i in range(4)]
    held = [_heldout_folder(tmp_path / f"ho{i}", {"a": 150.0 + i}, {"a_event": 150.0 + i}) for i in range(4)]
    on_porto, on_all, elsewhere = md.track(rules, held, ["porto"]), md.track(rules, held), md.track(rules, held, ["washington_dc", "nyc_man_north"])
    for name in md.RULE_SETS:
        assert on_porto[name]["a"][0] == pytest.approx(1.0) and on_all[name]["a"][0] == pytest.approx(-1.0), name
        assert elsewhere[name]["a"][0] == pytest.approx(-1.0), name
    assert md.set_tasks("skew variants 2.7", ["porto", "washington_dc"]) == ["porto~skew2.7", "washington_dc~skew2.7"]
    assert "(each set on porto only)" in capsys.readouterr().out
    with pytest.raises(SystemExit, match="no task of"):
        md.track(rules, held, ["rome"])
    from marl_amod.plots import save_figure

    fig = md.track_figure({"on porto": on_porto, "elsewhere": elsewhere})
    assert len(fig.axes) == 3 and save_figure(fig, tmp_path / "track.png").stat().st_size > 10_000  # two heatmaps and their colour bar
    assert fig.axes[0].images[0].get_array()[0, 0] == pytest.approx(1.0) and fig.axes[1].images[0].get_array()[0, 0] == pytest.approx(-1.0)


def test_told_shows_the_event_to_every_forecast_reader_and_refuses_a_day_without_one(monkeypatch, capsys):
    """benchmarks/meta_diagnostics.py told: the announced day is the evented day with the draw's expected demand as
    its forecast (the usual day's converse), so MPC-Forecast planning on it is MPC told the event, episode by
    episode; the meta-policy adapts on the announced day too; a day without an event has nothing to tell."""
    import meta_diagnostics as md

    from marl_amod.algos.meta_imitation import MPCToldTheShock
    from marl_amod.evaluation import evaluate

    evented = meta.task_city("synthetic~ev3x4@0-5")
    shown = md.announced(evented)
    np.testing.assert_array_equal(shown.forecast_rate, evented.demand_rate)
    np.testing.assert_array_equal(shown.demand_rate, evented.demand_rate)
    assert not np.array_equal(evented.forecast_rate, evented.demand_rate)  # the event was not in the forecast
    profit = lambda pol, city: [m["profit"] for m in evaluate(pol, city, 2, 0)["per_episode"]]  # noqa: E731
    told_profit = profit(MPCToldTheShock(), evented)
    assert profit("mpc-forecast", shown) == told_profit != profit("mpc-forecast", evented)
    adapted_on = []
    monkeypatch.setattr(md.meta, "load_policy", lambda policy, city, k, seed=0: adapted_on.append(city) or "equal-distribution")
    rows = md.told("unused.pt", ["synthetic~ev3x4@0-5"], episodes=2)["synthetic~ev3x4@0-5"]
    assert len(adapted_on) == 2  # as deployed, then on the announced day
    np.testing.assert_array_equal(adapted_on[1].forecast_rate, adapted_on[1].demand_rate)
    assert not np.array_equal(adapted_on[0].forecast_rate, adapted_on[0].demand_rate)
    assert rows["mpc told the event"].tolist() == told_profit
    assert "the event in the meta-policy's inputs is worth" in capsys.readouterr().out
    with pytest.raises(SystemExit, match="has no event"):
        md.told("unused.pt", ["synthetic"], episodes=1)
