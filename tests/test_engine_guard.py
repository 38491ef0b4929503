"""The guard of issue 49: the two engines derive the same law.

Every bundled example, every test spec and a set of fuzzed specs (a plant, an arm or
a URDF robot with integral action, observers, limits, references and constraints
drawn by :mod:`tests.fuzzing`) is derived, lowered and generated as a Python module
on SymPy (the reference) and on SymEngine (the fast core), and the two controllers'
inputs, vector fields and optimality errors agree to 1e-12 (relative to each output's
scale) at random states, times and parameters. The term order may differ between the
engines; the numbers may not.
"""

from __future__ import annotations

import copy
import functools
import itertools
import tempfile
from pathlib import Path
from types import ModuleType
from typing import Any

import numpy as np
import pytest

from tvopt_codegen import symbolic as sx
from tvopt_codegen.derivation import derive
from tvopt_codegen.lowering.ir import lower
from tvopt_codegen.renderer.rendering import render
from tvopt_codegen.spec import Spec, spec_from_dict

from .conftest import ROOT, SPECS, derivation, import_file, kernels
from .fuzzing import Case, build_spec, sample_states

EXAMPLES = sorted(p.stem for p in (ROOT / "tvopt_codegen" / "examples").glob("*.toml"))
#: The test specs (kinematic_car is refused on both engines: R is singular at its start).
TEST_SPECS = sorted(p.name for p in SPECS.glob("*.toml") if p.stem != "kinematic_car")
#: Fuzzed cases, one per kind and feature mix that the fuzzer's pairs walk meets most.
FUZZED = (
    "system:2:-:11",
    "system:2:integral+limits:5",
    "system:3:observer:7",
    "system:2:equality:3",
    "system:2:inequality+references:9",
    "system:2:eso:4",
    "arm:2:-:2",
    "arm:2:observer:8",
    "urdf:2:integral:6",
)
RELATIVE = 1e-12
_BUILD = Path(tempfile.mkdtemp(prefix="tvopt-engine-guard-"))
_COUNT = itertools.count()


@functools.cache
def _fuzzed_mapping(name: str) -> dict[str, Any]:
    """A fuzzed case's spec mapping and files, built once for both engines.

    The case alone decides them (the mapping is the same built on either engine, a URDF
    robot's file too), and a URDF case's build is 0.7 s: each engine reads its own spec
    from the one mapping.
    """
    folder = _BUILD / f"case{next(_COUNT)}"
    folder.mkdir()
    mapping, _ = build_spec(Case.parse(name), folder)
    return mapping


def _fuzzed_spec(name: str) -> Spec:
    return spec_from_dict(copy.deepcopy(_fuzzed_mapping(name)))


@functools.cache
def generated_module(kind: str, name: str, engine: str) -> tuple[ModuleType, Any]:
    """The generated Python controller for a spec, derived on ``engine``, and its derivation.

    An example's or test spec's derivation and kernels are conftest's, once per engine and
    worker: the same spec on the same engine is derived alike wherever it is asked for,
    and test_engine_det, test_report_printing and test_golden ask for these on SymPy, and
    most files on SymEngine.
    """
    with sx.using(engine):
        if kind == "fuzzed":
            d = derive(_fuzzed_spec(name))
            files = render(lower(d), "python")
        else:
            key = name if kind == "example" else str(SPECS / name)
            d = derivation(key)
            files = render(kernels(key), "python")
    # The law was built by the engine named, not converted from the other's.
    assert type(d.closed_loop.states[0]).__module__.split(".")[0] == engine
    ((filename, text),) = files.items()
    folder = _BUILD / f"{engine}{next(_COUNT)}"
    folder.mkdir()
    path = folder / filename
    path.write_text(text, encoding="utf-8")
    return import_file(path, f"_tvopt_guard_{engine}_{filename[:-3]}_{folder.name}"), d


def _close(what: str, theirs: np.ndarray, ours: np.ndarray) -> None:
    scale = max(float(np.abs(ours).max(initial=0.0)), 1e-300)
    worst = float(np.abs(theirs - ours).max(initial=0.0))
    assert theirs.shape == ours.shape, what
    assert worst <= RELATIVE * scale, f"{what}: differs by {worst:.3g} at scale {scale:.3g}"


def _agree(kind: str, name: str) -> None:
    reference, d = generated_module(kind, name, "sympy")
    fast, _ = generated_module(kind, name, "symengine")
    modules_agree(reference, fast, d, name)


def modules_agree(reference: ModuleType, fast: ModuleType, d: Any, name: str) -> None:
    """Two generated Python controllers of one spec compute the same law.

    ``fast``'s inputs, vector field and optimality error are ``reference``'s to
    :data:`RELATIVE` of each output's scale, at 64 random states of derivation ``d``
    (where ``reference``'s law is defined), three times and parameters drawn within 10 %
    of their defaults (and random reference jets, where the spec takes them).
    """
    assert fast.PARAMETERS.keys() == reference.PARAMETERS.keys()
    rng = np.random.default_rng(49)
    states = sample_states(d, rng, 64)
    names = getattr(reference, "REFERENCE_NAMES", ())
    for t in (0.0, 1.3, 7.9):
        params = {
            key: float(value) * float(rng.uniform(0.9, 1.1))
            for key, value in reference.PARAMETERS.items()
        }
        extra: dict[str, Any] = {}
        if names:
            # Reference jets given at run time: random values and derivatives.
            extra["refs"] = rng.uniform(-1.0, 1.0, size=(len(names), reference.REFERENCE_ORDER + 1))
        # Columns where the law is defined (a random state may be past a barrier).
        kept = [
            j for j in range(states.shape[1]) if _defined(reference, t, states[:, j], params, extra)
        ]
        assert len(kept) >= states.shape[1] // 2, f"{name}: the law is undefined at most states"
        at = states[:, kept]
        for call in ("control", "rhs", "optimality_error"):
            ours = np.asarray(getattr(reference, call)(t, at, params, **extra), dtype=float)
            theirs = np.asarray(getattr(fast, call)(t, at, params, **extra), dtype=float)
            _close(f"{name}: {call} at t = {t}", theirs, ours)


def _defined(module: ModuleType, t: float, state: np.ndarray, params: Any, extra: Any) -> bool:
    try:
        module.control(t, state, params, **extra)
    except module.ControllerError:
        return False
    return True


@pytest.mark.parametrize("name", EXAMPLES)
def test_both_engines_agree_on_every_example(name: str) -> None:
    _agree("example", name)


@pytest.mark.parametrize("name", TEST_SPECS)
def test_both_engines_agree_on_every_test_spec(name: str) -> None:
    _agree("test", name)


@pytest.mark.parametrize("case", FUZZED)
def test_both_engines_agree_on_fuzzed_specs(case: str) -> None:
    _agree("fuzzed", case)
