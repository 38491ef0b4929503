"""The safe expression parser: what it builds, and what it refuses with a position."""

from __future__ import annotations

import math

import numpy as np
import pytest
import sympy as sp
from hypothesis import given, settings
from hypothesis import strategies as st

from tvopt_codegen import symbolic as sx
from tvopt_codegen.spec.parse import ExpressionError, parse_expression
from tvopt_codegen.symbolic.border import to_sympy

# The expected values below are SymPy's (the reference), built once; what the parser
# builds is of the engine in use and crosses the border to be compared.
x, y = sp.symbols("x y", real=True)


def _names() -> dict[str, sx.Expr]:
    """x and y on the engine in use, as a spec's names (built per test, never at import)."""
    return {"x": sx.symbol("x"), "y": sx.symbol("y")}


@pytest.mark.parametrize(
    ("text", "expected"),
    [
        ("x + 2*y", x + 2 * y),
        (
            "0.5 - 0.5*tanh((x - 10)/1.5)",
            sp.Rational(1, 2) - sp.tanh((x - 10) / sp.Rational(3, 2)) / 2,
        ),
        ("x**2 - -y", x**2 + y),
        ("atan2(y, x) + sqrt(x) + pi", sp.atan2(y, x) + sp.sqrt(x) + sp.pi),
        ("1e-8*tan(x*pi/4)**2", sp.Rational(1, 10**8) * sp.tan(x * sp.pi / 4) ** 2),
        ("  x +\n    y", x + y),
    ],
)
def test_parses_exactly(text: str, expected: sp.Expr) -> None:
    assert sp.simplify(to_sympy(parse_expression(text, _names())) - expected) == 0


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("__import__('os').system('true')", "cannot call \"__import__('os').system\""),
        ("__import__('os')", "cannot call '__import__'"),
        ("x.__class__", "attribute access is not allowed"),
        ("(lambda: 1)()", "cannot call"),
        ("lambda: 1", "lambda is not allowed"),
        ("[i for i in x]", "comprehensions are not allowed"),
        ("f'{x}'", "f-strings are not allowed"),
        ("x if y else 1", "conditional expressions are not allowed"),
        ("x < y", "comparisons are not allowed"),
        ("x and y", "logical operators are not allowed"),
        ("x[0]", "indexing is not allowed"),
        ("x^2", "'^' is not a power"),
        ("z + 1", "unknown name 'z'"),
        ("sin(x, y)", "sin() takes 1 argument(s), got 2"),
        ("sin(x=1)", "takes no keyword arguments"),
        ("abs(x)", "cannot call 'abs'"),
        ("2**2**2**2**2", "exponent 65536 exceeds 64"),
        ("x**100", "exponent 100 exceeds 64"),
        ("1e13*x", "exceeds"),
        ("1e400", "non-finite number"),
        ("x/0", "division by zero"),
        ("log(0)", "undefined"),
        ("x # comment", "comments are not allowed"),
        ("x + \u0443", "non-ASCII character"),
        ("(" * 200 + "x" + " + 1)" * 200, "nesting deeper than 60"),
        ("", "empty expression"),
        ("x +", "syntax error"),
        ("True", "unsupported literal"),
        ("sin", "used without arguments"),
    ],
)
def test_refuses_with_reason(text: str, message: str) -> None:
    with pytest.raises(ExpressionError) as info:
        parse_expression(text, _names())
    assert message in str(info.value)
    assert str(info.value).startswith("column ")


def test_position_points_at_the_problem() -> None:
    with pytest.raises(ExpressionError) as info:
        parse_expression("x + foo", _names())
    assert info.value.column == 5


def test_too_long_is_refused_quickly() -> None:
    with pytest.raises(ExpressionError, match="longer than 1000000 characters"):
        parse_expression("x+" * 500_001 + "x", _names())


