"""A certificate never passes vacuously; a run where the law is undefined is a user error."""

from __future__ import annotations

import re
import types
from pathlib import Path

import numpy as np
import pytest

from tvopt_codegen.derivation import derive
from tvopt_codegen.errors import AssumptionError
from tvopt_codegen.lowering.ir import lower
from tvopt_codegen.report import render_report
from tvopt_codegen.simulation import (
    format_certificate,
    load_controller,
    resolve_options,
    simulate,
)
from tvopt_codegen.spec import load_spec

from .conftest import ROOT, Ran, derivation, module, run_main, write_spec

INTEGRATOR = (ROOT / "tvopt_codegen" / "examples" / "integrator.toml").read_text()


def _with_objective(tmp_path: Path, f0: str, name: str = "spec.toml") -> Path:
    lines = [
        f'f0 = "{f0}"' if line.startswith("f0 = ") else line for line in INTEGRATOR.splitlines()
    ]
    return write_spec(tmp_path, "\n".join(lines) + "\n", name)


def _cli(*args: str) -> Ran:
    return run_main(*args)


def test_a_flat_minimum_is_refused_where_it_matters(tmp_path: Path) -> None:
    # (y - r)**4: the Hessian is 12 (y - r)**2, positive near y(0) but 0 at y*(t).
    spec = _with_objective(tmp_path, "(y1 - o1)**4 + (y2 - o2)**4")
    done = _cli("check", str(spec))
    assert done.returncode == 3
    assert done.stderr.count("\n") == 1
    assert "f0 is not strongly convex at its minimiser: at t = " in done.stderr
    assert "(a flat minimum such as (y - r)**4" in done.stderr


def test_locally_strongly_convex_objective_gets_a_warning(tmp_path: Path) -> None:
    spec = _with_objective(tmp_path, "log(cosh(y1 - o1)) + log(cosh(y2 - o2))")
    d = derive(load_spec(spec))
    assert len(d.warnings) == 1
    assert "strongly convex only near its minimiser: at distance 10 from y*(t)" in d.warnings[0]
    done = _cli("check", str(spec))
    assert done.returncode == 0
    assert "tvopt-codegen: warning: " in done.stderr and "objective.f0:" in done.stderr
    # The bundled examples (quadratic, log cosh plus a quadratic, barriers) warn of nothing.
    for name in ("integrator", "flexible_joint", "two_unicycles_barrier", "unicycle_ring"):
        assert derivation(name).warnings == ()


def test_a_barely_convex_objective_fails_the_certificate(tmp_path: Path) -> None:
    # Strong enough convexity to be derived (2e-5 against a scale of about 100), but the
    # bound C e^(-alpha t) with C ~ 1/m_f says nothing over the run.
    spec = _with_objective(
        tmp_path, "(y1 - o1)**4 + (y2 - o2)**4 + 1e-5*((y1 - o1)**2 + (y2 - o2)**2)"
    )
    # The run and the certificate the command prints, in this process (the command's exit
    # 5 on a failed certificate is test_simulate's test_wrong_controller_fails_the_certificate;
    # its files and figures are not looked at here).
    barely = derive(load_spec(spec))
    run = simulate(barely, load_controller(lower(barely)), resolve_options(barely, points=101))
    printed = format_certificate(barely, run)
    assert not run.passed
    assert "certificate: FAILED" in printed
    assert "the bound is vacuous: m_f = 2e-05 is below 1e-06 of the Hessian's scale" in printed
    assert "is still above the initial |y - y*|" in printed
    # The bundled integrator passes with a meaningful bound: the certificate the command
    # would print (format_certificate; exit 0 is result.passed), without its files and
    # figures, which this test does not look at.
    d = derivation("integrator")
    result = simulate(d, module("integrator"), resolve_options(d, points=101))
    assert result.passed and "vacuous" not in format_certificate(d, result)


def test_a_singular_initial_state_is_a_user_error_and_writes_nothing(tmp_path: Path) -> None:
    out = tmp_path / "run"
    done = _cli("simulate", "unicycle_switch", "--initial", "v=0", "--out", str(out))
    assert done.returncode == 3
    assert done.stderr.count("\n") == 1
    assert "simulation.initial_state: the law is undefined at the initial state (" in done.stderr
    assert "v = 0" in done.stderr and "R is singular where v = 0" in done.stderr
    assert not out.exists()
    done = _cli("simulate", "integrator", "--initial", "x1=1e308", "--out", str(out))
    assert done.returncode == 3, done.stderr
    assert done.stderr.count("\n") == 1 and "near t = " in done.stderr
    assert not out.exists()


