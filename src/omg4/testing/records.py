"""The machine and commit a measurement ran on, and its result file as a record of runs.

Every ``benchmarks/results/<name>.json`` holds ``latest`` (the newest run) and ``history``: the runs
before it, keyed by ``"<date> <commit>"``. Each run carries its commit, its date (UTC), the machine and the
command that made it, so that the figure can be made again from that commit. A run from a tree whose sources,
benchmarks or tools differ from its commit is refused for the project's records (``+dirty`` is written only
to records elsewhere); a run that the project keeps but that could not be made from a clean commit says so in
its ``provenance``. The benchmarks (``benchmarks/speed``, ``benchmarks/studies``) and the tools (``tools/``) of a
checkout write through it; ``tests/test_records.py`` checks every record's latest run.
"""

from __future__ import annotations

import datetime
import json
import os
import platform
import shlex
import subprocess
import sys
import tempfile
from pathlib import Path

from omg4.atomic import write_text_atomic

REPO = Path(__file__).resolve().parents[3]
"""The checkout this package runs from (an editable install; elsewhere git finds no commit: "unknown")."""

RESULTS = REPO / "benchmarks" / "results"
"""Where the project's records live."""


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
    """The checked-out commit (short hash), ``+dirty`` when sources, benchmarks or tools (records aside) differ
    from it."""
    def git(*args):
        return subprocess.run(["git", *args], cwd=REPO, capture_output=True, text=True).stdout.strip()

    head = git("rev-parse", "--short=10", "HEAD") or "unknown"
    dirty = git("status", "--porcelain", "--untracked-files=normal", "--", "src", "benchmarks", "tools",
                ":!benchmarks/results")
    return head + ("+dirty" if dirty else "")


def command_line() -> str:
    """The command this process runs, as a shell would take it (``python <script> <arguments>``)."""
    script = Path(sys.argv[0])
    try:
        script = script.resolve().relative_to(REPO)
    except ValueError:
        pass
    return shlex.join(["python", str(script), *sys.argv[1:]])


def stamp() -> dict:
    """Commit, date, machine and command of a run starting now."""
    return {"commit": commit(), "date": datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%dT%H:%M:%SZ"),
            "machine": machine(), "command": command_line()}


def save_record(path: Path, result: dict) -> dict:
    """Add ``result`` (with :func:`stamp`: a ``command`` or ``machine`` of its own wins, never a commit or date) as the
    latest run of the record at ``path``; the previous latest run moves into the history. Written atomically; returns
    the stamped run. While the code differs from its commit, a project record (under :data:`RESULTS`) is written to
    the system's temporary folder instead, so that the project's records name only code that exists."""
    path = Path(path)
    stamped = stamp()
    run = {**stamped, **result, "commit": stamped["commit"], "date": stamped["date"]}
    if "dirty" in run["commit"] and path.resolve().parent == RESULTS.resolve():
        aside = Path(tempfile.gettempdir()) / "omg4-records" / path.name
        print(f"the sources, benchmarks or tools differ from commit {run['commit'].split('+')[0]}: the record goes "
              f"to {aside}, not {path} (commit, then run again for the project's record)")
        path = aside
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
