"""Atomic file writes: write to a temporary file beside the target, then rename.

An interrupted run never leaves a truncated output that looks valid. Temporaries are named
``.<stem>.<pid>-<random>.tmp<suffix>``; the next write of the same target deletes those
whose writing process has ended (a run killed with SIGKILL cannot clean up after itself).
"""

from __future__ import annotations

import contextlib
import os
import re
import shutil
import tempfile
from pathlib import Path
from typing import Iterator

from omg4.errors import OMG4Error


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike) -> Iterator[Path]:
    """Yield a temporary path in the target's folder; rename it onto ``path`` on success.

    The temporary file keeps the target's suffix so that writers choosing a format by
    extension (PNG, MP4, ...) behave as for the final name. On any exception the
    temporary file is removed and the target is left untouched; an operating-system error
    (permissions, a full disk, a read-only mount) becomes a one-line :class:`OMG4Error`.
    """
    target = Path(path)
    prefix, suffix = f".{target.stem}.", f".tmp{target.suffix}"
    try:
        target.parent.mkdir(parents=True, exist_ok=True)
        remove_stale_temporaries(target.parent, prefix, suffix)
        fd, tmp_name = tempfile.mkstemp(prefix=f"{prefix}{os.getpid()}-", suffix=suffix, dir=target.parent)
    except OSError as exc:
        raise OMG4Error(f"cannot write {target}: {exc.strerror or exc}") from None
    os.close(fd)
    tmp = Path(tmp_name)
    try:
        yield tmp
        # mkstemp creates 0600, and writers that replace the file (safetensors) keep a private mode: outputs get
        # the usual permissions
        os.chmod(tmp, 0o666 & ~_umask())
        os.replace(tmp, target)
    except BaseException as exc:
        tmp.unlink(missing_ok=True)
        if isinstance(exc, OSError):
            raise OMG4Error(f"cannot write {target}: {exc.strerror or exc}") from None
        raise


@contextlib.contextmanager
def atomic_folder(path: str | os.PathLike) -> Iterator[Path]:
    """Yield an empty temporary folder beside ``path``; when the block ends without an exception it replaces
    ``path`` (an existing folder there is moved aside first and deleted only after the rename), else it is
    deleted and ``path`` is left as it was. An interrupted write never leaves a half-written folder; an
    operating-system error becomes a one-line :class:`OMG4Error`."""
    target = Path(os.path.abspath(path))
    remove_stale_temporaries(target.parent, f".{target.name}.tmp-")
    remove_stale_temporaries(target.parent, f".{target.name}.old.")
    try:
        target.parent.mkdir(parents=True, exist_ok=True)
        tmp = Path(tempfile.mkdtemp(prefix=f".{target.name}.tmp-{os.getpid()}-", dir=target.parent))
        os.chmod(tmp, 0o777 & ~_umask())  # mkdtemp creates 0700
    except OSError as exc:
        raise OMG4Error(f"cannot write {target}: {exc.strerror or exc}") from None
    try:
        yield tmp
        old = None
        if target.exists() or target.is_symlink():
            old = Path(tempfile.mkdtemp(prefix=f".{target.name}.old.{os.getpid()}-", dir=target.parent))
            os.replace(target, old / "x")
        os.replace(tmp, target)
        if old is not None:
            shutil.rmtree(old, ignore_errors=True)
    except BaseException as exc:
        shutil.rmtree(tmp, ignore_errors=True)
        if isinstance(exc, OSError):
            raise OMG4Error(f"cannot write {target}: {exc.strerror or exc}") from None
        raise


# what mkstemp/mkdtemp and uuid put between prefix and suffix, after an optional "<pid>-"
_TEMP_MIDDLE = re.compile(r"(?:(\d+)-)?[a-z0-9_]{8,12}")


def remove_stale_temporaries(folder: Path, prefix: str, suffix: str = "") -> None:
    """Delete the files or folders ``prefix<pid>-<random>suffix`` in ``folder`` whose process ``pid`` has ended
    (and those of the older ``prefix<random>suffix`` form): what interrupted writes left behind."""
    try:
        entries = list(Path(folder).iterdir())
    except OSError:
        return
    for entry in entries:
        name = entry.name
        if not (name.startswith(prefix) and name.endswith(suffix) and len(name) > len(prefix) + len(suffix)):
            continue
        match = _TEMP_MIDDLE.fullmatch(name[len(prefix):len(name) - len(suffix)])
        if match is None or (match.group(1) and _process_alive(int(match.group(1)))):
            continue
        try:
            if entry.is_dir() and not entry.is_symlink():
                shutil.rmtree(entry, ignore_errors=True)
            else:
                entry.unlink(missing_ok=True)
        except OSError:  # another user's, say: not ours to remove, and no reason to fail the write
            continue


def _process_alive(pid: int) -> bool:
    if pid == os.getpid():
        return True
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except (PermissionError, OverflowError):
        return True
    return True


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def write_bytes_atomic(path: str | os.PathLike, data: bytes) -> None:
    """Write ``data`` to ``path`` atomically."""
    with atomic_path(path) as tmp:
        tmp.write_bytes(data)


def write_text_atomic(path: str | os.PathLike, text: str) -> None:
    """Write ``text`` (UTF-8) to ``path`` atomically."""
    write_bytes_atomic(path, text.encode("utf-8"))
