"""The repository carries its own design: every citation in the code resolves inside it.

Comments cite the paper and the reference behaviours with tags (``paper §4.3``, ``rt4dgs §1.4``,
``omg4 §6a``, ``data §2``) that ``docs/paper-map.md`` defines, and design documents by their
``docs/`` path; nothing cites a document outside the repository.
"""

from __future__ import annotations

import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SOURCES = sorted(p for folder in ("src", "tests", "benchmarks", "tools") for p in (ROOT / folder).rglob("*.py"))
TAG = re.compile(r"\b(paper|rt4dgs|omg4|data) §(\d+(?:\.\d+)?(?:-\d+)?[a-z]?)")
OUTSIDE = re.compile(r"DESIGN\.md|_reference\.md|data_metrics_viewer|rasterizer_backends|shared/reference|"
                     r"\b[Ii]ssue \d+")


def _text(path: Path) -> str:
    return path.read_text(encoding="utf-8")


def test_every_tag_is_a_heading_or_row_of_the_paper_map():
    paper_map = _text(ROOT / "docs" / "paper-map.md")
    tags = {f"{kind} §{number}" for path in SOURCES for kind, number in TAG.findall(_text(path))}
    assert len(tags) > 20  # the scan sees the code's citations
    missing = sorted(tag for tag in tags if tag not in paper_map)
    assert not missing, f"cited in the code but not defined in docs/paper-map.md: {missing}"


def test_no_citation_of_a_document_outside_the_repository():
    offenders = {str(path.relative_to(ROOT)): OUTSIDE.findall(_text(path)) for path in SOURCES
                 if path != Path(__file__).resolve()}
    offenders = {name: found for name, found in offenders.items() if found}
    assert not offenders, f"cite docs/ instead, or state the reason inline: {offenders}"


def test_cited_docs_exist():
    cited = {m for path in SOURCES for m in re.findall(r"docs/[\w-]+\.md", _text(path))}
    assert cited and all((ROOT / name).is_file() for name in cited), cited


#: words about how the work was organised, which the project's files never use about themselves
ORGANISATION_WORDS = re.compile(r"\bsessions?\b|\bissues? ?#?\d+|\bhelpers?\b|\bthrow-? ?away\b|\breview(s|ed|er|ers)?\b",
                                re.IGNORECASE)


def _project_files() -> list[Path]:
    """What a user reads: the README, the changelog, docs/, benchmarks/ with its scripts and results, tools/."""
    files = [ROOT / "README.md", ROOT / "CHANGELOG.md"]
    for folder in ("docs", "benchmarks", "tools"):
        files += [p for p in (ROOT / folder).rglob("*") if p.is_file() and p.suffix in (".md", ".py", ".json", ".toml")
                  and "__pycache__" not in p.parts]
    return sorted(p for p in files if p.exists())


def organisation_words(text: str) -> list[str]:
    return [m.group(0) for m in ORGANISATION_WORDS.finditer(text)]


def test_the_scan_finds_each_word_it_looks_for():
    planted = "In session 3 a helper did a throw-away run, reviewed for issue 12 (issue #7, throwaway review)."
    assert organisation_words(planted) == ["session", "helper", "throw-away", "reviewed", "issue 12", "issue #7",
                                           "throwaway", "review"]
    assert organisation_words("sessionless preview of the issuer's helpful reviewing tool") == []


def test_project_files_speak_of_the_project_alone():
    files = _project_files()
    assert len(files) > 30 and ROOT / "README.md" in files
    found = {str(p.relative_to(ROOT)): sorted(set(organisation_words(_text(p)))) for p in files}
    found = {name: words for name, words in found.items() if words}
    assert not found, f"words about how the work was organised: {found}"
