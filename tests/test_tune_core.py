"""The pure core of ``tvopt-codegen tune``: space, requirements, optimisers."""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest

from tvopt_codegen.errors import SpecError
from tvopt_codegen.maths import hurwitz
from tvopt_codegen.tune.requirements import (
    PENALTY,
    Constraint,
    Objective,
    Requirements,
    failure_bound,
    parse_constraint,
    parse_objective,
    requirements_from,
    score,
    statistic,
)
from tvopt_codegen.tune.search import (
    Optimizer,
    cma_optimizer,
    random_optimizer,
)
from tvopt_codegen.tune.space import (
    MAX_PAIR_DAMPING,
    Candidate,
    Space,
    parse_range,
    rounded,
    space_for,
)
from tvopt_codegen.tune.spec_text import pole_items

# --- the space ----------------------------------------------------------------------------

#: Two real poles, two pairs and a bandwidth: d = 2 + 4 + 1 = 7.
POLES = [-1.0, -1.5, complex(-2, 1), complex(-2, -1), complex(-3, 2), complex(-3, -2)]


def _space(integral: bool = False) -> Space:
    return space_for(POLES, 20.0, integral=integral)


def _points(space: Space, count: int, seed: int = 0) -> list[np.ndarray]:
    """``count`` uniform points and every corner of the box."""
    rng = np.random.default_rng(seed)
    corners = [np.array(c, float) for c in itertools.product((0.0, 1.0), repeat=space.dimension)]
    return corners + list(rng.random((count, space.dimension)))


def test_the_defaults_come_from_the_spec() -> None:
    space = _space()
    assert (space.count, space.pairs, space.reals, space.dimension) == (6, 2, 2, 7)
    assert space.magnitude == pytest.approx((1.0 / 5, math.hypot(3, 2) * 5))
    assert space.min_damping == 0.3
    assert space.bandwidth == pytest.approx((2.0, 200.0))
    assert space_for([-1.0, -2.0], None, integral=False).dimension == 2
    # Poles from coefficients: the double root of (s + 1)^2 (s + 2) comes out of the
    # companion matrix as -1 +- 1e-8 j, and is still two real poles, not a pair.
    eigenvalues = hurwitz.eigenvalues(hurwitz.coefficients_from_poles([-1.0, -1.0, -2.0]))
    assert space_for([complex(v) for v in eigenvalues], None, integral=True).pairs == 0


@pytest.mark.parametrize("integral", [False, True])
def test_every_point_of_the_box_is_hurwitz_with_the_structure(integral: bool) -> None:
    space = _space(integral)
    lo, hi = space.magnitude
    for x in _points(space, 1000):
        candidate = space.decode(x)
        poles = candidate.poles
        assert len(poles) == 6
        assert all(p.real < 0 for p in poles)
        assert sum(1 for p in poles if p.imag > 0) == 2
        assert sum(1 for p in poles if p.imag < 0) == 2
        # The bounds hold up to the 4-digit rounding (5e-4 relative).
        assert all(lo * (1 - 5e-4) <= abs(p) <= hi * (1 + 5e-4) for p in poles)
        pairs = [p for p in poles if p.imag > 0]
        assert all(-p.real / abs(p) >= 0.3 - 1e-3 for p in pairs)
        assert all(-p.real / abs(p) <= MAX_PAIR_DAMPING + 1e-3 for p in pairs)
        assert candidate.bandwidth is not None
        assert 2.0 * (1 - 5e-4) <= candidate.bandwidth <= 200.0 * (1 + 5e-4)
        # H itself, from the coefficients the spec will derive.
        assert hurwitz.decay_rate(candidate.coefficients) > 0
        if integral:
            assert hurwitz.integral_split(candidate.coefficients, poles) is not None


def test_the_box_corners_are_the_bounds() -> None:
    space = space_for([-1.0, -2.0], 10.0, integral=False, magnitude=(0.5, 20.0))
    low = space.decode(np.zeros(3))
    high = space.decode(np.ones(3))
    assert low.poles == (-0.5 + 0j, -0.5 + 0j) and low.bandwidth == 1.0
    assert high.poles == (-20 + 0j, -20 + 0j) and high.bandwidth == 100.0
    # Beyond the box: clipped.
    assert space.decode(np.array([-3.0, 7.0, 0.5])) == space.decode(np.array([0.0, 1.0, 0.5]))


