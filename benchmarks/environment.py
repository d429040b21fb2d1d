"""The machine a benchmark ran on, as the results JSON of ``decode.py``, ``decode_omg4.py`` and ``rate.py`` record it.

Imported by those scripts as a sibling module (``python benchmarks/<script>.py`` puts this folder on ``sys.path``).
"""

from __future__ import annotations

import os
import platform


def machine() -> dict:
    """Platform string, Python version and CPU count."""
    return {"platform": platform.platform(), "python": platform.python_version(), "cpu_count": os.cpu_count()}
