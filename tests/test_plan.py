"""The execution plan (tvopt_codegen.lowering.plan): well formed for every spec, and the one
source of the statuses and the tolerance that every backend prints."""

from __future__ import annotations

import re

import pytest

from tvopt_codegen.lowering.plan import PIVOT_TOLERANCE, Status, law_plan
from tvopt_codegen.renderer.rendering import render

from .conftest import ALL_SPECS, kernels


@pytest.mark.parametrize("spec", ALL_SPECS)
def test_every_step_reads_what_is_there(spec: str) -> None:
    """Inputs first, each value written before it is read, each kernel one of the set's,
    its arguments and results matching the kernel's inputs and outputs in size."""
    ks = kernels(spec)
    plan = ks.plan
    names = {kernel.name for kernel in ks.kernels}
    for ending in (plan.control, plan.rhs):
        known = {v.name for v in plan.values if v.role == "input"}
        for step in (*plan.per_batch, *plan.steps, *ending):
            assert set(step.args) <= known, (step, known)
            if step.op in ("call", "solve_ldl"):
                assert step.kernel in names
            if step.op == "call":
                kernel = ks[step.kernel]
                # Bound by position: a kernel names its inputs for itself (``q`` is p).
                assert len(kernel.inputs) == len(step.args)
                assert len(kernel.outputs) == len(step.results)
                for arg, name in zip(kernel.inputs, step.args, strict=True):
                    if arg.symbols:
                        assert len(arg.symbols) == plan.value(name).size, (step.kernel, name)
                for out, name in zip(kernel.outputs, step.results, strict=True):
                    size = 1
                    for dim in out.shape:
                        size *= dim
                    assert size == plan.value(name).size, (step.kernel, name)
            if step.op == "check":
                assert set(step.alone) <= set(step.args)
                assert step.status is Status.NONFINITE_OUTPUT
            known |= set(step.results)
        assert {"u"} <= known
    assert "ds" in {r for step in plan.rhs for r in step.results}
    # Every value the law leaves the law's buffers with is checked before it is used.
    checked = {a for step in plan.steps if step.op == "check" for a in step.args}
    assert {"r", "pvec"} <= checked


@pytest.mark.parametrize("spec", ALL_SPECS)
def test_runtime_pieces_follow_the_blocks_and_the_hessian(spec: str) -> None:
    ks = kernels(spec)
    sizes = {len(block) for block in ks.r_blocks}
    runtime = set(ks.plan.runtime)
    assert ("ldl" in runtime) == any(k.name == "cholesky" for k in ks.kernels)
    assert ("lu_1" in runtime) == (1 in sizes)
    assert ("lu_2" in runtime) == (2 in sizes)
    assert ("lu" in runtime) == any(size > 2 for size in sizes)


def test_a_three_by_three_block_and_no_time_terms() -> None:
    plan = law_plan(
        n_states=6,
        n_inputs=3,
        n_outputs=3,
        n_params=0,
        k=2,
        tau=0,
        hessian=6,
        r_blocks=((0, 1, 2),),
    )
    assert plan.per_batch == ()
    assert plan.runtime == ("ldl", "lu")
    assert plan.steps[0].args == ("t", "s", "p", "a")
    assert plan.value("p").size == 1  # kernels take a pointer even without parameters
    assert [s.op for s in plan.steps] == [
        "call",
        "check",
        "solve_ldl",
        "call",
        "check",
        "solve_lu",
    ]
    # w is solved in the buffer that holds b: one buffer for both.
    assert plan.value("b").storage == plan.value("w").storage == "w"
    assert [v.name for v in plan.locals] == ["hess", "jet_rhs", "z", "r", "pvec", "w"]


@pytest.mark.parametrize("spec", ["unicycle_switch", "two_unicycles_barrier"])
def test_backends_print_the_statuses_and_tolerance_of_the_plan(spec: str) -> None:
    ks = kernels(spec)
    python = render(ks, "python")[f"{spec}.py"]
    c_files = render(ks, "c")
    header, source = c_files[f"{spec}.h"], c_files[f"{spec}.c"]
    for status in Status:
        assert f"\nSTATUS_{status.name} = {status.value}\n" in python
        assert f"#define {spec.upper()}_{status.name} {status.value}\n" in header
    assert len(re.findall(r"^STATUS_\w+ = ", python, re.MULTILINE)) == len(Status)
    assert f"PIVOT_TOLERANCE = {PIVOT_TOLERANCE!r}\n" in python
    assert f"#define {spec.upper()}_PIVOT_TOLERANCE {PIVOT_TOLERANCE!r}\n" in source
