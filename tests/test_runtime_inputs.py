"""What the generated modules accept at run time, and the writer's and reader's bounds.

Every unusual array a user may pass is either read correctly (the same numbers as its
native copy, to the bit) or refused with a clear error; never misread.
"""

from __future__ import annotations

import os
import re
import resource
import subprocess
import sys
import time
import warnings
from pathlib import Path
from types import ModuleType

import numpy as np
import pytest
import sympy as sp

from tvopt_codegen.derivation import derive
from tvopt_codegen.emit import write_files
from tvopt_codegen.errors import BudgetError, OutputError, SpecError
from tvopt_codegen.limits import Budget
from tvopt_codegen.lowering.ir import lower
from tvopt_codegen.renderer.rendering import render
from tvopt_codegen.runs.summary import format_summary
from tvopt_codegen.spec import load_spec, parse_spec

from .conftest import EXAMPLES, ROOT, derivation, module, run_main, write_spec
from .test_c_backend import c_module
from .test_generated import random_states

STATE_FUNCTIONS = ("control", "rhs", "optimality_error")
OUTPUT_FUNCTIONS = ("objective", "gradient", "hessian")


def _misaligned(array: np.ndarray) -> np.ndarray:
    """A copy of ``array`` whose data starts one byte past an aligned address."""
    buffer = np.zeros(array.nbytes + 1, dtype=np.uint8)
    view = np.frombuffer(buffer.data, dtype=array.dtype, count=array.size, offset=1)
    view = view.reshape(array.shape)
    view[...] = array
    assert not view.flags.aligned
    return view


def _read_only(array: np.ndarray) -> np.ndarray:
    copy = array.copy()
    copy.setflags(write=False)
    return copy


def _layouts(values: np.ndarray) -> list[tuple[str, np.ndarray]]:
    """The same numbers in every layout a user may hand over (2-D and 1-D)."""
    return [
        ("big-endian", values.astype(">f8")),
        ("big-endian, one column", values[:, 2].astype(">f8")),
        ("little-endian explicit", values.astype("<f8")),
        ("Fortran order", np.asfortranarray(values)),
        ("strided columns", np.repeat(values, 2, axis=1)[:, ::2]),
        ("strided rows", np.repeat(values, 2, axis=0)[::2]),
        ("big-endian, strided", np.repeat(values, 2, axis=1).astype(">f8")[:, ::2]),
        ("read-only", _read_only(values)),
        ("misaligned", _misaligned(values)),
        ("misaligned, one column", _misaligned(values[:, 2])),
    ]


def _modules(spec: str, tmp_path_factory: pytest.TempPathFactory) -> list[ModuleType]:
    return [module(spec), c_module(spec, tmp_path_factory)]


@pytest.mark.parametrize("spec", EXAMPLES)
def test_every_layout_reads_the_same_numbers_in_both_backends(
    spec: str, tmp_path_factory: pytest.TempPathFactory
) -> None:
    states = random_states(spec, 6, seed=11)
    m = len(derivation(spec).spec.outputs)
    for mod in _modules(spec, tmp_path_factory):
        for label, layout in _layouts(states):
            native = np.array(layout, dtype=float, order="C")
            assert native.dtype.byteorder in "=|<"
            for name in STATE_FUNCTIONS:
                got = getattr(mod, name)(0.8, layout)
                want = getattr(mod, name)(0.8, native)
                assert np.array_equal(got, want), f"{mod.BACKEND}: {name}, {label}"
            y = layout[:m]
            for name in OUTPUT_FUNCTIONS:
                got = getattr(mod, name)(0.8, y)
                want = getattr(mod, name)(0.8, np.array(y, dtype=float))
                assert np.array_equal(got, want), f"{mod.BACKEND}: {name}, {label}"


