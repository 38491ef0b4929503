"""References measured at run time: jets as arguments, the closed-form law when exact."""

from __future__ import annotations

import functools
import math
import re
from collections.abc import Callable
from pathlib import Path
from types import ModuleType

import numpy as np
import pytest

from tvopt_codegen.errors import SpecError
from tvopt_codegen.simulation.references import exact_jets as reference_jets
from tvopt_codegen.spec import load_spec

from .conftest import derivation, module, write_spec
from .test_c_backend import c_module

TWINS = ["integrator", "unicycle_switch", "two_unicycles_barrier", "pvtol", "unicycle_ring"]


@functools.cache
def _jets(spec: str) -> Callable[[float], np.ndarray]:
    return reference_jets(derivation(spec), {})


def exact_jets(spec: str, t: float) -> np.ndarray:
    """The references' jets from their nominal closed forms: shape (n_refs, q + 1)."""
    return _jets(spec)(t)


def _pairs(
    name: str, tmp_path_factory: pytest.TempPathFactory
) -> list[tuple[ModuleType, ModuleType]]:
    return [
        (module(name), module(f"{name}_refs")),
        (c_module(name, tmp_path_factory), c_module(f"{name}_refs", tmp_path_factory)),
    ]


@pytest.mark.parametrize("name", TWINS)
def test_exact_jets_give_the_closed_form_controller(
    name: str, tmp_path_factory: pytest.TempPathFactory
) -> None:
    rng = np.random.default_rng(16)
    for closed, measured in _pairs(name, tmp_path_factory):
        assert measured.REFERENCE_ORDER == derivation(f"{name}_refs").jet.reference_order >= 1
        assert measured.STATE_NAMES == closed.STATE_NAMES
        base = np.array(closed.DEFAULT_STATE)
        m = len(closed.OUTPUT_NAMES)
        for t in (0.0, 3.7, 11.2):
            jets = exact_jets(f"{name}_refs", t)
            states = base[:, None] + 0.05 * rng.standard_normal((len(base), 3))
            for function in ("control", "rhs", "optimality_error"):
                want = getattr(closed, function)(t, states)
                got = getattr(measured, function)(t, states, refs=jets)
                np.testing.assert_allclose(got, want, rtol=1e-12, atol=1e-12, err_msg=function)
                # One state, and one jet per column, give the same.
                one = getattr(measured, function)(t, states[:, 0], refs=jets)
                np.testing.assert_allclose(one, want[..., 0], rtol=1e-12, atol=1e-12)
                per_column = np.repeat(jets[:, :, None], 3, axis=2)
                np.testing.assert_allclose(
                    getattr(measured, function)(t, states, refs=per_column), got, rtol=0, atol=0
                )
            outputs = states[:m]
            for function in ("objective", "gradient", "hessian"):
                want = getattr(closed, function)(t, outputs)
                got = getattr(measured, function)(t, outputs, refs=jets)
                np.testing.assert_allclose(got, want, rtol=1e-12, atol=1e-12, err_msg=function)


@pytest.mark.parametrize("name", ["unicycle_switch", "pvtol"])
def test_the_stateful_controller_with_exact_jets(
    name: str, tmp_path_factory: pytest.TempPathFactory
) -> None:
    for closed, measured in _pairs(name, tmp_path_factory):
        n = len(closed.PLANT_STATE_NAMES)
        x = np.array(closed.DEFAULT_STATE[:n])
        a = closed.Controller(x)
        b = measured.Controller(x, refs=exact_jets(f"{name}_refs", 0.0))
        for k in range(1, 60):
            t = 0.05 * k
            np.testing.assert_allclose(
                b.step(t, x, refs=exact_jets(f"{name}_refs", t)), a.step(t, x), rtol=1e-12,
                atol=1e-12,
            )  # fmt: skip


