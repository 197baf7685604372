"""BC, IQL and CQL end to end on a 3x3 grid: from a collected dataset to a policy that evaluates like any other."""

from __future__ import annotations

import hashlib
import json
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
import yaml
from typer.testing import CliRunner

from marl_amod.algos import common as C
from marl_amod.algos import offline as O
from marl_amod.algos.registry import ALGOS, args_for
from marl_amod.cli import app
from marl_amod.datasets import OfflineDataset
from marl_amod.errors import ConfigError, DataError
from marl_amod.evaluation import evaluate
from marl_amod.models import build_actor
from marl_amod.scenario import load_city


@pytest.fixture
def tiny(tiny_prop_dataset) -> tuple[str, str]:
    return tiny_prop_dataset


def _args(tmp_path: Path, tiny, **kw) -> dict:
    scenario, dataset = tiny
    return {"scenario": scenario, "dataset": dataset, "updates": 6, "batch_size": 8, "eval_every": 3, "eval_episodes": 1,
            "final_eval_episodes": 2, "hidden": 8, "run_dir": str(tmp_path / "run"), "policy_out": str(tmp_path / "p.pt"), **kw}


@pytest.mark.parametrize("algo", ["bc", "iql", "cql"])
@pytest.mark.parametrize("mode", ["centralised", "decentralised"])
def test_offline_algorithm_trains_from_a_dataset_and_ships_a_policy(tmp_path, tiny, algo, mode):
    extra = {"critic_hidden": 8} if algo != "bc" else {}
    if algo == "cql":
        extra.update(bc_steps=2, n_actions=2)
    summary = ALGOS[algo].train(args_for(algo, _args(tmp_path, tiny, mode=mode, **extra)))
    card = json.loads((tmp_path / "p.json").read_text())
    assert card["algorithm"] == algo and card["mode"] == mode and card["updates"] == 6 and card["kept"] == "last"
    assert card["dataset"]["policy"] == "prop" and "reference_scores" in card["dataset"]
    assert np.isfinite(O.card_normalised(card))
    log = (tmp_path / "run" / "log.csv").read_text()
    assert "eval/profit" in log and "loss/" in log
    res = evaluate(str(tmp_path / "p.pt"), load_city(tiny[0]), episodes=2, seed=0)
    assert res["metrics"]["profit"]["mean"] == pytest.approx(summary["card"]["profit_mean"])


def test_bc_learns_the_logged_actions(tmp_path, tiny):
    """After training, the cloned actor's mean action is closer to the logged one than at the start."""
    from marl_amod.algos import bc

    args = args_for("bc", _args(tmp_path, tiny, updates=150, eval_every=150, lr_actor=5e-3))
    city = load_city(tiny[0])
    data = O.Data(args, city)
    ei = torch.as_tensor(city.edge_index)
    b = O.Batch(data.tensors)
    torch.manual_seed(0)
    gap = lambda actor: (torch.nn.functional.normalize(actor(b["x"], ei), p=1, dim=-1) - b["action"]).abs().sum(-1).mean().item()  # noqa: E731
    before = gap(C.make_actor(args, city))
    bc.train(args)
    from marl_amod.checkpoints import load_actor

    actor, _ = load_actor(tmp_path / "p.pt", city)
    assert gap(actor) < 0.5 * before


def test_iql_resume_continues_from_the_saved_update(tmp_path, tiny):
    ALGOS["iql"].train(args_for("iql", _args(tmp_path, tiny, critic_hidden=8)))
    summary = ALGOS["iql"].train(args_for("iql", _args(tmp_path, tiny, critic_hidden=8, updates=9)), resume=str(tmp_path / "run" / "state.pt"))
    assert summary["card"]["updates"] == 9
    steps = [int(line.split(",")[0]) for line in (tmp_path / "run" / "log.csv").read_text().splitlines()[1:]]
    assert steps == sorted(steps) and min(steps) == 3 and max(steps) == 9


def test_dataset_of_another_city_or_lookahead_is_refused(tmp_path, tiny):
    other = tmp_path / "other.yaml"
    other.write_text(yaml.safe_dump({"name": "other", "source": "synthetic", "rows": 2, "cols": 2, "horizon": 6}))
    with pytest.raises(DataError, match="collected on tiny"):
        ALGOS["bc"].train(args_for("bc", {**_args(tmp_path, tiny), "scenario": str(other)}))
    with pytest.raises(ConfigError, match="lookahead"):
        ALGOS["bc"].train(args_for("bc", _args(tmp_path, tiny, lookahead=3)))
    with pytest.raises(ConfigError, match="episodes"):
        args_for("bc", _args(tmp_path, tiny, episodes=5))


def test_cli_trains_an_offline_config(tmp_path, tiny):
    config = tmp_path / "bc.yaml"
    config.write_text(yaml.safe_dump({"algo": "bc", "args": _args(tmp_path, tiny)}))
    result = CliRunner().invoke(app, ["train", "--config", str(config)])
    assert result.exit_code == 0, result.output
    assert (tmp_path / "p.pt").is_file()


