"""generated/ holds the committed controllers; regeneration must not change a byte.

Run ``make regen`` after an intended change to the generated code, review the diff,
and commit it.
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from tvopt_codegen.emit.stamp import is_pristine
from tvopt_codegen.renderer.rendering import render

from .conftest import EXAMPLES, ROOT, kernels

GENERATED = ROOT / "generated"


@pytest.mark.parametrize(("backend", "folder"), [("python", GENERATED), ("c", GENERATED / "c")])
@pytest.mark.parametrize("name", EXAMPLES)
def test_committed_files_are_what_the_tool_generates(name: str, backend: str, folder: Path) -> None:
    for file_name, text in render(kernels(name), backend).items():
        committed = (folder / file_name).read_text(encoding="utf-8")
        assert text == committed, f"{folder / file_name} is stale: run `make regen`"
        assert is_pristine(committed)


def test_generated_folder_holds_exactly_the_examples() -> None:
    assert sorted(p.name for p in GENERATED.iterdir() if p.is_file()) == sorted(
        f"{n}.py" for n in EXAMPLES
    )
    assert sorted(p.name for p in (GENERATED / "c").iterdir()) == sorted(
        f"{n}{ext}" for n in EXAMPLES for ext in (".c", ".h", "_c.py", ".ext.c")
    )


def test_output_is_identical_across_hash_seeds_and_folders(tmp_path: Path) -> None:
    """Byte-identical output whatever PYTHONHASHSEED or the working folder."""
    texts = []
    for seed, folder in (("0", tmp_path), ("1", ROOT), ("12345", tmp_path / "sub")):
        folder.mkdir(exist_ok=True)
        out = tmp_path / f"out{seed}"
        env = dict(os.environ, PYTHONHASHSEED=seed)
        subprocess.run(
            [
                sys.executable,
                "-m",
                "tvopt_codegen",
                "generate",
                "two_unicycles_barrier",
                "--out",
                str(out),
                "--quiet",
            ],
            cwd=folder,
            env=env,
            check=True,
        )
        texts.append((out / "two_unicycles_barrier.py").read_bytes())
    assert texts[0] == texts[1] == texts[2]
    assert texts[0] == (GENERATED / "two_unicycles_barrier.py").read_bytes()


def test_stamp_detects_edits() -> None:
    text = (GENERATED / "integrator.py").read_text()
    assert is_pristine(text)
    assert not is_pristine(text.replace("K = 1", "K = 2"))
    assert not is_pristine("# a file of someone else\n")