def test_a_long_flat_sum_or_product_parses_with_exact_columns() -> None:
    names = _names()
    x, y = names["x"], names["y"]
    assert parse_expression("x+" * 3000 + "x", names) == 3001 * x
    product = parse_expression("*".join(["x", "y"] * 1500) + "/y", names)
    assert product == x**1500 * y**1499
    assert parse_expression("x - " * 1000 + "(x + y)", names) == -999 * x - y
    with pytest.raises(ExpressionError, match="column 4001: unknown name 'z'"):
        parse_expression("x + " * 1000 + "z", names)


_leaves = st.sampled_from(["x", "y", "2", "0.25", "3"])
_trees = st.recursive(
    _leaves,
    lambda inner: st.one_of(
        st.tuples(inner, st.sampled_from(["+", "-", "*"]), inner).map(
            lambda t: f"({t[0]} {t[1]} {t[2]})"
        ),
        st.tuples(st.sampled_from(["sin", "cos", "exp", "tanh"]), inner).map(
            lambda t: f"{t[0]}({t[1]})"
        ),
        inner.map(lambda s: f"-{s}"),
        inner.map(lambda s: f"({s})**2"),
    ),
    max_leaves=12,
)


@settings(max_examples=150, deadline=None)
@given(_trees, st.floats(-2, 2), st.floats(-2, 2))
def test_parse_agrees_with_python_arithmetic(text: str, xv: float, yv: float) -> None:
    """The parsed expression evaluates like the same text in plain Python math."""
    expr = to_sympy(parse_expression(text, _names()))
    env = {"x": xv, "y": yv, "sin": math.sin, "cos": math.cos, "exp": math.exp, "tanh": math.tanh}
    # eval here runs test-generated text, never spec input: it is the oracle.
    try:
        expected = eval(text, {"__builtins__": {}}, env)  # noqa: S307
    except OverflowError:
        return
    # Evaluated in SymPy to 30 digits: the parsed tree is exact, the oracle's doubles not.
    got = float(expr.xreplace({x: sp.Float(xv), y: sp.Float(yv)}).evalf(30))
    assert got == pytest.approx(expected, rel=1e-9, abs=1e-9)


# The short cut is SymPy's alone (it skips SymPy's assumptions queries; SymEngine has
# none and builds the function as it is): its subject is SymPy's own eval.
@pytest.mark.engine("sympy")
def test_trigonometry_of_a_multiple_of_pi_is_what_sympys_eval_gives() -> None:
    """The parser's short cut for sin, cos, tan of pi times a symbolic factor."""
    from tvopt_codegen.spec.folding import _trig_of_pi_multiple

    a, b, d = sp.symbols("a b d", real=True)
    k = sp.Symbol("k", positive=True)
    arguments = [
        ((a - b) ** 2 + (a + b) ** 2) * sp.pi / (2 * d),
        -sp.pi * a / 3,
        sp.pi * (b - a),
        sp.pi * (a - b),
        2 * sp.pi * k,
        sp.pi * sp.sin(a) * sp.exp(b),
        -sp.pi * a * b / (2 * k),
        sp.Rational(3, 2) * sp.pi * a,
    ]
    for func in (sp.sin, sp.cos, sp.tan):
        for arg in arguments:
            assert _trig_of_pi_multiple(func, arg) == func(arg), (func, arg)
    # Not a multiple of pi with a symbolic factor: sympy evaluates as usual.
    n = sp.Symbol("n", integer=True)
    for arg in (sp.pi / 4, a + sp.pi, sp.pi**2 * a, sp.I * sp.pi * a, sp.pi * n, a):
        assert _trig_of_pi_multiple(sp.tan, arg) is None
    assert _trig_of_pi_multiple(sp.exp, sp.pi * a) is None


