"""Hostile and broken input: one line, a documented exit code, nothing written, fast.

Every case mutates the bundled unicycle spec (or writes a file of its own), runs the
CLI into a folder that already holds a file, and checks: the exit code, exactly one
line on stderr naming the file and the field (and the column in an expression), no
traceback, the folder unchanged byte for byte, and an answer within 5 seconds.
"""

from __future__ import annotations

import subprocess
import sys
import time
from pathlib import Path

import pytest

from tvopt_codegen.cli import main
from tvopt_codegen.errors import EXIT_ASSUMPTION, EXIT_BAD_SPEC, EXIT_BUDGET
from tvopt_codegen.spec.names import module_name_problem

from .conftest import ROOT, run_main

UNICYCLE = (ROOT / "tvopt_codegen" / "examples" / "unicycle_switch.toml").read_text()
F0 = 'f0 = "S*((y1 - o1x)**2 + (y2 - o1y)**2) + (1 - S)*((y1 - o2x)**2 + (y2 - o2y)**2)"'


def _snapshot(folder: Path) -> dict[str, bytes]:
    return {p.name: p.read_bytes() for p in sorted(folder.iterdir())}


def _run(
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
    spec: Path,
    code: int,
    field: str,
    message: str,
    command: str = "generate",
    extra: tuple[str, ...] = (),
) -> None:
    out = tmp_path / "out"
    out.mkdir(exist_ok=True)
    (out / "keep.txt").write_text("a file of the user's")
    before = _snapshot(out)
    start = time.perf_counter()
    args = [command, str(spec), *extra]
    if command != "check":
        args += ["--out", str(out)]
    assert main(args) == code
    elapsed = time.perf_counter() - start
    captured = capsys.readouterr()
    lines = captured.err.splitlines()
    assert len(lines) == 1, captured.err
    assert lines[0].startswith("tvopt-codegen: error: "), lines[0]
    assert field in lines[0] and message in lines[0], lines[0]
    assert "Traceback" not in captured.err and captured.out == ""
    assert _snapshot(out) == before
    assert elapsed < 5.0


def _spec(tmp_path: Path, text: str, name: str = "spec.toml") -> Path:
    path = tmp_path / name
    path.write_text(text, encoding="utf-8")
    return path


def _f0(expr: str) -> str:
    """The unicycle spec with f0 replaced, as a TOML literal string (no escapes at all)."""
    assert "'''" not in expr
    return UNICYCLE.replace(F0, "f0 = '''" + expr + "'''")


CODE_EXECUTION = [
    ("__import__('os').system('touch /tmp/tvopt-pwned')", "cannot call"),
    ("y1.__class__.__mro__", "attribute access is not allowed"),
    ("(lambda: 1)() + y1", "cannot call"),
    ("[y1 for y1 in (1, 2)]", "comprehensions are not allowed"),
    ("f'{y1}'", "f-strings are not allowed"),
    ("y1 if y2 else 0", "conditional expressions are not allowed"),
    ("eval('y1')", "cannot call 'eval'"),
    ("open('/etc/passwd')", "cannot call 'open'"),
    ("getattr(y1, 'real')", "cannot call 'getattr'"),
    ("y1[0]", "indexing is not allowed"),
    ("(y1 := 3)", "assignment expressions are not allowed"),
]


