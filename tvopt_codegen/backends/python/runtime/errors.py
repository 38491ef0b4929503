"""The base of every exception a generated controller raises.

The subclasses, one per error status (``NonFiniteInputError``, ...), are written by the
template from :class:`tvopt_codegen.contract.Status`.
"""

from __future__ import annotations

# --- copied verbatim into the generated controller below this line ---


class ControllerError(ArithmeticError):
    """The control law is undefined at the given time and state.

    Attributes
    ----------
    status : int
        The matching status code of the C backend (``STATUS_*``).
    index : int or None
        The column of a 2-D state at which the problem occurred.
    """

    status = -1

    def __init__(self, message: str, index: int | None = None) -> None:
        super().__init__(message)
        self.index = index
