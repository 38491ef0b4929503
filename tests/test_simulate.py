"""The simulate command: certificate, y*, output files, and failure modes."""

from __future__ import annotations

import csv
import io
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np
import pytest

from tvopt_codegen import simulation as sim
from tvopt_codegen.cli import main
from tvopt_codegen.derivation import derive
from tvopt_codegen.errors import EXIT_CERTIFICATE
from tvopt_codegen.lowering.ir import lower
from tvopt_codegen.spec import load_spec

from .conftest import ALL_SPECS, derivation, module, write_spec


@pytest.fixture(scope="module")
def results() -> dict[str, sim.Result]:
    out = {}
    for spec in ALL_SPECS:
        d = derivation(spec)
        out[spec] = sim.simulate(d, module(spec), sim.resolve_options(d))
    return out


@pytest.mark.parametrize("spec", ALL_SPECS)
def test_certificate_passes_for_every_example(results: dict[str, sim.Result], spec: str) -> None:
    result = results[spec]
    assert result.passed, result.failures
    assert result.deviation < 1e-6
    assert result.bound_ratio <= 1.0
    assert result.error[-1] < 1e-3 * result.error[0]
    if derivation(spec).closed_loop.integral_states:
        # Started bumplessly, the integrals' own (slowest) mode is not excited: E decays
        # with the other poles, faster than alpha.
        assert result.fitted_rate > 1.1 * result.alpha
    else:
        assert result.fitted_rate == pytest.approx(result.alpha, rel=0.1)


def test_target_matches_closed_form_integrator(results: dict[str, sim.Result]) -> None:
    r = results["integrator"]
    t = r.t
    expected = np.array([2 + 0.8 * t - 0.05 * t**2, -1 + 0.5 * t + 0.02 * t**2 - 0.001 * t**3])
    np.testing.assert_allclose(r.target, expected, atol=1e-8, rtol=0)


def test_target_matches_closed_form_switching(results: dict[str, sim.Result]) -> None:
    r = results["unicycle_switch"]
    t = r.t
    s = 0.5 - 0.5 * np.tanh((t - 10.0) / 1.5)
    o1 = np.array([-5 + 0.6 * t - 0.01 * t**2, -5 + 0.5 * t + 0.02 * t**2 - 0.001 * t**3])
    o2 = np.array([5 - 0.3 * t - 0.01 * t**2, -3 + 0.4 * t - 0.015 * t**2 + 0.0002 * t**3])
    np.testing.assert_allclose(r.target, s * o1 + (1 - s) * o2, atol=1e-8, rtol=0)


def test_theorem_constants(results: dict[str, sim.Result]) -> None:
    r = results["unicycle_switch"]
    # companion([-1.5, -2.5]) has eigenvalues -1, -1.5: distinct, so alpha is exact.
    assert r.alpha == pytest.approx(1.0) and r.alpha_exact
    assert r.c == pytest.approx(5.0990195, rel=1e-6)  # sup |expm(Ht)| e^t, computed
    assert r.m_f == pytest.approx(2.0)
    assert r.C == pytest.approx(r.c * np.linalg.norm(r.E[0]) / r.m_f)


def test_wrong_controller_fails_the_certificate(
    tmp_path: Path,
    unicycle_text: str,
    monkeypatch: pytest.MonkeyPatch,
    capsys: pytest.CaptureFixture[str],
) -> None:
    """A controller built for other poles than the spec claims: E leaves expm(Ht) E(0)."""
    wrong = load_spec(write_spec(tmp_path, unicycle_text.replace("[-1.0, -1.5]", "[-2.0, -3.0]")))
    impostor = sim.load_controller(lower(derive(wrong)))
    d = derivation("unicycle_switch")
    result = sim.simulate(d, impostor, sim.resolve_options(d))
    assert not result.passed
    assert any("deviates from expm(H t) E(0)" in f for f in result.failures)

    monkeypatch.setattr(sim, "load_controller", lambda kernels, backend: impostor)
    out = tmp_path / "out"
    assert main(["simulate", "unicycle_switch", "--out", str(out)]) == EXIT_CERTIFICATE
    assert "certificate: FAILED" in capsys.readouterr().out
    assert (out / "unicycle_switch_certificate.txt").read_text().count("FAILED") == 1


