"""A URDF file's elements checked where the file gives them: names, numbers, inertias, joints.

As Pinocchio, Drake and MuJoCo check theirs (see :func:`_check_elements`); every refusal
is one :class:`~tvopt_codegen.errors.SpecError` naming the link or joint, the field and
the value. The helpers the other steps of the import share (the refusal itself, spec
names from URDF names, the movable joint types) live here, at the bottom of the package.
"""

from __future__ import annotations

import math
import re
from typing import Any

import numpy as np

from tvopt_codegen.errors import SpecError

#: The joint types of a fixed-base serial chain the import accepts.
_MOVABLE = ("revolute", "continuous", "prismatic")

#: Relative tolerance of an inertia's triangle inequality (``Ixx + Iyy >= Izz`` of the
#: principal moments): files round their moments, a thin rod meets it with equality.
TRIANGLE_TOLERANCE = 1e-6


def _fail(source: str, where: str, problem: str) -> SpecError:
    return SpecError(source, where, problem)


def _identifier(name: str, prefix: str) -> str:
    """A spec name from a URDF name: other characters as ``_``, ``prefix`` if need be."""
    text = re.sub(r"[^A-Za-z0-9_]", "_", name).strip("_") or prefix
    if not text[0].isalpha():
        text = f"{prefix}_{text}"
    return text[:48]


#: A number as URDF writes one (no ``1_000``, no hex); ``nan`` and ``inf`` are read to be
#: named as not finite.
_NUMBER = re.compile(r"[+-]?(?:\d+\.?\d*|\.\d+)(?:[eE][+-]?\d+)?|[+-]?(?:nan|inf|infinity)", re.I)


def _numbers(
    element: Any, attribute: str, count: int, where: str, field: str, source: str
) -> list[float] | None:
    """``count`` finite numbers of an attribute, ``None`` if it is absent; else refused."""
    text = element.get(attribute)
    if text is None:
        return None
    parts = text.split()
    shown = f"{field} = {text.strip()!r}"
    if len(parts) != count or not all(_NUMBER.fullmatch(part) for part in parts):
        raise _fail(source, where, f"{shown}: expected {count} number{'s' * (count > 1)}")
    values = [float(part) for part in parts]
    if not all(math.isfinite(v) for v in values):
        raise _fail(source, where, f"{shown} is not finite")
    return values


def _origin(element: Any, where: str, prefix: str, source: str) -> None:
    """An ``<origin>``'s ``xyz`` and ``rpy``: three finite numbers each."""
    for origin in element.findall("origin"):
        for attribute in ("xyz", "rpy"):
            _numbers(origin, attribute, 3, where, f"{prefix}origin {attribute}", source)


def _check_elements(root: Any, source: str) -> None:
    """Every number the dynamics read, and every name, checked where the file gives it.

    As Pinocchio, Drake and MuJoCo check theirs: finite origins, masses and limits; a
    positive mass (zero only for a massless frame with no inertia); an inertia that is
    positive definite and obeys the triangle inequality; a movable joint's axis finite
    and non-zero; names unique, also once made spec names. Each refusal names the link
    or joint, the field and the value.
    """
    seen: dict[str, dict[str, str]] = {"link": {}, "joint": {}}
    # Each spec name's element, the other way round: a file's thousands of names are
    # checked in one pass, not one pass each (a spec name is refused the second time it
    # is made, so it has one owner).
    owner: dict[str, dict[str, str]] = {"link": {}, "joint": {}}
    for kind, prefix in (("link", "link"), ("joint", "joint")):
        for number, element in enumerate(root.findall(kind), start=1):
            name = element.get("name")
            if name is None:
                raise _fail(source, f"{kind} #{number}", "has no name attribute")
            where = f"{kind} {name!r}"
            if name in seen[kind]:
                raise _fail(source, where, f"two {kind}s are named {name!r}")
            spec_name = _identifier(name, prefix).casefold()
            other = owner[kind].get(spec_name)
            if other is not None:
                raise _fail(
                    source,
                    where,
                    f"{kind}s {other!r} and {name!r} both become {_identifier(name, prefix)!r} "
                    "in the spec (characters other than ASCII letters, digits and '_' become "
                    "'_', names are cut at 48 and compared ignoring case): rename one",
                )
            seen[kind][name] = spec_name
            owner[kind][spec_name] = name
    for link in root.findall("link"):
        _check_inertial(link, source)
    for joint in root.findall("joint"):
        _check_joint(joint, source)


