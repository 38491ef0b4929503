"""Optimisers over the unit box, by ask and tell, each deterministic given its seed.

An optimiser proposes a generation of points of [0, 1]^d (``ask``) and learns their
values (``tell``); it draws its random numbers from a generator of its own seeded by the
user, so the same seed proposes the same points whatever else runs in the process.
CMA-ES (the ``cma`` package) is the method for a noisy black box such as a sweep's
score; optuna's TPE is the alternative measured against it (``--method tpe``), uniform
random search the baseline. Because an optimiser is deterministic given its seed and the
values it is told, a fresh one told a recorded history again stands where the
interrupted one stood (:class:`tvopt_codegen.tune.session.Search` replays it).
"""

from __future__ import annotations

import sys
import warnings
from collections.abc import Sequence
from typing import Any, Protocol

import numpy as np

from tvopt_codegen.errors import SpecError


class Optimizer(Protocol):
    """Ask for a generation of points of [0, 1]^d, tell their values (lower is better)."""

    @property
    def population(self) -> int:
        """Points per generation."""
        ...

    def ask(self) -> list[np.ndarray]:
        """The next generation's points, each of shape (d,), inside the box."""
        ...

    def tell(self, xs: Sequence[np.ndarray], values: Sequence[float]) -> None:
        """The values of the points :meth:`ask` returned last, in its order."""
        ...


class CmaOptimizer:
    """CMA-ES (``cma.CMAEvolutionStrategy``) on [0, 1]^d, made by :func:`cma_optimizer`.

    Parameters
    ----------
    strategy : cma.CMAEvolutionStrategy
        Configured with bounds [0, 1] and a ``randn`` of its own.
    """

    def __init__(self, strategy: Any) -> None:
        self.strategy = strategy

    @property
    def population(self) -> int:
        """Points per generation."""
        return int(self.strategy.popsize)

    def ask(self) -> list[np.ndarray]:
        """The next generation (cma's bound transformation keeps it in the box)."""
        return [np.array(x, dtype=float) for x in self.strategy.ask()]

    def tell(self, xs: Sequence[np.ndarray], values: Sequence[float]) -> None:
        """Update the distribution from the generation's values."""
        self.strategy.tell(list(xs), [float(v) for v in values])


def cma_optimizer(
    start: np.ndarray, seed: int, population: int | None = None, sigma: float = 0.25
) -> CmaOptimizer:
    """CMA-ES from ``start`` with step size ``sigma``, quiet and seeded.

    No file is written and nothing printed (``verbose -9``, ``verb_log 0``,
    ``verb_disp 0``); the normal draws come from ``Generator(PCG64(seed))`` through cma's
    ``randn`` option (``seed`` set to NaN: cma then leaves numpy's global state alone).

    Parameters
    ----------
    start : numpy.ndarray, shape (d,)
        The initial mean, a point of [0, 1]^d (clipped to it); d = 1 (one pole) too.
    seed : int
        The random numbers' seed.
    population : int, optional
        Points per generation; default cma's ``4 + floor(3 ln d)``.
    sigma : float
        Initial step size, in box units.

    Returns
    -------
    CmaOptimizer

    Raises
    ------
    SpecError
        When the ``cma`` package is not installed.
    """
    try:
        cma = _import_cma()
    except ImportError:
        raise SpecError(
            "command line", "--method", "needs the cma package: pip install 'tvopt-codegen[tune]'"
        ) from None
    rng = np.random.Generator(np.random.PCG64(seed))

    def randn(*shape: int) -> np.ndarray:
        return rng.standard_normal(shape)

    options: dict[str, Any] = {
        "bounds": [0.0, 1.0],
        "verbose": -9,
        "verb_log": 0,
        "verb_disp": 0,
        "randn": randn,
        "seed": np.nan,
    }
    if population is not None:
        options["popsize"] = int(population)
    x0 = np.clip(np.asarray(start, dtype=float), 0.0, 1.0)
    return CmaOptimizer(cma.CMAEvolutionStrategy(x0.tolist(), float(sigma), options))


#: What ``import cma`` loads for what tune never uses, when nothing loaded it before:
#: pyplot for ``cma.s``'s shell shortcuts and scipy.stats for Kendall's tau of its
#: surrogate models. cma imports both inside ``try``, falling back without them.
CMA_OPTIONAL = ("matplotlib", "matplotlib.pyplot", "scipy.stats")


