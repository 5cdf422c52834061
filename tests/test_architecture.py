"""The package layering of src/deltar: one-way dependencies, no cycles, small files,
tests that mirror the tree.

Every ``import deltar.x`` / ``from deltar.x import`` is counted wherever it stands:
module level, inside functions and under ``TYPE_CHECKING`` alike, so a function-local
import cannot hide a cycle. docs/architecture.md shows the same graph.
"""

from __future__ import annotations

import ast
import re
from collections import defaultdict
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SRC = ROOT / "src" / "deltar"

#: Lowest first. A package may import packages of lower layers only; packages of one
#: layer do not import each other. ``camera``, ``contract`` and ``extras`` are the modules
#: src/deltar/camera.py, src/deltar/contract.py and src/deltar/extras.py.
LAYERS: tuple[tuple[str, ...], ...] = (
    ("camera", "contract", "weights", "extras"),
    ("sensor",),
    ("io",),
    ("calibration",),
    ("models",),
    ("data",),
    ("inference",),
    ("capture", "export"),
    ("evaluation",),
    ("training", "mapping"),
    ("cli",),
    ("__main__",),
)

#: Imports against the layering that are known and being removed:
#: (importing file relative to src/deltar, imported package) -> why it is still there.
KNOWN_EXCEPTIONS: dict[tuple[str, str], str] = {}


def _package_of(path: Path) -> str:
    """Node of a file: its subpackage, or the top-level module's name."""
    parts = path.relative_to(SRC).parts
    return parts[0] if len(parts) > 1 else path.stem


def _imported_modules(tree: ast.AST) -> list[tuple[str, int]]:
    found = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            found += [(alias.name, node.lineno) for alias in node.names]
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            found += [(f"{node.module}.{alias.name}", node.lineno) for alias in node.names]
        elif isinstance(node, ast.ImportFrom) and node.level:
            raise AssertionError(f"relative import at line {node.lineno}: use deltar.<...>")
    return found


def import_edges() -> dict[tuple[str, str], list[str]]:
    """(importer, imported) package pairs -> the places (``file:line``) that import."""
    edges: dict[tuple[str, str], list[str]] = defaultdict(list)
    for path in sorted(SRC.rglob("*.py")):
        importer = _package_of(path)
        for name, line in _imported_modules(ast.parse(path.read_text(), str(path))):
            parts = name.split(".")
            if parts[0] != "deltar" or len(parts) < 2:
                continue
            target = parts[1]
            if target != importer:
                rel = path.relative_to(SRC).as_posix()
                edges[(importer, target)].append(f"{rel}:{line}")
    return dict(edges)


def _layer() -> dict[str, int]:
    return {name: i for i, layer in enumerate(LAYERS) for name in layer}


def _is_known(importer: str, target: str, places: list[str]) -> bool:
    return all((p.rsplit(":", 1)[0], target) in KNOWN_EXCEPTIONS for p in places)


def layered_edges() -> set[tuple[str, str]]:
    """Package dependencies without the known exceptions."""
    return {(a, b) for (a, b), places in import_edges().items()
            if not _is_known(a, b, places)}


def test_every_package_has_a_layer():
    nodes = {_package_of(p) for p in SRC.rglob("*.py")} - {"__init__"}
    assert nodes - set(_layer()) == set(), "add new packages to LAYERS"


def test_imports_point_down_the_layers():
    layer = _layer()
    upward = {f"{a} -> {b}": [p for p in places if (p.rsplit(":", 1)[0], b)
                              not in KNOWN_EXCEPTIONS]
              for (a, b), places in import_edges().items()
              if layer[b] >= layer[a] and not _is_known(a, b, places)}
    assert upward == {}, "imports against the layering (see docs/architecture.md)"


def _reachable(graph: dict[str, set[str]], start: str) -> set[str]:
    seen, todo = set(), list(graph.get(start, ()))
    while todo:
        node = todo.pop()
        if node not in seen:
            seen.add(node)
            todo += graph.get(node, ())
    return seen


def _graph(edges: set[tuple[str, str]]) -> dict[str, set[str]]:
    graph: dict[str, set[str]] = defaultdict(set)
    for a, b in edges:
        graph[a].add(b)
    return graph


def test_no_package_cycles():
    graph = _graph(layered_edges())
    on_cycles = sorted(node for node in graph if node in _reachable(graph, node))
    assert on_cycles == [], f"packages on an import cycle: {on_cycles}"


def _reduced(edges: set[tuple[str, str]]) -> set[tuple[str, str]]:
    """The edges not implied by a longer path (the graph is acyclic)."""
    graph = _graph(edges)
    return {(a, b) for a, b in edges
            if not any(b in _reachable(graph, c) for c in graph[a] - {b})}


