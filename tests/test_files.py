"""Atomic writes and destination checks: an interrupted write leaves the previous file intact."""

from __future__ import annotations

import json
import os
import stat
from pathlib import Path

import pytest

from marl_amod.errors import OutputError
from marl_amod.files import atomic_write, check_destination, check_folder, torch_save, write_json


def test_interrupted_write_keeps_the_previous_file(tmp_path: Path) -> None:
    target = write_json(tmp_path / "r.json", {"a": 1})

    def dies(fh) -> None:
        fh.write(b"partial")
        raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        atomic_write(target, dies)
    assert json.loads(target.read_text()) == {"a": 1}
    assert [p.name for p in tmp_path.iterdir()] == ["r.json"]  # no temporary file left behind


def test_torch_save_round_trips(tmp_path: Path) -> None:
    torch = pytest.importorskip("torch")
    path = torch_save(tmp_path / "m.pt", {"w": torch.ones(3)})
    assert torch.equal(torch.load(path)["w"], torch.ones(3))


def test_bad_destinations_are_refused_before_any_work(tmp_path: Path) -> None:
    (tmp_path / "file").write_text("x")
    with pytest.raises(OutputError, match="is a directory"):
        check_destination(tmp_path)
    with pytest.raises(OutputError, match="is a file, not a folder"):
        check_destination(tmp_path / "file" / "out.json")
    assert check_destination(tmp_path / "new" / "deep" / "out.json").parent.is_dir()
    for folder in (tmp_path / "file", tmp_path / "file" / "run"):  # a file where the folder, or one above it, would be
        with pytest.raises(OutputError, match="is a file, not a folder"):
            check_folder(folder, what="run_dir")
    assert check_folder(tmp_path / "runs" / "a2c").is_dir()


def test_a_training_run_and_the_transfer_table_refuse_a_file_as_their_folder(tmp_path: Path) -> None:
    from typer.testing import CliRunner

    from marl_amod.algos.registry import args_for, run_training
    from marl_amod.cli import app

    (tmp_path / "file").write_text("x")
    args = args_for("a2c", {"scenario": "synthetic", "episodes": 1, "run_dir": str(tmp_path / "file"), "policy_out": str(tmp_path / "p.pt")})
    with pytest.raises(OutputError, match="run_dir .*is a file, not a folder"):
        run_training("a2c", args)
    result = CliRunner().invoke(app, ["transfer-table", "--study", "event", "--out", str(tmp_path / "file"), "--redraw"])
    assert isinstance(result.exception, OutputError) and "--out" in str(result.exception)


def test_written_files_get_the_permissions_a_plain_write_gives(tmp_path: Path) -> None:
    """mkstemp's owner-only temporary file must not make results unreadable to the group: a new file
    follows the umask, a replaced one keeps its mode."""
    old = os.umask(0o022)
    try:
        fresh = write_json(tmp_path / "fresh.json", {"a": 1})
        assert stat.S_IMODE(fresh.stat().st_mode) == 0o644
        kept = tmp_path / "kept.json"
        kept.write_text("{}")
        kept.chmod(0o640)
        atomic_write(kept, b"{}")
        assert stat.S_IMODE(kept.stat().st_mode) == 0o640
    finally:
        os.umask(old)