def test_a_law_undefined_along_the_run_is_exit_3_not_an_internal_error() -> None:
    d = derivation("integrator")
    real = module("integrator")
    fake = types.ModuleType("fake")
    fake.__dict__.update({k: v for k, v in vars(real).items() if not k.startswith("__")})

    def rhs(t: float, s: np.ndarray, params: object = None) -> np.ndarray:
        if t > 1.0:
            raise real.HessianNotPositiveDefiniteError("the Hessian of f0 is not positive")
        return real.rhs(t, s, params)

    fake.rhs = rhs
    with pytest.raises(
        AssumptionError,
        match=r"simulation: the law became undefined along the "
        r"run, near t = 1\.\d+: the Hessian of f0 is not positive",
    ):
        simulate(d, fake, resolve_options(d, points=21))


def test_repeated_poles_are_read_from_the_poles(tmp_path: Path) -> None:
    # Distinct poles (unicycle_switch: -1, -1.5): the bound's rate is the decay rate,
    # whatever rounding the companion matrix's eigenvalues carry.
    assert derivation("unicycle_switch").dynamics.certified_rate_exact
    text = (ROOT / "tvopt_codegen" / "examples" / "unicycle_switch.toml").read_text()
    assert "poles = [-1.0, -1.5]" in text
    spec = write_spec(tmp_path, text.replace("poles = [-1.0, -1.5]", "poles = [-1.0, -1.0]"))
    d = derive(load_spec(spec))
    assert not d.dynamics.certified_rate_exact and d.dynamics.certified_rate == pytest.approx(0.9)
    report = render_report(d, lower(d), formats=("md",))
    assert "(repeated poles: 10% epsilon)" in next(iter(report.values()))
    plain = derivation("unicycle_switch")
    report = render_report(plain, lower(plain), formats=("md",))
    assert "repeated poles" not in next(iter(report.values()))
    result = simulate(plain, load_controller(lower(plain)), resolve_options(plain, points=21))
    assert result.alpha_exact


SPECS = ROOT / "tests" / "specs"


def test_singular_sets_name_where_r_or_p_is_undefined(tmp_path: Path) -> None:
    car = derive(load_spec(SPECS / "kinematic_car.toml"))
    assert car.decoupling.singular_set == ("v = 0",) and car.decoupling.undefined_set == (
        "cos(phi) = 0",
    )
    assert (
        car.decoupling.singular_text
        == "R is singular where v = 0; R or p is undefined where cos(phi) = 0"
    )
    attitude = derive(load_spec(SPECS / "attitude.toml"))
    assert attitude.decoupling.singular_set == () and attitude.decoupling.undefined_set == (
        "cos(pitch) = 0",
    )
    done = _cli("check", str(SPECS / "attitude.toml"))
    assert (
        "never singular" in done.stdout and "R or p undefined where cos(pitch) = 0" in done.stdout
    )
    # A steering angle of pi/2: the message names the set the state lies on.
    done = _cli(
        "simulate",
        str(SPECS / "kinematic_car.toml"),
        "--initial",
        "v=1",
        "--initial",
        f"phi={np.pi / 2!r}",
        "--out",
        str(tmp_path / "run"),
    )
    assert done.returncode == 3
    assert "phi = 1.5708" in done.stderr and "R or p is undefined where cos(phi) = 0" in done.stderr
    mod = module(str(SPECS / "kinematic_car.toml"))
    state = np.array(mod.DEFAULT_STATE)
    with pytest.raises(mod.SingularDecouplingError, match="R or p is undefined where cos"):
        mod.control(0.0, state)
    # Every bundled example has nowhere R or p is undefined (the generated code is as before).
    for name in ("integrator", "unicycle_switch", "pvtol", "flexible_joint", "unicycle_ring"):
        assert derivation(name).decoupling.undefined_set == ()


