"""``simulate``'s side process: the constraints' SLSQP solves, found beside the run."""

from __future__ import annotations

import numpy as np
import pytest

from tvopt_codegen.runs.side import Side, can_fork
from tvopt_codegen.simulation import resolve_options, simulate
from tvopt_codegen.simulation.constraints import minimiser_process

from .conftest import derivation, module

pytestmark = pytest.mark.skipif(not can_fork(), reason="no process can be forked here")


def test_the_side_process_finds_the_minimisers_this_one_would() -> None:
    d = derivation("two_unicycles_corridor")
    controller = module("two_unicycles_corridor")
    options = resolve_options(d)
    with minimiser_process(d.model, options.params) as side:
        assert side.running
        beside = simulate(d, controller, options, side=side)
        # Still running: it answered (a failed request stops it, and the run works here).
        assert side.running
    here = simulate(d, controller, options)
    assert beside.constraints is not None and here.constraints is not None
    np.testing.assert_array_equal(beside.constraints.distance, here.constraints.distance)
    np.testing.assert_array_equal(beside.constraints.bound, here.constraints.bound)
    assert beside.passed and np.all(np.isfinite(beside.constraints.distance))


def test_a_request_at_other_parameter_values_is_solved_at_those() -> None:
    d = derivation("two_unicycles_corridor")
    controller = module("two_unicycles_corridor")
    name, default = d.model.params[-1].name, float(d.model.defaults[-1])
    options = resolve_options(d, params={name: 1.1 * default})
    # Started at the defaults, asked at the run's values: it lambdifies those anew.
    with minimiser_process(d.model, {}) as side:
        beside = simulate(d, controller, options, side=side)
        assert side.running
    here = simulate(d, controller, options)
    assert beside.constraints is not None and here.constraints is not None
    np.testing.assert_array_equal(beside.constraints.distance, here.constraints.distance)


def test_a_side_process_answers_and_a_failed_one_answers_none() -> None:
    with Side(lambda: lambda request: (request[0] * 2, np.arange(request[1]))) as side:
        doubled, numbers = side.ask((21, 3))
        assert doubled == 42 and numbers.tolist() == [0, 1, 2]
        assert side.ask(("x", 2))[0] == "xx"
        assert side.running
        # A request that fails there is refused, and the process stops.
        assert side.ask((None, 1)) is None
        assert not side.running
        assert side.ask((1, 1)) is None

    def broken() -> object:
        raise ImportError("no scipy here")

    with Side(broken) as side:
        assert side.ask((1, 1)) is None
        assert not side.running
