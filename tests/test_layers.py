"""The package's imports run down the layers only, and no files of different folders import each other in a circle:
read from the source (every import, at module level or inside a function), so a move that breaks it fails here."""

from __future__ import annotations

import ast
from pathlib import Path

PACKAGE = Path(__file__).resolve().parents[1] / "pinnmpc"
# bottom to top; folders on one rank may import each other's files, the entry points (top-level modules) come last
RANK = {
    "util": 0,
    "systems": 1,
    "references": 1,
    "plant": 2,
    "surrogate": 3,
    "controller": 4,
    "simulation": 5,
    "robot_data": 6,
    "training": 7,
    "cli": 8,
    "bench": 9,
}
COMMANDS = 10  # pinnmpc/<command>.py and the package's own __init__


def module_name(path: Path) -> str:
    """pinnmpc.a.b of pinnmpc/a/b.py (the package of an __init__.py)."""
    parts = path.relative_to(PACKAGE.parent).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def rank(module: str) -> int:
    """The layer of a pinnmpc module."""
    parts = module.split(".")
    return RANK.get(parts[1], COMMANDS) if len(parts) > 1 else COMMANDS


def folder(module: str) -> str:
    """pinnmpc.<folder> of a module (the package itself for top-level ones)."""
    return ".".join(module.split(".")[:2])


def imports() -> dict[str, set[str]]:
    """Every pinnmpc module's pinnmpc imports (the modules named, resolved to files that exist)."""
    files = {module_name(p): p for p in PACKAGE.rglob("*.py")}
    graph: dict[str, set[str]] = {}
    for module, path in files.items():
        targets: set[str] = set()
        for node in ast.walk(ast.parse(path.read_text())):
            names = []
            if isinstance(node, ast.ImportFrom) and node.module and node.module.startswith("pinnmpc"):
                names = [node.module] + [f"{node.module}.{a.name}" for a in node.names]
            elif isinstance(node, ast.Import):
                names = [a.name for a in node.names if a.name.startswith("pinnmpc")]
            targets |= {n for n in names if n in files and n != module}
        graph[module] = targets
    return graph


def test_no_import_runs_up_the_layers() -> None:
    upward = sorted(
        f"{m} -> {t}"
        for m, targets in imports().items()
        for t in targets
        if rank(m) < COMMANDS and rank(t) > rank(m) and folder(m) != folder(t)
    )
    assert not upward, "imports up the layers:\n" + "\n".join(upward)


def test_no_circle_between_files_of_different_folders() -> None:
    graph = imports()
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    circles: list[list[str]] = []

    def visit(v: str) -> None:
        """Tarjan's strongly connected components (a circle is a component of more than one module)."""
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in graph[v]:
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
            folders = {folder(m) for m in component}
            if len(component) > 1 and len(folders) > 1:
                circles.append(sorted(component))

    for v in graph:
        if v not in index:
            visit(v)
    assert not circles, "import circles across folders: " + "; ".join(" <-> ".join(c) for c in circles)


def test_the_checks_see_imports() -> None:
    """The graph is not empty by mistake: the closed loop's module imports the controller registry."""
    assert "pinnmpc.controller.registry" in imports()["pinnmpc.simulation.setup"]
