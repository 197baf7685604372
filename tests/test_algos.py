"""A2C and SAC end to end on a 3x3 grid, checkpoints, configs and the CLI."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch
import yaml

from marl_amod.checkpoints import load_policy, save_policy
from marl_amod.errors import ConfigError, DataError
from marl_amod.evaluation import evaluate
from marl_amod.models import build_actor
from marl_amod.scenario import load_city
from marl_amod.system import FleetSystem
from tests.conftest import ctrl_c_after


@pytest.fixture
def tiny_yaml(tmp_path: Path) -> str:
    """The 3x3, 6-step grid as a scenario file, so configs can name it."""
    path = tmp_path / "tiny.yaml"
    path.write_text(yaml.safe_dump({"name": "tiny", "source": "synthetic", "rows": 3, "cols": 3, "horizon": 6, "vehicles_per_region": 5}))
    return str(path)


def _common(tmp_path: Path, scenario: str, **kw) -> dict:
    return {"scenario": scenario, "eval_every": 4, "eval_episodes": 2, "final_eval_episodes": 2, "hidden": 8,
            "run_dir": str(tmp_path / "run"), "policy_out": str(tmp_path / "policies" / "p.pt"), **kw}


@pytest.mark.parametrize("mode", ["centralised", "decentralised"])
def test_a2c_tiny_run_writes_checkpoint_logs_and_card(tmp_path, tiny_yaml, mode):
    from marl_amod.algos import a2c

    summary = a2c.train(a2c.Args(**_common(tmp_path, tiny_yaml, mode=mode, episodes=8, episodes_per_update=2)))
    pt = tmp_path / "policies" / "p.pt"
    assert pt.is_file() and pt.with_suffix(".json").is_file() and pt.with_suffix(".md").is_file()
    card = json.loads(pt.with_suffix(".json").read_text())
    assert card["mode"] == mode and card["algorithm"] == "a2c" and card["episodes_trained"] == 8
    assert card["env_version"] == "v0"  # a card says which env version its score is on
    assert np.isfinite(card["profit_mean"]) and card["profit_mean"] == summary["card"]["profit_mean"]
    log = (tmp_path / "run" / "log.csv").read_text()
    assert "eval/profit" in log and "loss/policy" in log
    assert (tmp_path / "run" / "state.pt").is_file()
    assert any(p.name.startswith("events.out.tfevents") for p in (tmp_path / "run").iterdir())
    # the policy file evaluates through the same path as `marl-amod evaluate --policy x.pt`
    res = evaluate(str(pt), load_city(tiny_yaml), episodes=2, seed=0)
    assert res["metrics"]["profit"]["mean"] == pytest.approx(card["profit_mean"])


@pytest.mark.parametrize("mode", ["centralised", "decentralised"])
def test_sac_tiny_run_updates_and_writes_checkpoint(tmp_path, tiny_yaml, mode):
    from marl_amod.algos import sac

    summary = sac.train(sac.Args(**_common(tmp_path, tiny_yaml, mode=mode, episodes=4, batch_size=8, warmup_steps=8)))
    assert summary["card"]["algorithm"] == "sac" and summary["card"]["mode"] == mode
    assert "loss/q" in (tmp_path / "run" / "log.csv").read_text()
    assert (tmp_path / "policies" / "p.pt").is_file()


def test_sac_validates_its_warm_start_first(tmp_path, tiny_yaml, monkeypatch):
    """As A2C: a fine-tuned SAC run's first validation is of the actor it starts from, so the kept
    actor is never worse on the validation seeds than its start."""
    from marl_amod.algos import common as C
    from marl_amod.algos import sac

    sac.train(sac.Args(**_common(tmp_path, tiny_yaml, episodes=4, batch_size=8, warmup_steps=8)))
    start = tmp_path / "start.pt"
    for suffix in (".pt", ".json", ".md"):
        (tmp_path / "policies" / "p.pt").with_suffix(suffix).rename(start.with_suffix(suffix))
    validated, real = [], C.BestActor.validate

    def spy(self, actor, city, args):
        validated.append({k: v.clone() for k, v in actor.state_dict().items()})
        return real(self, actor, city, args)

    monkeypatch.setattr(C.BestActor, "validate", spy)
    sac.train(sac.Args(**_common(tmp_path, tiny_yaml, episodes=4, batch_size=8, warmup_steps=8, run_dir=str(tmp_path / "ft")), init_actor=str(start)))
    first = load_policy(start, load_city(tiny_yaml)).actor.state_dict()
    assert len(validated) >= 2 and all(torch.equal(validated[0][k], v) for k, v in first.items())


def test_a2c_init_actor_fine_tunes_from_the_given_actor(tmp_path, tiny_yaml):
    """A warm start begins at the given actor; with a vanishing learning rate it stays there
    (the start is validated, so it is what the run keeps), while a cold start does not."""
    from marl_amod.algos import a2c

    a2c.train(a2c.Args(**_common(tmp_path, tiny_yaml, episodes=4, episodes_per_update=2, seed=1)))
    start = tmp_path / "start.pt"
    for suffix in (".pt", ".json", ".md"):
        (tmp_path / "policies" / "p.pt").with_suffix(suffix).rename(start.with_suffix(suffix))
    city = load_city(tiny_yaml)
    init = load_policy(start, city).actor.state_dict()
    tuned_args = _common(tmp_path, tiny_yaml, episodes=4, episodes_per_update=2, seed=2, lr_actor=1e-12, run_dir=str(tmp_path / "ft"))
    a2c.train(a2c.Args(**tuned_args, init_actor=str(start)))
    tuned = load_policy(tmp_path / "policies" / "p.pt", city).actor.state_dict()
    assert all(torch.allclose(init[k], tuned[k], atol=1e-6) for k in init)
    a2c.train(a2c.Args(**{**tuned_args, "run_dir": str(tmp_path / "cold")}))
    cold = load_policy(tmp_path / "policies" / "p.pt", city).actor.state_dict()
    assert not all(torch.allclose(init[k], cold[k], atol=1e-6) for k in init)


def test_kl_to_is_zero_at_the_start_and_positive_away_from_it():
    from marl_amod.algos.a2c import kl_to

    alpha = torch.tensor([[1.0, 2.0, 3.0]])
    for mode in ("centralised", "decentralised"):
        assert kl_to(alpha, alpha, mode).item() == pytest.approx(0.0, abs=1e-6)
        assert kl_to(alpha, alpha.flip(-1), mode).item() > 0.1
    # scaling both concentrations keeps the Dirichlet mean but makes a deviation cost more
    assert kl_to(10 * alpha, 10 * alpha.flip(-1), "centralised") > kl_to(alpha, alpha.flip(-1), "centralised")


def test_a2c_kl_penalty_keeps_a_fine_tune_near_its_start(tmp_path, tiny_yaml):
    """Same seed, same fast actor step: with kl_coef the logged KL to the start ends smaller."""
    from marl_amod.algos import a2c
    from marl_amod.algos.common import read_curve
    from marl_amod.algos.registry import args_for

    a2c.train(a2c.Args(**_common(tmp_path, tiny_yaml, episodes=4, episodes_per_update=2, seed=1)))
    start = str(tmp_path / "policies" / "p.pt")
    kl = {}
    for coef in (0.0, 30.0):
        run = str(tmp_path / f"kl{coef}")
        args = _common(tmp_path, tiny_yaml, episodes=12, episodes_per_update=2, seed=2, lr_actor=3e-2, init_actor=start,
                       kl_coef=coef, action_concentration=5.0, run_dir=run, policy_out="")  # fmt: skip
        a2c.train(a2c.Args(**args))
        kl[coef] = read_curve(run, "loss/kl_start")[1]
    assert kl[0.0][0] == kl[30.0][0]  # the first batch is drawn at the start by both
    assert kl[30.0][-1] < 0.2 * kl[0.0][-1]
    with pytest.raises(ConfigError, match="init_actor"):
        args_for("a2c", {"scenario": tiny_yaml, "kl_coef": 1.0})


def test_a2c_resume_continues_from_saved_episode(tmp_path, tiny_yaml):
    from marl_amod.algos import a2c

    a2c.train(a2c.Args(**_common(tmp_path, tiny_yaml, episodes=4, episodes_per_update=2)))
    summary = a2c.train(a2c.Args(**_common(tmp_path, tiny_yaml, episodes=8, episodes_per_update=2)), resume=str(tmp_path / "run" / "state.pt"))
    assert summary["card"]["episodes_trained"] == 8
    episodes = [int(line.split(",")[0]) for line in (tmp_path / "run" / "log.csv").read_text().splitlines()[1:]]
    assert episodes == sorted(episodes) and max(episodes) == 8  # resumed at 4, not restarted at 0
    wider = a2c.Args(**_common(tmp_path, tiny_yaml, episodes=12, episodes_per_update=2, hidden=16))  # not the run that saved it
    with pytest.raises(DataError, match="state.pt was saved by a run with other settings .hidden: 8 -> 16."):
        a2c.train(wider, resume=str(tmp_path / "run" / "state.pt"))
    for changed in ({"seed": 5}, {"scenario": f"{tiny_yaml}~hot1x3"}, {"lr_actor": 0.1}):  # any setting that makes another run
        with pytest.raises(DataError, match=f"{next(iter(changed))}: "):
            a2c.train(a2c.Args(**{**_common(tmp_path, tiny_yaml, episodes=12, episodes_per_update=2), **changed}), resume=str(tmp_path / "run" / "state.pt"))
    saved = torch.load(tmp_path / "run" / "state.pt", weights_only=False)
    del saved["args"]  # a state of before states held their args: the architecture is still checked by the weights
    torch.save(saved, tmp_path / "older.pt")
    with pytest.raises(DataError, match="older.pt was saved by a run whose actor differs"):
        a2c.train(wider, resume=str(tmp_path / "older.pt"))


@pytest.mark.parametrize("kind", ["gnn", "mlp", "cnn"])
def test_save_load_round_trip_gives_identical_actions(tmp_path, tiny_city, kind):
    torch.manual_seed(0)
    actor = build_actor(kind, tiny_city, 13, 8)
    card = {"scenario": tiny_city.name, "algorithm": "a2c", "mode": "centralised", "actor": kind, "conv": "gcn",
            "hidden": 8, "n_features": 13, "lookahead": 6, "seed": 0}
    path = save_policy(tmp_path / "x.pt", actor, card)
    assert path.stat().st_size < 2_000_000
    system = FleetSystem(tiny_city)
    system.reset(3)
    from marl_amod.checkpoints import ActorPolicy

    fresh, loaded = ActorPolicy(actor, tiny_city), load_policy(path, tiny_city)
    for _ in range(4):
        w = fresh.weights(system)
        np.testing.assert_array_equal(w, loaded.weights(system))
        np.testing.assert_array_equal(fresh.target(system), loaded.target(system))
        system.step(loaded.target(system))


def test_discounted_returns():
    from marl_amod.algos.a2c import discounted_returns

    np.testing.assert_array_equal(discounted_returns([1.0, 2.0, 4.0], 0.5), [3.0, 4.0, 4.0])
    # episodes in lockstep: (T, E), each column its own episode
    np.testing.assert_array_equal(discounted_returns([[1.0, 0.0], [2.0, 0.0], [4.0, 8.0]], 0.5), [[3.0, 2.0], [4.0, 4.0], [4.0, 8.0]])


TYPO_CASES = [
    ("marl_amod.algos.registry:load_train_config", "algo: a2c\nargs: {episodse: 10}\n", "episodse"),
    ("marl_amod.algos.registry:load_train_config", "algo: a2c\nargz: {}\n", "argz"),
    ("marl_amod.algos.registry:load_train_config", "algo: a2c\nargs: {gamma: fast}\n", "gamma"),
    ("marl_amod.comparison:load_compare_config", "scenario: synthetic\nepisodez: 3\n", "episodez"),
    (
        "marl_amod.comparison:load_compare_config",
        "scenario: synthetic\nruns: [{label: x, algo: sac, args: {hiden: 3, policy_out: a.pt}}]\n",
        "hiden",
    ),
]


def _loader(spec: str):
    import importlib

    module, name = spec.split(":")
    return getattr(importlib.import_module(module), name)


@pytest.mark.parametrize(("loader", "text", "culprit"), TYPO_CASES)
def test_config_typo_is_a_clear_error_naming_the_key(tmp_path, loader, text, culprit):
    bad = tmp_path / "bad.yaml"
    bad.write_text(text)
    with pytest.raises(ConfigError, match=culprit):
        _loader(loader)(bad)


@pytest.mark.parametrize("loader", ["marl_amod.algos.registry:load_train_config", "marl_amod.comparison:load_compare_config"])
def test_malformed_or_missing_config_is_a_config_error_naming_the_file(tmp_path, loader):
    load = _loader(loader)
    bad = tmp_path / "broken.yaml"
    bad.write_text("algo: a2c\nargs: {episodes: [1, 2\n")
    with pytest.raises(ConfigError, match="malformed YAML in .*broken.yaml"):
        load(bad)
    bad.write_text("- just\n- a list\n")
    with pytest.raises(ConfigError, match="expected a mapping"):
        load(bad)
    with pytest.raises(ConfigError, match="not found"):
        load(tmp_path / "missing.yaml")


def test_bundled_configs_validate():
    import yaml

    from marl_amod.algos.registry import load_train_config
    from marl_amod.comparison import load_compare_config
    from marl_amod.integrations.rllib import load_rllib_config  # pydantic only: no Ray needed

    root = Path(__file__).resolve().parent.parent / "configs"
    for path in root.rglob("*.yaml"):
        if path.parent.name == "compare":
            load_compare_config(path)
        elif yaml.safe_load(path.read_text()).get("algo") == "ppo":
            load_rllib_config(path)
        else:
            load_train_config(path)


def test_cli_train_and_compare_on_tiny_city(tmp_path, tiny_yaml):
    from typer.testing import CliRunner

    from marl_amod.cli import app

    args = _common(tmp_path, tiny_yaml, episodes=4, episodes_per_update=2)
    cfg = tmp_path / "run.yaml"
    cfg.write_text(yaml.safe_dump({"algo": "a2c", "args": args}))
    res = CliRunner().invoke(app, ["train", "--config", str(cfg)])
    assert res.exit_code == 0, res.output
    assert (tmp_path / "policies" / "p.pt").is_file()
    assert json.loads((tmp_path / "policies" / "p.json").read_text())["config"] == str(cfg)  # card says how to reproduce
    args.pop("scenario")
    cmp_cfg = tmp_path / "compare.yaml"
    cmp_cfg.write_text(yaml.safe_dump({"scenario": tiny_yaml, "episodes": 2, "baselines": ["equal-distribution"],
                                       "output": str(tmp_path / "cmp"), "runs": [{"label": "gnn", "algo": "a2c", "args": args}]}))
    res = CliRunner().invoke(app, ["compare", "--config", str(cmp_cfg)])
    assert res.exit_code == 0, res.output
    table = json.loads((tmp_path / "cmp" / "compare.json").read_text())
    assert [r["label"] for r in table["rows"]] == ["equal-distribution", "gnn"]
    for name in ("compare.md", "learning_curves.png", "profit.png", "served_by_region.png"):
        assert (tmp_path / "cmp" / name).is_file()


def test_decentralised_execution_through_env_equals_centralised_evaluation(tiny_city):
    """Each agent acting on its own PettingZoo observation reproduces the global policy's episode."""
    from marl_amod.algos.rollout import WEIGHT_DIVISOR
    from marl_amod.checkpoints import ActorPolicy
    from marl_amod.env.observations import split_local
    from marl_amod.env.parallel import AmodParallelEnv
    from marl_amod.models import LocalActor

    torch.manual_seed(0)
    actor = LocalActor(13, 8)
    env = AmodParallelEnv(tiny_city)
    obs, _ = env.reset(seed=5)
    total = 0.0
    while env.agents:
        actions = {}
        for agent in env.agents:  # one agent at a time, its own observation only
            own, _ctx, nbrs, mask = split_local(torch.as_tensor(obs[agent]))
            actions[agent] = np.array([actor.forward_local(own, nbrs, mask).item() / WEIGHT_DIVISOR], dtype=np.float32)
        obs, rewards, _, _, _ = env.step(actions)
        total += rewards["region_0"]
    system = FleetSystem(tiny_city)
    system.reset(5)
    policy = ActorPolicy(actor.eval(), tiny_city)
    central = 0.0
    while not system.done:
        central += system.step(policy.target(system)).reward
    assert total == pytest.approx(central)


