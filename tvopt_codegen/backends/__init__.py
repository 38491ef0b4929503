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
import importlib.machinery
import os
import pkgutil
import sys
from collections.abc import Iterator
from typing import TYPE_CHECKING, Any

from tvopt_codegen.backends.base import Backend

if TYPE_CHECKING:
    from _collections_abc import dict_items, dict_keys, dict_values


class _Registry(dict[str, Backend]):
    """A dict of backends that finds them (:func:`_discover`) when first read.

    Finding them imports ``importlib.metadata`` and scans every installed package's entry
    points (0.03 s of CPU); ``--help``, ``--version``, ``examples`` and the parser of a
    command read no backend, so a cold command pays it only where a backend is looked up.
    """

    found = False

    def _find(self) -> None:
        if not self.found:
            self.found = True  # first: discovery registers, and registering reads
            try:
                _discover()
            except BaseException:
                self.found = False  # a broken plug-in fails every look-up, as it failed the import
                raise

    def __getitem__(self, name: str) -> Backend:
        self._find()
        return super().__getitem__(name)

    def __contains__(self, name: object) -> bool:
        self._find()
        return super().__contains__(name)

    def __iter__(self) -> Iterator[str]:
        self._find()
        return super().__iter__()

    def __len__(self) -> int:
        self._find()
        return super().__len__()

    def __repr__(self) -> str:
        self._find()
        return super().__repr__()

    def get(self, name: str, default: Any = None) -> Any:
        """``dict.get``, once the backends are found."""
        self._find()
        return super().get(name, default)

    def keys(self) -> dict_keys[str, Backend]:
        """``dict.keys``, once the backends are found."""
        self._find()
        return super().keys()

    def values(self) -> dict_values[str, Backend]:
        """``dict.values``, once the backends are found."""
        self._find()
        return super().values()

    def items(self) -> dict_items[str, Backend]:
        """``dict.items``, once the backends are found."""
        self._find()
        return super().items()

    def copy(self) -> dict[str, Backend]:
        """``dict.copy`` (a plain dict), once the backends are found."""
        self._find()
        return dict(super().items())


#: Backends by the name users give on the command line.
BACKENDS: dict[str, Backend] = _Registry()

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
    if not _maybe_declared():
        return
    from importlib import metadata  # noqa: PLC0415 - 0.03 s: only where a package may declare one

    for point in sorted(metadata.entry_points(group=ENTRY_POINT_GROUP), key=lambda e: e.name):
        backend = point.load()
        if isinstance(backend, Backend):
            register(backend)


def _maybe_declared() -> bool:
    """Whether an installed package may declare an entry point of :data:`ENTRY_POINT_GROUP`.

    False only when none can: the path finder is the only finder of distributions and
    no ``entry_points.txt`` of the metadata folders it reads (``*.dist-info``,
    ``*.egg-info`` in each folder of ``sys.path``) names the group. Listing them takes a
    millisecond; ``importlib.metadata`` takes 0.03 s to import, which every ``generate``
    paid (the spec's names are checked against every backend's reserved words).
    """
    finders = [f for f in sys.meta_path if hasattr(f, "find_distributions")]
    if len(finders) != 1 or not (
        finders[0] is importlib.machinery.PathFinder or _backport_path_finder(finders[0])
    ):
        return True  # another finder's distributions: importlib.metadata asks it
    group = ENTRY_POINT_GROUP.encode()
    for entry in sys.path:
        folder = entry or "."
        if not os.path.isdir(folder):
            if os.path.exists(folder):
                return True  # a zip file on the path: importlib.metadata reads inside it
            continue
        try:
            names = os.listdir(folder)
        except OSError:
            return True
        for name in names:
            if name.lower().endswith(("dist-info", "egg-info")):
                try:
                    with open(os.path.join(folder, name, "entry_points.txt"), "rb") as file:
                        if group in file.read():
                            return True
                except (FileNotFoundError, NotADirectoryError):
                    continue
                except OSError:
                    return True
    return False


def _backport_path_finder(finder: object) -> bool:
    """Whether ``finder`` is the importlib_metadata backport's path finder.

    Imported (by a library that supports older Pythons), the backport takes the path
    finder's ``find_distributions`` away and finds distributions itself, in the same
    metadata folders of ``sys.path``.
    """
    kind = type(finder)
    return kind.__name__ == "MetadataPathFinder" and kind.__module__ == "importlib_metadata"


__all__ = ["BACKENDS", "ENTRY_POINT_GROUP", "Backend", "register"]
