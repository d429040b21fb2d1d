"""Mutation testing: each package of omg4 against its own tests.

A *mutant* is one small change of the kind a developer writes by mistake, planted in one copy
of the package at a time: a comparison flipped (``<`` ↔ ``<=``, ``==`` ↔ ``!=``, ``is`` ↔ ``is not``),
an arithmetic or bitwise operator swapped (``+`` ↔ ``-``, ``*`` ↔ ``/``, ``&`` ↔ ``|``, …), ``and`` ↔ ``or``,
a ``not`` or a unary minus dropped, an integer off by one, ``True`` ↔ ``False``, ``min`` ↔ ``max``,
``break`` → ``continue``. A mutant is *killed* when a test of the package's folder fails (or the run
exceeds its time limit, or a test process dies of a signal), and *survives* when they all pass. The mutation score is killed / (all −
equivalent), where an equivalent mutant is one with no observable change, explained in
``tools/mutation_equivalents.toml``.

Why a harness of our own rather than mutmut or cosmic-ray: mutmut 3 runs each mutant in a process
forked from one that has already run torch's and numba's thread pools (neither is fork-safe) and
cannot place its trampolines inside ``@njit`` kernels; cosmic-ray runs the whole test command for
every mutant. Here each mutant runs in a fresh interpreter, only the tests that execute the mutated
line (from one coverage run per package with per-test contexts; for lines coverage cannot see —
numba kernels, which their callers in other modules run: every test of the target; code run at import:
every test that executes the module), fastest first, and they stop at the first failure.

Which mutants run: all of them with ``--fraction 1``, or the stable sample of the given fraction
(a mutant is in it when the hash of its identity — file, function, operator, text and occurrence,
not its line number — falls below the fraction; at least the ``--min-mutants`` lowest of a package), so an
edit elsewhere does not reshuffle the sample.

Usage: ``python tools/mutation.py [--packages compress train …] [--fraction 0.1] [--min-mutants 20]
[--json OUT]``.
Needs ``pytest-cov`` (``pip install pytest-cov``). Resumable: finished mutants are kept in
``--work``/outcomes.jsonl and skipped by a re-run of the same tree.
"""

from __future__ import annotations

import argparse
import ast
import hashlib
import json
import os
import shutil
import subprocess
import sys
import time
import tomllib
from dataclasses import dataclass
from pathlib import Path

from omg4.testing.records import save_record

REPO = Path(__file__).resolve().parents[1]
#: what is mutated → (its sources, the tests that guard it, whether coverage can map its lines to tests: not for
#: code that runs in the processes a test starts)
TARGETS: dict[str, tuple[tuple[str, ...], str, bool]] = {
    "compress": (("src/omg4/compress",), "tests/compress", True),
    "train": (("src/omg4/train",), "tests/train", True),
    "metrics": (("src/omg4/metrics",), "tests/metrics", True),
    "codec": (("src/omg4/codec",), "tests/codec", True),
    "models": (("src/omg4/models",), "tests/codec", True),  # the decoder's and the sequence's tests live there
    "gaussians": (("src/omg4/gaussians",), "tests/gaussians", True),
    "render": (("src/omg4/render",), "tests/render", True),
    "distributed": (("src/omg4/distributed.py", "src/omg4/app/launch.py"), "tests/test_distributed.py", False),
    "segments": (("src/omg4/data/segments.py",), "tests/data/test_segment_plans.py", True),
}
PACKAGES = tuple(TARGETS)
#: code that runs only on CUDA, whose tests a CPU machine skips: its mutants would measure nothing here
CUDA_ONLY = ("src/omg4/render/gsplat_backend.py",)
#: outcomes that catch the mutant: a test failed, the run overran its time, or a test process died of a signal
#: (the mutant made it run out of memory)
CAUGHT = ("killed", "timeout", "crashed")
EQUIVALENTS = Path(__file__).with_name("mutation_equivalents.toml")