# --------------------------------------------------------------------------------------------
# A new algorithm is one file + one registry line: a toy one, registered here only
# --------------------------------------------------------------------------------------------
def test_a_registered_toy_algorithm_trains_evaluates_and_compares_through_the_cli(tmp_path, tiny_yaml, monkeypatch):
    """Random search over GNN weights, written as a new algorithm file would be; nothing else is edited."""
    from pydantic import Field
    from typer.testing import CliRunner

    from marl_amod.algos.common import BestActor, Logger, RunArgs, Timer, finish_run, seed_everything
    from marl_amod.algos.registry import ALGOS, Algorithm
    from marl_amod.cli import app

    class ToyArgs(RunArgs):
        sigma: float = Field(0.1, gt=0)
        """perturbation scale"""
        run_dir: str = "runs/toy"

    def toy_train(args: ToyArgs, *, resume=None, progress=None, config_path=None):
        seed_everything(args.seed)
        city = load_city(args.scenario)
        actor = build_actor(args.actor, city, 1 + 2 * args.lookahead, args.hidden, args.conv)
        best, log, timer = BestActor.of(actor), Logger(args.run_dir, tensorboard=False), Timer()
        for ep in range(1, args.episodes + 1):
            with torch.no_grad():
                for p in actor.parameters():
                    p.add_(args.sigma * torch.randn_like(p))
            log.log(ep, **{"eval/profit": best.validate(actor, city, args)})
            actor.load_state_dict(best.state)
        log.close()
        return finish_run(args, "toy", actor, city, timer(), args.episodes, config_path)

    monkeypatch.setitem(ALGOS, "toy", Algorithm(ToyArgs, toy_train, "random search"))
    runner = CliRunner()
    args = _common(tmp_path, tiny_yaml, episodes=3, sigma=0.5)
    cfg = tmp_path / "toy.yaml"
    cfg.write_text(yaml.safe_dump({"algo": "toy", "args": args}))
    res = runner.invoke(app, ["train", "--config", str(cfg)])
    assert res.exit_code == 0, res.output
    card = json.loads((tmp_path / "policies" / "p.json").read_text())
    assert card["algorithm"] == "toy" and card["config"] == str(cfg) and card["args"]["sigma"] == 0.5
    assert card["env_version"] == "v0" and card["episodes_trained"] == 3
    out = tmp_path / "eval.json"
    res = runner.invoke(app, ["evaluate", "--scenario", tiny_yaml, "--policy", str(tmp_path / "policies" / "p.pt"),
                              "--episodes", "2", "--output", str(out)])
    assert res.exit_code == 0, res.output
    assert json.loads(out.read_text())["metrics"]["profit"]["mean"] == pytest.approx(card["profit_mean"])
    args.pop("scenario")
    cmp_cfg = tmp_path / "compare.yaml"
    cmp_cfg.write_text(yaml.safe_dump({"scenario": tiny_yaml, "episodes": 2, "baselines": ["equal-distribution"],
                                       "output": str(tmp_path / "cmp"), "runs": [{"label": "toy", "algo": "toy", "args": args, "retrain": True}]}))
    res = runner.invoke(app, ["compare", "--config", str(cmp_cfg)])
    assert res.exit_code == 0, res.output
    assert "TOY / centralised" in (tmp_path / "cmp" / "compare.md").read_text()
    cfg.write_text(yaml.safe_dump({"algo": "toy", "args": {**args, "sigma": 0}}))  # its own bounds apply
    with pytest.raises(ConfigError, match=r"args\.sigma: Input should be greater than 0"):
        from marl_amod.algos.registry import load_train_config

        load_train_config(cfg)