def test_decoding_rounds_to_four_significant_digits() -> None:
    space = space_for(
        [-1.0, complex(-1, 1), complex(-1, -1)],
        1.0,
        integral=False,
        magnitude=(1.0, 10.0),
        bandwidth_range=(1.0, 100.0),
    )
    # The real pole at 10^0.5 = 3.16227766..., the pair at w = 10^0.25 = 1.778279...
    # with zeta = 0.3 + 0.699 / 2 = 0.6495: re = -1.154993..., im = 1.352201...
    candidate = space.decode(np.array([0.5, 0.25, 0.5, 1 / 3]))
    w, zeta = 10**0.25, 0.3 + (MAX_PAIR_DAMPING - 0.3) / 2
    assert candidate.poles == (
        complex(-1.155, 1.352),
        complex(-1.155, -1.352),
        complex(-3.162, 0.0),
    )
    assert (-1.155, 1.352) == (rounded(-zeta * w), rounded(w * math.sqrt(1 - zeta**2)))
    assert candidate.bandwidth == 4.642  # 100^(1/3) = 4.6416
    assert pole_items(candidate.poles) == [(-1.155, 1.352), -3.162]
    # What the spec will say is what was evaluated: every number survives its printing.
    for x in _points(_space(), 200, seed=1):
        decoded = _space().decode(x)
        for p in decoded.poles:
            assert float(repr(p.real)) == p.real == rounded(p.real)
            assert rounded(p.imag) == p.imag
            assert len(repr(abs(p.real)).replace(".", "").strip("0")) <= 4


def test_the_spec_spelling_reads_back_to_the_same_poles() -> None:
    candidate = _space().decode(np.full(7, 0.3))
    back: list[complex] = []
    for entry in pole_items(candidate.poles):  # as settings.read_error_dynamics reads them
        if isinstance(entry, tuple):
            re, im = entry
            assert im > 0
            back += [complex(re, im), complex(re, -im)]
        else:
            back.append(complex(entry, 0.0))
    assert sorted(back, key=lambda p: (p.real, p.imag)) == sorted(
        candidate.poles, key=lambda p: (p.real, p.imag)
    )
    assert hurwitz.coefficients_from_poles(back) == candidate.coefficients


def test_permutations_of_a_point_give_the_same_candidate() -> None:
    space = _space()
    rng = np.random.default_rng(3)
    for _ in range(50):
        x = rng.random(7)
        swapped = x[[1, 0, 4, 5, 2, 3, 6]]  # the two reals, and the two pairs, exchanged
        assert space.decode(swapped) == space.decode(x)


def test_encode_inverts_decode() -> None:
    space = _space()
    for x in _points(space, 300, seed=2):
        candidate = space.decode(x)
        point = space.encode(candidate)
        assert point.shape == (7,) and np.all((point >= 0) & (point <= 1))
        assert space.decode(point) == candidate
        # The point itself comes back up to the rounding, in canonical order: the reals
        # sorted, the pairs by frequency (equal frequencies in either order).
        assert point[:2] == pytest.approx(sorted(x[:2]), abs=2e-3)
        assert point[6] == pytest.approx(x[6], abs=2e-3)
        given = {tuple(x[2:4]), tuple(x[4:6])}
        for pair in (point[2:4], point[4:6]):
            assert min(np.max(np.abs(pair - np.array(g))) for g in given) < 2e-3


def test_encode_fits_another_structure() -> None:
    # The spec's four real poles in a space with one pair: the two fastest join.
    space = space_for([-1.0, -1.5, -2.0, -2.5], None, integral=True, pairs=1)
    start = Candidate((-1.0 + 0j, -1.5 + 0j, -2.0 + 0j, -2.5 + 0j), None)
    decoded = space.decode(space.encode(start))
    assert [p for p in decoded.poles if p.imag == 0] == [-1.0 + 0j, -1.5 + 0j]
    pair = next(p for p in decoded.poles if p.imag > 0)
    assert abs(pair) == pytest.approx(math.sqrt(5.0), rel=1e-3)  # w^2 = 2 * 2.5
    assert -pair.real / abs(pair) == pytest.approx(MAX_PAIR_DAMPING, abs=1e-3)
    # A pair where the space has none: two real poles at its frequency.
    real = space_for([-1.0, -2.0], None, integral=False, pairs=0)
    back = real.decode(real.encode(Candidate((complex(-3, 4), complex(-3, -4)), None)))
    assert back.poles == (-5 + 0j, -5 + 0j)
    with pytest.raises(ValueError, match="expected 2 poles"):
        real.encode(Candidate((-1 + 0j,), None))