def test_shipped_offline_configs_validate():
    from marl_amod.algos.registry import load_train_config

    paths = sorted((Path(__file__).resolve().parent.parent / "configs").glob("[bic][cq]*/nyc_brooklyn_*.yaml"))
    assert len(paths) >= 15, paths  # BC, IQL and CQL on the five datasets at least, wherever pytest runs from
    for path in paths:
        algo, args = load_train_config(path)
        assert algo in ("bc", "iql", "cql") and args.dataset.startswith("runs/datasets/nyc_brooklyn_"), path


def test_online_runs_warm_start_from_an_offline_policy(tmp_path, tiny):
    """Offline -> online fine-tuning: init_actor loads the offline actor; a different architecture is refused."""
    from marl_amod.algos import a2c
    from marl_amod.algos import common as C
    from marl_amod.checkpoints import load_actor

    ALGOS["bc"].train(args_for("bc", _args(tmp_path, tiny)))
    city = load_city(tiny[0])
    offline, _ = load_actor(tmp_path / "p.pt", city)
    args = a2c.Args(scenario=tiny[0], hidden=8, init_actor=str(tmp_path / "p.pt"))
    actor = build_actor("gnn", city, 13, 8, "gcn")
    C.warm_start(actor, args, city)
    for key, value in offline.state_dict().items():
        assert torch.equal(actor.state_dict()[key], value)
    with pytest.raises(DataError, match="differs"):
        C.warm_start(build_actor("gnn", city, 13, 16, "gcn"), args, city)
    summary = a2c.train(a2c.Args(scenario=tiny[0], hidden=8, episodes=2, episodes_per_update=2, eval_every=2, eval_episodes=1,
                                 final_eval_episodes=1, run_dir=str(tmp_path / "a2c"), init_actor=str(tmp_path / "p.pt")))
    assert summary["card"]["args"]["init_actor"] == str(tmp_path / "p.pt")
    assert summary["card"]["start_sha256"] == hashlib.sha256((tmp_path / "p.pt").read_bytes()).hexdigest()  # the start, by content


class _FreeAlpha(torch.nn.Module):
    """An 'actor' whose concentrations are free parameters, the same in every state."""

    def __init__(self, n: int) -> None:
        super().__init__()
        self.raw = torch.nn.Parameter(torch.zeros(n))

    def forward(self, x, graph):
        return torch.nn.functional.softplus(self.raw).expand(x.shape[0], -1) + 1e-3


def _fitted_share(b: O.Batch, lr: float, steps: int, **loss) -> torch.Tensor:
    """The Dirichlet mean (N,) a free-concentration actor settles at under ``imitation_loss(**loss)`` on ``b``."""
    actor = _FreeAlpha(b["action"].shape[-1])
    opt = torch.optim.Adam(actor.parameters(), lr=lr)
    for _ in range(steps):
        value = O.imitation_loss(actor, b, None, local=False, **loss).mean()
        opt.zero_grad()
        value.backward()
        opt.step()
    alpha = actor(b["x"], None)[0].detach()
    return alpha / alpha.sum()


def test_imitation_loss_fits_the_mean_action_of_sparse_targets():
    """Logged targets are mostly zeros (INF, DTV, MPC): the fitted Dirichlet mean, which the
    deterministic policy plays, must be their average, as the cross-entropy makes it."""
    y = torch.tensor([[1.0, 0, 0]] * 6 + [[0, 0.5, 0.5]] * 2)  # average (0.75, 0.125, 0.125)
    b = O.Batch({"x": torch.zeros(8, 3, 1), "action": y})
    assert _fitted_share(b, 0.05, 600).tolist() == pytest.approx([0.75, 0.125, 0.125], abs=0.02)


def test_l1_imitation_fits_the_median_action_and_ce_the_mean():
    """imitation: l1 prices every vehicle alike: where the logged action is tied between two plans, it
    fits the more frequent one (the per-region median), while the cross-entropy fits their average."""
    y = torch.tensor([[0.8, 0.1, 0.1]] * 6 + [[0.2, 0.4, 0.4]] * 4)  # mean (0.56, 0.22, 0.22)
    b = O.Batch({"x": torch.zeros(10, 3, 1), "action": y})
    fitted = {kind: _fitted_share(b, 0.05, 800, kind=kind).tolist() for kind in ("ce", "l1")}
    assert fitted["ce"] == pytest.approx([0.56, 0.22, 0.22], abs=0.02)
    assert fitted["l1"] == pytest.approx([0.8, 0.1, 0.1], abs=0.02)
    with pytest.raises(ConfigError, match="imitation loss 'l2'"):
        O.imitation_loss(_FreeAlpha(3), b, None, local=False, kind="l2")  # type: ignore[arg-type]


def test_shortfall_weight_moves_a_receiving_regions_share_up_to_its_higher_logged_target():
    """Region 0 holds no idle vehicle and receives 3 or 5 of the 10 (60% / 40%): the plain absolute error
    fits 3, a shortfall priced 4 times the overshoot (where requests go unserved) fits 5; region 1, which
    sends, is weighted as before (the cross-entropy, whose vehicles it does not weigh, is refused at config load)."""
    y = torch.tensor([[0.3, 0.7]] * 6 + [[0.5, 0.5]] * 4)
    x = torch.tensor([[0.0], [0.1]]).expand(10, 2, 1)  # idle vehicles times FEATURE_SCALE: 0 and 10
    b = O.Batch({"x": x, "action": y})
    fitted = {shortfall: float(_fitted_share(b, 0.02, 1500, kind="l1", shortfall=shortfall)[0]) for shortfall in (0.0, 3.0)}
    assert fitted[0.0] == pytest.approx(0.3, abs=0.02)
    assert fitted[3.0] == pytest.approx(0.5, abs=0.02)