@pytest.mark.parametrize("spec", ["integrator", "unicycle_switch"])
def test_complex_input_is_refused_naming_the_argument(
    spec: str, tmp_path_factory: pytest.TempPathFactory
) -> None:
    states = random_states(spec, 3)
    m = len(derivation(spec).spec.outputs)
    for mod in _modules(spec, tmp_path_factory):
        for value in (states.astype(complex), states[:, 0].astype(np.complex64)):
            with pytest.raises(TypeError, match="s must be real, got complex values"):
                mod.control(0.5, value)
            with pytest.raises(TypeError, match="s must be real"):
                mod.rhs(0.5, value)
        objects = np.array([complex(v) for v in states[:, 0]], dtype=object)
        with pytest.raises(TypeError, match="s must be real"):
            mod.control(0.5, objects)
        with pytest.raises(TypeError, match="y must be real"):
            mod.gradient(0.5, states[:m].astype(complex))
        name = next(iter(mod.PARAMETERS), None)
        if name is not None:
            for bad in (1 + 0j, np.complex128(2.0)):
                with pytest.raises(TypeError, match=f"parameter '{name}' must be real"):
                    mod.control(0.5, states[:, 0], {name: bad})
        with pytest.raises(TypeError, match="t must be a real number"):
            mod.control(1 + 0j, states[:, 0])


@pytest.mark.parametrize("spec", EXAMPLES)
def test_huge_times_give_the_same_outcome_in_both_backends(
    spec: str, tmp_path_factory: pytest.TempPathFactory
) -> None:
    states = random_states(spec, 3)
    m = len(derivation(spec).spec.outputs)
    for t in (1e155, 1e200, -1e300):
        outcomes = []
        for mod in _modules(spec, tmp_path_factory):
            seen: list[tuple[object, ...]] = []
            for name, x in [(n, states) for n in STATE_FUNCTIONS] + [
                (n, states[:m]) for n in OUTPUT_FUNCTIONS
            ]:
                try:
                    getattr(mod, name)(t, x)
                    seen.append((name, "ok"))
                except mod.ControllerError as error:
                    assert f"not finite (column {error.index})" in str(error)
                    seen.append((name, type(error).__name__, error.index))
            outcomes.append(seen)
        assert outcomes[0] == outcomes[1], f"t = {t}"
    # The integrator's object moves like t**3: past 1e103 it is not finite at all.
    if spec == "integrator":
        for mod in _modules(spec, tmp_path_factory):
            with pytest.raises(mod.NonFiniteOutputError, match=r"\(column 0\)") as info:
                mod.control(1e200, states)
            assert info.value.index == 0


def _generate(spec: str, backend: str, out: Path) -> None:
    """``tvopt-codegen generate`` (in this process: the fresh interpreters are the users'
    of the generated files); it must succeed."""
    done = run_main("generate", spec, "--backend", backend, "--out", str(out), "--quiet")
    assert done.returncode == 0, done.stderr


def _tvopt(*args: str) -> subprocess.CompletedProcess[str]:
    """``tvopt-codegen ARGS`` in a fresh process."""
    return subprocess.run(
        [sys.executable, "-m", "tvopt_codegen", *args],
        check=False,
        capture_output=True,
        text=True,
    )


def _python(script: str, cwd: Path, env: dict[str, str]) -> subprocess.CompletedProcess[str]:
    """``script`` in a fresh interpreter, in ``cwd``, with exactly ``env``."""
    return subprocess.run(
        [sys.executable, "-c", script],
        cwd=cwd,
        env=env,
        check=False,
        capture_output=True,
        text=True,
    )


def _renamed(text: str, name: str) -> str:
    return text.replace('name = "unicycle_switch"', f'name = "{name}"', 1)


def test_a_spec_named_like_anothers_entry_point_does_not_clobber_it(
    tmp_path: Path, unicycle_text: str
) -> None:
    out = tmp_path / "out"
    for name in ("probe", "probe_ext"):
        spec = write_spec(tmp_path, _renamed(unicycle_text, name), f"{name}.toml")
        _generate(str(spec), "c", out)
    names = sorted(p.name for p in out.iterdir())
    assert names == sorted(
        f"{n}{ext}" for n in ("probe", "probe_ext") for ext in (".c", ".h", "_c.py", ".ext.c")
    )
    script = (
        "import probe_c as probe, probe_ext_c as probe_ext, numpy;"
        "s = numpy.array(probe.DEFAULT_STATE);"
        "assert probe._ENTRY is not None and probe_ext._ENTRY is not None;"
        "print((probe.control(0.5, s) == probe_ext.control(0.5, s)).all())"
    )
    done = _python(
        script, out, {"TVOPT_CODEGEN_CACHE": str(tmp_path / "cache"), "PATH": "/usr/bin:/bin"}
    )
    assert done.returncode == 0, done.stderr
    assert done.stdout.strip() == "True"