# --------------------------------------------------------------------------------------------
# Training state: exact resume, Ctrl-C, log rows
# --------------------------------------------------------------------------------------------
def _final_actor(tmp_path: Path, name: str) -> dict:
    return torch.load(tmp_path / "policies" / name, map_location="cpu", weights_only=True)["state_dict"]


@pytest.mark.parametrize("algo", ["a2c", "sac"])
def test_resume_continues_exactly_as_an_uninterrupted_run(tmp_path, tiny_yaml, algo):
    """Networks, optimisers, RNGs and (SAC) the replay buffer, generator and temperature optimiser all resume."""
    from marl_amod.algos.registry import ALGOS

    entry = ALGOS[algo]
    extra = {"episodes_per_update": 2} if algo == "a2c" else {"batch_size": 8, "warmup_steps": 8, "auto_entropy": True}
    kw = {"eval_every": 2, "eval_episodes": 1, "final_eval_episodes": 1, "hidden": 8, "scenario": tiny_yaml, **extra}
    entry.train(entry.args(**kw, episodes=4, run_dir=str(tmp_path / "full"), policy_out=str(tmp_path / "policies" / "full.pt")))
    entry.train(entry.args(**kw, episodes=2, run_dir=str(tmp_path / "half"), policy_out=""))
    entry.train(entry.args(**kw, episodes=4, run_dir=str(tmp_path / "half"), policy_out=str(tmp_path / "policies" / "resumed.pt")),
                resume=str(tmp_path / "half" / "state.pt"))
    full, resumed = _final_actor(tmp_path, "full.pt"), _final_actor(tmp_path, "resumed.pt")
    for k in full:
        torch.testing.assert_close(full[k], resumed[k], rtol=0, atol=0)
    state = torch.load(tmp_path / "half" / "state.pt", map_location="cpu", weights_only=False)
    assert state["episode"] == 4 and state["algorithm"] == algo
    if algo == "sac":
        assert state["replay"]["size"] == state["n_steps"] > 0 and "state" in state["opt_alpha"]