def test_surplus_price_moves_a_receiving_regions_share_back_down():
    """The set-up above, with the surplus at the receiving region priced too: short costs 4, over 1 + 2.
    The quantile the loss fits at region 0 is then 4 / 7, below the 60% of steps that log 3 vehicles, so
    it fits 3 again; only the over side of receivers is priced (the sender keeps weight 1)."""
    y = torch.tensor([[0.3, 0.7]] * 6 + [[0.5, 0.5]] * 4)
    x = torch.tensor([[0.0], [0.1]]).expand(10, 2, 1)
    b = O.Batch({"x": x, "action": y})
    fitted = {surplus: float(_fitted_share(b, 0.02, 1500, kind="l1", shortfall=3.0, surplus=surplus)[0]) for surplus in (0.0, 1.0, 2.0)}
    assert fitted[0.0] == pytest.approx(0.5, abs=0.02)
    assert fitted[1.0] == pytest.approx(0.5, abs=0.02)  # 4 / 6 is still above 60%
    assert fitted[2.0] == pytest.approx(0.3, abs=0.02)
    mean = torch.tensor([[0.4, 0.6]])  # 1 vehicle in 10 over at the receiver, 1 short at the sender
    one = O.Batch({"x": x[:1], "action": torch.tensor([[0.3, 0.7]])})
    per_row = O.imitation_loss(lambda *_: mean, one, None, local=False, kind="l1", shortfall=3.0, surplus=2.0)
    assert float(per_row) == pytest.approx(0.1 * 3 + 0.1 * 1)


def test_receiver_prices_read_the_trip_margin_and_the_cost_of_the_logged_moves(tiny):
    """trip: the mean fare minus operating cost over an episode's expected requests; move: the
    coordinator's cheapest rebalancing of the logged targets, its cost per vehicle moved. Two logged
    steps on the 3x3 grid: 4 vehicles from region 1 into 0 (one move each) and 2 from region 8 into 0
    (the far corner); a step that moves nothing only adds nothing. The weights are logged as the env
    takes a planner's targets: u / 2^k with 2^k >= M (exact in float32, datasets.env_action)."""
    city = load_city(tiny[0])
    idle = torch.zeros(3, 9)
    idle[:, 1], idle[:, 8] = 10, 10
    targets = torch.zeros(3, 9)
    targets[0, 0], targets[0, 1], targets[0, 8] = 4, 6, 10
    targets[1, 0], targets[1, 1], targets[1, 8] = 2, 10, 8
    targets[2] = idle[2]
    x = (idle * 0.01)[..., None].expand(3, 9, 13)
    prices = O.receiver_prices(city, x, targets / 32)
    h = city.horizon
    rate, margin = city.demand_rate[:h].ravel(), (city.price - city.beta * city.tstep * city.trip_time)[:h].ravel()
    assert prices["trip"] == pytest.approx(np.average(margin, weights=rate))
    assert prices["move"] == pytest.approx((4 * city.reb_cost[1, 0] + 2 * city.reb_cost[8, 0]) / 6)
    assert city.reb_cost[8, 0] > city.reb_cost[1, 0] > 0
    with pytest.raises(DataError, match="the logged actions move no vehicle"):
        O.receiver_prices(city, x[2:], targets[2:] / 32)


def test_receiver_prices_move_price_is_what_the_env_paid_on_a_metric_city(monkeypatch):
    """On a city whose travel times obey the triangle inequality (a grid) the coordinator solves the
    reduced network, where only surplus regions send; the full network ties with moves through a
    region that keeps its count (a -> b -> c costs what a -> c does) and moves more vehicles. The move
    price must be the env's own: its flows on the logged steps, cost over vehicles moved."""
    from marl_amod.coordinator.coordinator import Coordinator
    from marl_amod.coordinator.rebalance import satisfies_triangle_inequality
    from marl_amod.datasets import collect
    from marl_amod.policies import make_policy
    from marl_amod.scenario import grid_city

    city = grid_city(5, 5, seed=0, horizon=10, vehicles_per_region=8)
    assert satisfies_triangle_inequality(city.reb_time)
    flows: list[np.ndarray] = []
    real = Coordinator.rebalance

    def spy(self, idle, target, *, check=True):
        flows.append(real(self, idle, target, check=check))
        return flows[-1]

    monkeypatch.setattr(Coordinator, "rebalance", spy)
    data = collect(city, make_policy("prop", city), episodes=2, seed=0, noise=0.05)
    monkeypatch.setattr(Coordinator, "rebalance", real)
    paid = np.stack(flows)
    x = torch.tensor(data.global_view()["x"])
    prices = O.receiver_prices(city, x, torch.tensor(data.actions))
    assert prices["move"] == pytest.approx(float((paid * city.reb_cost).sum() / paid.sum()))


