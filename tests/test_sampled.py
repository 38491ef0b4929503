"""Sampled-data simulation: the stateful controller under a zero-order hold."""

from __future__ import annotations

from pathlib import Path
from types import ModuleType

import numpy as np
import pytest

from tvopt_codegen.cli import main
from tvopt_codegen.errors import EXIT_BAD_SPEC
from tvopt_codegen.simulation import resolve_options
from tvopt_codegen.simulation.sampled import ORDER_FLOOR, simulate_sampled

from .conftest import derivation, module
from .test_c_backend import c_module


@pytest.mark.parametrize(("spec", "horizon"), [("unicycle_switch", 8.0), ("pvtol", 6.0)])
def test_halving_h_halves_the_distance_to_the_continuous_loop(spec: str, horizon: float) -> None:
    d, mod = derivation(spec), module(spec)
    assert mod.CONTROLLER_STATE_NAMES  # both examples keep extension states
    options = resolve_options(d, horizon)
    # H = 2e-3 and 1e-3, half the steps of 1e-3 and 5e-4 for the same check: the observed
    # order is 0.99995 (unicycle_switch) and 0.9996 (pvtol) there, 0.99999 and 0.9998 at
    # the finer pair, both within 1% of the 0.05 the order is allowed to be off by.
    result = simulate_sampled(d, mod, options, 2e-3, convergence_order=True)
    coarse, fine = result.runs
    assert coarse.h == 2e-3 and fine.h == 1e-3
    assert len(coarse.t) == round(horizon / 2e-3) + 1 and coarse.t[-1] == horizon
    # Small at H = 2e-3 (6.7e-3 and 1.0e-3), and first order: the distance halves with H.
    assert 0 < coarse.deviation < 1e-2
    assert result.order is not None and 0.95 < result.order < 1.05
    assert fine.deviation == pytest.approx(coarse.deviation / 2, rel=0.05)
    assert result.passed and result.order >= ORDER_FLOOR
    # The controller really is sampled: u is constant between samples, and the first
    # sample's input is the continuous law's at the start.
    np.testing.assert_allclose(
        coarse.inputs[:, 0], mod.control(0.0, np.array(options.initial_state)), rtol=1e-14
    )
    # The run's states are [x; z] with z the controller's own.
    n = len(mod.PLANT_STATE_NAMES)
    np.testing.assert_allclose(coarse.states[:n, 0], options.initial_state[:n])


def test_the_c_controller_gives_the_same_sampled_run(
    tmp_path_factory: pytest.TempPathFactory,
) -> None:
    d = derivation("pvtol")
    options = resolve_options(d, 2.0)
    runs: list[np.ndarray] = []
    mods: list[ModuleType] = [module("pvtol"), c_module("pvtol", tmp_path_factory)]
    for mod in mods:
        result = simulate_sampled(d, mod, options, 2e-3)
        runs.append(result.runs[0].states)
    np.testing.assert_allclose(runs[0], runs[1], rtol=1e-10, atol=1e-12)


def test_the_command_writes_the_sampled_run_and_states_the_order(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "out"
    out.mkdir()
    # Half pvtol's 12 s: what the command writes and says is the subject here (the order's
    # accuracy is test_halving_h_halves_the_distance_to_the_continuous_loop's, over 6 s).
    code = main(
        [
            "simulate",
            "pvtol",
            "--t-final",
            "6",
            "--sample-time",
            "2e-3",
            "--convergence-order",
            "--out",
            str(out),
        ]
    )
    printed = capsys.readouterr().out
    assert code == 0, printed
    assert "under sampling (zero-order hold, controller stepped every H):" in printed
    assert "H = 0.002: max |y - y_continuous| " in printed
    assert "observed order in H: 1" in printed
    assert "sampled certificate: PASSED" in printed
    names = {p.name for p in out.iterdir()}
    assert {"pvtol_sampled.csv", "pvtol_sampled.npz", "pvtol_sampled.png"} <= names
    saved = np.load(out / "pvtol_sampled.npz")
    assert float(saved["h0"]) == 2e-3 and float(saved["h1"]) == 1e-3
    certificate = (out / "pvtol_certificate.txt").read_text()
    assert "observed order in H" in certificate
    header = (out / "pvtol_sampled.csv").read_text().splitlines()[0]
    assert header.startswith("t,x,z,theta,vx,vz,omega,thrust,thrust_d1,u_thrust,")


@pytest.mark.parametrize(
    ("arguments", "message"),
    [
        (["--sample-time", "0"], "--sample-time: must be positive and finite"),
        (["--sample-time", "nan"], "--sample-time: must be positive and finite"),
        (["--sample-time", "1"], "leaves fewer than 10 samples over the horizon 3"),
        (["--sample-time", "1e-9"], "samples over the horizon 3; at most 2000000"),
        (["--convergence-order"], "--convergence-order: needs --sample-time"),
    ],
)
def test_bad_sample_times_are_one_line_errors_that_write_nothing(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], arguments: list[str], message: str
) -> None:
    out = tmp_path / "out"
    out.mkdir()
    code = main(["simulate", "pvtol", "--t-final", "3", *arguments, "--out", str(out)])
    captured = capsys.readouterr()
    assert code == EXIT_BAD_SPEC
    lines = captured.err.strip().splitlines()
    assert len(lines) == 1 and message in lines[0], captured.err
    assert list(out.iterdir()) == []
