"""The package's layers point one way, and no import hides inside a function.

Read from the source with :mod:`ast` (no module is imported): every ``import`` and
``from … import`` of ``src/ajtwin``, at module level or in a function body, with its
line. The layer order is the one of the developers' layout (commands, pages and studies on
top; the engine; the applications; estimation and the store; the sensing and simulation
packages; the model; records, units, configuration and JAX at the bottom): an import may
point down, or within its own package, never up or sideways into another package of the
same layer, and the packages' import graph has no cycle.
"""

from __future__ import annotations

import ast
import re
from collections import defaultdict
from pathlib import Path

SRC = Path(__file__).resolve().parents[1] / "src"
PACKAGE = SRC / "ajtwin"

#: Top to bottom. Within a row the packages are peers (none may import another); where the
#: layout names peers that do depend on each other the row is split, the user above:
#: ``cli`` runs the studies (``ajtwin experiment``, ``control simulate``, ``demo``) and
#: serves the pages, the live demo (a study) serves them too; ``live`` feeds the engine
#: samples (the engine never imports it); ``profile_cnn`` reads camera frames with
#: ``vision``; ``_aot`` keeps programs traced with ``_jax``; ``ajtwin`` itself is the
#: version.
LAYERS = [
    ("cli",),
    ("studies",),
    ("web",),
    ("live",),
    ("engine",),
    ("apps",),
    ("store", "estimation"),
    ("profile_cnn",),
    ("simulation", "vision", "cfd"),
    # the machine's program: what the virtual printer prints and the camera looks at
    ("job",),
    ("model",),
    ("io",),
    ("units", "config", "_aot"),
    ("_jax",),
    ("ajtwin",),
]
RANK = {name: rank for rank, row in enumerate(LAYERS) for name in row}

#: Modules a function may import when it needs them, with why they are not at the top:
#: heavy optional modules that most uses of the importing module never need.
LAZY_ALLOWED = {
    "cv2": "OpenCV (~0.3 s): only reading or writing video needs it",
    "matplotlib": "figures only (~0.5 s, and a backend to choose)",
    "plotly": "only to find plotly.min.js for the dashboard (~1 s to import)",
    "uvicorn": "the dashboard's server: only when it serves",
    "dask": "the scheduler of batch work: only `ajtwin cfd sweep` and `ajtwin reprocess`",
    "pyarrow": "Parquet I/O only: a CSV record never needs it",
    "torch": "PyTorch (~2 s): only the height-profile CNN",
    "playwright": "a browser: only the dashboard's screenshots",
    "ajtwin.vision.extract": "loads OpenCV: only a print that comes with a video needs it",
    "skopt": "the develop study's generic Bayesian optimisation: an optional extra ([study])",
    "psycopg": "PostgreSQL's client (~0.2 s): only a registry on a PostgreSQL server needs it",
    "scipy.special": "~0.1 s: only the live detectors' χ² tails need it; `estimate` imports their "
    "module for the guard and never calls them",
}


def _modules():
    """(dotted name, path, tree) of every module of the package."""
    for path in sorted(PACKAGE.rglob("*.py")):
        parts = list(path.relative_to(SRC).with_suffix("").parts)
        if parts[-1] == "__init__":
            parts = parts[:-1]
        yield ".".join(parts), path, ast.parse(path.read_text(encoding="utf-8"))


def _imports(tree: ast.Module, module: str, is_package: bool):
    """(imported module, line, inside a function) of every import statement."""
    out = []

    def visit(node, in_function):
        for child in ast.iter_child_nodes(node):
            inside = in_function or isinstance(child, ast.FunctionDef | ast.AsyncFunctionDef)
            if isinstance(child, ast.Import):
                out.extend((alias.name, child.lineno, in_function) for alias in child.names)
            elif isinstance(child, ast.ImportFrom):
                if child.level:
                    base = module.split(".")[: len(module.split(".")) - child.level + is_package]
                    target = ".".join(base + ([child.module] if child.module else []))
                else:
                    target = child.module
                out.append((target, child.lineno, in_function))
            visit(child, inside)

    visit(tree, False)
    return out


def _package(module: str) -> str:
    """The top-level package of an ``ajtwin`` module (``ajtwin`` for the root's modules'
    parent, ``units`` for ``ajtwin.units``)."""
    parts = module.split(".")
    return parts[1] if len(parts) > 1 else "ajtwin"


def _edges():
    """(importer package, imported package, where) of every import between packages."""
    out = []
    for module, path, tree in _modules():
        for target, line, _ in _imports(tree, module, path.name == "__init__.py"):
            if target == "ajtwin" or target.startswith("ajtwin."):
                a, b = _package(module), _package(target)
                if a != b:
                    out.append((a, b, f"{path.relative_to(SRC)}:{line} imports {target}"))
    return out


def test_every_package_has_a_layer():
    packages = {_package(module) for module, _, _ in _modules()}
    assert packages <= set(RANK), f"packages without a layer: {sorted(packages - set(RANK))}"


def test_imports_point_down_the_layers():
    upward = [f"{where} ({a} → {b})" for a, b, where in _edges() if not RANK[a] < RANK[b]]
    assert not upward, "imports against the layer order:\n" + "\n".join(upward)


