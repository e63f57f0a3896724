"""The house rules of issue 10, read from the code's own imports (every import, lazy ones too):
``training/`` keeps at most 10 modules on its top floor, there are no import cycles, ``som_torch``
imports neither ``sim`` nor ``training``, ``sim`` does not import ``training``, the rooms
``identification`` and ``commissioning`` do not import each other, and one room reaches another
only through its face (never into a private ``_*.py`` of another room)."""

from __future__ import annotations

import ast
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
PACKAGES = ("som_torch", "sim", "training")


def _module_name(path: Path) -> str:
    parts = list(path.relative_to(REPO).with_suffix("").parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _imports(path: Path) -> set[str]:
    """The project modules ``path`` imports (``from a.b import c`` counts ``a.b.c`` when that is a module)."""
    name = _module_name(path)
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    out: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            out.update(a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                up = package.split(".")[: len(package.split(".")) - node.level + 1]
                base = ".".join(up + ([base] if base else []))
            out.add(base)
            out.update(f"{base}.{a.name}" for a in node.names)
    return {m for m in out if m.split(".")[0] in PACKAGES}


def _graph() -> dict[str, set[str]]:
    files = [p for pkg in PACKAGES for p in (REPO / pkg).rglob("*.py")]
    modules = {_module_name(p): p for p in files}
    return {m: {i for i in _imports(p) if i in modules and i != m} for m, p in modules.items()}


def test_training_top_floor_has_at_most_ten_modules() -> None:
    top = sorted(p.name for p in (REPO / "training").glob("*.py"))
    assert len(top) <= 10, top


def test_no_import_cycles() -> None:
    graph = _graph()
    # a package's face importing its own modules is not a cycle with them: drop child -> own face edges
    edges = {m: {i for i in deps if not (m.startswith(i + ".") and i in graph)} for m, deps in graph.items()}
    state: dict[str, int] = {}
    cycles: list[list[str]] = []

    def visit(m: str, stack: list[str]) -> None:
        state[m] = 1
        for n in sorted(edges[m]):
            if state.get(n) == 1:
                cycles.append(stack[stack.index(n):] + [n])
            elif n not in state:
                visit(n, stack + [n])
        state[m] = 2

    for m in sorted(edges):
        if m not in state:
            visit(m, [m])
    assert not cycles, cycles[:5]


def _reaches(graph: dict[str, set[str]], src: str, dst: str) -> list[str]:
    return sorted(f"{m} -> {i}" for m, deps in graph.items() if m == src or m.startswith(src + ".")
                  for i in deps if i == dst or i.startswith(dst + "."))


def test_package_direction() -> None:
    graph = _graph()
    assert not _reaches(graph, "som_torch", "sim")
    assert not _reaches(graph, "som_torch", "training")
    assert not _reaches(graph, "sim", "training")
    assert not _reaches(graph, "training.identification", "training.commissioning")
    assert not _reaches(graph, "training.commissioning", "training.identification")


def test_rooms_meet_through_their_faces() -> None:
    rooms = {p.parent.name for p in (REPO / "training").glob("*/__init__.py")}
    bad = []
    for m, deps in _graph().items():
        for i in deps:
            parts = i.split(".")
            if len(parts) >= 3 and parts[0] == "training" and parts[1] in rooms and parts[2].startswith("_"):
                if not m.startswith(f"training.{parts[1]}"):
                    bad.append(f"{m} -> {i}")
    assert not bad, bad
