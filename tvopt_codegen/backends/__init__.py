"""Code-generation backends: one plug-in per target language.

A backend is a :class:`~tvopt_codegen.backends.base.Backend`: a printer for
expressions and the templates it renders. Adding a backend adds an entry to
:data:`BACKENDS`; the derivation and the IR never change.
"""

from __future__ import annotations

from tvopt_codegen.backends.base import Backend
from tvopt_codegen.backends.c import C
from tvopt_codegen.backends.python import PYTHON

#: Backends by the name users give on the command line.
BACKENDS: dict[str, Backend] = {backend.name: backend for backend in (PYTHON, C)}

__all__ = ["BACKENDS", "Backend"]
