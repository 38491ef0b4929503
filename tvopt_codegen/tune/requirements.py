"""What ``tune`` minimises and what it must keep: requirements as the user says them.

An objective ``STAT(METRIC)`` (``p95(final_error)``) and constraints ``failure_bound <=
V``, ``STAT(saturation) <= V``, ``STAT(peak_input) <= V``, ``STAT(peak_<input>) <= V``
or ``STAT(<error metric>) <= V``, read from the command line or a spec's ``[tune]``
table, checked against what the sweep can ever show, and scored on a sweep's rows.

Statistics are over samples, by an order statistic (the nearest rank: ``pQ`` is the
``ceil(Q n / 100)``-th smallest of ``n``), deterministic and exact with infinities: a
failed sample counts as ``+inf`` in every error metric, so ``p95`` is infinite when more
than 5% of the samples fail.
"""

from __future__ import annotations

import math
import re
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from tvopt_codegen.errors import SpecError
from tvopt_codegen.sweep.results import clopper_pearson_upper

#: The statistics over samples, and the percentile each takes (None: the mean).
STATISTICS: dict[str, int | None] = {
    "mean": None,
    "median": 50,
    "p90": 90,
    "p95": 95,
    "p99": 99,
    "max": 100,
}

#: The error metrics (an objective's, or a constraint's) and their sweep columns without
#: and with a settling time ``after``: ``max_error_after`` and ``integrated_error`` are
#: the sweep's, measured from ``after`` (the integrated error from 0 when it is 0).
ERROR_METRICS: dict[str, tuple[str, str]] = {
    "final_error": ("final_error", "final_error"),
    "integrated_error": ("integrated_error", "integrated_error"),
    "max_error": ("max_error", "max_error_after"),
}

#: The constraint on the failure probability: its Clopper-Pearson 95% upper bound.
FAILURE_BOUND = "failure_bound"
#: The fraction of the horizon with an input clipped (``time_saturated / t_final``).
SATURATION = "saturation"
#: The largest ``|u_j|`` over the run and over the inputs; ``peak_<input>``: of one input.
PEAK_INPUT = "peak_input"
PEAK_PREFIX = "peak_"

#: Default objective.
DEFAULT_OBJECTIVE = "p95(final_error)"

#: The keys of a spec's ``[tune]`` table that this module reads (the command knows the rest).
REQUIREMENT_KEYS = ("objective", "constraints", "after")

#: ``value`` of a candidate that breaks a constraint, or whose objective is infinite, is
#: at least this: above the log10 of every finite double (308.3), the largest feasible.
PENALTY = 400.0
#: A penalty term's largest contribution (an infinite violation).
VIOLATION_CAP = 30.0
#: Below this bound a violation is measured relative to it instead (a bound of 0).
BOUND_FLOOR = 1e-12
#: log10 of an objective of 0 would be -inf: objectives are taken at least this.
OBJECTIVE_FLOOR = 1e-300

_CALL = re.compile(r"\s*([A-Za-z_]\w*)\s*\(\s*([A-Za-z_]\w*)\s*\)\s*")
_CONSTRAINT = re.compile(r"\s*(.*?)\s*(<=|>=|<|>|==|=)\s*(.*?)\s*")


@dataclass(frozen=True)
class Objective:
    """``STAT(METRIC)`` over the sweep's samples, to be minimised.

    Attributes
    ----------
    statistic : str
        One of :data:`STATISTICS`.
    metric : str
        One of :data:`ERROR_METRICS`.
    """

    statistic: str
    metric: str

    @property
    def label(self) -> str:
        """The canonical spelling, ``p95(final_error)``."""
        return f"{self.statistic}({self.metric})"


@dataclass(frozen=True)
class Constraint:
    """``STAT(METRIC) <= bound``, or ``failure_bound <= bound``.

    Attributes
    ----------
    metric : str
        ``failure_bound``, ``saturation``, ``peak_input``, ``peak_<input>`` or an error
        metric.
    statistic : str or None
        One of :data:`STATISTICS`; None for ``failure_bound`` (a property of the sweep,
        not of a sample).
    bound : float
        The largest value allowed.
    """

    metric: str
    statistic: str | None
    bound: float

    @property
    def label(self) -> str:
        """The canonical spelling, ``p95(saturation) <= 0.1``."""
        left = self.metric if self.statistic is None else f"{self.statistic}({self.metric})"
        return f"{left} <= {self.bound:g}"


@dataclass(frozen=True)
class Requirements:
    """An objective, constraints, and the settling time the error metrics start from.

    Attributes
    ----------
    objective : Objective
    constraints : tuple of Constraint
    after : float
        Settling time, s: ``max_error`` and ``integrated_error`` are measured from it
        (0: over the whole horizon).
    """

    objective: Objective
    constraints: tuple[Constraint, ...]
    after: float = 0.0

    def column(self, metric: str) -> str:
        """The sweep column of an error metric, given :attr:`after`."""
        plain, settled = ERROR_METRICS[metric]
        return settled if self.after > 0 else plain


