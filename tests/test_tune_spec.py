"""The tuned spec's text (``tune/spec_text``) and the ``[tune]`` table of the spec.

The writer changes only the tuned values: each test diffs the lines of the user's text
and the result, and reads the result back with the spec reader.
"""

from __future__ import annotations

import difflib
import tomllib
from pathlib import Path

import pytest

from tvopt_codegen.errors import SpecError
from tvopt_codegen.spec import TuneSettings, load_spec, parse_spec
from tvopt_codegen.tune.spec_text import pole_items, poles_text, tuned_text

from .conftest import ROOT, write_spec

PVTOL = ROOT / "tvopt_codegen" / "examples" / "pvtol.toml"
ROBUST_PVTOL = ROOT / "tests" / "specs" / "robust_pvtol.toml"


def changed_lines(old: str, new: str) -> list[str]:
    """The diff's removed and added lines, in order (``-`` and ``+`` prefixed)."""
    return [
        line.rstrip("\n")
        for line in difflib.unified_diff(old.splitlines(True), new.splitlines(True), n=0)
        if line[:1] in "+-" and not line.startswith(("+++", "---"))
    ]


def test_the_bundled_pvtol_gets_new_poles_and_nothing_else() -> None:
    text = PVTOL.read_text(encoding="utf-8")
    poles = [-1.2, complex(-2.0, 1.5), complex(-2.0, -1.5), -3.4]
    new = tuned_text(text, "pvtol.toml", poles=poles)
    assert changed_lines(text, new) == [
        "-poles = [-1.0, -1.5, -2.0, -2.5]",
        "+poles = [-1.2, [-2.0, 1.5], -3.4]",
    ]
    # The spec reader reads exactly the poles asked for, conjugates included.
    assert parse_spec("tuned", new.encode()).poles == (-1.2, -2 + 1.5j, -2 - 1.5j, -3.4)


def test_the_same_shape_is_replaced_item_by_item_with_the_shortest_decimals() -> None:
    text = PVTOL.read_text(encoding="utf-8")
    new = tuned_text(text, "pvtol.toml", poles=[-0.1 - 0.2, -1e-5, -2.5e16, -7.0])
    assert changed_lines(text, new) == [
        "-poles = [-1.0, -1.5, -2.0, -2.5]",
        "+poles = [-0.30000000000000004, -1e-05, -2.5e+16, -7.0]",
    ]
    assert parse_spec("tuned", new.encode()).poles == (-0.1 - 0.2, -1e-5, -2.5e16, -7.0)


def test_coefficients_become_poles(tmp_path: Path) -> None:
    text = PVTOL.read_text(encoding="utf-8").replace(
        "poles = [-1.0, -1.5, -2.0, -2.5]", "coefficients = [-24, -50, -35, -10]  # (s+1)..(s+4)"
    )
    new = tuned_text(text, "c.toml", poles=[-1.0, -2.0, complex(-1.5, 0.5), complex(-1.5, -0.5)])
    assert changed_lines(text, new) == [
        "-coefficients = [-24, -50, -35, -10]  # (s+1)..(s+4)",
        "+poles = [-1.0, -2.0, [-1.5, 0.5]]  # (s+1)..(s+4)",
    ]
    spec = load_spec(write_spec(tmp_path, new))
    assert spec.coefficients is None and spec.poles == (-1.0, -2.0, -1.5 + 0.5j, -1.5 - 0.5j)


