"""A tune's settings: everything on its command line that decides its result.

Recorded in ``tune.json`` (:meth:`Settings.as_dict`) and read back by ``--resume``, so
that a resumed tune searches the same space, by the same requirements, with the same
seeds.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any


@dataclass(frozen=True)
class Settings:
    """Everything that decides a tune's result (its record's ``settings``)."""

    evaluations: int
    samples: int
    seed: int
    check_samples: int
    check_seed: int
    method: str
    population: int | None
    objective: str | None
    constraints: tuple[str, ...]
    after: float | None
    pole_range: tuple[float, float] | None
    min_damping: float | None
    bandwidth_range: tuple[float, float] | None
    complex_pairs: int | None

    def as_dict(self) -> dict[str, Any]:
        """JSON-ready."""
        return {
            "evaluations": self.evaluations,
            "samples": self.samples,
            "seed": self.seed,
            "check_samples": self.check_samples,
            "check_seed": self.check_seed,
            "method": self.method,
            "population": self.population,
            "objective": self.objective,
            "constraints": list(self.constraints),
            "after": self.after,
            "pole_range": None if self.pole_range is None else list(self.pole_range),
            "min_damping": self.min_damping,
            "bandwidth_range": None if self.bandwidth_range is None else list(self.bandwidth_range),
            "complex_pairs": self.complex_pairs,
        }

    @classmethod
    def from_dict(cls, record: Any) -> Settings:
        """The inverse of :meth:`as_dict`, each value's type checked.

        Raises
        ------
        ValueError
            ``"<key>: <problem>"`` for a key missing or of the wrong type (a record
            edited by hand or cut short); the values' bounds are the command's to check.
        """
        if not isinstance(record, dict):
            raise ValueError(f"expected a table of settings, got {type(record).__name__}")

        def value(key: str) -> Any:
            if key not in record:
                raise ValueError(f"{key}: missing")
            return record[key]

        def integer(key: str, optional: bool = False) -> Any:
            found = value(key)
            if optional and found is None:
                return None
            if isinstance(found, bool) or not isinstance(found, int):
                raise ValueError(f"{key}: expected an integer, got {found!r}")
            return found

        def number(found: Any, key: str) -> float:
            if isinstance(found, bool) or not isinstance(found, (int, float)):
                raise ValueError(f"{key}: expected a number, got {found!r}")
            return float(found)

        def optional_number(key: str) -> float | None:
            found = value(key)
            return None if found is None else number(found, key)

        def text(found: Any, key: str) -> str:
            if not isinstance(found, str):
                raise ValueError(f"{key}: expected a string, got {found!r}")
            return found

        def pair(key: str) -> tuple[float, float] | None:
            found = value(key)
            if found is None:
                return None
            if not isinstance(found, list) or len(found) != 2:
                raise ValueError(f"{key}: expected [lo, hi], got {found!r}")
            return number(found[0], key), number(found[1], key)

        constraints = value("constraints")
        if not isinstance(constraints, list):
            raise ValueError(f"constraints: expected a list of strings, got {constraints!r}")
        objective = value("objective")
        return cls(
            evaluations=integer("evaluations"),
            samples=integer("samples"),
            seed=integer("seed"),
            check_samples=integer("check_samples"),
            check_seed=integer("check_seed"),
            method=text(value("method"), "method"),
            population=integer("population", optional=True),
            objective=None if objective is None else text(objective, "objective"),
            constraints=tuple(text(c, "constraints") for c in constraints),
            after=optional_number("after"),
            pole_range=pair("pole_range"),
            min_damping=optional_number("min_damping"),
            bandwidth_range=pair("bandwidth_range"),
            complex_pairs=integer("complex_pairs", optional=True),
        )
