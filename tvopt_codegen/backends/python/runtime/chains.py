"""Integrator chains advanced exactly: the controller states, and a jet's Taylor shift.

Sections: ``advance`` (the controller states over a step, each chain's drive held) and
``taylor_shift`` (a jet along its Taylor polynomial). The C twins are in
``templates/c/runtime/controller.jinja``, operation for operation.
"""

from __future__ import annotations

from tvopt_codegen.backends.python.runtime.linalg import _finite
from tvopt_codegen.backends.python.runtime.provided import _CHAINS, NonFiniteInputError

# --- copied verbatim into the generated controller below this line ---


# --- section: advance ---
def _advance(z: list[float], drive: list[float], h: float, t: float) -> list[float]:
    """The controller states ``h`` seconds on, each chain's drive held (Taylor, exact).

    States that overflow on the way (a step of 1e200 s) are an input of the law that is
    not finite, as in the C controller: NonFiniteInputError, before the law is tried.
    """
    out = list(z)
    for chain, (start, length) in enumerate(_CHAINS):
        for j in range(length):
            term, total = 1.0, 0.0
            for k in range(length - j):
                total += z[start + j + k] * term
                term *= h / (k + 1)
            out[start + j] = total + drive[chain] * term
    if not _finite(out):
        raise NonFiniteInputError(
            f"the controller states are not finite at t = {t!r}, {h!r} s after the last step: "
            "the step is too long for them"
        )
    return out


# --- section: taylor_shift ---
def _taylor_shift(jet: list[float], h: float) -> list[float]:
    """A jet h seconds on along its Taylor polynomial (entry j: sum_k jet[j + k] h^k / k!)."""
    out = []
    for j in range(len(jet)):
        term, total = 1.0, 0.0
        for k in range(len(jet) - j):
            total += jet[j + k] * term
            term *= h / (k + 1)
        out.append(total)
    return out
