"""``tvopt-codegen tune`` against hostile input: one line, the right exit, nothing written.

Every refusal names its file (or "command line") and field, exits 2 (bad spec, command
line or record) or 4 (output), and leaves the folders as they were; a valid but unusual
input (a spec by coefficients, complex pairs, integral action, a plant on which every
sample fails) runs to a tuned spec that ``check`` accepts. The tunes are tiny (4
samples, a handful of candidates, a 4 s horizon) on the in-process worker.
"""

from __future__ import annotations

import copy
import fcntl
import json
import os
import shutil
import tomllib
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest

from tvopt_codegen.errors import EXIT_BAD_SPEC, EXIT_OUTPUT, SpecError
from tvopt_codegen.tune.space import space_for

from .conftest import ROOT, SPECS, Ran, run_main, shared

pytest.importorskip("cma")
pytest.importorskip("pyarrow")

EXAMPLES = ROOT / "tvopt_codegen" / "examples"
PVTOL_TEXT = (EXAMPLES / "pvtol.toml").read_text(encoding="utf-8")

#: The sweep's and the search's options of a tiny tune (the spec comes first).
TINY = (
    "--samples", "4",
    "--evaluations", "6",
    "--population", "3",
    "--seed", "3",
    "--t-final", "4",
    "--points", "41",
    "--sample-time", "0.01",
    "--check-samples", "4",
    "--workers", "1",
    "--progress", "never",
)  # fmt: skip


def snapshot(folder: Path) -> dict[str, bytes | str]:
    """Every entry under ``folder``: a file's bytes, a link's target, a folder's mark."""
    found: dict[str, bytes | str] = {}
    for path in sorted(folder.rglob("*")):
        name = str(path.relative_to(folder))
        if path.is_symlink():
            found[name] = "-> " + os.readlink(path)
        elif path.is_file():
            found[name] = path.read_bytes()
        else:
            found[name] = "folder"
    return found


def refused(ran: Ran, code: int, *words: str) -> str:
    """The one line of a refusal, checked: its exit, no traceback, the words it names."""
    lines = ran.stderr.strip().splitlines()
    assert ran.returncode == code, ran.stderr
    assert len(lines) == 1, ran.stderr
    assert "Traceback" not in ran.stderr and "internal error" not in ran.stderr
    for word in words:
        assert word in lines[0], (word, lines[0])
    return lines[0]


# ------------------------------------------------------------------ the command line


@pytest.mark.parametrize(
    ("options", "named"),
    [
        (["--pole-range", "nan:2"], "--pole-range"),
        (["--pole-range", "1:inf"], "--pole-range"),
        (["--pole-range=-1:2"], "--pole-range"),
        (["--pole-range", "-1:2"], "--pole-range"),  # argparse's: it looks like an option
        (["--pole-range", "1:"], "--pole-range"),
        (["--pole-range", ":"], "--pole-range"),
        (["--pole-range", "1:2:3"], "--pole-range"),
        (["--pole-range", "abc"], "--pole-range"),
        (["--pole-range", "1:1e400"], "--pole-range"),
        (["--pole-range", "5:1"], "--pole-range"),
        (["--bandwidth-range", "1:2"], "--bandwidth-range"),  # PVTOL has no observer
        (["--min-damping", "nan"], "--min-damping"),
        (["--min-damping", "0"], "--min-damping"),
        (["--min-damping", "-1"], "--min-damping"),
        (["--min-damping", "inf"], "--min-damping"),
        (["--complex-pairs", "3"], "--complex-pairs"),
        (["--complex-pairs", "-1"], "--complex-pairs"),
        (["--population", "1"], "--population"),
        (["--population", str(10**9)], "--population"),
        (["--evaluations", str(10**12)], "--evaluations"),
        (["--samples", "0"], "--samples"),
        (["--check-samples", "0"], "--check-samples"),
        (["--check-seed", "-1"], "--check-seed"),
        (["--check-seed", str(2**64)], "--check-seed"),
        (["--after", "nan"], "--after"),
        (["--after", "inf"], "--after"),
        (["--after", "-1"], "--after"),
        (["--after", "4"], "--after"),  # the horizon itself
        (["--objective", ""], "--objective"),
        (["--objective", "p95()"], "--objective"),
        (["--objective", "P95(final_error)"], "--objective"),
        (["--objective", "p95(final_error"], "--objective"),
        (["--objective", "p95(fïnal_error)"], "--objective"),
        (["--objective", "\uff5095(final_error)"], "--objective"),  # a full-width p
        (["--constraint", "failure_bound <= nan"], "--constraint"),
        (["--constraint", "failure_bound <= inf"], "--constraint"),
        (["--constraint", "failure_bound >= 0.1"], "--constraint"),
        (["--constraint", "failure_bound <= 0.001"], "--constraint"),  # 4 samples cannot
        (["--constraint", "mean(saturation) <= -0.1"], "--constraint"),
        (["--constraint", "max(peak_nope) <= 3"], "--constraint"),
        # A horizon shorter than one controller period: the gains would act once.
        (["--t-final", "0.001"], "--t-final"),
        (["--method", "bogus"], "--method"),
    ],
)
def test_a_bad_option_is_one_line_and_writes_nothing(
    tmp_path: Path, options: list[str], named: str
) -> None:
    out = tmp_path / "out"
    ran = run_main("tune", "pvtol", *TINY, *options, "--out", str(out))
    refused(ran, EXIT_BAD_SPEC, named)
    assert not out.exists()


