"""The machine a benchmark ran on, and writing a result with it (``decode.py``, ``decode_omg4.py``, ``rate.py``).

Imported by those scripts as a sibling module (``python benchmarks/<script>.py`` puts this folder on ``sys.path``).
"""

from __future__ import annotations

import json
import os
import platform
from pathlib import Path

from omg4.atomic import write_text_atomic


def machine() -> dict:
    """Platform string, Python version and CPU count."""
    return {"platform": platform.platform(), "python": platform.python_version(), "cpu_count": os.cpu_count()}


def save_result(path: Path, result: dict) -> None:
    """Write ``result`` with the :func:`machine` it ran on as indented JSON to ``path`` (atomically) and say so."""
    write_text_atomic(path, json.dumps({**result, "machine": machine()}, indent=2) + "\n")
    print(f"wrote {path}")
