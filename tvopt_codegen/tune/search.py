"""Optimisers over the unit box, ask and tell, and a search that can stop and resume.

An optimiser proposes a generation of points of [0, 1]^d (``ask``) and learns their
values (``tell``); it draws its random numbers from its own ``numpy.random.Generator``
seeded by the user, so the same seed proposes the same points whatever else runs in
the process. CMA-ES (the ``cma`` package) is the method for a noisy black box such as
a sweep's score; uniform random search is the baseline it is measured against.

Nothing is saved here: a :class:`Search` keeps the ``(point, value)`` history in memory
and the command writes it. Because an optimiser is deterministic given its seed and
the values it is told, replaying a history (:func:`replay`) brings a fresh optimiser
to the state the interrupted one had, without evaluating anything again.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np

from tvopt_codegen.errors import SpecError

#: Two points are the same point of a history when no coordinate differs by more.
REPLAY_TOLERANCE = 1e-12


class Optimizer(Protocol):
    """Ask for a generation of points of [0, 1]^d, tell their values (lower is better)."""

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
        import cma  # type: ignore[import-untyped]  # noqa: PLC0415 - the tune extra
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


@dataclass(frozen=True)
class Replay:
    """Where an optimiser stands after :func:`replay`.

    Attributes
    ----------
    consumed : int
        History entries replayed (all of them).
    generations : int
        Complete generations told to the optimiser.
    asked : tuple of numpy.ndarray
        The generation asked but not yet told (empty when the history ended at a
        generation's end): the caller evaluates :attr:`pending` and tells the optimiser
        ``asked`` with ``told`` and the new values.
    told : tuple of float
        The recorded values of ``asked[:len(told)]``.
    """

    consumed: int
    generations: int
    asked: tuple[np.ndarray, ...]
    told: tuple[float, ...]

    @property
    def pending(self) -> tuple[np.ndarray, ...]:
        """The points of the open generation still to evaluate, in order."""
        return self.asked[len(self.told) :]


def _same(a: np.ndarray, b: np.ndarray) -> bool:
    return a.shape == b.shape and bool(np.all(np.abs(a - b) <= REPLAY_TOLERANCE))


def replay(optimizer: Optimizer, history: Sequence[tuple[np.ndarray, float]]) -> Replay:
    """Ask and tell ``history`` again, so that a fresh optimiser continues where it stopped.

    Parameters
    ----------
    optimizer : Optimizer
        Made as the recorded one was (same kind, start, seed, population), never asked.
    history : sequence of (numpy.ndarray, float)
        The evaluations in the order they were made, possibly ending mid-generation.

    Returns
    -------
    Replay
        The complete generations are told; the last, partial one is asked and left
        open, with its recorded values.

    Raises
    ------
    ValueError
        When an asked point differs from the recorded one (another seed, start, method
        or population than the history's).
    """
    consumed = generations = 0
    while consumed < len(history):
        asked = optimizer.ask()
        told: list[float] = []
        for x in asked:
            if consumed == len(history):
                return Replay(consumed, generations, tuple(asked), tuple(told))
            point, value = history[consumed]
            if not _same(x, np.asarray(point, dtype=float)):
                raise ValueError(
                    f"evaluation {consumed} of the history is not the point the optimiser asks "
                    "(another seed, start, method or population?)"
                )
            told.append(float(value))
            consumed += 1
        optimizer.tell(asked, told)
        generations += 1
    return Replay(consumed, generations, (), ())


class Search:
    """An optimiser and its history, one evaluation at a time, resumable.

    Parameters
    ----------
    optimizer : Optimizer
        A fresh optimiser (never asked).
    history : sequence of (numpy.ndarray, float), optional
        Evaluations of an earlier run of the same optimiser, replayed (:func:`replay`).

    Examples
    --------
    >>> search = Search(random_optimizer(2, seed=1, population=3))
    >>> for x in search.pending():
    ...     search.record(x, float(np.sum(x**2)))
    >>> search.generations
    1
    """

    def __init__(
        self, optimizer: Optimizer, history: Sequence[tuple[np.ndarray, float]] = ()
    ) -> None:
        self.optimizer = optimizer
        state = replay(optimizer, history)
        self.generations = state.generations
        self._history = [(np.array(x, dtype=float), float(v)) for x, v in history]
        self._asked = list(state.asked)
        self._told = list(state.told)

    def pending(self) -> list[np.ndarray]:
        """The open generation's points still to evaluate (asking a new one if none is open)."""
        if not self._asked:
            self._asked = self.optimizer.ask()
            self._told = []
        return [x.copy() for x in self._asked[len(self._told) :]]

    def record(self, x: np.ndarray, value: float) -> None:
        """The value of the first pending point; the generation's last tells the optimiser.

        Raises
        ------
        ValueError
            When ``x`` is not the first pending point, or ``value`` is not finite.
        """
        pending = self.pending()
        if not _same(np.asarray(x, dtype=float), pending[0]):
            raise ValueError("record the pending points in the order pending() gives them")
        if not np.isfinite(value):
            raise ValueError(f"an optimiser needs finite values, got {value}")
        self._told.append(float(value))
        self._history.append((pending[0], float(value)))
        if len(self._told) == len(self._asked):
            self.optimizer.tell(self._asked, self._told)
            self.generations += 1
            self._asked, self._told = [], []

    @property
    def history(self) -> tuple[tuple[np.ndarray, float], ...]:
        """Every evaluation so far, in order (the replayed ones first)."""
        return tuple((x.copy(), v) for x, v in self._history)

    @property
    def best(self) -> tuple[np.ndarray, float] | None:
        """The lowest value's point and value (the first of equals); None before any."""
        if not self._history:
            return None
        index = min(range(len(self._history)), key=lambda i: self._history[i][1])
        x, value = self._history[index]
        return x.copy(), value