def test_integral_action_keeps_a_real_pole() -> None:
    space = space_for([-1.0] * 5, None, integral=True, pairs=2)
    for x in _points(space, 100):
        poles = space.decode(x).poles
        assert sum(1 for p in poles if p.imag == 0) == 1
    with pytest.raises(SpecError) as refused:
        space_for([-1.0] * 4, None, integral=True, pairs=2)
    assert str(refused.value) == (
        "command line: --complex-pairs: 2 pairs of 4 poles leave no real pole for integral action "
        "(at most 1)"
    )
    # Without integral action the same is allowed.
    assert space_for([-1.0] * 4, None, integral=False, pairs=2).reals == 0


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"magnitude": (-1.0, 5.0)}, "--pole-range: LO must be positive, got -1"),
        ({"magnitude": (0.0, 5.0)}, "--pole-range: LO must be positive, got 0"),
        ({"magnitude": (5.0, 5.0)}, "--pole-range: LO must be below HI, got 5:5"),
        ({"magnitude": (5.0, 1.0)}, "--pole-range: LO must be below HI, got 5:1"),
        ({"magnitude": (1.0, math.inf)}, "--pole-range: bounds must be finite, got 1:inf"),
        ({"magnitude": (math.nan, 1.0)}, "--pole-range: bounds must be finite, got nan:1"),
        (
            {"magnitude": (1e-20, 1.0)},
            "--pole-range: bounds must lie within 1e-09:1e+09 rad/s, got 1e-20:1",
        ),
        ({"min_damping": 0.0}, "--min-damping: must be in (0, 1], got 0"),
        ({"min_damping": 1.5}, "--min-damping: must be in (0, 1], got 1.5"),
        (
            {"min_damping": 1.0, "pairs": 1},
            "--min-damping: 1 leaves no complex pair (a pair's damping is below 0.999; at 1 it "
            "is a double real pole): lower it or use 0 complex pairs",
        ),
        ({"pairs": 4}, "--complex-pairs: 4 complex pairs need 8 poles; H has 6"),
        ({"pairs": -1}, "--complex-pairs: the number of pairs cannot be negative, got -1"),
        ({"bandwidth_range": (-1.0, 5.0)}, "--bandwidth-range: LO must be positive, got -1"),
        ({"bandwidth_range": (5.0, 2.0)}, "--bandwidth-range: LO must be below HI, got 5:2"),
    ],
)
def test_bounds_without_a_hurwitz_choice_are_refused(kwargs: dict, message: str) -> None:
    with pytest.raises(SpecError) as refused:
        space_for(POLES, 20.0, integral=False, **kwargs)
    assert str(refused.value) == f"command line: {message}"


def test_refusals_name_the_spec_field_and_an_absent_observer() -> None:
    with pytest.raises(SpecError) as refused:
        space_for(POLES, None, integral=False, bandwidth_range=(1.0, 2.0))
    assert str(refused.value) == (
        "command line: --bandwidth-range: the spec has no observer bandwidth to tune"
    )
    with pytest.raises(SpecError) as refused:
        space_for(
            POLES,
            20.0,
            integral=False,
            magnitude=(2.0, 1.0),
            field_prefix="tune.",
            source="arm.toml",
        )
    assert str(refused.value) == "arm.toml: tune.pole_range: LO must be below HI, got 2:1"
    # A damping of 1 is fine when there is no pair to give it, and means real poles only.
    assert space_for([-1.0, -2.0], None, integral=False, min_damping=1.0).pairs == 0
    real_only = space_for(POLES, None, integral=False, min_damping=1.0)
    assert (real_only.pairs, real_only.dimension) == (0, 6)
    assert all(p.imag == 0 for p in real_only.decode(np.full(6, 0.4)).poles)


