"""The GNN's region identity (agent_id): place-dependent outputs, files (dense == torch-geometric: test_dense.py; config errors: test_readout.py)."""

from __future__ import annotations

import json

import pytest
import torch

from marl_amod.algos.registry import ALGOS, args_for
from marl_amod.checkpoints import architecture_args, load_actor, save_policy
from marl_amod.comparison import architecture
from marl_amod.errors import DataError
from marl_amod.evaluation import evaluate
from marl_amod.models import GNNActor, build_actor
from marl_amod.scenario import load_city


@pytest.mark.parametrize("conv", ["gcn", "sage"])
def test_regions_with_the_same_input_differ_only_with_the_region_identity(tiny_city, conv):
    """Every region sees the same features: a mean-aggregating GNN gives them one output (it cannot
    tell a corner from the centre), the same GNN with the identity a different output for each."""
    torch.manual_seed(0)
    ei = torch.tensor(tiny_city.edge_index)
    n = tiny_city.n_regions
    x = torch.rand(1, 13).expand(n, 13)
    if conv == "sage":  # (GCN's degree normalisation already separates a corner from the centre)
        plain = GNNActor(13, 16, conv)(x, ei)
        torch.testing.assert_close(plain, plain[:1].expand(n))
    alpha = GNNActor(13, 16, conv, agent_ids=n)(x, ei)
    gaps = (alpha[:, None] - alpha[None, :]).abs() + torch.eye(n)
    assert bool((gaps > 1e-6).all())  # pairwise distinct


def test_region_identity_widens_the_input_and_adds_no_state_dict_entry():
    """The one-hot is not a weight: the same parameter names, the first layer N columns wider;
    agent_ids=0 is the paper's model."""
    plain, with_id = GNNActor(13, 8).state_dict(), GNNActor(13, 8, agent_ids=9).state_dict()
    assert set(plain) == set(with_id)
    assert plain["trunk.conv.lin.weight"].shape == (13, 13) and with_id["trunk.conv.lin.weight"].shape == (22, 22)
    assert GNNActor(13, 8, agent_ids=0).region_id is None
    with pytest.raises(ValueError, match="9-region identity; this graph has 16"):
        GNNActor(13, 8, agent_ids=9)(torch.rand(16, 13), torch.zeros(2, 0, dtype=torch.long))


def test_agent_id_policy_file_round_trip_and_a_city_of_another_size(tmp_path, tiny_city, small_city):
    torch.manual_seed(3)
    actor = build_actor("gnn", tiny_city, 13, 8, "sage", "none", agent_id=True)
    card = {"scenario": tiny_city.name, "algorithm": "bc", "mode": "centralised", "actor": "gnn", "conv": "sage", "agent_id": True,
            "n_regions": tiny_city.n_regions, "hidden": 8, "n_features": 13, "lookahead": 6, "seed": 0}  # fmt: skip
    path = save_policy(tmp_path / "r.pt", actor, card)
    loaded, loaded_card = load_actor(path, tiny_city)
    assert loaded_card["agent_id"] is True and loaded.region_id is not None
    assert architecture_args(loaded_card)["agent_id"] is True and architecture(loaded_card) == "GNN, sage, region id"
    x, ei = torch.rand(4, 9, 13), torch.tensor(tiny_city.edge_index)
    torch.testing.assert_close(loaded(x, ei), actor(x, ei), rtol=0, atol=0)
    with pytest.raises(DataError, match=r"r\.pt: trained with agent_id .* 9 regions.* has 16"):
        load_actor(path, small_city)
    with pytest.raises(DataError, match="trained with agent_id"):  # the path `marl-amod evaluate --policy` takes
        evaluate(str(path), small_city, episodes=1, seed=0)
    # a card that lost its agent_id describes another network: refused, naming the file
    save_policy(tmp_path / "lost.pt", actor, {k: v for k, v in card.items() if k != "agent_id"})
    with pytest.raises(DataError, match="lost.pt"):
        load_actor(tmp_path / "lost.pt", tiny_city)


def test_bc_then_a2c_with_agent_id_rebuild_the_actor_from_the_card(tmp_path, tiny_prop_dataset):
    """BC writes agent_id on its card; architecture_args carries it into an A2C warm start, whose
    value critic reads the identity too; the default writes the cards it always wrote."""
    from marl_amod.algos import a2c

    scenario, dataset = tiny_prop_dataset
    args = {"scenario": scenario, "dataset": dataset, "updates": 4, "batch_size": 8, "eval_every": 4, "eval_episodes": 1,
            "final_eval_episodes": 2, "hidden": 8, "run_dir": str(tmp_path / "run"), "policy_out": str(tmp_path / "p.pt")}  # fmt: skip
    summary = ALGOS["bc"].train(args_for("bc", {**args, "agent_id": True}))
    card = json.loads((tmp_path / "p.json").read_text())
    assert card["agent_id"] is True and card["n_regions"] == 9
    res = evaluate(str(tmp_path / "p.pt"), load_city(scenario), episodes=2, seed=0)
    assert res["metrics"]["profit"]["mean"] == pytest.approx(summary["card"]["profit_mean"])
    plain = ALGOS["bc"].train(args_for("bc", {**args, "policy_out": str(tmp_path / "q.pt")}))
    assert "agent_id" not in plain["card"]

    run = tmp_path / "a2c"
    tuned = a2c.train(a2c.Args(scenario=scenario, **architecture_args(card), init_actor=str(tmp_path / "p.pt"), episodes=2,
                               episodes_per_update=2, eval_every=2, eval_episodes=1, final_eval_episodes=1, run_dir=str(run),
                               policy_out=str(tmp_path / "ft.pt")))  # fmt: skip
    assert tuned["card"]["agent_id"] is True
    critic = torch.load(run / "state.pt", weights_only=False)["critic"]
    assert critic["trunk.conv.lin.weight"].shape == (13 + 9, 13 + 9)  # critic_time off: F + N
    with pytest.raises(DataError, match="differs"):  # a plain actor does not start from the identity clone
        a2c.train(a2c.Args(scenario=scenario, hidden=8, init_actor=str(tmp_path / "p.pt"), episodes=2, episodes_per_update=2,
                           run_dir=str(tmp_path / "a2c_plain"), policy_out=""))  # fmt: skip