def test_pairs_keep_their_spacing_and_a_pair_can_replace_two_reals() -> None:
    text = PVTOL.read_text(encoding="utf-8").replace(
        "poles = [-1.0, -1.5, -2.0, -2.5]", "poles = [ [-1.0,0.5], -3.0 , [ -2.0 , 1.0 ] ]"
    )
    same = tuned_text(
        text,
        "p.toml",
        poles=[complex(-0.8, -0.25), complex(-0.8, 0.25), -4.5, complex(-2.5, 2), -2.5 - 2j],
    )
    assert changed_lines(text, same) == [
        "-poles = [ [-1.0,0.5], -3.0 , [ -2.0 , 1.0 ] ]",
        "+poles = [ [-0.8,0.25], -4.5 , [ -2.5 , 2.0 ] ]",
    ]
    # Another structure (two reals where a pair was): the array is written anew.
    other = tuned_text(text, "p.toml", poles=[-1.0, -1.1, -4.5, -2.0 + 1j, -2.0 - 1j])
    assert changed_lines(text, other)[1] == "+poles = [-1.0, -1.1, -4.5, [-2.0, 1.0]]"


def test_the_observer_bandwidth_of_robust_pvtol() -> None:
    text = ROBUST_PVTOL.read_text(encoding="utf-8")
    new = tuned_text(
        text,
        "robust_pvtol.toml",
        poles=[-0.7, -1.25, -2.0, -2.5, -3.0],
        bandwidth=12.5,
        header=["tuned by tvopt-codegen tune robust_pvtol.toml --seed 3", "objective 0.0412"],
    )
    assert changed_lines(text, new) == [
        "+# tuned by tvopt-codegen tune robust_pvtol.toml --seed 3",
        "+# objective 0.0412",
        "-poles = [-1.0, -1.5, -2.0, -2.5, -3.0]",
        "+poles = [-0.7, -1.25, -2.0, -2.5, -3.0]",
        "-bandwidth = 20.0",
        "+bandwidth = 12.5",
    ]
    spec = parse_spec("tuned", new.encode())
    assert spec.robust.observer == 12.5 and spec.robust.integral
    assert spec.poles == (-0.7, -1.25, -2.0, -2.5, -3.0)
    # Only the bandwidth: the poles stay as written.
    alone = tuned_text(text, "robust_pvtol.toml", poles=None, bandwidth=7.0)
    assert changed_lines(text, alone) == ["-bandwidth = 20.0", "+bandwidth = 7.0"]


def test_the_eso_bandwidth(tmp_path: Path) -> None:
    text = ROBUST_PVTOL.read_text(encoding="utf-8").replace("[robust.observer]", "[robust.eso]")
    new = tuned_text(text, "eso.toml", poles=None, eso_bandwidth=33.0)
    assert changed_lines(text, new) == ["-bandwidth = 20.0", "+bandwidth = 33.0"]
    assert load_spec(write_spec(tmp_path, new)).robust.eso == 33.0
    # The observer's bandwidth is not in this spec: nothing to rewrite.
    with pytest.raises(SpecError) as info:
        tuned_text(text, "eso.toml", poles=None, bandwidth=33.0)
    assert str(info.value) == (
        "eso.toml: robust.observer.bandwidth: cannot be rewritten in place: "
        "the spec does not set it"
    )


MULTI_LINE = '''\
# A hand-written spec: comments everywhere, the error dynamics before the plant.
name = "integrator2"
description = """Two integrators.
[error_dynamics]
poles = [-9.0]   # not a key: this is the description"""

[error_dynamics]          # the tuned table
poles = [
    -1.0,   # slow
    [-2.0, 1.0],  # a pair, re +/- i im
    # a comment line inside the array
    -3.0,
]  # after the array

[system]
states = ["x", "v"]
inputs = ["u"]

[system.dynamics]
x = "v"
v = "u"

[system.outputs]
y = "x"

[objective]
f0 = "(y - sin(t))**2"

[simulation]
initial_state = { x = 0.0, v = 0.0 }
'''


