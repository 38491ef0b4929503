"""The package's structure: its layers, and no import cycle between its modules.

An import inside a function or under ``if TYPE_CHECKING`` is a dependency too: it only
defers the loop it would close. Cycles and the layers' order are checked over all of
them; which modules load at import time (the command line's speed) is checked over
module-level imports alone.
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
    assert "tvopt_codegen.maths.jet" in graph["tvopt_codegen.derivation.objective"]
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
    assert not {
        m for m in graph["tvopt_codegen.spec.names"] if m.startswith("tvopt_codegen.backends.")
    }
    # Figures are drawn by one module on top of the verification stages.
    importers = sorted(
        m for m, imported in graph.items() if "tvopt_codegen.runs.figures" in imported
    )
    assert importers == ["tvopt_codegen.runs.artifacts"]
    # The writer does not reach back into the renderer (the stamp is its own module).
    assert "tvopt_codegen.renderer.rendering" not in graph["tvopt_codegen.emit"]


#: The package's layers, lowest first, each a tuple of paths below ``tvopt_codegen``
#: (a module, or a package with everything in it; ``""`` is the package's ``__init__``,
#: whose re-exports are imported on first use by name, not by an import statement). A
#: module imports only from its own layer and the layers below it.
LAYERS: tuple[tuple[str, ...], ...] = (
    # What every stage shares: the contract's tables, the errors, the bounds.
    ("", "contract", "errors", "limits"),
    # The one symbolic API over SymEngine and SymPy, and its border with SymPy.
    ("symbolic",),
    # The mathematics the derivation stands on; it reads no spec.
    ("maths",),
    # Load: a spec file, a SymPy mechanics model or a URDF robot -> a checked spec.
    ("spec", "mechanics", "urdf"),
    # The model and the derivation of the law (and what reads only the derivation).
    ("derivation",),
    # The law as kernels: the IR, its CSE, the plan, the printers' order.
    ("lowering", "cse"),
    # The writer, and the compiler lookup its library cache runs (``toolchain`` stays at
    # the top: inside ``emit/`` it would break the rule that only ``emit.caches`` compiles).
    ("emit", "toolchain"),
    # Kernels printed by a backend into its templates.
    ("renderer", "backends"),
    # What is done with a generated controller: runs, sweeps, the FMU, figures, reports.
    ("simulation", "sweep", "runs", "report", "interop", "tune"),
    # The doors: the command line.
    ("commands", "cli", "__main__"),
)

#: The imports that go up a layer, each as ``(importer, imported)`` with why it stays.
UPWARD_IMPORTS_ALLOWED = {
    # A spec's names may be no backend's reserved word: the reader asks the backends'
    # registry (``backends/__init__``, which itself loads only ``backends.base``) for the
    # words each backend, a plugin's too, reserves. It reaches no backend module.
    ("tvopt_codegen.spec.names", "tvopt_codegen.backends"),
}

#: Issue 48: the top of the package holds at most this many modules; the rest are layers.
MAX_TOP_LEVEL_MODULES = 12


def _layer(
    module: str, layers: tuple[tuple[str, ...], ...] = LAYERS, package: str = "tvopt_codegen"
) -> int:
    """The index in ``layers`` of ``module``'s layer; it must be in exactly one."""
    path = module.removeprefix(package).removeprefix(".")
    found = [
        index
        for index, layer in enumerate(layers)
        for prefix in layer
        if path == prefix or (prefix and path.startswith(f"{prefix}."))
    ]
    assert len(found) == 1, (module, found)
    return found[0]


def _upward_imports(
    graph: dict[str, set[str]],
    layers: tuple[tuple[str, ...], ...] = LAYERS,
    package: str = "tvopt_codegen",
) -> list[tuple[str, str]]:
    """Every ``(importer, imported)`` of ``graph`` that goes from a lower layer to a higher."""
    for module in graph:
        _layer(module, layers, package)  # every module is in exactly one layer
    return sorted(
        (module, imported)
        for module, imports in graph.items()
        for imported in imports
        if _layer(imported, layers, package) > _layer(module, layers, package)
    )


