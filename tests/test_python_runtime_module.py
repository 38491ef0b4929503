"""The generated Python's fixed run-time code lives in real modules, copied verbatim.

``tvopt_codegen/backends/python/runtime/`` holds the Python every generated controller
carries unchanged (the input checks, the solves, the controller's numerics); the
templates insert it with the ``verbatim`` filter. These tests hold the three promises
that makes: every piece reaches the generated files unchanged, a generated file still
imports nothing from tvopt-codegen, and the fixed code is not copied back into a
template.
"""

from __future__ import annotations

import ast
import functools
import importlib
import subprocess
import sys
from pathlib import Path

import pytest

from tvopt_codegen.backends.python import runtime
from tvopt_codegen.backends.python.runtime import provided
from tvopt_codegen.renderer.rendering import render

from .conftest import ROOT, SPECS, import_file, kernels, shared

RUNTIME = ROOT / "tvopt_codegen" / "backends" / "python" / "runtime"
TEMPLATES = ROOT / "templates" / "python"

#: Specs that together reach every piece: the plain law, a mass matrix, barriers,
#: references with their estimators, limits with integral action and an observer, and
#: an extended-state observer.
COVERING = (
    "pvtol",
    "planar_arm3",
    "two_unicycles_barrier",
    str(SPECS / "figure8_wall.toml"),
    str(SPECS / "robust_pvtol.toml"),
    # Levant's differentiator (figure8_wall's is the linear one).
    "pvtol_refs",
    # The extended-state observer (drag_vehicle with [robust.eso], see _spec_path).
    "drag_vehicle_eso",
)

#: The pieces the C backend's Python wrapper does without.
C_ONLY_IN_NUMPY = [
    ("arguments", "check"),
    ("domain", "definite"),
    ("domain", "margin"),
    ("linalg", "batch"),
    ("linalg", "one_point"),
    ("blocks", None),
    ("chains", "advance"),
    ("limits", None),
    ("estimator", "python"),
    ("differentiator_linear", None),
    ("differentiator_levant", None),
    ("eso", None),
    ("evaluators", "inside"),
    ("evaluators", "plant"),
]


def _spec_path(spec: str) -> str:
    """``spec`` as ``kernels`` takes it; ``drag_vehicle_eso`` is written once per run."""
    if spec != "drag_vehicle_eso":
        return spec

    def build(folder: Path) -> None:
        text = (ROOT / "tvopt_codegen" / "examples" / "drag_vehicle.toml").read_text("utf-8")
        (folder / f"{spec}.toml").write_text(text + "\n[robust.eso]\nbandwidth = 20.0\n", "utf-8")

    return str(shared("runtime_module_eso_spec", build) / f"{spec}.toml")


@functools.cache
def rendered(spec: str, backend: str) -> str:
    """The module users import, as text (the C backend's is its Python wrapper)."""
    files = render(kernels(_spec_path(spec)), backend)
    (name,) = [name for name in files if name.endswith(".py")]
    return files[name]


def _defined(text: str) -> set[str]:
    """The names a piece of Python defines at its top level."""
    names: set[str] = set()
    for node in ast.parse(text).body:
        if isinstance(node, (ast.FunctionDef, ast.ClassDef)):
            names.add(node.name)
        elif isinstance(node, ast.Assign):
            names.update(t.id for t in node.targets if isinstance(t, ast.Name))
    return names


def test_every_module_imports_and_is_listed() -> None:
    files = {path.stem for path in RUNTIME.glob("*.py")} - {"__init__", "provided"}
    assert set(runtime.MODULES) == files
    for name in (*runtime.MODULES, "provided"):
        importlib.import_module(f"tvopt_codegen.backends.python.runtime.{name}")
    for name in runtime.MODULES:
        text = (RUNTIME / f"{name}.py").read_text(encoding="utf-8")
        assert text.count(runtime.MARKER) == 1, name
        for piece in runtime.sections(name).values():
            assert piece.strip() and not piece.endswith("\n"), name
            ast.parse(piece)  # each piece is whole Python on its own


@pytest.mark.parametrize("backend", ["python", "c"])
def test_every_piece_reaches_a_generated_file_unchanged(backend: str) -> None:
    texts = [rendered(spec, backend) for spec in COVERING]
    missing = []
    for name in runtime.MODULES:
        for section, piece in runtime.sections(name).items():
            if not any(piece in text for text in texts):
                missing.append((name, section))
    # The NumPy module carries every piece. The C backend's wrapper shares the
    # contract's: its evaluators check their inputs, and the law's numerics, the
    # controller's chains and limits and the differentiators are in its C (its estimator
    # extrapolates in Python, with the Taylor shift).
    assert missing == ([] if backend == "python" else C_ONLY_IN_NUMPY)


