"""The package's layering: which module imports which (module level and inside functions)."""

from __future__ import annotations

import ast
from pathlib import Path

PACKAGE = Path(__file__).resolve().parents[1] / "pothole_detector"
# the method: knows nothing of recordings, ROS, the survey or the evaluation
METHOD = ("pipeline", "execution", "method", "backend", "stages", "kernels")
ABOVE_THE_METHOD = ("recordings", "replay", "survey", "evaluation", "ros", "cli")
# each subpackage (or module) above the method, and what it may import of those above the method
MAY_IMPORT = {"recordings": set(), "replay": {"recordings"},
              "survey": {"recordings", "replay"}, "evaluation": {"recordings", "replay", "survey"},
              "ros": {"recordings", "replay", "survey"},
              "cli": {"recordings", "replay", "survey", "evaluation", "ros"}}


def module_name(path: Path) -> str:
    parts = path.relative_to(PACKAGE).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def imports_of(path: Path) -> set[str]:
    """The package's modules that ``path`` imports anywhere in it (relative and absolute)."""
    name = module_name(path)
    package = name.split(".") if path.name == "__init__.py" else name.split(".")[:-1]
    found = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom):
            if node.level:
                base = package[:len(package) - node.level + 1]
                target = ".".join(base + ([node.module] if node.module else []))
            elif node.module and node.module.startswith("pothole_detector"):
                target = node.module.removeprefix("pothole_detector").lstrip(".")
            else:
                continue
            for alias in node.names:
                joined = f"{target}.{alias.name}" if target else alias.name
                found.add(joined if (PACKAGE / joined.replace(".", "/")).with_suffix(".py")
                          .exists() or (PACKAGE / joined.replace(".", "/")).is_dir()
                          else target)
        elif isinstance(node, ast.Import):
            for alias in node.names:
                if alias.name.startswith("pothole_detector."):
                    found.add(alias.name.removeprefix("pothole_detector."))
    return {f for f in found if f and f != name}


def graph() -> dict[str, set[str]]:
    return {module_name(p): imports_of(p) for p in PACKAGE.rglob("*.py")}


def cycles(edges: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components of more than one module (Tarjan)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    found: list[list[str]] = []

    def visit(node: str) -> None:
        index[node] = low[node] = len(index)
        stack.append(node)
        for target in edges.get(node, ()):
            if target not in index:
                visit(target)
                low[node] = min(low[node], low[target])
            elif target in stack:
                low[node] = min(low[node], index[target])
        if low[node] == index[node]:
            component = []
            while True:
                top = stack.pop()
                component.append(top)
                if top == node:
                    break
            if len(component) > 1:
                found.append(sorted(component))

    for node in sorted(edges):
        if node not in index:
            visit(node)
    return found


def top(name: str) -> str:
    return name.split(".")[0]


def test_the_graph_sees_relative_and_function_level_imports():
    edges = graph()
    assert "survey.motion" in edges["survey.tracking"]
    assert "geodesy" in edges["recordings.writing"]
    assert "survey.fleet" in edges["cli"]  # imported inside run_survey


def test_no_import_cycle():
    assert cycles(graph()) == []


def test_execution_runs_the_method_one_way():
    """The method knows nothing of how it is executed; the executor knows the method, not the
    pipeline that puts the two together."""
    edges = graph()
    assert not {"execution", "pipeline"} & edges["method"]
    assert "method" in edges["execution"] and "pipeline" not in edges["execution"]
    assert {"method", "execution"} <= edges["pipeline"]
    for source, targets in edges.items():
        if top(source) == "stages":
            assert not {"method", "execution", "pipeline"} & {top(t) for t in targets}, source


def test_subpackages_depend_one_way():
    between: dict[str, set[str]] = {}
    for source, targets in graph().items():
        for target in targets:
            if top(source) != top(target):
                between.setdefault(top(source), set()).add(top(target))
    assert cycles(between) == []


def test_the_method_imports_nothing_above_it():
    for source, targets in graph().items():
        if top(source) in METHOD:
            assert not {top(t) for t in targets} & set(ABOVE_THE_METHOD), source


def test_the_layers_above_the_method_import_only_those_below_them():
    for source, targets in graph().items():
        if top(source) in MAY_IMPORT:
            above = {top(t) for t in targets} & set(ABOVE_THE_METHOD) - {top(source)}
            assert above <= MAY_IMPORT[top(source)], (source, above)


def test_the_ros_graph_is_joined_only_under_ros():
    """rclpy's graph (nodes, publishers, executors) is used by ros/ only; the recordings may
    take its message classes and serialization, where ROS is installed."""
    for path in PACKAGE.rglob("*.py"):
        if top(module_name(path)) == "ros":
            continue
        for node in ast.walk(ast.parse(path.read_text())):
            modules = [alias.name for alias in node.names] if isinstance(node, ast.Import) \
                else [node.module or ""] if isinstance(node, ast.ImportFrom) else []
            for module in modules:
                assert module.split(".")[0] != "rclpy" or module == "rclpy.serialization", \
                    (path, module)