def test_complex_pairs_that_leave_no_real_pole_for_integral_action(tmp_path: Path) -> None:
    """robust_pvtol has 5 poles with integral action: 3 pairs do not fit; of an even
    count with integral action, count / 2 pairs would leave no real pole for the integral."""
    out = tmp_path / "out"
    spec = str(SPECS / "robust_pvtol.toml")
    ran = run_main("tune", spec, *TINY, "--complex-pairs", "3", "--out", str(out))
    refused(ran, EXIT_BAD_SPEC, "command line", "--complex-pairs", "H has 5")
    assert not out.exists()
    with pytest.raises(SpecError, match="no real pole for integral action") as error:
        space_for([-1.0, -2.0, -3.0, -4.0], None, integral=True, pairs=2)
    assert error.value.field == "--complex-pairs"


# ------------------------------------------------------------------ the spec's [tune] table


def spec_with_table(folder: Path, lines: str, text: str = PVTOL_TEXT) -> Path:
    path = folder / "spec.toml"
    path.write_text(f"{text}\n[tune]\n{lines}\n", encoding="utf-8")
    return path


@pytest.mark.parametrize(
    ("lines", "field"),
    [
        ("objective = 3", "tune.objective"),
        ('objective = "p95(nope)"', "tune.objective"),
        ('constraints = "x"', "tune.constraints"),
        ("constraints = [3]", "tune.constraints[0]"),
        ('constraints = ["p95(nope) <= 1"]', "tune.constraints[0]"),
        ('after = "1"', "tune.after"),
        ("after = 10.0", "tune.after"),
        ("after = nan", "tune.after"),
        ("pole_range = [1]", "tune.pole_range"),
        ("pole_range = [2, 1]", "tune.pole_range"),
        ("pole_range = [0, 1]", "tune.pole_range"),
        ('pole_range = ["a", "b"]', "tune.pole_range[0]"),
        ("pole_range = [1, inf]", "tune.pole_range[1]"),
        ("pole_range = [1e-300, 1e300]", "tune.pole_range"),
        ("min_damping = 2", "tune.min_damping"),
        ("min_damping = nan", "tune.min_damping"),
        ("bandwidth_range = [1, 2]", "tune.bandwidth_range"),  # no observer
        ("nope = 1", "tune.nope"),
    ],
)
def test_a_bad_tune_table_names_the_spec_and_its_key(
    tmp_path: Path, lines: str, field: str
) -> None:
    spec = spec_with_table(tmp_path, lines)
    out = tmp_path / "out"
    line = refused(run_main("tune", str(spec), *TINY, "--out", str(out)), EXIT_BAD_SPEC)
    assert f"{spec}: {field}:" in line, line
    assert not out.exists()


