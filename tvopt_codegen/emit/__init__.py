"""Stage 6: write output files. The only package of tvopt-codegen that writes.

Three modules, one concept each, so that the writer loads only what writing needs:

- :mod:`~tvopt_codegen.emit.transaction`: atomic, journaled publication of a set of
  files (:func:`write_files`) or of one file too large for memory
  (:func:`write_stream`), crash recovery (:func:`recover`), the manifest, and the rule
  that nothing a user wrote is replaced (read from each file's stamp).
- :mod:`~tvopt_codegen.emit.caches`: the cache folder, the compiled-library cache
  (:func:`cached_library`) and jinja's compiled templates (:func:`template_cache`); the
  only module here that imports jinja2 or runs a compiler.
- :mod:`~tvopt_codegen.emit.streams`: the sweep's streamed outputs, its Zarr store
  (:class:`TrajectoryStore`) and its locked folder of parts (:class:`SweepFolder`),
  built on the transaction's primitives.

This module re-exports what the single ``emit.py`` exported, so that its importers did
not change. The caches' names are imported on first use: ``import tvopt_codegen.emit``
loads no jinja2 and no toolchain.
"""

from __future__ import annotations

import importlib

# tests/test_faults.py patches os's functions through ``emit.os``, as it did the module's.
import os as os
from typing import TYPE_CHECKING, Any

from tvopt_codegen.emit.streams import SweepFolder, TrajectoryStore
from tvopt_codegen.emit.transaction import (
    JOURNAL_PREFIX,
    MANIFEST,
    Content,
    check_replaceable,
    prepare_folder,
    read_own_output,
    read_regular_file,
    recover,
    write_files,
    write_stream,
)
from tvopt_codegen.errors import OutputError

if TYPE_CHECKING:
    from tvopt_codegen.emit.caches import cache_folder, cached_library, template_cache

#: The names :mod:`~tvopt_codegen.emit.caches` defines, imported on first use.
_CACHES = frozenset({"cache_folder", "cached_library", "template_cache"})

__all__ = [
    "JOURNAL_PREFIX",
    "MANIFEST",
    "Content",
    "OutputError",
    "SweepFolder",
    "TrajectoryStore",
    "cache_folder",
    "cached_library",
    "check_replaceable",
    "prepare_folder",
    "read_own_output",
    "read_regular_file",
    "recover",
    "template_cache",
    "write_files",
    "write_stream",
]


def __getattr__(name: str) -> Any:
    """The cache function ``name``, its module imported on first use."""
    if name in _CACHES:
        return getattr(importlib.import_module("tvopt_codegen.emit.caches"), name)
    raise AttributeError(f"module 'tvopt_codegen.emit' has no attribute {name!r}")
