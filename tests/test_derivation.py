"""The derivation against hand-derived ground truth and the paper's formulas."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import sympy as sp

from tvopt_codegen import symbolic as sx
from tvopt_codegen.derivation import derive, jet_symbol
from tvopt_codegen.errors import AssumptionError, SpecError
from tvopt_codegen.lowering.ir import lower
from tvopt_codegen.maths import hurwitz
from tvopt_codegen.renderer.rendering import render
from tvopt_codegen.spec import load_spec
from tvopt_codegen.symbolic import linalg
from tvopt_codegen.symbolic.border import from_sympy, to_sympy

from .conftest import SPECS, derivation, import_file, write_spec
from .engine_cases import remembered_simplify


def test_raw_unicycle_is_rejected_with_the_prolongation_suggestion(
    tmp_path: Path, unicycle_text: str
) -> None:
    text = unicycle_text.replace("integrate = { v = 1 }", "").replace(", v = 1.0 }", " }")
    with pytest.raises(AssumptionError) as info:
        derive(load_spec(write_spec(tmp_path, text)))
    message = str(info.value)
    assert "decoupling matrix R is singular everywhere" in message
    assert "prolong input 'v' by 1 integrator(s): [extension] integrate = { v = 1 }" in message
    assert info.value.exit_code == 3


def test_two_unicycles_det_r_is_the_product_of_speeds() -> None:
    d = derivation("two_unicycles_barrier")
    va, vb = sx.symbols(["va", "vb"])
    assert sx.expand(d.decoupling.det_R - va * vb) == 0
    assert set(d.decoupling.singular_set) == {"va = 0", "vb = 0"}


def test_nonuniform_relative_degree_is_padded() -> None:
    d = derivation(str(SPECS / "nonuniform.toml"))
    assert d.linearization.relative_degree == (1, 2)
    assert d.dynamics.k == 2 and not d.dynamics.uniform
    assert d.closed_loop.padding == (("xi_y1_1",), ())
    assert d.closed_loop.state_names == ("x1", "x2", "x3", "xi_y1_1")
    xi = sx.symbol("xi_y1_1")
    x1, x2, x3 = sx.symbols(["x1", "x2", "x3"])
    # y1' is the Brunovsky input of channel 1, i.e. the padding state.
    assert d.jet.y_jet_values == ((x1, xi), (x2, x3))


def test_integrator_law_is_prediction_correction() -> None:
    """k = 1: y_imp' = -Hess^-1 (P grad + grad_t) with P = -a_0 (paper, Example 1)."""
    d = derivation("integrator")
    assert d.dynamics.k == 1 and d.dynamics.coefficients == (-1.0,)
    model = d.model
    subs = dict(model.signals)
    grad = d.objective.gradient.xreplace(subs)
    hess = d.hessian.xreplace(subs)
    grad_t = grad.diff(model.t)
    expected = -hess.inv() * (1 * grad + grad_t)
    program = d.jet.jet_program + d.jet.rest_program
    rest = sx.Matrix([program.inline(e) for e in d.jet.rest])
    e0 = sx.Matrix([program.inline(e) for e in d.jet.grad_jet[0]])
    law = hess.inv() * (d.dynamics.coefficients[0] * e0 - rest)
    jet = {
        jet_symbol(str(s), q): sx.diff(e, model.t, q) for s, e in model.signals for q in range(3)
    }
    rng = np.random.default_rng(1)
    for _ in range(20):
        point = {
            model.t: rng.uniform(0, 10),
            model.y[0]: rng.normal(),
            model.y[1]: rng.normal(),
            model.params[0]: 2.0,
        }
        at = {s: sx.real(value) for s, value in point.items()}
        got = law.xreplace(jet).xreplace(at)
        want = expected.xreplace(at)
        assert np.allclose(_floats(got), _floats(want), rtol=1e-12)


def _floats(matrix: sx.Expr) -> np.ndarray:
    """A matrix of numbers of the engine as a float array."""
    return np.array([[float(entry) for entry in row] for row in matrix.tolist()])


