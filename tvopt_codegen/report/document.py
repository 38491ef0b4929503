"""The whole report: its sections in order, results found beside it, HTML and Markdown."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path

from tvopt_codegen import __version__
from tvopt_codegen import symbolic as sx
from tvopt_codegen.derivation import Derivation
from tvopt_codegen.emit import read_own_output
from tvopt_codegen.lowering.ir import KernelSet
from tvopt_codegen.renderer.rendering import render_template
from tvopt_codegen.report.entries import Section
from tvopt_codegen.report.robust import _robustness
from tvopt_codegen.report.sections import (
    _control_law,
    _error_dynamics,
    _extension,
    _linearization,
    _model,
    _objective,
    _provenance,
    _simulation,
)

#: Report formats and their templates.
FORMATS = {"html": "report/report.html.jinja", "md": "report/report.md.jinja"}


#: Section headings, in order (the tests check every one is present).
HEADINGS = (
    "Model",
    "Dynamic extension and padding",
    "Relative degree and linearization",
    "Objective",
    "Error dynamics",
    "Control law",
    "Generated code and provenance",
    "Simulation",
)
#: The sections a spec with [robust] or [limits] adds after "Control law", one per option
#: it takes, in this order.
ROBUST_HEADINGS = (
    "Integral action",
    "Disturbance observer",
    "Extended-state observer",
    "Actuator limits",
)


#: Largest simulation output the report reads: a certificate is a few KB, a figure
#: a few hundred.
MAX_RESULT_BYTES = {"certificate.txt": 1_000_000, "png": 20_000_000}


def read_results(folder: str | Path, name: str) -> dict[str, bytes]:
    """The simulation outputs of ``name`` in ``folder`` the report shows (may be empty).

    Only files ``simulate`` wrote there and nobody changed since are read, each within
    a size bound, so a stray or huge file of that name costs neither memory nor trust.
    """
    found = {}
    for stem in ("certificate.txt", "paths.png", "convergence.png", "inputs.png"):
        file_name = f"{name}_{stem}"
        limit = MAX_RESULT_BYTES.get(stem, MAX_RESULT_BYTES["png"])
        data = read_own_output(folder, file_name, limit)
        if data is not None:
            found[file_name] = data
    return found


def report_sections(
    derivation: Derivation, kernels: KernelSet, results: Mapping[str, bytes] | None = None
) -> tuple[Section, ...]:
    """All sections of the report, in :data:`HEADINGS` order (and :data:`ROBUST_HEADINGS`)."""
    d = derivation
    robust = _robustness(d)
    return (
        _model(d),
        _extension(d),
        _linearization(d),
        _objective(d),
        _error_dynamics(d),
        _control_law(d),
        *robust,
        _provenance(d, kernels),
        _simulation(d, results or {}),
    )


def render_report(
    derivation: Derivation,
    kernels: KernelSet,
    results: Mapping[str, bytes] | None = None,
    formats: Sequence[str] = ("html", "md"),
) -> dict[str, str]:
    """The report files, ``<name>_report.html`` and/or ``<name>_report.md``, as text.

    Parameters
    ----------
    derivation : Derivation
        What to report.
    kernels : KernelSet
        The lowered kernels (for operation counts).
    results : mapping of str to bytes, optional
        Simulation outputs found beside the report (certificate and PNG figures).
    formats : sequence of str
        ``"html"``, ``"md"`` or both.
    """
    sections = report_sections(derivation, kernels, results)
    context = {
        "d": derivation,
        "spec": derivation.spec,
        "sections": sections,
        "tool_version": __version__,
        "engine": sx.engine_version(),
    }
    return {
        f"{derivation.spec.name}_report.{fmt}": render_template(FORMATS[fmt], context)
        for fmt in formats
    }
