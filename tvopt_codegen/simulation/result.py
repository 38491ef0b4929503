"""A closed-loop run's options and result, and the generated module it runs.

:func:`load_controller` imports what a backend wrote; :class:`Options` and :class:`Result`
are what :func:`~tvopt_codegen.simulation.run.simulate` takes and returns.
"""

from __future__ import annotations

import importlib.util
import tempfile
import types
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from tvopt_codegen.backends import BACKENDS
from tvopt_codegen.derivation import Derivation
from tvopt_codegen.emit import write_files
from tvopt_codegen.errors import BuildError, SpecError
from tvopt_codegen.limits import DEFAULT_ATOL, DEFAULT_POINTS, DEFAULT_RTOL, MAX_T_FINAL
from tvopt_codegen.lowering.ir import KernelSet
from tvopt_codegen.renderer.rendering import render


def load_controller(kernels: KernelSet, backend: str = "python") -> types.ModuleType:
    """Render a backend and load its Python module.

    A backend that says how (``Backend.load``: the Python backend compiles its module from
    memory) loads it so; the others are written to a private temporary folder through
    :func:`~tvopt_codegen.emit.write_files` and imported from there (the C backend compiles
    and caches its library on import).
    """
    files = render(kernels, backend)
    name = kernels.derivation.spec.name
    record = BACKENDS[backend]
    module_file = record.module.format(name=name)
    if record.load is not None:
        return record.load(files, module_file, name)
    with tempfile.TemporaryDirectory(prefix="tvopt-codegen-") as folder:
        write_files(files, folder)
        spec = importlib.util.spec_from_file_location(
            f"_tvopt_{backend}_{name}", Path(folder) / module_file
        )
        assert spec is not None and spec.loader is not None
        module = importlib.util.module_from_spec(spec)
        try:
            spec.loader.exec_module(module)
        except ImportError as exc:  # the C backend's build failed: say why, in one line
            raise BuildError(" ".join(str(exc).split())) from None
    return module


@dataclass(frozen=True)
class Options:
    """How to run one simulation.

    Attributes
    ----------
    t_final : float
        Horizon.
    initial_state : tuple of float
        Closed-loop initial state in ``STATE_NAMES`` order.
    params : mapping of str to float
        Parameter overrides.
    method : str
        ``solve_ivp`` method; RK45 (Dormand-Prince) as in the paper.
    rtol, atol : float
        Integration tolerances.
    points : int
        Number of output times.
    tolerance : float
        Largest accepted relative deviation of E from ``expm(H t) E(0)``.
    given : frozenset of str
        The states whose initial value the spec or the caller gave (the others of the
        integral action start bumplessly).
    """

    t_final: float
    initial_state: tuple[float, ...]
    params: Mapping[str, float] = field(default_factory=dict)
    method: str = "RK45"
    rtol: float = DEFAULT_RTOL
    atol: float = DEFAULT_ATOL
    points: int = DEFAULT_POINTS
    tolerance: float = 1e-6
    given: frozenset[str] = frozenset()


@dataclass(frozen=True)
class Trajectories:
    """A run sampled at its output times, before the certificate is checked along it.

    What :func:`~tvopt_codegen.simulation.run.simulate` hands its ``early`` callback:
    the figures that show the run alone are drawn from it while the run is certified.
    The arrays are the :class:`Result`'s own (the same objects).

    Attributes
    ----------
    options : Options
        As the :class:`Result`'s.
    t, states, inputs, outputs, target : numpy.ndarray
        As the :class:`Result`'s.
    references : ReferenceSource or None
        As the :class:`Result`'s.
    """

    options: Options
    t: np.ndarray
    states: np.ndarray
    inputs: np.ndarray
    outputs: np.ndarray
    target: np.ndarray
    references: Any = None


