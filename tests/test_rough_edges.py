"""The rough edges a new user hits: usage errors, pipes, budgets, long specs, long names."""

from __future__ import annotations

import os
import subprocess
import sys
import time
from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np
import pytest
import sympy as sp

from tvopt_codegen import symbolic as sx
from tvopt_codegen.derivation.singularity import _singular_set, undefined_causes
from tvopt_codegen.errors import clip_quotes
from tvopt_codegen.limits import ENGINE_VARIABLE, MAX_POINTS

from .conftest import ROOT, Ran, module, run_main, write_spec

INTEGRATOR = (ROOT / "tvopt_codegen" / "examples" / "integrator.toml").read_text()


def _process(*args: str, engine: str) -> subprocess.CompletedProcess[str]:
    """The command in a process of its own on ``engine``: for what a process does (budgets).

    The process's engine is its environment's: the test's engine marker switches only
    the test's own process.
    """
    return subprocess.run(
        [sys.executable, "-m", "tvopt_codegen", *args],
        check=False,
        capture_output=True,
        text=True,
        env={**os.environ, ENGINE_VARIABLE: engine},
    )


def _cli(*args: str) -> Ran:
    """The command in this process (what it writes and says)."""
    return run_main(*args)


def _with_objective(tmp_path: Path, f0: str) -> Path:
    lines = [
        f'f0 = "{f0}"' if line.startswith("f0 = ") else line for line in INTEGRATOR.splitlines()
    ]
    return write_spec(tmp_path, "\n".join(lines) + "\n")


def test_usage_errors_are_one_line_with_a_pointer_to_help() -> None:
    for args, text in (
        (("simulate",), "the following arguments are required: spec"),
        (("generate", "integrator", "--backend", "fortran"), "invalid choice: 'fortran'"),
        (("frobnicate",), "invalid choice: 'frobnicate'"),
    ):
        done = _cli(*args)
        assert done.returncode == 2
        assert done.stderr.count("\n") == 1, done.stderr
        assert text in done.stderr and "(see tvopt-codegen" in done.stderr
        assert "--help)" in done.stderr


def test_a_closed_pipe_ends_quietly_like_a_unix_tool() -> None:
    read, write = os.pipe()
    os.close(read)
    try:
        done = subprocess.run(
            [sys.executable, "-m", "tvopt_codegen", "check", "unicycle_switch"],
            stdout=write,
            stderr=subprocess.PIPE,
            text=True,
            check=False,
        )
    finally:
        os.close(write)
    assert done.returncode == 141
    assert done.stderr == ""


def _chain_spec(tmp_path: Path, order: int) -> Path:
    """One output through a chain of ``order`` integrators, f0 not quadratic: k = order.

    The gradient jet holds ``order`` total time derivatives of ``grad f0``, each
    ``log(cosh)`` term's more terms than the last: tens of seconds of SymEngine's work in
    small calls for order 40 (about 25 s of CPU here, two thirds of it in the gradient
    jet), while every expression stays inside the size budget. f0 is strongly
    convex in y: the derivation is refused for its time alone.
    """
    states = [f"x{i}" for i in range(order)]
    dynamics = [f'{s} = "{n}"' for s, n in zip(states, [*states[1:], "u"], strict=True)]
    poles = ", ".join(f"-{1 + i / 10:g}" for i in range(order))
    text = "\n".join(
        [
            'name = "long_chain"',
            "[system]",
            f"states = {states!r}".replace("'", '"'),
            'inputs = ["u"]',
            "[system.dynamics]",
            *dynamics,
            "[system.outputs]",
            'y = "x0"',
            "[signals]",
            'r = "0.5*sin(t) + 0.2*cos(0.3*t)"',
            "[objective]",
            'f0 = "(y - r)**2 + log(cosh(y - r))"',
            "[error_dynamics]",
            f"poles = [{poles}]",
            "[simulation]",
            "initial_state = { " + ", ".join(f"{s} = 0.1" for s in states) + " }",
        ]
    )
    return write_spec(tmp_path, text + "\n")


