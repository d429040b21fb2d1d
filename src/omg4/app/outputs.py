"""Output paths checked before any work: writable, not a folder where a file goes, never over an input.

The rule every command follows (outputs never destroy inputs):

* an output that resolves to one of the command's inputs (model, dataset file or folder,
  scores, camera file) is refused, ``--force`` or not;
* a file a dataset reader takes from a dataset folder (or would take, were it created:
  :func:`omg4.data.readers.is_dataset_file` — videos, poses, points, metadata, images in
  subfolders) is never an output, whether the folder is one of the command's inputs or any
  other dataset (the output's folder holding a layout's metadata file, :data:`DATASET_MARKERS`, or a
  Blender or Panoptic folder up to two levels above it);
  any other existing file inside an input dataset folder is replaced only with ``--force``;
* a file output may not be one of the files a folder output of the same command holds
  (``reserved``: e.g. a training run's model, configuration and checkpoints);
* two outputs of one command may not be the same file;
* the output's folder must exist or be creatable, and be writable (tried with a real file,
  so read-only mounts and permissions are caught as well), and a file output may not name
  a folder — all checked before the expensive step, so nothing is computed for nothing.

Every refusal is a one-line :class:`~omg4.errors.OMG4Error` (exit 2 on the command line).
"""

from __future__ import annotations

import os
import tempfile
from pathlib import Path
from typing import Iterable

from omg4.errors import OMG4Error


def _resolved(path: str | os.PathLike) -> Path:
    return Path(os.path.realpath(os.path.abspath(path)))


def _same_file(a: Path, b: Path) -> bool:
    """``a`` and ``b`` are one file or folder (same resolved path, or hard links of one inode)."""
    if _resolved(a) == _resolved(b):
        return True
    try:
        return os.path.samefile(a, b)
    except OSError:
        return False


def _inside(path: Path, folder: Path) -> bool:
    return _resolved(folder) in _resolved(path).parents


def _check_writable_folder(folder: Path, what: str) -> None:
    """``folder`` (or its nearest existing ancestor, where it will be created) is a writable folder."""
    existing = folder
    while not existing.exists():
        if existing.is_symlink():
            raise OMG4Error(f"{what}: {existing} is a broken link")
        existing = existing.parent
    if not existing.is_dir():
        raise OMG4Error(f"{what}: {existing} is not a folder")
    try:
        fd, probe = tempfile.mkstemp(prefix=".omg4-write-test-", dir=existing)
    except OSError as exc:
        raise OMG4Error(f"{what}: cannot write in {existing} ({exc.strerror or exc})") from None
    os.close(fd)
    os.unlink(probe)


DATASET_MARKERS = ("poses_bounds.npy", "transforms_*.json", "train_meta.json")
"""Files whose presence makes a folder a dataset (N3DV, Blender, Panoptic) for output checks."""
IMAGE_DATASET_MARKERS = ("transforms_*.json", "train_meta.json")
"""The layouts among them whose readers take images from subfolders (Blender, Panoptic)."""


def check_outputs(outputs: dict[str, str | os.PathLike | None], *, inputs: Iterable[str | os.PathLike | None] = (),
                  datasets: Iterable[str | os.PathLike | None] = (), folders: Iterable[str] = (),
                  reserved: dict[str, Iterable[str]] | None = None, force: bool = False) -> None:
    """Refuse, before any work, outputs that cannot be written or would destroy an input.

    Args:
        outputs: option name (for messages, e.g. ``"--out"``) → output path; ``None`` entries are skipped.
        inputs: files and folders the command reads; an output may be none of them.
        datasets: dataset folders among the inputs: no output may be a file their readers take, and an
            existing file inside one is not replaced without ``force``.
        folders: the option names whose output is a folder (the others are files).
        reserved: folder option name → names (first path component inside it) the command writes there;
            no file output may be one of them or lie under one.
        force: allow replacing existing files inside dataset folders.

    An operating-system error while looking (a name too long, a folder that cannot be listed) is a
    one-line :class:`OMG4Error` too.
    """
    inputs = [Path(p) for p in inputs if p is not None]
    datasets = [Path(p) for p in datasets if p is not None]
    seen: dict[Path, str] = {}
    try:
        for name, path in ((name, Path(p)) for name, p in outputs.items() if p is not None):
            source = next((s for s in inputs if _same_file(path, s)), None)
            if source is not None:
                raise OMG4Error(f"{name} {path} would overwrite the input {source}; choose another output path")
            key = _resolved(path)
            if key in seen:
                raise OMG4Error(f"{name} and {seen[key]} name the same file {path}")
            seen[key] = name
            _check_output(name, path, name in folders, datasets, force)
        _check_reserved(outputs, folders, reserved or {})
    except OSError as exc:
        raise OMG4Error(f"cannot check the output paths: {exc.strerror or exc}") from None


def _check_output(name: str, path: Path, is_folder: bool, datasets: list[Path], force: bool) -> None:
    """One output of :func:`check_outputs`, once it is known to be no input and no other output."""
    if is_folder and path.exists() and not path.is_dir():
        raise OMG4Error(f"{name} {path} exists and is not a folder")
    if not is_folder and path.is_dir():
        raise OMG4Error(f"{name} {path} is a folder; give a file name")
    dataset = None if is_folder else next((d for d in datasets if _inside(path, d)), None)
    if not is_folder:
        from omg4.data.readers import is_dataset_file

        for folder in ([dataset] if dataset is not None else []) + _datasets_around(path):
            if is_dataset_file(path, folder):
                raise OMG4Error(f"{name} {path} would overwrite or add a file of the dataset {folder}; choose "
                                "another output path")
    if dataset is not None:
        if path.exists() and not force:
            raise OMG4Error(f"{name} {path} would replace a file inside the dataset folder; choose another "
                            "output path or add --force")
    _check_writable_folder(path if is_folder else path.parent, name)


def _holds(folder: Path, patterns: Iterable[str]) -> bool:
    return folder.is_dir() and any(next(folder.glob(p), None) is not None for p in patterns)


def _datasets_around(path: Path) -> list[Path]:
    """Dataset folders a file output could belong to: its own folder when that holds a layout's metadata file
    (:data:`DATASET_MARKERS`), and up to two folders above it when they hold a Blender or Panoptic layout's, whose
    images live in subfolders (``train/r_000.png``, ``ims/<camera>/<frame>.jpg``; N3DV reads top-level files only)."""
    parents = _resolved(path).parents
    return [folder for depth, folder in enumerate(parents[:3])
            if _holds(folder, DATASET_MARKERS if depth == 0 else IMAGE_DATASET_MARKERS)]


def _check_reserved(outputs: dict[str, str | os.PathLike | None], folders: Iterable[str],
                    reserved: dict[str, Iterable[str]]) -> None:
    """No file output names (or lies under) a name a folder output of the same command writes."""
    for folder_name, names in reserved.items():
        folder = outputs.get(folder_name)
        if folder is None:
            continue
        for name, path in outputs.items():
            if path is None or name in folders or not _inside(Path(path), Path(folder)):
                continue
            first = _resolved(path).relative_to(_resolved(folder)).parts[0]
            if first in set(names):
                raise OMG4Error(f"{name} {path} would overwrite {first}, which {folder_name} {folder} holds; "
                                "choose another output path")


__all__ = ["DATASET_MARKERS", "check_outputs"]