def test_a_singular_default_state_is_warned_about(tmp_path: Path) -> None:
    car = derive(load_spec(SPECS / "kinematic_car.toml"))
    (warning,) = car.warnings
    assert "the law is undefined at the initial state (" in warning
    assert "the extension states v, v_d1 start at 0 unless simulation.initial_state gives them" in (
        warning
    )
    assert "DEFAULT_STATE cannot be simulated as it is" in warning
    for command in ("check", "generate"):
        args = ["--out", str(tmp_path / "gen")] if command == "generate" else []
        done = _cli(command, str(SPECS / "kinematic_car.toml"), *args)
        assert done.returncode == 0 and "warning:" in done.stderr and "DEFAULT_STATE" in done.stderr
    # With automatic extension the extension states may be given by name (PVTOL's thrust).
    pvtol = derivation("pvtol")
    assert pvtol.spec.extension_auto
    assert pvtol.closed_loop.initial_state[pvtol.closed_loop.state_names.index("thrust")] == 9.81
    assert pvtol.warnings == ()
    text = (SPECS / "kinematic_car.toml").read_text()
    given = text.replace("phi = 0.0 }", "phi = 0.0, v = 1.0 }")
    assert derive(load_spec(write_spec(tmp_path, given))).warnings == ()


@pytest.mark.parametrize("n", [20, 70])
def test_fading_convexity_is_found_among_many_outputs(n: int) -> None:
    """Beyond 16 outputs the probe steps along 16 fixed directions (not every axis):
    a log cosh objective over 20 outputs still gets the warning, and a quadratic none;
    beyond 64 the probe factors sparse Hessians instead of computing eigenvalues, with
    the same verdicts and the same warning (its eigenvalue computed where it fades)."""
    base = {
        "name": "many",
        "system": {
            "states": [f"x{i}" for i in range(n)],
            "inputs": [f"u{i}" for i in range(n)],
            "dynamics": {f"x{i}": f"u{i}" for i in range(n)},
            "outputs": {f"y{i}": f"x{i}" for i in range(n)},
        },
        "error_dynamics": {"poles": [-1.0]},
        "simulation": {"t_final": 5.0},
    }
    fading = " + ".join(f"log(cosh(y{i} - sin(t + {i})))" for i in range(n))
    d = derive({**base, "objective": {"f0": fading}})
    assert len(d.warnings) == 1
    assert "strongly convex only near its minimiser: at distance 10 from y*(t)" in d.warnings[0]
    # The eigenvalue the warning quotes: log cosh's second derivative at distance 10
    # along a direction of +-1 entries, 1/cosh(10)^2 = 8.24e-9 in every output, below
    # 1e-6 of its value 1 at y*.
    assert "the Hessian's smallest eigenvalue is 8.24e-09" in d.warnings[0]
    # tanh keeps the Hessian away from constant, so the sampled path is taken, not the
    # exact one of a quadratic: still no warning where f0 does not fade.
    steady = " + ".join(f"(y{i} - sin(t + {i}))**2 + 0.1*tanh(y{i})" for i in range(n))
    assert derive({**base, "objective": {"f0": steady}}).warnings == ()


def test_the_step_exponential_matches_a_fifty_digit_reference() -> None:
    # hurwitz.exponential replaces scipy's expm for the transient constant: it must be right
    # to the last bit on companion matrices (stiff, repeated poles) and on general ones.
    import mpmath  # noqa: PLC0415 - a dependency of sympy

    from tvopt_codegen.maths.hurwitz import coefficients_from_poles, companion, exponential

    rng = np.random.default_rng(7)
    matrices = [
        companion(coefficients_from_poles(poles)) * step
        for poles in ([-1.0] * 6, [-0.5 + 2j, -0.5 - 2j, -3.0], [-10.0] * 8)
        for step in (1e-3, 0.1, 2.0)
    ]
    matrices += [rng.normal(size=(k, k)) * scale for k in (1, 3, 5) for scale in (0.01, 1, 20)]
    with mpmath.workdps(50):
        for matrix in matrices:
            exact = np.array(mpmath.expm(mpmath.matrix(matrix.tolist())).tolist(), dtype=float)
            error = np.max(np.abs(exponential(matrix) - exact)) / max(1.0, np.max(np.abs(exact)))
            assert error < 1e-15, (matrix, error)


def test_the_step_exponential_is_kept_per_matrix_and_handed_out_as_a_fresh_array() -> None:
    # The memo hands out the bits a fresh computation gives, keyed by the matrix's bits:
    # a matrix one ulp away is computed anew, and an answer changed by its caller is not
    # what the next caller gets.
    from tvopt_codegen.maths import hurwitz

    matrix = hurwitz.companion(hurwitz.coefficients_from_poles([-1.0, -2.0, -3.0])) * 0.025
    hurwitz._exponential.cache_clear()
    first = hurwitz.exponential(matrix)
    assert hurwitz._exponential.cache_info().misses == 1
    first[0, 0] = np.nan
    again = hurwitz.exponential(matrix.copy())
    assert hurwitz._exponential.cache_info().hits == 1
    hurwitz._exponential.cache_clear()
    assert np.array_equal(again, hurwitz.exponential(matrix))  # the same bits, recomputed
    nudged = hurwitz.exponential(np.nextafter(matrix, 1.0))
    assert hurwitz._exponential.cache_info().misses == 2
    assert not np.array_equal(nudged, again)


