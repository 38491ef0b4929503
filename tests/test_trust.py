"""What a user trusts: errors that stay one line and say what to fix (issue 31)."""

from __future__ import annotations

import functools
import os
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import pytest

from tvopt_codegen.cli import main
from tvopt_codegen.errors import EXIT_BAD_SPEC, EXIT_BUDGET, one_line

from .conftest import ROOT, run_main

if TYPE_CHECKING:
    from tvopt_codegen.derivation import Derivation

BARRIER_SPEC = """name = "walled"
[system]
states = ["px", "py"]
inputs = ["ux", "uy"]
[system.dynamics]
px = "ux"
py = "uy"
[system.outputs]
x_out = "px"
y_out = "py"
[objective]
f0 = "(x_out - 1)**2 + (y_out - 2)**2"
[constraints]
wall = "x_out <= 3"
[constraints.{table}]
{key} = 1e-3
[error_dynamics]
poles = [-1.0]
"""


@pytest.mark.parametrize(
    ("table", "key", "field", "message"),
    [
        ("barier", "final_weight", "constraints.barier", "did you mean 'barrier'?"),
        (
            "barrier",
            "final_wieght",
            "constraints.barrier.final_wieght",
            "did you mean 'final_weight'?",
        ),
        (
            "walls",
            "final_weight",
            "constraints.walls",
            "a table, where a constraint is a comparison",
        ),
    ],
)
def test_a_misspelt_key_gets_the_key_it_was_meant_to_be(
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
    table: str,
    key: str,
    field: str,
    message: str,
) -> None:
    spec = tmp_path / "walled.toml"
    spec.write_text(BARRIER_SPEC.format(table=table, key=key))
    assert main(["check", str(spec)]) == EXIT_BAD_SPEC
    lines = capsys.readouterr().err.splitlines()
    assert len(lines) == 1
    assert f"{spec}: {field}: " in lines[0] and message in lines[0], lines[0]
    if table == "walls":
        assert "did you mean" not in lines[0]  # nothing close: no guess


@pytest.mark.parametrize("seconds", ["1e-9", "1e-6", "1e-4", "3e-3"])
def test_any_budget_however_small_ends_in_one_line(seconds: str) -> None:
    # In a process of its own: the budget's timer is a real signal.
    for _ in range(3):
        done = subprocess.run(
            [
                sys.executable,
                "-m",
                "tvopt_codegen",
                "check",
                "unicycle_switch",
                "--max-seconds",
                seconds,
            ],
            capture_output=True,
            text=True,
            check=False,
        )
        assert done.returncode == EXIT_BUDGET, done.stderr
        assert len(done.stderr.splitlines()) == 1, done.stderr
        assert "took longer than" in done.stderr