def test_the_imitation_option_reaches_bc_iql_and_cql_and_the_card(tmp_path, tiny, monkeypatch):
    """imitation: l1 and its shortfall weight are what BC, IQL and CQL clone with (their one imitation term),
    recorded on the card."""
    kinds: list[tuple[str, float, float]] = []
    real = O.imitation_loss

    def spy(*a, **k):
        kinds.append((k.get("kind", "ce"), k.get("shortfall", 0.0), k.get("surplus", 0.0)))
        return real(*a, **k)

    monkeypatch.setattr(O, "imitation_loss", spy)
    city = load_city(tiny[0])
    for algo in ("bc", "iql", "cql"):
        for priced in (False, True):
            kinds.clear()
            extra = {"critic_hidden": 8} if algo != "bc" else {}
            run = _args(tmp_path, tiny, imitation="l1", shortfall_weight=2.0, surplus_price=priced, updates=3, **extra)
            summary = ALGOS[algo].train(args_for(algo, run))
            card = summary["card"]
            assert card["args"]["imitation"] == "l1" and card["args"]["shortfall_weight"] == 2.0
            if not priced:
                assert kinds and set(kinds) == {("l1", 2.0, 0.0)} and "receiver_prices" not in card, algo
                continue
            data = O.Data(args_for(algo, run), city)
            prices = O.receiver_prices(city, data.tensors["x"], torch.tensor(OfflineDataset.load(tiny[1]).actions))
            weight = 2.0 * prices["move"] / prices["trip"]
            assert 0 < weight and kinds and all(k == ("l1", 2.0, pytest.approx(weight)) for k in kinds), algo
            assert card["receiver_prices"] == pytest.approx({**prices, "surplus_weight": weight})
    with pytest.raises(ConfigError, match="imitation: Input should be 'ce' or 'l1'"):
        args_for("bc", _args(tmp_path, tiny, imitation="l2"))
    with pytest.raises(ConfigError, match="shortfall_weight weighs the vehicles of imitation: l1; imitation is ce"):
        args_for("iql", _args(tmp_path, tiny, shortfall_weight=1.0))
    with pytest.raises(ConfigError, match="surplus_price prices a receiving region's surplus against its shortfall: set shortfall_weight"):
        args_for("bc", _args(tmp_path, tiny, imitation="l1", surplus_price=True))
    with pytest.raises(ConfigError, match="shortfall_weight: Input should be a finite number"):  # inf x 0 would make every loss NaN
        args_for("bc", _args(tmp_path, tiny, imitation="l1", shortfall_weight=float("inf")))


@pytest.mark.parametrize("algo", ["bc", "iql"])
def test_offline_actor_time_reads_the_logged_time_values_and_evaluates_as_trained(tmp_path, tiny, algo):
    """actor_time offline: the minibatches carry the dataset's time values, the card says so, and the
    shipped file evaluates to the run's own final score; CQL's sampled actions cannot, so it refuses."""
    extra = {"critic_hidden": 8} if algo != "bc" else {}
    summary = ALGOS[algo].train(args_for(algo, _args(tmp_path, tiny, actor_time=True, **extra)))
    assert summary["card"]["time_context"] is True
    res = evaluate(str(tmp_path / "p.pt"), load_city(tiny[0]), episodes=2, seed=0)
    assert res["metrics"]["profit"]["mean"] == pytest.approx(summary["card"]["profit_mean"])
    data = O.Data(args_for(algo, _args(tmp_path, tiny)), load_city(tiny[0]))
    steps = data.tensors["ctx"][:, 2] * load_city(tiny[0]).horizon  # step fraction t / horizon -> t
    assert torch.allclose(steps, steps.round(), atol=1e-4) and steps.max() > 0
    with pytest.raises(ConfigError, match="actor_time is not read"):
        args_for("cql", _args(tmp_path, tiny, actor_time=True))


@pytest.mark.parametrize("algo", ["iql", "cql"])
def test_mlp_clone_is_the_start_of_iql_and_cql_and_ships_as_an_mlp(tmp_path, tiny, algo):
    """The MPC-Forecast and DTV recipe: BC with the MLP actor (all regions' features in), then IQL or
    CQL starting from that clone; each file is an MLP policy that evaluates to its card's score, and
    the improvement step starts from the clone's weights (its first loss is the clone's)."""
    from marl_amod.checkpoints import load_actor

    bc = ALGOS["bc"].train(args_for("bc", _args(tmp_path, tiny, actor="mlp", policy_out=str(tmp_path / "bc.pt"))))
    assert bc["card"]["actor"] == "mlp"
    extra = {"critic_hidden": 8, "bc_steps": 6, "n_actions": 2} if algo == "cql" else {"critic_hidden": 8, "beta": 0.0}
    args = _args(tmp_path, tiny, actor="mlp", init_actor=str(tmp_path / "bc.pt"), lr_actor=1e-12, run_dir=str(tmp_path / "r2"), **extra)
    card = ALGOS[algo].train(args_for(algo, args))["card"]
    city = load_city(tiny[0])
    clone, _ = load_actor(tmp_path / "bc.pt", city)
    shipped, shipped_card = load_actor(tmp_path / "p.pt", city)
    assert shipped_card["actor"] == "mlp" and type(shipped) is type(clone)
    # a learning rate of 1e-12 leaves the start where it was: the step began from the clone
    assert all(torch.allclose(shipped.state_dict()[k], v, atol=1e-6) for k, v in clone.state_dict().items())
    res = evaluate(str(tmp_path / "p.pt"), city, episodes=2, seed=0)
    assert res["metrics"]["profit"]["mean"] == pytest.approx(card["profit_mean"])


