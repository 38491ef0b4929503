"""Lowering and rendering on both engines: the same kernels, the same numbers.

Bundled examples and test specs (one per feature of the kernels) are lowered on SymPy
(the reference) and on SymEngine, and every kernel of the two is evaluated in floats at
the same random inputs (its temporaries, then its outputs, by a walk of this file's own
that reads nothing of either engine's numerics): the outputs agree to 1e-12 relative.
The two engines' CSE may name and order temporaries differently, and hoist different
terms into ``tau``, so only the kernels' interfaces and values are compared.

SymEngine's lowering is given two derivations: SymPy's converted at the border
(:func:`tvopt_codegen.symbolic.border.from_sympy`, deep through the derivation's
records), which tests lowering alone, and SymEngine's own, the whole pipeline.
"""

from __future__ import annotations

import argparse
import dataclasses
import functools
import math
import random
import tomllib
import types
from collections.abc import Iterator, Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy
import pytest

from tvopt_codegen import symbolic as sx
from tvopt_codegen.commands import common
from tvopt_codegen.derivation import Derivation, derive
from tvopt_codegen.errors import BudgetError
from tvopt_codegen.lowering.ir import Kernel, KernelSet, check_kernels, lower
from tvopt_codegen.lowering.plan import Plan
from tvopt_codegen.simulation import load_controller
from tvopt_codegen.spec import Spec, spec_from_dict
from tvopt_codegen.symbolic import border

from .engine_cases import ON_A_LINE, float_value

TESTS = Path(__file__).resolve().parent
EXAMPLES = TESTS.parent / "tvopt_codegen" / "examples"
#: PVTOL, the unicycle's switching objective and the arm's mass matrix (its LDL^T in the
#: jet); the integrator's Hessian (the cholesky kernel) and its reference jets; integral
#: action and a disturbance observer; inequality constraints (the margin kernels); the
#: extended-state observer (eso_start); an equality (the KKT law).
NAMES = (
    "pvtol",
    "unicycle_switch",
    "planar_arm3",
    "integrator",
    "integrator_refs",
    "robust_pvtol",
    "figure8_wall",
    "unicycle_eso",
    "on_a_line",
)
RELATIVE = 1e-12


def spec(name: str) -> Spec:
    """The spec ``name`` on the process's engine: an example, a test spec, or one above."""
    if name == "on_a_line":
        return spec_from_dict(tomllib.loads(ON_A_LINE))
    if name == "unicycle_eso":
        with (EXAMPLES / "unicycle_switch.toml").open("rb") as stream:
            data = tomllib.load(stream)
        return spec_from_dict(data | {"robust": {"eso": {"bandwidth": 20.0}}})
    path = EXAMPLES / f"{name}.toml"
    with (path if path.exists() else TESTS / "specs" / f"{name}.toml").open("rb") as stream:
        return spec_from_dict(tomllib.load(stream))


@functools.cache
def sympy_derivation(name: str) -> Derivation:
    """The spec ``name`` derived on SymPy (the reference)."""
    with sx.using("sympy"):
        return derive(spec(name))


def converted(value: Any, memo: dict[Any, Any], seen: dict[int, Any]) -> Any:
    """``value`` with every SymPy expression and matrix in it made SymEngine's.

    Walks dataclasses (their fields set in place of a copy, frozen or not), tuples,
    lists and dicts; anything else that is not SymPy's is kept as it is.
    """
    import sympy  # noqa: PLC0415 - the reference engine, converted from

    done = seen.get(id(value))
    if done is not None:
        return done
    out: Any = value
    if isinstance(value, sympy.Basic | sympy.MatrixBase):
        out = border.from_sympy(value, memo)
    elif dataclasses.is_dataclass(value) and not isinstance(value, type):
        out = object.__new__(type(value))
        seen[id(value)] = out
        for field in dataclasses.fields(value):
            if hasattr(value, field.name):
                item = converted(getattr(value, field.name), memo, seen)
                object.__setattr__(out, field.name, item)
    elif isinstance(value, tuple) and hasattr(value, "_fields"):
        out = type(value)(*(converted(v, memo, seen) for v in value))
    elif isinstance(value, tuple | list):
        out = type(value)(converted(v, memo, seen) for v in value)
    elif isinstance(value, dict):
        out = {converted(k, memo, seen): converted(v, memo, seen) for k, v in value.items()}
    seen[id(value)] = out
    return out


