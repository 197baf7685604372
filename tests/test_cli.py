"""The command line a new user runs first: scenarios, evaluate, clear errors."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from typer.testing import CliRunner

from marl_amod.cli import app
from marl_amod.metrics import METRICS

runner = CliRunner()


def run_eval(tmp_path, *args):
    out = tmp_path / "r.json"
    result = runner.invoke(app, ["evaluate", "--episodes", "2", "--output", str(out), *args])
    assert result.exit_code == 0, result.output
    return json.loads(out.read_text()), result.output


def _commands(group, prefix=""):
    for name, command in group.commands.items():
        yield from _commands(command, f"{prefix}{name} ") if hasattr(command, "commands") else [(prefix + name, command)]


def test_every_command_has_help_whose_paragraphs_are_not_broken_mid_sentence():
    """Typer's --help prints a docstring's line breaks as they are: a paragraph wrapped in the source
    shows as lines cut mid-sentence, so each paragraph is one line; every command and option says what it does."""
    import inspect

    import typer.main

    commands = list(_commands(typer.main.get_command(app)))
    assert {"evaluate", "train", "plot wait-map"} <= {name for name, _ in commands}
    for name, command in commands:
        doc = inspect.cleandoc(command.callback.__doc__ or "")
        assert doc, f"{name} has no help"
        for paragraph in doc.split("\n\n"):
            assert "\n" not in paragraph, f"{name}: --help breaks the line inside {paragraph[:60]!r}"
        assert runner.invoke(app, [*name.split(), "--help"]).exit_code == 0
        bare = [p.opts[0] for p in command.params if p.opts[0].startswith("--") and not getattr(p, "help", None)]
        assert bare == [], f"{name}: options without help: {bare}"


def test_python_dash_m_marl_amod_is_the_command_with_its_exit_codes(tmp_path):
    """A checkout used without `pip install -e .` has no `marl-amod` script; `python -m marl_amod`
    is the same command: help exits 0, a user's mistake exits 2 with one line and no traceback."""
    import os
    import subprocess
    import sys

    root = Path(__file__).resolve().parent.parent
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(filter(None, [str(root), os.environ.get("PYTHONPATH")]))}
    run = lambda *args: subprocess.run([sys.executable, "-m", "marl_amod", *args], cwd=tmp_path, env=env,  # noqa: E731
                                       capture_output=True, text=True, timeout=120)  # fmt: skip
    ok = run("evaluate", "--help")
    assert ok.returncode == 0 and "--policy" in ok.stdout, ok.stderr
    bad = run("evaluate", "--episodes", "1", "--policy", "teleport")
    assert bad.returncode == 2 and "Traceback" not in bad.stdout + bad.stderr
    assert [line for line in bad.stdout.splitlines() if line.startswith("error:")] == [bad.stdout.strip().splitlines()[-1]]


def test_importing_marl_amod_main_runs_no_command(monkeypatch):
    """No import-time side effects: a tool that imports every module (docs, the docs-name test)
    must not start the CLI, which would parse its own argv and exit."""
    import importlib
    import sys

    monkeypatch.setattr(sys, "argv", ["pytest", "--no-such-flag"])
    monkeypatch.delitem(sys.modules, "marl_amod.__main__", raising=False)
    assert importlib.import_module("marl_amod.__main__").main is not None


def test_scenarios_lists_the_default_city():
    result = runner.invoke(app, ["scenarios"])
    assert result.exit_code == 0, result.output
    assert "synthetic" in result.output and "16" in result.output


def test_scenarios_says_when_the_data_folder_is_not_the_data_folder(monkeypatch, tmp_path):
    from marl_amod.data import ENV_VAR

    monkeypatch.setenv(ENV_VAR, str(tmp_path))  # restored afterwards: --data-dir sets it for the run
    result = runner.invoke(app, ["scenarios", "--data-dir", str(tmp_path)])  # it exists, but holds no macro/ or lux/
    assert result.exit_code == 0, result.output
    assert "holds neither macro/ nor lux/" in " ".join(result.output.split())