def test_parse_range() -> None:
    assert parse_range("0.5:20", "--pole-range") == (0.5, 20.0)
    assert parse_range(" 1e-1 : 3 ", "--pole-range") == (0.1, 3.0)
    for text in ("5", "1:2:3", "a:b", ""):
        with pytest.raises(SpecError) as refused:
            parse_range(text, "--pole-range")
        assert str(refused.value) == (
            f"command line: --pole-range: expected LO:HI (two numbers), got {text!r}"
        )
    with pytest.raises(SpecError, match="expected finite numbers"):
        parse_range("1:inf", "--bandwidth-range")


# --- requirements ---------------------------------------------------------------------------


def _rows(
    errors: list[float], failed: frozenset[int] = frozenset(), **columns: list[float]
) -> list[dict]:
    rows = []
    for i, error in enumerate(errors):
        ok = i not in failed
        row = {
            "status": "ok" if ok else "diverged",
            "final_error": error if ok else math.nan,
            "max_error": 2 * error if ok else math.nan,
            "max_error_after": error / 2 if ok else math.nan,
            "integrated_error": 3 * error if ok else math.nan,
            "time_saturated": 0.0,
            "max_abs_u1": 1.0,
            "max_abs_u2": 1.0,
        }
        for name, values in columns.items():
            row[name] = values[i]
        rows.append(row)
    return rows


def test_statistics_are_order_statistics() -> None:
    values = [float(v) for v in range(20, 0, -1)]  # 20 .. 1, unsorted
    assert statistic(values, "median") == 10.0  # ceil(0.5 * 20) = 10th smallest
    assert statistic(values, "p90") == 18.0
    assert statistic(values, "p95") == 19.0
    assert statistic(values, "p99") == 20.0  # ceil(19.8) = 20th
    assert statistic(values, "max") == 20.0
    assert statistic(values, "mean") == 10.5
    # 100 values: p95 is exactly the 95th (no 0.95 * 100 = 95.00000000000001 slip).
    assert statistic(np.arange(1.0, 101.0), "p95") == 95.0
    assert statistic(np.arange(1.0, 101.0), "p99") == 99.0
    # Infinities: the mean is infinite, the p90 of 18 finite and 2 infinite is not.
    with_inf = [*range(1, 19), math.inf, math.inf]
    assert statistic(with_inf, "mean") == math.inf
    assert statistic(with_inf, "p90") == 18.0
    assert statistic(with_inf, "p95") == math.inf
    assert statistic([], "p95") == math.inf
    with pytest.raises(ValueError, match="NaN"):
        statistic([1.0, math.nan], "max")


def test_parse_objective() -> None:
    assert parse_objective("p95(final_error)", "--objective") == Objective("p95", "final_error")
    assert parse_objective(" mean ( integrated_error ) ", "--objective") == Objective(
        "mean", "integrated_error"
    )
    cases = {
        "p97(final_error)": "unknown statistic 'p97' (expected mean, median, p90, p95, p99 or max)",
        "p95(saturation)": "unknown objective metric 'saturation' (expected final_error, "
        "integrated_error or max_error)",
        "p95 final_error": "expected STAT(METRIC), e.g. p95(final_error), got 'p95 final_error'",
        "": "expected STAT(METRIC), e.g. p95(final_error), got ''",
    }
    for text, problem in cases.items():
        with pytest.raises(SpecError) as refused:
            parse_objective(text, "tune.objective", "arm.toml")
        assert str(refused.value) == f"arm.toml: tune.objective: {problem}"