@dataclass(frozen=True)
class Score:
    """How well one candidate's sweep meets the requirements.

    Attributes
    ----------
    objective : float
        The objective's value (``inf`` when too many samples failed).
    constraints : tuple of (str, float, float)
        ``(label, value, bound)`` of each constraint, in the requirements' order.
    feasible : bool
        Every constraint holds (``value <= bound``).
    value : float
        What the optimiser minimises, always finite (see :func:`score`).
    """

    objective: float
    constraints: tuple[tuple[str, float, float], ...]
    feasible: bool
    value: float


def _choices(names: Sequence[str]) -> str:
    return ", ".join(names[:-1]) + f" or {names[-1]}" if len(names) > 1 else names[0]


def _statistic(name: str, fail: Callable[[str], SpecError]) -> str:
    if name not in STATISTICS:
        raise fail(f"unknown statistic {name!r} (expected {_choices(list(STATISTICS))})")
    return name


def parse_objective(text: str, field: str, source: str = "command line") -> Objective:
    """Read ``STAT(METRIC)``.

    Parameters
    ----------
    text : str
        E.g. ``"p95(final_error)"`` or ``"mean( integrated_error )"``.
    field : str
        The option or spec field, for errors (``--objective``, ``tune.objective``).
    source : str
        ``"command line"`` or the spec file.

    Raises
    ------
    SpecError
        One line: malformed text, an unknown statistic or metric.
    """

    def fail(problem: str) -> SpecError:
        return SpecError(source, field, problem)

    match = _CALL.fullmatch(text)
    if match is None:
        raise fail(f"expected STAT(METRIC), e.g. {DEFAULT_OBJECTIVE}, got {text!r}")
    statistic, metric = _statistic(match.group(1), fail), match.group(2)
    if metric not in ERROR_METRICS:
        raise fail(
            f"unknown objective metric {metric!r} (expected {_choices(list(ERROR_METRICS))})"
        )
    return Objective(statistic, metric)


def parse_constraint(
    text: str,
    field: str,
    *,
    samples: int,
    inputs: Sequence[str] = (),
    source: str = "command line",
) -> Constraint:
    """Read ``failure_bound <= V`` or ``STAT(METRIC) <= V`` and check it can ever hold.

    Parameters
    ----------
    text : str
        The constraint; spaces optional.
    field : str
        The option or spec field, for errors (``--constraint``, ``tune.constraints[1]``).
    samples : int
        Samples per sweep: with ``n`` of them the failure bound is never below
        ``1 - 0.05^(1/n)`` (no failure at all).
    inputs : sequence of str, optional
        The plant's inputs, for ``peak_<input>`` (none: every ``peak_<input>`` is refused).
    source : str
        ``"command line"`` or the spec file.

    Raises
    ------
    SpecError
        One line: malformed text, another comparison than ``<=``, an unknown statistic,
        metric or input, or a bound that can never hold (a failure bound below the
        smallest the sample count allows, a saturation outside [0, 1], a negative peak
        or error).
    """

    def fail(problem: str) -> SpecError:
        return SpecError(source, field, problem)

    match = _CONSTRAINT.fullmatch(text)
    if match is None:
        raise fail(f"expected 'failure_bound <= V' or 'STAT(METRIC) <= V', got {text!r}")
    left, operator, right = match.groups()
    if operator != "<=":
        raise fail(f"constraints are upper bounds, written with '<=', got {operator!r}")
    try:
        bound = float(right)
    except ValueError:
        raise fail(f"expected a number after '<=', got {right!r}") from None
    if not math.isfinite(bound):
        raise fail(f"expected a finite bound, got {right!r}")

    if left == FAILURE_BOUND:
        smallest = clopper_pearson_upper(0, samples)
        if smallest > bound:
            raise fail(
                f"failure_bound <= {bound:g} can never hold with {samples} samples (the bound "
                f"with no failure is {smallest:.4g}; it needs {_samples_for(bound)})"
            )
        return Constraint(FAILURE_BOUND, None, bound)

    call = _CALL.fullmatch(left)
    if call is None:
        raise fail(f"expected failure_bound or STAT(METRIC) before '<=', got {left!r}")
    statistic, metric = _statistic(call.group(1), fail), call.group(2)
    if metric == FAILURE_BOUND:
        raise fail("failure_bound is the sweep's, not a sample's: write 'failure_bound <= V'")
    if metric == SATURATION:
        if not 0 <= bound <= 1:
            raise fail(
                f"saturation is a fraction of the horizon, in [0, 1]; got a bound of {bound:g}"
            )
    elif metric == PEAK_INPUT or metric in ERROR_METRICS:
        if bound < 0:
            raise fail(f"{metric} is never negative; a bound of {bound:g} can never hold")
    elif metric.startswith(PEAK_PREFIX):
        name = metric[len(PEAK_PREFIX) :]
        if name not in inputs:
            known = ", ".join(inputs) if inputs else "none"
            raise fail(f"{metric!r}: {name!r} is not an input (inputs: {known})")
        if bound < 0:
            raise fail(f"{metric} is never negative; a bound of {bound:g} can never hold")
    else:
        names = [*ERROR_METRICS, SATURATION, PEAK_INPUT, "peak_<input>"]
        raise fail(f"unknown constraint metric {metric!r} (expected {_choices(names)})")
    return Constraint(metric, statistic, bound)


