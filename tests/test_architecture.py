"""The package's structure: no import cycle between its modules, counting every import.

An import inside a function or under ``if TYPE_CHECKING`` is a dependency too: it only
defers the loop it would close. Cycles are counted over all of them; which modules load
at import time (the command line's speed) is checked over module-level imports alone.
"""

from __future__ import annotations

import ast
from pathlib import Path

from .conftest import ROOT

PACKAGE = ROOT / "tvopt_codegen"


def _module_name(path: Path, root: Path = ROOT) -> str:
    parts = path.relative_to(root).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _imports(path: Path, modules: set[str], everywhere: bool, root: Path = ROOT) -> set[str]:
    """The package's modules ``path`` imports: anywhere in it, or at import time only
    (not in functions, not under ``if TYPE_CHECKING``)."""
    name = _module_name(path, root)
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    found: set[str] = set()

    def add(module: str, names: list[str]) -> None:
        for alias in names:
            candidate = f"{module}.{alias}"
            if candidate in modules:
                found.add(candidate)
            elif module in modules:
                found.add(module)

    def visit(statements: list[ast.stmt]) -> None:
        for node in statements:
            if isinstance(node, ast.Import):
                for alias in node.names:
                    module = alias.name
                    while module and module not in modules:
                        module = module.rpartition(".")[0]
                    if module:
                        found.add(module)
            elif isinstance(node, ast.ImportFrom):
                base = node.module or ""
                if node.level:
                    parts = package.split(".")
                    base = ".".join(parts[: len(parts) - node.level + 1] + ([base] if base else []))
                add(base, [a.name for a in node.names])
            elif isinstance(node, ast.If):
                typing_only = isinstance(node.test, ast.Name) and node.test.id == "TYPE_CHECKING"
                if everywhere or not typing_only:
                    visit(node.body)
                    visit(node.orelse)
            elif isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
                if everywhere or isinstance(node, ast.ClassDef):
                    visit(node.body)
            else:
                for field in ("body", "orelse", "finalbody", "handlers"):
                    block = getattr(node, field, None)
                    if isinstance(block, list):
                        visit(
                            [s for s in block if isinstance(s, ast.stmt)]
                            + [s for h in block if isinstance(h, ast.ExceptHandler) for s in h.body]
                        )

    visit(ast.parse(path.read_text()).body)
    return found - {name}


def _graph(
    everywhere: bool, root: Path = ROOT, package: str = "tvopt_codegen"
) -> dict[str, set[str]]:
    paths = {_module_name(p, root): p for p in (root / package).rglob("*.py")}
    modules = set(paths)
    return {name: _imports(path, modules, everywhere, root) for name, path in paths.items()}


def _cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components of more than one module (Tarjan)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found: list[list[str]] = []

    def connect(node: str) -> None:
        index[node] = low[node] = len(index)
        stack.append(node)
        on_stack.add(node)
        for nxt in sorted(graph[node]):
            if nxt not in index:
                connect(nxt)
                low[node] = min(low[node], low[nxt])
            elif nxt in on_stack:
                low[node] = min(low[node], index[nxt])
        if low[node] == index[node]:
            component = []
            while True:
                member = stack.pop()
                on_stack.discard(member)
                component.append(member)
                if member == node:
                    break
            if len(component) > 1:
                found.append(sorted(component))

    for name in sorted(graph):
        if name not in index:
            connect(name)
    return found


def test_no_import_cycle_counting_every_import() -> None:
    graph = _graph(everywhere=True)
    cycles = _cycles(graph)
    assert not cycles, "import cycles: " + "; ".join(" <-> ".join(c) for c in cycles)
    # The graph is real: deferred and type-only imports are in it.
    assert "tvopt_codegen.jet" in graph["tvopt_codegen.derivation.objective"]
    assert "tvopt_codegen.derivation" in graph["tvopt_codegen.commands.common"]


def test_the_cycle_finder_sees_deferred_and_type_only_imports(tmp_path: Path) -> None:
    package = tmp_path / "pkg"
    package.mkdir()
    (package / "__init__.py").write_text("")
    (package / "a.py").write_text("def f():\n    from pkg import b\n")
    (package / "b.py").write_text(
        "from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    from pkg.a import f\n"
    )
    (package / "c.py").write_text("from . import a\n")
    assert _cycles(_graph(True, tmp_path, "pkg")) == [["pkg.a", "pkg.b"]]
    assert _cycles(_graph(False, tmp_path, "pkg")) == []
    assert _graph(False, tmp_path, "pkg")["pkg.c"] == {"pkg.a"}


def test_every_layer_keeps_to_its_place() -> None:
    graph = _graph(everywhere=True)
    # Load knows nothing of render: the spec reader reaches no backend module by name.
    assert not {m for m in graph["tvopt_codegen.names"] if m.startswith("tvopt_codegen.backends.")}
    # Figures are drawn by one module on top of the verification stages.
    importers = sorted(m for m, imported in graph.items() if "tvopt_codegen.figures" in imported)
    assert importers == ["tvopt_codegen.artifacts"]
    # The writer does not reach back into the renderer (the stamp is its own module).
    assert "tvopt_codegen.rendering" not in graph["tvopt_codegen.emit"]


def test_the_command_line_loads_the_stages_only_inside_its_commands() -> None:
    graph = _graph(everywhere=False)
    assert "tvopt_codegen.jet" in graph["tvopt_codegen.derivation.objective"]
    assert "tvopt_codegen.derivation" not in graph["tvopt_codegen.cli"]
    assert "tvopt_codegen.figures" not in graph["tvopt_codegen.simulation"]


#: The derivation stage: the only modules that differentiate (sympy's diff, Derivative,
#: jacobian, hessian). Everything after it evaluates or lowers what it derived.
DERIVATION_STAGE = ("tvopt_codegen.derivation", "tvopt_codegen.jet", "tvopt_codegen.lie")
_DIFFERENTIATION = {"diff", "Derivative", "jacobian", "hessian", "idiff"}


def _differentiations(path: Path) -> list[str]:
    """Calls in ``path`` that differentiate symbolically (numpy's ``np.diff`` is not one)."""
    found = []
    for node in ast.walk(ast.parse(path.read_text())):
        if not isinstance(node, ast.Call):
            continue
        func = node.func
        if isinstance(func, ast.Name) and func.id in _DIFFERENTIATION - {"hessian"}:
            found.append(f"{path.name}:{node.lineno} {func.id}(")
        elif isinstance(func, ast.Attribute) and func.attr in _DIFFERENTIATION:
            owner = func.value.id if isinstance(func.value, ast.Name) else ""
            if owner in {"np", "numpy"}:
                continue
            # A generated controller's hessian() evaluates a kernel; sympy's differentiates.
            if func.attr == "hessian" and owner not in {"sp", "sympy"}:
                continue
            found.append(f"{path.name}:{node.lineno} {owner}.{func.attr}(")
    return found


def test_only_the_derivation_stage_differentiates() -> None:
    offenders = [
        call
        for path in sorted(PACKAGE.rglob("*.py"))
        if not _module_name(path).startswith(DERIVATION_STAGE)
        for call in _differentiations(path)
    ]
    assert not offenders, offenders
    # The scan sees what it must: the derivation's own calls.
    assert _differentiations(PACKAGE / "derivation" / "calculus.py")
