"""The project's import graph, read from the source with ``ast``: no circle between modules and
arrows one way, ``experiments -> controllers -> lfm_env``, with ``lfm_env.gp`` knowing no
system.

Every import that runs counts: at the top of a module, inside a function, and the
``"module:Class"`` entry points and lazy attribute tables imported on first use (the solver
registry, the worlds' registrations, :func:`lfm_env.lazy.lazy_attributes`). Imports under
``if TYPE_CHECKING:`` name types for annotations and never run, so they are left out. A
package's edges are its ``__init__``'s imports; ``from package import name`` is an edge to the
submodule ``package.name`` when there is one, else to the package.
"""

from __future__ import annotations

import ast
import re
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
#: The layers, lowest first: a module may import its own layer and the layers below.
LAYERS = ("lfm_env", "controllers", "experiments")
#: ``"package.module:Attribute"``: an entry point, imported when it is used.
ENTRY_POINT = re.compile(r"((?:lfm_env|controllers|experiments)(?:\.\w+)*):[A-Za-z_][\w.]*")
#: What ``lfm_env.gp`` (the kernels and their likelihood) may import of ``lfm_env``.
GP_ALLOWED = ("lfm_env.gp", "lfm_env.xp", "lfm_env.validation")


def module_files(root: Path = REPO, tops: tuple[str, ...] = LAYERS) -> dict[str, Path]:
    """Every module of the packages ``tops`` under ``root`` by dotted name (a package by its
    own name)."""
    found = {}
    for top in tops:
        for path in sorted((root / top).rglob("*.py")):
            parts = list(path.relative_to(root).with_suffix("").parts)
            if parts[-1] == "__init__":
                parts.pop()
            found[".".join(parts)] = path
    return found


def _absolute(node: ast.ImportFrom, module: str, is_package: bool) -> str:
    """The absolute module of a ``from`` import (relative ones resolved)."""
    if node.level == 0:
        return node.module or ""
    base = module.split(".") if is_package else module.split(".")[:-1]
    base = base[: len(base) - (node.level - 1)]
    return ".".join(base + ([node.module] if node.module else []))


def _is_type_checking(node: ast.AST) -> bool:
    """``if TYPE_CHECKING:`` (or ``if typing.TYPE_CHECKING:``)."""
    if not isinstance(node, ast.If):
        return False
    test = node.test
    return getattr(test, "id", getattr(test, "attr", None)) == "TYPE_CHECKING"


def _run_time_nodes(tree: ast.AST) -> list[ast.AST]:
    """Every node of ``tree`` but those under ``if TYPE_CHECKING:`` (its ``else`` kept)."""
    out, todo = [], [tree]
    while todo:
        node = todo.pop()
        out.append(node)
        if _is_type_checking(node):
            todo.extend(node.orelse)
        else:
            todo.extend(ast.iter_child_nodes(node))
    return out


def imported_modules(path: Path, module: str, known: set[str]) -> set[str]:
    """The project's modules that ``module`` (its source at ``path``) imports when it runs."""
    out: set[str] = set()
    is_package = path.name == "__init__.py"
    tree = ast.parse(path.read_text(), str(path))
    tables = {  # module-level NAME = {...}: a lazy table may be given by name
        t.id: n.value
        for n in tree.body
        if isinstance(n, ast.Assign) and isinstance(n.value, ast.Dict)
        for t in n.targets
        if isinstance(t, ast.Name)
    }
    for node in _run_time_nodes(tree):
        if isinstance(node, ast.Import):
            out.update(a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom):
            source = _absolute(node, module, is_package)
            for a in node.names:
                full = f"{source}.{a.name}"
                out.add(full if full in known else source)
        elif isinstance(node, ast.Constant) and isinstance(node.value, str):
            match = ENTRY_POINT.fullmatch(node.value.strip())
            if match:
                out.add(match.group(1))
        elif _is_lazy_attributes(node):
            table = node.args[1]
            table = tables.get(table.id) if isinstance(table, ast.Name) else table
            if isinstance(table, ast.Dict):
                out.update(v.value for v in table.values if isinstance(v, ast.Constant))
    return {m for m in out if m in known and m != module}


def _is_lazy_attributes(node: ast.AST) -> bool:
    """``lazy_attributes(__name__, {"Name": "package.module", ...})`` (or a table's name)."""
    return (
        isinstance(node, ast.Call)
        and getattr(node.func, "id", getattr(node.func, "attr", "")) == "lazy_attributes"
        and len(node.args) == 2
    )


def import_graph(root: Path = REPO, tops: tuple[str, ...] = LAYERS) -> dict[str, set[str]]:
    """``module -> the project's modules it imports``."""
    files = module_files(root, tops)
    known = set(files)
    return {m: imported_modules(p, m, known) for m, p in files.items()}


def circles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components of more than one module (Tarjan), sorted."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found: list[list[str]] = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in sorted(graph[v]):
            if w not in index:
                visit(w)
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

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return sorted(found)


def upward_arrows(graph: dict[str, set[str]]) -> list[str]:
    """Imports from a lower layer into a higher one (``lfm_env`` importing ``controllers``)."""
    rank = {top: i for i, top in enumerate(LAYERS)}
    return sorted(
        f"{m} -> {t}"
        for m, targets in graph.items()
        for t in targets
        if rank[t.partition(".")[0]] > rank[m.partition(".")[0]]
    )


