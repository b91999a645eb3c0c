"""How the rooms of the experiment layer import each other (read from the source with ast):
arrows one way, command lines on top, and only public names between folders."""

from __future__ import annotations

import ast
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]
TOPS = ("lfm_env", "controllers", "experiments")


def modules(top: str = "experiments") -> dict[str, Path]:
    """Every module of ``top`` by dotted name (a package by its own name)."""
    found = {}
    for path in sorted((REPO / top).rglob("*.py")):
        parts = list(path.relative_to(REPO).with_suffix("").parts)
        if parts[-1] == "__init__":
            parts.pop()
        found[".".join(parts)] = path
    return found


def is_module(name: str) -> bool:
    path = REPO.joinpath(*name.split("."))
    return path.with_suffix(".py").is_file() or (path / "__init__.py").is_file()


def folder(module: str) -> str:
    """The folder (package) a module lives in; a package is its own folder."""
    return (
        module
        if (REPO.joinpath(*module.split(".")) / "__init__.py").is_file()
        else (module.rpartition(".")[0])
    )


def imports(path: Path) -> list[tuple[int, str, str | None]]:
    """``(line, module, name)`` of every import of the project's packages, also inside
    functions; ``name`` is the imported name of a ``from`` import (None for a module)."""
    found = []
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            found += [(node.lineno, a.name, None) for a in node.names if a.name.startswith(TOPS)]
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            if node.module.startswith(TOPS):
                for a in node.names:
                    full = f"{node.module}.{a.name}"
                    found.append(
                        (node.lineno, full, None)
                        if is_module(full)
                        else (node.lineno, node.module, a.name)
                    )
    return found


def private(name: str) -> bool:
    return name.startswith("_") and not name.endswith("__")


def private_names_across_folders(path: Path, module: str) -> list[str]:
    """Private names this module takes from a module of another folder: imported by name,
    or read as an attribute of an imported module (``episode._check_seeds``)."""
    found, aliases = [], {}
    tree = ast.parse(path.read_text())
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            for a in node.names:
                full = f"{node.module}.{a.name}"
                if is_module(full):
                    aliases[a.asname or a.name] = full
                elif private(a.name) and folder(node.module) != folder(module):
                    found.append(f"{node.lineno}: {full}")
        elif isinstance(node, ast.Import):
            for a in node.names:
                aliases[a.asname or a.name] = a.name
    for node in ast.walk(tree):
        if isinstance(node, ast.Attribute) and private(node.attr):
            target = aliases.get(ast.unparse(node.value))
            if target and target.startswith(TOPS) and folder(target) != folder(module):
                found.append(f"{node.lineno}: {target}.{node.attr}")
    return found


def test_no_private_name_crosses_a_folder():
    found = {
        m: hits for m, path in modules().items() if (hits := private_names_across_folders(path, m))
    }
    assert found == {}


def test_the_library_never_imports_the_command_lines():
    found = [
        f"{m}:{line} imports {target}"
        for m, path in modules().items()
        if not m.startswith("experiments.cli")
        for line, target, _ in imports(path)
        if target == "experiments.cli" or target.startswith("experiments.cli.")
    ]
    assert found == []


def test_no_import_cycle_between_modules():
    mods = modules()
    graph = {
        m: {t for _, t, _ in imports(path) if t in mods and t != m} for m, path in mods.items()
    }
    # Depth-first search for a back edge (a package's edges are its __init__'s imports).
    state: dict[str, int] = {}
    cycles = []

    def visit(m: str, trail: list[str]) -> None:
        state[m] = 1
        for t in sorted(graph[m]):
            if state.get(t) == 1:
                cycles.append(trail[trail.index(t) :] + [t] if t in trail else [m, t])
            elif t not in state:
                visit(t, [*trail, t])
        state[m] = 2

    for m in sorted(graph):
        if m not in state:
            visit(m, [m])
    assert cycles == []


def test_the_checks_find_what_they_look_for(tmp_path):
    # The sweep's old imports: private names of the evaluation, read as module attributes.
    source = tmp_path / "sweep.py"
    source.write_text(
        "from experiments.evaluation import episode, storage\n"
        "from experiments.evaluation.storage import _warn\n"
        "episode._check_seeds([1])\nstorage._check_folder(1, 2)\n"
    )
    found = private_names_across_folders(source, "experiments.sweep")
    assert found == [
        "2: experiments.evaluation.storage._warn",
        "3: experiments.evaluation.episode._check_seeds",
        "4: experiments.evaluation.storage._check_folder",
    ]
    assert private_names_across_folders(source, "experiments.evaluation.run") == []
    assert (0, "experiments.cli", None) not in imports(source)