def _product_spec(tmp_path: Path) -> Path:
    """A product of 50 sums in f0: minutes of one SymPy call between two budget checks.

    SymEngine derives it in a moment (and refuses f0, not convex at 1e45 times the scale).
    """
    product = "*".join(f"(y1 + {k}*y2 + {k})" for k in range(1, 51))
    return _with_objective(tmp_path, f"0.5*(y1 - o1)**2 + 0.5*(y2 - o2)**2 + 1e-30*{product}")


@pytest.mark.parametrize(
    ("engine", "swelling"),
    [
        # The default core: many short SymEngine calls, the budget checked between them
        # (a timer's signal ends a C++ call only when it returns).
        ("symengine", lambda path: _chain_spec(path, 40)),
        # The reference engine: the timer's signal ends one long SymPy call.
        ("sympy", _product_spec),
    ],
    ids=["symengine-long-chain", "sympy-product"],
)
def test_the_time_budget_ends_a_swelling_derivation_in_a_named_stage(
    tmp_path: Path, engine: str, swelling: Callable[[Path], Path]
) -> None:
    spec = swelling(tmp_path)
    start = time.perf_counter()
    # A budget of 1 s: 0.5, 1 and 2 s end both in the same stage (the gradient jet on
    # SymEngine, the objective on SymPy), each second more only CPU spent swelling.
    done = _process("check", str(spec), "--max-seconds", "1", engine=engine)
    elapsed = time.perf_counter() - start
    assert done.returncode == 6, done.stderr
    assert "derivation stage '" in done.stderr and "took longer than 1 s" in done.stderr
    assert done.stderr.count("\n") == 1
    assert elapsed < 1 + 6  # the budget, plus start-up, within a few seconds


def test_a_long_flat_objective_is_not_deep(tmp_path: Path) -> None:
    # 400 terms written out by a program: a sum is not nesting.
    terms = " + ".join(f"{k}e-4*(y1 - o1)**2 + {k}e-4*w*(y2 - o2)**2" for k in range(1, 201))
    spec = _with_objective(tmp_path, terms)
    done = _cli("check", str(spec))
    assert done.returncode == 0, done.stderr
    done = _cli("generate", str(spec), "--out", str(tmp_path / "out"), "--quiet")
    assert done.returncode == 0, done.stderr


def test_long_names_are_quoted_short(tmp_path: Path) -> None:
    name = "x" * 10_000
    spec = _with_objective(tmp_path, f"(y1 - {name})**2 + y2**2")
    done = _cli("check", str(spec))
    assert done.returncode == 2
    assert len(done.stderr) < 300, done.stderr
    assert f"unknown name '{'x' * 57}...'" in done.stderr
    assert clip_quotes("a 'short' name") == "a 'short' name"


def test_zero_columns_give_empty_results_in_the_numpy_backend() -> None:
    mod = module("unicycle_switch")
    n, m = len(mod.STATE_NAMES), len(mod.OUTPUT_NAMES)
    empty = np.zeros((n, 0))
    assert mod.control(0.5, empty).shape == (len(mod.INPUT_NAMES), 0)
    assert mod.rhs(0.5, empty).shape == (n, 0)
    assert mod.optimality_error(0.5, empty).shape == (mod.K, m, 0)
    assert mod.objective(0.5, np.zeros((m, 0))).shape == (0,)
    assert mod.gradient(0.5, np.zeros((m, 0))).shape == (m, 0)
    assert mod.hessian(0.5, np.zeros((m, 0))).shape == (m, m, 0)