def test_the_command_line_overrides_its_own_key_of_the_table_and_no_other(
    tmp_path: Path,
) -> None:
    """--objective replaces the table's; the table's pole_range holds beside --min-damping.

    Before, any of the three bounds on the command line dropped the table's other two:
    the pole range the spec asked for was silently widened to the default.
    """
    spec = spec_with_table(tmp_path, 'objective = "mean(max_error)"\npole_range = [0.5, 3.0]')
    out = tmp_path / "out"
    ran = run_main(
        "tune", str(spec), *TINY, "--objective", "p90(final_error)", "--min-damping", "0.5",
        "--out", str(out),
    )  # fmt: skip
    assert ran.returncode == 0, ran.stderr
    record = json.loads((out / "tune.json").read_text())
    assert record["fresh"]["tuned"]["constraints"]  # it ran to the end
    assert "p90(final_error)" in (out / "tune.md").read_text()
    for evaluation in record["evaluations"][1:]:
        for re, im in evaluation["poles"]:
            assert 0.5 * 0.9999 <= abs(complex(re, im)) <= 3.0 * 1.0001, evaluation["poles"]


# ------------------------------------------------------------------ --out


@pytest.mark.parametrize("name", ["pvtol_tuned.toml", "tune.md", "evaluations.csv"])
def test_a_users_file_in_out_is_kept_unless_force(tmp_path: Path, name: str) -> None:
    out = tmp_path / "out"
    out.mkdir()
    (out / name).write_text("my own notes\n")
    ran = run_main("tune", "pvtol", *TINY, "--out", str(out))
    refused(ran, EXIT_OUTPUT, name, "--force")
    assert snapshot(out) == {name: b"my own notes\n"}


def test_force_replaces_a_users_tune_md(tmp_path: Path) -> None:
    out = tmp_path / "out"
    out.mkdir()
    (out / "tune.md").write_text("my own notes\n")
    ran = run_main("tune", "pvtol", *TINY, "--out", str(out), "--force")
    assert ran.returncode == 0, ran.stderr
    assert (out / "tune.md").read_text().startswith("#")


@pytest.mark.parametrize("force", [[], ["--force"]])
def test_the_tunes_copy_never_replaces_the_users_spec(tmp_path: Path, force: list[str]) -> None:
    """--out is the folder of SPEC, named <name>.toml: refused, even with --force.

    Before, --force wrote the tune's copy over the user's spec and claimed it in the
    folder's manifest as the tool's own file.
    """
    spec = tmp_path / "pvtol.toml"
    spec.write_text(PVTOL_TEXT + "\n# my comment, which the copy must not take over\n")
    before = snapshot(tmp_path)
    ran = run_main("tune", str(spec), *TINY, "--out", str(tmp_path), *force)
    refused(ran, EXIT_OUTPUT, str(spec), "choose another --out")
    assert snapshot(tmp_path) == before


def test_the_tuned_spec_never_replaces_the_users_spec(tmp_path: Path) -> None:
    spec = tmp_path / "pvtol_tuned.toml"
    spec.write_text(PVTOL_TEXT)
    before = snapshot(tmp_path)
    ran = run_main("tune", str(spec), *TINY, "--out", str(tmp_path), "--force")
    refused(ran, EXIT_OUTPUT, str(spec))
    assert snapshot(tmp_path) == before


def test_out_a_file_or_a_link_is_refused(tmp_path: Path) -> None:
    (tmp_path / "f").write_text("x")
    refused(run_main("tune", "pvtol", *TINY, "--out", str(tmp_path / "f")), EXIT_OUTPUT, "f")
    out = tmp_path / "out"
    out.mkdir()
    (tmp_path / "precious").write_text("precious")
    (out / "tune.json").symlink_to(tmp_path / "precious")
    before = snapshot(tmp_path)
    for force in ([], ["--force"]):
        ran = run_main("tune", "pvtol", *TINY, "--out", str(out), *force)
        refused(ran, EXIT_OUTPUT, "tune.json")
        assert snapshot(tmp_path) == before