def _check_inertial(link: Any, source: str) -> None:
    """A link's mass, centre of mass and inertia (see :func:`_check_elements`)."""
    where = f"link {link.get('name')!r}"
    inertials = link.findall("inertial")
    if len(inertials) > 1:
        raise _fail(source, where, f"has {len(inertials)} <inertial> elements, at most one")
    if not inertials:
        return
    inertial = inertials[0]
    _origin(inertial, where, "inertial ", source)
    mass_element = inertial.find("mass")
    mass = (
        None
        if mass_element is None
        else _numbers(mass_element, "value", 1, where, "inertial mass", source)
    )
    if mass is None:
        raise _fail(source, where, "inertial mass: no <mass value=...>")
    if mass[0] < 0:
        raise _fail(source, where, f"inertial mass = {mass[0]!r} is negative")
    keys = ("ixx", "ixy", "ixz", "iyy", "iyz", "izz")
    inertia = inertial.find("inertia")
    entries: dict[str, float] = {}
    for key in keys:
        given = (
            None if inertia is None else _numbers(inertia, key, 1, where, f"inertia {key}", source)
        )
        if given is not None:
            entries[key] = given[0]
    if mass[0] == 0:
        # A frame (a tool centre point, a flange): Pinocchio and the URDF format allow it.
        moving = {key: v for key, v in entries.items() if v != 0}
        if moving:
            key, nonzero = next(iter(moving.items()))
            raise _fail(
                source, where, f"inertia {key} = {nonzero!r} on a link of mass 0 (a massless "
                "frame has no inertia)",
            )  # fmt: skip
        return
    missing = [key for key in keys if key not in entries]
    if missing:
        raise _fail(source, where, f"inertia {missing[0]}: missing (a mass needs all six)")
    matrix = np.array(
        [
            [entries["ixx"], entries["ixy"], entries["ixz"]],
            [entries["ixy"], entries["iyy"], entries["iyz"]],
            [entries["ixz"], entries["iyz"], entries["izz"]],
        ]
    )
    shown = ", ".join(f"{key}={entries[key]!r}" for key in keys)
    moments = np.linalg.eigvalsh(matrix)
    if not moments[0] > 0:
        raise _fail(
            source, where, f"inertia ({shown}) is not positive definite (principal moments "
            f"{', '.join(f'{m:.6g}' for m in moments)})",
        )  # fmt: skip
    # Principal moments obey a + b >= c: the second moments of the mass, tr/2 - moment,
    # are never negative.
    slack = float(moments.sum() / 2 - moments[-1])
    if slack < -TRIANGLE_TOLERANCE * float(moments.sum()):
        raise _fail(
            source, where, f"inertia ({shown}) breaks the triangle inequality: principal "
            f"moments {moments[0]:.6g} + {moments[1]:.6g} < {moments[2]:.6g}",
        )  # fmt: skip


def _check_joint(joint: Any, source: str) -> None:
    """A joint's placement, axis, limits and mimic (see :func:`_check_elements`)."""
    where = f"joint {joint.get('name')!r}"
    kind = joint.get("type")
    _origin(joint, where, "", source)
    if kind in _MOVABLE:
        for axis in joint.findall("axis"):
            xyz = _numbers(axis, "xyz", 3, where, "axis xyz", source)
            if xyz is not None and not any(xyz):
                raise _fail(source, where, f"axis xyz = {axis.get('xyz').strip()!r} is zero")
    for limit in joint.findall("limit"):
        # A continuous joint's position limits are ignored, as the URDF format says.
        bounds = () if kind == "continuous" else ("lower", "upper")
        values = {
            key: _numbers(limit, key, 1, where, f"limit {key}", source)
            for key in (*bounds, "effort", "velocity")
        }
        low, high = values.get("lower"), values.get("upper")
        if kind in _MOVABLE and low is not None and high is not None and low[0] > high[0]:
            raise _fail(source, where, f"limit lower = {low[0]!r} is above upper = {high[0]!r}")
    for mimic in joint.findall("mimic"):
        for key in ("multiplier", "offset"):
            _numbers(mimic, key, 1, where, f"mimic {key}", source)