def _ring_and_star(m: int) -> list[tuple[list[tuple[int, int]], bool]]:
    """Two lower patterns of m outputs, and whether each is a narrow band: a ring (in its
    reverse Cuthill-McKee order) is, a star coupling every output to the first is not,
    in any order."""
    ring = [(i, i) for i in range(m)] + [
        (max(i, (i + 1) % m), min(i, (i + 1) % m)) for i in range(m)
    ]
    star = [(i, i) for i in range(m)] + [(i, 0) for i in range(1, m)]
    return [(ring, True), (star, False)]


def _symmetric(entries: list[tuple[int, int]], values: np.ndarray, m: int) -> np.ndarray:
    """The (P, m, m) symmetric matrices of stored lower entries (E, P)."""
    out = np.zeros((values.shape[1], m, m))
    for (i, j), v in zip(entries, values, strict=True):
        out[:, i, j] = out[:, j, i] = v
    return out


def test_sparse_definiteness_agrees_with_eigenvalues_banded_or_not() -> None:
    """The fading probe's definiteness test: a narrow band (a ring, in its reverse
    Cuthill-McKee order) by banded Cholesky, a wide pattern by SuperLU; both give the
    verdict of the smallest eigenvalue, on both sides of it."""
    from tvopt_codegen.derivation.hessians import _BAND_LIMIT, _SparseHessians

    rng = np.random.default_rng(11)
    m = 90
    for entries, banded in _ring_and_star(m):
        sparse = _SparseHessians(entries, m)
        assert (sparse.band <= _BAND_LIMIT) is banded
        for _ in range(20):
            values = rng.normal(size=len(entries))
            low = float(np.linalg.eigvalsh(_symmetric(entries, values[:, None], m)[0])[0])
            for shift in (-low + 1e-3, -low - 1e-3):
                verdict = sparse.positive_definite(values, shift)
                assert verdict is None or verdict == (low + shift > 0), (banded, shift)


def test_sparse_eigenvalues_and_newton_steps_agree_with_dense_algebra() -> None:
    """A team's convexity check and Newton search: banded eigenvalues and banded LU of
    the permuted matrix (a ring), dense ones for a wide pattern (a star), against numpy's
    dense eigvalsh and solve; a singular or non-finite matrix is reported unusable."""
    from tvopt_codegen.derivation.hessians import _BAND_LIMIT, _SparseHessians

    rng = np.random.default_rng(5)
    m = 90
    for entries, banded in _ring_and_star(m):
        sparse = _SparseHessians(entries, m)
        assert (sparse.band <= _BAND_LIMIT) is banded

        def dense(values: np.ndarray, entries: list[tuple[int, int]] = entries) -> np.ndarray:
            return _symmetric(entries, values, m)

        values = rng.normal(size=(len(entries), 6))
        values[:, 5] = 0.0  # the zero matrix: singular
        values[3, 4] = np.nan  # not finite
        grads = rng.normal(size=(6, m))
        matrices = dense(values)
        low, high = sparse.extremes(values, dense)
        steps, usable = sparse.solve(values, grads, dense)
        assert usable.tolist() == [True, True, True, True, False, False], banded
        assert np.isnan(low[4]) and np.isnan(high[4])
        for point in range(4):
            eig = np.linalg.eigvalsh(matrices[point])
            assert low[point] == pytest.approx(eig[0], rel=1e-12, abs=1e-12)
            assert high[point] == pytest.approx(np.max(np.abs(eig)), rel=1e-12)
            want = np.linalg.solve(matrices[point], grads[point])
            assert steps[point] == pytest.approx(want, rel=1e-9, abs=1e-9), (banded, point)
        assert np.array_equal(steps[4:], grads[4:])