def test_a_lower_layer_never_imports_a_higher_one() -> None:
    upward = set(_upward_imports(_graph(everywhere=True)))
    assert upward <= UPWARD_IMPORTS_ALLOWED, sorted(upward - UPWARD_IMPORTS_ALLOWED)
    # Every allowance is still needed: one that no longer happens is struck off.
    assert upward == UPWARD_IMPORTS_ALLOWED, sorted(UPWARD_IMPORTS_ALLOWED - upward)


def test_the_top_of_the_package_holds_few_modules() -> None:
    top = sorted(p.name for p in PACKAGE.glob("*.py"))
    assert len(top) <= MAX_TOP_LEVEL_MODULES, top


def test_the_layer_check_sees_an_upward_import(tmp_path: Path) -> None:
    package = tmp_path / "pkg"
    (package / "low").mkdir(parents=True)
    for init in (package / "__init__.py", package / "low" / "__init__.py"):
        init.write_text("")
    # Deferred, in a function: it counts all the same.
    (package / "low" / "a.py").write_text("def f():\n    from pkg.high import g\n")
    (package / "high.py").write_text("from pkg.low import a\n\n\ndef g():\n    pass\n")
    graph = _graph(True, tmp_path, "pkg")
    assert _upward_imports(graph, (("",), ("low",), ("high",)), "pkg") == [
        ("pkg.low.a", "pkg.high")
    ]
    assert _upward_imports(graph, (("",), ("high", "low")), "pkg") == []
    # A module in no layer, or in two, is refused.
    for wrong in ((("",), ("low",)), (("", "low"), ("low",), ("high",))):
        try:
            _upward_imports(graph, wrong, "pkg")
        except AssertionError:
            continue
        raise AssertionError(f"the layers {wrong} were accepted")


#: The URDF import's steps (``tvopt_codegen.urdf``), lowest first; its ``__init__`` runs them.
URDF_STEPS = ("elements", "reading", "chain", "dynamics", "objective", "mapping")


def test_the_urdf_import_steps_only_import_the_steps_below() -> None:
    graph = _graph(everywhere=True)
    package = "tvopt_codegen.urdf"
    steps = [f"{package}.{step}" for step in URDF_STEPS]
    assert {m for m in graph if m.startswith(f"{package}.")} == set(steps)
    for index, step in enumerate(steps):
        inside = {m for m in graph[step] if m == package or m.startswith(f"{package}.")}
        assert inside <= set(steps[:index]), (step, sorted(inside - set(steps[:index])))
    # The scan sees what it must: the package runs every step.
    assert set(steps) <= graph[package]


def test_the_command_line_loads_the_stages_only_inside_its_commands() -> None:
    graph = _graph(everywhere=False)
    assert "tvopt_codegen.maths.jet" in graph["tvopt_codegen.derivation.objective"]
    assert "tvopt_codegen.derivation" not in graph["tvopt_codegen.cli"]
    assert "tvopt_codegen.runs.figures" not in graph["tvopt_codegen.simulation"]


#: The derivation stage: the only modules that differentiate (sympy's diff, Derivative,
#: jacobian, hessian). Everything after it evaluates or lowers what it derived.
DERIVATION_STAGE = (
    "tvopt_codegen.derivation",
    "tvopt_codegen.maths.jet",
    "tvopt_codegen.maths.lie",
)
#: Modules of ``derivation/`` (their layer) that are not the differentiating stage: the
#: model is built before it, the law and the robustness read what it derived.
NOT_DIFFERENTIATING = tuple(
    f"tvopt_codegen.derivation.{name}" for name in ("model", "law", "robust")
)
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
        or _module_name(path).startswith(NOT_DIFFERENTIATING)
        for call in _differentiations(path)
    ]
    assert not offenders, offenders
    # The scan sees what it must: the derivation's own calls.
    assert _differentiations(PACKAGE / "derivation" / "calculus.py")


#: The writer's package, and the one module of it that may compile: templates (jinja2)
#: or C (the toolchain).
WRITER = PACKAGE / "emit"
WRITER_CACHES = "tvopt_codegen.emit.caches"
#: What finds or runs a compiler or compiles templates: the template engine, processes,
#: the interpreter's build settings, and the project's modules that run the C compiler.
_TOOLCHAIN = (
    "jinja2",
    "subprocess",
    "sysconfig",
    "tvopt_codegen.toolchain",
    "tvopt_codegen.runs.fmu",
)
#: A compiler looked up by name on PATH, as ``(module, name)``.
_TOOLCHAIN_LOOKUPS = {("shutil", "which"), ("os", "get_exec_path")}
_TERMINAL = {"stdout", "stderr", "__stdout__", "__stderr__"}


