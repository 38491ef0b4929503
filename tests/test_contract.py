"""The contract every registered backend keeps, checked against the independent oracle.

A new backend is added to the registry (a module of ``tvopt_codegen.backends``, an entry
point, or :func:`~tvopt_codegen.backends.register`) and these tests run over it
unchanged. A toy backend, a registry entry and a template folder and nothing else,
shows that nothing shared needs editing.
"""

from __future__ import annotations

import os
from pathlib import Path
from types import ModuleType

import numpy as np
import pytest

from tvopt_codegen import backends
from tvopt_codegen.backends import BACKENDS, Backend
from tvopt_codegen.cli import main
from tvopt_codegen.emit.stamp import is_pristine
from tvopt_codegen.errors import SpecError
from tvopt_codegen.lowering.ir import KernelSet
from tvopt_codegen.renderer.rendering import render
from tvopt_codegen.simulation import load_controller
from tvopt_codegen.spec import load_spec

from .conftest import derivation, kernels, write_spec
from .oracle import Oracle
from .test_generated import random_states

SPECS = ("integrator", "unicycle_switch", "two_unicycles_barrier")
_LOADED: dict[tuple[str, str], ModuleType] = {}


def _module(backend: str, spec: str, cache: Path) -> ModuleType:
    if (backend, spec) not in _LOADED:
        os.environ.setdefault("TVOPT_CODEGEN_CACHE", str(cache))
        _LOADED[backend, spec] = load_controller(kernels(spec), backend)
    return _LOADED[backend, spec]


@pytest.mark.parametrize("spec", SPECS)
@pytest.mark.parametrize("backend", sorted(BACKENDS))
def test_every_backend_keeps_the_contract(
    backend: str, spec: str, tmp_path_factory: pytest.TempPathFactory
) -> None:
    d = derivation(spec)
    mod = _module(backend, spec, tmp_path_factory.getbasetemp() / "cache")
    # Identity and constants.
    assert mod.BACKEND == backend
    assert mod.STATE_NAMES == d.closed_loop.state_names and mod.K == d.dynamics.k
    assert mod.OUTPUT_NAMES == d.spec.outputs and mod.INPUT_NAMES == d.spec.inputs
    assert mod.DEFAULT_STATE == d.closed_loop.initial_state
    # The law, against the oracle, in a batch and one state at a time.
    states = random_states(spec, 12, seed=17)
    p = np.array([v for _, v in d.spec.parameters], dtype=float)
    u_ref, ds_ref = Oracle(d).law(0.7, states, p)
    u, ds = mod.control(0.7, states), mod.rhs(0.7, states)
    np.testing.assert_allclose(u, u_ref, rtol=1e-9, atol=1e-9 * np.abs(u_ref).max())
    np.testing.assert_allclose(ds, ds_ref, rtol=1e-9, atol=1e-9 * np.abs(ds_ref).max())
    for j in (0, 5):
        np.testing.assert_allclose(mod.control(0.7, states[:, j]), u[:, j], rtol=1e-14, atol=0)
    assert mod.optimality_error(0.7, states).shape == (d.dynamics.k, len(d.spec.outputs), 12)
    # Errors: the exception classes, their status codes and the failing column.
    assert issubclass(mod.ControllerError, ArithmeticError)
    bad = states.copy()
    bad[0, 3] = np.nan
    with pytest.raises(mod.NonFiniteInputError) as info:
        mod.rhs(0.7, bad)
    assert info.value.status == 1 and info.value.index == 3
    if spec == "unicycle_switch":
        bad = states.copy()
        bad[3, 4] = 0.0  # v = 0
        with pytest.raises(mod.SingularDecouplingError, match="R is singular where v = 0"):
            mod.control(0.7, bad)
    # Files: stamped, and the module users import is the backend's own file name.
    files = render(kernels(spec), backend)
    assert BACKENDS[backend].module.format(name=d.spec.name) in files
    assert all(is_pristine(text) for text in files.values())


def _toy(root: Path) -> Backend:
    """A listing of every kernel: the least a target needs (printer, templates, context)."""
    (root / "toy").mkdir(parents=True)
    (root / "toy" / "listing.txt.jinja").write_text(
        '{% import "python/_contract.jinja" as contract with context %}'
        "{{ contract.stamp() }}"
        "{{ spec.name }}: {{ kernel_count }} kernels (toy backend)\n"
        "{% for name, k in kernels.items() %}"
        "{{ name }}: {{ k.ops }} operations\n"
        "{% for out in k.outputs %}{% for _i, _f, code in out.elements %}"
        "  {{ out.name }} = {{ code }}\n"
        "{% endfor %}{% endfor %}{% endfor %}"
    )

    def context(lowered: KernelSet) -> dict[str, object]:
        return {"kernel_count": len(lowered.kernels)}

    return Backend(
        name="toy",
        description="a listing of the kernels (test)",
        printer=BACKENDS["python"].printer,
        templates=(("toy/listing.txt.jinja", "{name}.kernels.txt"),),
        module="{name}.kernels.txt",
        context=context,
        template_root=root,
        reserved=frozenset({"begin"}),
    )


def test_a_toy_backend_needs_a_registry_entry_and_a_template_folder(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    monkeypatch.setattr(backends, "BACKENDS", dict(BACKENDS))
    monkeypatch.setattr("tvopt_codegen.renderer.rendering.BACKENDS", backends.BACKENDS)
    monkeypatch.setattr("tvopt_codegen.spec.names.BACKENDS", backends.BACKENDS)
    toy = backends.register(_toy(tmp_path / "templates"))
    with pytest.raises(ValueError, match="registered already"):
        backends.register(_toy(tmp_path / "other"))
    files = render(kernels("integrator"), "toy")
    (text,) = files.values()
    assert list(files) == ["integrator.kernels.txt"]
    assert is_pristine(text) and "spec name: integrator" in text
    assert f"integrator: {len(kernels('integrator').kernels)} kernels (toy backend)" in text
    assert "jet_time:" in text and "(t*t*t)" in text  # printed by its printer
    # Through the command line, like any backend.
    out = tmp_path / "out"
    assert main(["generate", "integrator", "--backend", "toy", "--out", str(out), "--quiet"]) == 0
    assert (out / "integrator.kernels.txt").read_text() == text
    # Its reserved words are every spec's reserved words.
    spec = write_spec(
        tmp_path,
        (Path(__file__).parent.parent / "tvopt_codegen" / "examples" / "integrator.toml")
        .read_text()
        .replace("w = 2.0", "begin = 2.0\nw = 2.0"),
    )
    with pytest.raises(SpecError, match="reserved word of the toy backend"):
        load_spec(spec)
    assert toy.name in backends.BACKENDS