def _samples_for(bound: float) -> str:
    """The samples a failure bound needs: ``1 - 0.05^(1/n) <= bound``."""
    if bound <= 0:
        return "a bound above 0"
    if bound >= 1:
        return "1 sample"
    n = math.ceil(math.log(0.05) / math.log1p(-bound))
    return f"at least {n} samples"


def requirements_from(
    table: Mapping[str, Any] | None,
    source: str,
    objective: str | None,
    constraints: Sequence[str],
    after: float | None,
    *,
    samples: int,
    t_final: float,
    inputs: Sequence[str],
) -> Requirements:
    """The requirements from a spec's ``[tune]`` table and the command line.

    The command line overrides the table, item by item: ``--objective`` its
    ``objective``, any ``--constraint`` all of its ``constraints``, ``--after`` its
    ``after``. Without either: :data:`DEFAULT_OBJECTIVE`, no constraint, ``after = 0``.

    Parameters
    ----------
    table : mapping or None
        The spec's ``[tune]`` table (keys :data:`REQUIREMENT_KEYS` are read, others are
        the command's); a key whose value is None counts as left out.
    source : str
        The spec file, for errors about the table.
    objective : str or None
        ``--objective``.
    constraints : sequence of str
        ``--constraint``, each one.
    after : float or None
        ``--after``, s.
    samples : int
        Samples per sweep (a failure bound must be reachable with them).
    t_final : float
        The sweep's horizon, s (``after`` must be below it).
    inputs : sequence of str
        The plant's inputs.

    Returns
    -------
    Requirements

    Raises
    ------
    SpecError
        One line naming the option (``--objective``, ``--constraint``, ``--after``) or
        the field (``tune.objective``, ``tune.constraints[1]``, ``tune.after``).
    """
    # A key set to None (or an empty list) is one left out, as Spec.tune keeps them.
    table = {key: value for key, value in (table or {}).items() if value is not None}
    cli = "command line"
    if objective is not None:
        goal = parse_objective(objective, "--objective", cli)
    elif "objective" in table:
        text = table["objective"]
        if not isinstance(text, str):
            raise SpecError(source, "tune.objective", f"expected a string, got {text!r}")
        goal = parse_objective(text, "tune.objective", source)
    else:
        goal = parse_objective(DEFAULT_OBJECTIVE, "--objective", cli)

    limits: list[Constraint] = []
    if constraints:
        for text in constraints:
            limits.append(
                parse_constraint(text, "--constraint", samples=samples, inputs=inputs, source=cli)
            )
    elif "constraints" in table:
        entries = table["constraints"]
        if not isinstance(entries, list | tuple):
            raise SpecError(
                source, "tune.constraints", f"expected a list of strings, got {entries!r}"
            )
        for index, text in enumerate(entries):
            field = f"tune.constraints[{index}]"
            if not isinstance(text, str):
                raise SpecError(source, field, f"expected a string, got {text!r}")
            limits.append(
                parse_constraint(text, field, samples=samples, inputs=inputs, source=source)
            )

    if after is not None:
        settle, where, origin = after, "--after", cli
    else:
        settle, where, origin = table.get("after", 0.0), "tune.after", source
    if isinstance(settle, bool) or not isinstance(settle, int | float):
        raise SpecError(origin, where, f"expected a number of seconds, got {settle!r}")
    settle = float(settle)
    if not (math.isfinite(settle) and 0 <= settle < t_final):
        raise SpecError(
            origin,
            where,
            f"the settling time must be in [0, t_final = {t_final:g}), got {settle:g}",
        )
    return Requirements(goal, tuple(limits), settle)


def _is_ok(row: Mapping[str, Any]) -> bool:
    return row.get("status") == "ok"


def failure_bound(rows: Sequence[Mapping[str, Any]]) -> float:
    """The Clopper-Pearson 95% upper bound on the failure probability of ``rows``.

    A failure is any status but ``ok``; no rows give 1.
    """
    failures = sum(1 for row in rows if not _is_ok(row))
    return clopper_pearson_upper(failures, len(rows))


