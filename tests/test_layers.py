"""The library's packages form layers: each imports only the layers below it, and nothing imports in a cycle.
The service's modules import one way too, and none of them, nor `Scene`'s module, outgrows one sitting.

The graph is built from the source (every ``import`` of every module under canonical_core, read
with ast, including imports made only for type checking), one node per package. The settings
module (``canonical_core.config``) is its own node, below every other: any layer may read
the settings. A second check imports each package first in a fresh interpreter, so no package
relies on another having been imported before it.
"""

from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
ROOT = REPO / "canonical_core"

# the layer order, lowest first: each layer may import the ones before it
LAYERS = ["settings", "resample", "calibration", "camera", "frame", "gaussians", "rendering", "evidence", "decode",
          "scene", "eval", "train"]
ALLOWED = {layer: set(LAYERS[:i]) for i, layer in enumerate(LAYERS)}
ALLOWED["datasets"] = {"resample", "calibration", "camera", "frame"}  # loaders need cameras and frames, nothing of the method
ALLOWED["eval"] |= {"datasets"}
ALLOWED["train"] |= {"datasets"}
ALLOWED["canonical_core"] = set(ALLOWED) - {"canonical_core"}  # the package's facade re-exports every layer


def module_name(path: Path, repo: Path = REPO) -> str:
    parts = path.relative_to(repo).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def node_of(module: str) -> str | None:
    """The graph node of a canonical_core module (None outside the library)."""
    parts = module.split(".")
    if parts[0] != "canonical_core":
        return None
    if parts[1:2] == ["config"]:
        return "settings"
    return parts[1] if len(parts) > 1 else "canonical_core"


def imported_modules(path: Path, repo: Path = REPO, top: str = "canonical_core") -> set[str]:
    """Absolute names of the modules of package ``top`` that ``path`` imports (anywhere in it)."""
    name = module_name(path, repo)
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    out = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            out |= {alias.name for alias in node.names}
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")[: len(package.split(".")) - node.level + 1]
                target = ".".join(base + ([node.module] if node.module else []))
            else:
                target = node.module
            out.add(target)
            if not node.module:  # `from . import x`: x is a submodule
                out |= {f"{target}.{alias.name}" for alias in node.names}
    return {m for m in out if m.split(".")[0] == top}


def package_graph(root: Path = ROOT) -> dict[str, set[str]]:
    """node -> the other nodes its modules import."""
    graph: dict[str, set[str]] = {}
    for path in sorted(root.rglob("*.py")):
        src = node_of(module_name(path, root.parent))
        targets = {node_of(m) for m in imported_modules(path, root.parent)} - {src, None}
        graph.setdefault(src, set()).update(targets)
    return graph


def find_cycle(graph: dict[str, set[str]]) -> list[str] | None:
    """A cycle of ``graph`` as a list of nodes (first == last), or None if it is acyclic."""
    state: dict[str, int] = {}  # 1: on the current path, 2: done
    path: list[str] = []

    def visit(node: str) -> list[str] | None:
        state[node] = 1
        path.append(node)
        for nxt in sorted(graph.get(node, ())):
            if state.get(nxt) == 1:
                return path[path.index(nxt):] + [nxt]
            if nxt not in state and (cycle := visit(nxt)):
                return cycle
        path.pop()
        state[node] = 2
        return None

    for node in sorted(graph):
        if node not in state and (cycle := visit(node)):
            return cycle
    return None


def layer_violations(graph: dict[str, set[str]]) -> list[tuple[str, str]]:
    """(importer, imported) pairs that break the layer order (unknown nodes are violations too)."""
    return sorted((a, b) for a, targets in graph.items() for b in targets if b not in ALLOWED.get(a, set()))


def test_the_checks_catch_a_cycle_and_an_upward_import():
    assert find_cycle({"a": {"b"}, "b": {"c"}, "c": {"a"}}) == ["a", "b", "c", "a"]
    assert find_cycle({"a": {"b"}, "b": {"c"}, "c": set()}) is None
    assert layer_violations({"evidence": {"scene", "rendering"}, "datasets": {"camera"}}) == [("evidence", "scene")]


