"""The generated controller and its plant as python-control systems.

``to_nlsys(module)`` is the stateful controller as a ``control.NonlinearIOSystem``: its
states are the controller states ``z`` (``CONTROLLER_STATE_NAMES``), its inputs the
plant states (named ``PLANT_STATE_NAMES``), its outputs the plant input (named
``INPUT_NAMES``). ``plant_nlsys(module)`` is the spec's plant: states and inputs ``x`` and
``u``, outputs ``x`` (named like the states) and ``y`` (``OUTPUT_NAMES``). Signals share
names, so python-control connects the two with no connection list::

    import control
    closed = control.interconnect(
        [plant_nlsys(m), to_nlsys(m)], inplist=[], outlist=list(m.OUTPUT_NAMES)
    )
    response = control.input_output_response(closed, T, 0, X0=m.DEFAULT_STATE)

The interconnection's state is ``[x; z]``: ``STATE_NAMES`` order, so ``DEFAULT_STATE``
starts it where ``simulate`` does. python-control is an optional extra
(``pip install 'tvopt-codegen[control]'``).

A spec with ``[references]`` measures its references at run time: its controller system
has the inputs ``reference_<name>_d<j>`` too (derivative ``j = 0 .. REFERENCE_ORDER`` of
each reference; the FMU's ``reference.<name>.d<j>``, with ``_`` for the ``.`` that
python-control reserves for ``system.signal``), which the interconnection takes from
outside (its ``inplist``) or from a system that produces the jets.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from types import ModuleType
from typing import Any

import numpy as np

from tvopt_codegen.errors import MissingExtraError


def _control() -> Any:
    try:
        import control  # noqa: PLC0415 - optional, loaded on use
    except ImportError as exc:
        raise MissingExtraError(
            "python-control is not installed: pip install 'tvopt-codegen[control]'"
        ) from exc
    return control


def _own(module: ModuleType, params: Mapping[str, float] | None) -> dict[str, float] | None:
    """The parameters of ``module`` among ``params`` (an interconnection passes all)."""
    if not params:
        return None
    own = {key: value for key, value in params.items() if key in module.PARAMETERS}
    return own or None


def to_nlsys(module: ModuleType, name: str = "controller") -> Any:
    """The stateful controller of a generated module as a python-control system.

    Parameters
    ----------
    module : module
        A generated controller module (either backend).
    name : str, optional
        The system's name.

    Returns
    -------
    control.NonlinearIOSystem
        States ``z`` (``CONTROLLER_STATE_NAMES``), inputs the plant states
        (``PLANT_STATE_NAMES``), outputs the plant input (``INPUT_NAMES``); the module's
        parameters by name. A spec with ``[limits]`` or ``[robust]``: the output is the
        input applied (clipped to ``INPUT_LOW`` and ``INPUT_HIGH``), the integral states
        and a clipped prolonged input's chain stop while clipped (the continuous form of
        the Controller's anti-windup), and a disturbance observer adds the states
        ``observer.<plant state>`` of its continuous form (see :func:`_robust_nlsys`).
        Slew rates act in the sampled Controller alone. A spec with ``[references]``:
        the inputs ``reference_<name>_d<j>`` follow the plant states (see the module's
        docstring).
    """
    control = _control()
    if hasattr(module, "INPUT_LOW"):
        return _robust_nlsys(module, name, control)
    plant_states = len(module.PLANT_STATE_NAMES)

    def update(t: float, z: np.ndarray, inputs: np.ndarray, params: Any) -> np.ndarray:
        x, refs = _split_inputs(module, inputs)
        ds = module.rhs(t, np.concatenate([x, z]), _own(module, params), **refs)
        return np.asarray(ds)[plant_states:]

    def output(t: float, z: np.ndarray, inputs: np.ndarray, params: Any) -> np.ndarray:
        x, refs = _split_inputs(module, inputs)
        return np.asarray(module.control(t, np.concatenate([x, z]), _own(module, params), **refs))

    return _controller_system(
        control, module, name, list(module.CONTROLLER_STATE_NAMES), update, output
    )


def reference_inputs(module: ModuleType) -> list[str]:
    """The names of a module's reference-jet inputs, ``reference_<name>_d<j>`` (or none)."""
    order = getattr(module, "REFERENCE_ORDER", 0)
    return [
        f"reference_{name}_d{j}"
        for name in getattr(module, "REFERENCE_NAMES", ())
        for j in range(order + 1)
    ]


def _split_inputs(module: ModuleType, inputs: np.ndarray) -> tuple[np.ndarray, dict[str, Any]]:
    """A controller system's input vector as the plant state and the module's ``refs``."""
    nx = len(module.PLANT_STATE_NAMES)
    names = getattr(module, "REFERENCE_NAMES", ())
    if not names:
        return inputs, {}
    jets = np.asarray(inputs[nx:], dtype=float).reshape(len(names), module.REFERENCE_ORDER + 1)
    return inputs[:nx], {"refs": jets}


