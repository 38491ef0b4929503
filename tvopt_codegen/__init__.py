"""tvopt-codegen: implicit trajectory planning controllers from a spec file.

The pipeline (``docs/architecture.md``), each stage a function of this package::

    load_spec or spec_from_dict -> derive -> lower -> render -> write_files
                                          lower -> load_controller -> simulate

``docs/api.md`` shows a complete example. The stages are imported on first use:
``import tvopt_codegen`` itself loads no sympy or numpy.
"""

from __future__ import annotations

import importlib
from typing import Any

__version__ = "0.1.0"

#: Each public name and the module that defines it.
_STAGES = {
    "load_spec": "tvopt_codegen.spec",
    "spec_from_dict": "tvopt_codegen.spec",
    "spec_from_sympy": "tvopt_codegen.mechanics",
    "spec_toml": "tvopt_codegen.mechanics",
    "spec_from_urdf": "tvopt_codegen.urdf",
    "Spec": "tvopt_codegen.spec",
    "build_model": "tvopt_codegen.derivation.model",
    "Model": "tvopt_codegen.derivation.model",
    "derive": "tvopt_codegen.derivation",
    "Derivation": "tvopt_codegen.derivation",
    "Budget": "tvopt_codegen.limits",
    "lower": "tvopt_codegen.lowering.ir",
    "KernelSet": "tvopt_codegen.lowering.ir",
    "render": "tvopt_codegen.renderer.rendering",
    "write_files": "tvopt_codegen.emit",
    "load_controller": "tvopt_codegen.simulation",
    "resolve_options": "tvopt_codegen.simulation",
    "simulate": "tvopt_codegen.simulation",
    "render_report": "tvopt_codegen.report",
    "BACKENDS": "tvopt_codegen.backends",
    "TvoptError": "tvopt_codegen.errors",
}

__all__ = [
    "__version__",
    "load_spec",
    "spec_from_dict",
    "spec_from_sympy",
    "spec_toml",
    "spec_from_urdf",
    "Spec",
    "build_model",
    "Model",
    "derive",
    "Derivation",
    "Budget",
    "lower",
    "KernelSet",
    "render",
    "write_files",
    "load_controller",
    "resolve_options",
    "simulate",
    "render_report",
    "BACKENDS",
    "TvoptError",
]


def __getattr__(name: str) -> Any:
    """The stage ``name``, imported on first use."""
    if name in _STAGES:
        return getattr(importlib.import_module(_STAGES[name]), name)
    raise AttributeError(f"module 'tvopt_codegen' has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted(__all__)