@pytest.mark.parametrize("spec", COVERING)
def test_a_generated_module_defines_what_the_pieces_read(spec: str, tmp_path: Path) -> None:
    """Every placeholder of ``provided`` that a copied piece reads is defined there."""
    text = rendered(spec, "python")
    path = tmp_path / "generated_module.py"
    path.write_text(text, encoding="utf-8")
    module = import_file(path, f"_tvopt_runtime_{Path(spec).stem}")
    copied = "\n".join(
        piece
        for name in runtime.MODULES
        for piece in runtime.sections(name).values()
        if piece in text
    )
    words = set(copied.replace("(", " ").replace(")", " ").replace("[", " ").split())
    for name in provided.__all__:
        if name in words or f"{name}," in words or f"{name}:" in words:
            assert hasattr(module, name), f"{spec}: {name} is read but not defined"


def test_the_generated_file_imports_without_tvopt_codegen(tmp_path: Path) -> None:
    """Users import generated modules without the tool installed."""
    for spec in ("pvtol", str(SPECS / "robust_pvtol.toml"), str(SPECS / "figure8_wall.toml")):
        stem = Path(spec).stem
        (tmp_path / f"{stem}.py").write_text(rendered(spec, "python"), encoding="utf-8")
    script = (
        "import sys\n"
        "class Refuse:\n"
        "    def find_spec(self, name, path=None, target=None):\n"
        "        if name.partition('.')[0] == 'tvopt_codegen':\n"
        "            raise ImportError('tvopt_codegen is not installed')\n"
        "sys.meta_path.insert(0, Refuse())\n"
        f"sys.path.insert(0, {str(tmp_path)!r})\n"
        "import numpy\n"
        "import pvtol, robust_pvtol, figure8_wall\n"
        "x = robust_pvtol.DEFAULT_STATE[:len(robust_pvtol.PLANT_STATE_NAMES)]\n"
        "robust_pvtol.Controller(x).step(0.01, x)\n"
        "s = numpy.array(pvtol.DEFAULT_STATE)\n"
        "assert pvtol.control(0.0, s).shape == (len(pvtol.INPUT_NAMES),)\n"
        "assert 'tvopt_codegen' not in sys.modules\n"
    )
    done = subprocess.run(
        [sys.executable, "-I", "-c", script],
        check=False,
        capture_output=True,
        text=True,
        cwd=tmp_path,
    )
    assert done.returncode == 0, done.stderr


def test_the_templates_do_not_carry_the_fixed_code() -> None:
    """A fix to the run-time code goes into its module, not into a template's copy."""
    fixed = set()
    for name in runtime.MODULES:
        for piece in runtime.sections(name).values():
            fixed |= _defined(piece)
    # The classes whose signatures and docstrings name the spec's sizes stay in the
    # templates; their logic is here.
    assert {"_Controller", "_ReferenceEstimator"}.isdisjoint(fixed)
    assert {"ControllerError", "ReferenceEstimator", "_start", "_measured"} <= fixed
    # Copied code adds no public name to a generated module: its API is the template's.
    assert {name for name in fixed if not name.startswith("_")} == {
        "ControllerError",
        "ReferenceEstimator",
    }
    # The C backend's _check_inputs does nothing (its compiled code checks): a template's
    # one-line alternative to the module's, not a copy of it.
    fixed.discard("_check_inputs")
    for template in sorted(TEMPLATES.glob("*.jinja")):
        text = template.read_text(encoding="utf-8")
        for name in sorted(fixed):
            assert f"def {name}(" not in text and f"class {name}(" not in text, (
                f"{template.name} defines {name}: edit runtime/ instead"
            )
            assert f"\n{name} = " not in text, f"{template.name} assigns {name}"


def test_an_unknown_module_or_section_is_an_error() -> None:
    with pytest.raises(runtime.RuntimeSourceError, match="no run-time module"):
        runtime.verbatim("nothing")
    with pytest.raises(runtime.RuntimeSourceError, match="no section 'nothing'"):
        runtime.verbatim("arguments", "nothing")
    with pytest.raises(runtime.RuntimeSourceError, match="no section None"):
        runtime.verbatim("arguments")
