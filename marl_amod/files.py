"""Writing results so that nothing computed is lost and nothing is half-written.

Every file marl_amod writes (policies, cards, training state, evaluation JSON, datasets, tables)
goes through :func:`atomic_write`: the bytes go to a temporary file in the destination's folder,
are flushed to disk, and replace the destination in one ``os.replace``. A reader therefore sees
the previous file or the new one, never a truncated mix, even if the process is interrupted.
:func:`check_destination` runs *before* long work, so a bad ``--output`` fails in a second, not
after an hour of training.
"""

from __future__ import annotations

import contextlib
import hashlib
import io
import json
import os
import tempfile
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import IO, Any

from marl_amod.errors import OutputError


def check_destination(path: str | Path, *, what: str = "output") -> Path:
    """The resolved ``path`` if a file can be written there (parent folders are created), else an
    :class:`OutputError` naming the path and the reason."""
    path = Path(path).expanduser()
    if path.is_dir():
        raise OutputError(f"{what} {path} is a directory; give a file name")
    _make_folder(path.parent, f"{what} {path}")
    return path


def check_folder(path: str | Path, *, what: str = "output folder") -> Path:
    """``path`` as a folder that exists now (created with its parents), else an :class:`OutputError`
    naming it and the reason (a file in the way, no permission): before the work that fills it."""
    path = Path(path).expanduser()
    _make_folder(path, f"{what} {path}")
    return path


def _make_folder(folder: Path, label: str) -> None:
    """Create ``folder`` (and its parents) or raise an :class:`OutputError` starting with ``label``."""
    for ancestor in (folder, *folder.parents):
        if ancestor.exists():
            if not ancestor.is_dir():
                raise OutputError(f"{label}: {ancestor} is a file, not a folder")
            break
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise OutputError(f"{label}: cannot create folder {folder} ({exc.strerror or exc})") from exc
    if not os.access(folder, os.W_OK | os.X_OK):
        raise OutputError(f"{label}: folder {folder} is not writable")


def _umask() -> int:
    """The process's umask (read by setting it and putting it back: there is no other portable way)."""
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


def _permissions(path: Path) -> int:
    """The mode a plain ``open(path, "w")`` would leave: the existing file's, else 0o666 less the umask.
    Why: ``mkstemp`` creates its file owner-only (0o600), and ``os.replace`` would carry that over."""
    try:
        return path.stat().st_mode & 0o7777
    except OSError:
        return 0o666 & ~_umask()


@contextlib.contextmanager
def atomic_open(path: str | Path, mode: str = "wb") -> Iterator[IO[Any]]:
    """A file handle whose content replaces ``path`` only when the ``with`` block succeeds; the
    file ends with the permissions a plain write would give it (:func:`_permissions`)."""
    path = Path(path)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        os.chmod(tmp, _permissions(path))
        with os.fdopen(fd, mode) as fh:
            yield fh
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        raise


def atomic_write(path: str | Path, data: bytes | str | Callable[[IO[bytes]], None]) -> Path:
    """Write ``data`` (bytes, text, or a function writing to a binary handle) to ``path`` atomically."""
    path = Path(path)
    with atomic_open(path, "wb") as fh:
        if callable(data):
            data(fh)
        else:
            fh.write(data.encode() if isinstance(data, str) else data)
    return path


def write_json(path: str | Path, payload: Any) -> Path:
    """Indented JSON (numpy scalars as floats), written atomically."""
    return atomic_write(path, json.dumps(payload, indent=2, default=float) + "\n")


def torch_save(path: str | Path, obj: Any) -> Path:
    """``torch.save`` through a buffer, so an interrupt never leaves a truncated checkpoint."""
    import torch

    buffer = io.BytesIO()
    torch.save(obj, buffer)
    return atomic_write(path, buffer.getvalue())


def save_or_fallback(path: str | Path, write: Callable[[Path], Any], *, what: str = "results") -> Path:
    """Write with ``write(path)``; if that fails after a long run (disk full, folder removed), write
    to a fresh folder under the system's temporary directory, then the working directory, and
    raise an :class:`OutputError` that says where the results are. Nothing computed is lost."""
    path = Path(path)
    try:
        write(path)
        return path
    except (OSError, OutputError) as exc:
        reason = getattr(exc, "strerror", None) or str(exc)
        tried = []
        for folder in (Path(tempfile.gettempdir()), Path.cwd()):
            try:
                fallback = Path(tempfile.mkdtemp(prefix="marl_amod-", dir=folder)) / path.name
                write(fallback)
            except OSError as again:
                tried.append(f"{folder} ({again.strerror or again})")
                continue
            raise OutputError(f"could not write {what} to {path} ({reason}); they are saved in {fallback}") from exc
        raise OutputError(f"could not write {what} to {path} ({reason}) nor to {', '.join(tried)}") from exc


def file_sha256(path: str | Path) -> str:
    """The SHA-256 of a file's bytes: what a card names its file by (a policy's ``pt_sha256``, a
    dataset's ``sha256``, a warm-started run's ``start_sha256``)."""
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()