def test_output_files_load_back(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "run"
    assert main(["simulate", "integrator", "--out", str(out), "--points", "51"]) == 0
    assert "certificate: PASSED" in capsys.readouterr().out
    names = sorted(p.name for p in out.iterdir())
    stems = ["paths", "convergence", "inputs"]
    expected = [f"integrator_{s}.{f}" for s in stems for f in ("png", "svg")]
    expected += [
        "integrator_trajectory.csv",
        "integrator_trajectory.npz",
        "integrator_certificate.txt",
        ".tvopt-manifest.json",
    ]
    assert names == sorted(expected)
    rows = list(csv.reader(io.StringIO((out / "integrator_trajectory.csv").read_text())))
    assert rows[0] == [
        "t",
        "x1",
        "x2",
        "u_u1",
        "u_u2",
        "y_y1",
        "y_y2",
        "ystar_y1",
        "ystar_y2",
        "E0_y1",
        "E0_y2",
    ]
    assert len(rows) == 52 and all(len(r) == 11 for r in rows)
    data = np.load(out / "integrator_trajectory.npz")
    assert data["t"].shape == (51,)
    assert data["states"].shape == (2, 51)
    assert data["inputs"].shape == (2, 51)
    assert data["y"].shape == data["y_star"].shape == (2, 51)
    assert data["E"].shape == (51, 1, 2)
    assert list(data["state_names"]) == ["x1", "x2"]
    for stem in stems:
        png = (out / f"integrator_{stem}.png").read_bytes()
        assert png.startswith(b"\x89PNG\r\n\x1a\n")
        root = ET.fromstring((out / f"integrator_{stem}.svg").read_bytes())
        assert root.tag.endswith("svg")
        # The PNG is cut from the one rendering along the box the SVG is written in:
        # the same picture, 120 pixels to the SVG's 72 points per inch.
        width, height = int.from_bytes(png[16:20], "big"), int.from_bytes(png[20:24], "big")
        points = [float(root.attrib[key].removesuffix("pt")) for key in ("width", "height")]
        assert abs(width - points[0] * 120 / 72) <= 1 and abs(height - points[1] * 120 / 72) <= 1
    # Log axes are labelled in plain text (10⁻³), never through mathtext.
    svg = (out / "integrator_convergence.svg").read_text()
    assert "10\u207b" in svg and "mathdefault" not in svg


def test_command_line_overrides(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "o"
    code = main(
        [
            "simulate",
            "unicycle_switch",
            "--out",
            str(out),
            "--t-final",
            "4",
            "--initial",
            "x2=2.5",
            "--param",
            "a=2",
            "--points",
            "21",
        ]
    )
    assert code == 0
    data = np.load(out / "unicycle_switch_trajectory.npz")
    assert data["t"][-1] == 4.0
    assert data["states"][1, 0] == 2.5
    capsys.readouterr()
    for args, message in (
        (["--initial", "phi=1"], "--initial: unknown state 'phi'"),
        (["--param", "c=1"], "--param: unknown parameter 'c'"),
        (["--param", "a"], "--param: expected NAME=VALUE"),
        (["--t-final", "-1"], "--t-final: must be positive"),
        (["--rtol", "0"], "--rtol: must be positive"),
    ):
        fresh = tmp_path / "never"
        assert main(["simulate", "unicycle_switch", "--out", str(fresh), *args]) == 2
        err = capsys.readouterr().err
        assert message in err and err.count("\n") == 1
        assert not fresh.exists()


def test_interrupt_leaves_no_file(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    def interrupted(*args: object, **kwargs: object) -> None:
        raise KeyboardInterrupt

    monkeypatch.setattr(sim, "simulate", interrupted)
    out = tmp_path / "o"
    out.mkdir()
    (out / "keep.txt").write_text("mine")
    assert main(["simulate", "integrator", "--out", str(out)]) == 130
    assert sorted(p.name for p in out.iterdir()) == ["keep.txt"]
    assert "interrupted" in capsys.readouterr().err


def test_progress_is_reported_on_long_runs(monkeypatch: pytest.MonkeyPatch) -> None:
    clock = iter(np.arange(0.0, 1e6, 0.7))
    monkeypatch.setattr(sim.run.time, "perf_counter", lambda: float(next(clock)))
    seen: list[tuple[float, float]] = []
    d = derivation("integrator")
    sim.simulate(
        d,
        module("integrator"),
        sim.resolve_options(d, t_final=2.0, points=11),
        progress=lambda t, total: seen.append((t, total)),
    )
    assert seen and all(total == 2.0 and 0 <= t <= 2.0 for t, total in seen)


def test_rerun_replaces_its_own_outputs_but_not_edited_ones(tmp_path: Path) -> None:
    out = tmp_path / "o"
    args = ["simulate", "integrator", "--out", str(out), "--points", "11", "--t-final", "1"]
    assert main(args) == 0
    assert main([*args[:-1], "2"]) == 0  # different run, same names: its own files, replaced
    csv_path = out / "integrator_trajectory.csv"
    csv_path.write_text(csv_path.read_text() + "# my note\n")
    assert main(args) == 4
    assert csv_path.read_text().endswith("# my note\n")


def test_simulate_with_the_c_backend(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    monkeypatch.setenv("TVOPT_CODEGEN_CACHE", str(tmp_path / "cache"))
    out = tmp_path / "c"
    assert main(["simulate", "unicycle_switch", "--backend", "c", "--out", str(out)]) == 0
    text = capsys.readouterr().out
    assert "certificate: PASSED" in text
    c_run = np.load(out / "unicycle_switch_trajectory.npz")
    # The Python backend's run, in this process: the command's run with the same options
    # writes these states to the bit (its files and figures are other tests' subject).
    d = derivation("unicycle_switch")
    py_run = sim.simulate(d, module("unicycle_switch"), sim.resolve_options(d))
    np.testing.assert_allclose(c_run["states"], py_run.states, rtol=1e-8, atol=1e-8)


def test_the_dormand_prince_tableau_is_scipys_bit_for_bit() -> None:
    from scipy.integrate import RK45

    from tvopt_codegen.maths import dopri

    for name in "CABEP":
        assert np.array_equal(getattr(dopri, name), getattr(RK45, name)), name


@pytest.mark.parametrize("spec", ["pvtol", "unicycle_switch", "two_unicycles_barrier"])
def test_simulates_rk45_steps_and_dense_output_are_solve_ivps_bit_for_bit(spec: str) -> None:
    from scipy.integrate import solve_ivp

    from tvopt_codegen.maths import dopri

    m = module(spec)
    start = np.array(m.DEFAULT_STATE, dtype=float)
    ours = dopri.integrate(m.rhs, 6.0, start, 1e-8, 1e-10)
    theirs = solve_ivp(m.rhs, (0.0, 6.0), start, rtol=1e-8, atol=1e-10, dense_output=True)
    assert ours.success and ours.message == theirs.message
    assert ours.nfev == theirs.nfev and len(ours.t) > 20
    assert np.array_equal(ours.t, theirs.t) and np.array_equal(ours.y, theirs.y)
    # Between steps, at the steps (the earlier step's quartic) and in any order.
    probe = np.concatenate([np.linspace(0.0, 6.0, 401), ours.t[::3]])[::-1]
    assert ours.sol is not None
    assert np.array_equal(ours.sol(probe), theirs.sol(probe))
    for t in (0.0, float(ours.t[5]), 2.5, 6.0):
        assert np.array_equal(ours.sol(t), theirs.sol(t))


def test_a_run_that_blows_up_ends_as_scipys_does() -> None:
    from scipy.integrate import solve_ivp

    from tvopt_codegen.maths import dopri

    def field(_t: float, y: np.ndarray) -> np.ndarray:
        return y * y  # y = 1 / (1 - t): infinite at t = 1

    with np.errstate(all="ignore"):
        ours = dopri.integrate(field, 2.0, np.array([1.0]), 1e-8, 1e-10)
        theirs = solve_ivp(field, (0.0, 2.0), [1.0], rtol=1e-8, atol=1e-10, dense_output=True)
    assert not ours.success and ours.message == theirs.message == dopri.TOO_SMALL
    assert np.array_equal(ours.t, theirs.t) and 0.99 < ours.t[-1] < 1.01
    assert ours.nfev == theirs.nfev


def test_simulate_imports_neither_scipy_nor_pyplot(tmp_path: Path) -> None:
    """RK45 is :mod:`tvopt_codegen.maths.dopri`; expm(H t) of the k x k companion is mpmath's."""
    import subprocess
    import sys

    code = (
        "import sys\nfrom tvopt_codegen.cli import main\n"
        f"main(['simulate', 'pvtol', '--out', {str(tmp_path / 'run')!r}, '--points', '41'])\n"
        "print(sorted(m for m in sys.modules if m.split('.')[0] == 'scipy' "
        "or m == 'matplotlib.pyplot'))"
    )
    done = subprocess.run([sys.executable, "-c", code], check=True, capture_output=True, text=True)
    assert done.stdout.splitlines()[-1] == "[]"


@pytest.mark.parametrize(
    "spec", ["unicycle_switch", "unicycle_switch_refs", "arm_on_line", "planar_arm3"]
)
def test_the_kernels_simulate_calls_give_the_public_functions_bits(spec: str) -> None:
    """simulation.direct: the kernels behind rhs, control, optimality_error, hessian and
    plant answer with the public functions' own numbers, with and without parameter
    overrides; where the public function refuses (a state that is not finite), the kernel
    declines and the public function's documented error is what a loop meets."""
    from tvopt_codegen.simulation import direct
    from tvopt_codegen.simulation.references import exact_jets

    d, mod = derivation(spec), module(spec)
    rng = np.random.default_rng(11)
    base = np.array(mod.DEFAULT_STATE, dtype=float)
    jets = exact_jets(d, {}) if getattr(mod, "REFERENCE_NAMES", ()) else None
    first = next(iter(mod.PARAMETERS), None)
    for params in (None, {} if first is None else {first: 1.25 * mod.PARAMETERS[first]}):
        given = params or None
        for name in ("rhs", "control", "optimality_error", "hessian"):
            kernel = direct.point_kernel(mod, name, given)
            function = direct.point_function(mod, name, given)
            assert kernel is not None, name
            for t in (0.0, 1.7):
                refs = None if jets is None else jets(t)
                extra = {} if refs is None else {"refs": refs}
                point = base + 0.05 * rng.standard_normal(len(base))
                if name == "hessian":
                    point = point[: len(mod.OUTPUT_NAMES)]
                want = getattr(mod, name)(t, point, given, **extra)
                assert np.array_equal(function(t, point, **extra), want), name
                flat = None if refs is None else refs.ravel().tolist()
                assert np.array_equal(np.reshape(kernel(t, point.tolist(), flat), want.shape), want)
        plant = direct.plant_kernel(mod, given)
        assert plant is not None
        n, m = len(mod.PLANT_STATE_NAMES), len(mod.INPUT_NAMES)
        x, u = base[:n] + 0.1, rng.standard_normal(m)
        assert np.array_equal(plant(0.5, x, u), mod.plant(0.5, x, u, given))
        assert plant(0.5, np.full(n, np.nan), u) is None
        # plant_function: the kernel's bits, and the public function's error where it
        # declines.
        field = direct.plant_function(mod, given)
        assert np.array_equal(field(0.5, x, u), mod.plant(0.5, x, u, given))
        with pytest.raises(mod.NonFiniteInputError):
            field(0.5, np.full(n, np.nan), u)
    bad = base.copy()
    bad[0] = np.nan
    refs = None if jets is None else jets(0.0)
    flat = None if refs is None else refs.ravel().tolist()
    assert direct.point_kernel(mod, "rhs", None)(0.0, bad.tolist(), flat) is None  # type: ignore[misc]
    with pytest.raises(mod.NonFiniteInputError):
        direct.point_function(mod, "rhs", None)(0.0, bad, *(() if refs is None else (refs,)))


def test_only_a_generated_python_modules_own_functions_have_kernels(
    tmp_path_factory: pytest.TempPathFactory,
) -> None:
    """The C backend's module, and a module whose public function was replaced (a fake,
    a wrapper that counts calls), are called through their public functions."""
    import types

    from tvopt_codegen.simulation import direct

    from .test_c_backend import c_module

    c = c_module("pvtol", tmp_path_factory)
    assert direct.point_kernel(c, "rhs", None) is None and direct.plant_kernel(c, None) is None
    real = module("pvtol")
    fake = types.ModuleType("fake")
    fake.__dict__.update({k: v for k, v in vars(real).items() if not k.startswith("__")})
    assert direct.point_kernel(fake, "rhs", None) is not None  # the module's own rhs
    fake.rhs = lambda t, s, params=None: real.rhs(t, s, params)
    fake.plant = lambda t, x, u, params=None: real.plant(t, x, u, params)
    assert direct.point_kernel(fake, "rhs", None) is None
    assert direct.plant_kernel(fake, None) is None
    assert direct.point_kernel(real, "rhs", {"nope": 1.0}) is None  # rhs says why


def test_the_sample_grid_steps_on_lists_as_on_arrays() -> None:
    """The run on the reference samples' grid steps on lists of floats: the same bits as
    its form on arrays, states, rates and interpolant."""
    from tvopt_codegen.simulation import direct, run
    from tvopt_codegen.simulation.references import exact_jets, sampled_source

    spec = "unicycle_switch_refs"
    d, mod = derivation(spec), module(spec)
    truth = exact_jets(d, {})
    times = np.arange(0.0, 1.0 + 5e-4, 1e-3)
    values = np.array([truth(float(t))[:, 0] for t in times]).T
    source = sampled_source(d, mod, {}, times, values, 1e-3, seed=2)

    def field(t: float, s: np.ndarray) -> np.ndarray:
        return np.asarray(mod.rhs(t, s, None, refs=source.jets(t)))

    kernel = direct.point_kernel(mod, "rhs", None)
    assert kernel is not None

    def lists(t: float, s: list[float]) -> list[float]:
        answer = kernel(t, s, source.flat_jets(t))
        assert answer is not None
        return answer

    start = np.array(mod.DEFAULT_STATE, dtype=float)
    # Samples farther apart than MAX_GRID_STEP are stepped between too.
    sparse = np.concatenate([times[:300], times[320::50]])
    for grid in (times, sparse):
        arrays = run._on_the_sample_grid(field, 0.9, start, grid)
        on_lists = run._on_the_sample_grid_lists(lists, 0.9, start, grid)
        assert np.array_equal(arrays.t, on_lists.t) and len(arrays.t) > 100
        assert np.array_equal(arrays.y, on_lists.y)
        probe = np.linspace(0.0, 0.9, 333)
        assert np.array_equal(arrays.sol(probe), on_lists.sol(probe))


def test_the_unrolled_taylor_shifts_are_the_loops_bits() -> None:
    """references._taylor's written-out forms (jets of 2 to 5 entries) give the general
    loop's bits, its order of operations kept: signed zeros, infinities, NaN, overflow."""
    from tvopt_codegen.simulation import references

    def loop(xi: list[list[float]], h: float) -> list[list[float]]:
        """The general loop (every jet length _UNROLLED has no form for), on h's terms."""
        return references._shifted(xi, references._terms(len(xi[0]) if xi else 0, h))

    special = [0.0, -0.0, np.inf, -np.inf, np.nan, 1e308, -1e308, 5e-324, 1.0]
    rng = np.random.default_rng(4)
    for order in range(1, 8):
        for _ in range(300):
            xi = [
                [
                    float(rng.choice(special))
                    if rng.random() < 0.3
                    else float(rng.standard_normal() * 10.0 ** rng.integers(-5, 5))
                    for _ in range(order)
                ]
                for _ in range(int(rng.integers(0, 4)))
            ]
            h = float(rng.choice([0.0, -0.0, 1e-3, -2.5e-4, 1e300, np.inf, 0.37]))
            got, want = references._taylor(xi, h), loop(xi, h)
            assert np.array(got).tobytes() == np.array(want).tobytes(), (xi, h)
