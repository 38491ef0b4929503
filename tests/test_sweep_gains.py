"""The sweep's run-time gains: one compiled loop, many candidates (what ``tune`` searches).

A candidate (``SweepProgram.with_gains``) runs on the library compiled for the spec's
gains, and its rows are those of the spec rewritten with the candidate's poles and
bandwidth and compiled anew, bit for bit; each thread runs with its own gains.
"""

from __future__ import annotations

import dataclasses
import functools
import math
import threading
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from tests.conftest import ROOT, SPECS
from tvopt_codegen.derivation import derive
from tvopt_codegen.errors import SpecError
from tvopt_codegen.lowering.ir import lower
from tvopt_codegen.maths import hurwitz
from tvopt_codegen.spec.files import parse_spec
from tvopt_codegen.sweep import (
    Distribution,
    SweepOptions,
    SweepProgram,
    loop_for,
    run_sample,
    sweep_program,
)
from tvopt_codegen.sweep.program import check_options, compiled_sources
from tvopt_codegen.sweep.table import failed_row

PVTOL = ROOT / "tvopt_codegen" / "examples" / "pvtol.toml"
ROBUST = SPECS / "robust_pvtol.toml"

#: The candidates: each spec's poles (and observer bandwidth) rewritten in its text.
PVTOL_POLES = (-2.0, -3.0, -4.0, -5.0)
ROBUST_POLES = (-2.0, -2.5, -3.0, -3.5, -4.0)
ROBUST_BANDWIDTH = 35.0


@functools.cache
def program(path: Path, edits: tuple[tuple[str, str], ...] = (), precision: str = "double") -> Any:
    """The sweep program of the spec at ``path`` with ``edits`` (old, new) made to its text."""
    text = path.read_text(encoding="utf-8")
    for old, new in edits:
        assert old in text
        text = text.replace(old, new)
    spec = parse_spec(str(path), text.encode("utf-8"))
    return sweep_program(lower(derive(spec)), precision)


def _pvtol_edits() -> tuple[tuple[str, str], ...]:
    return (("poles = [-1.0, -1.5, -2.0, -2.5]", f"poles = {list(PVTOL_POLES)}"),)


def _robust_edits() -> tuple[tuple[str, str], ...]:
    return (
        ("poles = [-1.0, -1.5, -2.0, -2.5, -3.0]", f"poles = {list(ROBUST_POLES)}"),
        ("bandwidth = 20.0", f"bandwidth = {ROBUST_BANDWIDTH}"),
    )


def _candidate(base: SweepProgram, poles: tuple[float, ...], bandwidth: float | None) -> Any:
    return base.with_gains(hurwitz.coefficients_from_poles(poles), bandwidth, poles=poles)


def _same(a: dict[str, Any], b: dict[str, Any]) -> bool:
    """Rows equal column by column, NaN equal to NaN."""
    if a.keys() != b.keys():
        return False
    return all(
        x == y
        or (isinstance(x, float) and isinstance(y, float) and math.isnan(x) and math.isnan(y))
        for x, y in ((a[k], b[k]) for k in a)
    )


def _rows(p: SweepProgram, options: SweepOptions) -> list[tuple[dict[str, Any], np.ndarray]]:
    out = []
    for i in range(options.samples):
        result = run_sample(p, options, i, keep=True)
        assert result.trajectory is not None
        out.append((result.row, result.trajectory))
    return out


def _check_identical(spec: SweepProgram, candidate: SweepProgram, options: SweepOptions) -> None:
    """The candidate on the spec's library runs as the rewritten spec's own library does."""
    expected = _rows(spec, options)
    got = _rows(candidate, options)
    for (row, trajectory), (want, wanted) in zip(got, expected, strict=True):
        assert row["status"] == "ok"
        assert _same(row, want), (row, want)
        assert np.array_equal(trajectory, wanted, equal_nan=True)


def test_pvtol_candidate_runs_as_the_spec_with_its_poles() -> None:
    """pvtol, continuous and nominal (the certificate's alpha and c are the candidate's)."""
    base = program(PVTOL)
    edited = program(PVTOL, _pvtol_edits())
    candidate = _candidate(base, PVTOL_POLES, None)
    # One library: the candidate's key is the spec's, not the rewritten spec's.
    assert candidate.key == base.key != edited.key
    assert candidate.sources == base.sources
    for field in ("coefficients", "alpha", "bumpless", "observer_bandwidth"):
        assert getattr(candidate, field) == getattr(edited, field), field
    # c is computed when a certificate first asks it: the rewritten spec's, to the bit.
    assert candidate.c is None and candidate.transient() == edited.c
    assert candidate.coefficients == (-120.0, -154.0, -71.0, -14.0)
    assert np.array_equal(candidate.gains(), [-120.0, -154.0, -71.0, -14.0])
    options = SweepOptions(
        samples=3,
        seed=4,
        t_final=2.0,
        points=41,
        initial=(("x", Distribution("uniform", (-1.5, -0.5))),),
        window=0.5,
    )
    original = _rows(base, options)
    _check_identical(edited, candidate, options)
    rows = [row for row, _ in _rows(candidate, options)]
    assert all(row["nominal"] and row["certificate_holds"] for row in rows)
    # The candidate's gains changed the runs (faster poles: less error after 0.5 s) and
    # the spec's own program still runs with the spec's (each run sets its gains).
    for row, (first, _) in zip(rows, original, strict=True):
        assert row["integrated_error"] < 0.8 * first["integrated_error"]
    assert all(_same(a[0], b[0]) for a, b in zip(_rows(base, options), original, strict=True))


