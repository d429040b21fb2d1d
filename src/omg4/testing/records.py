"""The machine and commit a measurement ran on, and its result file as a record of runs.

Every ``benchmarks/results/<name>.json`` holds ``latest`` (the newest run) and ``history``: the runs
before it, keyed by ``"<date> <commit>"``. Each run carries its commit (``+dirty`` when the working
tree differed from it), its date (UTC) and the machine. The benchmarks (``benchmarks/speed``,
``benchmarks/studies``) and the tools (``tools/``) of a checkout write through it.
"""

from __future__ import annotations

import datetime
import json
import os
import platform
import subprocess
from pathlib import Path

from omg4.atomic import write_text_atomic

REPO = Path(__file__).resolve().parents[3]
"""The checkout this package runs from (an editable install; elsewhere git finds no commit: "unknown")."""


def machine() -> dict:
    """Platform string, processor, Python version and CPU count."""
    return {"platform": platform.platform(), "processor": _processor(), "python": platform.python_version(),
            "cpu_count": os.cpu_count()}


def _processor() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor()


def commit() -> str:
    """The checked-out commit (short hash), ``+dirty`` when sources, benchmarks or tools differ from it."""
    def git(*args):
        return subprocess.run(["git", *args], cwd=REPO, capture_output=True, text=True).stdout.strip()

    head = git("rev-parse", "--short=10", "HEAD") or "unknown"
    dirty = git("status", "--porcelain", "--untracked-files=no", "--", "src", "benchmarks", "tools")
    return head + ("+dirty" if dirty else "")


def stamp() -> dict:
    """Commit, date and machine of a run starting now."""
    return {"commit": commit(), "date": datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%dT%H:%M:%SZ"),
            "machine": machine()}


def save_record(path: Path, result: dict) -> dict:
    """Add ``result`` (with :func:`stamp`) as the latest run of the record at ``path``; the previous latest run
    moves into the history. Written atomically; returns the stamped run."""
    path = Path(path)
    run = {**stamp(), **result}
    record = load_record(path)
    if record.get("latest"):
        previous = record["latest"]
        record["history"][f"{previous['date']} {previous['commit']}"] = previous
    record["latest"] = run
    path.parent.mkdir(parents=True, exist_ok=True)
    write_text_atomic(path, json.dumps({"latest": record["latest"], "history": record["history"]}, indent=2) + "\n")
    print(f"wrote {path}")
    return run


def load_record(path: Path) -> dict:
    """The record at ``path`` (``{"latest": None, "history": {}}`` when there is none)."""
    if not Path(path).exists():
        return {"latest": None, "history": {}}
    data = json.loads(Path(path).read_text())
    return {"latest": data.get("latest"), "history": dict(data.get("history", {}))}


def save_result(path: Path, result: dict) -> None:
    """Record ``result`` as the latest run at ``path`` (see :func:`save_record`)."""
    save_record(path, result)