@pytest.mark.parametrize(
    ("poles", "coefficients"),
    [
        ([-1.0], (-1.0,)),
        ([-1.0, -1.5], (-1.5, -2.5)),
        ([complex(-1, 2), complex(-1, -2)], (-5.0, -2.0)),
        ([-2.0, -2.0, -2.0, -2.0], (-16.0, -32.0, -24.0, -8.0)),
    ],
)
def test_coefficients_from_poles(poles: list[complex], coefficients: tuple[float, ...]) -> None:
    assert hurwitz.coefficients_from_poles(poles) == coefficients
    eig = np.sort_complex(hurwitz.eigenvalues(coefficients))
    assert np.allclose(eig, np.sort_complex(np.array(poles, dtype=complex)), atol=1e-3)


def test_non_hurwitz_coefficients_are_rejected(tmp_path: Path, unicycle_text: str) -> None:
    text = unicycle_text.replace("poles = [-1.0, -1.5]", "coefficients = [-2.0, 3.0]")
    with pytest.raises(AssumptionError, match="error_dynamics.coefficients: H is not Hurwitz"):
        derive(load_spec(write_spec(tmp_path, text)))


def test_wrong_number_of_poles_is_rejected(tmp_path: Path, unicycle_text: str) -> None:
    text = unicycle_text.replace("poles = [-1.0, -1.5]", "poles = [-1.0, [-2.0, 1.0]]")
    with pytest.raises(SpecError, match="order k = 2 .* give 2 poles, not 3"):
        derive(load_spec(write_spec(tmp_path, text)))


def test_non_convex_objective_is_rejected(tmp_path: Path, unicycle_text: str) -> None:
    text = unicycle_text.replace('f0 = "S*', 'f0 = "-3*y1**2 + S*')
    with pytest.raises(AssumptionError, match="not strongly convex"):
        derive(load_spec(write_spec(tmp_path, text)))


def test_output_without_relative_degree_is_rejected(tmp_path: Path, unicycle_text: str) -> None:
    text = unicycle_text.replace('y2 = "x2"', 'y2 = "a"')
    with pytest.raises(AssumptionError, match="no relative degree"):
        derive(load_spec(write_spec(tmp_path, text)))


def test_automatic_extension_finds_the_papers_prolongation(
    tmp_path: Path, unicycle_text: str
) -> None:
    text = unicycle_text.replace("integrate = { v = 1 }", "auto = true")
    d = derive(load_spec(write_spec(tmp_path, text)))
    assert d.linearization.extension.counts == (("v", 1),)
    assert d.linearization.extension_search == ("none", "v: 1")
    assert d.linearization.relative_degree == (2, 2)


def test_automatic_extension_prolongs_pvtol_thrust_twice() -> None:
    d = derivation("pvtol")
    assert d.linearization.extension.counts == (("thrust", 2),)
    assert d.linearization.extension_search == ("none", "thrust: 1", "torque: 1", "thrust: 2")
    assert d.linearization.relative_degree == (4, 4) and d.dynamics.k == 4
    assert d.closed_loop.state_names[-2:] == ("thrust", "thrust_d1")
    assert d.decoupling.singular_set == ("thrust = 0",)


def test_automatic_extension_failure_lists_what_was_tried(
    tmp_path: Path, unicycle_text: str
) -> None:
    text = unicycle_text.replace("integrate = { v = 1 }", "auto = true\nmax_total = 2")
    text = text.replace('y2 = "x2"', 'y2 = "x1 + 0*x2"')  # two equal outputs: never decoupled
    with pytest.raises(AssumptionError) as info:
        derive(load_spec(write_spec(tmp_path, text)))
    message = str(info.value)
    assert "extension.auto: no prolongation of the inputs with at most 2 integrators" in message
    assert "tried 6: none; v: 1; omega: 1; v: 2; v: 1, omega: 1; omega: 2" in message
    assert info.value.exit_code == 3


def test_flexible_joint_is_static_with_relative_degree_four() -> None:
    d = derivation("flexible_joint")
    assert (
        d.linearization.extension.counts == ()
        and d.linearization.relative_degree == (4,)
        and d.dynamics.k == 4
    )
    assert d.decoupling.singular_set == ("stiffness = 0",)
    assert d.objective.convexity.method == "sampled near y(0) and along y*(t)"
    assert d.objective.convexity.m_f > 2.0