def test_the_writer_refuses_to_replace_another_specs_file(
    tmp_path: Path, unicycle_text: str
) -> None:
    texts = {}
    for name, text in (
        ("alpha", unicycle_text),
        ("beta", unicycle_text),
        ("alpha", unicycle_text.replace("Unicycle switching", "A unicycle switching", 1)),
    ):
        spec = load_spec(write_spec(tmp_path, _renamed(text, name), f"{name}.toml"))
        ((_, rendered),) = render(lower(derive(spec)), "python").items()
        texts[name if name not in texts else "alpha, edited"] = rendered
    assert texts["alpha, edited"] != texts["alpha"]
    out = tmp_path / "out"
    write_files({"shared.py": texts["alpha"]}, out)
    with pytest.raises(OutputError, match="generated for spec 'alpha', not for spec 'beta'"):
        write_files({"shared.py": texts["beta"]}, out)
    assert (out / "shared.py").read_text() == texts["alpha"]
    with pytest.raises(OutputError, match="generated for spec 'alpha', not for this run"):
        write_files({"shared.py": "plain text\n"}, out)
    # The same spec regenerated (edited since) replaces its own file; --force anything.
    write_files({"shared.py": texts["alpha, edited"]}, out)
    assert (out / "shared.py").read_text() == texts["alpha, edited"]
    write_files({"shared.py": texts["beta"]}, out, force=True)
    assert (out / "shared.py").read_text() == texts["beta"]


def _child_peak_mb() -> float:
    return resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024


def test_report_reads_no_huge_or_foreign_results_file(tmp_path: Path) -> None:
    out = tmp_path / "run"
    out.mkdir()
    huge = out / "integrator_certificate.txt"
    with huge.open("wb") as handle:  # sparse: 3 GB on paper, nothing on disk
        handle.truncate(3_000_000_000)
    done = _tvopt("report", "integrator", "--out", str(out), "--format", "md")
    assert done.returncode == 0, done.stderr
    assert _child_peak_mb() < 1000
    assert "simulation results" not in done.stdout
    assert huge.stat().st_size == 3_000_000_000  # left alone


def test_report_includes_only_results_simulate_wrote_unchanged(tmp_path: Path) -> None:
    out = tmp_path / "run"
    done = run_main("simulate", "integrator", "--out", str(out), "--points", "41")
    assert done.returncode == 0, done.stderr
    args = ["report", "integrator", "--out", str(out), "--format", "md", "--force"]
    done = run_main(*args)
    assert done.returncode == 0 and "with the simulation results" in done.stdout
    certificate = out / "integrator_certificate.txt"
    certificate.write_text(certificate.read_text().replace("PASSED", "PASSED (edited)"))
    for figure in out.glob("integrator_*.png"):
        figure.unlink()
    done = run_main(*args)
    assert done.returncode == 0 and "with the simulation results" not in done.stdout
    assert "(edited)" not in (out / "integrator_report.md").read_text()


@pytest.mark.parametrize(
    ("text", "problem"),
    [
        (".".join(["a"] * 30_000) + " = 1\n", "a key has more than 32 dotted parts"),
        ("[" + ".".join(["t"] * 40) + "]\n", "a key has more than 32 dotted parts"),
        ("x = " + "[" * 5000 + "]" * 5000 + "\n", "arrays and inline tables nest deeper"),
        ("x = " + "{a = " * 200 + "1" + "}" * 200 + "\n", "arrays and inline tables nest deeper"),
    ],
)
def test_deep_toml_is_a_bad_file_at_once(text: str, problem: str) -> None:
    start = time.perf_counter()
    with pytest.raises(SpecError, match=f"spec.toml: \\(file\\): line 1: {problem}"):
        parse_spec("spec.toml", text.encode())
    assert time.perf_counter() - start < 1.0


def test_deep_toml_costs_no_memory_on_the_command_line(tmp_path: Path) -> None:
    spec = write_spec(tmp_path, ".".join(["a"] * 30_000) + " = 1\n")
    done = subprocess.run(
        [sys.executable, "-m", "tvopt_codegen", "check", str(spec)],
        check=False,
        capture_output=True,
        text=True,
    )
    assert done.returncode == 2
    assert done.stderr.count("\n") == 1 and "dotted parts" in done.stderr
    assert _child_peak_mb() < 1000


