"""``tvopt-codegen tune``'s pure core: the search space, the requirements, the optimisers.

- :mod:`~tvopt_codegen.tune.space`: the unit box [0, 1]^d and the candidates (poles of a
  Hurwitz H, an observer bandwidth) it decodes to, rounded to what the tuned spec says.
- :mod:`~tvopt_codegen.tune.requirements`: an objective ``STAT(METRIC)`` and constraints
  ``... <= V`` as the user writes them, checked, and scored on a sweep's rows.
- :mod:`~tvopt_codegen.tune.search`: CMA-ES and random search by ask and tell, seeded,
  and a search that replays its history to resume.

Nothing here runs a sweep, reads a spec file or writes one: the command does.
"""

from __future__ import annotations
