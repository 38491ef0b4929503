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
"""

from __future__ import annotations

from collections.abc import Mapping
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
        parameters by name.
    """
    control = _control()
    plant_states = len(module.PLANT_STATE_NAMES)

    def update(t: float, z: np.ndarray, x: np.ndarray, params: Any) -> np.ndarray:
        ds = module.rhs(t, np.concatenate([x, z]), _own(module, params))
        return np.asarray(ds)[plant_states:]

    def output(t: float, z: np.ndarray, x: np.ndarray, params: Any) -> np.ndarray:
        return np.asarray(module.control(t, np.concatenate([x, z]), _own(module, params)))

    states = list(module.CONTROLLER_STATE_NAMES)
    # A controller without states is static: python-control wants no update function.
    dynamic = {"states": states} if states else {}
    return control.nlsys(
        update if states else None,
        output,
        inputs=list(module.PLANT_STATE_NAMES),
        outputs=list(module.INPUT_NAMES),
        params=dict(module.PARAMETERS),
        name=name,
        **dynamic,
    )


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