def _big_det_spec(tmp_path: Path) -> Path:
    # Two inputs, two outputs, and R's entries long enough that det R has more than 400
    # nodes: not expanded for its size, not for m > 4.
    long = " + ".join(f"sin(x1 + {i})*cos(x2 - {i})" for i in range(1, 12))
    other = " + ".join(f"cos(x1 - {i})*sin(x2 + {i})" for i in range(1, 12))
    text = f"""
name = "bigdet"
[system]
states = ["x1", "x2"]
inputs = ["u1", "u2"]
[system.dynamics]
x1 = "(3 + 0.01*({long}))*u1 + 0.1*u2"
x2 = "0.1*u1 + (3 + 0.01*({other}))*u2"
[system.outputs]
y1 = "x1"
y2 = "x2"
[objective]
f0 = "0.5*(y1 - sin(t))**2 + 0.5*y2**2"
[error_dynamics]
poles = [-1.0]
[simulation]
t_final = 1.0
initial_state = {{ x1 = 0.1, x2 = 0.2 }}
"""
    return write_spec(tmp_path, text, "bigdet.toml")


def test_det_r_message_says_why_it_was_not_expanded(tmp_path: Path) -> None:
    d = derive(load_spec(_big_det_spec(tmp_path)))
    assert d.decoupling.det_R is None
    summary = format_summary(d, lower(d))
    assert "det R: not simplified symbolically (more than 400 expression nodes)" in summary
    assert "m > 4" not in summary
    ring = format_summary(derivation("unicycle_ring"), lower(derivation("unicycle_ring")))
    assert "det R: not expanded symbolically (m = " in ring


