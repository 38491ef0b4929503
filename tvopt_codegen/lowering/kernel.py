"""The IR's types: kernels (named straight-line programs) and a controller's set of them.

A kernel is a named straight-line program: ordered inputs (arrays addressed by slot),
CSE'd temporaries, and named outputs of fixed shape. Kernels hold the symbolic engine's
expressions only (:mod:`tvopt_codegen.symbolic`, either engine); printing them is the
backends' job, laying out files the templates'.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

from tvopt_codegen import symbolic as sx
from tvopt_codegen.maths.jet import Assignment

if TYPE_CHECKING:
    from tvopt_codegen.derivation import Derivation
    from tvopt_codegen.lowering.plan import Plan


@dataclass(frozen=True)
class Arg:
    """One array input of a kernel.

    Attributes
    ----------
    name : str
        The argument's name in generated code (``t``, ``s``, ``p``, ...).
    symbols : tuple of Symbol
        The slot symbols, one per element, in order (empty for the scalar ``t``).
    labels : tuple of str
        The user's name for each slot (for comments).
    doc : str
        What the argument is.
    """

    name: str
    symbols: tuple[sx.Expr, ...]
    labels: tuple[str, ...]
    doc: str


@dataclass(frozen=True)
class Output:
    """One output array of a kernel: ``shape`` and the row-major element expressions."""

    name: str
    shape: tuple[int, ...]
    exprs: tuple[sx.Expr, ...]
    doc: str


@dataclass(frozen=True)
class Kernel:
    """A named straight-line program over array inputs.

    Attributes
    ----------
    name : str
        Function name in generated code.
    doc : str
        One-line description.
    inputs : tuple of Arg
        Inputs in call order.
    body : tuple of (Symbol, Expr)
        Temporaries ``_t0, _t1, ...`` in evaluation order.
    outputs : tuple of Output
        Outputs in return order.
    ops : int
        Operation count of the body and outputs (after CSE).
    ops_before_cse : int
        Operation count of the same program before CSE.
    """

    name: str
    doc: str
    inputs: tuple[Arg, ...]
    body: tuple[Assignment, ...]
    outputs: tuple[Output, ...]
    ops: int
    ops_before_cse: int


@dataclass(frozen=True)
class KernelSet:
    """All kernels of one controller, with the derivation they came from.

    Attributes
    ----------
    derivation : Derivation
        The derived law.
    kernels : tuple of Kernel
        The kernels, see :func:`~tvopt_codegen.lowering.ir.lower`.
    plan : Plan
        The order of kernel calls, solves and checks that evaluates the law.
    r_blocks : tuple of tuple of int
        The diagonal blocks of R (output indices of each, in order). The ``R`` output
        of the ``jet`` kernel holds each block's entries row by row, block after block;
        a block-diagonal R (one block per agent) is solved block by block.
    lu_ops : int
        Operations of the LU solves of those blocks (with pivoting), counted like
        kernel operations.
    """

    derivation: Derivation
    kernels: tuple[Kernel, ...]
    plan: Plan
    r_blocks: tuple[tuple[int, ...], ...] = ()
    lu_ops: int = 0

    def __getitem__(self, name: str) -> Kernel:
        for kernel in self.kernels:
            if kernel.name == name:
                return kernel
        raise KeyError(name)
