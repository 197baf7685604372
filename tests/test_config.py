"""Training configs: bounds, keys the run would ignore, extends:, and one readable line per problem."""

from __future__ import annotations

from pathlib import Path

import pytest
import yaml

from marl_amod.algos.registry import load_train_config
from marl_amod.errors import ConfigError

CONFIGS = Path(__file__).resolve().parent.parent / "configs"


def _write(tmp_path: Path, name: str, payload: dict) -> Path:
    path = tmp_path / name
    path.write_text(yaml.safe_dump(payload))
    return path


@pytest.mark.parametrize(
    ("algo", "key", "value", "message"),
    [
        ("a2c", "episodes", 0, "greater than or equal to 1"),
        ("a2c", "gamma", 0, "greater than 0"),
        ("a2c", "gamma", 1.5, "less than or equal to 1"),
        ("a2c", "hidden", 0, "greater than or equal to 1"),
        ("a2c", "eval_every", 0, "greater than or equal to 1"),
        ("a2c", "lr_actor", 0.0, "greater than 0"),
        ("sac", "lr_critic", -1e-3, "greater than 0"),
        ("a2c", "final_eval_episodes", 0, "greater than or equal to 1"),
        ("a2c", "episodes_per_update", 0, "greater than or equal to 1"),
        ("sac", "batch_size", 0, "greater than or equal to 1"),
        ("sac", "polyak", 1.5, "less than or equal to 1"),
        ("a2c", "seed", -1, "greater than or equal to 0"),
    ],
)
def test_out_of_range_values_are_one_line_naming_file_and_key(tmp_path, algo, key, value, message):
    path = _write(tmp_path, "run.yaml", {"algo": algo, "args": {key: value}})
    with pytest.raises(ConfigError) as info:
        load_train_config(path)
    assert str(info.value) == f"{path}: args.{key}: Input should be {message}"


def test_several_problems_are_one_line_each(tmp_path):
    path = _write(tmp_path, "run.yaml", {"algo": "a2c", "args": {"episodes": 0, "gamma": 2, "episodse": 3}})
    with pytest.raises(ConfigError) as info:
        load_train_config(path)
    lines = str(info.value).splitlines()
    assert len(lines) == 3 and all(line.startswith(f"{path}: args.") for line in lines)
    assert f"{path}: args.episodse: unknown key" in lines


@pytest.mark.parametrize(
    ("algo", "args", "key"),
    [
        ("a2c", {"mode": "centralised", "central_critic": False}, "central_critic"),
        ("a2c", {"mode": "decentralised", "actor": "mlp"}, "actor"),
        ("a2c", {"mode": "decentralised", "central_critic": False, "conv": "gcn"}, "conv"),
        ("sac", {"mode": "decentralised", "central_critic": True}, "central_critic"),
        ("sac", {"lr_alpha": 0.01}, "lr_alpha"),
        ("bc", {"dataset": "d.npz", "num_envs": 4}, "num_envs"),  # offline runs step no env
        ("iql", {"dataset": "d.npz", "num_envs": 4}, "num_envs"),
        ("bc", {"dataset": "d.npz", "critic_time": True}, "critic_time"),  # BC has no critic
    ],
)
def test_keys_the_chosen_mode_ignores_are_rejected(tmp_path, algo, args, key):
    path = _write(tmp_path, "run.yaml", {"algo": algo, "args": args})
    with pytest.raises(ConfigError, match=rf"^{path}: args: {key} is not read: "):
        load_train_config(path)


def test_the_same_keys_are_accepted_where_they_are_read(tmp_path):
    _, args = load_train_config(_write(tmp_path, "a.yaml", {"algo": "a2c", "args": {"mode": "decentralised", "central_critic": False}}))
    assert args.central_critic is False
    _, args = load_train_config(_write(tmp_path, "s.yaml", {"algo": "sac", "args": {"auto_entropy": True, "lr_alpha": 0.01}}))
    assert args.lr_alpha == 0.01


def test_extends_starts_from_the_base_and_merges_args(tmp_path):
    _write(tmp_path, "base.yaml", {"algo": "a2c", "args": {"episodes": 10, "hidden": 4, "run_dir": "runs/base"}})
    (tmp_path / "v").mkdir()
    path = _write(tmp_path / "v", "variant.yaml", {"extends": "../base.yaml", "args": {"hidden": 6}})
    algo, args = load_train_config(path)
    assert (algo, args.episodes, args.hidden, args.run_dir) == ("a2c", 10, 6, "runs/base")
    assert "hidden" in args.model_fields_set and "lookahead" not in args.model_fields_set
    commented = tmp_path / "v" / "commented.yaml"
    commented.write_text("extends: ../base.yaml\nargs:\n  # hidden: 8\n")  # args: with only a comment is no keys, not no args
    assert load_train_config(commented)[1].run_dir == "runs/base"


def test_extends_cycle_and_missing_base_are_clear(tmp_path):
    _write(tmp_path, "a.yaml", {"extends": "b.yaml", "algo": "a2c"})
    _write(tmp_path, "b.yaml", {"extends": "a.yaml", "algo": "a2c"})
    with pytest.raises(ConfigError, match="makes a cycle"):
        load_train_config(tmp_path / "a.yaml")
    path = _write(tmp_path, "c.yaml", {"extends": "nowhere.yaml", "algo": "a2c"})
    with pytest.raises(ConfigError, match=r"c\.yaml: extends: nowhere\.yaml not found"):  # names the file that says it
        load_train_config(path)