def test_a_slow_det_simplification_is_charged_to_its_own_stage(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    # The kinematic car's det R, v**2*(tan(phi)**2 + 1)/wheelbase written out in sines and
    # cosines of theta, is no monomial in symbols, sines and cosines (tan is none of
    # them): on either engine it crosses the border and trigsimp reduces it
    # (singularity.simplified_det, read at call time). That is the call made slow here.
    # (unicycle_switch's v cos^2 + v sin^2 no longer serves: SymEngine decides it
    # without SymPy, singularity._monomial.)
    real = sp.trigsimp
    calls: list[object] = []

    def slow(seconds: float) -> object:
        def trigsimp(expr: sp.Expr, *args: object, **kwargs: object) -> sp.Expr:
            calls.append(expr)
            time.sleep(seconds)
            return real(expr, *args, **kwargs)

        return trigsimp

    spec = load_spec(ROOT / "tests" / "specs" / "kinematic_car.toml")
    marks = dict(derive(spec).timings)
    before = sum(marks[s] for s in ("model", "relative degree", "error dynamics"))
    budget = 3 * before + 0.5
    monkeypatch.setattr(sp, "trigsimp", slow(budget + 0.5))
    with pytest.raises(BudgetError, match="derivation stage 'decoupling matrix'"):
        derive(spec, budget=Budget(seconds=budget))
    assert len(calls) == 1  # the budget ended the slow call itself


@pytest.mark.parametrize("spec", ["integrator", "unicycle_switch"])
def test_non_finite_inputs_are_worded_alike_in_both_backends(
    spec: str, tmp_path_factory: pytest.TempPathFactory
) -> None:
    states = random_states(spec, 4)
    states[0, 2] = np.nan
    m = len(derivation(spec).spec.outputs)
    outcomes = []
    for mod in _modules(spec, tmp_path_factory):
        seen = []
        name = next(iter(mod.PARAMETERS))
        for t, x, params in (
            (np.inf, random_states(spec, 2), None),
            (0.5, states, None),
            (0.5, states[:, 2], None),
            (0.5, random_states(spec, 2), {name: np.nan}),
        ):
            for function in STATE_FUNCTIONS:
                with pytest.raises(mod.NonFiniteInputError) as info:
                    getattr(mod, function)(t, x, params)
                seen.append((str(info.value), info.value.index))
            for function in OUTPUT_FUNCTIONS:
                with pytest.raises(mod.NonFiniteInputError) as info:
                    getattr(mod, function)(t, np.asarray(x)[:m], params)
                seen.append((str(info.value), info.value.index))
        outcomes.append(seen)
    assert outcomes[0] == outcomes[1]
    assert ("the state is not finite (column 2)", 2) in outcomes[0]
    assert ("t = inf is not finite", None) in outcomes[0]
    assert ("a parameter is not finite", None) in outcomes[0]


def test_both_backends_share_an_output_folder(tmp_path: Path) -> None:
    out = tmp_path / "out"
    for backend in ("python", "c"):
        _generate("integrator", backend, out)
    assert sorted(p.name for p in out.iterdir()) == sorted(
        ["integrator.py", "integrator_c.py", "integrator.c", "integrator.h", "integrator.ext.c"]
    )
    script = (
        "import integrator as a, integrator_c as b, numpy;"
        "s = numpy.array(a.DEFAULT_STATE);"
        "print(a.BACKEND, b.BACKEND, numpy.allclose(a.control(1.0, s), b.control(1.0, s),"
        " rtol=1e-13, atol=0))"
    )
    done = _python(script, out, {**os.environ, "TVOPT_CODEGEN_CACHE": str(tmp_path / "cache")})
    assert done.returncode == 0, done.stderr
    assert done.stdout.split() == ["python", "c", "True"]


ALL_FUNCTIONS = STATE_FUNCTIONS + OUTPUT_FUNCTIONS


@pytest.mark.parametrize("spec", EXAMPLES)
def test_one_state_takes_the_fast_path_with_the_batch_bits(
    spec: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    mod = module(spec)
    states = random_states(spec, 5, seed=21)
    m = len(mod.OUTPUT_NAMES)
    for j in range(states.shape[1]):
        for name in ALL_FUNCTIONS:
            x = states[:, j] if name in STATE_FUNCTIONS else states[:m, j]
            batch = getattr(mod, name)(0.9, x[:, None])[..., 0]
            assert np.array_equal(getattr(mod, name)(0.9, x), batch), (name, j)
    # The one-point path answers alone: the array law is never called for one state.
    monkeypatch.setattr(mod, "_law", lambda *a, **k: (_ for _ in ()).throw(AssertionError))
    mod.control(0.9, states[:, 0])
    mod.rhs(0.9, states[:, 0])
    assert isinstance(mod.objective(0.9, states[:m, 0]), float)


def test_the_fast_path_leaves_every_error_to_the_array_path() -> None:
    mod = module("unicycle_switch")
    state = np.array(mod.DEFAULT_STATE)
    state[3] = 0.0  # v = 0: R is singular
    with pytest.raises(mod.SingularDecouplingError) as single:
        mod.control(0.5, state)
    with pytest.raises(mod.SingularDecouplingError) as batch:
        mod.control(0.5, state[:, None])
    assert str(single.value) == str(batch.value) and single.value.index == 0
    state[0] = np.nan
    with pytest.raises(mod.NonFiniteInputError, match=r"the state is not finite \(column 0\)"):
        mod.rhs(0.5, state)
    barrier = module("two_unicycles_barrier")
    at_pole = np.array(barrier.DEFAULT_STATE)
    at_pole[3:5] = at_pole[0:2]  # the two agents at one point: the barrier's tan is fine,
    for function in (barrier.control, barrier.rhs):  # its derivative jet too; same answer
        try:
            expected = function(0.5, at_pole[:, None])[..., 0]
        except barrier.ControllerError as error:
            with pytest.raises(type(error), match=re.escape(str(error))):
                function(0.5, at_pole)
        else:
            assert np.array_equal(function(0.5, at_pole), expected)


def test_the_fast_path_is_silent_and_obeys_strict_warning_filters() -> None:
    mod = module("flexible_joint")
    state = np.array(mod.DEFAULT_STATE)
    state[0] = 1e300  # cosh overflows on the way: the result is not finite
    # NumPy's warnings on the one-point path are silenced there (numpy.errstate); a caller
    # who turns warnings into errors gets the documented exception all the same.
    for strict in (False, True):
        with warnings.catch_warnings(record=True) as seen:
            warnings.simplefilter("error" if strict else "always")
            with pytest.raises(mod.NonFiniteOutputError):
                mod.control(0.5, state)
            with np.errstate(all="raise"), pytest.raises(mod.NonFiniteOutputError):
                mod.rhs(0.5, state)
        assert seen == []
    np.testing.assert_array_equal(
        mod.control(0.5, np.array(mod.DEFAULT_STATE)),
        mod.control(0.5, np.array(mod.DEFAULT_STATE)[:, None])[:, 0],
    )
