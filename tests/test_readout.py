"""The GNN's fleet-wide readout: whole-fleet reach, equivariance, files, config errors of both GNN options (dense == torch-geometric: test_dense.py)."""

from __future__ import annotations

import json

import pytest
import torch

from marl_amod.algos.registry import ALGOS, args_for
from marl_amod.checkpoints import load_actor, save_policy
from marl_amod.errors import ConfigError, DataError
from marl_amod.evaluation import evaluate
from marl_amod.models import GNNActor, GNNValueCritic, build_actor
from marl_amod.scenario import load_city

READOUTS = ["mean", "max", "mean-max"]


def _far_pair(edge_index: torch.Tensor, n: int) -> tuple[int, int]:
    """Two regions more than one hop apart (neither is the other's neighbour)."""
    adj = torch.zeros(n, n, dtype=torch.bool)
    adj[edge_index[0], edge_index[1]] = True
    adj |= adj.T | torch.eye(n, dtype=torch.bool)
    i, j = (~adj).nonzero()[0].tolist()
    return i, j


@pytest.mark.parametrize("readout", ["none", *READOUTS])
@pytest.mark.parametrize("conv", ["gcn", "sage"])
def test_a_far_region_moves_a_node_only_with_the_readout(tiny_city, conv, readout):
    torch.manual_seed(0)
    ei = torch.tensor(tiny_city.edge_index)
    i, far = _far_pair(ei, tiny_city.n_regions)
    x = torch.rand(3, tiny_city.n_regions, 13)
    moved = x.clone()
    moved[:, far] += 5.0 * torch.rand(3, 13)
    actor = GNNActor(13, 16, conv, readout)  # type: ignore[arg-type]
    change = (actor(moved, ei)[:, i] - actor(x, ei)[:, i]).abs()
    if readout == "none":
        assert change.max() == 0  # one hop: region i never sees a region two hops away
    else:
        assert bool((change > 1e-4).all())


@pytest.mark.parametrize("readout", READOUTS)
@pytest.mark.parametrize("conv", ["gcn", "sage"])
def test_readout_models_are_permutation_equivariant_and_size_agnostic(tiny_city, small_city, conv, readout):
    torch.manual_seed(1)
    ei = torch.tensor(tiny_city.edge_index)
    x = torch.rand(2, 9, 13)
    perm = torch.randperm(9)  # new node k is old node perm[k]
    ei_p = torch.argsort(perm)[ei]
    actor, critic = GNNActor(13, 16, conv, readout), GNNValueCritic(13, 16, conv, readout)  # type: ignore[arg-type]
    torch.testing.assert_close(actor(x[:, perm], ei_p), actor(x, ei)[:, perm])
    torch.testing.assert_close(critic(x[:, perm], ei_p), critic(x, ei))
    assert actor(torch.rand(16, 13), torch.tensor(small_city.edge_index)).shape == (16,)  # same weights, another city


def test_no_readout_keeps_the_papers_parameters():
    """readout: none adds no module, so every shipped GNN policy's state dict still fits."""
    plain = set(GNNActor(13, 8).state_dict())
    assert plain == {f"trunk.conv.{k}" for k in ("bias", "lin.weight")} | {f"head.{i}.{k}" for i in (0, 2, 4) for k in ("weight", "bias")}
    assert plain < set(GNNActor(13, 8, readout="mean").state_dict())
    with pytest.raises(ValueError, match="unknown readout"):
        GNNActor(13, 8, readout="sum")  # type: ignore[arg-type]


def test_readout_policy_file_round_trip(tmp_path, tiny_city):
    torch.manual_seed(3)
    actor = build_actor("gnn", tiny_city, 13, 8, "gcn", "mean-max")
    card = {"scenario": tiny_city.name, "algorithm": "bc", "mode": "centralised", "actor": "gnn", "conv": "gcn",
            "readout": "mean-max", "hidden": 8, "n_features": 13, "lookahead": 6, "seed": 0}  # fmt: skip
    path = save_policy(tmp_path / "r.pt", actor, card)
    loaded, loaded_card = load_actor(path, tiny_city)
    assert loaded_card["readout"] == "mean-max" and loaded.readout is not None
    x = torch.rand(4, 9, 13)
    ei = torch.tensor(tiny_city.edge_index)
    torch.testing.assert_close(loaded(x, ei), actor(x, ei), rtol=0, atol=0)
    # a card that lost its readout describes another network: refused, naming the file
    save_policy(tmp_path / "lost.pt", actor, {k: v for k, v in card.items() if k != "readout"})
    with pytest.raises(DataError, match="lost.pt"):
        load_actor(tmp_path / "lost.pt", tiny_city)


def test_bc_with_readout_ships_a_policy_that_rebuilds_from_its_card(tmp_path, tiny_prop_dataset):
    scenario, dataset = tiny_prop_dataset
    args = {"scenario": scenario, "dataset": dataset, "updates": 4, "batch_size": 8, "eval_every": 4, "eval_episodes": 1,
            "final_eval_episodes": 2, "hidden": 8, "run_dir": str(tmp_path / "run"), "policy_out": str(tmp_path / "p.pt")}  # fmt: skip
    summary = ALGOS["bc"].train(args_for("bc", {**args, "readout": "mean"}))
    assert json.loads((tmp_path / "p.json").read_text())["readout"] == "mean"
    res = evaluate(str(tmp_path / "p.pt"), load_city(scenario), episodes=2, seed=0)
    assert res["metrics"]["profit"]["mean"] == pytest.approx(summary["card"]["profit_mean"])
    plain = ALGOS["bc"].train(args_for("bc", {**args, "policy_out": str(tmp_path / "q.pt")}))
    assert "readout" not in plain["card"]  # the default writes the cards it always wrote


@pytest.mark.parametrize(("option", "extra", "message"), [
    ({"readout": "mean"}, {"mode": "decentralised"}, "decentralised actor reads only its local observation"),
    ({"readout": "mean"}, {"actor": "mlp"}, "GNN actor option"),
    ({"readout": "mean"}, {"readout": "sum"}, "readout"),
    ({"agent_id": True}, {"mode": "decentralised"}, "agent_id .*decentralised actor reads only its local observation"),
    ({"agent_id": True}, {"actor": "mlp"}, "agent_id is a GNN actor option"),
    ({"agent_id": True}, {"actor": "cnn"}, "agent_id is a GNN actor option"),
])  # fmt: skip
def test_gnn_options_where_they_cannot_apply_are_config_errors(tiny_prop_dataset, option, extra, message):
    """The readout and the region identity (``agent_id``) are centralised GNN options, checked by
    one validator of the run arguments and by ``build_actor``."""
    scenario, dataset = tiny_prop_dataset
    with pytest.raises(ConfigError, match=message):
        args_for("bc", {"scenario": scenario, "dataset": dataset, **option, **extra})
    with pytest.raises(ValueError, match=f"{next(iter(option))} is a GNN actor option"):
        build_actor("mlp", load_city(scenario), 13, 8, **option)