_COMPARE = {ast.Lt: "<=", ast.LtE: "<", ast.Gt: ">=", ast.GtE: ">", ast.Eq: "!=", ast.NotEq: "==",
            ast.Is: "is not", ast.IsNot: "is", ast.In: "not in", ast.NotIn: "in"}
_COMPARE_TEXT = {ast.Lt: "<", ast.LtE: "<=", ast.Gt: ">", ast.GtE: ">=", ast.Eq: "==", ast.NotEq: "!=",
                 ast.Is: "is", ast.IsNot: "is not", ast.In: "in", ast.NotIn: "not in"}
_BINARY = {ast.Add: ("+", "-"), ast.Sub: ("-", "+"), ast.Mult: ("*", "/"), ast.Div: ("/", "*"),
           ast.FloorDiv: ("//", "/"), ast.Mod: ("%", "//"), ast.Pow: ("**", "*"), ast.BitAnd: ("&", "|"),
           ast.BitOr: ("|", "&"), ast.BitXor: ("^", "|"), ast.LShift: ("<<", ">>"), ast.RShift: (">>", "<<")}
_SWAPPED_NAMES = {"min": "max", "max": "min", "minimum": "maximum", "maximum": "minimum", "amin": "amax",
                  "amax": "amin"}
_NUMBA_DECORATORS = {"njit", "jit", "vectorize", "guvectorize"}


@dataclass(frozen=True)
class Mutant:
    """One planted change: replace ``original`` at characters [start, end) of ``path`` by ``replacement``."""

    package: str
    path: str  # relative to the repository
    function: str  # qualified name of the enclosing function or class ("" at module level)
    line: int
    start: int
    end: int
    operator: str
    original: str
    replacement: str
    occurrence: int  # among the mutants of the same function, operator and texts
    in_kernel: bool  # inside a numba-compiled function (not traced by coverage)

    @property
    def key(self) -> str:
        """The identity that survives edits elsewhere in the file (no line number)."""
        return f"{self.path}::{self.function}::{self.operator}::{self.original}->{self.replacement}#{self.occurrence}"

    @property
    def draw(self) -> float:
        """Where the hash of :attr:`key` falls in [0, 1): the mutant's place in every sample."""
        return int.from_bytes(hashlib.sha256(self.key.encode()).digest()[:8], "big") / 2**64


def sample(mutants: list[Mutant], fraction: float, at_least: int) -> list[Mutant]:
    """The mutants whose :attr:`Mutant.draw` falls below ``fraction``, or the ``at_least`` lowest when those are
    fewer (a small package still gets a sample that can tell a score), in their order in the package."""
    ranked = sorted(mutants, key=lambda m: m.draw)
    chosen = {m.key for m in ranked[:max(sum(m.draw < fraction for m in mutants), at_least)]}
    return [m for m in mutants if m.key in chosen]


