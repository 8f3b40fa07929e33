"""The house stays small: module and function sizes, no import cycles, imports at the top,
configs of user settings, stages that talk through files, documents of bounded length."""

from __future__ import annotations

import ast
import dataclasses
import json
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
PACKAGE = REPO / "ctcvo"
MAX_MODULE_LINES = 600
MAX_FUNCTION_LINES = 80


def _modules() -> dict[str, Path]:
    out = {}
    for f in sorted(PACKAGE.rglob("*.py")):
        parts = list(f.relative_to(REPO).with_suffix("").parts)
        out[".".join(parts[:-1] if parts[-1] == "__init__" else parts)] = f
    return out


MODULES = _modules()
TREES = {name: ast.parse(f.read_text(), str(f)) for name, f in MODULES.items()}


def _is_cli(name: str) -> bool:
    return name.split(".")[-1] in ("cli", "__main__") or name.endswith("_cli")


def _imports(node: ast.AST) -> list[str]:
    """The ctcvo modules an import statement names (a ``from m import x`` names m.x where that is a module)."""
    if isinstance(node, ast.Import):
        return [a.name for a in node.names if a.name.startswith("ctcvo")]
    if isinstance(node, ast.ImportFrom) and node.module and node.module.startswith("ctcvo"):
        subs = [f"{node.module}.{a.name}" for a in node.names if f"{node.module}.{a.name}" in MODULES]
        return [node.module, *subs]
    return []


def test_the_checks_see_the_package() -> None:
    assert len(MODULES) > 40 and "ctcvo.teacher" in MODULES and "ctcvo.cli" in MODULES


def test_no_module_over_600_lines() -> None:
    big = {n: f.read_text().count("\n") for n, f in MODULES.items()}
    assert not {n: k for n, k in big.items() if k > MAX_MODULE_LINES}


def test_no_function_over_80_lines() -> None:
    long = [f"{n}:{d.lineno} {d.name} ({d.end_lineno - d.lineno + 1})" for n, t in TREES.items() for d in ast.walk(t)
            if isinstance(d, ast.FunctionDef | ast.AsyncFunctionDef) and d.end_lineno - d.lineno + 1 > MAX_FUNCTION_LINES]
    assert not long


def test_project_imports_at_module_top_except_in_clis() -> None:
    inner = [f"{n}:{s.lineno}" for n, t in TREES.items() if not _is_cli(n) for d in ast.walk(t)
             if isinstance(d, ast.FunctionDef | ast.AsyncFunctionDef) for s in ast.walk(d) if _imports(s)]
    assert not inner


def _graph() -> dict[str, set[str]]:
    return {n: {m for s in t.body for m in _imports(s) if m in MODULES and m != n} for n, t in TREES.items()}


def test_no_import_cycles() -> None:
    graph, state, cycles = _graph(), {}, []

    def visit(node: str, path: list[str]) -> None:
        state[node] = 1
        for nxt in sorted(graph[node]):
            if state.get(nxt) == 1:
                cycles.append(path[path.index(nxt):] + [nxt] if nxt in path else [node, nxt])
            elif nxt not in state:
                visit(nxt, [*path, nxt])
        state[node] = 2

    for n in sorted(graph):
        if n not in state:
            visit(n, [n])
    assert not cycles


@pytest.mark.parametrize("stage, forbidden", [
    ("ctcvo.data", ("ctcvo.teacher", "ctcvo.learner", "ctcvo.posegraph", "ctcvo.pipeline")),
    ("ctcvo.teacher", ("ctcvo.learner", "ctcvo.posegraph", "ctcvo.pipeline")),
    ("ctcvo.learner", ("ctcvo.teacher", "ctcvo.posegraph", "ctcvo.pipeline")),
    ("ctcvo.posegraph", ("ctcvo.teacher", "ctcvo.learner", "ctcvo.pipeline")),
])
def test_stages_talk_through_files(stage: str, forbidden: tuple[str, ...]) -> None:
    bad = [f"{n} -> {m}" for n, t in TREES.items() if n == stage or n.startswith(stage + ".")
           for s in ast.walk(t) for m in _imports(s) if m.startswith(forbidden)]
    assert not bad


def test_configs_hold_user_settings() -> None:
    from ctcvo.posegraph.config import PoseGraphConfig
    from ctcvo.teacher.config import TeacherConfig

    assert 0 < len(dataclasses.fields(TeacherConfig)) <= 20
    assert 0 < len(dataclasses.fields(PoseGraphConfig)) <= 15


def test_one_package_one_command() -> None:
    tomllib = pytest.importorskip("tomllib")
    project = tomllib.loads((REPO / "pyproject.toml").read_text())
    assert project["project"]["scripts"] == {"ctcvo": "ctcvo.cli:main"}
    assert project["tool"]["setuptools"]["packages"]["find"]["include"] == ["ctcvo*"]


def test_documents_are_for_readers() -> None:
    assert (REPO / "README.md").read_text().count("\n") <= 150
    assert (REPO / "bench" / "README.md").read_text().count("\n") <= 400
    results = sorted((REPO / "bench" / "results").glob("*.json"))
    assert len(results) >= 5
    for f in results:
        rec = json.loads(f.read_text())
        assert {"command", "revision", "date_utc", "machine", "config", "figures"} <= set(rec), f.name