@pytest.mark.parametrize("backend", ["python", "c"])
def test_missing_wrong_or_non_finite_jets_are_clear_errors(
    backend: str, tmp_path_factory: pytest.TempPathFactory
) -> None:
    name = "unicycle_switch_refs"
    mod = module(name) if backend == "python" else c_module(name, tmp_path_factory)
    s = np.array(mod.DEFAULT_STATE)
    jets = exact_jets(name, 1.0)
    with pytest.raises(
        TypeError, match=r"refs is required: the jets of REFERENCE_NAMES, shape \(4, 3\)"
    ):
        mod.control(1.0, s)
    with pytest.raises(
        ValueError, match=r"refs must have shape \(4, 3\) or \(4, 3, 1\), got \(4, 2\)"
    ):
        mod.rhs(1.0, s, refs=jets[:, :2])
    bad = jets.copy()
    bad[1, 2] = math.nan
    with pytest.raises(mod.NonFiniteInputError, match=r"a reference is not finite \(column 0\)"):
        mod.control(1.0, s, refs=bad)
    with pytest.raises(TypeError, match="refs is required"):
        mod.Controller(s[:3])
    with pytest.raises(TypeError, match="refs must be real"):
        mod.gradient(1.0, s[:2], refs=jets + 1j)


@pytest.mark.parametrize(
    ("table", "field", "problem"),
    [
        ('names = ["o1x"]\nnominal = { zz = "t" }', "references.nominal.zz", "not a declared"),
        ('names = ["o1x"]\n[references.estimator]\nkind = "kalman"', "kind", "expected one of"),
        (
            'names = ["o1x"]\n[references.estimator]\nlipschitz = 2.0',
            "lipschitz",
            "only meaningful for levant",
        ),
        ('names = ["y1"]', "references.y1", "name already declared"),
        ('names = ["o1x"]\nnominal = { o1x = "y1" }', "references.nominal.o1x", "may not appear"),
    ],
)
def test_bad_reference_tables_name_the_field(
    tmp_path: Path, unicycle_text: str, table: str, field: str, problem: str
) -> None:
    text = unicycle_text.replace('o1x = "', 'o1x_unused = "') + "\n[references]\n" + table + "\n"
    with pytest.raises(SpecError) as info:
        load_spec(write_spec(tmp_path, text))
    assert field in str(info.value) and problem in str(info.value), str(info.value)


@pytest.mark.parametrize("name", ["unicycle_switch_refs", "pvtol_refs"])
def test_the_estimators_converge_and_agree_to_the_bit(
    name: str, tmp_path_factory: pytest.TempPathFactory
) -> None:
    """Samples of the nominal references at 1 kHz: the jets approach the exact ones; the
    NumPy and the C estimators give the same bits, noise or not."""
    py, c = module(name), c_module(name, tmp_path_factory)
    assert py.ESTIMATOR == derivation(name).spec.estimator.kind
    estimators = [m.ReferenceEstimator(exact_jets(name, 0.0)[:, 0]) for m in (py, c)]
    h = 1e-3
    # Every update's jets, compared at once: 6,000 assert_array_equal calls took seconds.
    history: list[list[np.ndarray]] = [[], []]
    for k in range(1, 6001):
        t = k * h
        samples = exact_jets(name, t)[:, 0]
        jets = [e.update(t, samples) for e in estimators]
        for kept, jet in zip(history, jets, strict=True):
            kept.append(np.array(jet))  # a copy: a backend may reuse its buffer
    np.testing.assert_array_equal(history[0], history[1])
    error = np.abs(jets[0] - exact_jets(name, 6.0))
    scale = np.abs(exact_jets(name, 6.0)).max(axis=0) + 1.0
    # Value and first derivative to 1e-3 of their scale; every derivative to 5%.
    assert np.all(error[:, :2] <= 1e-3 * scale[:2]), error
    assert np.all(error <= 0.05 * scale), error
    # Between samples: the Taylor polynomial of the last estimate.
    ahead = estimators[0].jets(6.0 + 0.5 * h)
    np.testing.assert_allclose(ahead[:, 0], jets[0][:, 0] + 0.5 * h * jets[0][:, 1], rtol=1e-6)
    noisy = [m.ReferenceEstimator(exact_jets(name, 0.0)[:, 0]) for m in (py, c)]
    rng = np.random.default_rng(3)
    history = [[], []]
    for k in range(1, 500):
        samples = exact_jets(name, k * h)[:, 0] + 1e-2 * rng.standard_normal(
            len(py.REFERENCE_NAMES)
        )
        for kept, e in zip(history, noisy, strict=True):
            kept.append(np.array(e.update(k * h, samples)))
    np.testing.assert_array_equal(history[0], history[1])