def test_program_names_never_capture_user_names(tmp_path: Path, unicycle_text: str) -> None:
    """Parameters named like the derivation's own temporaries (g0, g1) change nothing."""
    weighted = unicycle_text.replace("b = 1.5", "b = 1.5\n{a} = 3.0\n{b} = 0.5").replace(
        'f0 = "S*(', 'f0 = "{a}*{b}*S*('
    )
    laws = []
    for a, b in (("g0", "g1"), ("w0", "w1")):
        text = weighted.replace("{a}", a).replace("{b}", b)
        spec = load_spec(write_spec(tmp_path, text, f"{a}.toml"))
        laws.append(lower(derive(spec)))
    mods = []
    for i, kernel_set in enumerate(laws):
        ((file_name, text),) = render(kernel_set, "python").items()
        path = tmp_path / f"capture{i}" / file_name
        path.parent.mkdir()
        path.write_text(text, encoding="utf-8")
        mods.append(import_file(path, f"_tvopt_test_capture{i}"))
    state = np.array([-4.0, 3.0, 0.3, 1.2])
    for t in (0.0, 3.0, 11.0):
        np.testing.assert_allclose(mods[0].control(t, state), mods[1].control(t, state), rtol=1e-13)


def test_why_the_extension_is_needed_is_said_in_one_readable_line() -> None:
    """The note on the plant before prolongation: R written out while it is small, its
    size alone for a team (a 64-agent ring's R is 128 x 128)."""
    small = derivation("unicycle_switch").linearization.unextended
    assert small is not None and "R = [[" in small and "generic rank 1 < 2" in small
    team = derivation("unicycle_ring").linearization.unextended
    assert team is not None and "R (8 x 8) has generic rank 4 < 8" in team
    assert len(team) < 200


def test_tree_size_counts_the_tree_and_stops_past_its_limit() -> None:
    from tvopt_codegen.derivation import tree_size

    def nodes(expr: sx.Expr) -> int:
        return 1 + sum(nodes(arg) for arg in expr.args)

    x, y = sx.symbols(["x", "y"])
    shared = sx.sin(x + y)
    expr = shared * shared.diff(x) + 3 * x  # the shared subtree is counted where it occurs
    assert nodes(expr) == 13  # Add(Mul(sin(Add(x, y)), cos(Add(x, y))), Mul(3, x))
    assert tree_size(expr, 10**6) == nodes(expr)
    assert tree_size(expr, 4) == 5  # at most limit + 1
    assert tree_size(x, 0) == 1


def _every_spec() -> list[str]:
    examples = sorted(
        p.stem for p in (Path(__file__).parent.parent / "tvopt_codegen" / "examples").glob("*.toml")
    )
    return examples + sorted(str(p) for p in SPECS.glob("*.toml"))


@pytest.mark.parametrize("spec", _every_spec())
def test_the_determinant_is_simplified_as_sympys_simplify_would(spec: str) -> None:
    """det R (and the equalities' Gram determinant) as factor(simplify(det)) gives it."""
    from tvopt_codegen.derivation.equalities import _equality_jacobian
    from tvopt_codegen.derivation.singularity import simplified_det

    d = derivation(spec)
    dets = []
    # The determinants as the derivation takes them (linalg.det: SymPy's Berkowitz on
    # SymPy, the same steps on SymEngine); simplify and factor are SymPy's (the border).
    if d.linearization.R.rows <= 4:
        dets.append(linalg.det(d.linearization.R))
    if 0 < len(d.model.equalities) <= 4:
        jacobian = sx.Matrix(_equality_jacobian(d.model))
        dets.append(linalg.det(jacobian * jacobian.T))
    # Where simplified_det's branch is simplify's, the reference's simplify is its answer.
    with remembered_simplify():
        for det in dets:
            # Compared on the engine: SymPy's Mul distributes a number over a sum as it is
            # built, so factor's c*(a + b) would not survive a crossing the other way.
            assert simplified_det(det) == from_sympy(sp.factor(sp.simplify(to_sympy(det))))


