"""marl-amod train-ensemble (marl_amod/side_by_side.py): members trained side by side in processes of their
own, then one ensemble file; bad plans refused before anything runs; a failed member writes no ensemble;
--resume keeps what is done."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import yaml
from typer.testing import CliRunner

from marl_amod.algos.registry import load_train_config
from marl_amod.cli import app
from marl_amod.ensemble import read_members
from marl_amod.errors import ConfigError
from marl_amod.side_by_side import plan
from tests.conftest import ctrl_c_after


@pytest.fixture
def tiny_yaml(tmp_path: Path) -> str:
    path = tmp_path / "tiny.yaml"
    path.write_text(yaml.safe_dump({"name": "tiny", "source": "synthetic", "rows": 3, "cols": 3, "horizon": 6, "vehicles_per_region": 5}))
    return str(path)


def _config(tmp_path: Path, scenario: str, seed: int, **kw) -> Path:
    args = {"scenario": scenario, "seed": seed, "episodes": 4, "episodes_per_update": 2, "eval_every": 4, "eval_episodes": 2,
            "final_eval_episodes": 2, "hidden": 8, "run_dir": str(tmp_path / f"run{seed}"),
            "policy_out": str(tmp_path / "policies" / f"p{seed}.pt"), **kw}  # fmt: skip
    path = tmp_path / f"member{seed}.yaml"
    path.write_text(yaml.safe_dump({"algo": "a2c", "args": args}))
    return path


def test_members_train_side_by_side_and_become_one_ensemble(tmp_path, tiny_yaml):
    configs = [_config(tmp_path, tiny_yaml, s) for s in (0, 1)]
    out = tmp_path / "policies" / "pair.yaml"
    res = CliRunner().invoke(app, ["train-ensemble", *map(str, configs), "--out", str(out)])
    assert res.exit_code == 0, res.output
    members = [tmp_path / "policies" / f"p{s}.pt" for s in (0, 1)]
    assert [Path(m).resolve() for m in read_members(out)] == [m.resolve() for m in members]
    cards = [json.loads(m.with_suffix(".json").read_text()) for m in members]
    assert [c["seed"] for c in cards] == [0, 1] and all(c["config"] == str(cfg) for c, cfg in zip(cards, configs, strict=True))
    for s in (0, 1):  # each member's output went to its own log, in its run folder
        assert "profit" in (tmp_path / f"run{s}" / "train.log").read_text()
    assert "wrote" in res.output and "min of wall time side by side" in res.output

    # --resume keeps members this config already trained: nothing runs again, the ensemble is rewritten
    stamps = [m.stat().st_mtime_ns for m in members]
    res = CliRunner().invoke(app, ["train-ensemble", *map(str, configs), "--out", str(out), "--resume"])
    assert res.exit_code == 0, res.output
    assert res.output.count("kept (--resume)") == 2 and [m.stat().st_mtime_ns for m in members] == stamps


def test_a_member_that_fails_writes_no_ensemble_and_names_its_log(tmp_path, tiny_yaml):
    good = _config(tmp_path, tiny_yaml, 0)
    bad = _config(tmp_path, tiny_yaml, 1, init_actor=str(tmp_path / "gone.pt"))  # valid as a config, fails when the run loads its start
    out = tmp_path / "policies" / "pair.yaml"
    members = plan([good, bad])
    assert members[1].config == bad
    res = CliRunner().invoke(app, ["train-ensemble", str(good), str(bad), "--out", str(out)])
    assert res.exit_code == 1, res.output
    assert not out.exists() and (tmp_path / "policies" / "p0.pt").is_file()
    assert "1 member(s) failed" in res.output
    said = next(line for line in res.output.splitlines() if line.startswith(f"{bad} failed"))
    assert str(tmp_path / "run1" / "train.log") in said and "gone.pt" in said  # the child's own error, its last line


@pytest.mark.parametrize("clash", ["run_dir", "policy_out"])
def test_a_plan_where_members_would_overwrite_each_other_is_refused_before_any_run(tmp_path, tiny_yaml, clash):
    first = _config(tmp_path, tiny_yaml, 0)
    second = _config(tmp_path, tiny_yaml, 1, **{clash: yaml.safe_load(first.read_text())["args"][clash]})
    with pytest.raises(ConfigError, match=f"share {clash}"):
        plan([first, second])
    res = CliRunner().invoke(app, ["train-ensemble", str(first), str(second), "--out", str(tmp_path / "e.yaml")])
    assert res.exit_code != 0 and not (tmp_path / "run0").exists()


def test_one_config_or_one_without_a_policy_is_no_ensemble(tmp_path, tiny_yaml):
    first = _config(tmp_path, tiny_yaml, 0)
    with pytest.raises(ConfigError, match="two or more"):
        plan([first])
    with pytest.raises(ConfigError, match="policy_out is empty"):
        plan([first, _config(tmp_path, tiny_yaml, 1, policy_out="")])
    with pytest.raises(ConfigError, match="member1.yaml: unknown scenario 'atlantis'"):  # here, not in the member's process
        plan([first, _config(tmp_path, "atlantis", 1)])


def test_resume_keeps_the_done_member_and_resumes_the_stopped_one_from_its_state(tmp_path, tiny_yaml, monkeypatch):
    """After a Ctrl-C one member is done and the other holds a training state: --resume runs only the
    second, from its state (its log keeps each episode once), and writes the ensemble."""
    configs = [_config(tmp_path, tiny_yaml, s) for s in (0, 1)]
    assert CliRunner().invoke(app, ["train", "--config", str(configs[0])]).exit_code == 0
    ctrl_c_after(monkeypatch, 2)
    assert CliRunner().invoke(app, ["train", "--config", str(configs[1])]).exit_code == 130
    monkeypatch.undo()
    done = tmp_path / "policies" / "p0.pt"
    stamp = done.stat().st_mtime_ns
    (tmp_path / "run1" / "train.log").write_text("the stopped run\n")  # a resumed member's log goes on after it; a fresh one starts anew
    out = tmp_path / "pair.yaml"
    res = CliRunner().invoke(app, ["train-ensemble", *map(str, configs), "--out", str(out), "--resume"])
    assert res.exit_code == 0, res.output
    assert done.stat().st_mtime_ns == stamp and res.output.count("kept (--resume)") == 1
    assert json.loads((tmp_path / "policies" / "p1.json").read_text())["episodes_trained"] == 4
    rows = [tuple(line.split(",")[:2]) for line in (tmp_path / "run1" / "log.csv").read_text().splitlines()[1:]]
    assert len(rows) == len(set(rows)) and sorted({int(e) for e, _ in rows}) == [2, 4]
    assert (tmp_path / "run1" / "train.log").read_text().startswith("the stopped run\n")
    assert len(read_members(out)) == 2


def test_progress_reads_the_last_whole_row_of_this_runs_log(tmp_path):
    """The bar counts what the run has logged: the last whole row (a row still being written is not
    read as a smaller number), and nothing from a log an earlier run left in the folder."""
    import os

    from marl_amod.side_by_side import Member

    member = Member(tmp_path / "c.yaml", "a2c", tmp_path, tmp_path / "p.pt", 100)
    assert member.progress(since=0) == 0  # no log yet
    log = tmp_path / "log.csv"
    log.write_text("episode,metric,value\n" + "".join(f"{e},loss,0.5\n" for e in range(1, 40)) + "4")  # 40 half written
    assert member.progress(since=0) == 39
    os.utime(log, (1_000, 1_000))
    assert member.progress(since=2_000) == 0  # older than this run: an earlier run's log


def test_meta_bc_members_that_would_collect_into_one_demonstrations_folder_are_refused():
    """Side by side, two meta-bc runs missing the same demonstration files would write them at once;
    RL² (meta) only reads its folder, so its members may share one."""
    root = Path(__file__).resolve().parent.parent / "configs" / "meta"
    with pytest.raises(ConfigError, match="share demos runs/meta_demos_seed1"):
        plan([root / "bc_dagger_l1_hot36.yaml", root / "bc_dagger_l1_ens1.yaml"])  # seed 1's two arms, one folder
    assert load_train_config(root / "bc_dagger_l1_whole_rep4.yaml")[1].outputs()["demos"] == "runs/meta_demos_seed4"
    assert len(plan([root / "bc_dagger_l1_whole_rep4.yaml", root / "bc_dagger_l1_whole_rep5.yaml"])) == 2
    assert all("demos" not in load_train_config(root / c)[1].outputs() for c in ("rl2_whole_rep4.yaml", "rl2_whole_rep5.yaml"))
    assert len(plan([root / "rl2_whole_rep4.yaml", root / "rl2_whole_rep5.yaml"])) == 2
