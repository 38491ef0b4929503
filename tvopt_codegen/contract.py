"""The generated controller's contract, as data: its statuses and its public functions.

Every artifact that names a status or a public function is generated from the two
tables here: the Python module's ``STATUS_*`` constants, exception classes and messages,
the C header's status macros, prototypes and ``<name>_status_message``, the C module's
Python wrapper, its CPython entry point, the FMU's log text and the sweep's outcomes.
Adding a status is one line of :class:`Status`; adding a public function is one row of
:data:`FUNCTIONS` (and the kernel or law that computes it).

Nothing here imports another module of the package: every stage may read the contract.
"""

from __future__ import annotations

import enum
from collections.abc import Mapping
from dataclasses import dataclass

#: A pivot not above this fraction of the largest entry of its matrix makes the matrix
#: singular (R) or not positive definite (the Hessian).
PIVOT_TOLERANCE = 1e-12


class Status(enum.IntEnum):
    """The outcome of one evaluation: a C function's return, a Python exception's status.

    Each member carries, beside its value, the facts every artifact prints:

    kind : str
        ``ok``, ``error`` (the evaluation failed and produced nothing) or ``flag`` (it
        produced a result, with something worth reporting).
    exception : str
        The Python exception class raised for it ("" for ``OK``); a subclass of
        ``ControllerError`` (an ``ArithmeticError``), and of ``ValueError`` too where
        the caller, not the law, is at fault.
    doc : str
        The exception's docstring.
    text : str
        What happened, as a clause: the head of every message. ``{result}`` stands for
        what is not finite (``the plant input``, ...).
    explain : str
        Why, after a colon in the Python messages ("" for none).
    """

    kind: str
    exception: str
    doc: str
    text: str
    explain: str

    def __new__(
        cls, value: int, kind: str, exception: str, doc: str, text: str, explain: str = ""
    ) -> Status:
        """A member from its line of the table (value first)."""
        member = int.__new__(cls, value)
        member._value_ = value
        member.kind = kind
        member.exception = exception
        member.doc = doc
        member.text = text
        member.explain = explain
        return member

    # One line per status: value, kind, exception, docstring, message, explanation.
    # fmt: off
    OK = 0, "ok", "", "", "no error"
    NONFINITE_INPUT = 1, "error", "NonFiniteInputError", "``t``, the state or a parameter is NaN or infinite.", "time, a plant state or a parameter is not finite"  # noqa: E501
    SINGULAR_DECOUPLING = 2, "error", "SingularDecouplingError", "The decoupling matrix R is singular: the law cannot steer the outputs here.", "the decoupling matrix R is singular"  # noqa: E501
    HESSIAN_NOT_PD = 3, "error", "HessianNotPositiveDefiniteError", "The Hessian of f0 is not positive definite: f0 is not strongly convex here.", "the Hessian of f0 is not positive definite", "f0 is not strongly convex at this output and time"  # noqa: E501
    NONFINITE_OUTPUT = 4, "error", "NonFiniteOutputError", "An intermediate or the result is not finite (a function left its domain).", "{result} is not finite", "a signal or f0 left its domain"  # noqa: E501
    DECREASING_TIME = 5, "error", "DecreasingTimeError", "A stateful controller was stepped to a time before its last step's.", "the time is before the last step's time"  # noqa: E501
    DEPENDENT_CONSTRAINTS = 6, "error", "DependentConstraintsError", "The equality constraints' gradients are dependent: the KKT matrix is singular.", "the equality constraints' gradients are dependent", "the KKT matrix is singular at this state and time"  # noqa: E501
    MASS_MATRIX_NOT_PD = 7, "error", "MassMatrixNotPositiveDefiniteError", "The mass matrix M(q) is not positive definite: its factorization failed.", "the mass matrix M(q) is not positive definite", "the plant's model has no valid inertia at this state"  # noqa: E501
    OUTSIDE_BARRIER = 8, "error", "OutsideBarrierError", "The outputs are past an inequality constraint's barrier, where the barrier objective is undefined.", "the outputs are past an inequality constraint's barrier", "a margin s(t) - g_i(y, t) is not positive"  # noqa: E501
    # fmt: on

    @classmethod
    def of(cls, value: int) -> Status:
        """The status whose value is ``value`` (``ValueError`` for none)."""
        for status in statuses():
            if status == value:
                return status
        raise ValueError(f"{value} is not a status of the contract")

    @property
    def label(self) -> str:
        """The name in tables and records: ``ok``, ``singular_decoupling``, ..."""
        return self.name.lower()

    def message(self, result: str = "a result of the law", detail: str = "") -> str:
        """The one-line message of the compiled code and the FMU (no column).

        Parameters
        ----------
        result : str
            What is not finite, for ``{result}`` in :attr:`text`.
        detail : str
            A spec's own words on where this happens ("" for none).
        """
        head = self.text.replace("{result}", result)
        return (
            head
            + (f": {self.explain}" if self.explain else "")
            + (f" ({detail})" if detail else "")
        )


#: The exception classes whose caller, not the law, is at fault: also a ``ValueError``.
CALLER_FAULTS = frozenset({"DECREASING_TIME"})


def statuses() -> tuple[Status, ...]:
    """Every status, by value: what the templates and the sweep loop over.

    Read at render time from :class:`Status` as this module holds it, so that a test can
    put a wider table in its place and find the new status in every artifact.
    """
    return tuple(sorted(Status, key=int))


