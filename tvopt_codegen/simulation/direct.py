"""The kernels behind a generated Python module's public functions, for checked loops.

Every public function of a generated module (``rhs``, ``control``,
``optimality_error``, ``plant``, ...) checks its arguments on every call (types,
shapes, finite values, the parameter mapping) and enters ``numpy.errstate``: for a
small spec that is most of a call's cost, and a run calls them tens of thousands of
times with arrays it made itself. The loops here (the closed loop on the reference
samples' grid, the sampled-data plant, the certificate's evaluations along a run)
call the kernels behind those functions instead: the same functions on the same
numbers, so the same bits. Wherever a kernel declines (its ``None``: a value that is
not finite, a singular pivot) or raises a Python float's ``ArithmeticError``, the
caller asks the public function, which answers or raises exactly as documented; so
does any module that offers no such kernel (the C backend's, a hand-written one).

Call these under ``numpy.errstate(all="ignore")``, as the public functions call them.
"""

from __future__ import annotations

import math
import types
from collections.abc import Callable, Mapping
from typing import Any

import numpy as np

#: ``kernel(t, state, jets)``: the public function's one-point answer as a list of
#: floats (row after row), or None where the public function must answer. ``jets`` is
#: the reference jets flat, row after row, for a spec with references (else None).
PointKernel = Callable[[float, list[float], list[float] | None], list[float] | None]

#: ``kernel(t, x, u)``: ``plant(t, x, u)`` at one state, or None where ``plant`` must answer.
PlantKernel = Callable[[float, np.ndarray, np.ndarray], np.ndarray | None]


def _finite(values: list[float]) -> bool:
    """Whether every value is finite (the generated module's own test).

    A sum of finite values that overflows is not finite: then each is looked at.
    """
    return math.isfinite(sum(values)) or all(map(math.isfinite, values))


def _python_module(controller: types.ModuleType) -> bool:
    """Whether ``controller`` is a generated Python module (whose kernels are known)."""
    return getattr(controller, "BACKEND", None) == "python"


def _behind(controller: types.ModuleType, name: str, kernel: Any) -> bool:
    """Whether ``controller.<name>`` is the module's own function over ``kernel``.

    A module whose public function was replaced (a test's fake, a user's wrapper that
    counts calls) keeps the replacement: it is then what a loop must call.
    """
    public = getattr(controller, name, None)
    return (
        getattr(public, "__name__", None) == name
        and getattr(public, "__module__", None) == getattr(kernel, "__module__", 0)
        and getattr(public, "__globals__", None) is getattr(kernel, "__globals__", 0)
    )


def _parameters(controller: types.ModuleType, params: Mapping[str, float] | None) -> Any:
    """The module's parameter vector for ``params``, checked by the module itself."""
    if params is None:
        return getattr(controller, "_DEFAULT_P", None)
    reader = getattr(controller, "_parameters", None)
    return None if reader is None else reader(params)


def point_kernel(
    controller: types.ModuleType, name: str, params: Mapping[str, float] | None
) -> PointKernel | None:
    """The one-point kernel behind the public function ``name``, or None if none is known.

    It answers exactly when the public function takes its own one-point path: a time,
    state and jets all finite, a kernel that neither declines nor raises, a finite
    result; then the public function returns these numbers as an array.

    Parameters
    ----------
    controller : module
        A generated module.
    name : str
        ``"rhs"``, ``"control"``, ``"optimality_error"``, ``"objective"``, ``"gradient"``
        or ``"hessian"``.
    params : mapping or None
        Parameter overrides, as the public function would be given them (None: the
        defaults). Checked here once, by the module: a mapping it refuses gives None.
    """
    if not _python_module(controller):
        return None
    table = getattr(controller, "_ONE_POINT", None)
    entry = table.get(name) if isinstance(table, dict) else None
    if entry is None:
        return None
    kernel: Callable[..., Any] = entry[0]
    if not _behind(controller, name, kernel):
        return None
    # The sizes the public function checks (a state, or a point of the outputs), and
    # whether the kernel takes the reference jets (a spec with references).
    names = "OUTPUT_NAMES" if name in ("objective", "gradient", "hessian") else "STATE_NAMES"
    rows = len(getattr(controller, names, ()))
    references = len(getattr(controller, "REFERENCE_NAMES", ()))
    jet_size = references * (int(getattr(controller, "REFERENCE_ORDER", 0)) + 1)
    try:
        vector = _parameters(controller, params)
    except (TypeError, ValueError):  # the public function says so, in its words
        return None
    if vector is None:
        return None
    p: list[float] = np.asarray(vector, dtype=float).tolist()
    if not _finite(p):
        return None

    def evaluate(t: float, state: list[float], jets: list[float] | None) -> list[float] | None:
        if not (len(state) == rows and math.isfinite(t) and _finite(state)):
            return None
        try:
            if jets is None and not references:
                result = kernel(t, state, p)
            elif jets is not None and len(jets) == jet_size and _finite(jets):
                result = kernel(t, state, p, jets)
            else:
                return None
        except ArithmeticError:  # a float's ZeroDivisionError or OverflowError
            return None
        if result is None or not _finite(result):
            return None
        values: list[float] = result
        return values

    return evaluate


