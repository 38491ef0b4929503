"""Shared fixtures: derivations, generated modules, and paths.

Deriving and importing a controller takes a fraction of a second; the cache below
makes each example's derivation and module shared by every test that needs it.

What is dearer than that is made once per run for every xdist worker: the run's
folder (:func:`run_folder`) holds whatever :func:`shared` builds (a reference sweep), the
first worker to ask building it while the others wait on its lock. What a compiler makes
outlasts the run, keyed by everything it read (:func:`kept_folder`, ``.test-cache/``):
the compiled C libraries (``TVOPT_CODEGEN_CACHE`` points there unless the caller set it)
and the strict profile's compiler and analyser runs (``tests/toolcache.py``).
"""

from __future__ import annotations

import contextlib
import dataclasses
import functools
import gc
import importlib.util
import io
import json
import os
import shutil
import signal
import sys
import tempfile
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from types import ModuleType
from typing import Any

import pytest
from hypothesis import settings

from tvopt_codegen import symbolic as sx
from tvopt_codegen.__main__ import one_blas_thread
from tvopt_codegen.derivation import Derivation, derive
from tvopt_codegen.lowering.ir import KernelSet, lower
from tvopt_codegen.renderer.rendering import render
from tvopt_codegen.spec import load_spec

# CI draws the same hypothesis examples on every run: a submission lands or fails on its
# own code, never on a new random draw; a developer's runs keep exploring.
settings.register_profile("ci", derandomize=True, database=None)
if os.environ.get("CI"):
    settings.load_profile("ci")

ROOT = Path(__file__).resolve().parent.parent
SPECS = Path(__file__).resolve().parent / "specs"
EXAMPLES = (
    "integrator",
    "unicycle_switch",
    "two_unicycles_barrier",
    "pvtol",
    "flexible_joint",
    "unicycle_ring",
    # An equality constraint: the KKT law, with multiplier chains among the states.
    "arm_on_line",
    # Mass-matrix form: M factored at run time in every kernel that needs it.
    "planar_arm3",
)
#: Every spec the closed-loop and oracle tests run: the bundled examples plus test specs.
ALL_SPECS = (
    *EXAMPLES,
    str(SPECS / "nonuniform.toml"),
    str(SPECS / "hovercraft.toml"),
    # R is one full 3 x 3 block: the general LU of the run-time library.
    str(SPECS / "coupled3.toml"),
    # Integral action, a disturbance observer, limits and a slew rate.
    str(SPECS / "robust_pvtol.toml"),
)


def derivation(spec: str) -> Derivation:
    """``spec``'s derivation on the engine in use, derived once per engine."""
    return _derivation(spec, sx.ENGINE)


def kernels(spec: str) -> KernelSet:
    """``spec``'s kernels on the engine in use, lowered once per engine."""
    return _kernels(spec, sx.ENGINE)


@functools.cache
def _derivation(spec: str, engine: str) -> Derivation:
    return derive(load_spec(spec))


@functools.cache
def _kernels(spec: str, engine: str) -> KernelSet:
    return lower(_derivation(spec, engine))


@pytest.fixture(autouse=True)
def _engine_of_the_test(request: pytest.FixtureRequest) -> Iterator[None]:
    """Run a test marked ``engine("sympy")`` on that engine, the default on any other.

    SymEngine is the default; the tests that hold SymPy's own trees (the reference
    engine's texts, hand-built SymPy expressions) name the engine they were written on.
    """
    marker = request.node.get_closest_marker("engine")
    if marker is None:
        yield
        return
    with sx.using(marker.args[0]):
        yield


@pytest.fixture(scope="session", autouse=True)
def _side_processes_forked_warm() -> None:
    """Load, once per worker, what ``simulate``'s forked processes import first.

    An in-process ``simulate`` forks its drawing process (which imports matplotlib) and,
    for constraints, its SLSQP process (``scipy.optimize``): in a test worker that holds
    them already, each fork inherits them, as it would in a notebook that drew before.
    Measured: an in-process ``simulate`` of two_unicycles_corridor spent 1.31 s of its
    children's CPU, 0.77 s so; a test worker runs dozens. The processes still fork and
    draw; what they import is the same. Whether a command loads these itself is tested
    in fresh interpreters (test_rough_edges, test_simulate).
    """
    import scipy.optimize  # noqa: F401

    from tvopt_codegen.runs import drawing

    drawing._load()