def test_a_multi_line_array_with_comments_keeps_its_layout() -> None:
    new = tuned_text(MULTI_LINE, "m.toml", poles=[-1.5, -2.5 + 0.5j, -2.5 - 0.5j, -4.0])
    assert changed_lines(MULTI_LINE, new) == [
        "-    -1.0,   # slow",
        "-    [-2.0, 1.0],  # a pair, re +/- i im",
        "+    -1.5,   # slow",
        "+    [-2.5, 0.5],  # a pair, re +/- i im",
        "-    -3.0,",
        "+    -4.0,",
    ]
    assert tomllib.loads(new)["description"] == tomllib.loads(MULTI_LINE)["description"]
    # Four poles in place of three items: one line, the comment after the array kept.
    four = tuned_text(MULTI_LINE, "m.toml", poles=[-1.0, -2.0, -3.0, -4.0, -5.0])
    start = MULTI_LINE.index("poles = [\n")
    end = MULTI_LINE.index("]  # after")
    assert four == (
        MULTI_LINE[:start] + "poles = [-1.0, -2.0, -3.0, -4.0, -5.0]" + MULTI_LINE[end + 1 :]
    )
    assert parse_spec("four", four.encode()).poles == (-1.0, -2.0, -3.0, -4.0, -5.0)


def test_the_dotted_spelling_at_the_top_and_an_inline_table() -> None:
    # MULTI_LINE without its [error_dynamics] table, given at the top as a dotted key.
    start = MULTI_LINE.index("[error_dynamics]  ")
    end = MULTI_LINE.index("]  # after the array\n") + len("]  # after the array\n")
    dotted = (MULTI_LINE[:start] + MULTI_LINE[end:]).replace(
        'name = "integrator2"\n',
        'name = "integrator2"\nerror_dynamics.coefficients = [-2.0, -3.0]  # (s+1)(s+2)\n',
    )
    new = tuned_text(dotted, "d.toml", poles=[-1.0 + 2j, -1.0 - 2j])
    assert changed_lines(dotted, new) == [
        "-error_dynamics.coefficients = [-2.0, -3.0]  # (s+1)(s+2)",
        "+error_dynamics.poles = [[-1.0, 2.0]]  # (s+1)(s+2)",
    ]
    assert parse_spec("d", new.encode()).poles == (-1 + 2j, -1 - 2j)

    inline = dotted.replace(
        "error_dynamics.coefficients = [-2.0, -3.0]  # (s+1)(s+2)",
        "error_dynamics = { poles = [-1.0, -2.0] }",
    )
    new = tuned_text(inline, "i.toml", poles=[-0.5, -6.0])
    assert changed_lines(inline, new) == [
        "-error_dynamics = { poles = [-1.0, -2.0] }",
        "+error_dynamics = { poles = [-0.5, -6.0] }",
    ]
    # A dotted key under [robust] and an inline table under it: both found.
    robust = ROBUST_PVTOL.read_text(encoding="utf-8").replace(
        "[robust.observer]\nbandwidth = 20.0", "observer.bandwidth = 20.0"
    )
    assert "bandwidth = 9.5" in tuned_text(robust, "r.toml", poles=None, bandwidth=9.5)
    robust = robust.replace("observer.bandwidth = 20.0", "observer = {bandwidth=20.0}")
    new = tuned_text(robust, "r.toml", poles=None, bandwidth=9.5)
    assert changed_lines(robust, new) == [
        "-observer = {bandwidth=20.0}",
        "+observer = {bandwidth=9.5}",
    ]


def test_crlf_files_keep_crlf_and_the_header_is_comments_only() -> None:
    text = PVTOL.read_text(encoding="utf-8").replace("\n", "\r\n")
    new = tuned_text(
        text,
        "p.toml",
        poles=[-1.0, -1.5, -2.0, -3.0],
        header=["tuned\nby tune", "a\x1bb", ""],
    )
    assert new.startswith("# tuned\r\n# by tune\r\n# a\\x1bb\r\n#\r\nname = ")
    assert new.count("\r\n") == text.count("\r\n") + 4 and "\n" not in new.replace("\r\n", "")
    assert tomllib.loads(new)["error_dynamics"]["poles"] == [-1.0, -1.5, -2.0, -3.0]