@pytest.mark.parametrize("backend", ["python", "c"])
def test_a_controller_fed_with_samples(
    backend: str, tmp_path_factory: pytest.TempPathFactory
) -> None:
    name = "unicycle_switch_refs"
    mod = module(name) if backend == "python" else c_module(name, tmp_path_factory)
    x = np.array(mod.DEFAULT_STATE[:3])
    by_samples = mod.Controller(x, samples=exact_jets(name, 0.0)[:, 0])
    estimator = mod.ReferenceEstimator(exact_jets(name, 0.0)[:, 0])
    by_jets = mod.Controller(x, refs=estimator.jets(0.0))
    for k in range(1, 40):
        t = 0.01 * k
        samples = exact_jets(name, t)[:, 0]
        np.testing.assert_array_equal(
            by_samples.step(t, x, samples=samples),
            by_jets.step(t, x, refs=estimator.update(t, samples)),
        )
    with pytest.raises(ValueError, match="samples need a controller started from samples"):
        by_jets.step(1.0, x, samples=samples)
    before = estimator.t
    with pytest.raises(ValueError, match="is before the last update's time"):
        estimator.update(0.1, samples)
    bad = samples.copy()
    bad[0] = math.nan
    with pytest.raises(mod.NonFiniteInputError, match="o1x = nan is not finite"):
        estimator.update(2.0, bad)
    assert estimator.t == before


def _write_samples(path: Path, name: str, horizon: float, rate: float = 1000.0) -> None:
    times = np.arange(0.0, horizon + 0.5 / rate, 1.0 / rate)
    names = [r.name for r in derivation(name).model.references]
    with open(path, "w", encoding="utf-8") as handle:
        handle.write(",".join(["t", *names]) + "\n")
        for t in times:
            row = exact_jets(name, float(t))[:, 0]
            handle.write(",".join(repr(float(v)) for v in (t, *row)) + "\n")