@pytest.mark.engine("sympy")
def test_a_rings_barrier_parses_as_sympy_would_build_it() -> None:
    from tvopt_codegen.spec import load_spec

    spec = load_spec("unicycle_ring")
    tans = [e for e in sp.preorder_traversal(spec.objective) if isinstance(e, sp.tan)]
    assert len(tans) == 4
    for term in tans:
        assert sp.tan(term.args[0]) == term
    names = {n: sp.Symbol(n, real=True) for n in ("px", "py", "d")}
    parsed = parse_expression("tan(-(px - py)**2*pi/(2*d)) + cos(-pi*px/d)", names)
    px, py, d = names.values()
    assert parsed == sp.tan(-((px - py) ** 2) * sp.pi / (2 * d)) + sp.cos(-sp.pi * px / d)


#: The arguments of the trigonometry tests, as a spec writes them and as SymPy builds them.
_PI_MULTIPLES = (
    ("((a - b)**2 + (a + b)**2)*pi/(2*d)", "((a - b)**2 + (a + b)**2)*pi/(2*d)"),
    ("-pi*a/3", "-pi*a/3"),
    ("pi*(b - a)", "pi*(b - a)"),
    ("2*pi*d", "2*pi*d"),
    ("pi*sin(a)*exp(b)", "pi*sin(a)*exp(b)"),
    ("-pi*a*b/(2*d)", "-pi*a*b/(2*d)"),
    ("1.5*pi*a", "3*pi*a/2"),
    ("pi/4 + a", "pi/4 + a"),
)


def test_trigonometry_of_a_multiple_of_pi_has_sympys_value_on_the_default_engine() -> None:
    """The same functions of pi times a factor, parsed on the default engine: the value
    SymPy's own function of the same argument has, at points of either sign."""
    names = {n: sx.symbol(n) for n in ("a", "b", "d")}
    reference = {n: sp.Symbol(n, real=True) for n in names}
    rng = np.random.default_rng(7)
    points = [
        {n: float(v) for n, v in zip(names, rng.uniform(-2, 2, size=3), strict=True)}
        for _ in range(4)
    ]
    for func in ("sin", "cos", "tan"):
        for text, built in _PI_MULTIPLES:
            ours = to_sympy(parse_expression(f"{func}({text})", names))
            theirs = getattr(sp, func)(sp.sympify(built, locals=reference))
            for point in points:
                at = {reference[n]: sp.Float(v) for n, v in point.items()}
                got, want = float(ours.xreplace(at).evalf(30)), float(theirs.xreplace(at).evalf(30))
                assert got == pytest.approx(want, rel=1e-12, abs=1e-12), (func, text, point)


def test_a_rings_barrier_parses_to_its_functions_on_the_default_engine() -> None:
    """The ring's four barriers are tangents of the engine as its constructor builds
    them, and a barrier's text parses to the expression built by hand."""
    from tvopt_codegen.spec import load_spec

    spec = load_spec("unicycle_ring")
    tans = spec.objective.atoms(sx.tan)
    assert len(tans) == 4
    for term in tans:
        assert sx.tan(term.args[0]) == term
    names = {n: sx.symbol(n) for n in ("px", "py", "d")}
    parsed = parse_expression("tan(-(px - py)**2*pi/(2*d)) + cos(-pi*px/d)", names)
    px, py, d = names.values()
    built = sx.tan(-((px - py) ** 2) * sx.pi / (2 * d)) + sx.cos(-sx.pi * px / d)
    assert parsed == built


@pytest.mark.parametrize("count", [1, 199, 200, 3000, 100_000])
def test_redundant_parentheses_are_flat(count: int) -> None:
    # Python's tokenizer stops at 200 open parentheses; these add no node at all.
    names = _names()
    x, y = names["x"], names["y"]
    around = "(" * count + "x" + ")" * count
    assert parse_expression(around, names) == x
    assert parse_expression(f"sin({around})**2 + ( ({around}) )*y", names) == (
        sx.sin(x) ** 2 + x * y
    )