def _writer_reach(path: Path, root: Path = ROOT) -> tuple[list[str], list[str]]:
    """What in ``path`` reaches the toolchain, and what reaches the terminal, a line each.

    Every import counts (module level, in functions, under ``TYPE_CHECKING``, and
    ``importlib.import_module`` or ``__import__`` of a literal name), as do
    ``shutil.which``-style lookups. The terminal is reached by a ``print`` call or any
    use of ``sys.stdout`` or ``sys.stderr`` (a ``write``, a ``file=`` argument, a
    ``from sys import``). Importing the writer's caches counts as reaching the toolchain.
    """
    name = _module_name(path, root)
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    imported: list[tuple[int, str]] = []
    toolchain: list[str] = []
    terminal: list[str] = []
    for node in ast.walk(ast.parse(path.read_text())):
        line = f"{path.name}:{getattr(node, 'lineno', 0)}"
        if isinstance(node, ast.Import):
            imported += [(node.lineno, alias.name) for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                parts = package.split(".")
                base = ".".join(parts[: len(parts) - node.level + 1] + ([base] if base else []))
            imported.append((node.lineno, base))
            for alias in node.names:
                imported.append((node.lineno, f"{base}.{alias.name}"))
                if (base, alias.name) in _TOOLCHAIN_LOOKUPS:
                    toolchain.append(f"{line} imports {base}.{alias.name}")
                if base == "sys" and alias.name in _TERMINAL:
                    terminal.append(f"{line} imports sys.{alias.name}")
        elif isinstance(node, ast.Call):
            func = node.func
            called = func.id if isinstance(func, ast.Name) else getattr(func, "attr", "")
            if called == "print":
                terminal.append(f"{line} calls print")
            elif called in {"import_module", "__import__"} and node.args:
                first = node.args[0]
                if isinstance(first, ast.Constant) and isinstance(first.value, str):
                    imported.append((node.lineno, first.value))
        elif isinstance(node, ast.Attribute) and isinstance(node.value, ast.Name):
            if (node.value.id, node.attr) in _TOOLCHAIN_LOOKUPS:
                toolchain.append(f"{line} uses {node.value.id}.{node.attr}")
            if node.value.id == "sys" and node.attr in _TERMINAL:
                terminal.append(f"{line} uses sys.{node.attr}")
    toolchain += [
        f"{path.name}:{lineno} imports {module}"
        for lineno, module in imported
        if any(module == m or module.startswith(f"{m}.") for m in (*_TOOLCHAIN, WRITER_CACHES))
    ]
    return sorted(set(toolchain)), sorted(set(terminal))


def test_the_writer_only_writes() -> None:
    """Only ``emit.caches`` reaches jinja2 or the compiler; nothing in ``emit`` prints.

    The package's ``__init__`` re-exports the caches' names, imported on first use, so
    it may name that module (and that module alone); the transaction and the sweep's
    streams may not, or writing a file would load the toolchain through them.
    """
    modules = {_module_name(p): p for p in sorted(WRITER.glob("*.py"))}
    assert {"transaction", "caches", "streams"} <= {m.rpartition(".")[2] for m in modules}
    offences = []
    for module, path in modules.items():
        toolchain, terminal = _writer_reach(path)
        offences += terminal
        if module == "tvopt_codegen.emit":
            offences += [
                o
                for o in toolchain
                if not f"{o.partition(' imports ')[2]}.".startswith(f"{WRITER_CACHES}.")
            ]
        elif module != WRITER_CACHES:
            offences += toolchain
    assert not offences, offences
    # The scan sees what it must: the caches' own jinja2, compiler and toolchain.
    caches, _ = _writer_reach(modules[WRITER_CACHES])
    for what in ("jinja2", "subprocess", "tvopt_codegen.toolchain"):
        assert any(o.endswith(f"imports {what}") for o in caches), (what, caches)


def test_the_writer_scan_sees_every_way_to_the_toolchain_or_the_terminal(
    tmp_path: Path,
) -> None:
    writer = tmp_path / "tvopt_codegen" / "emit"
    writer.mkdir(parents=True)
    bad = writer / "bad.py"
    bad.write_text(
        "import importlib, shutil, sys\n"
        "from typing import TYPE_CHECKING\n"
        "from .caches import cached_library\n"
        "if TYPE_CHECKING:\n"
        "    import jinja2\n"
        "def f():\n"
        "    from tvopt_codegen import toolchain\n"
        "    import subprocess as sp\n"
        "    importlib.import_module('sysconfig')\n"
        "    shutil.which('cc')\n"
        "    print('x')\n"
        "    sys.stderr.write('x')\n"
        "    print('y', file=sys.stdout)\n"
    )
    toolchain, terminal = _writer_reach(bad, tmp_path)
    for what in (
        "imports tvopt_codegen.emit.caches",
        "imports jinja2",
        "imports tvopt_codegen.toolchain",
        "imports subprocess",
        "imports sysconfig",
        "uses shutil.which",
    ):
        assert any(o.endswith(what) for o in toolchain), (what, toolchain)
    for what in ("calls print", "uses sys.stderr", "uses sys.stdout"):
        assert any(o.endswith(what) for o in terminal), (what, terminal)
    clean = writer / "clean.py"
    clean.write_text("import os\nfrom pathlib import Path\n\nos.replace(Path('a'), Path('b'))\n")
    assert _writer_reach(clean, tmp_path) == ([], [])


#: Issue 48's bounds on what a newcomer has to read at once.
MAX_MODULE_LINES, MAX_FUNCTION_LINES = 800, 120


def _oversized(root: Path) -> list[str]:
    """Modules over MAX_MODULE_LINES and functions (def to last line) over MAX_FUNCTION_LINES."""
    found = []
    for path in sorted(root.rglob("*.py")):
        text = path.read_text(encoding="utf-8")
        where = path.relative_to(root).as_posix()
        if text.count("\n") > MAX_MODULE_LINES:
            found.append(f"{where}: {text.count(chr(10))} lines")
        for node in ast.walk(ast.parse(text)):
            if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef):
                length = (node.end_lineno or node.lineno) - node.lineno + 1
                if length > MAX_FUNCTION_LINES:
                    found.append(f"{where}: {node.name} has {length} lines")
    return found