@functools.cache
def symengine_derivation(name: str) -> Derivation:
    """The SymPy derivation of ``name`` with its expressions converted to SymEngine."""
    source = sympy_derivation(name)
    with sx.using("symengine"):
        result: Derivation = converted(source, {}, {})
    return result


@functools.cache
def symengine_derived(name: str) -> Derivation:
    """The spec ``name`` derived on SymEngine from the start."""
    with sx.using("symengine"):
        return derive(spec(name))


#: SymEngine's derivation: SymPy's converted at the border (lowering alone under test),
#: or SymEngine's own (the whole pipeline).
SOURCES = {"converted": symengine_derivation, "derived": symengine_derived}


@functools.cache
def lowered(name: str, engine: str, source: str = "converted") -> KernelSet:
    """The example's kernels on ``engine`` (SymEngine's from ``source``)."""
    with sx.using(engine):
        if engine == "sympy":
            return lower(sympy_derivation(name))
        return lower(SOURCES[source](name))


def run(kernel: Kernel, inputs: Mapping[str, float], tau: list[float]) -> dict[str, list[float]]:
    """Evaluate ``kernel`` at slot values given by slot name: its outputs, flat.

    The jet's input ``tau`` (what ``jet_time`` returns, an engine's CSE decides its
    entries) is given by position.
    """
    env: dict[Any, float] = {}
    for arg in kernel.inputs:
        if arg.name == "tau":
            env.update(zip(arg.symbols, tau, strict=True))
            continue
        for symbol in arg.symbols or (sx.symbol("t"),):
            env[symbol] = inputs[str(symbol)]
    memo: dict[Any, Any] = {}
    for target, expr in kernel.body:
        env[target] = float_value(expr, env, memo)
    return {
        out.name: [float(float_value(sx.sympify(e), env, memo)) for e in out.exprs]
        for out in kernel.outputs
    }


def run_all(kernels: Sequence[Kernel], point: Mapping[str, float]) -> dict[str, list[float]]:
    """Every kernel's outputs at ``point`` (by ``kernel.output``), the jet after jet_time."""
    results: dict[str, list[float]] = {}
    tau: list[float] = []
    for kernel in kernels:
        for output, values in run(kernel, point, tau).items():
            results[f"{kernel.name}.{output}"] = values
        if kernel.name == "jet_time":
            tau = results["jet_time.tau"]
    return results


def interface(kernel: Kernel) -> tuple[Any, ...]:
    """What a caller of ``kernel`` sees: its inputs' slots and its outputs' shapes.

    ``tau`` aside, whose entries are what each engine's CSE finds to hoist.
    """
    return (
        kernel.name,
        tuple(
            (arg.name, tuple(map(str, arg.symbols)), arg.labels)
            for arg in kernel.inputs
            if arg.name != "tau"
        ),
        tuple((out.name, out.shape) for out in kernel.outputs if out.name != "tau"),
    )


def without_tau(plan: Plan) -> Plan:
    """``plan`` with the size of ``tau`` (an engine's CSE's choice) set to 0."""
    values = tuple(dataclasses.replace(v, size=0) if v.name == "tau" else v for v in plan.values)
    return dataclasses.replace(plan, values=values)


def random_points(kernels: Sequence[Kernel], seed: int, count: int) -> Iterator[dict[str, float]]:
    """``count`` random values of every slot of ``kernels``, by name (positive, away from 0)."""
    rng = random.Random(seed)
    names = sorted(
        {
            str(symbol)
            for kernel in kernels
            for arg in kernel.inputs
            if arg.name != "tau"
            for symbol in (arg.symbols or (sx.symbol("t"),))
        }
    )
    for _ in range(count):
        yield {name: rng.uniform(0.3, 1.2) for name in names}


