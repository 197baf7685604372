"""A2C and SAC on the batched path (num_envs > 1): the same episodes, the same networks, whole runs."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch
import yaml

from marl_amod.algos.rollout import BatchRollout, Rollout, train_seed
from marl_amod.errors import ConfigError
from marl_amod.scenario import load_city


@pytest.fixture
def tiny_yaml(tmp_path: Path) -> str:
    path = tmp_path / "tiny.yaml"
    path.write_text(yaml.safe_dump({"name": "tiny", "source": "synthetic", "rows": 3, "cols": 3, "horizon": 6, "vehicles_per_region": 5}))
    return str(path)


@pytest.mark.parametrize("mode", ["centralised", "decentralised"])
def test_batch_rollout_gives_each_episode_the_single_rollouts_episode(tiny_yaml, mode):
    """Episode b of a batch started at training episode k is Rollout's training episode k + b, step for step."""
    city = load_city(tiny_yaml)
    batch, first = BatchRollout(city, mode, num_envs=3), 5
    singles = [Rollout(city, mode) for _ in range(3)]
    obs = batch.reset(0, first)
    one = [r.reset(train_seed(0, first + b)) for b, r in enumerate(singles)]
    rng = np.random.default_rng(0)
    steps = 0
    while True:
        for b in range(3):
            torch.testing.assert_close(obs.x[b], one[b].x, rtol=0, atol=0)
            torch.testing.assert_close(obs.ctx[b], one[b].ctx, rtol=0, atol=0)
            if mode == "decentralised":
                for field in ("own", "nbrs", "mask"):
                    torch.testing.assert_close(getattr(obs, field)[b], getattr(one[b], field), rtol=0, atol=0)
        if batch.done:
            break
        w = rng.gamma(1.0, size=(3, city.n_regions))
        obs, rewards = batch.step(w)
        stepped = [r.step(w[b]) for b, r in enumerate(singles)]
        one = [o for o, _ in stepped]
        np.testing.assert_array_equal(rewards, [r for _, r in stepped])
        assert batch.done == singles[0].done
        steps += 1
    assert steps == city.horizon - 1


@pytest.mark.parametrize("mode", ["centralised", "decentralised"])
@pytest.mark.parametrize("algo", ["a2c", "sac"])
def test_batched_runs_train_validate_and_write_a_card(tmp_path, tiny_yaml, algo, mode):
    from marl_amod.algos.registry import ALGOS

    entry = ALGOS[algo]
    extra = {"episodes_per_update": 4} if algo == "a2c" else {"batch_size": 8, "warmup_steps": 8, "auto_entropy": True, "updates_per_step": 0.5}
    args = entry.args(scenario=tiny_yaml, mode=mode, num_envs=4, critic_time=True, episodes=8, eval_every=4, eval_episodes=1,
                      final_eval_episodes=1, hidden=8, run_dir=str(tmp_path / "run"), policy_out=str(tmp_path / "p.pt"), **extra)
    summary = entry.train(args)
    card = summary["card"]
    assert card["episodes_trained"] == 8 and card["args"]["num_envs"] == 4 and np.isfinite(card["profit_mean"])
    state = torch.load(tmp_path / "run" / "state.pt", map_location="cpu", weights_only=False)
    critic = state["critic"]
    first = next(v for k, v in critic.items() if k.endswith(("lin.weight", "lin_l.weight", "conv.weight")))
    assert first.shape[-1] == 13 + 3 + (1 if algo == "sac" else 0)  # features + time context (+ the action for Q)
    if algo == "sac":
        assert first.shape[0] == 2 and "q1.value.out.weight" not in critic  # the twin critics' weights stacked
        # 8 episodes x 5 steps, half an update per transition after the warm-up
        assert state["n_steps"] == 40 and state["replay"]["size"] == 40
        evals = [line for line in (tmp_path / "run" / "log.csv").read_text().splitlines() if ",eval/profit," in line]
        assert [line.split(",")[0] for line in evals] == ["4", "8"]