@pytest.mark.parametrize("algo", ["a2c", "sac"])
def test_a_ctrl_c_in_the_middle_of_an_episode_stops_after_its_update_and_resumes_exactly(tmp_path, tiny_yaml, algo, monkeypatch):
    """A real SIGINT during episode 2's third step: the run finishes that batch and its update, saves that
    state and stops; resumed, it ends as the uninterrupted run, bit for bit (a state saved mid-episode
    held that episode's transitions, updates and random draws)."""
    import signal

    from marl_amod.algos import common, rollout
    from marl_amod.algos.registry import ALGOS

    entry = ALGOS[algo]
    extra = {"episodes_per_update": 2} if algo == "a2c" else {"batch_size": 8, "warmup_steps": 8, "auto_entropy": True}
    kw = {"eval_every": 2, "eval_episodes": 1, "final_eval_episodes": 1, "hidden": 8, "scenario": tiny_yaml, "episodes": 4, **extra}
    entry.train(entry.args(**kw, run_dir=str(tmp_path / "full"), policy_out=str(tmp_path / "policies" / "full.pt")))
    real, calls = rollout.Rollout.step, []

    def step(self, weights):
        calls.append(1)
        if len(calls) == len_episode + 3:
            signal.raise_signal(signal.SIGINT)  # the handler marks the stop; the episode goes on
        return real(self, weights)

    len_episode = load_city(tiny_yaml).horizon - 1
    monkeypatch.setattr(rollout.Rollout, "step", step)
    args = entry.args(**kw, run_dir=str(tmp_path / "cut"), policy_out=str(tmp_path / "policies" / "resumed.pt"))
    with pytest.raises(common.TrainingInterrupted) as stop:
        entry.train(args)
    assert stop.value.episode == 2 and len(calls) == 2 * len_episode  # episode 2 ran to its end, nothing after it
    monkeypatch.undo()
    entry.train(args, resume=str(stop.value.path))
    full, resumed = _final_actor(tmp_path, "full.pt"), _final_actor(tmp_path, "resumed.pt")
    for k in full:
        torch.testing.assert_close(full[k], resumed[k], rtol=0, atol=0)