def assert_close(name: str, expected: list[float], actual: list[float]) -> None:
    """Equal to :data:`RELATIVE` of the output's largest entry (NaN where NaN)."""
    assert len(expected) == len(actual), name
    scale = max((abs(v) for v in expected if math.isfinite(v)), default=0.0)
    for i, (want, got) in enumerate(zip(expected, actual, strict=True)):
        if math.isnan(want):
            assert math.isnan(got), f"{name}[{i}]: {got} where SymPy gives NaN"
            continue
        tolerance = RELATIVE * max(abs(want), scale, 1e-300)
        assert abs(want - got) <= tolerance, f"{name}[{i}]: {got} against {want}"


def assert_same_values(
    reference: Sequence[Kernel], fast: Sequence[Kernel], seed: int, count: int
) -> int:
    """Both kernel sets at ``count`` random points agree; the number of values compared."""
    compared = 0
    for point in random_points(reference, seed, count):
        with sx.using("sympy"):
            expected = run_all(reference, point)
        with sx.using("symengine"):
            actual = run_all(fast, point)
        assert expected.keys() == actual.keys()
        for output, values in expected.items():
            if output != "jet_time.tau":
                assert_close(output, values, actual[output])
                compared += len(values)
    return compared


@pytest.mark.parametrize("source", SOURCES)
@pytest.mark.parametrize("name", NAMES)
def test_every_kernel_agrees_on_both_engines(name: str, source: str) -> None:
    reference, fast = lowered(name, "sympy"), lowered(name, "symengine", source)
    assert [interface(k) for k in fast.kernels] == [interface(k) for k in reference.kernels]
    assert without_tau(fast.plan) == without_tau(reference.plan)
    assert (fast.r_blocks, fast.lu_ops) == (reference.r_blocks, reference.lu_ops)
    with sx.using("symengine"):
        # Every expression of SymEngine's kernels is SymEngine's: none left over.
        body = [v for k in fast.kernels for _, v in k.body]
        outputs = [e for k in fast.kernels for out in k.outputs for e in out.exprs]
        assert all(isinstance(e, sx.Basic) for e in body + outputs)
    entries = sum(len(o.exprs) for k in reference.kernels for o in k.outputs if o.name != "tau")
    compared = assert_same_values(reference.kernels, fast.kernels, seed=len(name), count=3)
    assert compared == 3 * entries > 0


@pytest.mark.parametrize("source", SOURCES)
@pytest.mark.parametrize("name", ["planar_arm3", "figure8_wall", "on_a_line"])
def test_check_kernels_agree_on_both_engines(name: str, source: str) -> None:
    # The sweep's checks: the whole R (through the mass matrix's solve on the arm), the
    # slack and inequalities (figure8_wall), the equalities, their Jacobian and the
    # multipliers' curvature (on_a_line).
    with sx.using("sympy"):
        reference = check_kernels(sympy_derivation(name))
    with sx.using("symengine"):
        fast = check_kernels(SOURCES[source](name))
    pairs = [
        (want, got)
        for want, got in (
            (reference.decoupling, fast.decoupling),
            (reference.constraints, fast.constraints),
            (reference.equalities, fast.equalities),
        )
        if want is not None or got is not None
    ]
    assert len(pairs) == (1 if name == "planar_arm3" else 2)
    for want, got in pairs:
        assert want is not None and got is not None
        assert interface(got) == interface(want)
        entries = sum(len(out.exprs) for out in want.outputs)
        assert assert_same_values([want], [got], seed=3, count=3) == 3 * entries > 0


def loaded(kernels: KernelSet, engine: str) -> types.ModuleType:
    """The Python backend's controller of ``kernels``, rendered on ``engine``."""
    with sx.using(engine):
        return load_controller(kernels, "python")


