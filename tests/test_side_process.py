"""``simulate``'s work beside the run: the SLSQP solves, and figures drawn while it is certified.

Each test's body runs in a fresh interpreter: a process is forked only while one thread
runs, which a test process that has run a Dask sweep no longer is. The bodies share one
interpreter, run once per pytest run (``shared``): a cold interpreter and the corridor's
derivation once, not five times. Each runs only while that interpreter has one thread
(checked before it), and each test reports its own body's failure.
"""

from __future__ import annotations

import functools
import json
import subprocess
import sys
from pathlib import Path

import pytest

from tvopt_codegen.runs.drawing import Plot

#: One interpreter runs every test's body (a few seconds, paid by whichever test asks
#: first): the whole file is ``make test``'s.
pytestmark = pytest.mark.slow

#: Every test's body by its test's name (with numpy as np and this module's helpers).
BODIES: dict[str, str] = {}

RUNNER = """
import json, sys, textwrap, threading, traceback
import numpy as np
from tests.test_side_process import BODIES, _corridor, _plot
# What the forked side processes import first, loaded before them, as conftest's
# _side_processes_forked_warm does in every worker: each fork inherits it (0.4 s of
# their CPU here); they still fork, solve and draw.
import scipy.optimize
from tvopt_codegen.runs import drawing
drawing._load()
outcomes = {}
for name, body in BODIES.items():
    try:
        assert threading.active_count() == 1, f"{threading.active_count()} threads before it"
        code = compile(textwrap.dedent(body), name, "exec")
        exec(code, {"np": np, "_corridor": _corridor, "_plot": _plot})
        outcomes[name] = None
    except BaseException:
        outcomes[name] = traceback.format_exc()
with open(sys.argv[1], "w") as handle:
    json.dump(outcomes, handle)
"""


def _run_bodies(folder: Path) -> None:
    """Every body in one new interpreter; its outcomes (a traceback or null) in JSON."""
    done = subprocess.run(
        [sys.executable, "-c", RUNNER, str(folder / "outcomes.json")],
        capture_output=True,
        text=True,
        timeout=600,
        check=False,
    )
    assert done.returncode == 0, done.stderr


def _fresh(name: str) -> None:
    """Test ``name``'s body, run in a fresh interpreter, passed."""
    # Imported here, not at the top: the runner imports this module, and conftest's
    # pytest plugins and hypothesis were a quarter of a second of its start-up.
    from .conftest import shared  # noqa: PLC0415

    outcomes = json.loads(
        (shared("side-process-bodies", _run_bodies) / "outcomes.json").read_text()
    )
    assert outcomes[name] is None, outcomes[name]


@functools.cache
def _corridor() -> tuple[object, object]:
    """The corridor team's derivation and generated module (two constraints).

    Made as conftest's ``derivation`` and ``module`` make them, without importing conftest
    (see :func:`_fresh`): derived, lowered, rendered to a private folder and imported.
    """
    import importlib.util  # noqa: PLC0415
    import tempfile  # noqa: PLC0415

    from tvopt_codegen.derivation import derive  # noqa: PLC0415
    from tvopt_codegen.lowering.ir import lower  # noqa: PLC0415
    from tvopt_codegen.renderer.rendering import render  # noqa: PLC0415
    from tvopt_codegen.spec import load_spec  # noqa: PLC0415

    d = derive(load_spec("two_unicycles_corridor"))
    ((name, text),) = render(lower(d), "python").items()
    with tempfile.TemporaryDirectory(prefix="tvopt-side-") as folder:  # loaded, then gone
        path = Path(folder) / name
        path.write_text(text, encoding="utf-8")
        found = importlib.util.spec_from_file_location(f"_tvopt_side_{name[:-3]}", path)
        assert found is not None and found.loader is not None
        controller = importlib.util.module_from_spec(found)
        sys.modules[found.name] = controller
        found.loader.exec_module(controller)
    return d, controller


def _plot(stem: str, slope: float) -> Plot:
    plot = Plot(stem, (4.0, 3.0))
    plot.panels[0].plot([0.0, 1.0], [0.0, slope], label=f"slope {slope}")
    plot.panels[0].legend(fontsize=8)
    return plot


def test_the_side_process_finds_the_minimisers_this_one_would() -> None:
    _fresh("test_the_side_process_finds_the_minimisers_this_one_would")