@pytest.mark.skipif(os.geteuid() == 0, reason="by design: root writes in read-only folders")
def test_out_in_a_read_only_folder(tmp_path: Path) -> None:
    locked = tmp_path / "ro"
    locked.mkdir()
    locked.chmod(0o555)
    try:
        ran = run_main("tune", "pvtol", *TINY, "--out", str(locked / "out"))
        refused(ran, EXIT_OUTPUT)
        assert not (locked / "out").exists()
    finally:
        locked.chmod(0o755)


# ------------------------------------------------------------------ --resume


@pytest.fixture(scope="module")
def finished() -> Path:
    """One tiny complete tune of PVTOL (6 candidates in generations of 3), tuned once per
    run for every worker (the tests copy it, or check that it is left as it was)."""

    def tune_once(folder: Path) -> None:
        ran = run_main("tune", "pvtol", *TINY, "--out", str(folder / "out"))
        assert ran.returncode == 0, ran.stderr

    return shared("tune-hostile-finished", tune_once) / "out"


def interrupted_copy(finished: Path, folder: Path, keep: int = 4) -> Path:
    """``finished`` as an interrupted tune would have left it: ``keep`` evaluations."""
    out = folder / "t"
    shutil.copytree(finished, out)
    record = json.loads((out / "tune.json").read_text())
    record["state"] = "interrupted"
    record["evaluations"] = record["evaluations"][:keep]
    record.pop("best")
    record.pop("fresh")
    (out / "tune.json").write_text(json.dumps(record))
    return out


def test_a_resume_of_a_cut_tune_ends_where_the_whole_one_did(
    finished: Path, tmp_path: Path
) -> None:
    out = interrupted_copy(finished, tmp_path)
    ran = run_main("tune", "--resume", str(out))
    assert ran.returncode == 0, ran.stderr
    for name in ("pvtol_tuned.toml", "tune.md", "evaluations.csv"):
        assert (out / name).read_bytes() == (finished / name).read_bytes(), name
    assert json.loads((out / "tune.json").read_text()) == json.loads(
        (finished / "tune.json").read_text()
    )


def test_a_complete_tune_has_nothing_to_resume(finished: Path, tmp_path: Path) -> None:
    out = tmp_path / "t"
    shutil.copytree(finished, out)
    before = snapshot(out)
    ran = run_main("tune", "--resume", str(out))
    assert ran.returncode == 0 and "nothing to resume" in ran.stderr, ran.stderr
    assert snapshot(out) == before


Edit = Callable[[dict[str, Any], Path], object]


def _set(path: str, value: object) -> Edit:
    """Set ``record[a][b]...`` (``path`` as ``a.b``; a number is a list's index)."""

    def edit(record: dict[str, Any], _folder: Path) -> None:
        *parents, last = path.split(".")
        target: Any = record
        for key in parents:
            target = target[int(key)] if isinstance(target, list) else target[key]
        if isinstance(target, list):
            target[int(last)] = value
        else:
            target[last] = value

    return edit


def _drop(key: str) -> Edit:
    def edit(record: dict[str, Any], _folder: Path) -> None:
        del record[key]

    return edit


def _write(name: str, text: str) -> Edit:
    return lambda _record, folder: (folder / name).write_text(text)


def _remove(name: str) -> Edit:
    return lambda _record, folder: (folder / name).unlink()


def _raw(text: str) -> Edit:
    return lambda _record, folder: (folder / "tune.json").write_text(text)