def test_robust_pvtol_candidate_runs_as_the_spec_with_its_poles_and_bandwidth() -> None:
    """Integral action (its bumpless b_j), the observer's bandwidth and limits, sampled
    every 10 ms with noise on a plant whose mass is not the model's."""
    base = program(ROBUST)
    edited = program(ROBUST, _robust_edits())
    candidate = _candidate(base, ROBUST_POLES, ROBUST_BANDWIDTH)
    assert candidate.key == base.key
    for field in ("coefficients", "alpha", "bumpless", "observer_bandwidth"):
        assert getattr(candidate, field) == getattr(edited, field), field
    # c is computed when a certificate first asks it: the rewritten spec's, to the bit.
    assert candidate.c is None and candidate.transient() == edited.c
    assert candidate.observer_bandwidth == 35.0 and base.observer_bandwidth == 20.0
    # Coefficients, then b_0 .. b_3, then the bandwidth.
    assert np.array_equal(
        candidate.gains(), [*edited.coefficients, *edited.bumpless, ROBUST_BANDWIDTH]
    )
    assert len(candidate.gains()) == 5 + 4 + 1
    options = SweepOptions(
        samples=2,
        seed=9,
        t_final=2.0,
        points=41,
        sample_time=0.01,
        noise=1e-4,
        plant_params=(("m", Distribution("normal", (1.0, 0.1))),),
        limits=base.limits,
        window=1.0,
    )
    _check_identical(edited, candidate, options)
    # The bandwidth alone changes the runs: the observer is tuned at run time.
    alone = base.with_gains(base.coefficients, ROBUST_BANDWIDTH)
    # Without the poles the integral's pole is the computed eigenvalue: b_j to rounding.
    assert np.allclose(alone.bumpless, base.bumpless, rtol=1e-12, atol=0.0)
    first = run_sample(base, options, 0).row
    faster = run_sample(alone, options, 0).row
    assert faster["final_error"] != first["final_error"]


def test_single_precision_candidate_runs_as_the_spec_with_its_poles() -> None:
    """The float controller takes the gains too (rounded to float as its spec's are)."""
    base = program(PVTOL, precision="single")
    edited = program(PVTOL, _pvtol_edits(), precision="single")
    candidate = _candidate(base, PVTOL_POLES, None)
    assert any(name == "pvtol_f32.c" for name, _ in candidate.sources)
    options = SweepOptions(samples=2, seed=1, t_final=2.0, points=41, sample_time=0.01)
    _check_identical(edited, candidate, options)
    assert not _same(run_sample(base, options, 0).row, run_sample(candidate, options, 0).row)