BODIES["test_the_side_process_finds_the_minimisers_this_one_would"] = """
        from tvopt_codegen.simulation import resolve_options, simulate
        from tvopt_codegen.simulation.constraints import minimiser_process

        d, controller = _corridor()
        options = resolve_options(d)
        with minimiser_process(d.model, options.params) as side:
            assert side.running
            beside = simulate(d, controller, options, side=side)
            # Still running: it answered (a failed request stops it; the work is done here).
            assert side.running
        here = simulate(d, controller, options)
        np.testing.assert_array_equal(beside.constraints.distance, here.constraints.distance)
        np.testing.assert_array_equal(beside.constraints.bound, here.constraints.bound)
        assert beside.passed and np.all(np.isfinite(beside.constraints.distance))
        """


def test_a_request_at_other_parameter_values_is_solved_at_those() -> None:
    _fresh("test_a_request_at_other_parameter_values_is_solved_at_those")


BODIES["test_a_request_at_other_parameter_values_is_solved_at_those"] = """
        from tvopt_codegen.simulation import resolve_options, simulate
        from tvopt_codegen.simulation.constraints import minimiser_process

        d, controller = _corridor()
        name, default = d.model.params[-1].name, float(d.model.defaults[-1])
        options = resolve_options(d, params={name: 1.1 * default})
        # Started at the defaults, asked at the run's values: it lambdifies those anew.
        with minimiser_process(d.model, {}) as side:
            beside = simulate(d, controller, options, side=side)
            assert side.running
        here = simulate(d, controller, options)
        np.testing.assert_array_equal(beside.constraints.distance, here.constraints.distance)
        """


def test_a_side_process_answers_and_a_failed_one_answers_none() -> None:
    _fresh("test_a_side_process_answers_and_a_failed_one_answers_none")


BODIES["test_a_side_process_answers_and_a_failed_one_answers_none"] = """
        from tvopt_codegen.runs.side import Side

        with Side(lambda: lambda request: (request[0] * 2, np.arange(request[1]))) as side:
            doubled, numbers = side.ask((21, 3))
            assert doubled == 42 and numbers.tolist() == [0, 1, 2]
            assert side.ask(("x", 2))[0] == "xx"
            assert side.running
            # A request that fails there is refused, and the process stops.
            assert side.ask((None, 1)) is None
            assert not side.running
            assert side.ask((1, 1)) is None

        def broken():
            raise ImportError("no scipy here")

        with Side(broken) as side:
            assert side.ask((1, 1)) is None
            assert not side.running
        """


def test_figures_sent_in_batches_come_back_in_order_and_the_last_of_a_stem_counts() -> None:
    _fresh("test_figures_sent_in_batches_come_back_in_order_and_the_last_of_a_stem_counts")


BODIES["test_figures_sent_in_batches_come_back_in_order_and_the_last_of_a_stem_counts"] = """
        from tvopt_codegen.runs.drawing import Painter, draw_all

        with Painter() as painter:
            assert painter._pid is not None
            painter.submit([_plot("a", 1.0), _plot("b", 2.0)])
            painter.submit([_plot("c", 3.0)])
            painter.submit([_plot("a", -1.0)])  # drawn again: this one counts
            there = painter.collect()
        expected = draw_all([_plot("a", -1.0), _plot("b", 2.0), _plot("c", 3.0)])
        assert list(there) == list(expected) and there == expected
        assert there["a.png"] != draw_all([_plot("a", 1.0)])["a.png"]
        """


def test_the_run_alone_is_drawn_early_and_the_files_are_the_same() -> None:
    _fresh("test_the_run_alone_is_drawn_early_and_the_files_are_the_same")


BODIES["test_the_run_alone_is_drawn_early_and_the_files_are_the_same"] = """
        from tvopt_codegen.runs.artifacts import result_files, submit_early
        from tvopt_codegen.runs.drawing import Painter
        from tvopt_codegen.simulation import resolve_options, simulate

        d, controller = _corridor()
        runs, stems = [], []
        with Painter() as painter:
            def early(run):
                runs.append(run)
                stems.extend(submit_early(d, run, painter))

            result = simulate(d, controller, resolve_options(d), early=early)
            assert len(runs) == 1 and runs[0].outputs is result.outputs
            assert stems == ["two_unicycles_corridor_paths", "two_unicycles_corridor_inputs"]
            files = result_files(d, result, painter, stems)
        # Drawn here once (half a second of figures): the same bytes, in the same order.
        alone = result_files(d, result)
        assert files == alone and list(files) == list(alone)
        """