def test_bad_simulation_numbers_are_refused_at_once(tmp_path: Path) -> None:
    out = tmp_path / "run"
    for args, text in (
        (("--t-final", "inf"), "--t-final: must be positive and at most 1e+06"),
        (("--t-final", "1e300"), "--t-final: must be positive and at most 1e+06"),
        (("--points", "300000000"), f"--points: must be between 3 and {MAX_POINTS}"),
        (("--rtol", "inf"), "--rtol: must be positive and finite"),
    ):
        start = time.perf_counter()
        done = _cli("simulate", "integrator", "--out", str(out), *args)
        assert done.returncode == 2 and text in done.stderr, done.stderr
        assert done.stderr.count("\n") == 1
        assert time.perf_counter() - start < 10 and not out.exists()
    for value, text in (
        ("inf", "expected a finite number"),
        ("1e300", "must be positive and at most 1e+06"),
    ):
        spec = write_spec(tmp_path, INTEGRATOR.replace("t_final = 10.0", f"t_final = {value}"))
        done = _cli("simulate", str(spec), "--out", str(out))
        assert done.returncode == 2 and f"simulation.t_final: {text}" in done.stderr
    # A parameter that divides by zero: one line, not an internal error.
    spec = write_spec(
        tmp_path,
        INTEGRATOR.replace("w = 2.0", "w = 0.0").replace(
            "0.5*w*(y2 - o2)**2", "0.5*(y2 - o2)**2/w"
        ),
    )
    done = _cli("simulate", str(spec), "--out", str(out))
    assert done.returncode == 3 and done.stderr.count("\n") == 1
    assert "does a parameter divide by zero?" in done.stderr
    done = _cli("simulate", "integrator", "--param", "w=0", "--out", str(out))
    assert done.returncode == 3 and done.stderr.count("\n") == 1
    assert "(x1 = -1, x2 = 1.5; parameters w = 0)" in done.stderr
    assert not out.exists()


def test_a_name_of_the_wrong_kind_is_said_to_be_not_allowed(tmp_path: Path) -> None:
    cases = [
        (
            INTEGRATOR.replace('y1 = "x1"', 'y1 = "x1 + u1"'),
            "system.outputs.y1: column 6: input 'u1' may not appear here: outputs are functions "
            "of the states and parameters (y = h(x))",
        ),
        (
            INTEGRATOR.replace('o1 = "2 + 0.8*t', 'o1 = "x1 + 2 + 0.8*t'),
            "signals.o1: column 1: state 'x1' may not appear here: signals are functions of t, "
            "parameters, references and other signals",
        ),
        (
            INTEGRATOR.replace('f0 = "0.5*', 'f0 = "u2 + 0.5*'),
            "objective.f0: column 1: input 'u2' may not appear here: f0 is a function of the "
            "outputs, signals, references, parameters and t",
        ),
    ]
    for text, message in cases:
        done = _cli("check", str(write_spec(tmp_path, text)))
        assert done.returncode == 2 and message in done.stderr, done.stderr
    # A name declared nowhere is still just unknown.
    done = _cli("check", str(write_spec(tmp_path, INTEGRATOR.replace('y1 = "x1"', 'y1 = "q"'))))
    assert "column 1: unknown name 'q'" in done.stderr


def _imported_by(*args: str, then: Sequence[Sequence[str]] = ()) -> set[str]:
    """The modules a command loads, on the default engine (SymEngine): with ``then``,
    those it and the commands ``then`` run after it in the same process load together.

    Every command must succeed (exit 0, or ``SystemExit(0)`` for ``--help``): one that
    stopped early would load less than it does.
    """
    code = "import sys\nfrom tvopt_codegen.cli import main\ncodes = []\n"
    for command in (list(args), *map(list, then)):
        code += f"try:\n    codes.append(main({command!r}))\n"
        code += "except SystemExit as stop:\n    codes.append(stop.code)\n"
    code += "print(codes)\nprint(' '.join(sorted(sys.modules)))"
    done = subprocess.run(
        [sys.executable, "-c", code],
        check=True,
        capture_output=True,
        text=True,
        env={**os.environ, ENGINE_VARIABLE: "symengine"},
    )
    *_, codes, modules = done.stdout.strip().splitlines()  # the last two lines
    assert codes == str([0] * (1 + len(then))), (codes, done.stderr)
    return set(modules.split())


