"""Atomic writes and destination checks: an interrupted write leaves the previous file intact."""

from __future__ import annotations

import json
import os
import stat
from pathlib import Path

import pytest

from marl_amod.errors import OutputError
from marl_amod.files import atomic_write, check_destination, torch_save, write_json


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
