"""An error status as the exception a generated controller raises."""

from __future__ import annotations

from tvopt_codegen.backends.python.runtime.errors import ControllerError
from tvopt_codegen.backends.python.runtime.provided import _ERRORS

# --- copied verbatim into the generated controller below this line ---


def _error(status: int, index: int, result: str = "") -> ControllerError:
    """The exception of ``status`` at column ``index`` (``result``: what is not finite)."""
    kind, text, tail = _ERRORS[status]
    return kind(f"{text.replace('{result}', result)} (column {index}){tail}", index)