def test_help_and_version_load_none_of_the_heavy_libraries() -> None:
    # One process for the three: what none of them loaded, together, each did not load.
    loaded = _imported_by("--version", then=[["--help"], ["simulate", "--help"]])
    assert not {"sympy", "numpy", "scipy", "jinja2", "matplotlib"} & loaded


def test_generate_check_and_report_load_no_matplotlib_or_integrator(tmp_path: Path) -> None:
    # SymPy only where a command crosses the border (issue 49): not unicycle_switch's
    # det R, v cos^2 + v sin^2, which SymEngine reduces and whose singular set it finds
    # itself, nor a controller that needs none of SymPy, nor the report, which prints its
    # LaTeX and MathML itself. One process for the five commands (a cold interpreter each
    # was four more seconds of start-up): what none of them loaded, together, each did
    # not load; the first derives, so SymEngine is loaded by then.
    loaded = _imported_by(
        "check",
        "unicycle_switch",
        then=[
            ["generate", "integrator", "--out", str(tmp_path / "g"), "--quiet"],
            ["report", "integrator", "--out", str(tmp_path / "r")],
            # A controller needs no scipy at all (a fifth of a small command to import),
            # a team's with its fill-reducing order neither.
            ["generate", "unicycle_ring", "--out", str(tmp_path / "ring"), "--quiet"],
            # Nor SLSQP's search, where the constraints hold at the start already.
            ["check", "two_unicycles_corridor"],
        ],
    )
    assert "symengine" in loaded and "sympy" not in loaded
    assert not {"matplotlib", "scipy", "scipy.integrate", "scipy.optimize"} & loaded


def test_figures_leave_the_users_matplotlib_backend_alone(tmp_path: Path) -> None:
    code = (
        "import matplotlib; matplotlib.use('svg')\n"
        "from tvopt_codegen.cli import main\n"
        f"main(['simulate', 'integrator', '--out', {str(tmp_path / 'run')!r}, '--points', '21'])\n"
        "import sys; print(matplotlib.get_backend(), 'matplotlib.pyplot' in sys.modules)"
    )
    done = subprocess.run([sys.executable, "-c", code], check=True, capture_output=True, text=True)
    assert done.stdout.split()[-2:] == ["svg", "False"]
    assert (tmp_path / "run" / "integrator_convergence.png").read_bytes()[:4] == b"\x89PNG"


EMPTY_SETS = """name = "empty_sets"

[system]
states = ["x", "y", "vx", "vy"]
inputs = ["ax", "ay"]

[system.dynamics]
x = "vx"
y = "vy"
vx = "ax/sqrt(vx**2 + vy**2 + 1) + sqrt(x) + log(1 + x**2) + 1/(x - 3)"
vy = "ay*(vx**2 - vx*vy + vy**2 + 1) + tan(y)"

[system.outputs]
px = "x"
py = "y"

[signals]
ox = "1 + 0.1*sin(t)"
oy = "0.2*cos(t)"

[objective]
f0 = "(px - ox)**2 + (py - oy)**2"

[error_dynamics]
poles = [-1.0, -2.0]

[simulation]
initial_state = { x = 1.0, y = 0.0, vx = 0.0, vy = 0.0 }
"""