@pytest.mark.parametrize("algo", ["a2c", "sac"])
def test_batched_resume_continues_exactly_as_an_uninterrupted_run(tmp_path, tiny_yaml, algo):
    from marl_amod.algos.registry import ALGOS

    entry = ALGOS[algo]
    extra = {"episodes_per_update": 2} if algo == "a2c" else {"batch_size": 8, "warmup_steps": 8, "auto_entropy": True}
    kw = {"eval_every": 2, "eval_episodes": 1, "final_eval_episodes": 1, "hidden": 8, "scenario": tiny_yaml, "num_envs": 2, **extra}
    entry.train(entry.args(**kw, episodes=4, run_dir=str(tmp_path / "full"), policy_out=str(tmp_path / "full.pt")))
    entry.train(entry.args(**kw, episodes=2, run_dir=str(tmp_path / "half"), policy_out=""))
    entry.train(entry.args(**kw, episodes=4, run_dir=str(tmp_path / "half"), policy_out=str(tmp_path / "resumed.pt")),
                resume=str(tmp_path / "half" / "state.pt"))
    full, resumed = (torch.load(tmp_path / f, map_location="cpu", weights_only=False)["state_dict"] for f in ("full.pt", "resumed.pt"))
    for k in full:
        torch.testing.assert_close(full[k], resumed[k], rtol=0, atol=0)


def test_replay_adds_rows_around_the_ring():
    from marl_amod.algos.sac import Replay

    buf = Replay(5)
    buf.add(x=torch.tensor([0.0]), done=torch.tensor(0.0))
    buf.add(3, x=torch.tensor([[1.0], [2.0], [3.0]]), done=torch.tensor(1.0))
    buf.add(2, x=torch.tensor([[4.0], [5.0]]), done=torch.tensor(0.0))
    assert buf.size == 5 and buf.ptr == 1
    assert buf.data["x"][:, 0].tolist() == [5.0, 1.0, 2.0, 3.0, 4.0]
    assert buf.data["done"].tolist() == [0.0, 1.0, 1.0, 1.0, 0.0]


def test_a2c_batches_must_fill_whole_updates(tiny_yaml):
    from marl_amod.algos.registry import args_for

    with pytest.raises(ConfigError, match="multiple of num_envs"):
        args_for("a2c", {"scenario": tiny_yaml, "num_envs": 4, "episodes_per_update": 6})


def test_replay_sample_is_one_gather_whose_fields_are_the_stored_rows():
    from marl_amod.algos.sac import Replay

    buf = Replay(10)
    buf.add(6, x=torch.arange(6 * 4, dtype=torch.float32).view(6, 2, 2), reward=torch.arange(6.0), done=torch.tensor(0.0))
    idx = torch.randint(0, 6, (5,), generator=torch.Generator().manual_seed(1))
    b = buf.sample(5, torch.Generator().manual_seed(1))
    assert b["x"].shape == (5, 2, 2) and b["reward"].shape == (5,)
    torch.testing.assert_close(b["x"], torch.arange(24, dtype=torch.float32).view(6, 2, 2)[idx], rtol=0, atol=0)
    torch.testing.assert_close(b["reward"], idx.float(), rtol=0, atol=0)
    restored = Replay(10)
    restored.load_state_dict(buf.state_dict())
    torch.testing.assert_close(restored.storage, buf.storage, rtol=0, atol=0)