@dataclass(frozen=True)
class Function:
    """A public function of every generated controller.

    Attributes
    ----------
    name : str
        Its name in Python and, after the module prefix, in C.
    argument : str
        What its array arguments are: ``state`` (the closed-loop state ``s``), ``output``
        (the outputs ``y``), ``plant`` (the plant state ``x``) or ``plant_input`` (``x``
        and the plant input ``u``).
    result : str
        What it computes, in messages ("the plant input is not finite").
    shape : tuple of str
        Its result's shape at one point, in the sizes of :func:`sizes` (``()``: a number).
    kernel : str
        The kernel that computes it (``k_<kernel>`` in C); "" for the two functions the
        law's plan evaluates (``control``, ``rhs``).
    batch : bool
        Whether it has a batched form over many points (and takes reference jets).
    doc : str
        The summary, for the header and the docstrings.
    returns : str
        What it returns, for the docstrings.
    """

    name: str
    argument: str
    result: str
    shape: tuple[str, ...]
    kernel: str
    batch: bool
    doc: str
    returns: str

    def size(self, sizes: Mapping[str, int]) -> int:
        """The number of doubles of one result."""
        count = 1
        for name in self.shape:
            count *= sizes[name]
        return count

    def dims(self, sizes: Mapping[str, int]) -> tuple[int, ...]:
        """The result's shape at one point, in numbers."""
        return tuple(sizes[name] for name in self.shape)

    def c_size(self, guard: str) -> str:
        """The number of doubles of one result, as a C expression of the header's macros."""
        return " * ".join(f"{guard}_{C_SIZES[name]}" for name in self.shape) or "1"

    def c_dims(self, guard: str) -> tuple[str, str]:
        """The result's shape at one point in C macros, padded to two with 1."""
        dims = [f"{guard}_{C_SIZES[name]}" for name in self.shape] + ["1", "1"]
        return dims[0], dims[1]

    def c_width(self, guard: str) -> str:
        """The number of doubles of its (first) array argument at one point, in C."""
        return f"{guard}_{C_WIDTHS[self.argument]}"

    @property
    def c_arguments(self) -> tuple[str, ...]:
        """The names of its array arguments in C (before ``params``)."""
        return C_ARGUMENTS[self.argument]


#: The public functions, in the order of the CPython entry point's ``kind``: name,
#: argument, what it computes, shape, kernel, batch form, summary, what it returns.
# fmt: off
FUNCTIONS = (
    Function("control", "state", "the plant input", ("n_inputs",), "", True, "Plant input u of the implicit trajectory planning law.", "Plant input in ``INPUT_NAMES`` order."),  # noqa: E501
    Function("rhs", "state", "the closed-loop vector field", ("n_states",), "", True, "Time derivative of the closed-loop state, for ``scipy.integrate.solve_ivp``.", "``ds/dt``: plant and extension dynamics under the law, and the padding chains."),  # noqa: E501
    Function("optimality_error", "state", "the optimality error", ("k", "n_kkt"), "optimality", True, "The optimality error: row j is grad^(j) f0 along the closed loop.", "``E``; under the law ``dE/dt = H E`` (with equality constraints, row j is the j-th derivative of the KKT map ``F = [grad f0 + J_a^T nu; a]``, outputs then multipliers)."),  # noqa: E501
    Function("objective", "output", "f0", (), "objective", True, "The objective f0(y, t).", "f0 at each point."),  # noqa: E501
    Function("gradient", "output", "the gradient of f0", ("n_outputs",), "gradient", True, "The gradient of f0 with respect to y.", "``grad_y f0``."),  # noqa: E501
    Function("hessian", "output", "the Hessian of f0", ("n_outputs", "n_outputs"), "hessian", True, "The Hessian of f0 with respect to y.", "``grad_yy f0``."),  # noqa: E501
    Function("plant", "plant_input", "the plant's vector field", ("n_plant_states",), "plant", False, "The plant alone, ``x' = f(x) + G(x) u``: the spec's model, without the controller.", "``dx/dt``: the true plant of a sampled-data loop and of :func:`tvopt_codegen.interop.plant_nlsys`."),  # noqa: E501
    Function("outputs", "plant", "the outputs", ("n_outputs",), "outputs", False, "The outputs ``y = h(x)`` of the plant state.", "``y`` in ``OUTPUT_NAMES`` order."),  # noqa: E501
)
# fmt: on

#: The C name of each kind of argument (:attr:`Function.argument`).
C_ARGUMENTS = {
    "state": ("s",),
    "output": ("y",),
    "plant": ("x",),
    "plant_input": ("x", "u"),
}

#: The C size macro (after the prefix) of the first array argument of each kind.
C_WIDTHS = {
    "state": "N_STATES",
    "output": "N_OUTPUTS",
    "plant": "N_PLANT_STATES",
    "plant_input": "N_PLANT_STATES",
}

#: The C size macro (after the prefix) of each size name.
C_SIZES = {
    "n_inputs": "N_INPUTS",
    "n_states": "N_STATES",
    "n_outputs": "N_OUTPUTS",
    "n_plant_states": "N_PLANT_STATES",
    "n_kkt": "N_KKT",
    "k": "K",
}


def function(name: str) -> Function:
    """The row of :data:`FUNCTIONS` called ``name``."""
    for row in FUNCTIONS:
        if row.name == name:
            return row
    raise KeyError(name)
