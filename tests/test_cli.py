"""The command line: outputs, exit codes, and nothing written on failure."""

from __future__ import annotations

import gc
import os
import re
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest
from scipy.integrate import solve_ivp

from tvopt_codegen import cli
from tvopt_codegen.cli import main
from tvopt_codegen.commands import common
from tvopt_codegen.errors import EXIT_ASSUMPTION, EXIT_BAD_SPEC, EXIT_OUTPUT
from tvopt_codegen.runs import summary

from .conftest import ROOT, import_file, write_spec


def snapshot(folder: Path) -> dict[str, bytes]:
    return {p.name: p.read_bytes() for p in sorted(folder.iterdir())} if folder.exists() else {}


def test_generate_writes_an_importable_module(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "build"
    assert main(["generate", "unicycle_switch", "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    assert "det R = v; singular where v = 0" in printed
    assert f"written: {out}/unicycle_switch.py" in printed
    # Imported from its file and integrated here: a fresh interpreter (half a second of
    # SciPy's imports) is for what a process does; the generated files' own
    # interpreters are test_runtime_inputs' and test_package's.
    m = import_file(out / "unicycle_switch.py", "_tvopt_test_cli_unicycle_switch")
    assert solve_ivp(m.rhs, (0, 1), m.DEFAULT_STATE).success


def test_check_prints_summary_and_writes_nothing(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    before = snapshot(tmp_path)
    cwd = os.getcwd()
    os.chdir(tmp_path)
    try:
        assert main(["check", "two_unicycles_barrier"]) == 0
    finally:
        os.chdir(cwd)
    text = capsys.readouterr().out
    assert "relative degree: pa: 2, qa: 2, pb: 2, qb: 2" in text
    assert "extension: va integrated 1x; vb integrated 1x" in text
    assert "poles -1.5, -1" in text
    assert snapshot(tmp_path) == before


def test_a_long_list_in_the_summary_shows_its_ends_and_its_length(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A ring of 13 agents (39 states, 26 outputs: over summary.LISTED): every list's
    first and last items and how many there are, each line a line; 8 agents' 24 states
    whole."""
    bundled = (ROOT / "tvopt_codegen" / "examples" / "unicycle_ring.toml").read_text()
    for agents in (8, 13):
        spec = tmp_path / f"ring{agents}.toml"
        spec.write_text(re.sub(r"(?m)^i = \d+", f"i = {agents}", bundled), encoding="utf-8")
        assert main(["check", str(spec)]) == 0
        lines = capsys.readouterr().out.splitlines()
        (plant,) = [line for line in lines if line.startswith("  plant: ")]
        (state,) = [line for line in lines if line.startswith("  closed-loop state: ")]
        (degree,) = [line for line in lines if line.startswith("  relative degree: ")]
        if agents == 8:
            # 24 states and 16 outputs whole; 32 closed-loop states (the speeds added) not.
            assert "..." not in plant + degree
            assert "x_7, y_7, theta_7), 16 inputs" in plant
            assert state.endswith(", ..., v_5, v_6, v_7 (32 in all)")
            continue
        assert plant.startswith(
            "  plant: 39 states (x_0, y_0, theta_0, x_1, y_1, theta_1, x_2, y_2, theta_2, "
            "..., x_12, y_12, theta_12 (39 in all)), 26 inputs (v_0, omega_0,"
        )
        assert state.endswith(", ..., v_10, v_11, v_12 (52 in all)")
        assert degree.startswith("  relative degree: px_0: 2, py_0: 2, px_1: 2,")
        assert ", ..., py_11: 2, px_12: 2, py_12: 2 (26 in all)  (sum 52 = n;" in degree
        assert max(map(len, lines)) < 600  # the extension line: 13 integrations whole


def test_examples_lists_bundled_specs(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["examples"]) == 0
    text = capsys.readouterr().out
    for name in ("integrator", "unicycle_switch", "two_unicycles_barrier"):
        assert name in text


@pytest.mark.parametrize(
    ("mutation", "code", "message"),
    [
        (
            ('x1 = "v*cos(theta)"', 'x1 = "v*cos(theta"'),
            EXIT_BAD_SPEC,
            "system.dynamics.x1: column",
        ),
        (('theta = "omega"', 'theta = "omega*v"'), EXIT_BAD_SPEC, "not affine"),
        (("integrate = { v = 1 }", ""), EXIT_ASSUMPTION, "integrate = { v = 1 }"),
        (("poles = [-1.0, -1.5]", "poles = [-1.0, 1.5]"), EXIT_ASSUMPTION, "not Hurwitz"),
        # An integer where a boolean belongs was an internal error (exit 70).
        (
            ("[simulation]", "[robust]\nintegral = 1\n\n[simulation]"),
            EXIT_BAD_SPEC,
            "robust.integral: expected true or false, got integer 1",
        ),
        (
            ("[simulation]", "[robust.observer]\nbandwith = 20.0\n\n[simulation]"),
            EXIT_BAD_SPEC,
            "robust.observer.bandwith: unknown key: did you mean 'bandwidth'?",
        ),
    ],
)
def test_errors_exit_with_one_line_and_write_nothing(
    tmp_path: Path,
    unicycle_text: str,
    capsys: pytest.CaptureFixture[str],
    mutation: tuple[str, str],
    code: int,
    message: str,
) -> None:
    text = unicycle_text.replace(*mutation)
    if mutation[0].startswith("integrate"):
        text = text.replace(", v = 1.0 }", " }")
    spec = write_spec(tmp_path, text)
    out = tmp_path / "out"
    assert main(["generate", str(spec), "--out", str(out)]) == code
    captured = capsys.readouterr()
    assert captured.out == ""
    lines = captured.err.strip().splitlines()
    assert len(lines) == 1 and message in lines[0] and lines[0].startswith("tvopt-codegen: error: ")
    assert not out.exists()


def test_edited_file_is_never_overwritten_without_force(tmp_path: Path) -> None:
    out = tmp_path / "out"
    assert main(["generate", "integrator", "--out", str(out), "--quiet"]) == 0
    target = out / "integrator.py"
    assert main(["generate", "integrator", "--out", str(out), "--quiet"]) == 0  # unchanged: fine
    edited = target.read_text().replace("PIVOT_TOLERANCE = 1e-12", "PIVOT_TOLERANCE = 1e-9")
    target.write_text(edited)
    assert main(["generate", "integrator", "--out", str(out), "--quiet"]) == EXIT_OUTPUT
    assert target.read_text() == edited
    assert main(["generate", "integrator", "--out", str(out), "--quiet", "--force"]) == 0
    assert "PIVOT_TOLERANCE = 1e-12" in target.read_text()


def test_a_users_own_file_is_never_overwritten(tmp_path: Path) -> None:
    out = tmp_path / "out"
    out.mkdir()
    (out / "integrator.py").write_text("# my own notes\n")
    assert main(["generate", "integrator", "--out", str(out), "--quiet"]) == EXIT_OUTPUT
    assert (out / "integrator.py").read_text() == "# my own notes\n"
    assert [p.name for p in out.iterdir()] == ["integrator.py"]  # no temporary litter, no manifest


def test_symlinked_target_is_refused(tmp_path: Path) -> None:
    out = tmp_path / "out"
    out.mkdir()
    victim = tmp_path / "victim.txt"
    victim.write_text("precious")
    (out / "integrator.py").symlink_to(victim)
    assert main(["generate", "integrator", "--out", str(out), "--quiet"]) == EXIT_OUTPUT
    assert victim.read_text() == "precious"


def test_python_dash_m_and_console_script(tmp_path: Path) -> None:
    done = subprocess.run(
        [sys.executable, "-X", "importtime", "-m", "tvopt_codegen", "check", "integrator"],
        capture_output=True,
        text=True,
        cwd=tmp_path,
        check=False,
    )
    assert done.returncode == 0, done.stderr
    assert "k = 1" in done.stdout
    # A command imports its own module of the table only, and its spec's names are
    # checked against the backends without importlib.metadata (0.03 s) where no
    # installed package declares a backend (test_the_backends_other_packages_...).
    loaded = {line.rpartition("|")[2].strip() for line in done.stderr.splitlines()}
    commands = {m for m in loaded if m.startswith("tvopt_codegen.commands.")}
    assert commands == {f"tvopt_codegen.commands.{m}" for m in ("check", "common", "run_options")}
    assert "importlib.metadata" not in loaded and "tvopt_codegen.spec.names" in loaded
    bad = subprocess.run(
        [sys.executable, "-m", "tvopt_codegen", "check", "no_such_spec"],
        capture_output=True,
        text=True,
        cwd=tmp_path,
        check=False,
    )
    assert bad.returncode == EXIT_BAD_SPEC
    assert "Traceback" not in bad.stderr
    assert bad.stderr.count("\n") == 1


def test_the_backends_other_packages_declare_are_found_when_first_looked_up(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    from tvopt_codegen import backends  # noqa: PLC0415

    python = backends.BACKENDS["python"]
    # None declared on this path: the registry reads no package's metadata, whether the
    # standard library's path finder finds the distributions or the importlib_metadata
    # backport's, which takes its place once a library imports it.
    assert not backends._maybe_declared()

    # Another finder of distributions: importlib.metadata would ask it, and so is asked.
    class Finder:
        def find_distributions(self, context: object = None) -> list[object]:
            return []

    with monkeypatch.context() as patched:
        patched.setattr(sys, "meta_path", [*sys.meta_path, Finder()])
        assert backends._maybe_declared()
    # An installed package that declares one, through its metadata's entry points.
    (tmp_path / "toy_plugin.py").write_text(
        "import dataclasses\n"
        "from tvopt_codegen.backends.python import BACKEND\n"
        "PLUGIN = dataclasses.replace(BACKEND, name='plugin')\n"
    )
    info = tmp_path / "toy_plugin-1.0.dist-info"
    info.mkdir()
    (info / "METADATA").write_text("Metadata-Version: 2.1\nName: toy-plugin\nVersion: 1.0\n")
    (info / "entry_points.txt").write_text(
        f"[{backends.ENTRY_POINT_GROUP}]\nplugin = toy_plugin:PLUGIN\n"
    )
    monkeypatch.syspath_prepend(str(tmp_path))
    monkeypatch.delitem(sys.modules, "toy_plugin", raising=False)
    registry = backends._Registry()
    monkeypatch.setattr(backends, "BACKENDS", registry)
    assert dict.__len__(registry) == 0  # made, not read
    assert sorted(registry) == ["c", "plugin", "python"]
    assert registry["plugin"].name == "plugin" and registry["python"] is python
    # The parser's --backend offers it, read from the registry when given.
    with pytest.raises(SystemExit) as stop:
        main(["generate", "integrator", "--backend", "nosuch"])
    assert stop.value.code == EXIT_BAD_SPEC
    assert "(choose from 'c', 'plugin', 'python')" in capsys.readouterr().err


def test_demo_spec_file_path_works(tmp_path: Path) -> None:
    spec = ROOT / "tvopt_codegen" / "examples" / "integrator.toml"
    assert main(["generate", str(spec), "--out", str(tmp_path), "--quiet"]) == 0
    assert (tmp_path / "integrator.py").exists()


def test_derivation_progress_names_stage_count_and_time(
    capsys: pytest.CaptureFixture[str],
) -> None:
    assert main(["check", "unicycle_ring", "--progress", "always"]) == 0
    lines = capsys.readouterr().err.splitlines()
    stages = [line.split(":")[1].split(",")[0].strip() for line in lines]
    assert stages[0] == "model" and "gradient jet" in stages and "error bound" in stages
    assert stages[-1] == "kernels and CSE"
    counts = [int(line.split(", ")[1].split()[0]) for line in lines]
    nodes = [int(line.split("(")[1].split()[0]) for line in lines]
    seconds = [float(line.rsplit(", ", 1)[1].removesuffix(" s")) for line in lines]
    assert counts == sorted(counts) and counts[-1] > 100
    assert nodes == sorted(nodes) and nodes[-1] > 2 * counts[-1]
    assert seconds == sorted(seconds)
    # Off a terminal the default says nothing: logs and error messages stay clean.
    assert main(["check", "unicycle_ring"]) == 0
    assert capsys.readouterr().err == ""


def test_a_command_runs_with_the_collectors_thresholds_and_restores_them(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    seen: list[tuple[int, int, int]] = []
    before = gc.get_threshold()

    def run(argv: object) -> int:
        seen.append(gc.get_threshold())
        raise RuntimeError("boom")  # restored on every way out, an internal error too

    monkeypatch.setattr(cli, "run", run)
    assert main(["check", "integrator"]) != 0
    assert seen == [cli.GC_THRESHOLDS] != [before]
    assert gc.get_threshold() == before
    assert "internal error" in capsys.readouterr().err


def test_compiled_templates_are_cached_and_change_nothing(tmp_path: Path) -> None:
    # jinja's compiled templates are kept across commands; the output is the same cold,
    # warm, and with a cache folder that cannot be used.
    def generate(cache: Path, out: str) -> dict[str, bytes]:
        env = dict(os.environ, TVOPT_CODEGEN_CACHE=str(cache))
        command = [sys.executable, "-m", "tvopt_codegen", "generate", "integrator", "--quiet"]
        subprocess.run([*command, "--out", str(tmp_path / out)], env=env, check=True)
        return snapshot(tmp_path / out)

    cache = tmp_path / "cache"
    cold = generate(cache, "cold")
    entries = sorted((cache / "templates").iterdir())
    assert entries and all(e.name.startswith("__jinja2_") for e in entries)
    stamps = {e: e.stat().st_mtime_ns for e in entries}
    assert generate(cache, "warm") == cold
    assert {e: e.stat().st_mtime_ns for e in entries} == stamps  # read, not rewritten
    blocked = tmp_path / "a-file"
    blocked.write_text("not a folder\n")
    assert generate(blocked, "blocked") == cold


def test_the_process_ends_without_teardown_but_with_its_exit_handlers(tmp_path: Path) -> None:
    # entry() ends the process with os._exit (freeing a derivation's objects one by one
    # took a quarter of a command): exit handlers still run, output is whole, and the
    # exit code is kept; with another thread alive, Python exits as usual.
    script = (
        "import atexit, sys, threading\n"
        "atexit.register(lambda: print('handler ran', flush=True))\n"
        "stop = threading.Event()\n"
        "if sys.argv[1] == 'thread':\n"
        "    threading.Thread(target=stop.wait).start()\n"
        "from tvopt_codegen.__main__ import entry\n"
        "sys.argv = ['tvopt-codegen', *sys.argv[2:]]\n"
        "code = entry()\n"
        "print('returned', code, flush=True)\n"
        "stop.set()\n"
        "sys.exit(code)\n"
    )

    def run(*args: str) -> subprocess.CompletedProcess[str]:
        command = [sys.executable, "-c", script, *args]
        return subprocess.run(command, capture_output=True, text=True, check=False)

    done = run("main", "check", "pvtol")
    assert done.returncode == 0
    assert "relative degree" in done.stdout and "derivation time" in done.stdout
    assert done.stdout.rstrip().endswith("handler ran") and "returned" not in done.stdout
    bad = run("main", "check", "no_such_spec")
    assert bad.returncode == EXIT_BAD_SPEC and bad.stderr.count("\n") == 1
    assert bad.stdout == "handler ran\n"
    usual = run("thread", "check", "integrator")
    assert usual.returncode == 0 and "returned 0" in usual.stdout
    assert usual.stdout.rstrip().endswith("handler ran")


def test_the_derivation_runs_without_the_cyclic_collector_and_turns_it_back_on(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    # What the derivation built is frozen for the rest of the command (the collector's
    # next scan would visit all of it, for no garbage) and unfrozen when main returns.
    seen: list[bool] = []
    frozen: list[int] = []
    real_limit, real_summary = common.time_limit, summary.format_summary

    def spy(*args: Any) -> Any:
        seen.append(gc.isenabled())
        return real_limit(*args)

    def summarise(*args: Any) -> str:
        frozen.append(gc.get_freeze_count())
        return real_summary(*args)

    monkeypatch.setattr(common, "time_limit", spy)
    monkeypatch.setattr(summary, "format_summary", summarise)
    gc.unfreeze()
    assert main(["check", "integrator"]) == 0
    assert seen == [False] and gc.isenabled()
    assert frozen[0] > 10000 and gc.get_freeze_count() == 0
    bad = write_spec(tmp_path, "not toml [")
    assert main(["check", str(bad)]) != 0
    assert gc.isenabled() and gc.get_freeze_count() == 0  # also after an error


def test_a_budget_signal_swallowed_where_it_landed_still_ends_the_block() -> None:
    """The timer's Overrun can land in a garbage collector's callback or a __del__, where
    Python prints it and goes on (seen under a loaded suite: an import wrote its files
    past its budget): the budget still ran out, so the block ends with the budget's error
    and the command writes nothing after it."""
    import time

    from tvopt_codegen.errors import BudgetError

    progress = common.DeriveProgress("never")
    progress.stage = "a stage"
    ran_on = []
    with pytest.raises(BudgetError, match="a stage"):
        with common.time_limit(0.05, ["spec.toml"], progress):
            try:
                time.sleep(1.0)
            except common.Overrun:
                pass  # as a gc callback would swallow it
            ran_on.append(True)
    assert ran_on == [True]  # the block ran on, and its end still ran out
