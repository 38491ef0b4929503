"""Specs with repeated parts: the [index] table, x[i] names, sum(i, ...) and len(i)."""

from __future__ import annotations

import re
from importlib import resources

import numpy as np
import pytest
import sympy as sp

from tvopt_codegen import symbolic as sx
from tvopt_codegen.derivation import derive
from tvopt_codegen.derivation.law import diagonal_blocks
from tvopt_codegen.errors import SpecError
from tvopt_codegen.lowering.ir import lower
from tvopt_codegen.spec import Spec, load_spec, parse_spec
from tvopt_codegen.symbolic.border import to_sympy


def ring_text(agents: int) -> str:
    text = (resources.files("tvopt_codegen.examples") / "unicycle_ring.toml").read_text()
    return re.sub(r"(?m)^i = \d+", f"i = {agents}", text)


def ring(agents: int) -> Spec:
    return parse_spec("ring.toml", ring_text(agents).encode())


def test_ring_expands_agent_by_agent() -> None:
    spec = ring(3)
    assert spec.states[:4] == ("x_0", "y_0", "theta_0", "x_1")
    assert spec.inputs == ("v_0", "omega_0", "v_1", "omega_1", "v_2", "omega_2")
    assert spec.outputs == ("px_0", "py_0", "px_1", "py_1", "px_2", "py_2")
    assert spec.extension == (("v_0", 1), ("v_1", 1), ("v_2", 1))
    assert spec.indices == (("i", 3),)
    assert spec.agents == (("px_0", "py_0"), ("px_1", "py_1"), ("px_2", "py_2"))
    assert spec.objects[2] == ("ox_2", "oy_2")
    initial = dict(spec.initial_state)
    # "2.5*cos(2*pi*i/len(i)) - 1" at i = 1 of 3
    assert initial["x_1"] == pytest.approx(2.5 * np.cos(2 * np.pi / 3) - 1, rel=1e-15)
    assert initial["v_2"] == 1.0


def test_sum_wraps_around_the_ring() -> None:
    spec = ring(3)
    barriers = [atom.free_symbols for atom in spec.objective.atoms(sx.tan)]
    pairs = {frozenset(str(s) for s in free if str(s).startswith("px")) for free in barriers}
    # One barrier per ring neighbour pair, the last agent's with the first one included.
    assert pairs == {
        frozenset({"px_0", "px_1"}),
        frozenset({"px_1", "px_2"}),
        frozenset({"px_2", "px_0"}),
    }


def test_the_ring_equals_the_same_spec_written_out() -> None:
    flat = """
name = "ring_flat"
[system]
states = ["x_0", "y_0", "theta_0", "x_1", "y_1", "theta_1"]
inputs = ["v_0", "omega_0", "v_1", "omega_1"]
[system.dynamics]
x_0 = "v_0*cos(theta_0)"
y_0 = "v_0*sin(theta_0)"
theta_0 = "omega_0"
x_1 = "v_1*cos(theta_1)"
y_1 = "v_1*sin(theta_1)"
theta_1 = "omega_1"
[system.outputs]
px_0 = "x_0"
py_0 = "y_0"
px_1 = "x_1"
py_1 = "y_1"
[extension]
integrate = { v_0 = 1, v_1 = 1 }
[parameters]
alpha = 1e-3
d = 40.0
radius = 2.0
spin = 0.1
[signals]
ox_0 = "radius*cos(2*pi*0/2 + spin*t) + 0.3*t"
oy_0 = "radius*sin(2*pi*0/2 + spin*t) + 0.2*t"
ox_1 = "radius*cos(2*pi*1/2 + spin*t) + 0.3*t"
oy_1 = "radius*sin(2*pi*1/2 + spin*t) + 0.2*t"
[objective]
f0 = '''(px_0 - ox_0)**2 + (py_0 - oy_0)**2
  + alpha*tan(((px_0 - px_1)**2 + (py_0 - py_1)**2)*pi/(2*d))**2
  + (px_1 - ox_1)**2 + (py_1 - oy_1)**2
  + alpha*tan(((px_1 - px_0)**2 + (py_1 - py_0)**2)*pi/(2*d))**2'''
[error_dynamics]
poles = [-1.0, -1.5]
"""
    indexed, written = ring(2), parse_spec("flat.toml", flat.encode())
    assert indexed.states == written.states and indexed.outputs == written.outputs
    # Equal up to simplification: SymPy's simplify, across the border.
    assert sp.simplify(to_sympy(indexed.objective - written.objective)) == 0
    for (_, a), (_, b) in zip(indexed.signals, written.signals, strict=True):
        assert sp.simplify(to_sympy(a - b)) == 0
    assert indexed.dynamics == written.dynamics