def test_a_path_with_a_newline_is_printed_escaped(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    folder = tmp_path / "a\nb"
    folder.mkdir()
    spec = folder / "tab\there.toml"
    spec.write_text('name = "bad"\n[system]\nstates = ["x"]\n')
    assert main(["check", str(spec)]) == EXIT_BAD_SPEC
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "a\\nb/tab\\there.toml" in err, err
    blocker = tmp_path / "a\nb" / "file"
    blocker.write_text("")
    code = main(
        [
            "generate",
            str(ROOT / "tvopt_codegen" / "examples" / "integrator.toml"),
            "--out",
            str(blocker / "sub"),
        ]
    )
    err = capsys.readouterr().err
    assert code != 0 and err.count("\n") == 1 and "a\\nb/file" in err, err


def test_one_line_escapes_what_would_break_a_line_and_keeps_the_rest() -> None:
    assert one_line("a\nb\rc\td\x00e\x1bf\u2028g") == "a\\nb\\rc\\td\\x00e\\x1bf\\u2028g"
    assert one_line("café → ok 'quoted'") == "café → ok 'quoted'"


def test_messages_name_values_in_words_not_python_reprs(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    text = (ROOT / "tvopt_codegen" / "examples" / "unicycle_switch.toml").read_text()
    spec = tmp_path / "no_extension.toml"
    spec.write_text(text.replace("[extension]\nintegrate = { v = 1 }\n", ""))
    assert main(["check", str(spec)]) == 3
    err = capsys.readouterr().err
    assert "relative degrees y1 = 1, y2 = 1" in err, err
    assert "{" not in err.split("prolong")[0], err


def test_the_examples_listing_is_aligned_whole_sentences_without_internal_labels() -> None:
    # In this process: what the command prints, not how a process starts (a cold
    # process is a second of imports this one has paid).
    done = run_main("examples")
    assert done.returncode == 0, done.stderr
    lines = done.stdout.splitlines()
    names = [line.split()[0] for line in lines]
    assert "two_unicycles_barrier_refs" in names and len(lines) == len(names)
    starts = {
        len(line) - len(line[len(name) :].lstrip()) for line, name in zip(lines, names, strict=True)
    }
    assert len(starts) == 1  # one column of summaries, past the longest name
    for line in lines:
        assert line.endswith("."), line  # a whole sentence, not a cut line
        assert "issue" not in line and "{" not in line, line


def test_a_summary_is_the_first_sentence_whatever_its_abbreviations() -> None:
    from tvopt_codegen.spec.files import first_sentence

    assert (
        first_sentence("Two robots (paper, Sec. V-B). f0 = ...") == "Two robots (paper, Sec. V-B)."
    )
    assert first_sentence("The team of Fig. 3 kept\nin a corridor. More.") == (
        "The team of Fig. 3 kept in a corridor."
    )
    assert first_sentence("No full stop at all") == "No full stop at all"


def test_the_report_keeps_phi_for_the_coordinates_and_b_for_the_barrier_objective(
    tmp_path: Path,
) -> None:
    assert main(["report", "two_unicycles_corridor", "--out", str(tmp_path)]) == 0
    text = (tmp_path / "two_unicycles_corridor_report.md").read_text()
    assert "minimiser of B = f0 - mu(t)" in text
    assert "Phi = f0" not in text and "Coordinates Phi" in text


REFS = "unicycle_switch_refs"


def _reference_rows(rate: float, horizon: float = 20.0) -> tuple[list[str], np.ndarray]:
    from tvopt_codegen.simulation.references import exact_jets

    from .conftest import derivation

    d = derivation(REFS)
    names = [r.name for r in d.model.references]
    jets = exact_jets(d, {})
    times = np.arange(0.0, horizon + 0.5 / rate, 1.0 / rate)
    table = np.array([[t, *jets(float(t))[:, 0]] for t in times])
    return ["t", *names], table


def _write(
    path: Path, header: list[str], table: np.ndarray, sep: str = ",", head: str = ""
) -> None:
    lines = [sep.join(header)] + [sep.join(repr(float(v)) for v in row) for row in table]
    path.write_text(head + "\n".join(lines) + "\n", encoding="utf-8")


def _read(path: Path, **options: Any) -> tuple[np.ndarray, np.ndarray]:
    from tvopt_codegen.simulation.references import read_reference_file

    from .conftest import derivation

    return read_reference_file(path, derivation(REFS), 20.0, **options)


def test_a_reference_file_from_a_spreadsheet_reads_as_the_plain_one(tmp_path: Path) -> None:
    header, table = _reference_rows(100.0)
    plain = tmp_path / "plain.csv"
    _write(plain, header, table)
    expected = _read(plain)
    excel = tmp_path / "excel.csv"
    # Excel's "CSV UTF-8" (a byte-order mark), a comment line, semicolons.
    _write(excel, header, table, sep=";", head="\ufeff# exported from the lab's logger\n")
    got = _read(excel)
    assert got[0].tobytes() == expected[0].tobytes() and got[1].tobytes() == expected[1].tobytes()
    tabbed = tmp_path / "tabbed.csv"
    _write(tabbed, header, table, sep="\t", head="\n# blank and comment lines skip\n")
    assert _read(tabbed)[1].tobytes() == expected[1].tobytes()


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("time,a,b\n0,1,2\n", "missing column 't': expected a header t, o1x, o1y, o2x, o2y"),
        ("time,a,b\n0,1,2\n", "found the columns time, a, b"),
        (
            "t;o1x;o1y;o2x;o2y\n0;1,5;2;3;4\n",
            "line 2: o1x: expected a number, got '1,5' (a decimal comma",
        ),
        ("# a comment\nt,o1x,o1y,o2x,o2y\n0,1,2,3,4\n0,1,2,3,4\n", "line 4: t must increase"),
    ],
)
def test_a_reference_file_that_cannot_be_read_says_what_was_found(
    tmp_path: Path, text: str, message: str
) -> None:
    from tvopt_codegen.errors import SpecError

    path = tmp_path / "refs.csv"
    path.write_text(text, encoding="utf-8")
    with pytest.raises(SpecError) as caught:
        _read(path)
    assert message in str(caught.value), str(caught.value)