@pytest.mark.parametrize(
    "name", ["pvtol", "planar_arm3", "integrator", "robust_pvtol", "figure8_wall", "on_a_line"]
)
def test_rendered_controllers_agree_on_both_engines(name: str) -> None:
    # Rendering prints SymEngine's kernels through the backends' printers: the
    # generated modules compute the same law, batch of states by batch of states.
    reference = loaded(lowered(name, "sympy"), "sympy")
    fast = loaded(lowered(name, "symengine", "derived"), "symengine")
    rng = numpy.random.default_rng(len(name))
    start = numpy.array(reference.DEFAULT_STATE)
    states = start[:, None] + rng.uniform(-0.2, 0.2, (len(start), 4))
    plant = states[: len(reference.PLANT_STATE_NAMES)]
    inputs = rng.uniform(-1.0, 1.0, (len(reference.INPUT_NAMES), 4))
    outputs = reference.outputs(0.3, plant)
    # Reference jets where the spec has references: one jet for every point.
    refs = {}
    if hasattr(reference, "REFERENCE_ORDER"):
        shape = (len(reference.REFERENCE_NAMES), reference.REFERENCE_ORDER + 1)
        refs = {"refs": rng.uniform(-0.2, 0.2, shape)}
    calls: list[tuple[str, tuple[Any, ...], dict[str, Any]]] = [
        ("control", (0.3, states), refs),
        ("rhs", (0.3, states), refs),
        ("optimality_error", (0.3, states), refs),
        ("objective", (0.3, outputs), refs),
        ("gradient", (0.3, outputs), refs),
        ("hessian", (0.3, outputs), refs),
        ("plant", (0.3, plant, inputs), {}),
        ("outputs", (0.3, plant), {}),
    ]
    finite = 0
    for function, args, options in calls:
        want, got = (outcome(m, function, args, options) for m in (reference, fast))
        if isinstance(want, str):
            # The law fails alike (a state past a barrier, say): the same error.
            assert got == want, function
            continue
        assert isinstance(got, numpy.ndarray) and want.shape == got.shape, function
        assert numpy.all(numpy.isfinite(want)), function
        scale = numpy.max(numpy.abs(want))
        assert numpy.max(numpy.abs(got - want)) <= RELATIVE * max(scale, 1e-300), function
        finite += 1
    assert finite >= 5


def outcome(
    module: types.ModuleType, function: str, args: tuple[Any, ...], options: dict[str, Any]
) -> numpy.ndarray | str:
    """A generated function's values, or the name of the controller error it raises."""
    try:
        return numpy.asarray(getattr(module, function)(*args, **options))
    except module.ControllerError as error:
        return type(error).__name__


def derive_args(name: str, **options: Any) -> argparse.Namespace:
    """A deriving command's arguments for the example ``name``."""
    values: dict[str, Any] = {
        "spec": str(EXAMPLES / f"{name}.toml"),
        "extension": "spec",
        "progress": "never",
        "max_seconds": 120.0,
        "max_size": 20_000,
    }
    return argparse.Namespace(**(values | options))


def test_the_commands_budgets_hold_on_symengine(capsys: pytest.CaptureFixture[str]) -> None:
    # The size budget counts SymEngine's nodes as SymPy's: pvtol's largest expression
    # is between 5 and 20,000 nodes on both engines.
    for engine in ("sympy", "symengine"):
        with sx.using(engine):
            _, kernels = common.derive(derive_args("pvtol", progress="always"))
            assert all(isinstance(e, sx.Basic) for e in kernels["jet"].outputs[0].exprs)
            with pytest.raises(BudgetError, match="past 5 nodes"):
                common.derive(derive_args("pvtol", max_size=5))
            with pytest.raises(BudgetError, match="longer than 1e-06 s"):
                common.derive(derive_args("pvtol", max_seconds=1e-6))
        lines = capsys.readouterr().err.splitlines()
        assert lines[-1].startswith("  deriving: kernels and CSE, ")
        expressions, nodes = (
            int(lines[-1].split(", ")[1].split()[0]),
            int(lines[-1].split("(")[1].split()[0]),
        )
        assert nodes > expressions > 10, engine