def test_the_determinant_simplification_knows_trigonometry_and_fractions() -> None:
    from tvopt_codegen.derivation.singularity import simplified_det

    v, x, q = sp.symbols("v x q", real=True)
    cases = [
        v * sp.cos(q) ** 2 + v * sp.sin(q) ** 2,
        (sp.cosh(x) ** 2 - sp.sinh(x) ** 2) * v,
        (x**2 - 1) / (x - 1),
        -sp.sin(q) * sp.cos(q + x) + sp.sin(q + x) * sp.cos(q),
    ]
    # Random 2 x 2 determinants of trigonometric entries: where trigsimp leaves some
    # trigonometry, simplify's form is kept (the short path's was longer in one of six).
    rng = np.random.default_rng(3)
    atoms = [sp.sin(q), sp.cos(q), sp.sin(q + x), sp.cos(q + x), v, x, sp.Integer(1)]
    for _ in range(4):
        entries = [
            sum(
                int(rng.choice([-1, 1, 2])) * atoms[rng.integers(7)] * atoms[rng.integers(7)]
                for _ in range(int(rng.integers(1, 3)))
            )
            for _ in range(4)
        ]
        cases.append(sp.Matrix(2, 2, entries).det(method="berkowitz"))
    # Each determinant enters as one of the engine (the derivation's are), and SymPy's
    # factor(simplify) crosses back to be compared on the engine. Where trigonometry
    # remains, simplified_det's branch asked SymPy for this very simplify(det) (a third of
    # this test's time): remembered, not worked out twice.
    with remembered_simplify():
        for det in cases:
            assert simplified_det(from_sympy(det)) == from_sympy(sp.factor(sp.simplify(det)))
    assert simplified_det(from_sympy(cases[0])) == from_sympy(v)
    assert simplified_det(from_sympy(cases[2])) == from_sympy(x + 1)


def test_one_circular_factor_is_what_simplify_leaves_alone() -> None:
    """The short path's monomials (an arm's l1*l2*sin(q2)): simplify gives them back."""
    from tvopt_codegen.derivation.singularity import _one_circular_factor, simplified_det

    rng = np.random.default_rng(11)
    # Real, as the derivation's symbols are (SymEngine's carry no assumptions).
    symbols = list(sp.symbols("l1 l2 m q1 q2 z", real=True))
    functions = [sp.sin, sp.cos, sp.tan, sp.sinh, sp.cosh, sp.tanh, sp.cot, sp.sec, sp.csc]
    for _ in range(30):
        chosen = rng.choice(len(symbols), size=int(rng.integers(0, 4)), replace=False)
        powers = sp.Mul(*(symbols[i] ** int(rng.integers(-2, 4)) for i in chosen))
        circular = functions[rng.integers(len(functions))](symbols[rng.integers(len(symbols))])
        expr = sp.Rational(int(rng.integers(1, 10)), int(rng.integers(1, 5))) * powers * circular
        assert _one_circular_factor(expr)  # SymPy's expression: a border helper
        assert simplified_det(from_sympy(expr)) == from_sympy(sp.factor(sp.simplify(expr)))
    q1, q2, l1 = symbols[3], symbols[4], symbols[0]
    # Two functions, a function of a sum, a sum: simplify decides.
    for expr in (sp.sin(q1) * sp.cos(q1), l1 * sp.sin(q1 + q2), sp.sin(q1) + l1):
        assert not _one_circular_factor(expr)


def test_a_time_limit_inside_the_command_lines_timer_keeps_that_timer() -> None:
    """time_limited interrupts a long call, then re-arms an outer timer with what is left;
    an outer timer that fires first is left to fire."""
    import signal
    import time

    from tvopt_codegen.derivation.meter import TimeLimitError, time_limited

    fired: list[float] = []

    def outer(_signum: int, _frame: object) -> None:
        fired.append(time.monotonic())

    previous = signal.signal(signal.SIGALRM, outer)
    try:
        start = time.monotonic()
        signal.setitimer(signal.ITIMER_REAL, 0.6)
        with pytest.raises(TimeLimitError), time_limited(0.1):
            while True:  # a long call that never returns by itself
                pass
        assert time.monotonic() - start < 0.4 and not fired
        remaining = signal.getitimer(signal.ITIMER_REAL)[0]
        assert 0.1 < remaining < 0.55
        while not fired and time.monotonic() - start < 3.0:
            time.sleep(0.01)
        assert fired and 0.5 < fired[0] - start < 1.5
        # The outer timer fires first: time_limited leaves it alone.
        fired.clear()
        signal.setitimer(signal.ITIMER_REAL, 0.05)
        with time_limited(5.0):
            time.sleep(0.2)
        assert fired
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, previous)
