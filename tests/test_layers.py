"""The packages' floors (docs/architecture.md, "Allowed import directions"): every ``omg4`` import of every module,
lazy ones inside functions included, points only where its package's row allows; a climb fails here."""

from __future__ import annotations

import ast
import re
from pathlib import Path

SOURCE = Path(__file__).resolve().parents[1] / "src" / "omg4"

ANYTHING = None
"""The application layer may import any package."""

FLOORS: dict[str, tuple[str, ...] | None] = {
    "errors": (),
    "allocator": (),
    "kernels": (),
    "atomic": ("errors",),
    "device": ("errors",),
    "distributed": ("errors",),
    "settings": ("errors",),
    "metrics": ("errors", "atomic"),
    "data": ("errors", "atomic"),
    "data.synthetic.writer": ("errors", "atomic", "io.video"),
    "render": ("device", "data", "kernels", "errors"),
    "gaussians": ("render", "kernels", "errors", "atomic"),
    "codec": ("errors", "atomic"),
    "models": ("codec", "gaussians", "render", "data", "device", "errors", "atomic"),
    "io": ("gaussians", "render.view", "data.scene", "codec.browser", "codec.coders", "codec.sequence", "errors",
           "atomic"),
    "evaluate": ("data", "render", "metrics", "distributed", "errors"),
    "prepare": ("data", "io.video", "errors", "atomic"),
    "optimize": ("data", "gaussians", "render", "metrics", "kernels", "device", "distributed", "errors"),
    "train": ("optimize", "data", "gaussians", "render", "metrics", "models", "kernels", "device", "distributed",
              "settings", "errors", "atomic"),
    "compress": ("optimize", "models", "metrics", "codec", "gaussians", "render", "data", "kernels", "device",
                 "distributed", "settings", "errors", "atomic"),
    "app.outputs": ("data", "errors"),
    "app.report": ("metrics", "atomic"),
    "api": ("compress", "data", "evaluate", "gaussians", "models", "render", "train", "errors"),
    **{app: ANYTHING for app in ("__init__", "__main__", "app", "testing")},
}
"""Package (or module, more specific) → the packages and modules it may import besides its own package."""

def imports(source: str) -> list[str]:
    """The ``omg4`` modules a module's source imports, anywhere in it, without the ``omg4.`` prefix
    (``from omg4.a import b`` counts as ``a.b`` where ``b`` is a module, else as ``a``)."""
    found = []
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.ImportFrom) and node.level == 0 and node.module and _within(node.module, "omg4"):
            package = node.module[len("omg4."):] if node.module != "omg4" else ""
            for alias in node.names:
                submodule = ".".join(filter(None, (package, alias.name)))
                found.append(submodule if _is_module(submodule) else package)
        elif isinstance(node, ast.Import):
            found += [alias.name[len("omg4."):] for alias in node.names if alias.name.startswith("omg4.")]
    return found


def _is_module(name: str) -> bool:
    path = SOURCE.joinpath(*name.split("."))
    return path.with_suffix(".py").is_file() or (path / "__init__.py").is_file()


def _within(name: str, prefix: str) -> bool:
    return name == prefix or name.startswith(prefix + ".")


def rule(module: str) -> tuple[str, tuple[str, ...] | None]:
    """The most specific row of :data:`FLOORS` for a module (dotted, without ``omg4.``)."""
    rows = [key for key in FLOORS if _within(module, key)]
    if not rows:
        raise KeyError(f"{module}: no row in FLOORS; give its package a floor")
    key = max(rows, key=len)
    return key, FLOORS[key]


def climbs(module: str, source: str) -> list[str]:
    """The imports of ``module`` that its row does not allow."""
    _, allowed = rule(module)
    if allowed is ANYTHING:
        return []
    own = module.split(".")[0]
    return [name for name in imports(source) if not _within(name, own) and not any(_within(name, a) for a in allowed)]


def modules() -> dict[str, Path]:
    out = {}
    for path in SOURCE.rglob("*.py"):
        parts = path.relative_to(SOURCE).with_suffix("").parts
        out[".".join(parts[:-1] if parts[-1] == "__init__" and len(parts) > 1 else parts)] = path
    return out


def test_every_import_points_down_its_floors():
    found = {m: climbs(m, p.read_text()) for m, p in sorted(modules().items())}
    assert {m: c for m, c in found.items() if c} == {}


def test_the_density_controls_sit_below_the_training_config_and_trainer():
    """The strategies own their settings: their package imports nothing else of training (the config is made from
    them, not they from it)."""
    found = {m: [name for name in imports(p.read_text()) if _within(name, "train")
                 and not _within(name, "train.strategies")]
             for m, p in modules().items() if _within(m, "train.strategies")}
    assert len(found) == 4 and {m: names for m, names in found.items() if names} == {}
    assert imports("from omg4.train.config import TrainConfig\n") == ["train.config"]


def test_a_climb_is_caught_lazy_or_not():
    lazy = "def f():\n    from omg4.compress.pipeline import CompressConfig\n"
    assert climbs("gaussians.model", lazy) == ["compress.pipeline"]
    assert climbs("codec.payload", "import omg4.gaussians.model\n") == ["gaussians.model"]
    assert climbs("codec.sequence", "from omg4.models import sequence\n") == ["models.sequence"]  # bytes only
    assert climbs("models.compact", "from omg4.gaussians import model\n") == []  # its row allows the decoder's parts
    assert climbs("data.scene", "from omg4 import io\n") == ["io"]
    assert climbs("data.synthetic.writer", "from omg4.io.video import write_video\n") == []
    assert climbs("app.commands.train", "from omg4.compress import api\n") == []
    assert climbs("app.report", "from omg4.compress import api\n") == ["compress.api"]  # a stricter row in the app
    assert rule("data.synthetic.writer")[0] == "data.synthetic.writer" and rule("codec.payload")[0] == "codec"