def test_ctrl_c_saves_state_prints_one_line_and_resume_logs_each_episode_once(tmp_path, tiny_yaml, monkeypatch):
    from typer.testing import CliRunner

    from marl_amod.cli import app

    args = _common(tmp_path, tiny_yaml, episodes=8, episodes_per_update=2, eval_every=6)
    cfg = tmp_path / "run.yaml"
    cfg.write_text(yaml.safe_dump({"algo": "a2c", "args": args}))
    ctrl_c_after(monkeypatch, 4)
    res = CliRunner().invoke(app, ["train", "--config", str(cfg)])
    state = tmp_path / "run" / "state.pt"
    assert res.exit_code == 130
    last = res.output.strip().splitlines()[-1]
    assert last == f"interrupted at episode 4: training state in {state}; resume with: marl-amod train --config {cfg} --resume {state}"
    assert not (tmp_path / "policies" / "p.pt").exists()
    assert torch.load(state, map_location="cpu", weights_only=False)["episode"] == 4

    monkeypatch.undo()
    fresh = CliRunner().invoke(app, ["train", "--config", str(cfg)])  # without --resume: the saved state is not erased
    assert isinstance(fresh.exception, ConfigError) and f"interrupted at episode 4: continue it with --resume {state}" in str(fresh.exception)
    assert torch.load(state, map_location="cpu", weights_only=False)["episode"] == 4
    res = CliRunner().invoke(app, ["train", "--config", str(cfg), "--resume", str(state)])
    assert res.exit_code == 0, res.output
    rows = [tuple(line.split(",")[:2]) for line in (tmp_path / "run" / "log.csv").read_text().splitlines()[1:]]
    assert len(rows) == len(set(rows))
    assert sorted({int(e) for e, _ in rows}) == [2, 4, 6, 8]
    again = CliRunner().invoke(app, ["train", "--config", str(cfg)])  # resumed and finished: a fresh run may start there
    assert again.exit_code == 0, again.output
    assert len(list((tmp_path / "run").glob("events.out.tfevents.*"))) == 1  # the fresh run's curves alone