class _Collector(ast.NodeVisitor):
    """Walks one module and lists its mutants (skips docstrings, annotations, decorators, f-strings)."""

    def __init__(self, package: str, path: str, source: str):
        self.package, self.path, self.source = package, path, source
        self.line_starts = [0]
        for line in source.splitlines(keepends=True):
            self.line_starts.append(self.line_starts[-1] + len(line))
        self.lines = source.splitlines(keepends=True)
        self.scope: list[str] = []
        self.kernel_depth = 0
        self.found: list[tuple] = []

    # -- positions (ast gives UTF-8 byte columns)
    def offset(self, line: int, col: int) -> int:
        text = self.lines[line - 1].encode()
        return self.line_starts[line - 1] + len(text[:col].decode())

    def span(self, node) -> tuple[int, int]:
        return self.offset(node.lineno, node.col_offset), self.offset(node.end_lineno, node.end_col_offset)

    def add(self, node_line: int, start: int, end: int, operator: str, replacement: str) -> None:
        self.found.append((".".join(self.scope), node_line, start, end, operator, self.source[start:end], replacement,
                           self.kernel_depth > 0))

    def token_between(self, left, right, token: str, line: int, operator: str, replacement: str) -> None:
        """Mutate the operator ``token`` found between the end of ``left`` and the start of ``right``."""
        a = self.offset(left.end_lineno, left.end_col_offset)
        b = self.offset(right.lineno, right.col_offset)
        gap = self.source[a:b]
        code = gap.split("#")[0] if "\n" not in gap else gap
        at = _find_token(code, token)
        if at >= 0:
            self.add(line, a + at, a + at + len(token), operator, replacement)

    # -- scopes
    def _visit_scope(self, node, name: str, body_fields: tuple[str, ...]) -> None:
        kernel = any(_decorator_name(d) in _NUMBA_DECORATORS for d in getattr(node, "decorator_list", ()))
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):  # evaluated where the function is defined
            for default in (*node.args.defaults, *(d for d in node.args.kw_defaults if d is not None)):
                self.visit(default)
        self.scope.append(name)
        self.kernel_depth += kernel
        body = node.body
        if body and isinstance(body[0], ast.Expr) and isinstance(body[0].value, ast.Constant) and isinstance(
                body[0].value.value, str):
            body = body[1:]  # the docstring
        for stmt in body:
            self.visit(stmt)
        self.kernel_depth -= kernel
        self.scope.pop()

    def visit_FunctionDef(self, node):
        self._visit_scope(node, node.name, ("body",))

    visit_AsyncFunctionDef = visit_FunctionDef

    def visit_ClassDef(self, node):
        for base in node.bases:
            self.visit(base)
        self._visit_scope(node, node.name, ("body",))

    def visit_Module(self, node):
        body = node.body
        if body and isinstance(body[0], ast.Expr) and isinstance(body[0].value, ast.Constant):
            body = body[1:]
        for stmt in body:
            self.visit(stmt)

    # -- what is never mutated
    def visit_AnnAssign(self, node):
        if node.value is not None:
            self.visit(node.value)

    def visit_JoinedStr(self, node):
        return

    def visit_Assign(self, node):
        if any(isinstance(t, ast.Name) and t.id == "__all__" for t in node.targets):
            return
        self.generic_visit(node)

    def visit_If(self, node):
        if _is_main_guard(node.test):
            return
        self.generic_visit(node)

    def visit_Expr(self, node):
        if isinstance(node.value, ast.Constant):
            return  # a bare string (comment-like)
        self.generic_visit(node)

    # -- operators
    def visit_Compare(self, node):
        left = node.left
        for op, right in zip(node.ops, node.comparators):
            kind = type(op)
            self.token_between(left, right, _COMPARE_TEXT[kind], node.lineno, "compare", _COMPARE[kind])
            left = right
        self.generic_visit(node)

    def visit_BinOp(self, node):
        if type(node.op) in _BINARY:
            token, replacement = _BINARY[type(node.op)]
            self.token_between(node.left, node.right, token, node.lineno, "binary", replacement)
        self.generic_visit(node)

    def visit_AugAssign(self, node):
        if type(node.op) in _BINARY:
            token, replacement = _BINARY[type(node.op)]
            self.token_between(node.target, node.value, token + "=", node.lineno, "augmented", replacement + "=")
        self.generic_visit(node)

    def visit_BoolOp(self, node):
        token, replacement = ("and", "or") if isinstance(node.op, ast.And) else ("or", "and")
        for left, right in zip(node.values, node.values[1:]):
            self.token_between(left, right, token, node.lineno, "boolean", replacement)
        self.generic_visit(node)

    def visit_UnaryOp(self, node):
        if isinstance(node.op, (ast.Not, ast.USub, ast.Invert)):
            start = self.offset(node.lineno, node.col_offset)
            token = "not" if isinstance(node.op, ast.Not) else self.source[start]
            self.add(node.lineno, start, start + len(token), "unary", "")
        self.generic_visit(node)

    def visit_Constant(self, node):
        start, end = self.span(node)
        if isinstance(node.value, bool):
            self.add(node.lineno, start, end, "boolean constant", str(not node.value))
        elif isinstance(node.value, int) and self.source[start:end].isdigit():
            self.add(node.lineno, start, end, "integer", str(node.value + 1))

    def visit_Name(self, node):
        if node.id in _SWAPPED_NAMES and isinstance(node.ctx, ast.Load):
            start, end = self.span(node)
            self.add(node.lineno, start, end, "min/max", _SWAPPED_NAMES[node.id])

    def visit_Attribute(self, node):
        self.visit(node.value)
        if node.attr in _SWAPPED_NAMES and isinstance(node.ctx, ast.Load):
            end = self.offset(node.end_lineno, node.end_col_offset)
            self.add(node.end_lineno, end - len(node.attr), end, "min/max", _SWAPPED_NAMES[node.attr])

    def visit_Break(self, node):
        start, end = self.span(node)
        self.add(node.lineno, start, end, "break", "continue")

    def visit_arguments(self, node):
        return  # defaults are visited by the function; annotations never

    def visit_Lambda(self, node):
        self.visit(node.body)