def import_graph(sources: dict[str, str]) -> dict[str, set[str]]:
    """Module → the modules of ``sources`` it imports (lazy, ``TYPE_CHECKING`` and package-level imports alike: a
    package's import counts as its ``__init__``'s), itself left out."""
    def known(name: str) -> str | None:
        while name and name not in sources:
            name = name.rsplit(".", 1)[0] if "." in name else ""
        return name or None

    return {m: {t for t in map(known, imports(src)) if t and t != m} for m, src in sources.items()}


def cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected groups of more than one module (Tarjan's algorithm, iterative)."""
    index, low, on_stack, stack, found, counter = {}, {}, set(), [], [], [0]
    for root in graph:
        if root in index:
            continue
        work = [(root, iter(sorted(graph[root])))]
        index[root] = low[root] = counter[0]
        counter[0] += 1
        stack.append(root)
        on_stack.add(root)
        while work:
            node, children = work[-1]
            child = next(children, None)
            if child is not None:
                if child not in index:
                    index[child] = low[child] = counter[0]
                    counter[0] += 1
                    stack.append(child)
                    on_stack.add(child)
                    work.append((child, iter(sorted(graph[child]))))
                elif child in on_stack:
                    low[node] = min(low[node], index[child])
                continue
            work.pop()
            if work:
                low[work[-1][0]] = min(low[work[-1][0]], low[node])
            if low[node] == index[node]:
                group = []
                while True:
                    member = stack.pop()
                    on_stack.discard(member)
                    group.append(member)
                    if member == node:
                        break
                if len(group) > 1:
                    found.append(sorted(group))
    return found


def test_no_module_imports_itself_back():
    sources = {m: p.read_text() for m, p in modules().items()}
    assert cycles(import_graph(sources)) == []


def test_a_cycle_is_caught_lazy_or_hidden():
    sources = {"codec.carry": "if TYPE_CHECKING:\n    from omg4.codec.payload import CompressedPayload\n",
               "codec.payload": "from omg4.codec import carry\n", "codec.types": ""}
    assert cycles(import_graph(sources)) == [["codec.carry", "codec.payload"]]
    sources["codec.carry"] = "def f():\n    from omg4.codec.types import CompressedPayload\n"
    assert cycles(import_graph(sources)) == []
    package = {"render": "from omg4.render.view import render_view\n",
               "render.view": "def f():\n    from omg4.render import rasterize\n"}
    assert cycles(import_graph(package)) == [["render", "render.view"]]


CODEC_NAME_BRANCH = re.compile(r"""codec\b[\w.\]\["']*\s*(?:===?|!==?)\s*["'](?:compact|ans|paper)["']"""
                               r"""|["'](?:compact|ans|paper)["']\s*(?:===?|!==?)\s*[\w.\]\["']*codec\b""")
"""A comparison of a codec (a header's ``codec``, a ``codec`` variable) with a built-in codec's name."""


def codec_name_branches(text: str) -> list[str]:
    return [m.group(0) for m in CODEC_NAME_BRANCH.finditer(text)]


def test_no_branch_on_a_codec_name_outside_the_codecs_table():
    """What a codec does, writes and may hold is its class in ``codec/coders.py``; the browser reads the same table
    (``web/decoder/codecs.js``, written from it). Nothing else, in Python or JavaScript, asks which codec it is."""
    table = {SOURCE / "codec" / "coders.py", SOURCE / "web" / "decoder" / "codecs.js"}
    forger = SOURCE / "testing"  # forges files of one codec or another on purpose: no library module imports it
    found = {str(p.relative_to(SOURCE)): codec_name_branches(p.read_text()) for p in sorted(SOURCE.rglob("*"))
             if p.suffix in (".py", ".js") and p not in table and forger not in p.parents}
    assert {name: hits for name, hits in found.items() if hits} == {}


def test_a_codec_name_branch_is_caught():
    assert codec_name_branches('if (("quaternions" in h) !== (h.codec === "compact"))') == ['codec === "compact"']
    assert codec_name_branches('codec = "ans" if header["codec"] == "paper" else x') == ['codec"] == "paper"']
    assert codec_name_branches('if "paper" != codec:') == ['"paper" != codec']
    assert codec_name_branches('decode_indices(data, n, count, "ans")') == []  # an encoding, not a codec


LIBRARY_EXCEPT = ("app", "testing", "__main__")
"""The packages whose modules may import where they need (the commands start fast by importing late)."""


def unexplained_late_imports(source: str) -> list[int]:
    """Lines of the imports inside functions of ``source`` with no reason beside them (a comment on the import or
    on the line above it)."""
    lines = source.split("\n")
    found = []
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
            for sub in ast.walk(node):
                if isinstance(sub, (ast.Import, ast.ImportFrom)):
                    beside = "".join(lines[sub.lineno - 1:sub.end_lineno])
                    if "#" not in beside and not lines[sub.lineno - 2].strip().startswith("#"):
                        found.append(sub.lineno)
    return sorted(set(found))


def test_library_modules_import_at_the_top_or_say_why_not():
    found = {m: unexplained_late_imports(p.read_text()) for m, p in sorted(modules().items())
             if m.split(".")[0] not in LIBRARY_EXCEPT}
    assert {m: lines for m, lines in found.items() if lines} == {}


def test_a_late_import_without_a_reason_is_caught():
    assert unexplained_late_imports("def f():\n    import json\n    return json\n") == [2]
    assert unexplained_late_imports("def f():\n    import gsplat  # CUDA only\n") == []
    assert unexplained_late_imports("def f():\n    # CUDA only\n    import gsplat\n") == []