def test_a_state_saved_with_two_critics_resumes_with_the_stacked_critics():
    """Training states written before the critics were stacked: critics, targets and Adam moments are
    stacked, so the next update is the one the two critics would have made."""
    import copy

    from marl_amod.algos.sac import stack_twin_state
    from marl_amod.models import TwinQ
    from marl_amod.models.dense import DenseGraph
    from marl_amod.models.gnn import StackedTwinQ
    from marl_amod.scenario import grid_city

    city = grid_city(3, 3, seed=0)
    graph = DenseGraph(torch.tensor(city.edge_index), city.n_regions)
    torch.manual_seed(0)
    x, action = torch.rand(5, 9, 16), torch.rand(5, 9)
    twin = TwinQ(16, 8, "gcn")
    target = copy.deepcopy(twin)
    opt = torch.optim.Adam(twin.parameters(), lr=1e-2)

    def step(critic: torch.nn.Module, optimiser: torch.optim.Optimizer) -> None:
        optimiser.zero_grad()
        q1, q2 = critic(x, graph, action)
        ((q1 - 1).square().sum() + (q2 + 1).square().sum()).backward()
        optimiser.step()

    for _ in range(3):
        step(twin, opt)
    state = {"critic": twin.state_dict(), "critic_targ": target.state_dict(), "opt_c": opt.state_dict(), "episode": 3}
    converted = stack_twin_state(copy.deepcopy(state), TwinQ(16, 8, "gcn"))
    stacked, stacked_target = StackedTwinQ(TwinQ(16, 8, "gcn")), StackedTwinQ(TwinQ(16, 8, "gcn"))
    stacked.load_state_dict(converted["critic"])
    stacked_target.load_state_dict(converted["critic_targ"])
    opt_stacked = torch.optim.Adam(stacked.parameters(), lr=1e-2, fused=True)
    opt_stacked.load_state_dict(converted["opt_c"])
    step(twin, opt)
    step(stacked, opt_stacked)
    for net, ref in ((stacked, twin), (stacked_target, target)):
        for q, r in zip(net(x, graph, action), ref(x, graph, action), strict=True):
            torch.testing.assert_close(q, r, atol=1e-5, rtol=1e-5)


def test_a2c_actor_time_feeds_the_actor_the_time_context_in_training_and_evaluation(tmp_path, tiny_yaml):
    """actor_time: the actor's first layer reads F + 3 columns, the card says so, and evaluating the
    shipped file reproduces the run's own final evaluation (the same input at every step)."""
    from marl_amod.algos import a2c
    from marl_amod.evaluation import evaluate

    args = a2c.Args(scenario=tiny_yaml, conv="sage", actor_time=True, num_envs=2, episodes_per_update=2, episodes=4, eval_every=2,
                    eval_episodes=1, final_eval_episodes=2, hidden=8, run_dir=str(tmp_path / "run"), policy_out=str(tmp_path / "p.pt"))
    card = a2c.train(args)["card"]
    assert card["time_context"] is True
    state = torch.load(tmp_path / "p.pt", map_location="cpu", weights_only=False)["state_dict"]
    assert state["trunk.conv.lin_l.weight"].shape == (16, 13 + 3)
    shipped = evaluate(str(tmp_path / "p.pt"), load_city(tiny_yaml), episodes=2, seed=0)["metrics"]["profit"]["mean"]
    assert shipped == pytest.approx(card["profit_mean"])


def test_actor_time_is_refused_where_the_actor_cannot_read_it(tiny_yaml):
    from marl_amod.algos.registry import args_for

    with pytest.raises(ConfigError, match="actor_time is not read"):
        args_for("a2c", {"scenario": tiny_yaml, "mode": "decentralised", "actor_time": True})
    with pytest.raises(ConfigError, match="actor_time is not read"):
        args_for("sac", {"scenario": tiny_yaml, "actor_time": True})


def test_a2c_action_concentration_multiplies_the_sampled_concentrations_only(tmp_path, tiny_yaml, monkeypatch):
    """The first update's samples come from k * alpha of the same untrained actor (same seed)."""
    from marl_amod.algos import a2c

    seen: list[torch.Tensor] = []
    real_act = a2c.act

    def recording_act(alpha, mode):
        seen.append(alpha.detach().clone())
        return real_act(alpha, mode)

    monkeypatch.setattr(a2c, "act", recording_act)
    firsts = {}
    for k in (1.0, 7.0):
        seen.clear()
        a2c.train(a2c.Args(scenario=tiny_yaml, num_envs=2, episodes_per_update=2, episodes=2, eval_every=2, eval_episodes=1,
                           final_eval_episodes=1, hidden=8, action_concentration=k, run_dir=str(tmp_path / f"r{k}")))
        firsts[k] = seen[0]
    torch.testing.assert_close(firsts[7.0], 7.0 * firsts[1.0])