def test_a_column_the_spec_does_not_know_is_ignored_with_a_warning(tmp_path: Path) -> None:
    header, table = _reference_rows(100.0)
    path = tmp_path / "refs.csv"
    _write(path, [*header, "o3x"], np.column_stack([table, table[:, 1]]))
    said: list[str] = []
    _read(path, warn=said.append)
    assert len(said) == 1 and "column 'o3x' ignored: not a reference of the spec" in said[0]


def test_samples_the_estimator_cannot_follow_are_refused_unless_allowed(tmp_path: Path) -> None:
    from tvopt_codegen.errors import SpecError

    header, table = _reference_rows(1000.0)
    gap = tmp_path / "gap.csv"
    keep = (table[:, 0] < 2.5) | (table[:, 0] > 12.5)
    _write(gap, header, table[keep])
    with pytest.raises(SpecError, match=r"gap of 10\.002 s \(t = 2\.499 to 12\.501\)"):
        _read(gap)
    slow = tmp_path / "slow.csv"
    _write(slow, *_reference_rows(1.0))
    with pytest.raises(SpecError, match=r"samples every 1 s .* bandwidth 20 rad/s"):
        _read(slow)
    assert _read(gap, allow_gaps=True)[0].size == int(keep.sum())
    assert _read(slow, allow_gaps=True)[0].size == 21