def point_function(
    controller: types.ModuleType, name: str, params: Mapping[str, float] | None
) -> Callable[..., Any]:
    """``controller.<name>`` at one point with ``params`` bound: ``f(t, point, refs=None)``.

    What the public function returns for a one-dimensional float array ``point`` (and
    ``refs`` of the jets' shape), by its kernel where it answers (:func:`point_kernel`),
    else by the public function itself, which answers or raises as documented.
    """
    public: Callable[..., Any] = getattr(controller, name)
    kernel = point_kernel(controller, name, params)

    def by_public(t: float, point: np.ndarray, refs: np.ndarray | None = None) -> Any:
        return public(t, point, params) if refs is None else public(t, point, params, refs=refs)

    if kernel is None:
        return by_public
    shape = tuple(controller._ONE_POINT[name][1])
    jet_shape = (
        len(getattr(controller, "REFERENCE_NAMES", ())),
        int(getattr(controller, "REFERENCE_ORDER", 0)) + 1,
    )

    def evaluate(t: float, point: np.ndarray, refs: np.ndarray | None = None) -> Any:
        if (
            type(point) is np.ndarray
            and point.ndim == 1
            and point.dtype == np.float64
            and isinstance(t, float | int)
            and (
                refs is None
                or (
                    type(refs) is np.ndarray
                    and refs.dtype == np.float64
                    and refs.shape == jet_shape
                )
            )
        ):
            jets = None if refs is None else refs.ravel().tolist()
            values = kernel(float(t), point.tolist(), jets)
            if values is not None:
                if not shape:
                    return float(values[0])
                answer = np.array(values)
                return answer if len(shape) == 1 else answer.reshape(shape)
        return by_public(t, point, refs)

    return evaluate


def plant_kernel(
    controller: types.ModuleType, params: Mapping[str, float] | None
) -> PlantKernel | None:
    """The array kernel behind ``plant``, at one state, or None if none is known.

    It answers exactly when ``plant(t, x, u, params)`` returns: a finite time, state,
    input and field (``x`` and ``u`` one-dimensional float arrays of the right sizes).
    """
    if not _python_module(controller):
        return None
    kernel: Callable[..., Any] | None = getattr(controller, "_plant", None)
    names = getattr(controller, "PLANT_STATE_NAMES", None)
    inputs = getattr(controller, "INPUT_NAMES", None)
    if kernel is None or names is None or inputs is None:
        return None
    if not _behind(controller, "plant", kernel):
        return None
    try:
        p = _parameters(controller, params)
    except (TypeError, ValueError):
        return None
    if p is None or not np.all(np.isfinite(p)):
        return None
    rows, columns, real = (len(names),), (len(inputs),), np.dtype(np.float64)

    def evaluate(t: float, x: np.ndarray, u: np.ndarray) -> np.ndarray | None:
        if x.shape != rows or u.shape != columns or x.dtype != real or u.dtype != real:
            return None
        # x.dot(x) is finite only if every entry is (an overflow only sends the call on).
        if not (math.isfinite(t) and math.isfinite(x.dot(x)) and math.isfinite(u.dot(u))):
            return None
        column: np.ndarray = kernel(t, x[:, None], u[:, None], p)[:, 0]
        if not math.isfinite(column.dot(column)):
            return None
        return column

    return evaluate


def plant_function(
    controller: types.ModuleType, params: Mapping[str, float] | None
) -> Callable[[float, np.ndarray, np.ndarray], np.ndarray]:
    """``controller.plant`` with ``params`` bound: ``f(t, x, u)``.

    By its kernel where it answers (:func:`plant_kernel`), else by the public function,
    which answers or raises as documented: the same numbers either way.
    """
    kernel = plant_kernel(controller, params)

    def plant(t: float, x: np.ndarray, u: np.ndarray) -> np.ndarray:
        if kernel is not None:
            dx = kernel(t, x, u)
            if dx is not None:
                return dx
        return np.asarray(controller.plant(t, x, u, params), dtype=float)

    return plant