def test_keep_best_with_a_start_ships_the_start_unless_a_validation_beats_it(tmp_path, tiny, monkeypatch):
    """A conservative improvement step: with init_actor and keep best the start is validated first,
    so a run whose every later validation is worse ships its start unchanged."""
    from marl_amod.algos import common as C
    from marl_amod.checkpoints import load_actor

    ALGOS["bc"].train(args_for("bc", _args(tmp_path, tiny)))
    city = load_city(tiny[0])
    start, _ = load_actor(tmp_path / "p.pt", city)
    real, calls = C.evaluate_actor, []

    def scripted(actor, city_, episodes, seed, *rest):  # validations: the start 100, every later one 50
        out = real(actor, city_, episodes, seed, *rest)
        if seed == 1000:
            out["metrics"]["profit"]["mean"] = 100.0 if not calls else 50.0
            calls.append(seed)
        return out

    monkeypatch.setattr(C, "evaluate_actor", scripted)
    args = _args(tmp_path, tiny, init_actor=str(tmp_path / "p.pt"), keep="best", lr_actor=0.5, run_dir=str(tmp_path / "r2"),
                 policy_out=str(tmp_path / "q.pt"))  # fmt: skip
    card = ALGOS["bc"].train(args_for("bc", args))["card"]
    assert len(calls) == 3 and card["best_validation"] == 100.0  # the start, then updates 3 and 6
    shipped, _ = load_actor(tmp_path / "q.pt", city)
    assert all(torch.equal(shipped.state_dict()[k], v) for k, v in start.state_dict().items())
    last = torch.load(tmp_path / "r2" / "state.pt", weights_only=False)["actor"]
    assert any(not torch.equal(last[k], v) for k, v in start.state_dict().items())  # the updates did move it


def test_training_seeds_get_their_own_files_and_start_and_the_table_averages_them(tmp_path, tiny, monkeypatch):
    """benchmarks/offline_seeds.py: seed s writes apart and starts from its start's seed-s run where
    it exists (else the config's start); offline_table.py reports mean +- std over the seeds."""
    import offline_seeds
    import offline_table

    monkeypatch.setattr(offline_seeds, "SEED_DIR", tmp_path / "seeds")
    args = args_for("cql", _args(tmp_path, tiny, init_actor="policies/bc_x.pt", policy_out="policies/cql_x.pt"))
    assert offline_seeds.seed_args(args, 0) is args  # the config's own seed: the shipped policy
    one = offline_seeds.seed_args(args, 1)
    assert one.seed == 1 and one.policy_out == str(tmp_path / "seeds" / "cql_x_s1.pt") and one.init_actor == "policies/bc_x.pt"
    (tmp_path / "seeds").mkdir()
    (tmp_path / "seeds" / "bc_x_s2.pt").write_bytes(b"")
    assert offline_seeds.seed_args(args, 2).init_actor == str(tmp_path / "seeds" / "bc_x_s2.pt")
    assert offline_seeds.comparable(one) == offline_seeds.comparable(args)  # the same experiment
    # a run recorded before an option existed (absent) or with it spelled out at its default is the
    # same experiment; a non-default value is not
    recorded = {**args.model_dump(mode="json"), "readout": "none"}
    del recorded["selection"]
    assert offline_seeds.essential(type(args), recorded) == offline_seeds.comparable(args)
    assert offline_seeds.essential(type(args), {**recorded, "readout": "mean"}) != offline_seeds.comparable(args)
    # a start retrained since is told by content, not by file times
    start = tmp_path / "start.pt"
    start.write_bytes(b"one")
    from marl_amod.files import file_sha256

    card = {"start_sha256": file_sha256(start)}
    assert not offline_seeds.started_elsewhere(card, str(start)) and not offline_seeds.started_elsewhere({}, str(start))
    start.write_bytes(b"two")
    assert offline_seeds.started_elsewhere(card, str(start))
    cell = {"seeds": {str(s): {"profit_mean": p, "profit_std": 10.0} for s, p in enumerate((100.0, 110.0, 120.0))}}
    refs = {"equal-distribution": {"mean": 100.0}, "mpc-oracle": {"mean": 200.0}}
    stats = offline_table.over_seeds(cell, 100.0, refs)
    assert stats["n"] == 3 and stats["mean"] == pytest.approx(110.0) and stats["std"] == pytest.approx(10.0)
    assert stats["vs_behaviour_pct"] == pytest.approx(10.0) and stats["normalised"] == pytest.approx(10.0)
    assert offline_table.over_seeds({"seeds": {"0": cell["seeds"]["0"]}}, 100.0, refs) is None


