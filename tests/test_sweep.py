"""Monte-Carlo sweeps: the compiled loop against scipy, the statistics, the command."""

from __future__ import annotations

import math
import os
import socket
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from scipy.integrate import solve_ivp
from scipy.stats import binomtest

from tests.conftest import derivation, kernels, module
from tvopt_codegen import sweep
from tvopt_codegen.cli import main
from tvopt_codegen.contract import Status
from tvopt_codegen.errors import EXIT_BAD_SPEC, MissingExtraError, SpecError
from tvopt_codegen.simulation import minimizer_path
from tvopt_codegen.sweep import (
    Distribution,
    SweepOptions,
    clopper_pearson_upper,
    draw,
    loop_for,
    parse_distribution,
    run_sample,
    sweep_program,
)

pq = pytest.importorskip("pyarrow.parquet")
xr = pytest.importorskip("xarray")


def program(name: str) -> sweep.SweepProgram:
    return _programs.setdefault(name, sweep_program(kernels(name)))


_programs: dict[str, sweep.SweepProgram] = {}


def _columns(p: sweep.SweepProgram) -> dict[str, slice]:
    n, m, nu = len(p.state_names), len(p.output_names), len(p.input_names)
    return {
        "s": slice(1, 1 + n),
        "x": slice(1, 1 + len(p.plant_state_names)),
        "y": slice(1 + n, 1 + n + m),
        "target": slice(1 + n + m, 1 + n + 2 * m),
        "u": slice(1 + n + 2 * m, 1 + n + 2 * m + nu),
    }


# ------------------------------------------------------------------ the compiled loop


def test_continuous_loop_takes_scipys_steps_and_matches_its_states() -> None:
    """Dormand-Prince with scipy's error control: the same steps, the same states."""
    p = program("unicycle_switch")
    options = SweepOptions(samples=1, seed=3, t_final=20.0, points=101)
    sample = draw(p, options, 0)
    outcome, rows, info = loop_for(p).run(options, sample)
    assert outcome == Status.OK
    mod = module("unicycle_switch")
    solution = solve_ivp(
        mod.rhs,
        (0.0, 20.0),
        sample.s0,
        method="RK45",
        rtol=options.rtol,
        atol=options.atol,
        t_eval=rows[:, 0],
    )
    # scipy: 6 evaluations per step (accepted or rejected) and 2 for the first step.
    assert info[2] + info[3] == (solution.nfev - 2) / 6
    assert np.max(np.abs(solution.y.T - rows[:, _columns(p)["s"]])) < 1e-12
    # y* by the same Newton path as simulate's certificate.
    c = _columns(p)
    target = minimizer_path(mod, rows[:, 0], rows[-1, c["y"]], {})
    assert np.max(np.abs(target.T - rows[:, c["target"]])) < 1e-10


def test_the_target_path_jumps_where_newton_converges_and_agrees_in_both_languages() -> None:
    """y* of a barrier's f0 by extrapolation and undamped Newton, in C as in Python.

    Each row's y* is exact to f0's rounding (a Newton step from it is below 1e-12), the
    careful substeps run only where the jump was refused, and the compiled loop's target
    column is the Python path's.
    """
    name = "two_unicycles_barrier"
    p = program(name)
    options = SweepOptions(samples=1, seed=5, t_final=10.0, points=201)
    outcome, rows, _info = loop_for(p).run(options, draw(p, options, 0))
    assert outcome == Status.OK
    c = _columns(p)
    mod = module(name)
    calls = {"gradient": 0}

    class Counted:
        def __getattr__(self, attribute: str) -> object:
            if attribute == "gradient":
                calls["gradient"] += 1
            return getattr(mod, attribute)

    ts = rows[:, 0]
    target = minimizer_path(Counted(), ts, rows[-1, c["y"]], {})  # type: ignore[arg-type]
    assert np.max(np.abs(target.T - rows[:, c["target"]])) < 1e-12
    steps = [
        np.linalg.norm(np.linalg.solve(mod.hessian(t, y, {}), mod.gradient(t, y, {})))
        for t, y in zip(ts, target.T, strict=True)
    ]
    assert max(steps) < 1e-12
    # Five damped substeps of several iterations per row took about 18 gradients a row.
    assert calls["gradient"] < 5 * len(ts)