_BUILD = Path(tempfile.mkdtemp(prefix="tvopt-test-modules-"))

#: Names the run's folder for the xdist workers, which inherit the controller's
#: environment: the process that made the folder (the controller, or a run without
#: xdist) is the one that removes it.
RUN_FOLDER = "TVOPT_TEST_RUN_FOLDER"
_MADE: list[Path] = []


def run_folder() -> Path:
    """The folder every process of this pytest run shares (made in :func:`pytest_configure`)."""
    return Path(os.environ[RUN_FOLDER])


@contextlib.contextmanager
def _locked(path: Path) -> Iterator[None]:
    """Hold an exclusive lock on ``path`` (made if missing) across processes."""
    import fcntl  # noqa: PLC0415 - POSIX only, like the signal and /proc tests

    with open(path, "a", encoding="utf-8") as handle:
        fcntl.flock(handle, fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(handle, fcntl.LOCK_UN)


def shared(key: str, build: Callable[[Path], None]) -> Path:
    """A folder that ``build`` fills once per run, whichever worker asks first.

    The others wait on the lock and then read what it made: an artifact that takes
    seconds (a 4,000-sample sweep) is made once, not once per worker. A build that
    raised leaves no mark, so the next test to ask builds it again (and fails alike).

    Parameters
    ----------
    key
        The artifact's name in the run's folder: one name, one recipe.
    build
        Fills the (empty) folder it is given.

    Returns
    -------
    pathlib.Path
        The filled folder; read it, do not change it.
    """
    folder = run_folder() / key
    done = folder / ".done"
    if not done.exists():
        with _locked(run_folder() / f"{key}.lock"):
            if not done.exists():
                shutil.rmtree(folder, ignore_errors=True)
                folder.mkdir()
                build(folder)
                done.touch()
    return folder


@functools.cache
def module(spec: str) -> ModuleType:
    """Generate the Python backend for ``spec`` into a private folder and import it."""
    files = render(kernels(spec), "python")
    ((name, text),) = files.items()
    folder = _BUILD / f"m{len(list(_BUILD.iterdir()))}"
    folder.mkdir()
    path = folder / name
    path.write_text(text, encoding="utf-8")
    return import_file(path, f"_tvopt_test_{name[:-3]}")


@dataclasses.dataclass
class Ran:
    """A command line's outcome, as ``subprocess.run(..., text=True)`` would give it."""

    returncode: int
    stdout: str
    stderr: str


def remembered(
    read: Callable[[Any], Any], key: Callable[[Any], Any] = lambda value: value
) -> Callable[[Any], Any]:
    """``read`` worked out once per ``key(value)``, for a ``read`` that is a function of
    its value alone (SymPy's simplify, its printers, a conversion to SymPy).

    A value that cannot be a key (a mutable matrix) is read each time; a read that raised
    is not remembered.
    """
    known: dict[Any, Any] = {}

    def once(value: Any) -> Any:
        name = key(value)
        try:
            return known[name]
        except KeyError:
            known[name] = found = read(value)
            return found
        except TypeError:  # not hashable: not a key
            return read(value)

    return once


def run_main(*args: str, cwd: Path | None = None, env: dict[str, str] | None = None) -> Ran:
    """``tvopt-codegen ARGS`` in this process, its output captured.

    For tests of what a command writes and says, not of the process (signals, imports,
    start-up): a subprocess costs a second of imports that this worker has already paid,
    and derives with cold caches. ``cwd`` and ``env`` hold for the call only.
    """
    from tvopt_codegen.cli import main  # noqa: PLC0415

    out, err = io.StringIO(), io.StringIO()
    saved = {name: os.environ.get(name) for name in env or {}}
    before = Path.cwd()
    try:
        os.environ.update(env or {})
        if cwd is not None:
            os.chdir(cwd)
        with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
            try:
                code = main(list(args))
            except SystemExit as stop:  # argparse's usage errors and --help end so
                code = stop.code if isinstance(stop.code, int) else int(stop.code is not None)
    finally:
        os.chdir(before)
        for name, value in saved.items():
            if value is None:
                os.environ.pop(name, None)
            else:
                os.environ[name] = value
    return Ran(code, out.getvalue(), err.getvalue())


def import_file(path: Path, mod_name: str) -> ModuleType:
    """Import a generated Python module from its file under a unique module name."""
    loader = importlib.util.spec_from_file_location(mod_name, path)
    assert loader is not None and loader.loader is not None
    mod = importlib.util.module_from_spec(loader)
    sys.modules[mod_name] = mod
    loader.loader.exec_module(mod)
    return mod


def write_spec(tmp_path: Path, text: str, name: str = "spec.toml") -> Path:
    path = tmp_path / name
    path.write_text(text, encoding="utf-8")
    return path


@pytest.fixture
def unicycle_text() -> str:
    return (ROOT / "tvopt_codegen" / "examples" / "unicycle_switch.toml").read_text()


def pytest_addoption(parser: pytest.Parser) -> None:
    parser.addoption(
        "--update-golden",
        action="store_true",
        help="rewrite tests/golden files from the current output",
    )


@pytest.fixture
def update_golden(request: pytest.FixtureRequest) -> bool:
    return bool(request.config.getoption("--update-golden"))


#: What enables a skipped test, by a word of its reason; a reason that matches none is a
#: skip by design (a fragment a page marks as such, a platform the test is not for).
_ENABLERS = (
    # tests/embedded/harness.py's INSTALL: the cross compilers and QEMU of the ARM tests.
    (
        "arm toolchain",
        "apt-get install --no-install-recommends gcc-arm-none-eabi libnewlib-arm-none-eabi"
        " qemu-system-arm qemu-user gcc-aarch64-linux-gnu gcc-arm-linux-gnueabihf"
        " libc6-dev-arm64-cross libc6-dev-armhf-cross (as root, `.ci/run` does it)",
    ),
    ("chromium", "apt-get install chromium (as root, `.ci/run` does it)"),
    ("clang", "apt-get install clang"),
    ("cppcheck", "apt-get install cppcheck (as root, `.ci/run` does it)"),
    ("c compiler", "apt-get install gcc"),
    ("python headers", "apt-get install python3-dev"),
    ("sanitizer", "apt-get install gcc (with libasan and libubsan)"),
    ("could not import", "make .venv/.installed (pip install -e '.[dev,all]')"),
    ("extra", "make .venv/.installed (pip install -e '.[dev,all]')"),
    ("needs ", "make .venv/.installed (pip install -e '.[dev,all]')"),
)


def skip_summary(reasons: list[str]) -> str:
    """One line: how many tests skipped, and the command that would run each group.

    Parameters
    ----------
    reasons
        The skip reason of each skipped test.

    Returns
    -------
    str
        ``""`` when nothing was skipped.
    """
    if not reasons:
        return ""
    groups: dict[str, int] = {}
    for reason in reasons:
        low = reason.lower()
        enabler = next((how for word, how in _ENABLERS if word in low), "by design")
        groups[enabler] = groups.get(enabler, 0) + 1
    parts = [
        f"{n} by design" if how == "by design" else f"{n} need `{how}`"
        for how, n in sorted(groups.items(), key=lambda item: (item[0] == "by design", item[0]))
    ]
    return f"skipped {len(reasons)}: " + "; ".join(parts)


@pytest.hookimpl(trylast=True)
def pytest_terminal_summary(terminalreporter: pytest.TerminalReporter) -> None:
    """Count the skipped tests in one line, with what would run them (issue 48)."""
    reasons = []
    for report in terminalreporter.stats.get("skipped", []):
        longrepr = report.longrepr
        # A skip's longrepr is (file, line, "Skipped: reason").
        text = longrepr[2] if isinstance(longrepr, tuple) else str(longrepr)
        reasons.append(text.removeprefix("Skipped: "))
    line = skip_summary(reasons)
    if line:
        terminalreporter.write_line(line, yellow=True)


#: Python text of an import hook that refuses SymPy, for scripts run in a fresh process
#: (``sys.meta_path.insert(0, Refuse())``): what must run without SymPy proves it there.
REFUSE_SYMPY = """
class Refuse:
    def find_spec(self, name, path=None, target=None):
        if name == "sympy" or name.startswith("sympy."):
            raise ImportError("SymPy refused: " + name)
        return None
"""

#: A test that took longer than this (seconds, in ``tests/durations.json``) is ``slow``:
#: ``make test`` runs it, ``make test-fast`` does not. The durations are of a whole run on
#: both cores of this 2-core machine with warm caches; ``make test-durations`` measures
#: them again. At 0.5 s the quick part took 69 s against the whole suite's 386-407 s,
#: 0.17; once the suite's dearest tests got cheaper (2026-12-05 afternoon) more of them
#: fell under 0.5 s, and the quick part took 92 s of 363 s, 0.25; at 0.3 s 76 s of 351 s,
#: 0.22: hence 0.2 s. Cheaper again (2026-12-05 evening), the quick part at 0.2 s took 56 s
#: of 223 s, 0.25: hence 0.1 s.
SLOW_SECONDS = 0.1
#: The least duration ``durations.json`` records (moving the threshold below it needs a
#: new ``make test-durations``).
RECORDED_SECONDS = 0.1
DURATIONS = Path(__file__).resolve().parent / "durations.json"


def pytest_configure(config: pytest.Config) -> None:
    """Give the suite Python's own SIGINT handler when it starts with SIGINT ignored.

    pytest-xdist's workers start so, and so does a run started in the background by a
    shell without job control. An ignored signal stays ignored across ``exec``: the
    command-line processes the signal tests interrupt would never see their Ctrl-C, and
    the tests of the handlers the tool restores would find ``SIG_IGN`` to begin with.
    """
    if signal.getsignal(signal.SIGINT) == signal.SIG_IGN:
        signal.signal(signal.SIGINT, signal.default_int_handler)
    # The run's folder, made before xdist starts its workers so that they inherit it; a
    # pytest run inside a test inherits it too, and leaves it to its maker.
    if RUN_FOLDER not in os.environ:
        made = Path(tempfile.mkdtemp(prefix="tvopt-test-run-"))
        _MADE.append(made)
        os.environ[RUN_FOLDER] = str(made)
    # One cache of compiled libraries: each generated C module, sweep loop and FMU
    # library is compiled once, not once per worker or per run (and not into the user's
    # ~/.cache). The libraries are keyed by their sources, compiler and flags and
    # published by rename, so workers that compile the same one at once both get it
    # whole. Tests of the cache itself set a folder of their own.
    kept = kept_folder()
    libraries = kept / "c-cache" if kept is not None else run_folder() / "c-cache"
    os.environ.setdefault("TVOPT_CODEGEN_CACHE", str(libraries))
    # One BLAS thread in each worker, as the command line asks for itself (set before
    # xdist starts the workers, whose NumPy loads after): two workers of two BLAS
    # threads each fought over the machine's two cores.
    one_blas_thread()


def pytest_unconfigure(config: pytest.Config) -> None:
    """Remove the run's folder, in the process that made it, and stale kept entries."""
    for folder in _MADE:
        shutil.rmtree(folder, ignore_errors=True)
    kept = kept_folder()
    if _MADE and kept is not None:
        _prune(kept, KEPT_DAYS * 86400.0)


#: Names the folder the suite keeps across runs; ``off`` keeps nothing past a run.
TEST_CACHE = "TVOPT_TEST_CACHE"
#: A kept entry not written for this many days is removed at the end of a run (the next
#: run that needs it makes it again): the folder does not grow without end.
KEPT_DAYS = 30


def kept_folder() -> Path | None:
    """The folder that outlasts a run: compiled libraries and kept tool runs, or None.

    ``.test-cache/`` in the checkout unless ``TVOPT_TEST_CACHE`` names another (``off``:
    none, and the libraries go to the run's folder). Everything in it is keyed by what
    made it (sources, flags, the tool's file): see ``tests/toolcache.py``. ``make clean``
    removes it; CI starts from a clean clone, so every run there is a cold one.
    """
    value = os.environ.get(TEST_CACHE, str(ROOT / ".test-cache"))
    return None if value in ("", "off") else Path(value)


def _prune(folder: Path, age: float) -> None:
    """Remove the entries of ``folder``'s subfolders last written over ``age`` seconds ago."""
    now = time.time()
    for entry in folder.glob("*/*"):
        with contextlib.suppress(OSError):
            if now - entry.stat().st_mtime > age:
                if entry.is_dir():
                    shutil.rmtree(entry, ignore_errors=True)
                else:
                    entry.unlink()


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    """Mark ``slow`` every test whose recorded duration is over :data:`SLOW_SECONDS`, and
    every case of a parametrized test one of whose cases is; order the modules by their
    recorded time, dearest first.

    The cases of one test share what they build (a compiled controller, one Chromium for
    every example): the case that ran first recorded the whole cost, and in ``make
    test-fast`` without it another would pay it (a few seconds for the browser).
    """
    try:
        durations = json.loads(DURATIONS.read_text(encoding="utf-8"))
    except FileNotFoundError:
        return
    slow = {
        (item.path, getattr(item, "originalname", item.name))
        for item in items
        if durations.get(item.nodeid, 0.0) > SLOW_SECONDS
    }
    for item in items:
        if (item.path, getattr(item, "originalname", item.name)) in slow:
            item.add_marker(pytest.mark.slow)
    # The dearest modules first, each module's tests together and in order (its fixtures
    # are set up once): the workers share out the cheap ones at the end, where a dear
    # module last in the alphabet left one worker running alone.
    weight: dict[Path, float] = {}
    for item in items:
        weight[item.path] = weight.get(item.path, 0.0) + durations.get(item.nodeid, 0.0)
    first = {path: index for index, path in enumerate(dict.fromkeys(i.path for i in items))}
    items.sort(key=lambda item: (-weight[item.path], first[item.path]))


def pytest_collection_finish(session: pytest.Session) -> None:
    """Freeze what collection left alive (the libraries and the test modules)."""
    gc.freeze()


@pytest.hookimpl(trylast=True)
def pytest_runtest_teardown(item: pytest.Item, nextitem: pytest.Item | None) -> None:
    """Freeze what a test leaves alive once its fixtures are torn down.

    That is the run's caches (derivations, kernels, modules, compiled functions, SymPy's
    own), which grow to hundreds of megabytes in a worker: the collector's full passes
    rescanned all of it, 58 s of the whole suite's 216 s in-process CPU (46 s in 55
    passes of the oldest generation, measured with gc.callbacks). Frozen objects are
    never scanned again; a test's own garbage is still collected while the test runs,
    and a cycle that outlives its test stays until the worker ends.
    """
    gc.freeze()


_MEASURED: dict[str, float] = {}


def pytest_runtest_logreport(report: pytest.TestReport) -> None:
    """Add up each test's setup, call and teardown when ``make test-durations`` asks."""
    if os.environ.get("TVOPT_TEST_DURATIONS"):
        _MEASURED[report.nodeid] = _MEASURED.get(report.nodeid, 0.0) + report.duration


def pytest_sessionfinish(session: pytest.Session) -> None:
    """Write the durations ``make test-durations`` measured (the controller's, once)."""
    target = os.environ.get("TVOPT_TEST_DURATIONS")
    if not target or os.environ.get("PYTEST_XDIST_WORKER") or not _MEASURED:
        return
    kept = {k: round(v, 2) for k, v in sorted(_MEASURED.items()) if v >= RECORDED_SECONDS}
    Path(target).write_text(json.dumps(kept, indent=0, sort_keys=True) + "\n", encoding="utf-8")
