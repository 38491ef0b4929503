"""The generated Python module: its contract, and its numbers against an oracle."""

from __future__ import annotations

import numpy as np
import pytest

from .conftest import ALL_SPECS, SPECS, derivation, module
from .oracle import Oracle


def random_states(spec: str, count: int, seed: int = 3) -> np.ndarray:
    """States near the spec's initial state: prolonged speeds kept away from zero."""
    d = derivation(spec)
    rng = np.random.default_rng(seed)
    base = np.array(d.closed_loop.initial_state)
    states = base[:, None] + rng.uniform(-0.2, 0.2, size=(len(base), count))
    for name in d.linearization.extension.states:
        i = d.closed_loop.state_names.index(name)
        states[i] = rng.uniform(0.5, 1.5, size=count) * rng.choice([-1, 1], size=count)
    return states


@pytest.mark.parametrize("spec", ALL_SPECS)
def test_control_and_rhs_match_the_oracle(spec: str) -> None:
    mod = module(spec)
    oracle = Oracle(derivation(spec))
    p = np.array(list(mod.PARAMETERS.values()), dtype=float)
    states = random_states(spec, 1000)
    for t in (0.0, 3.7, 11.2):
        u_ref, ds_ref = oracle.law(t, states, p)
        np.testing.assert_allclose(
            mod.control(t, states), u_ref, rtol=1e-10, atol=1e-10 * np.abs(u_ref).max()
        )
        np.testing.assert_allclose(
            mod.rhs(t, states), ds_ref, rtol=1e-10, atol=1e-10 * np.abs(ds_ref).max()
        )
        E_ref = oracle.optimality_error(t, states, p)
        np.testing.assert_allclose(
            mod.optimality_error(t, states), E_ref, rtol=1e-10, atol=1e-10 * np.abs(E_ref).max()
        )


def test_parameters_are_overridable_at_run_time() -> None:
    spec = "unicycle_switch"
    mod = module(spec)
    oracle = Oracle(derivation(spec))
    states = random_states(spec, 50)
    moved = mod.control(9.0, states, {"a": 4.0})
    assert not np.allclose(moved, mod.control(9.0, states))
    u_ref, _ = oracle.law(9.0, states, np.array([4.0, 1.5]))
    np.testing.assert_allclose(moved, u_ref, rtol=1e-10, atol=1e-12)
    with pytest.raises(ValueError, match=r"unknown parameter\(s\) \['c'\]"):
        mod.control(0.0, states, {"c": 1.0})


@pytest.mark.parametrize("spec", ALL_SPECS)
def test_one_dimensional_and_batched_calls_agree(spec: str) -> None:
    mod = module(spec)
    states = random_states(spec, 7)
    batched = mod.rhs(1.5, states)
    assert batched.shape == states.shape
    for j in range(states.shape[1]):
        single = mod.rhs(1.5, states[:, j])
        assert single.shape == (states.shape[0],)
        np.testing.assert_array_equal(single, batched[:, j])
    assert mod.control(1.5, states[:, 0]).shape == (len(mod.INPUT_NAMES),)
    width = len(mod.OUTPUT_NAMES) + len(mod.MULTIPLIER_NAMES)
    assert mod.optimality_error(1.5, states[:, 0]).shape == (mod.K, width)


def test_contract_of_the_unicycle_module() -> None:
    mod = module("unicycle_switch")
    assert mod.STATE_NAMES == ("x1", "x2", "theta", "v")
    assert mod.INPUT_NAMES == ("v", "omega")
    assert mod.OUTPUT_NAMES == ("y1", "y2")
    assert mod.PARAMETERS == {"a": 10.0, "b": 1.5}
    assert mod.RELATIVE_DEGREE == {"y1": 2, "y2": 2}
    assert mod.K == 2
    assert mod.HURWITZ_COEFFICIENTS == (-1.5, -2.5)
    assert mod.DEFAULT_STATE == (-5.0, 4.0, 0.0, 1.0)
    assert mod.EXTENSION == {"v": 1}
    for name in ("control", "rhs", "optimality_error", "objective", "gradient", "hessian"):
        assert callable(getattr(mod, name))
        assert "Parameters" in getattr(mod, name).__doc__
    assert "s[2]  theta" in mod.__doc__
    for exc in (
        mod.NonFiniteInputError,
        mod.SingularDecouplingError,
        mod.HessianNotPositiveDefiniteError,
        mod.NonFiniteOutputError,
    ):
        assert issubclass(exc, mod.ControllerError)
        assert issubclass(exc, ArithmeticError)
        assert not issubclass(exc, (ZeroDivisionError, FloatingPointError))


def test_padding_state_names_of_the_nonuniform_module() -> None:
    mod = module(str(SPECS / "nonuniform.toml"))
    assert mod.STATE_NAMES == ("x1", "x2", "x3", "xi_y1_1")
    assert mod.RELATIVE_DEGREE == {"y1": 1, "y2": 2}
    assert mod.DEFAULT_STATE == (1.0, -1.0, 0.5, 0.0)


def test_objective_gradient_hessian() -> None:
    mod = module("integrator")
    y = np.array([0.3, -0.7])
    t = 2.0
    o1, o2 = 2 + 0.8 * t - 0.05 * t**2, -1 + 0.5 * t + 0.02 * t**2 - 0.001 * t**3
    w = 2.0
    assert mod.objective(t, y) == pytest.approx(
        0.5 * (y[0] - o1) ** 2 + 0.5 * w * (y[1] - o2) ** 2, rel=1e-14
    )
    np.testing.assert_allclose(mod.gradient(t, y), [y[0] - o1, w * (y[1] - o2)], rtol=1e-14)
    np.testing.assert_allclose(mod.hessian(t, y), [[1.0, 0.0], [0.0, w]])
    batch = np.stack([y, y + 1], axis=1)
    assert mod.objective(t, batch).shape == (2,)
    assert mod.hessian(t, batch).shape == (2, 2, 2)