def test_mismatch_and_saturation_match_an_independent_loop() -> None:
    """The true plant's parameters and clipped inputs, against solve_ivp on the model."""
    p = program("pvtol")
    options = SweepOptions(
        samples=1,
        seed=0,
        t_final=6.0,
        plant_params=(("m", Distribution("fixed", (1.15,))), ("J", Distribution("fixed", (0.9,)))),
        limits=(("torque", -0.5, 0.5),),
        points=61,
    )
    sample = draw(p, options, 0)
    outcome, rows, _ = loop_for(p).run(options, sample)
    assert outcome == Status.OK
    mod = module("pvtol")
    model = derivation("pvtol").model
    plant_params = dict(zip(p.param_names, sample.pp, strict=True))
    nx = len(p.plant_state_names)

    def rhs(t: float, s: np.ndarray) -> np.ndarray:
        ds = np.array(mod.rhs(t, s))
        u = np.clip(mod.control(t, s), [-np.inf, -0.5], [np.inf, 0.5])
        ds[:nx] = mod.plant(t, s[:nx], u, plant_params)
        return ds

    solution = solve_ivp(
        rhs,
        (0.0, 6.0),
        sample.s0,
        rtol=options.rtol,
        atol=options.atol,
        t_eval=rows[:, 0],
        method="RK45",
    )
    assert np.max(np.abs(solution.y.T - rows[:, _columns(p)["s"]])) < 1e-9
    assert model.params  # m and J are the spec's parameters
    result = run_sample(p, options, 0)
    assert result.row["time_saturated"] > 0
    assert result.row["max_abs_torque"] > 0.5  # commanded, before the limit
    assert result.row["nominal"] is False and result.row["certificate_holds"] is None


def test_sampled_loop_matches_the_stateful_controller_under_scipy() -> None:
    """Zero-order hold every H with noisy measurements: the generated Controller and
    solve_ivp per interval give the same plant states."""
    p = program("unicycle_switch")
    h = 0.05
    options = SweepOptions(samples=2, seed=11, t_final=4.0, noise=1e-3, sample_time=h, points=81)
    sample = draw(p, options, 1)
    assert sample.noise is not None and sample.noise.shape == (81, 3)
    outcome, rows, _ = loop_for(p).run(options, sample)
    assert outcome == Status.OK
    mod = module("unicycle_switch")
    nx = len(p.plant_state_names)
    x = sample.s0[:nx].copy()
    controller = mod.Controller(x + sample.noise[0], 0.0, sample.s0[nx:])
    u = controller.u
    states = [x.copy()]
    for k in range(80):
        solution = solve_ivp(
            lambda t, x, u=u: mod.plant(t, x, u),
            (k * h, (k + 1) * h),
            x,
            method="RK45",
            rtol=options.rtol,
            atol=options.atol,
        )
        x = solution.y[:, -1]
        states.append(x.copy())
        u = controller.step((k + 1) * h, x + sample.noise[k + 1])
    assert np.max(np.abs(np.array(states) - rows[:, _columns(p)["x"]])) < 1e-9
    quiet = run_sample(p, SweepOptions(samples=2, seed=11, t_final=4.0, sample_time=h), 1)
    assert quiet.row["final_error"] != run_sample(p, options, 1).row["final_error"]


def test_a_singular_law_is_an_outcome_not_an_error() -> None:
    """PVTOL at zero thrust: R is singular; the sample says so and the sweep goes on."""
    p = program("pvtol")
    options = SweepOptions(
        samples=1, seed=0, t_final=2.0, initial=(("thrust", Distribution("fixed", (0.0,))),)
    )
    result = run_sample(p, options, 0)
    assert result.row["status"] == "singular_decoupling"
    assert math.isnan(result.row["final_error"])


