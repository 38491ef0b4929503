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
    def from_dict(cls, record: dict[str, Any]) -> Settings:
        """The inverse of :meth:`as_dict`."""

        def pair(value: Any) -> tuple[float, float] | None:
            return None if value is None else (float(value[0]), float(value[1]))

        return cls(
            evaluations=int(record["evaluations"]),
            samples=int(record["samples"]),
            seed=int(record["seed"]),
            check_samples=int(record["check_samples"]),
            check_seed=int(record["check_seed"]),
            method=str(record["method"]),
            population=None if record["population"] is None else int(record["population"]),
            objective=None if record["objective"] is None else str(record["objective"]),
            constraints=tuple(str(c) for c in record["constraints"]),
            after=None if record["after"] is None else float(record["after"]),
            pole_range=pair(record["pole_range"]),
            min_damping=None if record["min_damping"] is None else float(record["min_damping"]),
            bandwidth_range=pair(record["bandwidth_range"]),
            complex_pairs=None if record["complex_pairs"] is None else int(record["complex_pairs"]),
        )
