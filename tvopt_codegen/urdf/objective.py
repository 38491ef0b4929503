"""The default objective an import writes, kept clear of singularities.

Each joint follows a slow sine about its start, or, with a tip, the tip link's position
follows a circle in the horizontal plane (the tip's ``px, py, pz`` replace the first three
joints as outputs, so that the outputs still number the inputs). That circle is checked
along the run the law makes (:func:`_tip_circle`): where it would come near a singularity
of the decoupling matrix or out of reach, three other joints, a smaller circle or another
plane is taken, and the notes say which.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Callable, Mapping, Sequence

import numpy as np
import sympy as sp

from tvopt_codegen.urdf.chain import _Body
from tvopt_codegen.urdf.dynamics import _placements, _position, _text

#: The default objective's circle is kept where the tip Jacobian (of the first three
#: joints) keeps at least this inverse condition number along the whole run.
SAFE_CONDITION = 0.05


class _Kinematics:
    """The tip's position and its Jacobian at a configuration, numerically.

    Called thousands of times by :func:`_circle_margin` (Newton's method at each of a
    run's 301 points, for each circle tried): what does not depend on the configuration
    is worked out once here, and the cross products are written out. Each number is made
    by the same floating-point operations as :func:`~tvopt_codegen.urdf.chain._turn` and
    ``numpy.cross`` would make it, so the margins, and the circle chosen, are the same to
    the last bit.
    """

    def __init__(self, bodies: Sequence[_Body], tip: str, n: int) -> None:
        index = next(i for i, body in enumerate(bodies) if body.link == tip)
        path: list[_Body] = []
        while index >= 0:
            path.append(bodies[index])
            index = bodies[index].parent
        self.n = n
        self.parts = []
        for body in reversed(path):
            axis = np.array(body.axis.tolist(), dtype=float).ravel()
            x, y, z = axis
            self.parts.append(
                (
                    np.array(body.rotation.tolist(), dtype=float),
                    np.array(body.offset.tolist(), dtype=float).ravel(),
                    axis,
                    body.kind,
                    body.coordinate,
                    # _turn's constant terms: the identity, the cross-product matrix of
                    # the axis, and its outer product with itself.
                    np.eye(3),
                    np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]]),
                    np.outer(axis, axis),
                )
            )

    def __call__(self, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        turn = np.eye(3)
        at = np.zeros(3)
        axes: list[tuple[int, np.ndarray, np.ndarray | None]] = []
        for rotation, offset, axis, kind, coordinate, eye, cross, outer in self.parts:
            at = at + turn @ offset
            turn = turn @ rotation
            if kind == "revolute":
                axes.append((coordinate, turn @ axis, at))
                angle = float(q[coordinate])
                c, s = math.cos(angle), math.sin(angle)
                turn = turn @ (c * eye + s * cross + (1 - c) * outer)
            elif kind == "prismatic":
                direction = turn @ axis
                axes.append((coordinate, direction, None))
                at = at + direction * float(q[coordinate])
        jacobian = np.zeros((3, self.n))
        for coordinate, direction, pivot in axes:
            if pivot is None:
                jacobian[:, coordinate] = direction
                continue
            (a0, a1, a2), (b0, b1, b2) = direction.tolist(), (at - pivot).tolist()
            jacobian[:, coordinate] = (a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0)
        return at, jacobian


#: The default objective's motions: the tip's circle and each other joint's sine (rad/s).
_FREQUENCY = 0.5
_SWING = 0.2
_POLES = (-2.0, -3.0)
_T_FINAL = 10.0
_PLANES = {"x-y": (0, 1), "x-z": (0, 2), "y-z": (1, 2)}


def _settle(e0: np.ndarray, v0: np.ndarray, t: float) -> np.ndarray:
    """The error ``y - y*`` at ``t`` under the error dynamics' two real poles."""
    p1, p2 = _POLES
    b = (v0 - p1 * e0) / (p2 - p1)
    return np.asarray((e0 - b) * math.exp(p1 * t) + b * math.exp(p2 * t))


def _circle_margin(
    kinematics: _Kinematics,
    start: np.ndarray,
    radius: float,
    plane: tuple[int, int],
    solved: Sequence[int],
    enough: float = -math.inf,
) -> tuple[float, float]:
    """The tip Jacobian's smallest inverse condition number along a run, and at its start.

    The run is the one the law makes exactly: each output is its target plus the error
    that the poles let decay from the start at rest, so the tip path is known without
    integrating. The three ``solved`` joints (those the tip's position replaces as
    outputs) are solved for along it by Newton's method from the previous point; the
    others are their own outputs. The Jacobian is the tip's with respect to the solved
    joints: the decoupling matrix is singular exactly where it is. An unreachable point,
    or a jump between two points (a change of branch), counts as 0.

    The run stops once the smallest falls below ``enough``: a caller that only asks
    whether the circle keeps clear of that margin has its answer (the number returned
    is then that of the run so far, an upper bound of the whole run's).
    """
    n = kinematics.n
    chosen = list(solved)
    rest = [i for i in range(n) if i not in chosen]
    centre, _ = kinematics(start)
    a, b = np.eye(3)[plane[0]], np.eye(3)[plane[1]]
    e_tip = -radius * a
    v_tip = -radius * _FREQUENCY * b
    v_joint = -_SWING * _FREQUENCY * np.ones(len(rest))
    q = start.astype(float).copy()
    worst = math.inf
    first = math.nan
    scale = 1.0 + float(np.abs(centre).max())
    for t in np.linspace(0.0, _T_FINAL, 301):
        angle = _FREQUENCY * t
        target = centre + radius * (math.cos(angle) * a + math.sin(angle) * b)
        target = target + _settle(e_tip, v_tip, t)
        swing = _SWING * math.sin(angle) + _settle(np.zeros(len(rest)), v_joint, t)
        q[rest] = start[rest] + swing
        before = q[chosen].copy()
        for _ in range(40):
            position, jacobian = kinematics(q)
            miss = target - position
            if float(np.abs(miss).max()) < 1e-10 * scale:
                break
            step = np.linalg.lstsq(jacobian[:, chosen], miss, rcond=None)[0]
            q[chosen] += np.clip(step, -0.5, 0.5)
        else:
            return 0.0, first
        if float(np.abs(q[chosen] - before).max()) > 0.5:
            return 0.0, first
        values = np.linalg.svd(jacobian[:, chosen], compute_uv=False)
        ratio = float(values[-1] / values[0]) if values[0] > 0 else 0.0
        first = ratio if math.isnan(first) else first
        worst = min(worst, ratio)
        if worst < enough:
            break
    return worst, first


def _tip_circle(
    bodies: Sequence[_Body], tip: str, start: np.ndarray, names: Sequence[str], notes: list[str]
) -> tuple[float, str, tuple[int, ...]]:
    """The default tip objective, kept clear of singularities: radius, plane, solved joints.

    The tip's position replaces the first three joints as outputs and follows a 0.1 m
    circle in the horizontal plane, unless that would take it near a singular
    configuration or out of reach. Then three other joints the tip depends on (the best
    conditioned at the start first: a Panda's shoulder and upper-arm roll are aligned at
    its zero pose), then a smaller circle or another plane, whichever first stays clear.
    Says which in ``notes``, with the margin.
    """
    kinematics = _Kinematics(bodies, tip, len(start))
    _, jacobian = kinematics(start)
    moving = [i for i in range(len(start)) if np.any(jacobian[:, i] != 0)]
    triples = [triple for triple in itertools.combinations(moving, 3) if triple != (0, 1, 2)]

    def conditioning(triple: tuple[int, ...]) -> float:
        values = np.linalg.svd(jacobian[:, list(triple)], compute_uv=False)
        return float(values[-1] / values[0]) if values[0] > 0 else 0.0

    triples.sort(key=conditioning, reverse=True)
    default = math.nan
    for radius in (0.1, 0.05, 0.02):
        for plane, axes in _PLANES.items():
            for solved in [(0, 1, 2), *triples[:6]]:
                # The default's margin is told whatever it is; another circle's only
                # if it keeps clear, so its run can stop once it does not.
                enough = SAFE_CONDITION if not math.isnan(default) else -math.inf
                margin, first = _circle_margin(kinematics, start, radius, axes, solved, enough)
                if math.isnan(default):
                    default = margin
                if margin < SAFE_CONDITION:
                    continue
                where = f"{radius:g} m circle in the {plane} plane about the start"
                if (radius, plane, solved) == (0.1, "x-y", (0, 1, 2)):
                    notes.append(
                        f"the default objective, the tip's {where}, keeps the tip Jacobian's "
                        f"inverse condition number >= {margin:.3g} along the run (margin; "
                        f"{first:.3g} at the start, {SAFE_CONDITION:g} required)"
                    )
                else:
                    joints = ", ".join(names[i] for i in solved)
                    notes.append(
                        "the default (the tip's 0.1 m circle in the x-y plane, replacing the "
                        "first three joints as outputs) would bring the tip Jacobian's inverse "
                        f"condition number to {default:.3g} (near a singularity or out of "
                        f"reach): the tip follows a {where}, replacing {joints} as outputs "
                        f"(margin {margin:.3g}, {SAFE_CONDITION:g} required)"
                    )
                return radius, plane, solved
    notes.append(
        "no tip circle of 0.1, 0.05 or 0.02 m about the start keeps clear of a singularity "
        f"(the default's margin is {default:.3g}, {SAFE_CONDITION:g} required): the default "
        "is kept; give a bent pose (--initial) or edit the objective"
    )
    return 0.1, "x-y", (0, 1, 2)


def _objective(
    bodies: Sequence[_Body],
    tip: str | None,
    q: Sequence[sp.Symbol],
    names: Sequence[str],
    start: Mapping[str, float],
    notes: list[str],
    report: Callable[[str], None],
) -> tuple[dict[str, str], dict[str, str], list[str]]:
    """The default objective's outputs, their targets (as signals) and its terms.

    Each joint the tip's position does not replace follows a slow sine about its start
    (``y_<joint>`` tracks ``r_<joint>``); with ``tip``, :func:`_tip_objective` comes first.
    """
    outputs: dict[str, str] = {}
    signals: dict[str, str] = {}
    terms: list[str] = []
    solved: tuple[int, ...] = ()
    if tip is not None:
        report("checking the default objective")
        outputs, signals, terms, solved = _tip_objective(bodies, tip, q, names, start, notes)
    for coordinate in (c for i, c in enumerate(names) if i not in solved):
        outputs[f"y_{coordinate}"] = coordinate
        signals[f"r_{coordinate}"] = f"{start[coordinate]!r} + {_SWING!r}*sin({_FREQUENCY!r}*t)"
        terms.append(f"(y_{coordinate} - r_{coordinate})**2")
    return outputs, signals, terms


def _tip_objective(
    bodies: Sequence[_Body],
    tip: str,
    q: Sequence[sp.Symbol],
    names: Sequence[str],
    start: Mapping[str, float],
    notes: list[str],
) -> tuple[dict[str, str], dict[str, str], list[str], tuple[int, ...]]:
    """The tip's position ``px, py, pz`` following the circle :func:`_tip_circle` keeps.

    Returns its outputs, their targets ``ox, oy, oz`` about the start (as signals), its
    terms, and the joints whose outputs it replaces.
    """
    radius, plane, solved = _tip_circle(bodies, tip, np.array(list(start.values())), names, notes)
    position = _position(bodies, _placements(bodies, q), tip)
    point = dict(zip(q, start.values(), strict=True))
    first, second = _PLANES[plane]
    motions = ["", "", ""]
    motions[first] = f"{radius!r}*cos({_FREQUENCY!r}*t)"
    motions[second] = f"{radius!r}*sin({_FREQUENCY!r}*t)"
    outputs: dict[str, str] = {}
    signals: dict[str, str] = {}
    terms: list[str] = []
    for axis, expr, motion in zip("xyz", position, motions, strict=True):
        centre = round(float(expr.xreplace(point)), 6)
        outputs[f"p{axis}"] = _text(expr)
        signals[f"o{axis}"] = f"{centre!r} + {motion}" if motion else repr(centre)
        terms.append(f"(p{axis} - o{axis})**2")
    return outputs, signals, terms, solved