def _find_token(code: str, token: str) -> int:
    """Index of ``token`` as a whole operator in ``code`` (no longer operator containing it), or −1."""
    symbols = "<>=!*/%&|^+-"
    at = code.find(token)
    while at >= 0:
        before = code[at - 1] if at else " "
        after = code[at + len(token)] if at + len(token) < len(code) else " "
        if token.isalpha() or " " in token:
            whole = not (before.isalnum() or before == "_") and not (after.isalnum() or after == "_")
        else:
            whole = before not in symbols and after not in symbols
        if whole:
            return at
        at = code.find(token, at + 1)
    return -1


def _decorator_name(node) -> str:
    node = node.func if isinstance(node, ast.Call) else node
    return node.attr if isinstance(node, ast.Attribute) else getattr(node, "id", "")


def _is_main_guard(test) -> bool:
    return (isinstance(test, ast.Compare) and isinstance(test.left, ast.Name) and test.left.id == "__name__")


def mutants_of(package: str, path: Path) -> list[Mutant]:
    """Every mutant of one module of ``package``."""
    source = path.read_text()
    collector = _Collector(package, str(path.relative_to(REPO)), source)
    collector.visit(ast.parse(source))
    seen: dict[tuple, int] = {}
    out = []
    for function, line, start, end, operator, original, replacement, kernel in sorted(collector.found,
                                                                                      key=lambda f: f[2]):
        ident = (function, operator, original, replacement)
        seen[ident] = seen.get(ident, -1) + 1
        out.append(Mutant(package, collector.path, function, line, start, end, operator, original, replacement,
                          seen[ident], kernel))
    return out


def package_mutants(package: str) -> list[Mutant]:
    """Every mutant of a target's sources (:data:`TARGETS`)."""
    paths = []
    for source in TARGETS[package][0]:
        path = REPO / source
        paths += sorted(path.rglob("*.py")) if path.is_dir() else [path]
    return [m for path in paths if str(path.relative_to(REPO)) not in CUDA_ONLY for m in mutants_of(package, path)]