def _controller_system(
    control: Any,
    module: ModuleType,
    name: str,
    states: list[str],
    update: Callable[..., np.ndarray],
    output: Callable[..., np.ndarray],
) -> Any:
    """A controller's ``nlsys``: the plant states in, the plant input out.

    A controller without states is static: python-control wants no update function, and
    its interconnection evaluates a static system's output first with the inputs it has
    not computed yet, all zero (the first pass of its algebraic iteration). A law that is
    undefined there (the unicycle's at v = 0) answers that one pass with zeros, which the
    next pass, at the real plant state, replaces. NaN cannot serve: the interconnection
    multiplies every output by its connection matrix, and 0 * NaN poisons every input.
    A second all-zero call in a row is a real plant state of zero: the law's error is
    raised there, so no undefined law is ever answered with a number the loop keeps.
    """
    dynamic = {"states": states} if states else {}
    if not states:
        law = output
        stale = [False]  # the last call answered the first, stale pass

        def output(t: float, z: np.ndarray, inputs: np.ndarray, params: Any) -> np.ndarray:
            first_pass = not stale[0] and not np.any(np.asarray(inputs) != 0.0)
            stale[0] = False
            try:
                return law(t, z, inputs, params)
            except ArithmeticError:
                if not first_pass:
                    raise
                stale[0] = True
                return np.zeros(len(module.INPUT_NAMES))

    return control.nlsys(
        update if states else None,
        output,
        inputs=[*module.PLANT_STATE_NAMES, *reference_inputs(module)],
        outputs=list(module.INPUT_NAMES),
        params=dict(module.PARAMETERS),
        name=name,
        **dynamic,
    )


def _robust_nlsys(module: ModuleType, name: str, control: Any) -> Any:
    """:func:`to_nlsys` for a controller with limits, integral action or an observer.

    The observer's continuous form: ``psi' = beta (beta x - psi + f(x) + G(x) u)`` with
    ``u`` the applied input, so that ``sigma = beta x - psi`` obeys
    ``sigma' = beta (G d - sigma)``; ``d_hat`` is the least-squares solution of
    ``G(x) d = sigma`` (G's columns from ``plant``), and the law commands ``u - d_hat``.
    It starts at ``psi = beta x(0)`` (``sigma = 0``): give the interconnection that
    start for the observer's states.
    """
    nx, nu = len(module.PLANT_STATE_NAMES), len(module.INPUT_NAMES)
    nz = len(module.CONTROLLER_STATE_NAMES)
    low, high = np.array(module.INPUT_LOW), np.array(module.INPUT_HIGH)
    beta = module.OBSERVER_BANDWIDTH
    chains = module._CHAINS
    integral = [chains[c][0] for c in module._INTEGRAL_CHAINS]
    input_chains = module._INPUT_CHAINS

    def estimate(t: float, x: np.ndarray, psi: np.ndarray, p: Any) -> np.ndarray:
        if beta is None:
            return np.zeros(nu)
        base = np.asarray(module.plant(t, x, np.zeros(nu), p))
        columns = np.array(
            [np.asarray(module.plant(t, x, np.eye(nu)[i], p)) - base for i in range(nu)]
        ).T
        solution: np.ndarray = np.linalg.lstsq(columns, beta * x - psi, rcond=None)[0]
        return solution

    def split(t: float, w: np.ndarray, inputs: np.ndarray, params: Any) -> tuple[Any, ...]:
        p = _own(module, params)
        x, refs = _split_inputs(module, inputs)
        z, psi = w[:nz], w[nz:]
        s = np.concatenate([x, z])
        commanded = np.asarray(module.control(t, s, p, **refs)) - estimate(t, x, psi, p)
        return p, s, psi, commanded, np.clip(commanded, low, high), x, refs

    def update(t: float, w: np.ndarray, inputs: np.ndarray, params: Any) -> np.ndarray:
        p, s, psi, commanded, applied, x, refs = split(t, w, inputs, params)
        dz = np.array(module.rhs(t, s, p, **refs), dtype=float)[nx:]
        excess = commanded - applied
        if np.any(excess != 0.0):
            dz[integral] = 0.0
            for i, chain in enumerate(input_chains):
                if chain >= 0 and excess[i] != 0.0:
                    start, length = chains[chain]
                    block = dz[start : start + length]
                    block[block * excess[i] > 0.0] = 0.0
        if beta is None:
            return dz
        dpsi = beta * (beta * x - psi + np.asarray(module.plant(t, x, applied, p)))
        return np.concatenate([dz, dpsi])

    def output(t: float, w: np.ndarray, inputs: np.ndarray, params: Any) -> np.ndarray:
        return np.asarray(split(t, w, inputs, params)[4])

    states = list(module.CONTROLLER_STATE_NAMES)
    if beta is not None:
        states += [f"observer.{n}" for n in module.PLANT_STATE_NAMES]
    return _controller_system(control, module, name, states, update, output)


def plant_nlsys(module: ModuleType, name: str = "plant") -> Any:
    """The spec's plant of a generated module as a python-control system.

    Parameters
    ----------
    module : module
        A generated controller module (either backend).
    name : str, optional
        The system's name.

    Returns
    -------
    control.NonlinearIOSystem
        States ``x`` (``PLANT_STATE_NAMES``), inputs ``u`` (``INPUT_NAMES``), outputs the
        plant states (named like them) and then ``y`` (``OUTPUT_NAMES``).
    """
    control = _control()

    def update(t: float, x: np.ndarray, u: np.ndarray, params: Any) -> np.ndarray:
        return np.asarray(module.plant(t, x, u, _own(module, params)))

    def output(t: float, x: np.ndarray, u: np.ndarray, params: Any) -> np.ndarray:
        y = np.asarray(module.outputs(t, x, _own(module, params)))
        return np.concatenate([np.asarray(x, dtype=float), y])

    return control.nlsys(
        update,
        output,
        inputs=list(module.INPUT_NAMES),
        outputs=[*module.PLANT_STATE_NAMES, *module.OUTPUT_NAMES],
        states=list(module.PLANT_STATE_NAMES),
        params=dict(module.PARAMETERS),
        name=name,
    )