def test_block_diagonal_decoupling_and_sparse_hessian() -> None:
    d = derive(ring(4))
    assert diagonal_blocks(d.linearization.R) == tuple((2 * a, 2 * a + 1) for a in range(4))
    kernels = lower(d)
    assert kernels["jet"].outputs[2].shape == (16,)  # 4 blocks of 2 x 2, not 8 x 8
    # Each output couples to itself and its two ring neighbours: a sparse Hessian.
    nonzero = sum(1 for i in range(8) for j in range(i + 1) if d.hessian[i, j] != 0)
    assert kernels["jet"].outputs[0].shape == (nonzero,) and nonzero < 8 * 9 // 2


def test_operations_grow_linearly_with_the_agents() -> None:
    ops = {}
    for agents in (5, 10):
        kernels = lower(derive(ring(agents)))
        law = ("jet_time", "jet", "cholesky", "decoupling", "closed_loop")
        ops[agents] = sum(kernels[k].ops for k in law) + kernels.lu_ops
    # Doubling the ring at most doubles the law (plus a constant): no dense solve.
    assert ops[10] <= 2.1 * ops[5], ops


@pytest.mark.parametrize(
    ("old", "new", "field", "problem"),
    [
        ("i = 4 ", "i = 0 ", "index.i", "1..4096"),
        ("i = 4 ", "i = 4097 ", "index.i", "1..4096"),
        ("i = 4 ", 'i = "N" ', "index.i", "whole number"),
        ('"x[i]" = "v[i]*cos(theta[i])"', '"x[j]" = "v[i]*cos(theta[i])"', "x[j]", "unknown index"),
        ('"x[i]" = "v[i]*cos(theta[i])"', '"x[i]" = "v[i]*cos(theta[i + 0.5])"', "x[i]", "integer"),
        ('"x[i]" = "v[i]*cos(theta[i])"', '"x[i]" = "v*cos(theta[i])"', "x[i]", "unknown name 'v'"),
        (
            '"x[i]" = "v[i]*cos(theta[i])"',
            '"x[i]" = "q[i]*cos(theta[i])"',
            "x[i]",
            "not an indexed",
        ),
        ("sum(i, (px[i]", "sum(j, (px[i]", "objective.f0", "not an index"),
        ("sum(i, (px[i]", "((px[i]", "objective.f0", "not bound"),
        ('"theta[i]" = 0.0', '"theta[i]" = "1/0"', "initial_state.theta[i]", "division by zero"),
        ('agents = [["px[i]", "py[i]"]]', 'agents = [["px[i]", "oy[i]"]]', "agents[0]", "output"),
    ],
)
def test_index_errors_name_the_field(old: str, new: str, field: str, problem: str) -> None:
    text = ring_text(4)
    assert old in text
    with pytest.raises(SpecError) as info:
        parse_spec("ring.toml", text.replace(old, new, 1).encode())
    message = str(info.value)
    assert message.startswith("ring.toml: ") and field in message and problem in message, message
    assert "\n" not in message


def test_bundled_ring_loads() -> None:
    assert load_spec("unicycle_ring").indices == (("i", 4),)