@pytest.mark.parametrize(
    ("label", "edit", "field"),
    [
        ("not a tune's", _remove("tune.json"), "tune.json"),
        ("cut short", _raw('{"kind": "tune", "settings": {"evalu'), "tune.json"),
        ("not JSON", _raw("hello"), "tune.json"),
        ("a list", _raw("[1, 2]"), "kind"),
        ("another kind", _set("kind", "sweep"), "kind"),
        ("a strange state", _set("state", "weird"), "state"),
        ("settings missing", _drop("settings"), "settings"),
        ("samples a string", _set("settings.samples", "x"), "settings"),
        ("samples 0", _set("settings.samples", 0), "settings.samples"),
        ("10^12 candidates", _set("settings.evaluations", 10**12), "settings.evaluations"),
        ("a method that is not", _set("settings.method", "bogus"), "settings.method"),
        ("population 1", _set("settings.population", 1), "settings.population"),
        ("seed -1", _set("settings.seed", -1), "settings.seed"),
        ("a float seed", _set("settings.check_seed", 1.5), "settings"),
        ("pole range of one", _set("settings.pole_range", [2]), "settings"),
        ("pole range backwards", _set("settings.pole_range", [2, 1]), "settings.pole_range"),
        ("an unknown objective", _set("settings.objective", "p95(x)"), "settings (--objective)"),
        ("constraints a string", _set("settings.constraints", "abc"), "settings"),
        ("evaluations a dict", _set("evaluations", {}), "evaluations"),
        ("evaluations null", _set("evaluations", None), "evaluations"),
        ("an evaluation a string", _set("evaluations.1", "x"), "evaluations[1]"),
        ("poles strings", _set("evaluations.1.poles", ["a", "b"]), "evaluations[1]"),
        ("too few poles", _set("evaluations.1.poles", [[-1.0, 0.0]]), "evaluations[1]"),
        ("unstable poles", _set("evaluations.1.poles", [[1.0, 0.0]] * 4), "evaluations[1]"),
        ("an objective NaN", _set("evaluations.1.value", "nan"), "evaluations[1]"),
        ("a negative index", _set("evaluations.1.index", -1), "evaluations[1]"),
        ("an index gap", _set("evaluations.2.index", 5), "evaluations[2]"),
        ("a generation not asked", _set("evaluations.2.generation", 7), "evaluations[2]"),
        ("a position not asked", _set("evaluations.2.position", 99), "evaluations[2]"),
        ("a point moved", _set("evaluations.2.x.0", 0.123), "evaluations[2]"),
        ("options not a table", _set("options", [1]), "options"),
        ("initial a list", _set("options.initial", [1]), "options"),
        ("the spec's copy missing", _remove("pvtol.toml"), "pvtol.toml"),
        ("the spec's copy edited", _write("pvtol.toml", PVTOL_TEXT + "# x\n"), "spec_sha256"),
        (
            "the spec's copy another spec",
            _write("pvtol.toml", (SPECS / "robust_pvtol.toml").read_text()),
            "spec_sha256",
        ),
        ("the spec's name a path", _set("spec", "../x.toml"), "spec"),
    ],
)
def test_a_bad_record_is_refused_before_anything_changes(
    finished: Path, tmp_path: Path, label: str, edit: Edit, field: str
) -> None:
    out = interrupted_copy(finished, tmp_path)
    record = json.loads((out / "tune.json").read_text())
    if edit(record, out) is None and (out / "tune.json").exists():
        (out / "tune.json").write_text(json.dumps(record))
    before = snapshot(out)
    line = refused(run_main("tune", "--resume", str(out)), EXIT_BAD_SPEC, field)
    assert str(out) in line, line
    assert snapshot(out) == before, label


@pytest.mark.parametrize(
    ("extra", "named"),
    [(["pvtol"], "--resume"), (["--out", "elsewhere"], "--out"), (["--samples", "5"], "--samples")],
)
def test_resume_takes_no_spec_and_no_options(
    finished: Path, tmp_path: Path, extra: list[str], named: str
) -> None:
    out = interrupted_copy(finished, tmp_path)
    before = snapshot(out)
    refused(run_main("tune", "--resume", str(out), *extra), EXIT_BAD_SPEC, named)
    assert snapshot(out) == before


def test_a_second_tune_in_a_locked_folder_is_refused(finished: Path, tmp_path: Path) -> None:
    """The folder's lock is held (as a running tune holds it): a resume and a new tune wait."""
    out = interrupted_copy(finished, tmp_path)
    with open(out / ".tvopt-sweep.lock", "a") as handle:
        fcntl.flock(handle, fcntl.LOCK_EX)
        before = snapshot(out)
        for command in (("--resume", str(out)), ("pvtol", *TINY, "--out", str(out), "--force")):
            refused(run_main("tune", *command), EXIT_OUTPUT, "another tune")
            assert snapshot(out) == before