class _Refusing:
    """An import hook refusing ``names`` (and their submodules) that are not loaded yet."""

    def __init__(self, names: Sequence[str]) -> None:
        self.names = [n for n in names if n not in sys.modules]

    def find_spec(self, name: str, path: object = None, target: object = None) -> None:
        """Refuse a listed module; leave every other to the next finder."""
        if any(name == n or name.startswith(n + ".") for n in self.names):
            raise ImportError(f"{name}: not loaded for cma (tvopt_codegen.tune.search)")


def _import_cma() -> Any:
    """``cma``, loaded without :data:`CMA_OPTIONAL`: 0.55 s of a small tune's 1.6 s of CPU.

    What is loaded already is cma's as usual. CMA-ES asks the same points either way: its
    sampling and updates use NumPy only (a tune's records are the same bytes). Pyplot
    unloaded also leaves the user's matplotlib backend unchosen.
    """
    loaded = sys.modules.get("cma")
    if loaded is not None:
        return loaded
    hook = _Refusing(CMA_OPTIONAL)
    sys.meta_path.insert(0, hook)
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # cma's note that cma.plot() needs pyplot
            import cma  # noqa: PLC0415 - the tune extra
    finally:
        sys.meta_path.remove(hook)
    return cma


class RandomOptimizer:
    """Uniform random search on [0, 1]^d: the baseline CMA-ES must beat.

    Parameters
    ----------
    dimension : int
        d.
    seed : int
        The random numbers' seed.
    population : int
        Points per generation (as CMA's, for a like-for-like comparison).
    """

    def __init__(self, dimension: int, seed: int, population: int) -> None:
        if dimension < 1 or population < 1:
            raise ValueError("a random search needs a dimension and a population of at least 1")
        self.dimension = dimension
        self.population = population
        self.rng = np.random.Generator(np.random.PCG64(seed))

    def ask(self) -> list[np.ndarray]:
        """``population`` uniform points."""
        return list(self.rng.random((self.population, self.dimension)))

    def tell(self, xs: Sequence[np.ndarray], values: Sequence[float]) -> None:
        """Nothing is learnt; the sizes are checked."""
        if len(xs) != len(values):
            raise ValueError(f"{len(xs)} points and {len(values)} values")


def random_optimizer(dimension: int, seed: int, population: int) -> RandomOptimizer:
    """Uniform random search; see :class:`RandomOptimizer`."""
    return RandomOptimizer(dimension, seed, population)


class TpeOptimizer:
    """optuna's Tree-structured Parzen Estimator on [0, 1]^d, made by :func:`tpe_optimizer`.

    A generation is ``population`` trials asked together (the sampler draws each from the
    model of the trials told so far) and told together.
    """

    def __init__(self, study: Any, dimension: int, population: int) -> None:
        self.study = study
        self.dimension = dimension
        self.population = population
        self._trials: list[Any] = []

    def ask(self) -> list[np.ndarray]:
        """The next ``population`` trials' points."""
        self._trials = [self.study.ask() for _ in range(self.population)]
        return [
            np.array([t.suggest_float(f"x{i}", 0.0, 1.0) for i in range(self.dimension)])
            for t in self._trials
        ]

    def tell(self, xs: Sequence[np.ndarray], values: Sequence[float]) -> None:
        """The values of the trials :meth:`ask` returned last, in its order."""
        if len(xs) != len(self._trials) or len(values) != len(xs):
            raise ValueError(f"{len(xs)} points and {len(values)} values for {len(self._trials)}")
        for trial, value in zip(self._trials, values, strict=True):
            self.study.tell(trial, float(value))


def tpe_optimizer(start: np.ndarray, seed: int, population: int) -> TpeOptimizer:
    """Optuna's TPE (multivariate), seeded, its first trial the spec's own gains ``start``.

    Raises
    ------
    SpecError
        When optuna is not installed.
    """
    try:
        import optuna  # noqa: PLC0415 - the tpe extra
    except ImportError:
        raise SpecError(
            "command line", "--method", "tpe needs optuna: pip install 'tvopt-codegen[tpe]'"
        ) from None
    optuna.logging.set_verbosity(optuna.logging.WARNING)
    sampler = optuna.samplers.TPESampler(seed=seed, multivariate=True)
    study = optuna.create_study(direction="minimize", sampler=sampler)
    x0 = np.clip(np.asarray(start, dtype=float), 0.0, 1.0)
    study.enqueue_trial({f"x{i}": float(v) for i, v in enumerate(x0)})
    return TpeOptimizer(study, len(x0), population)