def test_scenarios_list_reads_yaml_only_and_survives_a_broken_file(monkeypatch, tmp_path):
    """Listing builds no city, says the missing-data hint once, and a broken YAML spoils only its row."""
    from marl_amod.scenario import registry

    def no_build(*args, **kwargs):
        raise AssertionError("listing must not build a city")

    monkeypatch.setattr(registry, "build_city", no_build)
    (tmp_path / "good.yaml").write_text("name: good\nsource: synthetic\nrows: 2\ncols: 3\nvehicles_per_region: 5\n")
    (tmp_path / "city.yaml").write_text("name: city\nsource: json\ndata_file: macro/x.json\nstart_hour: 8\n"
                                        "demand_ratio: 1\nbeta: 0.5\n")  # fmt: skip
    (tmp_path / "broken.yaml").write_text("name: broken\nsource: synthetic\nrowz: 3\n")
    monkeypatch.setattr(registry, "scenario_dirs", lambda: [tmp_path])
    monkeypatch.delenv("MARL_AMOD_DATA", raising=False)
    result = runner.invoke(app, ["scenarios"])
    assert result.exit_code == 0, result.output
    lines = result.output.splitlines()
    good = next(line for line in lines if "good" in line)
    assert "synthetic" in good and " 6 " in good and " 30 " in good
    assert any(line.startswith("│ broken") and line.count("broken") >= 2 for line in lines) and "rowz" in result.output
    assert any(line.startswith("│ city") and "data" in line for line in lines)
    assert result.output.count("MARL_AMOD_DATA") == 1 and "could not be read" in result.output


def test_evaluate_writes_the_documented_json(tmp_path):
    data, output = run_eval(tmp_path, "--policy", "equal-distribution", "--seed", "3")
    assert data["scenario"] == "synthetic" and data["policy"] == "equal-distribution"
    assert data["episodes"] == 2 and data["seed"] == 3
    assert set(data["metrics"]) == set(METRICS)
    for value in data["metrics"].values():
        assert set(value) == {"mean", "std"}
    assert data["metrics"]["served_demand"]["mean"] <= data["metrics"]["demand"]["mean"]
    assert "equal-distribution" in output and "profit" in output


def test_same_seed_identical_numbers_different_seed_different(tmp_path):
    a, _ = run_eval(tmp_path, "--policy", "random", "--seed", "1")
    b, _ = run_eval(tmp_path, "--policy", "random", "--seed", "1")
    c, _ = run_eval(tmp_path, "--policy", "random", "--seed", "2")
    assert a["metrics"] == b["metrics"]
    assert a["metrics"]["demand"] != c["metrics"]["demand"]


def test_several_policies_give_one_comparison(tmp_path):
    data, output = run_eval(tmp_path, "--policy", "no-rebalancing", "--policy", "plus-one")
    assert [r["policy"] for r in data["results"]] == ["no-rebalancing", "plus-one"]
    assert data["results"][0]["metrics"]["rebalancing_cost"]["mean"] == 0


def test_policy_options_reach_the_policy(tmp_path):
    """--policy-option KEY=VALUE builds the policy with that option (read as a YAML scalar)."""
    plain, _ = run_eval(tmp_path, "--policy", "mpc-forecast", "--policy-option", "horizon=4")
    scaled, output = run_eval(
        tmp_path, "--policy", "mpc-forecast", "--policy-option", "horizon=4", "--policy-option", "demand_scale=1.5"
    )
    assert plain["policy"] == "mpc-forecast" and scaled["policy"] == "mpc-forecast+scale1.5"
    assert scaled["metrics"]["rebalancing_cost"] != plain["metrics"]["rebalancing_cost"]
    assert "mpc-forecast+scale1.5" in output
    two, _ = run_eval(tmp_path, "--policy", "mpc-scenarios", "--policy-option", "horizon=3", "--policy-option", "scenarios=2")
    assert two["policy"] == "mpc-scenarios+s2" and two["metrics"]["profit"]["mean"] > 0


def test_policy_option_numbers_are_read_as_python_writes_them():
    """PyYAML reads YAML 1.1: `noise=5e-2` was the string '5e-2' (then refused as "not a finite
    number") and `horizon=010` octal 8; other values stay YAML scalars."""
    from marl_amod.cli import parse_policy_options
    from marl_amod.policies import make_policy

    items = ["noise=5e-2", "horizon=010", "demand_scale=1.2", "backend=cvxpy", "flag=true", "none=~", "big=1_000"]
    options = parse_policy_options(items)
    expected = {"noise": 0.05, "horizon": 10, "demand_scale": 1.2, "backend": "cvxpy", "flag": True, "none": None, "big": 1000}
    assert options == expected
    assert make_policy("mpc-forecast", noise=options["noise"]).noise == 0.05