def test_the_transient_constant_is_the_supremum_on_its_grid() -> None:
    """c = sup_t |expm(H t)|_2 e^(alpha t), sampled where transient_constant samples it
    (its powers of one step, their norms in one batched call), against expm at each t."""
    from scipy.linalg import expm  # noqa: PLC0415

    from tvopt_codegen.maths.hurwitz import (
        certified_rate,
        coefficients_from_poles,
        companion,
        eigenvalues,
        transient_constant,
    )

    for poles in ([-1.5, -1.0], [-1.0] * 4, [-0.5 + 2j, -0.5 - 2j, -3.0], [-0.1, -5.0]):
        a = coefficients_from_poles(poles)
        alpha, _ = certified_rate(a)
        fastest = float(np.max(np.abs(eigenvalues(a))))
        horizon = 40.0 / alpha
        grid = np.linspace(0.0, horizon, int(min(20000, max(2000, 40 * fastest * horizon))))
        reference = max(
            np.linalg.norm(expm(companion(a) * t), 2) * np.exp(alpha * t) for t in grid[::7]
        )
        c = transient_constant(a, alpha)
        assert reference * (1 - 1e-9) <= c <= reference * 1.01, poles


@pytest.mark.parametrize(
    "name", ["integrator", "unicycle_switch", "pvtol", "flexible_joint", "unicycle_ring"]
)
def test_the_predicted_error_is_expm_at_every_output_time(name: str) -> None:
    """``hurwitz.flow`` steps expm(H h) over the grid (a few exponentials of the k x k
    companion, not one of H per time): it agrees with scipy's expm(H t) E(0) at each time
    to 1e-12 of |E(0)|."""
    from scipy.linalg import expm

    from tvopt_codegen.maths import hurwitz

    d = derivation(name)
    H = hurwitz.error_matrix(d.dynamics.coefficients, d.jet.n_kkt)
    start = np.random.default_rng(7).normal(size=H.shape[0])
    for times in (np.linspace(0.0, d.spec.t_final, 401), np.sort([0.0, 0.3, 0.31, 2.0, 7.5])):
        stepped = hurwitz.flow(d.dynamics.coefficients, d.jet.n_kkt, start, times)
        direct = np.array([expm(H * t) @ start for t in times])
        assert np.max(np.abs(stepped - direct)) <= 1e-12 * np.linalg.norm(start)


@pytest.mark.parametrize("name", ["integrator", "unicycle_switch", "pvtol"])
def test_a_quadratic_objectives_minimizer_takes_two_steps_a_time(name: str) -> None:
    """With a constant Hessian, y* is two full Newton steps at each time, from the last
    one, and equals the continuation with substeps and line search."""
    from tvopt_codegen.simulation.target import minimizer_path

    d = derivation(name)
    assert d.objective.convexity.quadratic
    mod = module(name)
    ts = np.linspace(0.0, d.spec.t_final, 101)
    start = np.random.default_rng(5).normal(size=len(d.spec.outputs)) * 3.0
    general = minimizer_path(mod, ts, start, None)

    calls = []

    class Counting:
        """The module, its f0, gradient and Hessian counted per evaluation (wrapped, they
        are what minimizer_path calls: simulation.direct keeps a replaced function)."""

        def __getattr__(self, attr: str) -> object:
            value = getattr(mod, attr)
            if attr not in ("objective", "gradient", "hessian"):
                return value

            def counted(*args: object, **kwargs: object) -> object:
                calls.append(attr)
                return value(*args, **kwargs)

            return counted

    quick = minimizer_path(Counting(), ts, start, None, quadratic=True)  # type: ignore[arg-type]
    np.testing.assert_allclose(quick, general, rtol=0, atol=1e-12 * (1 + np.abs(general).max()))
    assert calls.count("gradient") == 2 * len(ts) and calls.count("hessian") == len(ts)
    assert "objective" not in calls


# ------------------------------------------------------------------ runs into singular R

BEYOND_REACH = SPECS / "arm2_beyond_reach.toml"


def _boundary_crossing() -> tuple[float, float]:
    """When and where the exact E' = -E path of the tip leaves the arm's reach of 2.

    ``y(t) = p + e^(-t) (y(0) - p)`` with ``p = (3, 0)``: the arm is straight there
    (``q2 = 0``, ``det R = sin(q2) = 0``), pointing at ``atan2(y)``.
    """
    from scipy.optimize import brentq

    q1, q2 = 0.3, 1.2
    y0 = np.array([np.cos(q1) + np.cos(q1 + q2), np.sin(q1) + np.sin(q1 + q2)])
    p = np.array([3.0, 0.0])

    def tip(t: float) -> np.ndarray:
        return p + np.exp(-t) * (y0 - p)

    t_star = brentq(lambda t: np.linalg.norm(tip(t)) - 2.0, 0.0, 5.0)
    return float(t_star), float(np.arctan2(tip(t_star)[1], tip(t_star)[0]))