def test_parse_constraint() -> None:
    def parse(text: str) -> Constraint:
        return parse_constraint(text, "--constraint", samples=100, inputs=("u1", "u2"))

    assert parse("failure_bound<=0.05") == Constraint("failure_bound", None, 0.05)
    assert parse(" p95( saturation ) <= 0.1 ") == Constraint("saturation", "p95", 0.1)
    assert parse("max(peak_input)<=3e1") == Constraint("peak_input", "max", 30.0)
    assert parse("p99(peak_u2) <= 4") == Constraint("peak_u2", "p99", 4.0)
    assert parse("median(max_error) <= 0.5").label == "median(max_error) <= 0.5"
    cases = {
        # 1 - 0.05^(1/100) = 2.95%; 1% needs ceil(ln 0.05 / ln 0.99) = 299 samples.
        "failure_bound <= 0.01": "failure_bound <= 0.01 can never hold with 100 samples (the "
        "bound with no failure is 0.02951; it needs at least 299 samples)",
        "failure_bound <= 0": "failure_bound <= 0 can never hold with 100 samples (the bound "
        "with no failure is 0.02951; it needs a bound above 0)",
        "p95(saturation) <= 1.5": "saturation is a fraction of the horizon, in [0, 1]; got a "
        "bound of 1.5",
        "p95(saturation) <= -0.1": "saturation is a fraction of the horizon, in [0, 1]; got a "
        "bound of -0.1",
        "max(peak_input) <= -1": "peak_input is never negative; a bound of -1 can never hold",
        "max(peak_u1) <= -1": "peak_u1 is never negative; a bound of -1 can never hold",
        "max(final_error) <= -1": "final_error is never negative; a bound of -1 can never hold",
        "max(peak_u9) <= 3": "'peak_u9': 'u9' is not an input (inputs: u1, u2)",
        "max(speed) <= 3": "unknown constraint metric 'speed' (expected final_error, "
        "integrated_error, max_error, saturation, peak_input or peak_<input>)",
        "p42(saturation) <= 0.1": "unknown statistic 'p42' (expected mean, median, p90, p95, "
        "p99 or max)",
        "p95(failure_bound) <= 0.1": "failure_bound is the sweep's, not a sample's: write "
        "'failure_bound <= V'",
        "p95(saturation) >= 0.1": "constraints are upper bounds, written with '<=', got '>='",
        "p95(saturation) <= abc": "expected a number after '<=', got 'abc'",
        "p95(saturation) <= nan": "expected a finite bound, got 'nan'",
        "p95(saturation)": "expected 'failure_bound <= V' or 'STAT(METRIC) <= V', got "
        "'p95(saturation)'",
        "saturation <= 0.1": "expected failure_bound or STAT(METRIC) before '<=', got 'saturation'",
    }
    for text, problem in cases.items():
        with pytest.raises(SpecError) as refused:
            parse(text)
        assert str(refused.value) == f"command line: --constraint: {problem}", text
        assert "\n" not in str(refused.value)
    # 299 samples suffice for the 1% bound above.
    assert parse_constraint("failure_bound <= 0.01", "c", samples=299, inputs=()).bound == 0.01


def test_requirements_from_the_table_and_the_command_line() -> None:
    table = {
        "objective": "median(max_error)",
        "constraints": ["failure_bound <= 0.5", "p95(saturation) <= 0.2"],
        "after": 2.0,
        "method": "cma",  # the command's key: not read here
    }
    common = {"samples": 50, "t_final": 10.0, "inputs": ("u1", "u2")}
    spec = requirements_from(table, "arm.toml", None, (), None, **common)
    assert spec == Requirements(
        Objective("median", "max_error"),
        (Constraint("failure_bound", None, 0.5), Constraint("saturation", "p95", 0.2)),
        2.0,
    )
    assert spec.column("max_error") == "max_error_after"
    assert spec.column("integrated_error") == "integrated_error"
    # The command line overrides item by item.
    cli = requirements_from(
        table, "arm.toml", "mean(final_error)", ["max(peak_u1) <= 3"], 0.0, **common
    )
    assert cli == Requirements(
        Objective("mean", "final_error"), (Constraint("peak_u1", "max", 3.0),), 0.0
    )
    assert cli.column("max_error") == "max_error"
    default = Requirements(Objective("p95", "final_error"), (), 0.0)
    assert requirements_from(None, "arm.toml", None, (), None, **common) == default
    # Spec.tune keeps a key left out as None (constraints as a tuple).
    unset = {"objective": None, "constraints": (), "after": None, "pole_range": None}
    assert requirements_from(unset, "arm.toml", None, (), None, **common) == default
    kept = {"objective": None, "constraints": ("max(peak_u1) <= 3",), "after": None}
    assert requirements_from(kept, "arm.toml", None, (), None, **common).constraints == (
        Constraint("peak_u1", "max", 3.0),
    )
    bad = {
        "tune.constraints[1]": ({"constraints": ["failure_bound <= 0.5", "p95(bogus) <= 1"]},),
        "tune.objective": ({"objective": 3},),
        "tune.constraints": ({"constraints": "p95(saturation) <= 0.1"},),
        "tune.after": ({"after": 10.0},),
    }
    for field, (bad_table,) in bad.items():
        with pytest.raises(SpecError) as refused:
            requirements_from(bad_table, "arm.toml", None, (), None, **common)
        assert str(refused.value).startswith(f"arm.toml: {field}: "), str(refused.value)
    with pytest.raises(SpecError) as refused:
        requirements_from(table, "arm.toml", None, (), -1.0, **common)
    assert str(refused.value) == (
        "command line: --after: the settling time must be in [0, t_final = 10), got -1"
    )


