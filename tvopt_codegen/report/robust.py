"""The report's sections on a plant that is not the model: one per option a spec takes.

Integral action, the disturbance observer, the extended-state observer and the actuator
limits, as the controller runs them (titled as in
:data:`~tvopt_codegen.report.document.ROBUST_HEADINGS`). They read
:attr:`Derivation.robustness` and :attr:`Derivation.rejection`; they derive nothing.
"""

from __future__ import annotations

from tvopt_codegen.derivation import Derivation
from tvopt_codegen.report.entries import Entry, Section
from tvopt_codegen.report.sections import _pole


def _robustness(d: Derivation) -> tuple[Section, ...]:
    """Integral action, the disturbance observer and the limits, as the controller runs them.

    One section per option the spec takes, titled as in ``ROBUST_HEADINGS``.
    """
    spec = d.spec
    sections: list[Section] = []
    if d.closed_loop.integral_states:
        pole = d.dynamics.integral_pole
        others = [p for p in d.dynamics.eigenvalues]
        for index, value in enumerate(others):
            if (
                value.imag == 0
                and pole is not None
                and abs(value.real - pole) < 1e-9 * (1 + abs(pole))
            ):
                del others[index]
                break
        integral = [
            Entry(
                "text",
                text=(
                    "Integral action: the controller integrates each entry of the optimality "
                    "error's first row, z_I' = grad f0, and the law adds a_0 z_I to "
                    "Hess y_imp^(k), so that a constant matched disturbance leaves grad f0 at 0. "
                    "H_I's polynomial is (s - lambda) p(s): on z_I = z*(E) = sum_j b_j E_j the "
                    "error moves as under the law with p's poles alone, and delta = z_I - z*(E) "
                    "obeys delta' = lambda delta. The Controller starts on z*(E(0)) (bumpless) "
                    "and, while an input is clipped, keeps delta instead of integrating (no "
                    "windup)."
                ),
            ),
            Entry(
                "table",
                text="The integral's pole and the bumpless start.",
                header=("quantity", "value"),
                rows=(
                    ("lambda: the integral's pole (real, closest to zero)", f"{pole:.6g}"),
                    ("p's poles: the nominal response", ", ".join(_pole(v) for v in others)),
                    ("b_0 .. b_{k-1}", ", ".join(f"{b:.10g}" for b in d.dynamics.bumpless)),
                ),
            ),
        ]
        sections.append(Section("Integral action", tuple(integral)))
    robust = d.robustness
    if robust.observer is not None:
        beta = robust.observer
        rows = ", ".join(spec.states[k] for k in robust.observed_states)
        blocks = "; ".join(
            ", ".join(spec.inputs[i] for i in block) for block in robust.observer_blocks
        )
        observer = Entry(
            "text",
            text=(
                f"Disturbance observer, bandwidth beta = {beta:.6g} rad/s: a matched input "
                "disturbance d in x' = f(x) + G(x) (u + d), from the measured plant state "
                "and the applied input. Each step, r = (x_k - x_{k-1}) / h - (F_{k-1} + "
                "F_k) / 2 with F = f(x) + G(x) u (G d to O(h^2)); sigma += (1 - "
                "exp(-beta h)) (r - sigma), every pole of sigma at "
                f"{-beta:.6g}; d_hat solves G(x) d = sigma in the least-squares sense (f(x) "
                "and G(x) from the law's jet kernel); the controller commands u - d_hat. "
                "Nominally d_hat = 0 up to the trapezoid rule's O(h^2). The residual is kept "
                f"on the plant states an input acts on ({rows}: the rows of G that are not "
                "structurally zero), and the least squares are solved per block of inputs "
                f"whose columns of G share a row ({blocks})."
            ),
        )
        sections.append(Section("Disturbance observer", (observer,)))
    if d.rejection is not None:
        sections.append(_extended_state_observer(d))
    if spec.limits:
        limits = Entry(
            "table",
            text=(
                "Actuator limits: the Controller clips the commanded input to [low, high] "
                "and, after its first step, to within rate h of the last one; the "
                "integral states and a clipped prolonged input's extension chain follow "
                "the applied input (anti-windup); Controller.saturated, the C struct's "
                "saturated mask and the FMU's saturated outputs say which were clipped."
            ),
            header=("input", "low", "high", "rate (1/s)"),
            rows=tuple(
                (limit.input, f"{limit.low:g}", f"{limit.high:g}", f"{limit.rate:g}")
                for limit in spec.limits
            ),
        )
        sections.append(Section("Actuator limits", (limits,)))
    return tuple(sections)


def _extended_state_observer(d: Derivation) -> Section:
    """The extended-state observer: its coordinates, what it estimates, its poles."""
    eso = d.rejection
    assert eso is not None
    omega = eso.bandwidth
    text = Entry(
        "text",
        text=(
            f"Extended-state observer, bandwidth omega = {omega:.6g} rad/s. Per output y_i of "
            "relative degree r_i, in the law's own coordinates: estimates of y_i, y_i', .., "
            "y_i^(r_i - 1) and of the lumped disturbance d_i in y_i^(r_i) = p_i(x) + (R(x) "
            "w)_i + d_i, which holds for the true derivatives of y_i whatever row of the "
            "plant the mismatch enters. It measures y = h(x) alone: under mismatch L_f^j h(x)"
            f" is not y^(j). eta_j' = eta_{{j+1}} + l_{{j+1}} e, eta_{{r-1}}' = v + l_r e, "
            f"d_hat' = l_{{r+1}} e with e = y - eta_0 and l_j = C(r + 1, j) omega^j, every "
            f"pole of the estimation error at {-omega:.6g}. The law reads the measured y and "
            "eta_1 .. eta_(r-1) where it read Phi(x), and commands R w = v - p - d_hat. The "
            "sampled controller runs the exact discrete twin: the chain moved with v held "
            "over the step (Taylor), then corrected by the newest output with gains that put "
            "every pole at exp(-omega h). Started at eta = Phi(x0), d_hat = 0, the error is "
            "zero on the model and stays zero: the nominal closed loop is the plain law's, "
            "and the certificate above holds for it."
        ),
    )
    rows = tuple(
        (
            output,
            str(r),
            ", ".join(chain[:-1]),
            chain[-1],
            ", ".join(f"{g:.6g}" for g in gains),
            f"{-omega:.6g} (x{r + 1})",
        )
        for output, r, chain, gains in zip(
            d.spec.outputs, eso.orders, eso.states, eso.continuous, strict=True
        )
    )
    table = Entry(
        "table",
        text="The observer's coordinates (controller states), gains and poles, per output.",
        header=(
            "output",
            "r_i",
            "estimates of y .. y^(r_i - 1)",
            "d_hat",
            "l_1 .. l_{r+1}",
            "poles",
        ),
        rows=rows,
    )
    return Section("Extended-state observer", (text, table))
