"""tvopt-codegen: implicit trajectory planning controllers from a spec file.

The pipeline (see ``ARCHITECTURE.md``): :func:`load_spec` -> :func:`derive` ->
:func:`lower` -> :func:`render` -> :func:`write_files`.
"""

from __future__ import annotations

__version__ = "0.1.0"

__all__ = ["__version__"]