def test_what_cannot_be_written_is_refused() -> None:
    text = PVTOL.read_text(encoding="utf-8")
    with pytest.raises(ValueError, match="no conjugate"):
        tuned_text(text, "p.toml", poles=[-1.0, -2.0 + 1j])
    with pytest.raises(ValueError, match="not finite"):
        tuned_text(text, "p.toml", poles=[float("nan")])
    with pytest.raises(ValueError, match="no poles"):
        tuned_text(text, "p.toml", poles=[])
    with pytest.raises(ValueError, match="not a positive bandwidth"):
        tuned_text(text, "p.toml", poles=None, bandwidth=0.0)
    # No error dynamics to rewrite (the reader would refuse this spec too).
    bare = text.replace("poles = [-1.0, -1.5, -2.0, -2.5]", "")
    with pytest.raises(SpecError) as info:
        tuned_text(bare, "p.toml", poles=[-1.0])
    assert str(info.value) == (
        "p.toml: error_dynamics.poles: cannot be rewritten in place: neither "
        "error_dynamics.poles nor error_dynamics.coefficients was found"
    )
    with pytest.raises(SpecError, match=r"^p.toml: \(file\): TOML syntax error"):
        tuned_text(text + "\n[error_dynamics]\n", "p.toml", poles=[-1.0])
    # A bandwidth that is a table, not a number: the scanner does not guess.
    table = ROBUST_PVTOL.read_text(encoding="utf-8").replace(
        "bandwidth = 20.0", "bandwidth = { value = 20.0 }"
    )
    with pytest.raises(SpecError, match="robust.observer.bandwidth: .* not a number"):
        tuned_text(table, "r.toml", poles=None, bandwidth=5.0)


def test_an_array_of_tables_is_refused_not_guessed() -> None:
    # An array of tables holding the key: TOML allows it, the spec has no such table,
    # and the scanner files it where no tuned value is looked for.
    text = PVTOL.read_text(encoding="utf-8").replace(
        "[error_dynamics]\npoles = [-1.0, -1.5, -2.0, -2.5]",
        "[[error_dynamics]]\npoles = [-1.0, -1.5, -2.0, -2.5]",
    )
    with pytest.raises(SpecError, match="error_dynamics.poles: cannot be rewritten in place"):
        tuned_text(text, "p.toml", poles=[-1.0])


def test_a_wrong_rewrite_is_caught_by_reading_back(monkeypatch: pytest.MonkeyPatch) -> None:
    """The read-back check fails loudly when the replaced spans were the wrong ones."""
    from tvopt_codegen.tune import spec_text

    text = ROBUST_PVTOL.read_text(encoding="utf-8")

    def wrong_span(*args: object) -> tuple[int, int, str]:
        start = text.index("integral = true") + len("integral = ")
        return start, start + len("true"), "false"

    monkeypatch.setattr(spec_text, "_bandwidth_edit", wrong_span)
    with pytest.raises(SpecError) as info:
        tuned_text(text, "r.toml", poles=None, bandwidth=5.0)
    assert str(info.value).startswith("r.toml: robust.integral: cannot be rewritten in place")


def test_pole_items_pair_conjugates_where_the_first_stands() -> None:
    assert pole_items([-1 - 2j, -3.0, -1 + 2j]) == [(-1.0, 2.0), -3.0]
    assert poles_text([(-1.0, 2.0), -3.0]) == "[[-1.0, 2.0], -3.0]"
    # A repeated pair is two pairs.
    assert pole_items([-1 + 1j, -1 + 1j, -1 - 1j, -1 - 1j]) == [(-1.0, 1.0), (-1.0, 1.0)]


# ------------------------------------------------------------------ the [tune] table

TUNE = """
[tune]
objective = "p95(max_error)"
constraints = ["p95(peak_thrust) <= 14.0", "failure_bound <= 0.05"]
after = 2
pole_range = [0.5, 8]
min_damping = 0.5
bandwidth_range = [5.0, 50.0]
"""