def test_the_graph_reads_relative_and_absolute_imports(tmp_path):
    pkg = tmp_path / "canonical_core"
    (pkg / "evidence").mkdir(parents=True)
    (pkg / "scene").mkdir()
    (pkg / "__init__.py").write_text("")
    (pkg / "evidence" / "__init__.py").write_text("from ..scene import batch\n")
    (pkg / "scene" / "__init__.py").write_text("import canonical_core.evidence\nfrom ..config import X\n")
    (pkg / "config.py").write_text("")
    graph = package_graph(pkg)
    assert graph == {"canonical_core": set(), "evidence": {"scene"}, "scene": {"evidence", "settings"}, "settings": set()}
    assert find_cycle(graph) == ["evidence", "scene", "evidence"]


def test_the_library_is_acyclic_and_layered():
    graph = package_graph()
    assert set(graph) <= set(ALLOWED), f"packages without a layer: {sorted(set(graph) - set(ALLOWED))}"
    assert find_cycle(graph) is None
    assert layer_violations(graph) == []


@pytest.mark.parametrize("package", sorted({p.parent.name for p in ROOT.glob("*/__init__.py")} | {"camera", "frame"}))
def test_each_package_imports_first_on_its_own(package):
    name = "canonical_core" if package == "canonical_core" else f"canonical_core.{package}"
    subprocess.run([sys.executable, "-c", f"import {name}"], cwd=REPO, check=True, capture_output=True)


# -- the service ----------------------------------------------------------------------------------
SERVER = REPO / "server"
MAX_LINES = 400  # a module a reader can hold in one sitting


def server_node(module: str) -> str | None:
    """The graph node of a server module: its module, or its subpackage (routes, cluster, viewer)."""
    parts = module.split(".")
    return None if parts[0] != "server" else parts[1] if len(parts) > 1 else "server"


def server_graph(root: Path = SERVER) -> dict[str, set[str]]:
    """node -> the other server nodes its modules import (type-checking imports too)."""
    graph: dict[str, set[str]] = {}
    for path in sorted(root.rglob("*.py")):
        src = server_node(module_name(path, root.parent))
        # "server" itself: `from .. import wire` names the package only to reach its module
        targets = {server_node(m) for m in imported_modules(path, root.parent, "server")} - {src, None, "server"}
        graph.setdefault(src, set()).update(targets)
    return graph


def levels(graph: dict[str, set[str]]) -> dict[str, int]:
    """Each node's level in an acyclic graph: 0 imports nothing, others one above the highest they import."""
    level: dict[str, int] = {}

    def of(node: str) -> int:
        if node not in level:
            level[node] = 1 + max((of(n) for n in graph.get(node, ())), default=-1)
        return level[node]

    for node in graph:
        of(node)
    return level


def drawing(graph: dict[str, set[str]]) -> str:
    """The graph as text, top level first: ``level  node -> what it imports``."""
    level = levels(graph)
    rows = sorted(graph, key=lambda n: (-level[n], n))
    width = max(map(len, rows))
    return "\n".join(f"{level[n]:>2}  {n:<{width}} -> {', '.join(sorted(graph[n], key=lambda m: (-level[m], m))) or '-'}"
                     for n in rows)


def test_the_service_imports_one_way():
    graph = server_graph()
    assert find_cycle(graph) is None
    assert not graph["session_errors"] and "routes" not in set().union(*(graph[n] for n in graph if n != "app"))


def test_levels_and_drawing_of_a_small_graph():
    graph = {"a": {"b", "c"}, "b": {"c"}, "c": set()}
    assert levels(graph) == {"a": 2, "b": 1, "c": 0}
    assert drawing(graph).splitlines() == [" 2  a -> b, c", " 1  b -> c", " 0  c -> -"]


@pytest.mark.parametrize("path", sorted(SERVER.rglob("*.py")) + [ROOT / "scene" / "scene.py"],
                         ids=lambda p: str(p.relative_to(REPO)))
def test_a_module_fits_one_sitting(path):
    assert len(path.read_text().splitlines()) <= MAX_LINES


def sizes(root: Path) -> str:
    """Lines of each module under ``root``, largest first."""
    counts = sorted(((len(p.read_text().splitlines()), str(p.relative_to(REPO))) for p in root.rglob("*.py")), reverse=True)
    return "\n".join(f"{n:>5}  {name}" for n, name in counts)


if __name__ == "__main__":  # the drawings and sizes in docs/architecture.md: python -m tests.test_layers
    print("canonical_core (packages):\n" + drawing(package_graph()) + "\n\nserver (modules):\n" + drawing(server_graph())
          + "\n\nserver (lines):\n" + sizes(SERVER) + "\n\ncanonical_core/scene (lines):\n" + sizes(ROOT / "scene"))
