"""Run-time numerics: the C library of routines the generated code uses, and their constants.

Every numerical routine a generated C file needs is one template macro in
``templates/c/runtime/``, listed here with the routines it calls. A translation unit
asks for a set of routines; :func:`closure` adds what they call and orders them so that
each comes after its callees, and each is emitted once (CasADi's ``add_auxiliary`` does
the same). The controller asks through its plan (``Plan.runtime``); the sweep's loop,
which includes the controller's C file, emits what it asks for beyond that.

The constants of Newton's method are one table, :data:`NEWTON`: the Python certificate
(:mod:`tvopt_codegen.simulation.target`) runs with them, and the sweep's C prints them.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass


@dataclass(frozen=True)
class NewtonRule:
    """Damped Newton on f0 (or on the KKT map ``|F|^2``) as both languages run it.

    Attributes
    ----------
    step_cap : float
        Longest step in the outputs (a step is scaled down to it).
    armijo : float
        Sufficient decrease: accept ``scale`` when the merit drops by ``armijo * scale``
        times the directional derivative.
    shrink : float
        Backtracking factor.
    smallest_scale : float
        Backtracking stops below this step fraction (the step is then taken as it is).
    stop : float
        Converged when a step is below ``stop * (1 + |y|)``.
    iterations : int
        Iterations from a warm start (a row's neighbour on the path).
    rounding : float
        f0's relative rounding: a decrease below ``rounding * |f0|`` is not resolved, and
        a path's jump takes such a last Newton step whole (see
        :func:`tvopt_codegen.simulation.target.minimizer_path`).
    """

    step_cap: float = 0.02
    armijo: float = 1e-4
    shrink: float = 0.5
    smallest_scale: float = 1e-8
    stop: float = 1e-14
    iterations: int = 200
    rounding: float = 16 * 2.0**-52


#: The one Newton rule of the certificate and the sweep.
NEWTON = NewtonRule()


@dataclass(frozen=True)
class Routine:
    """One routine of the C run-time library.

    Attributes
    ----------
    template : str
        The template that defines its macro (under ``templates/``).
    macro : str
        The macro that emits it.
    calls : tuple of str
        The routines it calls (emitted before it).
    """

    template: str
    macro: str
    calls: tuple[str, ...] = ()


#: The C run-time library, by routine name.
ROUTINES: dict[str, Routine] = {
    "rk45": Routine("c/runtime/rk45.jinja", "rk45"),
    "dot": Routine("c/runtime/linalg.jinja", "dot"),
    "lu": Routine("c/runtime/linalg.jinja", "lu"),
    "lu_det": Routine("c/runtime/linalg.jinja", "lu_det", ("lu",)),
    "eigen": Routine("c/runtime/linalg.jinja", "smallest_eigenvalue"),
    "newton": Routine("c/runtime/newton.jinja", "newton", ("lu_det", "dot")),
    "convexity": Routine("c/runtime/newton.jinja", "convexity", ("eigen",)),
    "minimizer_path": Routine("c/runtime/newton.jinja", "minimizer_path", ("newton", "convexity")),
    "kkt": Routine("c/runtime/kkt.jinja", "kkt", ("dot",)),
    "kkt_newton": Routine("c/runtime/kkt.jinja", "kkt_newton", ("kkt", "lu_det", "dot")),
    "kkt_convexity": Routine("c/runtime/kkt.jinja", "kkt_convexity", ("kkt", "eigen")),
    "kkt_path": Routine("c/runtime/kkt.jinja", "kkt_path", ("kkt_newton", "kkt_convexity")),
    "chain_advance": Routine("c/runtime/controller.jinja", "chain_advance"),
    "taylor_shift": Routine("c/runtime/controller.jinja", "taylor_shift"),
    "differentiator": Routine("c/runtime/controller.jinja", "differentiator", ("taylor_shift",)),
}


def controller_routines(references: bool) -> tuple[str, ...]:
    """The library routines every controller's C file emits (its plan's solves aside).

    The integrator chains' advance always; with references, the Taylor shift and the
    differentiator too. A translation unit that includes the controller has these.
    """
    return ("chain_advance", *(("taylor_shift", "differentiator") if references else ()))


def closure(requested: Iterable[str], emitted: Iterable[str] = ()) -> tuple[Routine, ...]:
    """The routines to emit for ``requested``: with what they call, callees first, once.

    Parameters
    ----------
    requested : iterable of str
        Names in :data:`ROUTINES`.
    emitted : iterable of str, optional
        Routines the translation unit has already (left out).

    Returns
    -------
    tuple of Routine
        In an order in which every routine follows the ones it calls.

    Raises
    ------
    KeyError
        For a name that is not a routine of the library.
    """
    done = set(emitted)
    order: list[Routine] = []

    def visit(name: str) -> None:
        if name in done:
            return
        done.add(name)
        routine = ROUTINES[name]
        for callee in routine.calls:
            visit(callee)
        order.append(routine)

    for name in requested:
        visit(name)
    return tuple(order)