@pytest.mark.parametrize(
    "args, message",
    [
        (["--policy", "teleport"], "unknown policy"),
        (["--scenario", "atlantis"], "unknown scenario"),
        (["--scenario", "synthetic~hot2"], "is no variant"),
        (["--objective", "fun"], "objective"),
        (["--policy", "mpc-forecast", "--policy-option", "demand_scale=0"], "demand_scale"),
        (["--policy", "mpc-forecast", "--policy-option", "demand_scale"], "KEY=VALUE"),
        (["--policy", "mpc-forecast", "--policy-option", "max_wait=2"], "--max-wait"),
        (["--policy", "random", "--policy-option", "seed=3"], "use --seed"),
        (["--policy", "mpc-forecast", "--policy-option", "episodes=3"], "use --episodes"),
        (["--policy", "mpc-forecast", "--policy-option", "progress=1"], "the run's, not the policy's"),
        (["--policy", "mpc-forecast", "--policy-option", "horizon=[1"], "not a YAML value"),
        (["--policy", "mpc-scenarios", "--policy-option", "scenarios=0"], "scenarios"),
        (["--policy", "equal-distribution", "--policy-option", "demand_scale=1.2"], "demand_scale"),
    ],
)
def test_user_errors_exit_2_with_one_clear_line(args, message, capsys):
    from marl_amod.cli import main

    with pytest.raises(SystemExit) as exc:
        import sys

        argv, sys.argv = sys.argv, ["marl-amod", "evaluate", "--episodes", "1", *args]
        try:
            main()
        finally:
            sys.argv = argv
    assert exc.value.code == 2
    assert message in capsys.readouterr().out


@pytest.mark.parametrize("command", [["evaluate"], ["plot", "wait-map", "--output", "w.png"]])
@pytest.mark.parametrize("bad", ["teleport", "missing.pt"])
def test_a_bad_last_policy_fails_before_the_others_run(monkeypatch, tmp_path, command, bad):
    """`--policy A --policy B`: a typo or a missing checkpoint in B is reported before A's episodes run."""
    import marl_amod.evaluation
    from marl_amod.errors import ConfigError

    ran = []
    monkeypatch.setattr(marl_amod.evaluation, "evaluate", lambda *a, **k: ran.append(a) or {})
    monkeypatch.chdir(tmp_path)
    result = runner.invoke(app, [*command, "--episodes", "1", "--policy", "equal-distribution", "--policy", bad])
    assert isinstance(result.exception, ConfigError), result.output
    assert bad in str(result.exception) and ran == []


@pytest.mark.parametrize("policies, message", [("inf,teleport", "teleport"), (" , ", "no policy"), ("inf,inf", "twice"),
                                              ("policies/a2c_gnn_synthetic.pt,./policies/a2c_gnn_synthetic.pt", "would write one dataset")])  # fmt: skip
def test_datasets_checks_every_behaviour_policy_before_collecting(monkeypatch, tmp_path, policies, message):
    import marl_amod.datasets
    from marl_amod.errors import ConfigError

    monkeypatch.setattr(marl_amod.datasets, "collect", lambda *a, **k: pytest.fail("collected before the names were checked"))
    result = runner.invoke(app, ["datasets", "--scenario", "synthetic", "--policies", policies, "--out-dir", str(tmp_path)])
    assert isinstance(result.exception, ConfigError) and message in str(result.exception)


def test_wait_map_refuses_a_figure_format_before_evaluating(monkeypatch, tmp_path):
    """`--output map.txt` was a matplotlib traceback after every policy's episodes had run."""
    import marl_amod.evaluation
    from marl_amod.errors import OutputError

    monkeypatch.setattr(marl_amod.evaluation, "evaluate", lambda *a, **k: pytest.fail("evaluated before the output was checked"))
    result = runner.invoke(app, ["plot", "wait-map", "--episodes", "1", "--output", str(tmp_path / "map.txt")])
    assert isinstance(result.exception, OutputError) and ".txt" in str(result.exception) and "png" in str(result.exception)


def test_a_data_dir_that_is_not_a_folder_is_named_as_the_flag_the_user_gave(monkeypatch, tmp_path):
    from marl_amod.data import ENV_VAR
    from marl_amod.errors import DataError

    monkeypatch.setenv(ENV_VAR, str(tmp_path))  # restored afterwards: --data-dir sets it for the run
    missing = tmp_path / "nowhere"
    result = runner.invoke(app, ["evaluate", "--scenario", "nyc_brooklyn", "--episodes", "1", "--data-dir", str(missing)])
    assert isinstance(result.exception, DataError) and "--data-dir" in str(result.exception)
    assert str(missing) in str(result.exception)


def test_error_messages_print_verbatim_including_brackets(monkeypatch, capsys):
    """Errors name extras like `marl-amod[sumo]`; rich must not eat them as markup."""
    import sys

    import marl_amod.scenario
    from marl_amod.cli import main
    from marl_amod.errors import ConfigError

    def missing_extra(*_a, **_k):
        raise ConfigError('needs the extra: pip install "marl-amod[sumo]"')

    monkeypatch.setattr(marl_amod.scenario, "load_city", missing_extra)
    monkeypatch.setattr(sys, "argv", ["marl-amod", "evaluate", "--episodes", "1"])
    with pytest.raises(SystemExit) as exc:
        main()
    assert exc.value.code == 2
    assert 'pip install "marl-amod[sumo]"' in capsys.readouterr().out