def gp_knows(graph: dict[str, set[str]]) -> list[str]:
    """What ``lfm_env.gp`` imports beyond the kernels, ``xp`` and ``validation``."""
    return sorted(
        f"{m} -> {t}"
        for m, targets in graph.items()
        if m == "lfm_env.gp" or m.startswith("lfm_env.gp.")
        for t in targets
        if not any(t == a or t.startswith(a + ".") for a in GP_ALLOWED)
    )


# --------------------------------------------------------------------------- the project


def test_no_import_circle_between_modules():
    assert circles(import_graph()) == []


def test_arrows_go_experiments_to_controllers_to_lfm_env():
    assert upward_arrows(import_graph()) == []


def test_the_gp_layer_knows_no_system_or_world():
    assert gp_knows(import_graph()) == []


def test_the_graph_holds_the_imports_it_should():
    graph = import_graph()
    assert len(graph) > 130  # every module of the three packages
    # A top-level import, a function-level import, an entry point and a lazy table.
    assert "controllers.config" in graph["controllers.agents.registry"]
    assert "lfm_env.model" in graph["lfm_env.config.world"]  # inside make_model
    assert "controllers.solvers.fast.solver" in graph["controllers.solvers"]
    assert "lfm_env.worlds.sine_track.env" in graph["lfm_env.worlds"]


def _root(node: ast.AST) -> str | None:
    """The name at the root of ``a.b[c].d``."""
    while isinstance(node, (ast.Attribute, ast.Subscript)):
        node = node.value
    return node.id if isinstance(node, ast.Name) else None


#: Methods that change a table in place.
MUTATORS = ("update", "append", "extend", "setdefault", "add", "insert", "pop", "clear")


def foreign_writes(path: Path, module: str) -> list[str]:
    """Module-level statements that change a table of another top-level package: an item or
    attribute set on a name imported from it, or one of :data:`MUTATORS` called on it."""
    tree = ast.parse(path.read_text(), str(path))
    top = module.partition(".")[0]
    foreign = set()
    for node in tree.body:
        if isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            if node.module.partition(".")[0] in LAYERS and not node.module.startswith(top):
                foreign.update(a.asname or a.name for a in node.names)
        elif isinstance(node, ast.Import):
            for a in node.names:
                if a.name.partition(".")[0] in LAYERS and not a.name.startswith(top):
                    foreign.add(a.asname or a.name.partition(".")[0])
    found = []
    for node in tree.body:
        targets = []
        if isinstance(node, (ast.Assign, ast.AugAssign, ast.AnnAssign)):
            targets = node.targets if isinstance(node, ast.Assign) else [node.target]
            targets = [t for t in targets if isinstance(t, (ast.Attribute, ast.Subscript))]
        elif isinstance(node, ast.Expr) and isinstance(node.value, ast.Call):
            func = node.value.func
            if isinstance(func, ast.Attribute) and func.attr in MUTATORS:
                targets = [func.value]
        found += [f"{module}:{node.lineno}" for t in targets if _root(t) in foreign]
    return found


def test_no_module_writes_into_another_packages_tables():
    files = module_files()
    assert [w for m, p in files.items() for w in foreign_writes(p, m)] == []


# --------------------------------------------------------------------------- the checks themselves


def test_the_checks_find_circles_and_wrong_arrows(tmp_path):
    """On a small tree: a circle through a function-level import and a relative one (an
    annotation-only import beside it left out), an upward arrow through an entry point, and
    the gp importing a world."""
    files = {
        "lfm_env/__init__.py": "",
        "lfm_env/a.py": "def f():\n    from lfm_env import b\n",
        "lfm_env/b.py": (
            "from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    from lfm_env import c\n"
            "else:\n    from .a import f\n"
        ),
        "lfm_env/c.py": "",
        "lfm_env/gp/__init__.py": "from lfm_env.worlds import w\n",
        "lfm_env/worlds/__init__.py": "",
        "lfm_env/worlds/w.py": "X = 'controllers.c:Thing'\n",
        "controllers/__init__.py": "",
        "controllers/c.py": "import lfm_env.a\n",
        "experiments/__init__.py": "",
    }
    for name, text in files.items():
        (tmp_path / name).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / name).write_text(text)
    graph = import_graph(tmp_path)
    assert graph["lfm_env.b"] == {"lfm_env.a"}
    assert circles(graph) == [["lfm_env.a", "lfm_env.b"]]
    assert upward_arrows(graph) == ["lfm_env.worlds.w -> controllers.c"]
    assert gp_knows(graph) == ["lfm_env.gp -> lfm_env.worlds.w"]


def test_the_check_finds_a_write_into_another_packages_table(tmp_path):
    source = tmp_path / "config.py"
    source.write_text(
        "from lfm_env.config.compose import SECTION_TYPES\n"
        "from controllers.local import TABLE\n"
        "SECTION_TYPES['agents'] = object\n"
        "TABLE['mine'] = 1\n"  # its own package's: allowed
        "SECTION_TYPES.update(x=1)\n"
    )
    assert foreign_writes(source, "controllers.config") == [
        "controllers.config:3",
        "controllers.config:5",
    ]
