"""docs/adding-a-spec-option.md, followed as written: its edits make a working option.

The page's edits are applied to a copy of the package and of ``docs/``; the copy then
reads the new option, refuses its bad values in one line naming the field, suggests it
for a misspelling, and lists it in its spec.md table.
"""

from __future__ import annotations

import json
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from .conftest import ROOT

PAGE = ROOT / "docs" / "adding-a-spec-option.md"

#: An edit of the page: the comment above a fenced block names its file and place.
_EDIT = re.compile(
    r"<!-- fragment: edit (\S+) \| (after|before|replace): (.*?) -->\n```\w*\n(.*?)```", re.S
)


def edits(page: Path = PAGE) -> list[tuple[str, str, str, str]]:
    """The page's edits: (file, where, anchor, text), in the page's order."""
    return [m.groups() for m in _EDIT.finditer(page.read_text(encoding="utf-8"))]


def apply(text: str, where: str, anchor: str, block: str) -> str:
    """``text`` with ``block`` after or before the line(s) of ``anchor``, or in its place."""
    if text.count(anchor) != 1:
        raise AssertionError(f"the anchor {anchor!r} occurs {text.count(anchor)} times")
    start = text.index(anchor)
    if where == "replace":
        return text.replace(anchor, block.rstrip("\n"))
    if where == "after":
        end = text.index("\n", start + len(anchor)) + 1
        return text[:end] + block + text[end:]
    line = text.rindex("\n", 0, start) + 1
    return text[:line] + block + text[line:]


def test_the_page_has_an_edit_for_each_place_an_option_touches() -> None:
    files = [file for file, *_ in edits()]
    assert files == [
        "tvopt_codegen/spec/types.py",
        "tvopt_codegen/spec/types.py",
        "tvopt_codegen/spec/settings.py",
        "tvopt_codegen/spec/settings.py",
        "tvopt_codegen/spec/reader.py",
        "docs/spec.md",
    ]


def test_an_anchor_that_is_not_unique_is_refused() -> None:
    with pytest.raises(AssertionError, match="occurs 2 times"):
        apply("a\nb\na\n", "after", "a", "x\n")
    assert apply("a\nb\n", "before", "b", "x\n") == "a\nx\nb\n"
    assert apply("a\nb\n", "after", "a", "x\n") == "a\nx\nb\n"


_CHECK = """
import json, sys
from pathlib import Path
from tvopt_codegen.errors import SpecError
from tvopt_codegen.spec import load_spec

base = Path(sys.argv[1]).read_text(encoding="utf-8")
out = {}
for name, extra in [("absent", ""), ("good", "max_step = 0.01"), ("negative", "max_step = -1"),
                    ("text", 'max_step = "small"'), ("misspelt", "max_stepp = 0.01")]:
    path = Path(sys.argv[2]) / f"{name}.toml"
    path.write_text(base.replace("[simulation]", "[simulation]\\n" + extra, 1), encoding="utf-8")
    try:
        out[name] = load_spec(path).max_step
    except SpecError as exc:
        out[name] = "error: " + str(exc)
print(json.dumps(out))
"""


def test_the_pages_edits_make_a_working_option(tmp_path: Path) -> None:
    copy = tmp_path / "copy"
    shutil.copytree(
        ROOT / "tvopt_codegen", copy / "tvopt_codegen", ignore=shutil.ignore_patterns("__pycache__")
    )
    shutil.copytree(ROOT / "docs", copy / "docs")
    for file, where, anchor, block in edits():
        target = copy / file
        target.write_text(apply(target.read_text(encoding="utf-8"), where, anchor, block))
    spec = ROOT / "tvopt_codegen" / "examples" / "integrator.toml"
    assert "[simulation]" in spec.read_text(encoding="utf-8")
    run = subprocess.run(
        [sys.executable, "-c", _CHECK, str(spec), str(tmp_path)],
        cwd=copy,
        env={"PYTHONPATH": str(copy), "PATH": "/usr/bin:/bin"},
        capture_output=True,
        text=True,
        check=True,
    )
    read = json.loads(run.stdout)
    assert read["absent"] is None
    assert read["good"] == 0.01
    for bad, why in [
        ("negative", "simulation.max_step: must be positive and at most"),
        ("text", "simulation.max_step:"),
        ("misspelt", "simulation.max_stepp: unknown key: did you mean 'max_step'?"),
    ]:
        assert read[bad].startswith("error: ") and why in read[bad], read[bad]
        assert "\n" not in read[bad]
    # The docs: the row sits in spec.md's field table, right under t_final's.
    table = (copy / "docs" / "spec.md").read_text(encoding="utf-8").splitlines()
    row = table.index(next(line for line in table if line.startswith("| `simulation.t_final`")))
    assert table[row + 1].startswith("| `simulation.max_step` | positive number |")
    # And the checkout itself is untouched: the option is the page's, not the tool's.
    assert "max_step" not in (ROOT / "tvopt_codegen" / "spec" / "types.py").read_text()
