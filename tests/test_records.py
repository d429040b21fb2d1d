"""Every figure can be made again: each record's latest run names a commit of this history (never a modified tree),
its date, machine and command, and the script its command runs exists at that commit; docs/results.md cites only
records that exist, and every section of it that shows a table names its record or says that it has none."""

from __future__ import annotations

import json
import re
import shlex
import subprocess
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "benchmarks" / "results"
RECORDS = sorted(RESULTS.glob("*.json"))


def git(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run(["git", *args], cwd=ROOT, capture_output=True, text=True)


def history_available() -> bool:
    shallow = git("rev-parse", "--is-shallow-repository")
    return shallow.returncode == 0 and shallow.stdout.strip() == "false"


needs_history = pytest.mark.skipif(not history_available(), reason="needs the project's whole git history")


def latest(path: Path) -> dict:
    return json.loads(path.read_text())["latest"]


def test_there_are_records():
    assert len(RECORDS) > 50


@pytest.mark.parametrize("path", RECORDS, ids=lambda p: p.name)
def test_a_records_latest_run_names_its_date_machine_and_command(path):
    run = latest(path)
    assert isinstance(run, dict), f"{path.name} has no latest run"
    assert re.fullmatch(r"\d{4}-\d\d-\d\dT\d\d:\d\d:\d\dZ", str(run.get("date"))), f"{path.name}: date"
    assert run.get("machine"), f"{path.name}: machine"
    assert isinstance(run.get("command"), str) and run["command"].strip(), f"{path.name}: command"
    assert re.fullmatch(r"[0-9a-f]{7,40}", str(run.get("commit"))), \
        f"{path.name}: commit {run.get('commit')!r} is not a clean commit (no +dirty, no notes)"
    assert isinstance(run.get("provenance", ""), str)


@needs_history
@pytest.mark.parametrize("path", RECORDS, ids=lambda p: p.name)
def test_a_records_commit_is_in_the_history_and_holds_the_script_it_ran(path):
    run = latest(path)
    commit = run["commit"]
    assert git("cat-file", "-e", f"{commit}^{{commit}}").returncode == 0, f"{path.name}: no commit {commit}"
    try:
        words = shlex.split(run["command"].split(";")[0])
    except ValueError:
        words = run["command"].split()
    scripts = [w for w in words if w.endswith(".py") and not w.startswith("-")]
    for script in scripts[:1]:
        assert git("cat-file", "-e", f"{commit}:{script}").returncode == 0, \
            f"{path.name}: {script} does not exist at {commit}"


RESULTS_PAGE = (ROOT / "docs" / "results.md").read_text()


def test_the_results_page_cites_only_records_that_exist():
    cited = set(re.findall(r"benchmarks/results/([\w.-]+\.(?:json|md|png))", RESULTS_PAGE))
    assert cited
    missing = sorted(name for name in cited if not (RESULTS / name).exists())
    assert not missing, f"docs/results.md cites records that do not exist: {missing}"


def sections(text: str) -> list[tuple[str, str]]:
    parts = re.split(r"^(#{2,3} .*)$", text, flags=re.M)
    return [(parts[i].strip(), parts[i + 1]) for i in range(1, len(parts) - 1, 2)]


def test_every_table_of_the_results_page_names_its_record():
    """A section with a table cites a record (its own, or the one of the ``##`` section it belongs to)."""
    outer_cites = False
    unsourced = []
    for heading, body in sections(RESULTS_PAGE):
        cites = "benchmarks/results/" in body or "no record:" in body
        if heading.startswith("## "):
            outer_cites = cites
        has_table = re.search(r"^\|.*\|\s*$", body, flags=re.M) is not None
        if has_table and not (cites or outer_cites):
            unsourced.append(heading)
    assert not unsourced, f"sections of docs/results.md with a table but no record: {unsourced}"