def test_a_long_error_is_one_line_however_narrow_the_console(monkeypatch, capsys):
    """An unknown name lists every known one: well past the console width, still one line to grep."""
    import sys

    import marl_amod.scenario
    from marl_amod.cli import console, main
    from marl_amod.errors import ConfigError

    message = "unknown thing 'x'; known: " + ", ".join(f"name_{i}" for i in range(60))

    def fail(*_a, **_k):
        raise ConfigError(message)

    monkeypatch.setattr(marl_amod.scenario, "load_city", fail)
    monkeypatch.setattr(console, "width", 80)
    monkeypatch.setattr(sys, "argv", ["marl-amod", "evaluate", "--episodes", "1"])
    with pytest.raises(SystemExit):
        main()
    assert capsys.readouterr().out.strip() == f"error: {message}"


def test_wait_column_is_explained_only_when_requests_cannot_wait(tmp_path):
    data, output = run_eval(tmp_path, "--policy", "equal-distribution")
    assert data["metrics"]["wait_time"]["mean"] == 0.0 and "requests do not wait at --max-wait 0" in " ".join(output.split())
    data, output = run_eval(tmp_path, "--policy", "equal-distribution", "--max-wait", "2")
    assert data["metrics"]["wait_time"]["mean"] > 0.0 and "do not wait" not in output


def test_the_train_summary_counts_every_demonstration_and_dagger_episode():
    """A meta-imitation's closing line counts the variants' demonstrations and the DAgger episodes
    beside the cities' (its card holds them apart), and names the collection time its wall leaves out."""
    from marl_amod.policy_catalogue import trained_on

    demos = {"policy": "mpc-forecast", "cities": [f"c{i}" for i in range(10)], "episodes_per_city": 64, "collection_wall_s": 750.0,
             "hotspot_variants": [f"c{i}~hot1x2" for i in range(10)], "episodes_per_variant": 32}  # fmt: skip
    card = {"algorithm": "meta-bc", "updates": 2664, "training_wall_s": 3300.0, "demonstrations": demos,
            "dagger": {"rounds": 5, "episodes_per_city": 4, "shock_prob": 0.3, "collection_wall_s": 400.0}}  # fmt: skip
    assert trained_on(card) == ("2,664 updates on 960 MPC-Forecast demonstration episodes and 400 DAgger episodes in 55.0 min "
                                "(+ 12.5 min collecting the demonstrations)")  # fmt: skip
    assert trained_on({"updates": 10, "training_wall_s": 60.0, "dataset": {"transitions": 4000}}) == "10 updates on 4,000 logged transitions in 1.0 min"
    assert trained_on({"episodes_trained": 512, "training_wall_s": 90.0}) == "512 episodes in 1.5 min"


@pytest.mark.parametrize("terminal", [False, True])
def test_long_commands_log_a_line_a_tenth_when_not_on_a_terminal(terminal):
    """Off a terminal rich draws the bar only at its end: the progress bar then prints a line at each
    tenth (once, however it is reached), and on a terminal none (the live bar shows it)."""
    import io

    from rich.console import Console

    from marl_amod.cli import LoggedProgress

    out = io.StringIO()
    with LoggedProgress(console=Console(file=out, force_terminal=terminal, width=200)) as bar:
        steps = bar.add_task("collect", total=20)
        for _ in range(10):
            bar.advance(steps)
        jumps = bar.add_task("train", total=1000)
        bar.update(jumps, completed=750)  # one jump past several tenths: one line
        bar.update(jumps, completed=760)
        bar.update(jumps, completed=1000)  # the end is the bar's own last line
    lines = [ln for ln in out.getvalue().splitlines() if "%)" in ln]
    if terminal:
        assert lines == []
    else:
        assert [ln.split(":")[0] for ln in lines] == ["collect"] * 5 + ["train"]
        assert "10/20 (50%)" in lines[4] and "750/1,000 (70%)" in lines[5]


def test_a_checkpoints_dataset_is_named_by_its_file_not_its_path(monkeypatch, tmp_path):
    written = []
    monkeypatch.setattr("marl_amod.cli._collect_one", lambda scenario, name, episodes, seed, out, *a: written.append(out))
    result = runner.invoke(app, ["datasets", "--scenario", "synthetic", "--policies", "policies/a2c_gnn_synthetic.pt,prop", "--out-dir", str(tmp_path)])
    assert result.exit_code == 0, result.output
    assert written == [tmp_path / "synthetic_a2c_gnn_synthetic.npz", tmp_path / "synthetic_prop.npz"]