def test_unknown_algorithm_and_top_level_key(tmp_path):
    with pytest.raises(ConfigError, match=r"algo: unknown algorithm 'ppo2'; known: a2c, bc, cql, iql, meta, meta-bc, sac"):
        load_train_config(_write(tmp_path, "x.yaml", {"algo": "ppo2"}))
    with pytest.raises(ConfigError, match=r"x\.yaml: argz: unknown key"):
        load_train_config(_write(tmp_path, "x.yaml", {"algo": "a2c", "argz": {}}))


def test_rllib_args_are_the_same_model_with_the_same_bounds(tmp_path):
    from marl_amod.config import CommonArgs
    from marl_amod.integrations.rllib import RllibArgs, load_rllib_config

    assert issubclass(RllibArgs, CommonArgs)
    path = _write(tmp_path, "ppo.yaml", {"algo": "ppo", "args": {"gamma": 2, "final_eval_episodes": 0}})
    with pytest.raises(ConfigError) as info:
        load_rllib_config(path)
    assert str(info.value).splitlines() == [
        f"{path}: args.gamma: Input should be less than or equal to 1",
        f"{path}: args.final_eval_episodes: Input should be greater than or equal to 1",
    ]


def test_configs_are_grouped_by_algorithm_and_variants_extend_a_base():
    groups = {p.parent.name for p in CONFIGS.rglob("*.yaml")}
    assert groups == {"a2c", "sac", "ppo_rllib", "compare", "meta", "bc", "iql", "cql"}
    assert not list(CONFIGS.glob("*.yaml"))
    for variant in ("a2c/nyc_brooklyn_sage.yaml", "a2c/nyc_brooklyn_dec.yaml", "sac/nyc_brooklyn_long.yaml", "iql/nyc_brooklyn_dtv.yaml"):
        assert "extends" in yaml.safe_load((CONFIGS / variant).read_text())


def test_a_compare_run_is_a_training_config_plus_overrides(tmp_path):
    from marl_amod.comparison import load_compare_config

    (tmp_path / "a2c").mkdir()
    _write(tmp_path / "a2c", "city.yaml", {"algo": "a2c", "args": {"scenario": "synthetic", "episodes": 7, "policy_out": "p.pt"}})
    (tmp_path / "compare").mkdir()
    run = {"label": "dec", "config": "../a2c/city.yaml", "args": {"mode": "decentralised", "policy_out": "d.pt"}}
    path = _write(tmp_path / "compare", "city.yaml", {"scenario": "synthetic", "runs": [run]})
    (resolved,) = load_compare_config(path).runs
    assert resolved.algo == "a2c" and resolved.args == {"scenario": "synthetic", "episodes": 7, "policy_out": "d.pt", "mode": "decentralised"}
    path = _write(tmp_path / "compare", "other.yaml", {"scenario": "nyc_brooklyn", "runs": [run]})
    with pytest.raises(ConfigError, match=r"run 'dec': args.scenario: synthetic is not the comparison's nyc_brooklyn"):
        load_compare_config(path)
    path = _write(tmp_path / "compare", "sac.yaml", {"scenario": "synthetic", "runs": [{**run, "algo": "sac"}]})
    with pytest.raises(ConfigError, match="algo sac differs from ../a2c/city.yaml's a2c"):
        load_compare_config(path)


@pytest.mark.parametrize(("algo", "needed"), [("a2c", {}), ("sac", {}), ("iql", {"dataset": "d.npz"}), ("meta-bc", {})])
def test_validation_on_the_report_streams_is_refused(tmp_path, algo, needed):
    path = _write(tmp_path, "run.yaml", {"algo": algo, "args": {**needed, "eval_seed": 0}})
    report = r"eval_seed 0 is the report seed \(marl-amod evaluate --seed 0\): validation must not run on the report streams"
    with pytest.raises(ConfigError, match=rf"^{path}: args: {report}"):
        load_train_config(path)
    assert load_train_config(_write(tmp_path, "ok.yaml", {"algo": algo, "args": {**needed, "eval_seed": 7}}))  # any other stream is fine
    if algo == "meta-bc":  # reads no final_eval_seed (its card is scored on the validation streams)
        return
    moved = {**needed, "eval_seed": 0, "final_eval_seed": 7000}  # final_eval_seed moved: seed 0 is still the report streams
    with pytest.raises(ConfigError, match=f"args: {report}"):
        load_train_config(_write(tmp_path, "moved.yaml", {"algo": algo, "args": moved}))
    with pytest.raises(ConfigError, match="args: eval_seed 7000 is final_eval_seed's: validation must not run on the report streams"):
        load_train_config(_write(tmp_path, "same.yaml", {"algo": algo, "args": {**moved, "eval_seed": 7000}}))


def test_a_policy_file_is_named_pt(tmp_path):
    """It was written as x.pt while its card and the config named x.txt."""
    path = _write(tmp_path, "run.yaml", {"algo": "a2c", "args": {"policy_out": "policies/mine.txt"}})
    with pytest.raises(ConfigError, match=r"policy_out 'policies/mine.txt': a policy file is a \.pt"):
        load_train_config(path)
    assert load_train_config(_write(tmp_path, "ok.yaml", {"algo": "a2c", "args": {"policy_out": ""}}))[1].policy_out == ""


@pytest.mark.parametrize(("algo", "key", "value"), [("a2c", "hidden", True), ("sac", "lr_actor", False), ("bc", "updates", True)])
def test_a_switch_where_a_number_belongs_is_refused(tmp_path, algo, key, value):
    """pydantic's lax mode read `hidden: true` as 1 unit."""
    path = _write(tmp_path, "run.yaml", {"algo": algo, "args": {key: value, **({"dataset": "d.npz"} if algo == "bc" else {})}})
    with pytest.raises(ConfigError, match=rf"args: {key} must be a number, got {value}"):
        load_train_config(path)