def test_a_sweep_whose_nominal_plant_fails_at_its_start_is_refused(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """PVTOL started at zero thrust: every sample would fail for the model's one reason."""
    p = program("pvtol")
    still = (("thrust", Distribution("fixed", (0.0,))),)
    spread = (("m", Distribution("normal", (1.0, 0.1))),)
    options = SweepOptions(samples=4, seed=0, t_final=2.0, initial=still, plant_params=spread)
    assert sweep.nominal_start(p, options) is Status.SINGULAR_DECOUPLING
    # Each sample fails alike: the table would be 100% failures as an ordinary outcome.
    results = [run_sample(p, options, i) for i in range(4)]
    assert {r.row["status"] for r in results} == {"singular_decoupling"}
    # The centre of a spread start: uniform(0, 20) starts at thrust 10, where R is regular.
    around = (("thrust", Distribution("uniform", (0.0, 20.0))),)
    assert sweep.nominal_start(p, SweepOptions(4, 0, 2.0, initial=around)) is Status.OK
    assert sweep.nominal_start(p, SweepOptions(4, 0, 2.0, sample_time=0.01)) is Status.OK
    # The check's horizon (1e-9 of the sweep's) never underflows to 0 (then: nonfinite_input).
    assert sweep.nominal_start(p, SweepOptions(4, 0, 5e-324)) is Status.OK
    out = tmp_path / "out"
    args = ["sweep", "pvtol", "--samples", "4", "--initial", "thrust=0", "--workers", "1"]
    code = main([*args, "--plant-param", "m=normal(1, 0.1)", "--out", str(out)])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 3 and len(err) == 1, err
    assert "sweep: the nominal plant fails at its start" in err[0]
    assert "singular_decoupling (the decoupling matrix R is singular)" in err[0]
    assert not out.exists()
    # A run that fails everywhere later on is tabulated, under a headline that says so.
    text = sweep.format_summary("pvtol", options, sweep.summarize(results, 4, False))
    assert text.splitlines()[2].startswith("**Every sample failed** (`singular_decoupling`)")
    ok = sweep.summarize([run_sample(p, SweepOptions(1, 0, 2.0), 0)], 1, False)
    assert "Every sample failed" not in sweep.format_summary("pvtol", options, ok)


def test_nominal_samples_meet_the_certificate_and_mismatch_degrades_tracking() -> None:
    p = program("unicycle_switch")
    spread = (("x1", parse_distribution("normal(-5, 1)", "--initial", "x1")),)
    nominal = SweepOptions(samples=6, seed=5, t_final=20.0, initial=spread)
    rows = [run_sample(p, nominal, i).row for i in range(6)]
    assert all(r["nominal"] and r["certificate_holds"] for r in rows)
    assert max(r["final_error"] for r in rows) < 1e-6
    q = program("pvtol")
    mismatched = SweepOptions(
        samples=6, seed=5, t_final=12.0, plant_params=(("m", Distribution("normal", (1.0, 0.1))),)
    )
    worse = [run_sample(q, mismatched, i).row for i in range(6)]
    ideal = run_sample(q, SweepOptions(samples=1, seed=5, t_final=12.0), 0).row
    assert ideal["nominal"] and ideal["certificate_holds"]
    assert all(r["status"] == "ok" and not r["nominal"] for r in worse)
    assert min(r["final_error"] for r in worse) > 100 * ideal["final_error"]


# ------------------------------------------------------------------ draws and statistics


def test_distributions_parse_and_refuse_in_one_line() -> None:
    assert parse_distribution("2.5", "--param", "a") == Distribution("fixed", (2.5,))
    assert parse_distribution(" normal(1, 0.1) ", "--param", "a") == Distribution(
        "normal", (1.0, 0.1)
    )
    assert parse_distribution("uniform(-1,1)", "--param", "a").kind == "uniform"
    assert parse_distribution("lognormal(0, 0.2)", "--param", "a").kind == "lognormal"
    for bad, words in (
        ("normal(1)", "takes two numbers"),
        ("gauss(0, 1)", "unknown distribution"),
        ("normal(0, -1)", "sd must be >= 0"),
        ("uniform(2, 1)", "lo <= hi"),
        ("normal(0, 1", "malformed"),
        ("abc", "not a number"),
        ("nan", "finite"),
    ):
        with pytest.raises(SpecError, match=words) as caught:
            parse_distribution(bad, "--param", "a")
        assert "\n" not in str(caught.value) and "--param" in str(caught.value)


def test_each_sample_draws_alone_from_its_recorded_seed() -> None:
    p = program("pvtol")
    options = SweepOptions(
        samples=50,
        seed=7,
        t_final=1.0,
        initial=(("x", Distribution("uniform", (-1.0, 1.0))),),
        plant_params=(("m", Distribution("lognormal", (0.0, 0.1))),),
    )
    first = draw(p, options, 37)
    again = draw(p, options, 37)
    assert first.seed == again.seed and first.values == again.values
    rng = np.random.default_rng(first.seed)
    assert first.values["initial.x"] == rng.uniform(-1.0, 1.0)
    assert first.values["plant.m"] == rng.lognormal(0.0, 0.1)
    assert len({draw(p, options, i).seed for i in range(50)}) == 50
    assert 0 <= first.seed < 2**63


def test_clopper_pearson_upper_bound() -> None:
    # 0 failures in 299 runs: below 1% (the example), exactly 1 - 0.05^(1/299).
    assert clopper_pearson_upper(0, 299) == pytest.approx(1 - 0.05 ** (1 / 299), rel=1e-12)
    assert clopper_pearson_upper(0, 299) < 0.01
    # One-sided 95% = the upper end of the two-sided exact 90% interval.
    exact = binomtest(5, 100).proportion_ci(0.90, method="exact").high
    assert clopper_pearson_upper(5, 100) == pytest.approx(exact, rel=1e-10)
    assert clopper_pearson_upper(3, 3) == 1.0


# ------------------------------------------------------------------ the command


def _sweep(out: Path, *extra: str, spec: str = "unicycle_switch") -> int:
    return main(
        [
            "sweep",
            spec,
            "--samples",
            "24",
            "--seed",
            "4",
            "--t-final",
            "6",
            "--initial",
            "x1=normal(-5, 0.3)",
            "--plant-param",
            "b=uniform(1, 2)",
            "--out",
            str(out),
            *extra,
        ]
    )


def _table(folder: Path) -> list[dict[str, object]]:
    return pq.read_table(folder / "summary.parquet").to_pylist()


def test_sweep_is_the_same_whatever_the_workers_and_chunks(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    # Chunks of 5 on two workers: test_a_real_scheduler_and_two_workers_give_the_local_table
    # (its cluster is there anyway; a local one here was two more cold interpreters).
    assert _sweep(tmp_path / "a", "--workers", "1", "--chunk-size", "24", "--trajectories") == 0
    assert _sweep(tmp_path / "b", "--workers", "1", "--chunk-size", "5") == 0
    a, b = (tmp_path / "a" / "summary.parquet"), (tmp_path / "b" / "summary.parquet")
    assert a.read_bytes() == b.read_bytes()
    rows = _table(tmp_path / "a")
    assert [r["sample"] for r in rows] == list(range(24))
    required = {"sample", "seed", "status", "final_error", "max_error", "settling_1pct"}
    assert required | {"settling_01pct", "max_abs_v", "max_abs_omega", "time_saturated"} <= set(
        rows[0]
    )
    assert {"min_det_ratio", "nominal", "certificate_holds", "initial.x1", "plant.b"} <= set(
        rows[0]
    )
    text = (tmp_path / "a" / "summary.md").read_text()
    assert "Clopper-Pearson 95% upper bound" in text and "| ok | 24 |" in text
    assert (tmp_path / "a" / "sweep_histograms.png").stat().st_size > 1000
    assert (tmp_path / "a" / "sweep_worst.png").stat().st_size > 1000
    # The trajectories, read with xarray, are the runs the table measured.
    store = xr.open_zarr(tmp_path / "a" / "trajectories.zarr", consolidated=False)
    assert store.sizes["sample"] == 24 and list(store.state_name.values)[:2] == ["x1", "x2"]
    last = store.isel(sample=17, time=-1)
    # The table's formula (a row-wise norm); a 1-D norm goes through BLAS's dot, whose last
    # bit depends on the CPU's vector unit.
    gap = (last.output.values - last.target.values)[np.newaxis, :]
    assert float(np.linalg.norm(gap, axis=1)[0]) == rows[17]["final_error"]
    # Replay one sample alone: the same row, the whole trajectory.
    capsys.readouterr()
    assert main(["sweep", "--replay", str(tmp_path / "a"), "17", "--out", str(tmp_path / "r")]) == 0
    assert "the sweep's row matches this run" in capsys.readouterr().out
    replayed = np.loadtxt(tmp_path / "r" / "sample_17.csv", delimiter=",", skiprows=1)
    assert np.array_equal(replayed[:, 0], store.t.isel(sample=17).values)
    # A second sweep into the same folder is refused: nothing of the first is lost.
    before = a.read_bytes()
    assert _sweep(tmp_path / "a") == 4
    assert a.read_bytes() == before


@pytest.mark.parametrize(
    ("extra", "words"),
    [
        (["--param", "mass=1"], "unknown parameter 'mass'"),
        (["--plant-param", "a=normal(1)"], "takes two numbers"),
        (["--initial", "omega=1"], "unknown state 'omega'"),
        (["--saturation", "thrust=1"], "unknown input 'thrust'"),
        (["--measurement-noise", "0.1"], "needs --sample-time"),
        (["--samples", "-3"], "must be positive"),
        (["--scheduler", "tcp://127.0.0.1:{port}"], "cannot reach"),
    ],
)
def test_bad_input_is_one_line_exit_2_and_writes_nothing(
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
    monkeypatch: pytest.MonkeyPatch,
    extra: list[str],
    words: str,
) -> None:
    monkeypatch.setattr(sweep.driver, "SCHEDULER_TIMEOUT", 2.0)
    extra = [e.format(port=_free_port()) for e in extra]  # a port nobody listens on
    out = tmp_path / "out"
    assert _sweep(out, *extra) == EXIT_BAD_SPEC
    err = capsys.readouterr().err.strip()
    assert words in err and len(err.splitlines()) == 1
    assert not out.exists()


def test_missing_dask_says_what_to_install(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setitem(sys.modules, "distributed", None)
    with pytest.raises(MissingExtraError, match=r"pip install 'tvopt-codegen\[sweep\]'"):
        sweep.connect(2, None)
    # One worker is this process: no Dask needed.
    client, cluster = sweep.connect(1, None)
    assert isinstance(client, sweep.InlineClient) and cluster is None


@pytest.mark.parametrize(
    ("workers", "samples", "cores", "expected"),
    [
        (None, 4, 2, 1),
        (None, 32, 2, 1),
        (None, 33, 2, 2),
        (None, 10**6, 2, 2),
        (None, 100, 1, 1),
        (3, 4, 2, 3),
        (1, 10**6, 2, 1),
        (None, None, 2, 2),
    ],
)
def test_a_local_worker_is_started_only_for_enough_samples(
    monkeypatch: pytest.MonkeyPatch,
    workers: int | None,
    samples: int | None,
    cores: int,
    expected: int,
) -> None:
    monkeypatch.setattr("os.cpu_count", lambda: cores)
    assert sweep.local_workers(workers, samples) == expected


def _free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return int(probe.getsockname()[1])


def test_a_real_scheduler_and_two_workers_give_the_local_table(tmp_path: Path) -> None:
    """`dask scheduler` and two `dask worker` processes, reached through --scheduler; the
    workers compile the loop themselves (their own cache) from the sources they receive.

    The workers start without a nanny (a nanny is one more cold interpreter per worker,
    which spawns the worker and takes seconds to stop it): the sweep meets the same two
    workers. They start once the scheduler listens: started with it, a worker's
    connection retries back off exponentially (with jitter) and once took 20 s more.

    The cluster is stopped through its scheduler: closing, it tells each worker to close,
    and they end within a second. A worker without a nanny sent SIGTERM itself leaves its
    Worker open (dask's CLI closes only nannies on a signal) and hung in asyncio's task
    cancellation until killed after the 20 s wait: two runs in four took 20 s longer.
    """
    dask = Path(sys.executable).parent / "dask"
    port = _free_port()
    address = f"tcp://127.0.0.1:{port}"
    env = dict(os.environ, TVOPT_CODEGEN_CACHE=str(tmp_path / "worker-cache"))
    logs = (tmp_path / "dask.log").open("w")
    processes = [
        subprocess.Popen(
            [
                str(dask),
                "scheduler",
                "--host",
                "127.0.0.1",
                "--port",
                str(port),
                "--dashboard-address",
                ":0",
            ],
            stdout=logs,
            stderr=logs,
            env=env,
        )
    ]
    try:
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline:
            with socket.socket() as probe:
                if probe.connect_ex(("127.0.0.1", port)) == 0:
                    break
            time.sleep(0.05)
        for _ in range(2):
            processes.append(
                subprocess.Popen(
                    [str(dask), "worker", address, "--nthreads", "1", "--no-nanny"]
                    + ["--no-dashboard"],
                    stdout=logs,
                    stderr=logs,
                    env=env,
                )
            )
        from distributed import Client

        with Client(address, timeout="30s") as client:
            client.wait_for_workers(2, timeout=60)
        # Chunks of 5, a few ahead per worker: they finish out of order, and the table is
        # still the one of a single chunk swept here.
        assert _sweep(tmp_path / "remote", "--scheduler", address, "--chunk-size", "5") == 0
        # The local table from the command's own process: no third cluster to start.
        assert _sweep(tmp_path / "local", "--workers", "1", "--chunk-size", "24") == 0
        remote = (tmp_path / "remote" / "summary.parquet").read_bytes()
        assert remote == (tmp_path / "local" / "summary.parquet").read_bytes()
        built = list((tmp_path / "worker-cache").glob("unicycle_switch_sweep-*.so"))
        assert built, "the workers built the loop from its sources"
    finally:
        processes[0].terminate()  # the scheduler: it closes its workers
        for process in processes:
            try:
                process.wait(timeout=20)
            except subprocess.TimeoutExpired:  # a worker that never met the scheduler
                process.kill()
                process.wait()
        logs.close()


def test_constraints_are_measured_on_every_run() -> None:
    """The corridor: the barrier's margin s(t) - g_i and the largest g_i at each output
    time, checked against the constraints evaluated here from the run's outputs."""
    import sympy as sp

    name = "two_unicycles_corridor"
    p = program(name)
    options = SweepOptions(
        samples=3, seed=2, t_final=20.0, initial=(("ya", Distribution("normal", (-3.0, 0.1))),)
    )
    result = run_sample(p, options, 1, keep=True)
    row, rows = result.row, result.trajectory
    assert rows is not None and row["status"] == "ok"
    model = derivation(name).model
    values = dict(zip(model.params, model.defaults, strict=True))
    signals = dict(model.signals)
    functions = [
        sp.lambdify(
            [model.t, *model.y],
            sp.sympify(e).subs(signals).subs(values),
            "numpy",
        )
        for e in (model.slack, *(c.g for c in model.constraints))
    ]
    y = rows[:, _columns(p)["y"]]
    evaluated = np.array(
        [np.broadcast_to(f(rows[:, 0], *y.T), rows[:, 0].shape) for f in functions]
    )
    margin = np.min(evaluated[0] - evaluated[1:], axis=0)
    assert np.allclose(sweep.tail(rows, "margin"), margin, rtol=0, atol=1e-12)
    assert np.allclose(
        sweep.tail(rows, "max_constraint"), evaluated[1:].max(axis=0), rtol=0, atol=1e-12
    )
    assert np.all(np.isnan(sweep.tail(rows, "max_equality")))
    assert row["violations"] == 0 and row["min_margin"] == pytest.approx(margin.min(), abs=1e-12)
    assert row["min_margin"] > 0 and row["final_constraint"] <= 0


def test_the_tables_buffers_are_pyarrows_conversions() -> None:
    """sweep.table builds its batches and reads its columns from NumPy buffers (pyarrow's
    own conversions import pandas): the same arrays as ``from_pylist`` and ``to_numpy``,
    with nulls, non-ASCII text, infinities, NaN, empty chunks and a sliced chunk."""
    import pyarrow as pa

    from tvopt_codegen.sweep.table import record_batch, to_numpy

    schema = pa.schema(
        [("n", pa.int64()), ("x", pa.float64()), ("s", pa.string()), ("b", pa.bool_())]
    )
    rows = [
        {"n": 3, "x": math.inf, "s": "ok", "b": True},
        {"n": -(2**62), "x": math.nan, "s": None, "b": None},
        {"n": 0, "x": -0.0, "s": "é ∞ \\n", "b": False},
        {"x": 5e-324, "s": "", "b": True},  # a missing key is a null, as from_pylist has it
    ]
    for chosen in (rows, rows[:1], []):
        ours, theirs = (
            record_batch(chosen, schema),
            pa.RecordBatch.from_pylist(chosen, schema=schema),
        )
        assert ours.schema == theirs.schema and ours.num_rows == theirs.num_rows
        for mine, reference in zip(ours.columns, theirs.columns, strict=True):
            # repr: NaN is NaN, -0.0 is -0.0 (Arrow's equals takes NaN for unequal).
            assert [repr(v) for v in mine.to_pylist()] == [repr(v) for v in reference.to_pylist()]
            assert mine.null_count == reference.null_count
            mine.validate(full=True)
    batch = record_batch(rows, schema)
    for name in ("n", "x", "b"):
        column = batch.column(name)
        for array in (column, column.slice(1, 2), pa.chunked_array([column, column.slice(2)])):
            want = array.to_numpy(zero_copy_only=False)
            got = to_numpy(array)
            assert got.dtype == want.dtype, name
            assert [repr(v) for v in got.tolist()] == [repr(v) for v in want.tolist()], name
    clean = record_batch([r for r in rows if r.get("n") is not None and r["b"] is not None], schema)
    for name in ("n", "b"):
        sliced = clean.column(name).slice(1)
        assert np.array_equal(to_numpy(sliced), sliced.to_numpy(zero_copy_only=False))
        assert to_numpy(pa.chunked_array([], type=clean.column(name).type)).size == 0