def test_ctrl_c_in_the_final_evaluation_says_how_to_finish(tmp_path, tiny_yaml, monkeypatch):
    from typer.testing import CliRunner

    from marl_amod.algos import common
    from marl_amod.cli import app

    cfg = tmp_path / "run.yaml"
    cfg.write_text(yaml.safe_dump({"algo": "a2c", "args": _common(tmp_path, tiny_yaml, episodes=4, episodes_per_update=2)}))

    def interrupted(*a, **k):
        raise KeyboardInterrupt

    monkeypatch.setattr(common, "finish_run", interrupted)
    res = CliRunner().invoke(app, ["train", "--config", str(cfg)])
    state = tmp_path / "run" / "state.pt"
    assert res.exit_code == 130 and f"finish with: marl-amod train --config {cfg} --resume {state}" in " ".join(res.output.split())
    monkeypatch.undo()
    done = CliRunner().invoke(app, ["train", "--config", str(cfg), "--resume", str(state)])
    assert done.exit_code == 0, done.output
    assert (tmp_path / "policies" / "p.pt").is_file()


def test_resume_from_an_older_state_drops_the_rows_logged_after_it(tmp_path, tiny_yaml):
    """A crash (no Ctrl-C handler) after episode 6 resumes from the state of episode 4: rows 5..6 are not kept twice."""
    import shutil

    from marl_amod.algos import a2c

    def keep_state_4(ep, total, stats):
        if ep == 4:
            shutil.copy(tmp_path / "run" / "state.pt", tmp_path / "state4.pt")

    args = _common(tmp_path, tiny_yaml, episodes=6, episodes_per_update=2, eval_every=4)
    a2c.train(a2c.Args(**args), progress=keep_state_4)
    a2c.train(a2c.Args(**{**args, "episodes": 8}), resume=str(tmp_path / "state4.pt"))
    rows = [tuple(line.split(",")[:2]) for line in (tmp_path / "run" / "log.csv").read_text().splitlines()[1:]]
    assert len(rows) == len(set(rows)) and sorted({int(e) for e, _ in rows}) == [2, 4, 6, 8]