def test_the_tune_table_is_read_as_written(tmp_path: Path) -> None:
    spec = load_spec(write_spec(tmp_path, ROBUST_PVTOL.read_text(encoding="utf-8") + TUNE))
    assert spec.tune == TuneSettings(
        objective="p95(max_error)",
        constraints=("p95(peak_thrust) <= 14.0", "failure_bound <= 0.05"),
        after=2.0,
        pole_range=(0.5, 8.0),
        min_damping=0.5,
        bandwidth_range=(5.0, 50.0),
    )
    assert spec.tune is not None and spec.tune.pole_range is not None
    assert isinstance(spec.tune.after, float) and isinstance(spec.tune.pole_range[1], float)
    # Without the table: None; an empty table: every choice left to tune.
    assert load_spec(ROBUST_PVTOL).tune is None
    empty = load_spec(write_spec(tmp_path, PVTOL.read_text(encoding="utf-8") + "\n[tune]\n"))
    assert empty.tune == TuneSettings()


def test_the_tune_table_leaves_everything_else_alone(tmp_path: Path) -> None:
    text = ROBUST_PVTOL.read_text(encoding="utf-8")
    plain = load_spec(write_spec(tmp_path, text, "plain.toml"))
    tuned = load_spec(write_spec(tmp_path, text + TUNE, "tuned.toml"))
    for name in plain.__dataclass_fields__:
        if name not in {"source", "sha256", "tune"}:
            assert getattr(plain, name) == getattr(tuned, name), name
    # The tuned spec keeps its [tune] table: the writer rewrites only the values.
    new = tuned_text(text + TUNE, "t.toml", poles=[-1.0, -2.0, -3.0, -4.0, -5.0], bandwidth=9.0)
    assert new.endswith(TUNE)
    assert parse_spec("t", new.encode()).tune == tuned.tune


BAD_TUNE = [
    # (the table's line, the error's field and message)
    ("objective = 3", "tune.objective: expected a string, got integer 3"),
    ('objective = "  "', "tune.objective: expected a requirement, got an empty string"),
    ('constraints = "a <= 1"', "tune.constraints: expected a list of strings, got string 'a <= 1'"),
    ('constraints = ["a <= 1", true]', "tune.constraints[1]: expected a string, got boolean true"),
    ("after = -0.5", "tune.after: must be a time >= 0 (seconds), got -0.5"),
    ('after = "2 s"', "tune.after: expected a number, got string '2 s'"),
    ("pole_range = 3.0", "tune.pole_range: expected [lo, hi], got float 3.0"),
    (
        "pole_range = [1.0, 2.0, 3.0]",
        "tune.pole_range: expected [lo, hi], got array [1.0, 2.0, 3.0]",
    ),
    ("pole_range = [4.0, 2.0]", "tune.pole_range: expected 0 < lo < hi, got [4, 2]"),
    ("pole_range = [0.0, 2.0]", "tune.pole_range: expected 0 < lo < hi, got [0, 2]"),
    ('pole_range = [1.0, "fast"]', "tune.pole_range[1]: expected a number, got string 'fast'"),
    ("min_damping = 0.0", "tune.min_damping: a damping ratio in (0, 1] is needed, got 0"),
    ("min_damping = 1.5", "tune.min_damping: a damping ratio in (0, 1] is needed, got 1.5"),
    ("bandwidth_range = [50.0, 5.0]", "tune.bandwidth_range: expected 0 < lo < hi, got [50, 5]"),
    ("pole_rang = [1.0, 2.0]", "tune.pole_rang: unknown key: did you mean 'pole_range'?"),
]


@pytest.mark.parametrize(("line", "message"), BAD_TUNE)
def test_a_bad_tune_value_is_one_line_naming_it(tmp_path: Path, line: str, message: str) -> None:
    path = write_spec(tmp_path, ROBUST_PVTOL.read_text(encoding="utf-8") + f"\n[tune]\n{line}\n")
    with pytest.raises(SpecError) as info:
        load_spec(path)
    text = str(info.value)
    assert text.startswith(f"{path}: {message}") and "\n" not in text, text


