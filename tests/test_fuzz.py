"""The differential fuzzer at a small budget (``make fuzz`` runs it at any budget).

Hypothesis draws the cases (``tests/fuzzing.py``): each random plant of known structure
with random features must agree with the independent oracle (and with Pinocchio, for a
URDF chain), or be refused with a one-line SpecError or AssumptionError. Derandomized
here, so the suite sees the same cases on every run; ``FUZZ_CASES`` raises the budget.
"""

from __future__ import annotations

import os

import pytest

from .fuzzing import AGREES, Case, cases_strategy, run_case

hypothesis = pytest.importorskip("hypothesis")
from hypothesis import HealthCheck, given, settings  # noqa: E402

pytest.importorskip("yourdfpy", reason="the URDF cases need the urdf extra")
pytest.importorskip("pinocchio", reason="the URDF cases are checked against Pinocchio")

#: About 1 s of CPU each, chains of at most 2 (``make fuzz`` draws up to 3).
CASES = int(os.environ.get("FUZZ_CASES", "5"))


def _ends_well(case: Case) -> None:
    outcome = run_case(case)
    assert outcome == AGREES or outcome.startswith(
        ("refused: SpecError: ", "refused: AssumptionError: ")
    ), outcome


@settings(
    max_examples=CASES,
    derandomize=True,
    database=None,
    deadline=None,
    suppress_health_check=list(HealthCheck),
)
@given(cases_strategy(c_rate=0.0, fmu_rate=0.0, max_size=2))
def test_random_cases_agree_with_the_oracle_or_are_refused(case: Case) -> None:
    _ends_well(case)


@pytest.mark.parametrize(
    "case",
    [
        # Unequal chains (padding), integral action, a reference, limits, C.
        "system:3:c+integral+limits+references:11",
        # A forward speed prolonged by extension.auto, an observer and an inequality.
        "system:4:auto+inequality+observer+unicycle:12",
        # A three-link arm from SymPy mechanics with an equality constraint.
        "arm:3:equality+integral:13",
        # A URDF chain against Pinocchio, and its controller in the FMU.
        "urdf:2:fmu+limits+observer:14",
    ],
)
def test_chosen_cases_across_every_target(case: str) -> None:
    _ends_well(Case.parse(case))