@pytest.fixture(scope="module")
def samples_file(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """1 kHz samples of unicycle_switch_refs's nominal references over its 20 s, written
    once for the two tests that read them (20,001 rows of closed-form jets)."""
    path = tmp_path_factory.mktemp("samples") / "objects.csv"
    _write_samples(path, "unicycle_switch_refs", 20.0)
    return path


# The samples' run in two tests, each about 10 s: two noise levels in one process, and the
# command on the same samples at the third. As one test (20-30 s) it was among the longest
# of the suite, the last to end on two workers. Marked slow by hand: tests/durations.json
# has only the one test's time.


@pytest.mark.slow
def test_simulate_from_samples_tracks_and_the_iss_bound_holds_at_every_noise(
    samples_file: Path,
) -> None:
    """No noise and noise 1e-2 here; 1e-3 (the same draw, seed 1) is the command's run in
    test_simulate_command_from_a_samples_file, whose exit code 0 is the same certificate.

    The run without noise is also this spec's case of
    test_the_default_estimator_on_clean_1khz_samples_ends_within_1e3_of_the_start: the
    same 1 kHz samples of the nominal closed forms (written with repr, read back to the
    bit), the same estimator and grid, so its first 15 s are that test's run."""
    from tvopt_codegen.simulation import resolve_options, simulate
    from tvopt_codegen.simulation.references import read_reference_file, sampled_source

    name = "unicycle_switch_refs"
    d, mod = derivation(name), module(name)
    assert d.spec.estimator is not None and d.spec.estimator.kind == "linear"
    assert len(mod._ESTIMATOR_GAINS) == d.jet.reference_order + 2
    options = resolve_options(d)
    times, values = read_reference_file(samples_file, d, options.t_final)
    finals = []
    for noise in (0.0, 1e-2):
        source = sampled_source(d, mod, {}, times, values, noise, seed=1)
        result = simulate(d, mod, options, references=source)
        assert result.passed, result.failures
        assert result.iss_ratio <= 1.0 and result.disturbance > 0
        finals.append(result.error[-1] / result.error[0])
        if noise == 0.0:
            # The default estimator's check at 15 s (an output time of the run).
            at = int(np.searchsorted(result.t, 15.0))
            assert result.t[at] == 15.0
            assert result.error[at] <= 1e-3 * result.error[0]
    # 1 kHz samples of the closed form, no noise: the final error is below 1e-3 of the
    # initial one; noise raises it, as the bound allows.
    assert finals[0] <= 1e-3
    assert finals[0] <= finals[1]


@pytest.mark.slow
def test_simulate_command_from_a_samples_file(
    tmp_path: Path, samples_file: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """The command on the samples with noise 1e-3: it passes the certificate (exit 0), the
    input-to-state bound among its checks, and says so."""
    name = "unicycle_switch_refs"
    out = tmp_path / "out"
    out.mkdir()
    from tvopt_codegen.cli import main

    code = main(
        ["simulate", name, "--reference-file", str(samples_file), "--reference-noise", "1e-3"]
        + ["--seed", "1", "--out", str(out)]
    )
    printed = capsys.readouterr().out
    assert code == 0, printed
    assert "references estimated online from 20001 samples" in printed
    assert "noise sd 0.001" in printed and "certificate: PASSED" in printed
    disturbance = re.search(r"sup \|d\| +(\S+)", printed)
    ratio = re.search(r"int c e\^\(-alpha \(t-s\)\) \|d\(s\)\| ds   max ratio (\S+)", printed)
    assert disturbance is not None and float(disturbance.group(1)) > 0, printed
    assert ratio is not None and float(ratio.group(1)) <= 1.0, printed
    assert (out / f"{name}_references.png").is_file()


@pytest.mark.parametrize(
    ("content", "message"),
    [
        ("t,o1x,o1y,o2x\n0,1,2,3\n", "(header): missing column 'o2y'"),
        ("t,o1x,o1y,o2x,o2y\n0,1,2,3,4\n0.5,1,2,3,4\n0.4,1,2,3,4\n", "line 4: t must increase"),
        ("t,o1x,o1y,o2x,o2y\n0,1,2,3,4\n30,1,nan,3,4\n", "line 3: o1y = nan is not finite"),
        ("t,o1x,o1y,o2x,o2y\n0,1,2,3,4\n10,1,2,3,4\n", "the samples cover [0, 10]"),
        ("t,o1x,o1y,o2x,o2y\n0,1,x,3,4\n30,1,2,3,4\n", "line 2: o1y: expected a number"),
    ],
)
def test_bad_reference_files_are_one_line_errors_that_write_nothing(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], content: str, message: str
) -> None:
    from tvopt_codegen.cli import main
    from tvopt_codegen.errors import EXIT_BAD_SPEC

    samples_file = tmp_path / "bad.csv"
    samples_file.write_text(content)
    out = tmp_path / "out"
    out.mkdir()
    code = main(
        ["simulate", "unicycle_switch_refs", "--reference-file", str(samples_file), "--out"]
        + [str(out)]
    )
    captured = capsys.readouterr()
    assert code == EXIT_BAD_SPEC
    lines = captured.err.strip().splitlines()
    assert len(lines) == 1 and message in lines[0] and str(samples_file) in lines[0], lines
    assert list(out.iterdir()) == []


def test_the_report_lists_references_order_and_estimator(tmp_path: Path) -> None:
    from tvopt_codegen.lowering.ir import lower
    from tvopt_codegen.report import render_report

    d = derivation("pvtol_refs")
    text = render_report(d, lower(d), None, ("md",))["pvtol_refs_report.md"]
    assert "References measured at run time" in text
    assert "derivative q = 4" in text and "levant differentiator" in text
    assert "| ox | ox, ox', ox'', ox''', ox^(4) |" in text


@pytest.mark.parametrize(
    "spec",
    [
        "integrator_refs",
        # unicycle_switch_refs: its run on the same samples is the noiseless one of
        # test_simulate_from_samples_tracks_and_the_iss_bound_holds_at_every_noise, which
        # makes this test's checks on it at 15 s.
        "two_unicycles_barrier_refs",
        "unicycle_ring_refs",
        # A figure-eight with a wall term (a barrier): the case the linear estimator of the
        # law's own order left at 0.8% of the initial error.
        str(Path(__file__).resolve().parent / "specs" / "figure8_wall.toml"),
    ],
)
def test_the_default_estimator_on_clean_1khz_samples_ends_within_1e3_of_the_start(
    spec: str,
) -> None:
    """One derivative beyond the law's, and a first-order hold between the samples."""
    from tvopt_codegen.simulation import resolve_options, simulate
    from tvopt_codegen.simulation.references import exact_jets, sampled_source

    d = derivation(spec)
    assert d.spec.estimator is not None and d.spec.estimator.kind == "linear"
    mod = module(spec)
    assert len(mod._ESTIMATOR_GAINS) == d.jet.reference_order + 2
    params = dict(d.spec.parameters)
    truth = exact_jets(d, params)
    # 15 s at most: past the start's transient, and a stricter test than the horizon's
    # end (docs/references.md gives the whole horizon's figures, made by make
    # reference-noise).
    horizon = min(d.spec.t_final, 15.0)
    times = np.arange(0.0, horizon + 5e-4, 1e-3)
    values = np.array([truth(float(t))[:, 0] for t in times]).T
    source = sampled_source(d, mod, {}, times, values)
    options = resolve_options(d, t_final=horizon, points=201)
    result = simulate(d, mod, options, references=source)
    assert result.error[-1] <= 1e-3 * result.error[0]


@pytest.mark.parametrize("name", ["unicycle_switch_refs", "pvtol_refs"])
def test_a_gap_the_estimator_has_forgotten_is_one_bounded_exact_step(
    name: str, tmp_path_factory: pytest.TempPathFactory
) -> None:
    """After a gap of 80 / bandwidth the linear differentiator's state is the steady state
    on the samples' line: set in one step (a Unix-time gap took hours in Python, and past
    1.2e17 s the C step count overflowed a long), the same bits in both backends, and what
    integrating over the gap gives."""
    import time  # noqa: PLC0415

    from tvopt_codegen.spec.estimator import FORGETTING_GAP  # noqa: PLC0415

    py, c = module(name), c_module(name, tmp_path_factory)
    if py.ESTIMATOR != "linear":
        pytest.skip("Levant's differentiator takes one Euler step whatever the gap")
    start = exact_jets(name, 0.0)[:, 0]
    later = start + np.random.default_rng(5).normal(size=start.shape)
    for gap in (1.7e9, 1e20, 1e300):
        jets = []
        for m in (c, py):  # the C first: it returned the stale estimate, Python hung
            began = time.perf_counter()
            jets.append(m.ReferenceEstimator(start).update(gap, later))
            np.testing.assert_array_equal(jets[-1][:, 0], later)
            np.testing.assert_array_equal(jets[-1][:, 1], (later - start) / gap)
            assert not np.any(jets[-1][:, 2:])
            assert time.perf_counter() - began < 0.5
        np.testing.assert_array_equal(jets[0], jets[1])
    # Just past the gap: the one step is what the integration in two halves gives (the
    # middle sample on the same line, so the estimator sees the same input).
    h = 1.01 * FORGETTING_GAP / py.ESTIMATOR_BANDWIDTH
    for m in (py, c):
        direct = m.ReferenceEstimator(start).update(h, later)
        halves = m.ReferenceEstimator(start)
        halves.update(h / 2, (start + later) / 2)
        np.testing.assert_allclose(halves.update(h, later), direct, rtol=0, atol=1e-12)