@dataclass(frozen=True)
class Result:
    """A simulated closed loop and its certificate.

    Attributes
    ----------
    t : numpy.ndarray, shape (T,)
        Output times.
    states : numpy.ndarray, shape (n, T)
        Closed-loop states.
    inputs : numpy.ndarray, shape (m, T)
        Plant inputs.
    outputs, target : numpy.ndarray, shape (m, T)
        ``y`` and ``y*``.
    error : numpy.ndarray, shape (T,)
        ``|y - y*|``.
    E, E_predicted : numpy.ndarray, shape (T, K, m)
        The optimality error and ``expm(H t) E(0)``.
    alpha, c, m_f, C : float
        The theorem's constants (``alpha_exact`` tells whether alpha is the slowest
        pole's decay or reduced by the Jordan-block margin).
    bound : numpy.ndarray, shape (T,)
        ``C e^{-alpha t}``.
    deviation : float
        ``max_t |E(t) - expm(H t) E(0)| / |E(0)|``.
    bound_ratio : float
        ``max_t |y - y*| / (C e^{-alpha t})`` (where the bound exceeds 1e-10).
    fitted_rate : float
        Decay rate of ``|E|`` fitted along the run.
    nfev : int
        Right-hand side evaluations.
    wall_time : float
        Seconds spent integrating.
    passed : bool
        Whether the certificate holds.
    failures : tuple of str
        Why it does not.
    dense : callable or None
        The integrator's interpolant: the closed-loop state at any time of the run
        (``dense(t)``, shape (n,) or (n, T)).
    references : ReferenceSource or None
        Where the reference jets came from (None without references).
    disturbance : float
        With estimated reference jets: ``sup |d|`` of ``E' = H E + d`` along the run
        (NaN otherwise).
    iss_ratio : float
        With estimated reference jets: ``max_t |E(t)| / (c e^{-alpha t} |E(0)| +
        (c / alpha)(1 - e^{-alpha t}) sup |d|)``, which the certificate checks is at most 1.
    reintegrated : str
        Empty, or, when a check failed at the requested tolerances, what happened: the
        run was integrated again, far more accurately (this result is that run's), and
        whether the failure was the integrator's error or the law's.
    iss_final : float
        With estimated reference jets: that bound at the end of the run; over ``m_f`` it
        bounds the final ``|y - y*|`` (``|grad f0(y)| >= m_f |y - y*|``). NaN otherwise.
    constraints : RunCheck or None
        For a spec with ``[constraints]``: margins, final values and the distance to the
        constrained minimiser along the run
        (:func:`tvopt_codegen.simulation.constraints.check_run`).
    """

    options: Options
    t: np.ndarray
    states: np.ndarray
    inputs: np.ndarray
    outputs: np.ndarray
    target: np.ndarray
    error: np.ndarray
    E: np.ndarray
    E_predicted: np.ndarray
    alpha: float
    alpha_exact: bool
    c: float
    m_f: float
    C: float
    bound: np.ndarray
    deviation: float
    bound_ratio: float
    fitted_rate: float
    nfev: int
    wall_time: float
    passed: bool
    failures: tuple[str, ...]
    dense: Any = None
    references: Any = None
    disturbance: float = float("nan")
    iss_ratio: float = float("nan")
    iss_final: float = float("nan")
    constraints: Any = None
    reintegrated: str = ""


def resolve_options(
    derivation: Derivation,
    t_final: float | None = None,
    initial: Mapping[str, float] | None = None,
    params: Mapping[str, float] | None = None,
    **rest: Any,
) -> Options:
    """Build :class:`Options` from the spec's ``[simulation]`` and overrides by name.

    Raises
    ------
    SpecError
        For an unknown state or parameter name, or a non-positive horizon (the field
        is the command-line option).
    """
    names = derivation.closed_loop.state_names
    state = dict(zip(names, derivation.closed_loop.initial_state, strict=True))
    for key, value in (initial or {}).items():
        if key not in state:
            raise SpecError(
                "command line", "--initial", f"unknown state {key!r} (states: {', '.join(names)})"
            )
        state[key] = float(value)
    known = {n for n, _ in derivation.spec.parameters}
    for key in params or {}:
        if key not in known:
            raise SpecError(
                "command line",
                "--param",
                f"unknown parameter {key!r} (parameters: {', '.join(sorted(known))})",
            )
    horizon = derivation.spec.t_final if t_final is None else float(t_final)
    if not 0 < horizon <= MAX_T_FINAL:
        raise SpecError(
            "command line", "--t-final", f"must be positive and at most {MAX_T_FINAL:g}"
        )
    return Options(
        t_final=horizon,
        initial_state=tuple(state[n] for n in names),
        params=dict(params or {}),
        given=frozenset(name for name, _ in derivation.spec.initial_state) | set(initial or {}),
        **rest,
    )


def columns(derivation: Derivation) -> list[str]:
    """Column names of the trajectory table."""
    d = derivation
    names = ["t", *d.closed_loop.state_names, *(f"u_{n}" for n in d.spec.inputs)]
    names += [*(f"y_{n}" for n in d.spec.outputs), *(f"ystar_{n}" for n in d.spec.outputs)]
    names += [f"E{j}_{n}" for j in range(d.dynamics.k) for n in d.spec.outputs]
    return names