def test_no_module_or_function_is_too_long_to_read() -> None:
    assert _oversized(PACKAGE) == []


def test_the_size_check_sees_a_long_function_and_a_long_module(tmp_path: Path) -> None:
    body = "".join(f"    x{i} = {i}\n" for i in range(MAX_FUNCTION_LINES))
    (tmp_path / "long.py").write_text(f"def f() -> None:\n{body}", encoding="utf-8")
    (tmp_path / "big.py").write_text("x = 1\n" * (MAX_MODULE_LINES + 1), encoding="utf-8")
    assert _oversized(tmp_path) == [
        f"big.py: {MAX_MODULE_LINES + 1} lines",
        f"long.py: f has {MAX_FUNCTION_LINES + 1} lines",
    ]


#: The derivation's stages after build_model: they read the Model, never the Spec.
MODEL_READERS = (
    "linearization",
    "singularity",
    "convexity",
    "equalities",
    "objective",
    "meter",
    "robust",
    "rejection",
    "law",
    "calculus",
)


def _spec_uses(path: Path) -> list[str]:
    """Where a module imports or names the ``Spec`` type (docstrings do not count)."""
    tree = ast.parse(path.read_text(encoding="utf-8"))
    found = []
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom) and any(a.name == "Spec" for a in node.names):
            found.append(f"{path.name}:{node.lineno}: imports Spec")
        elif isinstance(node, ast.Name) and node.id == "Spec":
            found.append(f"{path.name}:{node.lineno}: names Spec")
    return found


def test_the_stages_after_build_model_read_the_model_not_the_spec(tmp_path: Path) -> None:
    folder = PACKAGE / "derivation"
    assert [use for name in MODEL_READERS for use in _spec_uses(folder / f"{name}.py")] == []
    # The scan sees both ways in.
    probe = tmp_path / "probe.py"
    probe.write_text("from tvopt_codegen.spec import Spec\n\ndef f(s: Spec) -> None: ...\n")
    assert len(_spec_uses(probe)) == 2