def test_the_table_finds_each_cell_under_the_actor_its_file_names(tmp_path):
    """offline_table.cell_name: a cell's policy is bc_gnn_... or bc_mlp_... (the card's actor); two are an error."""
    import offline_table

    assert offline_table.cell_name(tmp_path, "bc", "nyc_brooklyn", "dtv") is None
    (tmp_path / "bc_mlp_nyc_brooklyn_dtv.json").write_text("{}")
    assert offline_table.cell_name(tmp_path, "bc", "nyc_brooklyn", "dtv") == "bc_mlp_nyc_brooklyn_dtv"
    assert offline_table.cell_name(tmp_path, "cql", "nyc_brooklyn", "dtv") is None
    (tmp_path / "bc_gnn_nyc_brooklyn_dtv.json").write_text("{}")
    with pytest.raises(ConfigError, match="two policies"):
        offline_table.cell_name(tmp_path, "bc", "nyc_brooklyn", "dtv")


def test_the_paired_rule_averages_a_recipes_seeds_per_episode_and_refuses_the_report_seeds():
    """benchmarks/offline_paired.py: the docs' selection test (margin and two standard errors of the
    paired mean); a recipe against one file, or against another recipe seed by seed."""
    import offline_paired

    ref = np.array([[100.0, 200.0, 300.0, 400.0]])
    recipe = ref + np.array([[150.0, 250.0, 150.0, 250.0], [50.0, -50.0, 50.0, -50.0]])  # per episode +100, +100, ...
    t = offline_paired.compare(recipe, ref, margin=100.0)
    assert t["diff"] == pytest.approx(100.0) and t["se"] == pytest.approx(0.0) and t["passes"] and t["above"] == 4
    assert t["per_seed"] == [pytest.approx(200.0), pytest.approx(0.0)]
    assert not offline_paired.compare(recipe, ref, margin=100.5)["passes"]
    paired = offline_paired.compare(recipe, recipe - 10.0, margin=10.0)  # seed s against seed s
    assert paired["diff"] == pytest.approx(10.0) and paired["per_seed"] == [pytest.approx(10.0)] * 2
    with pytest.raises(SystemExit, match="pairs with one of 1 or 2"):
        offline_paired.compare(recipe, np.zeros((3, 4)), margin=0.0)
    with pytest.raises(SystemExit, match="report seeds"):
        offline_paired.profits("inf", "nyc_brooklyn", 0, 10, {})


def test_the_paired_cache_is_kept_per_scenario(monkeypatch, tmp_path):
    """benchmarks/offline_paired.py resumes from ``--out``: a policy's episodes on one scenario are
    not read back as its episodes on another."""
    import offline_paired

    import marl_amod.evaluation

    calls = []

    def fake(policy, scenario, episodes, seed):
        calls.append(scenario)
        return {"per_episode": [{"profit": 1.0 if scenario == "nyc_brooklyn" else 2.0}] * episodes}

    monkeypatch.setattr(marl_amod.evaluation, "evaluate", fake)
    cache: dict = {}
    assert offline_paired.profits("inf", "nyc_brooklyn", 7000, 2, cache) == [1.0, 1.0]
    assert offline_paired.profits("inf", "nyc_brooklyn", 7000, 2, cache) == [1.0, 1.0]  # resumed: not run again
    assert offline_paired.profits("inf", "san_francisco", 7000, 2, cache) == [2.0, 2.0]
    assert calls == ["nyc_brooklyn", "san_francisco"]
    monkeypatch.setattr(sys, "argv", ["offline_paired.py", "--sets", "7000", "--out", str(tmp_path / "score.json"), "--reference", "ref=inf",
                                      "--recipe", "new=equal-distribution", "--against", "new:reference"])  # fmt: skip
    with pytest.raises(SystemExit, match=r"--against 'new:reference': give RECIPE:REFERENCE, two of the names \['ref', 'new'\]"):
        offline_paired.main()
    assert calls == ["nyc_brooklyn", "san_francisco"]  # refused before any episode is scored


def test_sink_margin_keeps_a_receiving_regions_target_under_the_envs_floor():
    """The env plays floor(w_i M): a clone's share a little below a planner's exact target loses a
    vehicle at the region that receives; the margin centres that target inside the floor's bin,
    taking it from the regions that send (whose lower target costs nothing)."""
    from marl_amod.coordinator.rebalance import floor_targets

    idle = torch.tensor([[4.0, 4.0, 2.0], [0.0, 0.0, 0.0]])  # M = 10; the second step has no idle vehicle
    x = torch.zeros(2, 3, 13)
    x[..., 0] = idle * 0.01  # the node features hold idle / 100
    logged = torch.tensor([[2.0, 3.0, 5.0], [1.0, 1.0, 2.0]]) / 16  # targets u / 2^k: region 2 receives 3
    shares = O.sink_margin_targets(x, logged, 0.5)
    assert torch.allclose(shares.sum(-1), torch.ones(2))
    assert torch.allclose(shares[1], torch.tensor([0.25, 0.25, 0.5]))  # no idle vehicle: the logged share
    low = lambda y: floor_targets(y[0].double().numpy() + [0.03, 0.0, -0.03], 10)  # noqa: E731 - a clone 0.3 vehicle low at the receiver
    assert low(logged / logged.sum(-1, keepdim=True))[2] == 4  # without the margin the receiver misses one
    assert low(shares)[2] == 5 and (low(shares)[:2] <= torch.tensor([2, 3]).numpy()).all()