def statistic(values: Sequence[float] | np.ndarray, name: str) -> float:
    """``name`` (one of :data:`STATISTICS`) of ``values``, inf-safe and deterministic.

    A percentile is the nearest-rank order statistic: the ``ceil(Q n / 100)``-th smallest
    (in integers, no rounding of ``0.95 n``); the mean is infinite when a value is.
    No values give ``inf`` (nothing was shown).
    """
    data = np.sort(np.asarray(values, dtype=float))
    if not len(data):
        return math.inf
    if np.isnan(data).any():
        raise ValueError("a statistic of NaN: map unmeasured samples to +inf first")
    percent = STATISTICS[name]
    if percent is None:
        return float(np.mean(data)) if np.all(np.isfinite(data)) else math.inf
    rank = -(-percent * len(data) // 100)  # ceil(percent n / 100), at least 1
    return float(data[max(rank, 1) - 1])


def _measured(value: Any) -> float:
    """A sample's number; not measured (None, NaN) counts as +inf."""
    if value is None:
        return math.inf
    number = float(value)
    return math.inf if math.isnan(number) else number


def metric_values(
    requirements: Requirements,
    metric: str,
    rows: Sequence[Mapping[str, Any]],
    t_final: float,
    inputs: Sequence[str],
) -> np.ndarray:
    """One value per sample of ``metric``, as the statistics read it.

    Error metrics are ``+inf`` for a failed sample; saturation and peaks are what the
    sample measured up to its end (``+inf`` when it measured nothing).
    """
    if metric in ERROR_METRICS:
        column = requirements.column(metric)
        return np.array(
            [_measured(row.get(column)) if _is_ok(row) else math.inf for row in rows], float
        )
    if metric == SATURATION:
        return np.array([_measured(row.get("time_saturated")) / t_final for row in rows], float)
    names = inputs if metric == PEAK_INPUT else (metric[len(PEAK_PREFIX) :],)
    return np.array(
        [
            max((_measured(row.get(f"max_abs_{n}")) for n in names), default=math.inf)
            for row in rows
        ],
        float,
    )


def _violation(value: float, bound: float) -> float:
    """``min(CAP, log10(1 + (value - bound)^+ / max(bound, floor)))``: 0 when it holds."""
    if value <= bound:
        return 0.0
    if math.isinf(value):
        return VIOLATION_CAP
    excess = (value - bound) / max(bound, BOUND_FLOOR)
    return min(VIOLATION_CAP, math.log10(1.0 + excess))


def score(
    requirements: Requirements,
    rows: Sequence[Mapping[str, Any]],
    t_final: float,
    inputs: Sequence[str],
) -> Score:
    """Score one candidate's sweep.

    ``value``, what the optimiser minimises, is always finite:

    - feasible and a finite objective ``J``: ``log10(max(J, 1e-300))``, at most 308.3;
    - otherwise ``PENALTY + sum_i v_i + CAP u`` with ``PENALTY = 400`` (above every
      feasible value), ``v_i = min(CAP, log10(1 + (c_i - b_i)^+ / max(b_i, 1e-12)))``
      the violation of constraint ``i`` (value ``c_i``, bound ``b_i``; ``CAP = 30`` for
      an infinite one) and ``u`` the fraction of samples whose objective metric is
      infinite (failed). A candidate that breaks its constraints less, or fails in fewer
      samples, ranks better; among feasible ones only ``J`` counts.

    Parameters
    ----------
    requirements : Requirements
    rows : sequence of mapping
        The sweep's summary rows (``status``, the error columns, ``time_saturated``,
        ``max_abs_<input>``).
    t_final : float
        The sweep's horizon, s (saturation is ``time_saturated / t_final``).
    inputs : sequence of str
        The plant's inputs (``peak_input`` is the largest of their peaks).

    Returns
    -------
    Score
    """
    goal = requirements.objective
    errors = metric_values(requirements, goal.metric, rows, t_final, inputs)
    objective = statistic(errors, goal.statistic)
    results: list[tuple[str, float, float]] = []
    for constraint in requirements.constraints:
        if constraint.statistic is None:
            value = failure_bound(rows)
        else:
            values = metric_values(requirements, constraint.metric, rows, t_final, inputs)
            value = statistic(values, constraint.statistic)
        results.append((constraint.label, value, constraint.bound))
    feasible = all(value <= bound for _, value, bound in results)
    if feasible and math.isfinite(objective):
        scalar = math.log10(max(objective, OBJECTIVE_FLOOR))
    else:
        unmeasured = float(np.mean(np.isinf(errors))) if len(errors) else 1.0
        scalar = PENALTY + sum(_violation(v, b) for _, v, b in results) + VIOLATION_CAP * unmeasured
    return Score(objective, tuple(results), feasible, scalar)