def test_scores_with_hand_computed_numbers() -> None:
    errors = [float(v) for v in range(1, 21)]
    saturated = [0.1 * v for v in range(20)]  # s; over t_final = 10: 0, 0.01, ..., 0.19
    rows = _rows(errors, time_saturated=saturated, max_abs_u2=[5.0] * 19 + [9.0])
    requirements = Requirements(
        Objective("p95", "final_error"),
        (
            Constraint("failure_bound", None, 0.2),
            Constraint("saturation", "p95", 0.2),
            Constraint("peak_input", "max", 10.0),
        ),
    )
    result = score(requirements, rows, 10.0, ("u1", "u2"))
    assert result.objective == 19.0
    # No failure in 20: 1 - 0.05^(1/20).
    assert result.constraints[0][1] == pytest.approx(1 - 0.05 ** (1 / 20), rel=1e-12)
    assert result.constraints[1] == ("p95(saturation) <= 0.2", pytest.approx(0.18), 0.2)
    assert result.constraints[2] == ("max(peak_input) <= 10", 9.0, 10.0)
    assert result.feasible
    assert result.value == pytest.approx(math.log10(19.0))

    # A constraint broken: 400 + log10(1 + (0.18 - 0.1) / 0.1).
    tight = Requirements(requirements.objective, (Constraint("saturation", "p95", 0.1),))
    broken = score(tight, rows, 10.0, ("u1", "u2"))
    assert not broken.feasible
    assert broken.value == pytest.approx(PENALTY + math.log10(1.8))
    tighter = Requirements(requirements.objective, (Constraint("saturation", "p95", 0.05),))
    assert score(tighter, rows, 10.0, ("u1", "u2")).value > broken.value > 308.3

    # The settled columns: max_error_after is error / 2 in these rows.
    settled = Requirements(Objective("max", "max_error"), (), after=1.0)
    assert score(settled, rows, 10.0, ("u1", "u2")).objective == 10.0
    assert score(Requirements(Objective("max", "max_error"), ()), rows, 10.0, ()).objective == 40


def test_failed_samples_are_infinite_errors() -> None:
    rows = _rows([float(v) for v in range(1, 21)], failed=frozenset({0, 1}))
    requirements = Requirements(Objective("p90", "final_error"), ())
    # 18 finite (3 .. 20) and 2 infinite: the 18th smallest is 20.
    assert score(requirements, rows, 10.0, ()).objective == 20.0
    p95 = score(Requirements(Objective("p95", "final_error"), ()), rows, 10.0, ())
    assert p95.objective == math.inf and not math.isinf(p95.value)
    assert p95.value == pytest.approx(PENALTY + 30 * 2 / 20)
    # Fewer failures rank better among infinite objectives.
    worse = score(
        Requirements(Objective("p95", "final_error"), ()),
        _rows([1.0] * 20, frozenset({0, 1, 2})),
        10.0,
        (),
    )
    assert worse.value > p95.value
    # The failure bound: 2 failures of 20, Beta(3, 18)'s 95% quantile.
    assert failure_bound(rows) == pytest.approx(0.2826, abs=1e-4)
    assert failure_bound([]) == 1.0
    # An unmeasured peak (NaN) is infinite: the constraint cannot hold.
    unmeasured = _rows([1.0, 2.0], max_abs_u1=[1.0, math.nan])
    peak = Requirements(Objective("max", "final_error"), (Constraint("peak_u1", "max", 5.0),))
    assert score(peak, unmeasured, 10.0, ("u1", "u2")).constraints[0][1] == math.inf
    assert score(peak, unmeasured, 10.0, ("u1", "u2")).value == pytest.approx(PENALTY + 30)