def test_a_policy_trained_with_a_longer_lookahead_evaluates_with_it(tmp_path, tiny):
    """collect --lookahead L logs F = 1 + 2L features, BC trains with lookahead L, and the card
    carries L so `marl-amod evaluate` scores the file as the run did (not with the default 6)."""
    scenario = tiny[0]
    data = tmp_path / "la.npz"
    args = ["collect", "--scenario", scenario, "--policy", "prop", "--episodes", "2", "--lookahead", "9",
            "--output", str(data), "--eval-episodes", "0"]  # fmt: skip
    result = CliRunner().invoke(app, args)
    assert result.exit_code == 0, result.output
    from marl_amod.datasets import OfflineDataset

    assert OfflineDataset.load(data).meta["n_features"] == 19
    summary = ALGOS["bc"].train(args_for("bc", _args(tmp_path, (scenario, str(data)), lookahead=9, actor="mlp")))
    assert summary["card"]["lookahead"] == 9 and summary["card"]["n_features"] == 19
    out = tmp_path / "eval.json"
    result = CliRunner().invoke(app, ["evaluate", "--scenario", scenario, "--policy", str(tmp_path / "p.pt"), "--episodes", "2", "--output", str(out)])
    assert result.exit_code == 0, result.output
    assert json.loads(out.read_text())["metrics"]["profit"]["mean"] == pytest.approx(summary["card"]["profit_mean"])


def test_a_standardised_mlp_reads_its_inputs_in_any_units():
    """With standardise the actor's function does not depend on the units of its inputs: the same
    weights fitted to rescaled and shifted data give the same concentrations on the rescaled inputs."""
    from marl_amod.models import MLPActor

    x = torch.rand(64, 3, 4) * torch.tensor([0.01, 1.0, 40.0, 3.0])
    scale, shift = torch.tensor([100.0, 0.5, 0.01, 7.0]), torch.tensor([1.0, -2.0, 0.0, 5.0])
    actors = []
    for data in (x, x * scale + shift):
        torch.manual_seed(0)
        actor = MLPActor(4, 16, 3, standardise=True)
        actor.fit_inputs(data)
        actors.append(actor)
    with torch.no_grad():
        assert torch.allclose(actors[0](x[:5]), actors[1](x[:5] * scale + shift), rtol=1e-4, atol=1e-5)
        torch.manual_seed(0)
        plain = MLPActor(4, 16, 3)
        assert not torch.allclose(plain(x[:5]), plain(x[:5] * scale + shift), rtol=1e-2)


def test_standardise_inputs_ships_the_datasets_statistics_and_iql_keeps_its_starts(tmp_path, tiny):
    from marl_amod.checkpoints import load_actor

    city = load_city(tiny[0])
    bc = ALGOS["bc"].train(args_for("bc", _args(tmp_path, tiny, actor="mlp", standardise_inputs=True, policy_out=str(tmp_path / "bc.pt"))))
    assert bc["card"]["standardise_inputs"] is True
    clone, _ = load_actor(tmp_path / "bc.pt", city)
    x = O.Data(args_for("bc", _args(tmp_path, tiny)), city).tensors["x"].flatten(1)
    assert torch.allclose(clone.input_mean, x.mean(0)) and torch.allclose(clone.input_std, x.std(0).clamp_min(1e-3))
    res = evaluate(str(tmp_path / "bc.pt"), city, episodes=2, seed=0)
    assert res["metrics"]["profit"]["mean"] == pytest.approx(bc["card"]["profit_mean"])
    blob = torch.load(tmp_path / "bc.pt", map_location="cpu", weights_only=True)
    blob["state_dict"]["input_mean"] += 1.0  # the start's statistics, told apart from the (same) dataset's
    torch.save(blob, tmp_path / "start.pt")
    start = {"actor": "mlp", "init_actor": str(tmp_path / "start.pt"), "critic_hidden": 8, "beta": 0.0, "run_dir": str(tmp_path / "r2")}
    ALGOS["iql"].train(args_for("iql", _args(tmp_path, tiny, standardise_inputs=True, lr_actor=1e-12, **start)))
    shipped, _ = load_actor(tmp_path / "p.pt", city)
    assert torch.equal(shipped.input_mean, clone.input_mean + 1.0) and torch.equal(shipped.input_std, clone.input_std)
    with pytest.raises(DataError, match="standardise_inputs"):
        ALGOS["iql"].train(args_for("iql", _args(tmp_path, tiny, **start)))
    with pytest.raises(ConfigError, match="standardise_inputs"):
        args_for("bc", _args(tmp_path, tiny, standardise_inputs=True))  # the GNN actor has no such option