def test_a_bandwidth_range_needs_an_observer(tmp_path: Path) -> None:
    path = write_spec(tmp_path, PVTOL.read_text() + "\n[tune]\nbandwidth_range = [1.0, 9.0]\n")
    with pytest.raises(SpecError) as info:
        load_spec(path)
    assert str(info.value) == (
        f"{path}: tune.bandwidth_range: the spec has no [robust.observer] or [robust.eso] "
        "bandwidth to tune"
    )
    # The extended-state observer's bandwidth is tuned as well.
    eso = ROBUST_PVTOL.read_text().replace("[robust.observer]", "[robust.eso]")
    eso_path = write_spec(tmp_path, eso + "\n[tune]\nbandwidth_range = [1, 9]\n", "e.toml")
    assert load_spec(eso_path).tune == TuneSettings(bandwidth_range=(1.0, 9.0))
    misspelt = write_spec(tmp_path, PVTOL.read_text() + "\n[tunee]\n", "t.toml")
    with pytest.raises(SpecError, match=r"tunee: unknown key: did you mean 'tune'\?"):
        load_spec(misspelt)


SPECS = sorted(
    [
        *(ROOT / "tvopt_codegen" / "examples").glob("*.toml"),
        *(ROOT / "tests" / "specs").glob("*.toml"),
    ]
)


@pytest.mark.parametrize("path", SPECS, ids=lambda p: p.name)
def test_the_scanner_finds_every_value_of_every_spec_as_tomllib_reads_it(path: Path) -> None:
    from tvopt_codegen.tune.spec_text import _Scanner

    text = path.read_text(encoding="utf-8")
    data = tomllib.loads(text)
    entries = _Scanner(text).document()
    assert entries
    for key, entry in entries.items():
        value: object = data
        for part in key:
            assert isinstance(value, dict)
            value = value[part]
        span = text[entry.value.start : entry.value.end]
        assert tomllib.loads(f"v = {span}")["v"] == value, key
        assert text[entry.key_start : entry.key_end].strip("\"'") == key[-1]

    # Every leaf of the document is one of them, or inside one (an inline table's entries
    # are found too).
    def leaves(table: dict[str, object], prefix: tuple[str, ...]) -> set[tuple[str, ...]]:
        found = set()
        for name, item in table.items():
            found |= leaves(item, (*prefix, name)) if isinstance(item, dict) else {(*prefix, name)}
        return found

    assert leaves(data, ()) <= set(entries)


def test_generate_writes_the_same_files_with_a_tune_table(tmp_path: Path) -> None:
    from tvopt_codegen.cli import main

    text = (ROOT / "tvopt_codegen" / "examples" / "integrator.toml").read_text(encoding="utf-8")
    plain = write_spec(tmp_path, text, "plain.toml")
    tuned = write_spec(tmp_path, text + '\n[tune]\nobjective = "p95(final_error)"\n', "t.toml")
    outputs = []
    for spec in (plain, tuned):
        out = tmp_path / spec.stem
        assert main(["generate", str(spec), "--out", str(out), "--quiet"]) == 0
        files = {p.relative_to(out): p.read_text(encoding="utf-8") for p in out.rglob("*.py")}
        outputs.append(files)
    assert outputs[0].keys() == outputs[1].keys() and outputs[0]
    digests = [load_spec(spec).sha256 for spec in (plain, tuned)]

    def unstamped(text: str, digest: str, source: str) -> list[str]:
        # The stamp names the spec's bytes and their file, and hashes the rest.
        text = text.replace(digest, "<spec>").replace(source, "<file>")
        return [line for line in text.splitlines() if not line.startswith("# content sha256:")]

    for name, text in outputs[0].items():
        plain_lines = unstamped(text, digests[0], "plain.toml")
        assert plain_lines == unstamped(outputs[1][name], digests[1], "t.toml"), name
        assert any("<spec>" in line for line in plain_lines)
