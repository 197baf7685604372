"""The package's import graph: no cycle among marl_amod's modules, and data flows one way
(scenario -> simulator). Only module-level imports count: an import inside a function runs on
first use (an optional extra, a heavy backend) and cannot make a cycle at import time."""

from __future__ import annotations

import ast
from pathlib import Path

import numpy as np
from scipy.sparse import csr_matrix
from scipy.sparse.csgraph import connected_components

import marl_amod

ROOT = Path(marl_amod.__file__).resolve().parent


def _modules(root: Path, package: str) -> dict[str, Path]:
    """Dotted name -> file of every module of the package under ``root`` (``__init__`` is the package)."""
    out = {}
    for path in sorted(root.rglob("*.py")):
        parts = path.relative_to(root).with_suffix("").parts
        if parts[-1] == "__init__":
            parts = parts[:-1]
        out[".".join((package, *parts))] = path
    return out


def _module_level(nodes) -> list[ast.Import | ast.ImportFrom]:
    """Import statements that run when the module is imported: not inside functions, not under
    ``if TYPE_CHECKING:``; class bodies and ``if``/``try``/``with`` blocks included."""
    found = []
    for node in nodes:
        if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef):
            continue
        if isinstance(node, ast.If) and "TYPE_CHECKING" in ast.unparse(node.test):
            found += _module_level(node.orelse)
        elif isinstance(node, ast.Import | ast.ImportFrom):
            found.append(node)
        else:
            found += _module_level(ast.iter_child_nodes(node))
    return found


def import_graph(root: Path, package: str, *, lazy: bool = False) -> dict[str, set[str]]:
    """Module -> the package's modules it imports at module level (with ``lazy``, anywhere, inside
    functions too). ``from a.b import c`` points at the module ``a.b.c`` when there is one, else
    at ``a.b`` (a name its ``__init__`` defines)."""
    modules = _modules(root, package)
    graph: dict[str, set[str]] = {}
    for name, path in modules.items():
        is_package = path.name == "__init__.py"
        targets: set[str] = set()
        tree = ast.parse(path.read_text(), filename=str(path))
        imports = [n for n in ast.walk(tree) if isinstance(n, ast.Import | ast.ImportFrom)] if lazy else _module_level(tree.body)
        for node in imports:
            if isinstance(node, ast.Import):
                targets.update(a.name for a in node.names if a.name in modules)
            elif isinstance(node, ast.ImportFrom):
                if node.level:  # relative: from the module's own package upwards
                    base_parts = name.split(".")[: len(name.split(".")) - node.level + (1 if is_package else 0)]
                    base = ".".join([*base_parts, *([node.module] if node.module else [])])
                else:
                    base = node.module or ""
                for alias in node.names:
                    candidate = f"{base}.{alias.name}"
                    targets.add(candidate if candidate in modules else base)
        graph[name] = {t for t in targets if t in modules}
    return graph


def cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The import cycles: strongly connected groups of modules (and modules importing themselves)."""
    names = sorted(graph)
    index = {m: k for k, m in enumerate(names)}
    rows = [index[a] for a in names for b in graph[a]]
    cols = [index[b] for a in names for b in graph[a]]
    adj = csr_matrix((np.ones(len(rows)), (rows, cols)), shape=(len(names), len(names)))
    _, label = connected_components(adj, directed=True, connection="strong")
    groups = [[names[k] for k in np.flatnonzero(label == c)] for c in np.unique(label)]
    return [g for g in groups if len(g) > 1 or g[0] in graph[g[0]]]


def test_no_import_cycle_among_marl_amod_modules():
    found = cycles(import_graph(ROOT, "marl_amod"))
    assert not found, "import cycles (module-level imports): " + "; ".join(" <-> ".join(g) for g in found)


def test_cycle_finder_sees_a_cycle_through_a_package_and_ignores_lazy_imports(tmp_path: Path):
    pkg = tmp_path / "pkg"
    (pkg / "sub").mkdir(parents=True)
    (pkg / "__init__.py").write_text("")
    (pkg / "sub" / "__init__.py").write_text("from pkg.sub.b import thing\n")
    (pkg / "a.py").write_text("from pkg.sub import thing\n")  # a name of sub's __init__: an edge to it
    (pkg / "sub" / "b.py").write_text("import pkg.a\nthing = 1\n")
    (pkg / "lazy.py").write_text("def f():\n    import pkg.c\n")
    (pkg / "c.py").write_text("from pkg import lazy\nfrom typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    import pkg.c\n")
    graph = import_graph(pkg, "pkg")
    assert graph["pkg.a"] == {"pkg.sub"} and graph["pkg.sub.b"] == {"pkg.a"}
    assert cycles(graph) == [["pkg.a", "pkg.sub", "pkg.sub.b"]]
    assert graph["pkg.lazy"] == set() and graph["pkg.c"] == {"pkg.lazy"}
    assert import_graph(pkg, "pkg", lazy=True)["pkg.lazy"] == {"pkg.c"}


def test_scenarios_never_import_the_simulators():
    """One-way flow: a scenario builds data (a City with a SimSpec); the simulator package reads
    it. Lazy imports count here: a scenario that built its simulator on demand would still
    depend on it."""
    graph = import_graph(ROOT, "marl_amod", lazy=True)
    back = sorted(
        (a, b) for a, bs in graph.items() if a.startswith("marl_amod.scenario") for b in bs if b.startswith("marl_amod.sim")
    )
    assert not back, f"scenario modules import simulator modules: {back}"


def test_the_leg_simulator_does_not_know_the_taxi_simulator():
    graph = import_graph(ROOT, "marl_amod", lazy=True)
    meso = {m for m in graph if m.startswith("marl_amod.sim.meso") and m != "marl_amod.sim.meso.taxi_sim"}
    assert not any("marl_amod.sim.meso.taxi_sim" in graph[m] for m in meso)