def test_check_lists_only_sets_that_hold_somewhere_with_their_cause(tmp_path: Path) -> None:
    # R's gains vx**2 + vy**2 + 1 and the definite quadratic vx**2 - vx*vy + vy**2 + 1 vanish
    # nowhere, log(1 + x**2) is defined everywhere: check once said "singular where
    # vx**2 + vy**2 + 1 = 0" and "undefined where vx**2 + vy**2 + 1 = 0".
    done = _cli("check", str(write_spec(tmp_path, EMPTY_SETS)))
    assert done.returncode == 0, done.stderr
    # det R in lowest terms, up to the order of its terms (each engine writes its own).
    det = next(line for line in done.stdout.splitlines() if line.startswith("  det R = "))
    assert det.endswith("; never singular"), det
    written = det.removeprefix("  det R = ").removesuffix("; never singular")
    assert sp.sympify(written) == sp.sympify(
        "(vx**2 - vx*vy + vy**2 + 1)/sqrt(vx**2 + vy**2 + 1)"
    ), det
    undefined = next(line for line in done.stdout.splitlines() if "undefined where" in line)
    assert undefined == (
        "  R or p undefined where cos(y) = 0 (the cosine under tan vanishes); "
        "x < 0 (a square root of a negative); x - 3 = 0 (a denominator vanishes)"
    )
    # The law line defines each of its letters, and none is the decay rate's alpha.
    law = next(line for line in done.stdout.splitlines() if line.startswith("  law: "))
    assert law == (
        "  law: u = R^-1 (v - p): R the decoupling matrix, p the drift of the outputs' "
        "highest derivatives (their value at zero input), v = y_imp^(2), the implicit "
        "trajectory's 2nd derivative (uniform relative degree theorem)"
    )
    assert "decay rate alpha = 1" in done.stdout


def test_an_extended_plants_law_line_names_the_extended_inputs() -> None:
    done = _cli("check", str(ROOT / "tests" / "specs" / "robust_pvtol.toml"))
    assert done.returncode == 0, done.stderr
    law = next(line for line in done.stdout.splitlines() if line.startswith("  law: "))
    assert law.startswith("  law: w = R^-1 (v - p): R the decoupling matrix")
    assert "v = y_imp^(4), the implicit trajectory's 4th derivative" in law
    assert "w = (thrust_d2, torque), the extended plant's inputs" in law
    assert "alpha" not in law and "beta" not in law


def test_the_sign_tests_behind_the_sets() -> None:
    x, y = sx.symbol("x"), sx.symbol("y")
    assert _singular_set(x**2 + y**2 + 1) == ()
    assert _singular_set((x**2 - x * y + y**2 + 1) * (x - 1)) == ("x - 1 = 0",)
    # (x - 1)**2 vanishes at x = 1; x**2 - 3*x*y + y**2 + 1 is indefinite.
    assert _singular_set(x**2 - 2 * x + 1) == ("x - 1 = 0",)
    assert _singular_set(x**2 - 3 * x * y + y**2 + 1) == ("x**2 - 3*x*y + y**2 + 1 = 0",)
    assert _singular_set(-(x**2) - 4) == ()
    # Monomials in symbols, sines and cosines (found without SymPy on SymEngine): one
    # condition per atom of the numerator, in SymPy's order of factors.
    assert _singular_set(3 * x**2 * sx.cos(y) / y) == ("cos(y) = 0", "x = 0")
    assert _singular_set(-2 * y * sx.sin(x) ** 2 * x**3) == ("y = 0", "sin(x) = 0", "x = 0")
    causes = undefined_causes(
        [
            1 / sx.sqrt(x**2 + 1),
            sx.log(x**2 + 1),
            sx.sqrt((x - 1) ** 2),
            1 / sx.sqrt(y),
            sx.log(x),
            1 / sx.cos(sx.atan(x)),
            sx.cot(y),
        ],
        {x, y},
    )
    assert dict(causes) == {
        "y = 0": "a denominator vanishes",
        "y < 0": "a square root of a negative",
        "x <= 0": "a log of a non-positive",
        "sin(y) = 0": "the sine under cot vanishes",
    }


def test_a_padded_plants_law_line_defines_v_by_the_padding_chains() -> None:
    done = _cli("check", str(ROOT / "tests" / "specs" / "nonuniform.toml"))
    assert done.returncode == 0, done.stderr
    law = next(line for line in done.stdout.splitlines() if line.startswith("  law: "))
    assert "v = the padding chains' output, driven by y_imp^(2)" in law
    assert law.endswith("(non-uniform theorem)")
    assert not {"alpha", "beta", "xi"} & set(law.replace(",", " ").replace("(", " ").split())