def test_the_summary_states_the_final_error_the_bound_guarantees(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    slow = tmp_path / "slow.csv"
    _write(slow, *_reference_rows(1.0))
    out = tmp_path / "out"
    assert main(["simulate", REFS, "--reference-file", str(slow), "--out", str(out)]) == 2
    assert "--allow-gaps runs anyway" in capsys.readouterr().err
    args = ["simulate", REFS, "--reference-file", str(slow), "--allow-gaps", "--out", str(out)]
    assert main(args) == 0
    printed = capsys.readouterr().out
    line = next(x for x in printed.splitlines() if "guaranteed <=" in x)
    guaranteed = float(line.split("<=")[1].split()[0])
    observed = float(line.rsplit("observed", 1)[1].strip(" )"))
    assert 0 < observed <= guaranteed


def test_the_c_controllers_step_from_python_takes_the_entry_point_and_behaves_alike() -> None:
    from tvopt_codegen.simulation import load_controller

    from .conftest import kernels

    mod = load_controller(kernels("unicycle_switch"), "c")
    if mod._ENTRY_STEP is None:
        pytest.skip("no Python headers: the C module calls through ctypes")
    n = len(mod.PLANT_STATE_NAMES)
    x0 = np.array(mod.DEFAULT_STATE[:n])
    fast, general = mod.Controller(x0), mod.Controller(x0)
    x = x0.copy()
    for k in range(1, 200):
        x = x + 1e-3 * np.array([0.3, -0.2, 0.05, 0.0][:n])
        a = fast.step(k * 1e-3, x)  # float64 vector: the entry point
        b = general.step(k * 1e-3, x.tolist())  # a list: the general path converts it
        assert a.tobytes() == b.tobytes() and fast.state.tobytes() == general.state.tobytes()
    # A strided view or a float32 vector is not taken as is: converted, same answer.
    wide = np.repeat(x, 2)[::2]
    assert fast.step(0.2, wide).tobytes() == general.step(0.2, x.tolist()).tobytes()
    before = (fast.t, fast.state.tobytes(), fast.u.tobytes())
    bad = x.copy()
    bad[1] = np.nan
    with pytest.raises(mod.NonFiniteInputError, match=mod.PLANT_STATE_NAMES[1]):
        fast.step(0.3, bad)
    with pytest.raises(mod.DecreasingTimeError, match="before the last step"):
        fast.step(0.1, x)
    assert (fast.t, fast.state.tobytes(), fast.u.tobytes()) == before
    # The returned input is the caller's to keep: the next step does not overwrite it.
    first = fast.step(0.3, x)
    kept = first.copy()
    fast.step(0.31, x + 0.01)
    assert first.tobytes() == kept.tobytes()


GEOFENCE = """name = "geofence"
[system]
states = ["px", "py", "theta"]
inputs = ["v", "omega"]
[system.dynamics]
px = "v*cos(theta)"
py = "v*sin(theta)"
theta = "omega"
[system.outputs]
y1 = "px"
y2 = "py"
[extension]
integrate = {{ v = 1 }}
[signals]
ox = "4*cos(0.3*t)"
oy = "4*sin(0.3*t)"
[objective]
f0 = "(y1 - ox)**2 + (y2 - oy)**2"
[constraints]
fence = "{fence}"
[constraints.barrier]
final_weight = 1e-3
[error_dynamics]
poles = [-1.0, -1.5]
[simulation]
t_final = 20.0
initial_state = {{ px = 0.0, py = {y0}, theta = 0.0, v = 1.0 }}
"""


def _geofence(tmp_path: Path, y0: float, fence: str = "y1**2 + y2**2 <= 9") -> Path:
    path = tmp_path / f"geofence{y0}.toml"
    path.write_text(GEOFENCE.format(y0=y0, fence=fence))
    return path


_GEOFENCES = Path(tempfile.mkdtemp(prefix="tvopt-trust-geofence-"))


@functools.cache
def _geofence_derivation(y0: float) -> Derivation:
    """The disc geofence's derivation from ``y0``, derived once: two tests read it."""
    from tvopt_codegen.derivation import derive
    from tvopt_codegen.spec import load_spec

    return derive(load_spec(str(_geofence(_GEOFENCES, y0))))


@pytest.mark.parametrize("y0", [-1.0, -2.0, -2.5, -3.0, -3.001, -3.1])
def test_a_disc_geofence_is_accepted_from_every_start_with_the_barriers_modulus(
    y0: float,
) -> None:
    d = _geofence_derivation(y0)
    # Inside {g < s(t)} the barrier objective is at least as convex as f0 (2 I).
    assert d.objective.convexity.m_f >= 2.0 - 1e-9, d.objective.convexity


@pytest.mark.parametrize("y0", [-3.0, -3.1])
def test_a_disc_geofence_from_its_edge_and_outside_it_certifies(y0: float) -> None:
    """Simulated in this process as ``simulate SPEC`` simulates it (its exit 0 is ``passed``).

    The command's files and figures (its drawing process) are test_simulate's subject;
    without the command's minimiser process the certificate's numbers are the same
    (``simulate``'s ``side``), found in this process.
    """
    from tvopt_codegen.lowering.ir import lower
    from tvopt_codegen.simulation import (
        format_certificate,
        load_controller,
        resolve_options,
        simulate,
    )

    d = _geofence_derivation(y0)
    result = simulate(d, load_controller(lower(d)), resolve_options(d))
    assert result.passed, format_certificate(d, result)


def test_a_constraint_empty_over_part_of_the_horizon_is_named_with_the_interval(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    spec = _geofence(tmp_path, -1.0, "y1**2 + y2**2 <= (t - 10)**2/100 + 1 - 0.1*t")
    assert main(["check", str(spec)]) == 3
    err = capsys.readouterr().err
    assert "constraints.fence: infeasible for t in [10, 20] of the horizon [0, 20]" in err, err
    assert "convex" not in err


def test_a_hessian_that_fails_is_blamed_on_f0_or_on_the_barrier() -> None:
    from tvopt_codegen.derivation.convexity import _culprit
    from tvopt_codegen.derivation.model import build_model
    from tvopt_codegen.spec import spec_from_dict

    text = GEOFENCE.format(y0=-1.0, fence="y1**2 + y2**2 <= 9")
    import tomllib

    model = build_model(spec_from_dict(tomllib.loads(text)))
    field, cause = _culprit(model, np.array([0.0, -3.5]), 10.0)
    assert field == "constraints" and "barrier term of the constraints fence" in cause
    flat = tomllib.loads(text)
    flat["objective"]["f0"] = "(y1 - ox)**4 + (y2 - oy)**2"
    model = build_model(spec_from_dict(flat))
    field, cause = _culprit(model, np.array([4 * np.cos(3.0), 0.0]), 10.0)
    assert field == "objective.f0" and "f0's own Hessian" in cause


def test_a_vacuous_bound_with_equalities_names_the_kkt_matrix(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    from tvopt_codegen.simulation import certificate

    monkeypatch.setattr(certificate, "_kkt_eigenvalues", lambda *args: np.array([1e-9, 1.0, 3.0]))
    failures: list[str] = []
    m_f = certificate._modulus(
        None, None, {}, np.zeros(1), np.zeros((2, 1)), np.zeros((2, 1)), (object(), None, None),
        lambda t: {}, failures,
    )  # fmt: skip
    assert m_f == 1e-9 and len(failures) == 1
    assert "the KKT matrix's smallest singular value 1e-09" in failures[0]
    assert "f0" not in failures[0].split("(")[0]


def test_a_certificate_does_not_fail_on_an_integration_tolerance_alone() -> None:
    from tvopt_codegen.simulation import Options, simulate

    from .conftest import derivation, module

    d, mod = derivation("unicycle_switch"), module("unicycle_switch")
    loose = Options(
        t_final=20.0, initial_state=tuple(mod.DEFAULT_STATE), method="RK45", rtol=1e-6, atol=1e-8
    )
    result = simulate(d, mod, loose)
    assert result.passed, result.failures
    assert result.options.method == "DOP853" and result.options.rtol == 1e-13
    assert "RK45 at rtol 1e-06 failed" in result.reintegrated
    assert "the integrator's error, not the law's" in result.reintegrated


def test_a_wrong_law_still_fails_when_integrated_again() -> None:
    import types

    from tvopt_codegen.simulation import Options, simulate

    from .conftest import derivation, module

    d, mod = derivation("unicycle_switch"), module("unicycle_switch")
    wrong = types.ModuleType("wrong")
    wrong.__dict__.update(mod.__dict__)

    def rhs(t: float, s: Any, params: Any = None, **jets: Any) -> Any:
        rates = np.array(mod.rhs(t, s, params, **jets), dtype=float)
        rates[3] *= 1.001  # the prolonged speed's drive, 0.1% off the law's
        return rates

    wrong.rhs = rhs
    options = Options(t_final=10.0, initial_state=tuple(mod.DEFAULT_STATE))
    result = simulate(d, wrong, options)
    assert not result.passed
    assert "E deviates from expm(H t) E(0)" in "; ".join(result.failures)
    assert "it fails as well: the law's, not the integrator's" in result.reintegrated


@pytest.mark.parametrize(
    ("deviations", "passed", "orders"),
    [
        # Pre-asymptotic at H (order 0.65), then first order: H is halved again, and passes.
        ((3.3e-2, 2.1e-2, 1.1e-2), True, 2),
        # Not approaching at all: every halving tried, then refused.
        ((1e-2, 1e-2, 1e-2, 1e-2), False, 3),
    ],
)
def test_the_sampled_order_is_fitted_until_it_is_asymptotic(
    monkeypatch: pytest.MonkeyPatch, deviations: tuple[float, ...], passed: bool, orders: int
) -> None:
    import types

    from tvopt_codegen.simulation import Options, sampled

    from .conftest import derivation, module

    d, mod = derivation("integrator"), module("integrator")
    steps: list[float] = []

    def fake_run(d: Any, c: Any, o: Any, h: float, *rest: Any) -> Any:
        steps.append(h)
        return types.SimpleNamespace(
            h=h,
            deviation=deviations[len(steps) - 1],
            iss_ratio=0.5,
            saturated_time=0.0,
            ultimate=1e-6,
            t=np.arange(0.0, 2.0 + h / 2, h),
            wall_time=0.1,
            disturbance=0.3,
        )

    monkeypatch.setattr(sampled, "sampled_run", fake_run)
    options = Options(t_final=2.0, initial_state=tuple(mod.DEFAULT_STATE))
    result = sampled.simulate_sampled(d, mod, options, 0.01, convergence_order=True)
    assert steps == [0.01 / 2**k for k in range(orders + 1)]
    assert len(result.orders) == orders and result.passed is passed
    assert result.orders[0] == pytest.approx(np.log2(3.3 / 2.1) if passed else 0.0)
    if passed:
        assert result.order == pytest.approx(np.log2(2.1 / 1.1))
        assert "(H to H/2), 0.933 (H/2 to H/4) (1 for a zero-order hold): not yet asymptotic" in (
            sampled.format_sampled(d, result)
        )
    else:
        assert "observed order 0, 0, 0 from H = 0.01 to 0.00125" in result.failures[-1]


@pytest.mark.parametrize("method", ["RK45", "DOP853"])
@pytest.mark.parametrize("name", ["two_unicycles_corridor", "arm_on_line"])
def test_the_constrained_examples_certify_with_either_integrator(name: str, method: str) -> None:
    import dataclasses

    from tvopt_codegen.simulation import resolve_options, simulate

    from .conftest import derivation, module

    d = derivation(name)
    options = dataclasses.replace(resolve_options(d, points=101), method=method)
    result = simulate(d, module(name), options)
    assert result.passed, result.failures
    assert not result.reintegrated  # at the requested settings, not after a second run


def test_docstrings_write_shapes_as_python_prints_them() -> None:
    import re

    from tvopt_codegen.lowering.ir import lower
    from tvopt_codegen.renderer.rendering import render

    from .conftest import derivation

    text = render(lower(derivation("pvtol")), "python")["pvtol.py"]
    assert "numpy.ndarray, shape (4, 2) or (4, 2, N)" in text
    assert re.search(r"shape \(\d+, \d+,\)", text) is None


def test_the_c_controllers_failures_name_their_cause() -> None:
    from tvopt_codegen.simulation import load_controller

    from .conftest import kernels

    mod = load_controller(kernels("pvtol"), "c")
    x = np.array(mod.DEFAULT_STATE[:6])
    controller = mod.Controller(x)
    # Far in the future: the thrust's chain, advanced by h**2 / 2, overflows: not a parameter.
    with pytest.raises(mod.NonFiniteInputError, match="controller states are not finite"):
        controller.step(1e200, x)
    assert controller.t == 0.0
    # Another thread's step in between: the C's DECREASING_TIME is that error, not a KeyError.
    with pytest.raises(mod.DecreasingTimeError, match="time must not decrease"):
        mod.Controller._fail(mod.STATUS_DECREASING_TIME, 1.0, x, None, 2.0)


def test_run_time_edges_of_the_long_jobs_round(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    # Issue 34: --seed -1 is a one-line usage error, not an internal error.
    out = tmp_path / "out"
    assert main(["simulate", "unicycle_switch", "--seed", "-1", "--out", str(out)]) == 2
    assert "--seed: must be between 0 and 2**63 - 1" in capsys.readouterr().err
    # A module named after a C header would shadow it: refused, exit 2.
    text = (ROOT / "tvopt_codegen" / "examples" / "integrator.toml").read_text()
    spec = tmp_path / "stddef.toml"
    spec.write_text(text.replace('name = "integrator"', 'name = "stddef"'))
    assert main(["check", str(spec)]) == 2
    assert "would write stddef.h, which shadows the C header" in capsys.readouterr().err


def test_a_feasible_nonconvex_constraint_from_its_stationary_point_is_not_infeasible(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    # Issue 34: outputs starting at the centre of y1**2 + y2**2 >= 0.01, where the
    # least-violation search cannot move; the set is not empty.
    text = GEOFENCE.format(y0=0.0, fence="y1**2 + y2**2 >= 0.01").replace(
        "[constraints.barrier]", "allow_nonconvex = true\n[constraints.barrier]"
    )
    spec = tmp_path / "away.toml"
    spec.write_text(text)
    main(["check", str(spec)])
    assert "infeasible" not in capsys.readouterr().err


def test_a_reference_file_is_a_regular_bounded_table(tmp_path: Path) -> None:
    import os

    from tvopt_codegen.errors import SpecError

    # Issue 34: a FIFO would block, /dev/zero would fill the memory; a huge field, a
    # column given twice.
    fifo = tmp_path / "fifo.csv"
    os.mkfifo(fifo)
    for path in (fifo, Path("/dev/zero")):
        with pytest.raises(SpecError, match="not a regular file"):
            _read(path)
    wide = tmp_path / "wide.csv"
    wide.write_text("t,o1x,o1y,o2x,o2y\n0," + "1" * 200_000 + ",2,3,4\n")
    with pytest.raises(SpecError, match="line 2: not a CSV row: field larger than"):
        _read(wide)
    # A file is read a line at a time: a line without end, or more rows than a run takes,
    # stops the reading there (a 171 MB file once ran out of memory).
    endless = tmp_path / "endless.csv"
    endless.write_text("t,o1x,o1y,o2x,o2y\n0,1,2,3," + "4" * (2 << 20))
    with pytest.raises(SpecError, match="line 2: longer than 1048576 characters"):
        _read(endless)
    many = tmp_path / "many.csv"
    many.write_text("t,o1x,o1y,o2x,o2y\n" + "".join(f"{k},1,2,3,4\n" for k in range(1200)))
    with pytest.MonkeyPatch.context() as patch:
        from tvopt_codegen.simulation import references

        patch.setattr(references, "MAX_SAMPLES", 1000)
        with pytest.raises(SpecError, match="more than 1000 samples"):
            _read(many)
    twice = tmp_path / "twice.csv"
    twice.write_text("t,o1x,o1y,o2x,o2y,o1x\n0,1,2,3,4,5\n30,1,2,3,4,5\n")
    with pytest.raises(SpecError, match="column 'o1x' appears more than once"):
        _read(twice)


@pytest.mark.parametrize("backend", ["python", "c"])
def test_an_estimators_jets_at_a_time_it_cannot_reach_raise(backend: str) -> None:
    from tvopt_codegen.simulation import load_controller

    from .conftest import kernels

    mod = load_controller(kernels("unicycle_switch_refs"), backend)
    estimator = mod.ReferenceEstimator(np.array([1.0, 2.0, 3.0, 4.0]), 0.0)
    estimator.update(0.01, np.array([1.01, 2.0, 3.0, 4.02]))
    assert np.all(np.isfinite(estimator.jets(0.02)))
    with pytest.raises(mod.NonFiniteInputError, match="t = nan is not finite"):
        estimator.jets(float("nan"))
    with pytest.raises(mod.NonFiniteOutputError, match="extrapolated to t = 1e\\+300"):
        estimator.jets(1e300)


def test_a_spec_file_name_with_dashes_makes_a_well_formed_fmu(tmp_path: Path) -> None:
    import xml.etree.ElementTree as ET
    import zipfile

    from tvopt_codegen.renderer.rendering import xml_text

    assert "--" not in xml_text("robot---v2 ----- -- -")
    pytest.importorskip("fmpy")
    spec = tmp_path / "robot---v2.toml"
    spec.write_text((ROOT / "tvopt_codegen" / "examples" / "integrator.toml").read_text())
    out = tmp_path / "out"
    assert main(["export", str(spec), "--fmu", "--out", str(out)]) == 0
    with zipfile.ZipFile(out / "integrator.fmu") as archive:
        ET.fromstring(archive.read("modelDescription.xml"))  # well-formed


def test_markup_and_control_characters_stay_out_of_the_reports(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    text = (ROOT / "tvopt_codegen" / "examples" / "integrator.toml").read_text()
    folder = tmp_path / "a`b-->c"
    folder.mkdir()
    spec = folder / "x`y-->.toml"
    spec.write_text(text)
    out = tmp_path / "out"
    assert main(["report", str(spec), "--out", str(out)]) == 0
    md = (out / "integrator_report.md").read_text()
    head, body = md.split("-->", 1)[0], md.split("\n# ", 1)[1]
    assert "-->" not in head.split("<!--", 1)[1][:-1]  # the comment closes where it should
    assert f"`` {spec} ``" in body  # a code span no backtick inside can close
    html = (out / "integrator_report.html").read_text()
    assert html.count("-->") == html.count("<!--")
    # A control character in the description is refused where it was written.
    bad = tmp_path / "bad.toml"
    bad.write_text(text.replace('description = """', 'description = """\\u001b[2J', 1))
    assert main(["check", str(bad)]) == 2
    assert "description: holds the control character U+001B" in capsys.readouterr().err


def test_the_c_controller_refuses_missing_reference_jets() -> None:
    import ctypes

    from tvopt_codegen.simulation import load_controller

    from .conftest import kernels

    mod = load_controller(kernels("unicycle_switch_refs"), "c")
    memory = np.zeros(mod._CONTROLLER_SIZE // 8 + 1)
    x = np.array(mod.DEFAULT_STATE[:3])
    init = mod._LIB.unicycle_switch_refs_controller_init
    init.argtypes = (ctypes.c_void_p, ctypes.c_double) + (ctypes.c_void_p,) * 4
    init.restype = ctypes.c_int
    # refs = NULL: a status, not a crash; the struct is left as it was.
    assert (
        init(memory.ctypes.data, 0.0, x.ctypes.data, None, None, None) == mod.STATUS_NONFINITE_INPUT
    )
    assert not memory.any()


def test_the_c_controllers_step_with_reference_jets_takes_the_entry_point_too() -> None:
    from tvopt_codegen.simulation import load_controller
    from tvopt_codegen.simulation.references import exact_jets

    from .conftest import derivation, kernels

    mod = load_controller(kernels("unicycle_switch_refs"), "c")
    if mod._ENTRY_STEP is None:
        pytest.skip("no Python headers: the C module calls through ctypes")
    jets = exact_jets(derivation("unicycle_switch_refs"), {})
    x = np.array(mod.DEFAULT_STATE[:3])
    fast, general = mod.Controller(x, refs=jets(0.0)), mod.Controller(x, refs=jets(0.0))
    for k in range(1, 100):
        t = k * 1e-2
        a = fast.step(t, x, refs=jets(t))  # a float64 (4, 3) array: the entry point
        b = general.step(t, x.tolist(), refs=jets(t).tolist())  # lists: the general path
        assert a.tobytes() == b.tobytes() and fast.state.tobytes() == general.state.tobytes()
    bad = jets(1.0)
    bad[2, 1] = np.nan
    with pytest.raises(mod.NonFiniteInputError):
        fast.step(1.0, x, refs=bad)
    with pytest.raises(ValueError):
        fast.step(1.0, x, refs=jets(1.0)[:, :2])  # the wrong shape, as the general path says


@pytest.mark.parametrize("backend", ["python", "c"])
def test_a_copied_controller_is_a_controller_of_its_own(backend: str) -> None:
    import copy

    from tvopt_codegen.simulation import load_controller

    from .conftest import kernels

    # Issue 34: copy.copy of the C Controller shared its struct with the original.
    mod = load_controller(kernels("pvtol"), backend)
    x = np.array(mod.DEFAULT_STATE[:6])
    original = mod.Controller(x)
    original.step(0.01, x)
    for make in (copy.copy, copy.deepcopy):
        twin = make(original)
        before = twin.state.tobytes(), twin.t
        original.step(original.t + 0.01, x + 0.01)
        assert (twin.state.tobytes(), twin.t) == before  # the original's step left it alone
        assert twin.step(original.t, x + 0.01).tobytes() == original.u.tobytes()


@pytest.mark.parametrize("module", ["pvtol", "pvtol_c"])
def test_a_pickled_controller_goes_on_in_another_process(module: str) -> None:
    """Both backends' Controllers pickle with their whole state (the C struct's memory is
    plain doubles): unpickled in a fresh process, the next step gives the same bits."""
    import importlib
    import pickle
    import subprocess
    import sys

    root = Path(__file__).resolve().parents[1]
    folders = [str(root / "generated"), str(root / "generated" / "c")]
    sys.path[:0] = folders
    # No bytecode beside the committed files (test_golden holds generated/ to them).
    writes, sys.dont_write_bytecode = sys.dont_write_bytecode, True
    try:
        mod = importlib.import_module(module)
    finally:
        del sys.path[:2]
        sys.dont_write_bytecode = writes
    x = np.array(mod.DEFAULT_STATE[:6])
    controller = mod.Controller(x)
    controller.step(0.01, x)
    data = pickle.dumps(controller)
    expected = controller.step(0.02, x + 0.01)
    code = (
        "import pickle, sys, numpy\n"
        "controller = pickle.loads(sys.stdin.buffer.read())\n"
        f"u = controller.step(0.02, numpy.array({(x + 0.01).tolist()!r}))\n"
        "sys.stdout.write(u.tobytes().hex())\n"
    )
    done = subprocess.run(
        [sys.executable, "-c", code],
        input=data,
        capture_output=True,
        env={**os.environ, "PYTHONPATH": os.pathsep.join(folders), "PYTHONDONTWRITEBYTECODE": "1"},
        check=False,
    )
    assert done.returncode == 0, done.stderr.decode()
    assert bytes.fromhex(done.stdout.decode()) == expected.tobytes()


def test_an_apostrophe_in_a_message_does_not_clip_the_prose_around_it() -> None:
    from tvopt_codegen.errors import clip_quotes

    prose = "a name 'stddef' that shadows a header of that name, or one of the C library's)"
    assert clip_quotes(prose) == prose
    assert clip_quotes("name '" + "x" * 200 + "' is bad") == "name '" + "x" * 57 + "...' is bad"