# --- optimisers ------------------------------------------------------------------------------


def _sphere(x: np.ndarray) -> float:
    """A shifted sphere, in log space as the tuner's scores are."""
    return math.log10(float(np.sum((x - np.array([0.3, 0.7, 0.2, 0.6])) ** 2)) + 1e-12)


def _rosenbrock(x: np.ndarray) -> float:
    z = 4.0 * x - 2.0  # [0, 1]^5 -> [-2, 2]^5, the minimum 0 at z = 1 (x = 0.75)
    return float(np.sum(100.0 * (z[1:] - z[:-1] ** 2) ** 2 + (1.0 - z[:-1]) ** 2))


def _minimise(optimizer: Optimizer, function, evaluations: int) -> list[tuple[np.ndarray, float]]:
    """Ask and tell until ``evaluations`` points: the history, in order."""
    history: list[tuple[np.ndarray, float]] = []
    while len(history) < evaluations:
        xs = optimizer.ask()
        values = [function(x) for x in xs]
        history += list(zip(xs, values, strict=True))
        optimizer.tell(xs, values)
    return history[:evaluations]


def _best(history: list[tuple[np.ndarray, float]]) -> tuple[np.ndarray, float]:
    return min(history, key=lambda item: item[1])


def test_optimisers_are_deterministic_and_leave_numpy_alone() -> None:
    def asks(make, seed: int, global_seed: int) -> list[np.ndarray]:
        np.random.seed(global_seed)
        before = np.random.get_state()[1].copy()
        history = _minimise(make(seed), _sphere, 30)
        assert np.array_equal(np.random.get_state()[1], before)  # numpy's global untouched
        return [x for x, _ in history]

    for make in (
        lambda seed: cma_optimizer(np.full(4, 0.5), seed, population=6),
        lambda seed: random_optimizer(4, seed, 6),
    ):
        first, again = asks(make, 7, 1), asks(make, 7, 2)
        assert all(np.array_equal(a, b) for a, b in zip(first, again, strict=True))
        other = asks(make, 8, 1)
        assert not np.array_equal(first[0], other[0])
        assert all(np.all((x >= 0) & (x <= 1)) for x in first)


def test_cma_optimises() -> None:
    history = _minimise(cma_optimizer(np.full(4, 0.5), seed=11, population=6), _sphere, 120)
    assert _best(history)[1] < -2.5  # |x - c| < 0.06 (from 0.42 at the start)


def test_cma_searches_a_single_pole() -> None:
    # One pole and no observer: d = 1, which cma handles (the integrator example's case).
    space = space_for([-1.0], None, integral=False)
    target = space.encode(Candidate((-2 + 0j,), None))
    history = _minimise(
        cma_optimizer(space.encode(Candidate((-1 + 0j,), None)), seed=4),
        lambda x: float(abs(x[0] - target[0])),
        80,
    )
    (pole,) = space.decode(_best(history)[0]).poles
    assert abs(pole + 2) <= 2e-3 and pole.imag == 0  # from -1, to the digits kept


def test_cma_beats_random_search_on_rosenbrock() -> None:
    cma_best, random_best = [], []
    for seed in range(5):
        # From x = 0.2 (z = -1.2, Rosenbrock's classic start): f = 2807 there.
        cma_best.append(_best(_minimise(cma_optimizer(np.full(5, 0.2), seed), _rosenbrock, 200))[1])
        random_best.append(_best(_minimise(random_optimizer(5, seed, 8), _rosenbrock, 200))[1])
    # Measured: CMA 3.2 .. 35 (median 9.3), random 34 .. 94 (median 50).
    assert all(c < r for c, r in zip(cma_best, random_best, strict=True))
    assert np.median(cma_best) < np.median(random_best) / 3
