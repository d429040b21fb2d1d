"""``omg4 export MODEL --format web --out DIR``: a static folder that plays an ``.omg4`` file in any browser.

The folder holds ``index.html``, the player's ES modules (``src/omg4/web/``: the decoder, the WebGL2 renderer,
the page; no build step, nothing fetched from the network), ``model.omg4`` — the model file itself, rewritten
losslessly where it holds sections the browser has no decoder for (:func:`omg4.codec.browser.browser_decodable`);
for a long capture's sequence, ``sequence.json`` and each segment's file in ``segments/``, fetched as playback
reaches it — ``cameras.json`` with the dataset's cameras (test cameras first) when ``--data`` is given, and
``omg4-web.json``, the list of what the export wrote. Any static file server serves it
(``python -m http.server -d DIR``).

An export only ever replaces an earlier export: a folder that holds anything the list does not name is
refused before anything is written. The folder is built beside ``--out`` and renamed into place when complete, so
a failed export (a damaged file, say) leaves what was there before.
"""

from __future__ import annotations

import json
import os
from pathlib import Path

from omg4.atomic import atomic_folder
from omg4.codec.browser import browser_decodable
from omg4.codec.coders import browser_module
from omg4.codec.sequence import is_sequence, read_index, read_segment
from omg4.errors import CorruptFileError, OMG4Error

PLAYER_ROOT = Path(__file__).resolve().parent.parent / "web"
PLAYER_SUFFIXES = (".html", ".js", ".css")
MANIFEST = "omg4-web.json"
MODEL = "model.omg4"
CAMERAS = "cameras.json"
SEQUENCE = "sequence.json"
SEGMENTS = "segments"
CODECS_MODULE = Path("decoder", "codecs.js")
"""The player's table of the codecs' reading rules, written from the codecs' table as it is at export time."""


def player_files() -> list[Path]:
    """The player's files, relative to :data:`PLAYER_ROOT`."""
    return sorted(p.relative_to(PLAYER_ROOT) for p in PLAYER_ROOT.rglob("*")
                  if p.is_file() and p.suffix in PLAYER_SUFFIXES)


def check_export_folder(out: Path) -> None:
    """Refuse (one-line :class:`OMG4Error`) a folder that holds anything but an earlier export's files."""
    if not out.exists():
        return
    if not out.is_dir():
        raise OMG4Error(f"--out {out} exists and is not a folder")
    present = {p.relative_to(out).as_posix() for p in out.rglob("*") if not p.is_dir()}
    if not present:
        return
    try:
        written = set(json.loads((out / MANIFEST).read_text())["files"])
    except (OSError, ValueError, KeyError, TypeError):
        raise OMG4Error(f"--out {out} holds files and is not an omg4 web export; choose an empty or new folder") \
            from None
    extra = sorted(present - written - {MANIFEST})
    if extra:
        raise OMG4Error(f"--out {out} holds {extra[0]}, which no omg4 web export wrote; choose an empty or new folder")


def export_web(out: str | os.PathLike, model: str | os.PathLike, cameras: list | None = None,
               test_cameras: int = 0) -> dict:
    """Write the player folder ``out`` for the ``.omg4`` file ``model`` (a single model, or a sequence: then
    ``sequence.json`` and one file per segment in ``segments/``, which the page fetches as playback reaches them);
    ``cameras`` (:class:`~omg4.data.scene.Camera`, the first ``test_cameras`` of them held out) become the page's
    presets. Returns the manifest."""
    out = Path(out)
    check_export_folder(out)
    written, total, rewritten = [], 0, False
    with atomic_folder(out) as folder:  # a failure leaves the folder as it was, never half an export

        def write(name: str, content: bytes) -> None:
            path = folder / name
            path.parent.mkdir(parents=True, exist_ok=True)
            path.write_bytes(content)
            written.append(name)

        for p in player_files():
            write(p.as_posix(), browser_module().encode() if p == CODECS_MODULE else (PLAYER_ROOT / p).read_bytes())
        if is_sequence(model):
            index, segments = read_index(model), []
            for entry in index.segments:
                original = read_segment(model, entry)
                try:
                    data = browser_decodable(original)
                except CorruptFileError as exc:
                    raise CorruptFileError(f"{model}: segment {entry.index}: {str(exc).removeprefix('data: ')}") \
                        from None
                name = f"{SEGMENTS}/{entry.index:03d}.omg4"
                write(name, data)
                segments.append({"file": name, "time_range": list(entry.time_range), "frames": list(entry.frames),
                                 "bytes": len(data), "reference": entry.reference})
                total, rewritten = total + len(data), rewritten or data != original
            write(SEQUENCE, json.dumps({"fps": index.fps, "key_interval": index.key_interval, "segments": segments},
                                       indent=1).encode())
        else:
            data = browser_decodable(model)
            write(MODEL, data)
            total, rewritten = len(data), data != Path(model).read_bytes()
        if cameras:
            presets = [{**c.to_json(), "test": i < test_cameras} for i, c in enumerate(cameras)]
            write(CAMERAS, json.dumps({"cameras": presets}, indent=1).encode())
        manifest = {"files": sorted(written), "model_bytes": total, "rewritten": rewritten}
        (folder / MANIFEST).write_text(json.dumps(manifest, indent=1))
    return manifest


__all__ = ["CAMERAS", "MANIFEST", "MODEL", "SEGMENTS", "SEQUENCE", "check_export_folder", "export_web", "player_files"]