def test_singular_decoupling_raises_with_the_cause() -> None:
    mod = module("unicycle_switch")
    with pytest.raises(mod.SingularDecouplingError, match="v = 0") as info:
        mod.control(0.0, [-5.0, 4.0, 0.3, 0.0])
    assert info.value.status == mod.STATUS_SINGULAR_DECOUPLING
    states = np.array([[-5.0, -5.0], [4.0, 4.0], [0.0, 0.0], [1.0, 0.0]])
    with pytest.raises(mod.SingularDecouplingError) as info:
        mod.rhs(0.0, states)
    assert info.value.index == 1


def test_non_finite_input_raises() -> None:
    mod = module("unicycle_switch")
    with pytest.raises(mod.NonFiniteInputError, match="state is not finite"):
        mod.control(0.0, [np.nan, 4.0, 0.0, 1.0])
    with pytest.raises(mod.NonFiniteInputError, match="t = inf"):
        mod.rhs(np.inf, [0.0, 4.0, 0.0, 1.0])
    with pytest.raises(mod.NonFiniteInputError, match="parameter"):
        mod.rhs(0.0, [0.0, 4.0, 0.0, 1.0], {"b": np.nan})


def test_hessian_that_is_not_positive_definite_raises() -> None:
    mod = module("integrator")
    # The integrator's Hessian is diagonal: the kernel takes H00 and H11 only.
    indefinite = np.array([[1.0], [-1.0]])
    with pytest.raises(mod.HessianNotPositiveDefiniteError, match="not positive definite"):
        mod._cholesky_solve(indefinite, np.ones((2, 1)))
    with pytest.raises(mod.HessianNotPositiveDefiniteError):
        mod.control(0.0, [0.0, 0.0], {"w": -1.0})


def test_barrier_outside_its_domain_never_returns_nan() -> None:
    mod = module("two_unicycles_barrier")
    state = np.array(mod.DEFAULT_STATE)
    state[3] = state[0] + np.sqrt(2.0)  # |pa - pb|^2 = d: tan(pi/2), the barrier's pole
    state[4] = state[1]
    try:
        u = mod.control(0.0, state)
    except mod.ControllerError:
        return
    assert np.all(np.isfinite(u))


def test_wrong_shapes_are_rejected() -> None:
    mod = module("unicycle_switch")
    with pytest.raises(ValueError, match=r"s must have shape \(4,\) or \(4, N\)"):
        mod.control(0.0, [1.0, 2.0, 3.0])


def test_constant_hessian_is_inverted_at_generation_time() -> None:
    """Quadratic f0: no run-time Cholesky; a parameter-dependent Hessian keeps it."""
    from .conftest import kernels

    unicycle = kernels("unicycle_switch")["jet"]
    assert [o.name for o in unicycle.outputs] == ["z", "R", "pvec"]
    integrator = kernels("integrator")["jet"]  # Hessian diag(1, w): w is a parameter
    assert [o.name for o in integrator.outputs] == ["hessian", "jet_rhs", "R", "pvec"]


def test_batches_larger_than_a_block() -> None:
    # The NumPy backend evaluates a batch in blocks of _BLOCK columns (cache-sized):
    # results join seamlessly and an error names its column in the whole batch.
    mod = module("two_unicycles_barrier")
    count = 2 * mod._BLOCK + 77
    states = random_states("two_unicycles_barrier", count, seed=8)
    for name in ("control", "rhs", "optimality_error"):
        whole = getattr(mod, name)(1.3, states)
        assert whole.shape[-1] == count
        for start in (0, mod._BLOCK - 1, 2 * mod._BLOCK + 3):
            np.testing.assert_array_equal(
                whole[..., start], getattr(mod, name)(1.3, states[:, start])
            )
    y = states[: len(mod.OUTPUT_NAMES)]
    for name in ("objective", "gradient", "hessian"):
        whole = getattr(mod, name)(1.3, y)
        np.testing.assert_array_equal(whole[..., -1], getattr(mod, name)(1.3, y[:, -1]))
    bad = 2 * mod._BLOCK + 5
    states[6, bad] = 0.0  # va = 0: R is singular there
    with pytest.raises(mod.SingularDecouplingError, match=rf"\(column {bad}\)") as info:
        mod.control(1.3, states)
    assert info.value.index == bad
    states[6, bad] = np.nan
    with pytest.raises(mod.NonFiniteInputError, match=rf"\(column {bad}\)"):
        mod.rhs(1.3, states)


def test_control_never_evaluates_the_vector_field(monkeypatch: pytest.MonkeyPatch) -> None:
    # Like the C backend's control: the plant input alone is computed and checked, so a
    # vector field that overflows where u is fine cannot make the two backends disagree.
    mod = module("unicycle_switch")
    states = random_states("unicycle_switch", 5)
    expected = mod.control(0.4, states)

    def vector_field(*args: object) -> None:
        raise AssertionError("control evaluated ds/dt")

    monkeypatch.setattr(mod, "_closed_loop", vector_field)
    np.testing.assert_array_equal(mod.control(0.4, states), expected)
    with pytest.raises(AssertionError, match="ds/dt"):
        mod.rhs(0.4, states)
