"""Code-generation backends: one plug-in per target language.

A backend is a :class:`~tvopt_codegen.backends.base.Backend`: its printers, the templates
it renders and the files they become, its own template variables, the module users
import and the words its language reserves. The registry :data:`BACKENDS` is filled
without editing any shared module: by every module of this package that defines
``BACKEND``, by the entry points of the group ``tvopt_codegen.backends`` that other
packages declare, and by :func:`register`. See ``docs/backends.md``.
"""

from __future__ import annotations

import importlib
import importlib.metadata
import pkgutil

from tvopt_codegen.backends.base import Backend

#: Backends by the name users give on the command line.
BACKENDS: dict[str, Backend] = {}

#: The entry-point group through which other packages add backends.
ENTRY_POINT_GROUP = "tvopt_codegen.backends"


def register(backend: Backend) -> Backend:
    """Add ``backend`` to :data:`BACKENDS` (a name may be registered once).

    Raises
    ------
    ValueError
        When another backend already has that name.
    """
    known = BACKENDS.get(backend.name)
    if known is not None and known is not backend:
        raise ValueError(f"a backend named {backend.name!r} is registered already")
    BACKENDS[backend.name] = backend
    return backend


def _discover() -> None:
    for info in sorted(pkgutil.iter_modules(__path__), key=lambda i: i.name):
        if info.name != "base":
            module = importlib.import_module(f"{__name__}.{info.name}")
            if isinstance(getattr(module, "BACKEND", None), Backend):
                register(module.BACKEND)
    for point in sorted(
        importlib.metadata.entry_points(group=ENTRY_POINT_GROUP), key=lambda e: e.name
    ):
        backend = point.load()
        if isinstance(backend, Backend):
            register(backend)


_discover()

__all__ = ["BACKENDS", "ENTRY_POINT_GROUP", "Backend", "register"]