def test_standardise_inputs_covers_the_time_context_of_an_actor_time_mlp(tmp_path, tiny):
    """actor_time appends the time context to every node: the statistics are of those inputs too."""
    from marl_amod.checkpoints import load_actor

    city = load_city(tiny[0])
    args = args_for("bc", _args(tmp_path, tiny, actor="mlp", standardise_inputs=True, actor_time=True, policy_out=str(tmp_path / "bc.pt")))
    ALGOS["bc"].train(args)
    clone, _ = load_actor(tmp_path / "bc.pt", city)
    t = O.Data(args, city).tensors
    x = C.with_time(t["x"], t["ctx"], True).flatten(1)
    assert torch.allclose(clone.input_mean, x.mean(0)) and torch.allclose(clone.input_std, x.std(0).clamp_min(1e-3))


def test_an_online_run_refuses_standardise_inputs_with_nothing_to_fit_them_from(tmp_path, tiny):
    """Online, the statistics come only from a start (init_actor); without one they would stay 0 and 1."""
    online = {"scenario": tiny[0], "actor": "mlp", "standardise_inputs": True, "run_dir": str(tmp_path / "r")}
    with pytest.raises(ConfigError, match="init_actor"):
        args_for("a2c", online)
    assert args_for("a2c", {**online, "init_actor": str(tmp_path / "bc.pt")}).standardise_inputs
    assert args_for("bc", _args(tmp_path, tiny, actor="mlp", standardise_inputs=True)).standardise_inputs


def test_the_docs_page_holds_the_tables_as_generated_and_the_figure_draws_every_cell(tmp_path):
    """docs/offline/table.md is offline_table.py's rendering of table.json, index.md holds it
    verbatim (a regenerated table not pasted there fails), and the figure has a bar per cell."""
    import offline_table

    folder = Path(__file__).resolve().parent.parent / "docs" / "offline"
    table = json.loads((folder / "table.json").read_text())
    md = offline_table.markdown(table)
    md += f"\n{extra}" if (extra := offline_table.seeds_markdown(table)) else ""
    assert (folder / "table.md").read_text() == md
    assert md.strip() in (folder / "index.md").read_text()
    from marl_amod.plots import score_bars_figure

    cells = sum(key in r for r in table["rows"] for key in ("behaviour", *offline_table.ALGOS))
    ax = score_bars_figure(offline_table.groups(table)).axes[0]
    assert len(ax.patches) == cells and [t.get_text() for t in ax.get_xticklabels()][0] == table["rows"][0]["dataset"].upper()
    assert offline_table.figure(table, tmp_path / "t.png").read_bytes()[:4] == b"\x89PNG"


def test_iql_learns_from_a_mixture_and_its_card_scores_each_behaviour(tmp_path, tiny):
    """MPC's own episodes beside its noisy ones is the MPC-Forecast row's remaining experiment: a
    mixture trains like any dataset, and the policy's card keeps each part's behaviour score."""
    from marl_amod.datasets import collect, mix, mix_cards, write_card
    from marl_amod.policies import make_policy

    city = load_city(tiny[0])
    noisy = collect(city, make_policy("prop", city), episodes=2, seed=1, noise=0.05)
    path = noisy.save(tmp_path / "noisy.npz")
    write_card(path, noisy, city, make_policy("prop", city), eval_episodes=1, eval_seed=0)
    mixed = mix([OfflineDataset.load(tiny[1]), noisy])
    out = mixed.save(tmp_path / "mixed.npz")
    mix_cards(out, mixed, [tiny[1], path])
    ALGOS["iql"].train(args_for("iql", _args(tmp_path, (tiny[0], str(out)), critic_hidden=8)))
    card = json.loads((tmp_path / "p.json").read_text())
    assert card["dataset"]["policy"] == "prop & prop+noise0.05" and card["dataset"]["episodes"] == 6
    assert [s["behaviour"] for s in card["dataset"]["behaviour_scores"]] == ["prop", "prop+noise0.05"]
    assert "behaviour_score" not in card["dataset"] and np.isfinite(O.card_normalised(card))


def test_the_fqe_page_is_its_benchmarks_rendering_and_index_holds_its_choices():
    """docs/offline/fqe.md is offline_fqe.py's page of fqe.json, and index.md quotes its choice table
    row for row (an FQE study rerun and not pasted there fails)."""
    import offline_fqe

    folder = Path(__file__).resolve().parent.parent / "docs" / "offline"
    md = offline_fqe.page(json.loads((folder / "fqe.json").read_text()))
    assert (folder / "fqe.md").read_text() == md
    choices = [line for line in md.splitlines() if line.startswith("| ") and line.endswith(" |") and line.count("|") == 6 and "k |" in line and not line.startswith("| dataset")]
    assert len(choices) == 5 and all(line in (folder / "index.md").read_text() for line in choices)


def test_the_time_limit_stops_an_offline_run_at_the_update_that_runs_out(tmp_path, tiny):
    """Checked every update (not only at validations), and that update is validated and saved, so the
    actor it ended with competes; a limit already passed stops after the first update."""
    summary = ALGOS["bc"].train(args_for("bc", _args(tmp_path, tiny, updates=10_000, eval_every=5_000, time_limit_s=1e-9)))
    card = summary["card"]
    assert card["updates"] == 1 and card["best_validation"] is not None
    assert torch.load(tmp_path / "run" / "state.pt", weights_only=False)["episode"] == 1
