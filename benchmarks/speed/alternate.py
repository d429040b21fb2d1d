"""Before and after on one host: a benchmark run in alternating processes on another checkout's code and on this one's.

``--against CHECKOUT`` in a benchmark of this folder runs the benchmark itself ``--repeats`` times a side, the two
sides taking turns (``PYTHONPATH=<CHECKOUT>/src`` before, this checkout's ``src`` after), so that a slow spell of
a shared host falls on both; each side's run is recorded in a temporary file and the pairs are returned for one record.
"""

from __future__ import annotations

import json
import os
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

from omg4.testing.records import save_record

REPO = Path(__file__).resolve().parents[2]


def commit_of(checkout: Path) -> str:
    out = subprocess.run(["git", "rev-parse", "--short=10", "HEAD"], cwd=checkout, capture_output=True, text=True)
    return out.stdout.strip() or "unknown"


def alternating(script: Path, argv: list[str], against: Path, repeats: int) -> list[dict]:
    """``[{"code": "before"|"after", "rep": r, **that run's record}]``: ``script argv`` run ``repeats`` times on each
    side, alternating (before first)."""
    if not (against / "src" / "omg4").is_dir():
        raise SystemExit(f"--against {against}: not a checkout of omg4 (no src/omg4)")
    runs = []
    with tempfile.TemporaryDirectory() as tmp:
        for rep in range(1, repeats + 1):
            for code, src in (("before", against / "src"), ("after", REPO / "src")):
                out = Path(tmp) / f"{code}{rep}.json"
                env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(src), os.environ.get("PYTHONPATH", "")])}
                subprocess.run([sys.executable, str(script), *argv, "--json", str(out)], env=env, check=True)
                run = json.loads(out.read_text())["latest"]
                runs.append({"code": code, "rep": rep, **{k: v for k, v in run.items()
                                                          if k not in ("commit", "date", "machine", "command")}})
    return runs


def median_of(runs: list[dict], code: str, value) -> float:
    """The median over the ``code`` side's runs of ``value(run)``."""
    return statistics.median(value(r) for r in runs if r["code"] == code)


def save_alternating(record: Path, command: str, against: Path, summary: dict, runs: list[dict]) -> None:
    """Record a before/after run of :func:`alternating`: the command, the method, the ``--against`` checkout's commit,
    the ``summary`` of medians and every run's measurements."""
    save_record(record, {"command": command, "method": "alternating processes, before (the --against checkout's code "
                         "through PYTHONPATH) then after, each --repeats times; medians of the runs' medians",
                         "before_commit": commit_of(against), "summary": summary, "measurements": runs})


__all__ = ["alternating", "commit_of", "median_of", "save_alternating"]