@pytest.mark.parametrize(
    ("content", "message"),
    [(b"", "is empty"), (b"not a checkpoint", "is not a training state: a text file"), (b"PK\x03\x04 cut", "truncated")],
)
def test_bad_resume_file_is_a_data_error_naming_it(tmp_path, tiny_yaml, content, message):
    from marl_amod.algos import a2c
    from marl_amod.errors import DataError

    bad = tmp_path / "state.pt"
    bad.write_bytes(content)
    with pytest.raises(DataError, match=rf"{bad}.*{message}"):
        a2c.train(a2c.Args(**_common(tmp_path, tiny_yaml, episodes=2, episodes_per_update=2)), resume=str(bad))


def test_resuming_another_algorithms_state_is_refused(tmp_path, tiny_yaml):
    from marl_amod.algos import a2c, sac
    from marl_amod.errors import DataError

    a2c.train(a2c.Args(**_common(tmp_path, tiny_yaml, episodes=2, episodes_per_update=2, policy_out="")))
    with pytest.raises(DataError, match="is a a2c training state; this config trains sac"), pytest.warns(UserWarning, match="no update"):
        sac.train(sac.Args(**_common(tmp_path, tiny_yaml, episodes=2)), resume=str(tmp_path / "run" / "state.pt"))


def test_a_bad_policy_destination_fails_before_training(tmp_path, tiny_yaml, monkeypatch):
    from marl_amod.algos import a2c
    from marl_amod.algos.registry import ALGOS, Algorithm, run_training
    from marl_amod.errors import OutputError

    monkeypatch.setitem(ALGOS, "a2c", Algorithm(a2c.Args, lambda *a, **k: pytest.fail("trained before checking policy_out")))
    (tmp_path / "taken.pt").mkdir()  # a folder where the policy file would go
    args = a2c.Args(**_common(tmp_path, tiny_yaml, episodes=2, policy_out=str(tmp_path / "taken.pt")))
    with pytest.raises(OutputError, match="is a directory"):
        run_training("a2c", args)