@pytest.mark.parametrize(("expr", "message"), CODE_EXECUTION)
def test_code_execution_attempts(
    expr: str, message: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    _run(tmp_path, capsys, _spec(tmp_path, _f0(expr)), EXIT_BAD_SPEC, "objective.f0", message)
    assert not Path("/tmp/tvopt-pwned").exists()


RESOURCES = [
    ("y1**(10**10)", "exponent 10000000000 exceeds 64"),
    ("2**2**2**2**2 + y1", "exceeds 64"),
    ("10**999999 + y1", "exceeds 64"),
    ("1e400 + y1", "non-finite number"),
    ("y1 + 123456789012345678", "exceeds 1e+12"),
    ("(((9**64)**64)**64)**64 + y1", "constant too large (about 10^3910"),
    ("*".join(["9**64"] * 24) + " + y1", "constant too large"),
    ("sin(" * 100 + "y1" + ")" * 100, "nesting deeper than 60"),
    ("-" * 300 + "y1", "nest"),
    # Parentheses that each hold a sum are nesting, however many (redundant ones parse:
    # test_redundant_parentheses_are_flat below).
    ("(" * 1000 + "y1" + " + 1)" * 1000 + "**2", "column 61: nesting deeper than 60"),
    ("(" * 100_000 + "y1" + "+1)" * 100_000 + "**2", "column 61: nesting deeper than 60"),
    ("(" * 250 + "y1" + "+1)" * 250, "nesting deeper than 60"),
]


@pytest.mark.parametrize(("expr", "message"), RESOURCES)
def test_resource_attacks_in_expressions(
    expr: str, message: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    _run(tmp_path, capsys, _spec(tmp_path, _f0(expr)), EXIT_BAD_SPEC, "objective.f0", message)


@pytest.mark.parametrize("count", [200, 3000, 100_000])
def test_redundant_parentheses_are_flat(
    count: int, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    # The fourth hostile round's 3,000 pairs around f0 exhausted the stack (exit 6): they
    # add nothing, so the spec is the unicycle's own and checks like it.
    wrapped = "(" * count + F0[len('f0 = "') : -1] + ")" * count
    assert main(["check", str(_spec(tmp_path, _f0(wrapped)))]) == 0
    captured = capsys.readouterr()
    assert "f0: strongly convex" in captured.out and captured.err == ""


def test_huge_file(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    spec = _spec(tmp_path, UNICYCLE + "\n# " + "x" * 1_100_000 + "\n")
    _run(tmp_path, capsys, spec, EXIT_BAD_SPEC, "(file)", "the limit is 1000000")


@pytest.mark.parametrize("depth", [40, 58])
def test_derivatives_that_explode_stop_at_the_budget(
    depth: int, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """An output nested ``depth`` deep: its second Lie derivative has ~depth**3 nodes.

    (Derivatives of the objective and the signals no longer swell: they are taken on
    straight-line programs. Lie derivatives are expressions, checked by the budget.)
    """
    nested = "sin(" * depth + "x1/10" + ")" * depth
    old = 'y1 = "x1"'
    assert old in UNICYCLE
    _run(
        tmp_path,
        capsys,
        _spec(tmp_path, UNICYCLE.replace(old, f'y1 = "{nested}"')),
        EXIT_BUDGET,
        "derivation stage 'relative degree'",
        "grew past 20000 nodes",
    )


def test_size_budget_is_configurable_and_names_the_stage(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    spec = _spec(tmp_path, UNICYCLE)
    _run(
        tmp_path,
        capsys,
        spec,
        EXIT_BUDGET,
        "derivation stage",
        "grew past 10 nodes",
        extra=("--max-size", "10"),
    )


WRONG_MATH = [
    ("y1 < y2", "comparisons are not allowed"),
    ("y1 and y2", "logical operators are not allowed"),
    ("not y1", "operator Not is not allowed"),
    ("y1 + speed", "column 6: unknown name 'speed'"),
    ("sin(y1, y2)", "sin() takes 1 argument(s), got 2"),
    ("sin(x=y1)", "takes no keyword arguments"),
    ("sin(*[y1])", "starred arguments are not allowed"),
    ("y1^2", "'^' is not a power; write '**'"),
    ("y1/(y2 - y2)", "division by zero"),
    ("log(0)*y1", "undefined"),
    ("y1 + 1/0.0", "division by zero"),
    ("y1 + \u0443", "non-ASCII character"),  # Cyrillic u, looks like y
    ("y\u2081 + y2", "non-ASCII character"),  # subscript one
    ("y1\u00a0+ y2", "non-ASCII character"),  # no-break space
    ("y1 # + y2", "comments are not allowed"),
    ("y1 +", "syntax error"),
    ("", "empty expression"),
    ("True", "unsupported literal"),
    ("3j + y1", "unsupported literal"),
]


@pytest.mark.parametrize(("expr", "message"), WRONG_MATH)
def test_wrong_math(
    expr: str, message: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    _run(tmp_path, capsys, _spec(tmp_path, _f0(expr)), EXIT_BAD_SPEC, "objective.f0", message)


NAMES = [
    (
        'states = ["x1", "x2", "theta"]',
        'states = ["x1", "x2", "def"]',
        "system.states[2]",
        "Python keyword",
    ),
    (
        'states = ["x1", "x2", "theta"]',
        'states = ["x1", "x2", "while"]',
        "system.states[2]",
        "Python keyword",
    ),
    (
        'states = ["x1", "x2", "theta"]',
        'states = ["x1", "x2", "volatile"]',
        "system.states[2]",
        "C keyword",
    ),
    ('inputs = ["v", "omega"]', 'inputs = ["v", "printf"]', "system.inputs[1]", "C library"),
    ('inputs = ["v", "omega"]', 'inputs = ["v", "exp"]', "system.inputs[1]", "built-in function"),
    ('inputs = ["v", "omega"]', 'inputs = ["v", "_omega"]', "system.inputs[1]", "underscore"),
    ('inputs = ["v", "omega"]', 'inputs = ["v", "t"]', "system.inputs[1]", "reserved"),
    ('inputs = ["v", "omega"]', 'inputs = ["v", "om\u00e9ga"]', "system.inputs[1]", "not ASCII"),
    (
        'inputs = ["v", "omega"]',
        'inputs = ["v", "../omega"]',
        "system.inputs[1]",
        "not an identifier",
    ),
    ("a = 10.0", "x1 = 10.0", "parameters.x1", "already declared"),
    ("a = 10.0", "X1 = 10.0", "parameters.X1", "ignoring case"),
    ('S = "0.5', 'theta = "0.5', "signals.theta", "already declared"),
    ('name = "unicycle_switch"', 'name = "json"', "name", "standard module"),
    ('name = "unicycle_switch"', 'name = "numpy"', "name", "installed package"),
    ('name = "unicycle_switch"', 'name = "con"', "name", "reserved device name"),
    ('name = "unicycle_switch"', 'name = "../../etc/passwd"', "name", "not an identifier"),
    ('name = "unicycle_switch"', 'name = "Unicycle"', "name", "lower case"),
]


@pytest.mark.parametrize(("old", "new", "field", "message"), NAMES)
def test_names(
    old: str, new: str, field: str, message: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    assert old in UNICYCLE
    _run(
        tmp_path,
        capsys,
        _spec(tmp_path, UNICYCLE.replace(old, new, 1)),
        EXIT_BAD_SPEC,
        field,
        message,
    )


FILE_FORMAT = [
    (b'name = "x"\n[system\n', "(file)", "TOML syntax error"),
    (b'name = "a"\nname = "b"\n', "(file)", "TOML syntax error"),
    (b"", "name", "missing required key"),
    (b"\x00\x01binary\x02", "(file)", "binary file"),
    ("name = 'x'".encode("utf-16"), "(file)", "not UTF-8"),
    (b"description = no\n", "(file)", "TOML syntax error"),
    (
        UNICYCLE.replace('states = ["x1", "x2", "theta"]', 'states = "x1"').encode(),
        "system.states",
        "expected a non-empty list of names",
    ),
    (
        UNICYCLE.replace("t_final = 20.0", 't_final = "20"').encode(),
        "simulation.t_final",
        "expected a number",
    ),
    (
        UNICYCLE.replace("poles = [-1.0, -1.5]", 'poles = "fast"').encode(),
        "error_dynamics.poles",
        "expected a non-empty list",
    ),
    (UNICYCLE.replace("[objective]", "[objectve]").encode(), "objectve", "unknown key"),
    (UNICYCLE.replace("b = 1.5", "b = true").encode(), "parameters.b", "expected a number"),
]


@pytest.mark.parametrize(("content", "field", "message"), FILE_FORMAT)
def test_file_format(
    content: bytes, field: str, message: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    spec = tmp_path / "spec.toml"
    spec.write_bytes(content)
    _run(tmp_path, capsys, spec, EXIT_BAD_SPEC, field, message)


def test_yaml_is_refused_with_a_reason(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    spec = tmp_path / "robot.yaml"
    spec.write_text("name: robot\nenabled: no\ntolerance: 1e-3\n")
    _run(tmp_path, capsys, spec, EXIT_BAD_SPEC, "(file)", "YAML specs are not supported")


RAW_UNICYCLE = UNICYCLE.replace("integrate = { v = 1 }", "").replace(", v = 1.0 }", " }")
CONTROL = [
    (UNICYCLE.replace('y2 = "x2"', 'y2 = "b"'), "system.outputs.y2", "no relative degree"),
    (RAW_UNICYCLE, "extension", "integrate = { v = 1 }"),
    # Hidden zero: the omega column of G vanishes identically, which only sampling sees.
    (
        UNICYCLE.replace('theta = "omega"', 'theta = "omega*(sin(theta)**2 + cos(theta)**2 - 1)"'),
        "extension",
        "singular everywhere",
    ),
    (_f0("-y1**2 + y2**2"), "objective.f0", "not strongly convex"),
    (
        UNICYCLE.replace("poles = [-1.0, -1.5]", "poles = [-1.0, 0.5]"),
        "error_dynamics.poles",
        "not Hurwitz",
    ),
    (
        UNICYCLE.replace('y2 = "x2"', 'y2 = "x2"\ny3 = "theta"'),
        "system.outputs",
        "2 inputs but 3 outputs",
    ),
]


def test_a_wrong_pole_count_is_the_spec_s_error(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    text = UNICYCLE.replace("poles = [-1.0, -1.5]", "poles = [-1.0]")
    spec = _spec(tmp_path, text)
    _run(tmp_path, capsys, spec, EXIT_BAD_SPEC, "error_dynamics.poles", "give 2 poles, not 1")


@pytest.mark.parametrize(("text", "field", "message"), CONTROL)
def test_control_theoretic_rejections(
    text: str, field: str, message: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    _run(tmp_path, capsys, _spec(tmp_path, text), EXIT_ASSUMPTION, field, message)


@pytest.mark.parametrize("command", ["generate", "check", "simulate", "report"])
def test_every_command_rejects_the_same_way(
    command: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    spec = _spec(tmp_path, _f0("y1 + __import__('os')"))
    _run(tmp_path, capsys, spec, EXIT_BAD_SPEC, "objective.f0", "cannot call", command=command)


def test_text_reaching_generated_files_is_escaped(tmp_path: Path) -> None:
    """A description and a file name full of comment, string and trigraph breakers."""
    import ast
    import shutil
    import subprocess

    nasty = 'End """ here \\ */ /* ??/ ??= \\n <script>alert(1)</script> # x'
    text = UNICYCLE.replace(
        UNICYCLE[UNICYCLE.index('description = """') : UNICYCLE.index('"""\n\n[system]') + 3],
        "description = '''" + nasty + "'''",
    )
    # The path itself holds "*/" and "??/" (a folder ending in "*", another in "??").
    folder = tmp_path / "odd*" / "x??"
    folder.mkdir(parents=True)
    spec = folder / "we??= ird name.toml"
    assert "*/" in str(spec) and "??/" in str(spec)
    spec.write_text(text)
    out = tmp_path / "out"
    assert main(["generate", str(spec), "--out", str(out), "--quiet"]) == 0
    assert main(["generate", str(spec), "--backend", "c", "--out", str(out / "c"), "--quiet"]) == 0
    assert main(["report", str(spec), "--out", str(out / "r")]) == 0

    module = ast.parse((out / "unicycle_switch.py").read_text())
    docstring = ast.get_docstring(module)
    assert docstring is not None and nasty in docstring
    top = {n.name for n in module.body if isinstance(n, ast.FunctionDef | ast.ClassDef)}
    assert {
        "control",
        "rhs",
        "optimality_error",
        "objective",
        "gradient",
        "hessian",
        "ControllerError",
    } <= top
    assigned = {
        t.id
        for n in module.body
        if isinstance(n, ast.Assign)
        for t in n.targets
        if isinstance(t, ast.Name)
    }
    assert {"STATE_NAMES", "PARAMETERS", "K", "HURWITZ_COEFFICIENTS"} <= assigned
    assert not any(
        isinstance(n, ast.Expr) and not isinstance(n.value, ast.Constant) for n in module.body
    )  # no statement smuggled in

    if shutil.which("gcc"):
        for name in ("unicycle_switch.c", "unicycle_switch.h"):
            assert "??" not in (out / "c" / name).read_text().split("*/")[0]
        done = subprocess.run(
            [
                "gcc",
                "-std=c99",
                "-Wall",
                "-Wextra",
                "-Werror",
                "-pedantic",
                "-Wtrigraphs",
                "-c",
                str(out / "c" / "unicycle_switch.c"),
                "-o",
                str(tmp_path / "x.o"),
            ],
            capture_output=True,
            text=True,
            check=False,
        )
        assert done.returncode == 0, done.stderr
    html = (out / "r" / "unicycle_switch_report.html").read_text()
    assert "<script>" not in html and "&lt;script&gt;" in html


def test_memory_stays_bounded_on_an_exploding_spec(tmp_path: Path) -> None:
    """Under a 2 GiB address-space limit the budget, not the allocator, stops the run."""
    import resource
    import subprocess
    import sys

    nested = "sin(" * 58 + "x1/10" + ")" * 58
    spec = _spec(tmp_path, UNICYCLE.replace('y1 = "x1"', f'y1 = "{nested}"'))
    limit = 2 * 1024**3

    def cap() -> None:
        resource.setrlimit(resource.RLIMIT_AS, (limit, limit))

    start = time.perf_counter()
    done = subprocess.run(
        [sys.executable, "-m", "tvopt_codegen", "check", str(spec)],
        capture_output=True,
        text=True,
        preexec_fn=cap,
        timeout=60,
        check=False,
    )
    assert done.returncode == EXIT_BUDGET, done.stderr
    assert done.stderr.count("\n") == 1 and "MemoryError" not in done.stderr
    assert time.perf_counter() - start < 10.0


def test_objective_undefined_near_the_start(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """exp(exp(exp(-y1))) overflows near y1 = -5: no convexity can be claimed."""
    f0 = "exp(exp(exp(-y1))) + (y1 - o1x)**2 + (y2 - o1y)**2"
    _run(
        tmp_path,
        capsys,
        _spec(tmp_path, _f0(f0)),
        EXIT_ASSUMPTION,
        "objective.f0",
        "not finite at any of 24 points",
    )


def test_deeply_nested_signal_is_differentiated_without_swell(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A signal nested 55 deep: as a program its k-th derivative is linear in its size."""
    nested = "0.5 + 0.1*" + "sin(" * 55 + "t/10" + ")" * 55
    old = 'S = "0.5 - 0.5*tanh((t - a)/b)"'
    start = time.perf_counter()
    assert main(["check", str(_spec(tmp_path, UNICYCLE.replace(old, f'S = "{nested}"')))]) == 0
    assert time.perf_counter() - start < 10.0
    assert "strongly convex" in capsys.readouterr().out


RING = (ROOT / "tvopt_codegen" / "examples" / "unicycle_ring.toml").read_text()
TOWER = "exp(exp(exp(exp(exp(exp(exp(exp(i))))))))"


@pytest.mark.slow  # its 3 s budget (tests/durations.json knows its cases by their old ids)
def test_bombs_answer_within_the_budget(tmp_path: Path) -> None:
    # 256 agents: minutes of derivation, stopped at the budget. A process of its own: the
    # budget's real-time timer and the swollen derivation are the process's.
    spec = _spec(tmp_path, RING.replace("i = 4 ", "i = 256 "))
    start = time.perf_counter()
    done = subprocess.run(
        [sys.executable, "-m", "tvopt_codegen", "check", str(spec), "--max-seconds", "3"],
        capture_output=True,
        text=True,
        check=False,
    )
    elapsed = time.perf_counter() - start
    assert done.returncode == 6, done.stderr
    assert done.stderr.count("\n") == 1 and "took longer than 3 s" in done.stderr
    assert elapsed < 3 + 6  # the budget, plus start-up: within a few seconds


@pytest.mark.parametrize(
    ("text", "message"),
    [
        (
            RING.replace('"theta[i]" = 0.0', f'"theta[i]" = "{TOWER}"'),
            "simulation.initial_state.theta[i]: 'exp(exp(",
        ),
        (
            RING.replace("alpha = 1e-3", f'"w[i]" = "{TOWER}"\nalpha = 1e-3'),
            "parameters.w[i]: 'exp(exp(",
        ),
    ],
)
def test_towers_in_indexed_constants_are_refused_in_doubles_at_once(
    tmp_path: Path, text: str, message: str
) -> None:
    # Exponential towers in indexed constants: refused in doubles, not evaluated exactly.
    # In this process (what the command says and its code; a cold interpreter each was
    # most of these cases' cost).
    spec = _spec(tmp_path, text)
    start = time.perf_counter()
    done = run_main("check", str(spec))
    elapsed = time.perf_counter() - start
    assert done.returncode == EXIT_BAD_SPEC, done.stderr
    assert done.stderr.count("\n") == 1 and message in done.stderr
    assert elapsed < 6  # at once, not after an exact evaluation


def test_a_module_name_is_refused_where_installed_not_where_generated(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    # A module generated earlier into the working folder, which python -m puts on
    # sys.path, does not make its name "installed": regenerating it must work.
    work = tmp_path / "work"
    work.mkdir()
    (work / "my_robot.py").write_text("X = 1\n")
    monkeypatch.chdir(work)
    monkeypatch.syspath_prepend(str(work))
    assert module_name_problem("my_robot") is None
    # The same name in a folder of installed code is refused, like numpy is.
    site = tmp_path / "site"
    (site / "my_robot").mkdir(parents=True)
    (site / "my_robot" / "__init__.py").write_text("")
    monkeypatch.syspath_prepend(str(site))
    assert module_name_problem("my_robot") == (
        "module name 'my_robot' shadows the installed package of that name"
    )