def test_removing_redundant_parentheses_keeps_columns_and_tuples() -> None:
    with pytest.raises(ExpressionError) as info:
        parse_expression("((((x + zz))))", _names())
    assert (info.value.column, info.value.message) == (9, "unknown name 'zz'")
    # (y, x) is one argument, a tuple, however many parentheses wrap it.
    with pytest.raises(ExpressionError, match=r"atan2\(\) takes 2 argument\(s\), got 1"):
        parse_expression("atan2(((y, x)))", _names())
    names = _names()
    assert parse_expression("((x) + 1)*((y))", names) == (names["x"] + 1) * names["y"]


@pytest.mark.parametrize("depth", [61, 300, 3000])
def test_truly_deep_parentheses_are_refused_as_nesting(depth: int) -> None:
    # Each pair holds a sum: nothing here is redundant.
    with pytest.raises(ExpressionError, match="nesting deeper than 60"):
        parse_expression("(" * depth + "x" + " + 1)" * depth, _names())
    assert parse_expression("(" * 50 + "x" + " + 1)" * 50, _names()) == _names()["x"] + 50


def test_a_misspelt_name_gets_the_nearest_known_one() -> None:
    theta, omega = sx.symbols(["theta", "omega"])
    names = {"theta": theta, "omega": omega}
    with pytest.raises(ExpressionError) as info:
        parse_expression("omega*cos(thetta)", names)
    assert str(info.value) == "column 11: unknown name 'thetta': did you mean 'theta'?"
    with pytest.raises(ExpressionError) as info:
        parse_expression("2*p", names)
    assert str(info.value) == "column 3: unknown name 'p'"
    # pi is a name too; a 10,000-character name is no typo and is not compared.
    with pytest.raises(ExpressionError, match="did you mean 'pi'"):
        parse_expression("sin(pii)", names)
    with pytest.raises(ExpressionError) as info:
        parse_expression("theta" * 2000, names)
    assert "did you mean" not in str(info.value)


@settings(max_examples=100, deadline=None)
@given(_trees, st.lists(st.integers(0, 400), min_size=1, max_size=6))
def test_doubling_parentheses_changes_nothing(text: str, counts: list[int]) -> None:
    """Any pair doubled any number of times is the same expression, past Python's 200."""
    # Double the outermost pair and some inner ones: each "(" at index i with its ")".
    closing: dict[int, int] = {}
    stack: list[int] = []
    for index, char in enumerate(text):
        if char == "(":
            stack.append(index)
        elif char == ")":
            closing[stack.pop()] = index
    chosen = sorted(closing)[: len(counts)]
    extra_open = {start: count for start, count in zip(chosen, counts, strict=False)}
    extra_close = {closing[start]: count for start, count in extra_open.items()}
    wrapped = "".join(
        "(" * extra_open.get(i, 0) + ch + ")" * extra_close.get(i, 0) for i, ch in enumerate(text)
    )
    outer = counts[0]
    wrapped = "(" * outer + wrapped + ")" * outer
    assert parse_expression(wrapped, _names()) == parse_expression(text, _names())


@pytest.mark.parametrize("engine_name", ["symengine", "sympy"])
def test_a_difference_multiplies_its_minus_into_a_sum_as_sympy_does(engine_name: str) -> None:
    """x - (x + y) is -y, whether the text is parsed whole or, past 2,000 characters, as
    a chain of pieces (hypothesis found SymEngine's whole parse keeping x - (x + y)
    where the chain wrote -y); a product keeps its sum, as in SymPy."""
    with sx.using(engine_name):
        x, y = sx.symbols(["x", "y"])
        names = {"x": x, "y": y}
        deep = "(" * 1000 + "x - (x + y)" + ")" * 1000
        assert len(deep) > 2000
        assert parse_expression("x - (x + y)", names) == -y
        assert parse_expression(deep, names) == -y
        assert parse_expression("1 - 2*(x - y)", names) == 1 - 2 * x + 2 * y
        kept = parse_expression("x - x*(x + y)", names)
        assert kept == x - x * (x + y) and kept != x - x**2 - x * y