def test_two_threads_run_one_loop_with_their_own_gains() -> None:
    """ctypes releases the GIL: the gains are per thread, so concurrent candidates of one
    loaded library each get their own rows."""
    base = program(ROBUST)
    candidate = _candidate(base, ROBUST_POLES, ROBUST_BANDWIDTH)
    assert loop_for(candidate) is loop_for(base)
    options = SweepOptions(
        samples=1, seed=3, t_final=1.0, points=21, sample_time=0.01, limits=base.limits
    )
    expected = {id(p): run_sample(p, options, 0).row for p in (base, candidate)}
    assert not _same(expected[id(base)], expected[id(candidate)])
    start = threading.Barrier(2)
    found: dict[int, list[dict[str, Any]]] = {id(base): [], id(candidate): []}

    def work(p: SweepProgram) -> None:
        start.wait()
        for _ in range(15):
            found[id(p)].append(run_sample(p, options, 0).row)

    threads = [threading.Thread(target=work, args=(p,)) for p in (base, candidate)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    for key, rows in found.items():
        assert len(rows) == 15
        assert all(_same(row, expected[key]) for row in rows)


def test_a_spec_that_differs_by_its_stamp_alone_is_not_compiled_again() -> None:
    """A copy of the spec under another name (or with another [tune] table) differs in its
    files' stamp comments alone: the library compiled is the same, the sweep's identity
    (``key``) still tells the two apart, and a change below the stamp is compiled."""
    base = program(PVTOL)
    compiled = compiled_sources(base)
    assert compiled.keys() == {name for name, _ in base.sources}
    assert all(not text.startswith("/* Generated") for text in compiled.values())
    assert not any("sha256" in text.split("*/", 1)[0] for text in compiled.values())
    renamed = tuple(
        (n, t.replace(" from pvtol.toml.", " from pvtol copy.toml.", 1)) for n, t in base.sources
    )
    copy = dataclasses.replace(base, sources=renamed, key="another sweep")
    assert copy.sources != base.sources and compiled_sources(copy) == compiled
    name, text = base.sources[-1]
    edited = dataclasses.replace(base, sources=(*base.sources[:-1], (name, text + "\n/* */\n")))
    assert compiled_sources(edited)[name] == compiled[name] + "\n/* */\n"


def test_with_gains_refuses_what_the_loop_cannot_run() -> None:
    base = program(ROBUST)
    five = hurwitz.coefficients_from_poles(ROBUST_POLES)

    def refused(*args: Any, **kwargs: Any) -> str:
        with pytest.raises(SpecError) as caught:
            base.with_gains(*args, **kwargs)
        message = str(caught.value)
        assert message.startswith("command line") and "\n" not in message
        return message

    assert "give 5 coefficients" in refused(five[:4], 35.0)
    assert "not Hurwitz" in refused(hurwitz.coefficients_from_poles((0.5, -1, -2, -3, -4)), 35.0)
    # A pole at 0, exact as written, is not inside the left half-plane.
    zero = (0.0, -1.0, -2.0, -3.0, -4.0)
    assert "not Hurwitz" in refused(hurwitz.coefficients_from_poles(zero), 35.0, poles=zero)
    assert "observer's bandwidth is needed" in refused(five, None)
    assert "must be > 0" in refused(five, -1.0)
    assert "must be > 0" in refused(five, math.nan)
    assert "not those of the coefficients" in refused(five, 35.0, poles=PVTOL_POLES + (-1.0,))
    assert "no disturbance observer" in str(
        pytest.raises(SpecError, program(PVTOL).with_gains, (-1.0, -4.0, -6.0, -4.0), 20.0).value
    )
    # Integral action splits off a real pole: four complex ones leave it none (a program of
    # k = 3 with integral action, its three integrals a stand-in).
    integral = dataclasses.replace(program(PVTOL), integral_rows=(6,))
    complex_poles = hurwitz.coefficients_from_poles((-1 + 1j, -1 - 1j, -2 + 1j, -2 - 1j))
    assert "takes a real pole" in str(
        pytest.raises(SpecError, integral.with_gains, complex_poles, None).value
    )
    # Nothing refused: the candidate runs.
    assert base.with_gains(five, 35.0).observer_bandwidth == 35.0


def test_integrated_error_is_the_trapezoid_of_the_kept_trajectory() -> None:
    base = program(PVTOL)
    n, m = len(base.state_names), len(base.output_names)
    for window in (0.0, 0.5, 0.73):
        options = SweepOptions(samples=1, seed=2, t_final=2.0, points=41, window=window)
        result = run_sample(base, options, 0, keep=True)
        assert result.trajectory is not None
        rows = result.trajectory
        t = rows[:, 0]
        error = np.linalg.norm(
            rows[:, 1 + n : 1 + n + m] - rows[:, 1 + n + m : 1 + n + 2 * m], axis=1
        )
        inside = t >= window
        grid = np.concatenate(([window], t[inside])) if t[inside][0] > window else t[inside]
        values = np.interp(grid, t, error)
        assert result.row["integrated_error"] == pytest.approx(
            np.trapezoid(values, grid), rel=1e-14
        )
        assert result.row["max_error_after"] == float(np.max(error[inside]))
        if window == 0.0:
            assert result.row["integrated_error"] == float(np.trapezoid(error, t))
            assert result.row["max_error_after"] == result.row["max_error"]
    # 0.73 s falls between output times (every 0.05 s): the piece from 0.73 to 0.75 counts.
    assert not np.any(np.isclose(t, 0.73))
    # A failed sample measures nothing; a sweep.json from before the window measured from 0.
    failed = failed_row(base, options, 0, 0, RuntimeError("no"))
    assert math.isnan(failed["integrated_error"]) and math.isnan(failed["max_error_after"])
    record = options.as_dict()
    assert record["window"] == 0.73
    del record["window"]
    assert SweepOptions.from_dict(record) == dataclasses.replace(options, window=0.0)
    with pytest.raises(SpecError, match="--after"):
        check_options(base, dataclasses.replace(options, window=2.5))