def test_a_run_into_singular_r_names_det_r_the_time_and_the_state(tmp_path: Path) -> None:
    out = tmp_path / "out"
    done = _cli("simulate", str(BEYOND_REACH), "--out", str(out))
    assert done.returncode == 3, done.stderr
    assert done.stderr.count("\n") == 1, done.stderr
    assert "less than spacing" not in done.stderr
    found = re.search(
        r"simulation: det R -> 0 at t = (\S+) s \(det R = (\S+); (\S+) of its value at t = 0, "
        r"and the integrator's step size collapsed\): the run reached the singular set of R "
        r"\(R is singular where sin\(q2\) = 0\), where the law is undefined; "
        r"state: q1 = (\S+), q2 = (\S+)$",
        done.stderr.strip(),
    )
    assert found is not None, done.stderr
    t, det, ratio, q1, q2 = (float(v) for v in found.groups())
    t_star, angle = _boundary_crossing()
    assert abs(t - t_star) < 1e-5 and abs(q1 - angle) < 1e-5
    # det R = sin(q2) at the reported state, and far below its start sin(1.2) = 0.93.
    assert abs(det - np.sin(q2)) < 5e-3 * abs(det) and 0 < abs(det) < 1e-4
    assert ratio == pytest.approx(abs(det) / np.sin(1.2), rel=0.05)
    assert not out.exists()


def test_a_singular_pivot_along_the_run_names_det_r_and_the_state() -> None:
    d = derive(load_spec(BEYOND_REACH))
    real = load_controller(lower(d))
    fake = types.ModuleType("fake")
    fake.__dict__.update({k: v for k, v in vars(real).items() if not k.startswith("__")})

    def rhs(t: float, s: np.ndarray, params: object = None) -> np.ndarray:
        if t > 0.2:
            raise real.SingularDecouplingError("the decoupling matrix R is singular")
        return real.rhs(t, s, params)

    fake.rhs = rhs
    with pytest.raises(AssumptionError) as caught:
        simulate(d, fake, resolve_options(d, points=21))
    message = str(caught.value)
    assert "simulation: det R -> 0 at t = 0.2" in message and "\n" not in message
    assert "a pivot of R's LU fell below 1e-12 of its largest entry" in message
    _, q2 = (float(v) for v in re.findall(r"q\d = (\S+?)(?:,|$)", message))
    t = float(re.search(r"at t = (\S+) s", message).group(1))  # type: ignore[union-attr]
    det = float(re.search(r"\(det R = (\S+);", message).group(1))  # type: ignore[union-attr]
    assert det == pytest.approx(np.sin(q2), rel=5e-3)
    # The elbow of the exact tip path y(t) = p + e^(-t) (y(0) - p) at that time.
    q1, elbow = 0.3, 1.2
    y0 = np.array([np.cos(q1) + np.cos(q1 + elbow), np.sin(q1) + np.sin(q1 + elbow)])
    tip = np.array([3.0, 0.0]) + np.exp(-t) * (y0 - np.array([3.0, 0.0]))
    assert q2 == pytest.approx(np.arccos((tip @ tip - 2.0) / 2.0), abs=1e-4)


def test_det_r_of_a_mass_matrix_plant_is_det_j_m_inverse_b(tmp_path: Path) -> None:
    from tvopt_codegen.simulation.run import decoupling_determinant

    spec = write_spec(
        tmp_path,
        (SPECS / "arm2_mass.toml")
        .read_text()
        .replace('y1 = "q1"', 'tx = "cos(q1) + cos(q1 + q2)"')
        .replace('y2 = "q2"', 'ty = "sin(q1) + sin(q1 + q2)"')
        .replace("(y1 - sin(t))**2 + (y2 - 0.5*cos(t))**2", "(tx - 1)**2 + (ty - 1)**2"),
    )
    d = derive(load_spec(spec))
    det = decoupling_determinant(d, {"a2": 0.7})
    assert det is not None
    rng = np.random.default_rng(4)
    for _ in range(5):
        s = rng.normal(size=4)
        q2 = s[1]
        a1, a2, a3 = 3.0, 0.7, 0.4
        mass = (a1 + 2 * a2 * np.cos(q2)) * a3 - (a3 + a2 * np.cos(q2)) ** 2
        assert det(0.0, s) == pytest.approx(np.sin(q2) / mass, rel=1e-12, abs=1e-15)
