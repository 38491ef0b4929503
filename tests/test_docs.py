"""Every example in the README and docs/ runs as written (issue 31).

A ```python block is executed in a fresh folder where the bundled ``unicycle_switch``
module is importable; a ```toml block that is a whole spec is derived, any other is
parsed. A block the page marks ``<!-- fragment: why -->`` needs what a page cannot give
(a robot's sensors, a sweep's folder): it is only compiled, or skipped for TOML. The
README's worked example runs command by command, as a user would.
"""

from __future__ import annotations

import re
import runpy
import shlex
import sys
import textwrap
import tomllib
from pathlib import Path

import pytest

from tvopt_codegen.cli import main

from .conftest import ROOT

PAGES = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
_BLOCK = re.compile(
    r"(<!-- fragment: [^>]* -->\n)?[ \t]*```(python|toml|console)\n(.*?)[ \t]*```", re.S
)


def _blocks(page: Path, language: str) -> list[tuple[str, bool]]:
    """The page's code blocks in ``language``: (text, whether marked a fragment)."""
    found = []
    for match in _BLOCK.finditer(page.read_text(encoding="utf-8")):
        if match.group(2) == language:
            found.append((textwrap.dedent(match.group(3)), bool(match.group(1))))
    return found


def _ids(language: str) -> list[tuple[Path, int]]:
    return [(page, k) for page in PAGES for k in range(len(_blocks(page, language)))]


@pytest.mark.parametrize(
    ("page", "index"), _ids("python"), ids=lambda v: v.name if isinstance(v, Path) else str(v)
)
def test_a_python_example_runs(
    page: Path, index: int, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    text, fragment = _blocks(page, "python")[index]
    code = compile(text, f"{page.name} python block {index}", "exec")
    if fragment:
        return
    if page.name == "README.md":
        pytest.skip("the README's worked example runs in its own test, after its commands")
    pytest.importorskip("control") if "import control" in text else None
    assert main(["generate", "unicycle_switch", "--out", str(tmp_path), "--quiet"]) == 0
    monkeypatch.chdir(tmp_path)
    monkeypatch.syspath_prepend(str(tmp_path))
    exec(code, {"__name__": "__doc_example__"})  # noqa: S102 - the docs' own examples


@pytest.mark.parametrize(
    ("page", "index"), _ids("toml"), ids=lambda v: v.name if isinstance(v, Path) else str(v)
)
def test_a_toml_example_reads(page: Path, index: int) -> None:
    text, fragment = _blocks(page, "toml")[index]
    if fragment:
        pytest.skip("a fragment the page marks as such")
    table = tomllib.loads(text)
    if "system" in table and "name" in table:
        from tvopt_codegen.derivation import derive
        from tvopt_codegen.spec import spec_from_dict

        derive(spec_from_dict(table))


def test_the_readmes_worked_example_runs_as_a_user_would(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    readme = ROOT / "README.md"
    ((spec, _),) = _blocks(readme, "toml")
    ((console, _),) = _blocks(readme, "console")
    ((program, _),) = _blocks(readme, "python")
    monkeypatch.chdir(tmp_path)
    Path("robot.toml").write_text(spec, encoding="utf-8")
    for line in console.splitlines():
        command = shlex.split(line.removeprefix("$ "))
        assert command[0] == "tvopt-codegen"
        assert main(command[1:]) == 0, line
    printed = capsys.readouterr().out
    assert "certificate: PASSED" in printed and "det R = v; singular where v = 0" in printed
    monkeypatch.setattr(sys, "path", list(sys.path))
    (tmp_path / "loop.py").write_text(program, encoding="utf-8")
    runpy.run_path(str(tmp_path / "loop.py"), run_name="__main__")
    distance = float(capsys.readouterr().out.rsplit(":", 1)[1].split()[0])
    assert distance < 1e-3  # the robot is on the moving point


def test_the_readme_lists_only_commands_that_exist(capsys: pytest.CaptureFixture[str]) -> None:
    text = (ROOT / "README.md").read_text(encoding="utf-8")
    commands = set(re.findall(r"^\| `tvopt-codegen (\w+)", text, re.M))
    assert commands >= {"check", "generate", "simulate", "report", "export", "sweep", "examples"}
    for command in sorted(commands):
        with pytest.raises(SystemExit) as done:
            main([command, "--help"])
        assert done.value.code == 0
    capsys.readouterr()