# ------------------------------------------------------------------------------------------ running
class Workspace:
    """A private copy of the repository's sources and tests in which mutants are planted one at a time."""

    def __init__(self, folder: Path):
        folder = folder.resolve()
        self.root = folder / "tree"
        if self.root.exists():
            shutil.rmtree(self.root)
        for part in ("src", "tests", "benchmarks", "docs"):  # some tests read benchmark modules and the docs
            shutil.copytree(REPO / part, self.root / part, ignore=shutil.ignore_patterns("__pycache__", "*.nbi",
                                                                                         "*.nbc", "results"))
        for name in ("pyproject.toml", "README.md"):
            shutil.copy(REPO / name, self.root / name)
        shared = Path(os.environ.get("OMG4_SHARED_DATA", REPO.parent / "shared" / "data")).resolve()
        self.env = {**os.environ, "PYTHONPATH": str(self.root / "src"), "PYTHONDONTWRITEBYTECODE": "1",
                    "NUMBA_CACHE_DIR": str(folder / "numba_cache"), "OMG4_SHARED_DATA": str(shared),
                    "OMP_WAIT_POLICY": "PASSIVE"}
        imported = subprocess.run([sys.executable, "-c", "import omg4; print(omg4.__file__)"], cwd=self.root,
                                  env=self.env, capture_output=True, text=True).stdout.strip()
        if not Path(imported).is_relative_to(self.root / "src"):
            raise SystemExit(f"the copy's tests would import omg4 from {imported}, not from the copy")

    def pytest(self, args: list[str], timeout: float) -> tuple[int, float]:
        """Exit status of ``pytest args`` in the copy (−1 on timeout) and its seconds."""
        t0 = time.perf_counter()
        cmd = [sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", *args]
        try:
            proc = subprocess.run(cmd, cwd=self.root, env=self.env, stdout=subprocess.DEVNULL,
                                  stderr=subprocess.DEVNULL, timeout=timeout)
            return proc.returncode, time.perf_counter() - t0
        except subprocess.TimeoutExpired:
            return -1, time.perf_counter() - t0

    def collects(self, tests: list[str]) -> bool:
        """Whether pytest collects the files of ``tests`` in the copy (a mutant that breaks importing the package
        or building a test's parameters makes their ids unknown to pytest, exit 4)."""
        rc, _ = self.pytest(["--collect-only", *sorted({t.split("::")[0] for t in tests})], timeout=600)
        return rc == 0

    def planted(self, mutant: Mutant):
        return _Planted(self.root / mutant.path, mutant)


class _Planted:
    def __init__(self, path: Path, mutant: Mutant):
        self.path, self.mutant = path, mutant

    def __enter__(self):
        self.original = self.path.read_text()
        m = self.mutant
        assert self.original[m.start:m.end] == m.original, (m.key, self.original[m.start:m.end])
        self.path.write_text(self.original[:m.start] + m.replacement + self.original[m.end:])

    def __exit__(self, *exc):
        self.path.write_text(self.original)


@dataclass
class TestMap:
    """Which tests execute each line of a package (from a coverage run with per-test contexts)."""

    by_line: dict[str, dict[int, list[str]]]  # path → line → test ids
    by_module: dict[str, list[str]]  # path → tests that execute any of its function bodies
    seconds: dict[str, float]  # test id → seconds (under coverage)
    every: list[str] | None = None  # all the target's tests, for every mutant (code the tests run in subprocesses)

    def tests_for(self, mutant: Mutant) -> list[str]:
        if self.every is not None:
            return self.every
        if mutant.in_kernel:  # coverage never sees a kernel's lines, and its callers live in other modules
            return sorted(self.seconds, key=lambda t: (self.seconds[t], t))
        tests = self.by_line.get(mutant.path, {}).get(mutant.line, [])
        if not tests and (mutant.function == "" or "." not in mutant.function):
            # values fixed at import: the tests that run the module, or every test of the target
            tests = self.by_module.get(mutant.path) or list(self.seconds)
        return sorted(set(tests), key=lambda t: (self.seconds.get(t, 0.0), t))


def map_tests(workspace: Workspace, package: str, folder: Path) -> TestMap:
    """Run the target's tests once under coverage, one context per test; fails if a test fails. A target whose
    code runs in processes the tests start gets every one of its tests for every mutant."""
    sources, tests_path, mapped = TARGETS[package]
    data = folder / f"coverage_{package}"
    report = folder / f"durations_{package}.xml"
    modules = [f"--cov={s[len('src/'):].removesuffix('.py').replace('/', '.')}" for s in sources] if mapped else []
    rc, seconds = workspace.pytest([tests_path, *modules, "--cov-context=test", "--cov-report=",
                                    f"--junitxml={report}"] if mapped else [tests_path, f"--junitxml={report}"],
                                   timeout=3600)
    generated = workspace.root / ".coverage"
    if rc != 0:
        raise SystemExit(f"the unmutated tests of {package} do not pass (pytest exit {rc})")
    import xml.etree.ElementTree as ET

    seconds = {}
    for case in ET.parse(report).iter("testcase"):
        file = case.get("classname", "").replace(".", "/") + ".py"
        test = f"{file}::{case.get('name').split('[', 1)[0]}"  # a function, all its parameter sets
        seconds[test] = seconds.get(test, 0.0) + float(case.get("time", 0))
    if not mapped:
        every = sorted(seconds)
        return TestMap({}, {}, seconds, every)
    shutil.move(generated, data)
    import coverage

    cov = coverage.CoverageData(basename=str(data))
    cov.read()
    by_line: dict[str, dict[int, list[str]]] = {}
    by_module: dict[str, list[str]] = {}
    for measured in cov.measured_files():
        path = str(Path(measured).relative_to(workspace.root))
        # by test function (parameter ids may hold bytes that pytest cannot take back on its command line)
        lines = {line: sorted({c.rsplit("|", 1)[0].split("[", 1)[0] for c in ctx if c}) for line, ctx in
                 cov.contexts_by_lineno(measured).items()}
        by_line[path] = {line: tests for line, tests in lines.items() if tests}
        by_module[path] = sorted({t for tests in by_line[path].values() for t in tests})
    print(f"{package}: {len(seconds)} tests mapped", flush=True)
    return TestMap(by_line, by_module, seconds)


def run_mutant(workspace: Workspace, tests: TestMap, mutant: Mutant) -> dict:
    selected = tests.tests_for(mutant)
    if not selected:
        return {"outcome": "no tests", "seconds": 0.0, "selected": 0}
    budget = 60.0 + 3.0 * sum(tests.seconds.get(t, 5.0) for t in selected)
    with workspace.planted(mutant):
        rc, seconds = workspace.pytest(["-x", *selected], timeout=budget)
        if rc in (3, 4) and not workspace.collects(selected):  # its tests no longer import or collect: caught
            rc = 1
    outcome = {0: "survived", 1: "killed", 2: "killed", -1: "timeout", 5: "no tests"}.get(
        rc, "crashed" if rc < 0 else f"pytest exit {rc}")
    return {"outcome": outcome, "seconds": round(seconds, 2), "selected": len(selected)}


def load_equivalents() -> dict[str, str]:
    """Mutant key → why it changes nothing observable."""
    if not EQUIVALENTS.exists():
        return {}
    return {k: v for k, v in tomllib.loads(EQUIVALENTS.read_text()).get("equivalent", {}).items()}


def summarize(package: str, total: int, rows: list[dict], equivalents: dict[str, str]) -> dict:
    killed = sum(r["outcome"] in CAUGHT for r in rows)
    equivalent = [r for r in rows if r["outcome"] not in CAUGHT and r["key"] in equivalents]
    survivors = [r for r in rows if r["outcome"] not in CAUGHT]
    counted = len(rows) - len(equivalent)
    return {
        "mutants": total,
        "run": len(rows),
        "killed": killed,
        "timeouts": sum(r["outcome"] == "timeout" for r in rows),
        "survived": len(survivors),
        "equivalent": len(equivalent),
        "score": round(killed / counted, 4) if counted else None,
        "survivors": [{**{k: r[k] for k in ("key", "line", "original", "replacement", "outcome")},
                       "explanation": equivalents.get(r["key"])} for r in survivors],
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--packages", nargs="+", default=list(PACKAGES), choices=PACKAGES)
    ap.add_argument("--fraction", type=float, default=0.1, help="the stable sample of mutants to run (1 = all)")
    ap.add_argument("--min-mutants", type=int, default=20,
                    help="run at least this many of each package (the lowest in the sample's order)")
    ap.add_argument("--work", type=Path, default=Path("runs/mutation"))
    ap.add_argument("--json", type=Path, default=REPO / "benchmarks" / "results" / "mutation.json")
    ap.add_argument("--count", action="store_true", help="only count the mutants of each package")
    args = ap.parse_args()
    if args.count:
        for package in args.packages:
            ms = package_mutants(package)
            print(f"{package}: {len(ms)} mutants, {len(sample(ms, args.fraction, args.min_mutants))} in the sample")
        return
    args.work = args.work.resolve()
    args.work.mkdir(parents=True, exist_ok=True)
    outcomes_path = args.work / "outcomes.jsonl"
    done = {}
    if outcomes_path.exists():
        for line in outcomes_path.read_text().splitlines():
            row = json.loads(line)
            done[row["key"]] = row
    workspace = Workspace(args.work)
    equivalents = load_equivalents()
    packages = {}
    t_start = time.perf_counter()
    for package in args.packages:
        mutants = package_mutants(package)
        chosen = sample(mutants, args.fraction, args.min_mutants)
        tests_hash = _fingerprint(sorted((workspace.root / "tests").rglob("*.py")), workspace.root)
        earlier = {m.key: _reusable(done.get(m.key), m, tests_hash, workspace.root, equivalents) for m in chosen}
        tests = map_tests(workspace, package, args.work) if None in earlier.values() else None
        rows = []
        for i, m in enumerate(chosen):
            row = earlier[m.key]
            if row is None:
                row = {"key": m.key, "module": _fingerprint([workspace.root / m.path], workspace.root),
                       "tests": tests_hash, "line": m.line,
                       "original": m.original, "replacement": m.replacement, **run_mutant(workspace, tests, m)}
                with outcomes_path.open("a") as f:
                    f.write(json.dumps(row) + "\n")
                print(f"[{package} {i + 1}/{len(chosen)}] {row['outcome']:>8} {row['seconds']:6.1f}s "
                      f"{m.path}:{m.line} {m.original!r} -> {m.replacement!r}", flush=True)
            rows.append(row)
        packages[package] = summarize(package, len(mutants), rows, equivalents)
        s = packages[package]
        print(f"{package}: {s['killed']}/{s['run']} killed, {s['equivalent']} equivalent, score {s['score']}",
              flush=True)
    save_record(args.json, {
        "command": "python tools/mutation.py " + " ".join(sys.argv[1:]),
        "fraction": args.fraction, "min_mutants": args.min_mutants,
        "wall_time_s": round(time.perf_counter() - t_start, 1),
        "packages": packages,
    })


def _fingerprint(paths, root: Path) -> str:
    """A hash of the files (their path below ``root`` and bytes): the copy the mutants ran against."""
    h = hashlib.sha256()
    for path in paths:
        h.update(str(path.relative_to(root)).encode() + path.read_bytes())
    return h.hexdigest()[:16]


def _reusable(row: dict | None, mutant: Mutant, tests_hash: str, root: Path, equivalents: dict[str, str]
              ) -> dict | None:
    """An earlier outcome of ``mutant`` that still holds: same module source, and killed (tests are only
    added), explained as equivalent (no test can see it), or run against the same tests."""
    if row is None or row["module"] != _fingerprint([root / mutant.path], root):
        return None
    if row["outcome"] == "no tests":  # the mapping may find some now
        return None
    return row if row["outcome"] in CAUGHT or row["tests"] == tests_hash or mutant.key in equivalents else None


if __name__ == "__main__":
    main()
