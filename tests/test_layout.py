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


#: The most decisions one function may hold (McCabe's cyclomatic complexity, counted as radon does).
MAX_COMPLEXITY = 20

_NESTED = (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)


def _decisions(node: ast.AST) -> int:
    """The decision points of one node, as radon's ComplexityVisitor counts them."""
    if isinstance(node, ast.Try):
        return len(node.handlers) + bool(node.orelse)
    if isinstance(node, ast.BoolOp):
        return len(node.values) - 1
    if isinstance(node, (ast.If, ast.IfExp, ast.Assert)):
        return 1
    if isinstance(node, (ast.For, ast.While, ast.AsyncFor)):
        return 1 + bool(node.orelse)
    if isinstance(node, ast.comprehension):
        return 1 + len(node.ifs)
    if isinstance(node, ast.Match):
        wildcard = any(getattr(case.pattern, "pattern", False) is None for case in node.cases)
        return max(0, len(node.cases) - wildcard)
    return 0


def complexity(function: ast.FunctionDef | ast.AsyncFunctionDef) -> int:
    """1 + the decisions of the body, nested functions and classes left out (they count on their own)."""
    total, todo = 1, list(function.body)
    while todo:
        node = todo.pop()
        if not isinstance(node, _NESTED):
            total += _decisions(node)
            todo.extend(ast.iter_child_nodes(node))
    return total


def _complexities() -> dict[str, int]:
    out = {}
    for path in sorted(p for pkg in PACKAGES for p in (REPO / pkg).rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                out[f"{path.relative_to(REPO)}:{node.lineno} {node.name}"] = complexity(node)
    return out


def test_complexity_counts_as_radon_does() -> None:
    code = ("def f(x, ys):\n"
            "    if x and ys or not x:\n"          # if +1, two BoolOps +2
            "        return [y for y in ys if y]\n"  # comprehension +1, its if +1
            "    for y in ys:\n"                   # for +1, else +1
            "        try:\n"
            "            x = 1 if y else 2\n"      # ternary +1
            "        except ValueError:\n"         # handler +1
            "            pass\n"
            "    else:\n"
            "        def g():\n"                   # a closure counts on its own
            "            if x: return 1\n"
            "    assert x\n"                       # +1
            "    while x: x -= 1\n")               # +1
    f = ast.parse(code).body[0]
    assert complexity(f) == 12
    assert complexity(f.body[1].orelse[0]) == 2


def test_no_function_is_too_complex() -> None:
    """A function a newcomer can change without rereading the rest: at most MAX_COMPLEXITY decisions."""
    over = {name: c for name, c in _complexities().items() if c > MAX_COMPLEXITY}
    assert not over, f"functions above complexity {MAX_COMPLEXITY}: {over}"


#: Class names that hold tuned numbers: each is a frozen dataclass (settings cannot drift while in use).
SETTINGS_SUFFIXES = ("Settings", "Config", "Policy", "Rules", "Tolerances", "Spec", "Bounds", "Sizing")


def test_settings_are_frozen_dataclasses() -> None:
    loose = []
    for path in sorted(p for pkg in PACKAGES for p in (REPO / pkg).rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if isinstance(node, ast.ClassDef) and node.name.endswith(SETTINGS_SUFFIXES):
                frozen = any(isinstance(d, ast.Call) and ast.unparse(d.func).endswith("dataclass")
                             and any(k.arg == "frozen" and getattr(k.value, "value", False) for k in d.keywords)
                             for d in node.decorator_list)
                if not frozen:
                    loose.append(f"{path.relative_to(REPO)}:{node.name}")
    assert not loose, f"settings classes that are not frozen dataclasses: {loose}"


def test_the_refinement_stages_register() -> None:
    """Every stage module of the refinement is in the registry, runs in the pipeline, and keeps its
    frozen settings in the RefineConfig field of its name."""
    import dataclasses

    from training.identification._refine import _pipeline
    from training.identification._refine._config import RefineConfig

    modules = {p.stem for p in (REPO / "training/identification/_refine").glob("_*.py")
               if "STAGE = " in p.read_text() or "STAGE: " in p.read_text()}
    assert {f"_{name}" for name in _pipeline.STAGES} == modules
    assert sorted(_pipeline.PIPELINE) == sorted(_pipeline.STAGES)
    config = RefineConfig()
    for name, stage in _pipeline.STAGES.items():
        assert stage.name == name and stage.runs_when and "\n" not in stage.runs_when
        assert dataclasses.is_dataclass(stage.settings) and stage.settings.__dataclass_params__.frozen
        assert isinstance(getattr(config, name), stage.settings)


def test_the_rule_lists_name_their_rules() -> None:
    """The commissioning's chain stages and rules, and the identifier's steps, are named functions in
    one list each; a rule's docstring starts with its code (or ``Last``) and says when it runs."""
    import re

    from training.commissioning._chain import STAGES
    from training.commissioning._excitation import EXCITATION_RULES
    from training.commissioning._rules import CONTROLLER_RULES
    from training.identification._assembly import ADJUSTMENTS
    from training.identification._policy import REFINED_WHEN

    names = [name for name, _ in STAGES]
    assert len(set(names)) == len(names) and all(callable(step) for _, step in STAGES)
    for rules, code in ((EXCITATION_RULES, "E"), (CONTROLLER_RULES, "R")):
        for rule in rules:
            assert re.match(rf"({code}\d+\w*|Last)\b[^.]*\bruns\b", (rule.__doc__ or "").strip()), rule.__name__
    for steps in (ADJUSTMENTS, REFINED_WHEN):
        assert all(callable(step) and step.__doc__ for step in steps)