def test_architecture_doc_shows_this_graph():
    text = (ROOT / "docs" / "architecture.md").read_text()
    edges = {(a, b) for a, b in layered_edges() if a != "__main__"}
    block = re.search(r"```mermaid\n(.*?)```", text, re.S)
    assert block, "docs/architecture.md needs a ```mermaid block with the import graph"
    drawn = set(re.findall(r"^\s*(\w+) --> (\w+)\s*$", block.group(1), re.M))
    assert drawn == _reduced(edges), (
        f"missing in the doc: {sorted(_reduced(edges) - drawn)}; "
        f"not in the code: {sorted(drawn - _reduced(edges))}")
    listed = re.search(r"```text\n(.*?)```", text, re.S)
    assert listed, "docs/architecture.md needs a ```text block: 'package: its imports'"
    direct = {(line.split(":")[0].strip(), dep.strip())
              for line in listed.group(1).splitlines() if ":" in line
              for dep in line.split(":", 1)[1].split(",") if dep.strip() != "-"}
    assert direct == edges, (f"missing in the doc: {sorted(edges - direct)}; "
                             f"not in the code: {sorted(direct - edges)}")


def _module_of(path: Path) -> str:
    parts = path.relative_to(SRC.parent).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def module_edges() -> dict[str, set[str]]:
    """Module -> the deltar modules it imports, function-local imports included.

    ``from deltar.a import b`` counts as importing ``deltar.a.b`` when that is a module,
    else ``deltar.a``; a package's ``__init__`` is the module ``deltar.a``.
    """
    modules = {_module_of(p) for p in SRC.rglob("*.py")}
    graph: dict[str, set[str]] = defaultdict(set)
    for path in sorted(SRC.rglob("*.py")):
        importer = _module_of(path)
        for name, _ in _imported_modules(ast.parse(path.read_text(), str(path))):
            target = name if name in modules else name.rsplit(".", 1)[0]
            while target not in modules and "." in target:
                target = target.rsplit(".", 1)[0]
            if target.startswith("deltar") and target != importer and target in modules:
                graph[importer].add(target)
    return dict(graph)


def test_no_module_cycles():
    """No two files import each other, directly or through others (lazy imports too).

    A module importing its own package's ``__init__`` counts too: modules import their
    siblings, never the package that re-exports them.
    """
    graph = module_edges()
    on_cycles = sorted(node for node in graph if node in _reachable(graph, node))
    assert on_cycles == [], f"modules on an import cycle: {on_cycles}"



#: Most lines a source file may have: a file longer than this holds more than one
#: concept and is split by concern (docs/architecture.md names the modules).
MAX_FILE_LINES = 500


def test_no_source_file_is_over_the_line_limit():
    sizes = {path.relative_to(SRC).as_posix(): len(path.read_text().splitlines())
             for path in sorted(SRC.rglob("*.py"))}
    over = {name: lines for name, lines in sizes.items() if lines > MAX_FILE_LINES}
    assert over == {}, f"files over {MAX_FILE_LINES} lines (split them by concern): {over}"


TESTS = ROOT / "tests"

#: Test files that test no single module, and what they test instead.
CROSS_CUTTING_TESTS: dict[str, str] = {
    "test_architecture.py": "the tree itself: layering, cycles, file sizes, this mirror",
    "test_docs_examples.py": "the Python examples of README.md and docs/ (they run)",
    "cli/test_bad_input.py": "every command's refusal of bad input (one error line, early)",
    "inference/test_bad_input_api.py": "the Python API's refusal of bad input",
    "weights/test_bundled_model.py": "the model file the package ships (deltar.weights)",
    "weights/test_bundled_onnx.py": "the bundled model's ONNX file (deltar.weights)",
    "cli/test_without_torch.py": "the commands of the base install, without PyTorch",
    "benchmarks/test_cross_scene.py": "the protocol script's comparisons (benchmarks/)",
}


def test_tests_mirror_the_tree():
    """Each ``tests/<package>/test_<module>.py`` tests ``src/deltar/<package>/<module>.py``."""
    modules = {p.relative_to(SRC).with_suffix("").as_posix() for p in SRC.rglob("*.py")}
    stray = []
    for path in sorted(TESTS.rglob("test_*.py")):
        rel = path.relative_to(TESTS)
        if rel.as_posix() in CROSS_CUTTING_TESTS:
            continue
        module = rel.with_name(rel.stem.removeprefix("test_")).as_posix()
        if module not in modules and f"{module}/__init__" not in modules:
            stray.append(rel.as_posix())
    assert stray == [], f"test files beside no module (name them test_<module>.py): {stray}"
