"""Figures drawn in a drawing process started before the derivation (tvopt_codegen.runs.drawing)."""

from __future__ import annotations

import pickle
import subprocess
import sys
import textwrap
import threading

import numpy as np
import pytest

from tvopt_codegen.runs.drawing import Painter, Panel, Plot, draw, draw_all


def _plots() -> list[Plot]:
    t = np.linspace(0.0, 5.0, 101)
    one = Plot("decay", (6.4, 4.0))
    one.panels[0].semilogy(t, np.exp(-t), "--", color="tab:red", lw=2, label="exp(-t)")
    one.panels[0].set_title("decay")
    one.panels[0].legend(fontsize=8)
    two = Plot("waves", (6.4, 6.0), rows=2, sharex=True)
    top, bottom = two.panels
    top.plot(t, np.sin(t), color="tab:blue", label="sin")
    top.grid(alpha=0.3)
    bottom.step(t, np.cos(t), where="post")
    bottom.set_xlabel("t")
    three = Plot("histogram", (9.0, 3.6), cols=2)
    three.panels[0].hist(np.sin(np.arange(200.0)), bins=20)
    three.panels[1].plot(t, t**2)
    return [one, two, three]


@pytest.fixture(scope="module")
def drawn_here() -> dict[str, bytes]:
    """The plots' files drawn in this process, once for the module's tests."""
    return draw_all(_plots())


def _fresh(body: str, expected: dict[str, bytes] | None = None) -> None:
    """Run ``body`` in a new interpreter, with this module's plots (and ``expected``, the
    files drawn in this process, as ``expected``).

    A drawing process is forked only while one thread runs, which a test process that
    has run a Dask sweep no longer is.
    """
    code = "import os, pickle, signal, sys, time\n"
    code += "from tests.test_drawing import Painter, _plots, draw_all\n"
    code += "expected = pickle.loads(sys.stdin.buffer.read())\n"
    code += textwrap.dedent(body)
    done = subprocess.run(
        [sys.executable, "-c", code],
        input=pickle.dumps(expected),
        capture_output=True,
        timeout=120,
        check=False,
    )
    assert done.returncode == 0, done.stderr.decode()


def test_a_drawing_process_draws_the_same_bytes_in_the_plots_order(
    drawn_here: dict[str, bytes],
) -> None:
    # The drawing process's files against this process's: the same bytes whichever
    # process draws (the one drawing here serves the module's other tests too).
    stems = ("decay", "waves", "histogram")
    assert list(drawn_here) == [f"{stem}.{kind}" for stem in stems for kind in ("png", "svg")]
    _fresh(
        """
        with Painter() as painter:
            pid = painter._pid
            assert pid is not None
            painter.submit(_plots())
            there = painter.collect()
        assert list(there) == list(expected)
        assert there == expected
        try:
            os.kill(pid, 0)
        except ProcessLookupError:
            pass  # reaped
        else:
            raise AssertionError("the drawing process outlived its block")
        """,
        drawn_here,
    )


def test_plots_travel_without_sympy_and_panels_refuse_unknown_calls() -> None:
    plots = _plots()
    copies = pickle.loads(pickle.dumps(plots))
    assert [p.panels[0].calls[0][0] for p in copies] == ["semilogy", "plot", "hist"]
    assert draw(copies[0]) == draw(plots[0])
    with pytest.raises(AttributeError, match="records no 'imshow'"):
        Panel().imshow(np.eye(2))


def test_a_drawing_process_that_dies_leaves_the_drawing_here(
    drawn_here: dict[str, bytes],
) -> None:
    _fresh(
        """
        with Painter() as painter:
            assert painter._pid is not None
            os.kill(painter._pid, signal.SIGKILL)
            time.sleep(0.05)
            painter.submit(_plots())
            files = painter.collect()
        assert files == expected
        """,
        drawn_here,
    )


def test_a_painter_never_given_work_is_stopped_at_once() -> None:
    _fresh(
        """
        started = time.perf_counter()
        with Painter() as painter:
            pid = painter._pid
            assert pid is not None
        # Killed while it imported matplotlib, not waited for; and reaped.
        assert time.perf_counter() - started < 0.5, time.perf_counter() - started
        try:
            os.kill(pid, 0)
        except ProcessLookupError:
            pass
        else:
            raise AssertionError("not reaped")
        """
    )


def test_no_fork_while_other_threads_run(drawn_here: dict[str, bytes]) -> None:
    release = threading.Event()
    worker = threading.Thread(target=release.wait)
    worker.start()
    try:
        with Painter() as painter:
            assert painter._pid is None
            painter.submit(_plots())
            assert painter.collect() == drawn_here
    finally:
        release.set()
        worker.join()