# ------------------------------------------------------------------ valid but unusual


COEFFICIENTS = PVTOL_TEXT.replace(
    "poles = [-1.0, -1.5, -2.0, -2.5]", "coefficients = [-24.0, -50.0, -35.0, -10.0]"
)
PAIRS = PVTOL_TEXT.replace("poles = [-1.0, -1.5, -2.0, -2.5]", "poles = [[-1.0, 1.0], -2.0, -3.0]")


@pytest.mark.parametrize(
    ("text", "pairs"),
    [(COEFFICIENTS, 0), (PAIRS, 1), ((SPECS / "robust_pvtol.toml").read_text(), 0)],
    ids=["coefficients", "complex-pairs", "integral-action-and-observer"],
)
def test_an_unusual_spec_tunes_to_a_spec_that_checks(tmp_path: Path, text: str, pairs: int) -> None:
    assert text != PVTOL_TEXT
    spec = tmp_path / "mine.toml"
    spec.write_text(text)
    out = tmp_path / "out"
    ran = run_main("tune", str(spec), *TINY, "--evaluations", "3", "--out", str(out))
    assert ran.returncode == 0, ran.stderr
    name = tomllib.loads(text)["name"]
    tuned = out / f"{name}_tuned.toml"
    record = json.loads((out / "tune.json").read_text())
    chosen = record["evaluations"][record["best"]]
    dynamics = tomllib.loads(tuned.read_text())["error_dynamics"]
    if record["best"] == 0:
        # The spec's own gains won: its [error_dynamics] stays as written (coefficients).
        assert dynamics == tomllib.loads(text)["error_dynamics"]
        assert run_main("check", str(tuned)).returncode == 0
        return
    poles = dynamics["poles"]
    written = [complex(*p) if isinstance(p, list) else complex(p) for p in poles]
    assert len([p for p in poles if isinstance(p, list)]) == pairs
    recorded = {complex(re, abs(im)) for re, im in chosen["poles"]}
    assert {complex(p.real, abs(p.imag)) for p in written} == recorded
    assert (out / f"{name}.toml").read_text() == text
    checked = run_main("check", str(tuned))
    assert checked.returncode == 0, checked.stderr


def test_every_sample_failing_keeps_the_specs_gains_and_a_strict_record(
    tmp_path: Path,
) -> None:
    """A plant a billion times lighter than the model: every sample diverges.

    The tune ends (exit 0) with the spec's gains (nothing is better), and its record has
    no NaN or Infinity token (strict JSON, which the fresh check's infinite objective and
    missing input effort once broke), and reads back for --resume.
    """
    out = tmp_path / "out"
    options = (*TINY, "--evaluations", "2", "--population", "2")
    ran = run_main(
        "tune", "pvtol", *options, "--plant-param", "m=uniform(1e-9, 2e-9)", "--out", str(out)
    )
    assert ran.returncode == 0, ran.stderr
    text = (out / "tune.json").read_text()

    def no_constant(word: str) -> None:
        raise AssertionError(f"{word} in tune.json")

    record = json.loads(text, parse_constant=no_constant)
    assert all(e["failures"] == e["runs"] == 4 for e in record["evaluations"])
    assert record["best"] == 0
    assert record["fresh"]["tuned"]["objective"] == "inf"
    tuned = tomllib.loads((out / "pvtol_tuned.toml").read_text())
    assert tuned["error_dynamics"]["poles"] == [-1.0, -1.5, -2.0, -2.5]
    # Cut to the spec's gains and the first candidate, it resumes to the same end.
    cut = copy.deepcopy(record)
    cut["state"] = "interrupted"
    cut["evaluations"] = cut["evaluations"][:2]
    del cut["best"], cut["fresh"]
    (out / "tune.json").write_text(json.dumps(cut))
    again = run_main("tune", "--resume", str(out))
    assert again.returncode == 0, again.stderr
    assert json.loads((out / "tune.json").read_text()) == record