def _cycles(graph: dict) -> list[list[str]]:
    """Strongly connected components of more than one node (Tarjan)."""
    index, low, stack, on_stack, found = {}, {}, [], set(), []

    def connect(v):
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in graph.get(v, ()):
            if w not in index:
                connect(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                component.append(w)
                if w == v:
                    break
            if len(component) > 1:
                found.append(sorted(component))

    for v in list(graph):
        if v not in index:
            connect(v)
    return found


def test_no_cycle_between_packages_or_between_the_apps_subpackages():
    graph = defaultdict(set)
    for a, b, _ in _edges():
        graph[a].add(b)
    subgraph = defaultdict(set)
    for module, path, tree in _modules():
        if not module.startswith("ajtwin.apps."):
            continue
        for target, _, _ in _imports(tree, module, path.name == "__init__.py"):
            if target.startswith("ajtwin.apps.") and target.split(".")[2] != module.split(".")[2]:
                subgraph[module.split(".")[2]].add(target.split(".")[2])
    assert not _cycles(graph) and not _cycles(subgraph), (_cycles(graph), _cycles(subgraph))


def test_the_cycle_finder_finds_a_cycle():
    assert _cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]


def _commented_lazy(lines: list[str], line: int) -> bool:
    """Whether the import block around ``line`` is preceded by a ``# lazy …`` comment."""
    k = line - 2
    while k >= 0:
        text = lines[k].strip()
        if text.startswith("#"):
            if "lazy" in text.lower():
                return True
        elif not (
            text.startswith(("from ", "import ")) or text.endswith((",", "(")) or text == ")"
        ):
            return False
        k -= 1
    return False


def test_no_import_inside_a_function_but_the_commented_lazy_cli_and_heavy_modules():
    hidden = []
    for module, path, tree in _modules():
        lines = path.read_text(encoding="utf-8").splitlines()
        for target, line, in_function in _imports(tree, module, path.name == "__init__.py"):
            if not in_function:
                continue
            if target.split(".")[0] in LAZY_ALLOWED or target in LAZY_ALLOWED:
                continue
            if module.startswith("ajtwin.cli.") and _commented_lazy(lines, line):
                continue  # lazy CLI loading: `ajtwin X --help` imports no library
            hidden.append(f"{path.relative_to(SRC)}:{line} imports {target}")
    assert not hidden, "imports inside function bodies:\n" + "\n".join(hidden)


#: the store's modules that hold statements and connections: the repository (the registry),
#: its schema and the two databases; every other module reads and writes through the
#: registry's methods
STATEMENT_MODULES = {
    "ajtwin.store.registry",
    "ajtwin.store.schema",
    "ajtwin.store.database",
    "ajtwin.store.connection",
}


def test_only_the_registry_runs_statements_on_a_connection():
    outside = [
        f"{path.relative_to(SRC)}:{n}"
        for module, path, _ in _modules()
        if module not in STATEMENT_MODULES
        for n, text in enumerate(path.read_text(encoding="utf-8").splitlines(), 1)
        if re.search(r"\._conn\b|\._db\b|\.execute\(|\bsqlite3\.connect\(|psycopg\.connect", text)
    ]
    assert not outside, "statements or connections outside the registry: " + ", ".join(outside)


def test_the_command_list_imports_no_command():
    """``ajtwin --help`` lists the commands from a table, so ``cli/__init__`` imports no
    command module (each is imported when its command runs)."""
    tree = ast.parse((PACKAGE / "cli" / "__init__.py").read_text(encoding="utf-8"))
    targets = [t for t, _, _ in _imports(tree, "ajtwin.cli", True)]
    assert all(not t.startswith("ajtwin.cli.") for t in targets), targets
    assert [t for t in targets if t.startswith("ajtwin")] == ["ajtwin"]  # the version


#: what the engine may take from the model: its vocabulary and its limits
ENGINE_MODEL_MODULES = {"ajtwin.model.names", "ajtwin.model.limits"}
#: what the engine may not import at all: the filter's math, JAX (nothing jitted of its own)
ENGINE_FORBIDDEN = ("ajtwin.estimation.filters", "ajtwin._jax", "ajtwin._aot", "jax", "jaxlib")


def _engine_model_names() -> set[str]:
    """The names ``ajtwin.model`` re-exports from its vocabulary and limits modules."""
    names = set()
    for module in ENGINE_MODEL_MODULES:
        tree = ast.parse((SRC / (module.replace(".", "/") + ".py")).read_text(encoding="utf-8"))
        for node in tree.body:
            targets = node.targets if isinstance(node, ast.Assign) else []
            if isinstance(node, ast.AnnAssign):
                targets = [node.target]
            names |= {t.id for t in targets if isinstance(t, ast.Name)}
            if isinstance(node, ast.ClassDef | ast.FunctionDef):
                names.add(node.name)
    return names


def test_the_engine_only_wires():
    """engine/ computes nothing: no model internals (the vocabulary in ``model/names.py``
    and the limits aside), not the filter, nothing jitted of its own."""
    vocabulary = _engine_model_names()
    found = []
    for module, path, tree in _modules():
        if not module.startswith("ajtwin.engine"):
            continue
        for node in ast.walk(tree):
            if isinstance(node, ast.Import):
                targets = [(alias.name, None) for alias in node.names]
            elif isinstance(node, ast.ImportFrom) and node.module and not node.level:
                targets = [(node.module, [alias.name for alias in node.names])]
            else:
                continue
            for target, names in targets:
                where = f"{path.relative_to(SRC)}:{node.lineno} imports {target}"
                if any(target == f or target.startswith(f + ".") for f in ENGINE_FORBIDDEN):
                    found.append(where)
                elif target == "ajtwin.model":
                    extra = sorted(set(names or ["*"]) - vocabulary)
                    if extra:
                        found.append(f"{where} ({', '.join(extra)})")
                elif target.startswith("ajtwin.model.") and target not in ENGINE_MODEL_MODULES:
                    found.append(where)
    assert not found, "the engine reaches into the model or the filter:\n" + "\n".join(found)
