"""A spec from a robot's URDF file: a fixed-base serial chain in mass-matrix form.

:func:`spec_from_urdf` reads the file with ``yourdfpy`` (the ``urdf`` extra; the text
is XML, parsed strictly, and never executed), checks it where it enters as Pinocchio,
Drake and MuJoCo check theirs (a regular file of at most 1 MB, decoded before a DOCTYPE
is looked for; names unique once made spec names; finite origins, axes and limits;
positive masses; positive-definite inertias obeying the triangle inequality: see
:func:`_check_elements`), checks that it describes what the method can control (with a
tip, the joints beyond it are held fixed), and builds ``M(q)`` and the bias forces
symbolically by the recursive
Newton-Euler algorithm: the bias ``C(q, q') q' + g(q)`` is one pass at zero joint
acceleration, column ``j`` of ``M`` one pass at unit acceleration of joint ``j`` without
velocity and gravity. That is algebra on rotations and cross products, never a
derivative and never an inverse, and it is what Pinocchio computes numerically (the
tests compare the two). Every vector the algorithm forms is a named definition of the
spec (``[system.mechanics] definitions``), so that each stays a few operations long:
substituted into one another they would grow with the cube of the chain's length.

The spec it returns (see :func:`tvopt_codegen.mechanics.spec_toml` for its text) has
the movable joints as coordinates (``d<joint>`` their rates), a torque or force
``tau_<joint>`` per joint, every link's mass and inertia as named parameters
(``m_<link>``, ``Ixx_<link>``, ...) that ``--plant-param`` can perturb, and a quadratic
tracking objective to edit: each joint follows a slow sine about its start, or, with
``tip``, the tip link's position follows a circle in the horizontal plane (the tip's
``px, py, pz`` replace the first three joints as outputs, so that the outputs still
number the inputs). That circle is checked along the run the law makes (:func:`_tip_circle`):
where it would come near a singularity of the decoupling matrix or out of reach, three
other joints, a smaller circle or another plane is taken, and the notes say which.
"""

from __future__ import annotations

import codecs
import io
import itertools
import math
import os
import re
import stat
import warnings
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import sympy as sp

from tvopt_codegen.errors import BudgetError, SpecError
from tvopt_codegen.names import name_problem
from tvopt_codegen.spec.files import MAX_SPEC_BYTES
from tvopt_codegen.toml_shape import MAX_NESTING

__all__ = ["spec_from_urdf"]

#: The joint types of a fixed-base serial chain the import accepts.
_MOVABLE = ("revolute", "continuous", "prismatic")

#: Numbers this close to 0 or +-1 in a joint's placement are those (an rpy of pi/2 gives
#: cos = 6e-17): the expressions stay short and exact where the file meant exactness.
_SNAP = 1e-12

#: Most XML elements a URDF file may hold (the spec's own limits are on bytes and depth).
MAX_ELEMENTS = 200_000

#: Most joints the import drives. The Newton-Euler definitions grow with the square of
#: the chain and the derivation with more (20 joints: 13 s to import and 11 s to check;
#: 32 joints: 30 s and 90 s, on a loaded core): a longer chain is refused before any
#: algebra, with the exit code of a budget, rather than run for minutes.
MAX_JOINTS = 24

#: Most links the chain may carry, fixed ones included: each is a few vectors in every
#: Newton-Euler pass (a Panda with its hand is 12, a humanoid a hundred or so).
MAX_LINKS = 256

#: Relative tolerance of an inertia's triangle inequality (``Ixx + Iyy >= Izz`` of the
#: principal moments): files round their moments, a thin rod meets it with equality.
TRIANGLE_TOLERANCE = 1e-6

#: The default objective's circle is kept where the tip Jacobian (of the first three
#: joints) keeps at least this inverse condition number along the whole run.
SAFE_CONDITION = 0.05


@dataclass(frozen=True)
class _Body:
    """One link of the chain and the joint that carries it (fixed joints included)."""

    link: str
    joint: str
    kind: str  # revolute, prismatic or fixed (continuous is revolute)
    parent: int  # index of the parent body, -1 for the base
    rotation: sp.Matrix  # the joint frame in the parent's, at q = 0
    offset: sp.Matrix  # the joint frame's origin in the parent's
    axis: sp.Matrix  # unit axis in the joint frame
    mass: sp.Expr
    com: sp.Matrix  # centre of mass in the link frame
    inertia: sp.Matrix  # about the centre of mass, in the link frame
    coordinate: int  # index among the movable joints, -1 for fixed


def _fail(source: str, where: str, problem: str) -> SpecError:
    return SpecError(source, where, problem)


def _snap(value: float) -> sp.Expr:
    """A float of the file as an exact 0 or +-1 where it is one to rounding, else a Float."""
    if abs(value) < _SNAP:
        return sp.Integer(0)
    if abs(abs(value) - 1.0) < _SNAP:
        return sp.Integer(1 if value > 0 else -1)
    return sp.Float(repr(float(value)), 17)


def _matrix(values: np.ndarray) -> sp.Matrix:
    rows = values.shape[0]
    cols = values.shape[1] if values.ndim > 1 else 1
    return sp.Matrix(rows, cols, [_snap(float(v)) for v in values.ravel()])


def _identifier(name: str, prefix: str) -> str:
    """A spec name from a URDF name: other characters as ``_``, ``prefix`` if need be."""
    text = re.sub(r"[^A-Za-z0-9_]", "_", name).strip("_") or prefix
    if not text[0].isalpha():
        text = f"{prefix}_{text}"
    return text[:48]


class _NameTakenError(Exception):
    """A definition's name is a joint's or link's spec name (args: the owner, the problem)."""


class _Lets:
    """Named intermediate values, the spec's ``definitions``.

    Each non-trivial expression the algorithm forms gets a name, so that every one stays
    a few operations long.
    """

    def __init__(self, owners: Mapping[str, str]) -> None:
        self.items: list[tuple[str, sp.Expr]] = []
        self.owners = dict(owners)  # casefolded name: the URDF element that made it

    def __call__(self, name: str, expr: sp.Expr) -> sp.Expr:
        expr = sp.sympify(expr)
        if expr.is_Atom or (
            expr.is_Mul and len(expr.args) == 2 and expr.args[0].is_Number and expr.args[1].is_Atom
        ):
            return expr
        owner = self.owners.get(name.casefold())
        if owner is not None:
            raise _NameTakenError(
                owner,
                f"its spec name is {name!r}, which the import also gives one of its "
                "definitions: rename it",
            )
        self.owners[name.casefold()] = "an intermediate"
        self.items.append((name, expr))
        return sp.Symbol(name, real=True)

    def vector(self, name: str, vector: sp.Matrix) -> sp.Matrix:
        return sp.Matrix([self(f"{name}{axis}", e) for axis, e in zip("xyz", vector, strict=True)])


def _rodrigues(axis: sp.Matrix, c: sp.Expr, s: sp.Expr) -> sp.Matrix:
    """The rotation about the unit ``axis`` by the angle whose cosine and sine are given."""
    x, y, z = axis
    cross = sp.Matrix([[0, -z, y], [z, 0, -x], [-y, x, 0]])
    outer = axis * axis.T
    return c * sp.eye(3) + s * cross + (1 - c) * outer


def _read(path: Path) -> bytes:
    """The file's bytes, once it is known to be a regular file of bounded size.

    Opened without blocking and checked on the open descriptor: a FIFO would wait for a
    writer forever and ``/dev/zero`` never ends, and a check by name before opening
    could be raced by a rename.
    """
    source = str(path)
    flags = os.O_RDONLY | getattr(os, "O_NONBLOCK", 0) | getattr(os, "O_NOCTTY", 0)
    try:
        fd = os.open(path, flags)
    except OSError as exc:
        raise _fail(source, "(file)", f"cannot read: {exc.strerror or exc}") from None
    try:
        info = os.fstat(fd)
        if not stat.S_ISREG(info.st_mode):
            raise _fail(source, "(file)", f"is {_file_kind(info.st_mode)}, not a regular file")
        if info.st_size > MAX_SPEC_BYTES:
            raise _fail(
                source, "(file)", f"{info.st_size} bytes, larger than {MAX_SPEC_BYTES} bytes"
            )
        with os.fdopen(fd, "rb", closefd=False) as handle:
            data = handle.read(MAX_SPEC_BYTES + 1)
    except OSError as exc:
        raise _fail(source, "(file)", f"cannot read: {exc.strerror or exc}") from None
    finally:
        os.close(fd)
    if len(data) > MAX_SPEC_BYTES:  # it grew while it was read
        raise _fail(source, "(file)", f"larger than {MAX_SPEC_BYTES} bytes")
    return data


def _file_kind(mode: int) -> str:
    """What a file that is not a regular one is, in words."""
    kinds = (
        (stat.S_ISDIR, "a directory"),
        (stat.S_ISFIFO, "a FIFO (named pipe)"),
        (stat.S_ISCHR, "a character device"),
        (stat.S_ISBLK, "a block device"),
        (stat.S_ISSOCK, "a socket"),
    )
    return next((word for test, word in kinds if test(mode)), "a special file")


#: Byte-order marks, longest first (UTF-32 LE's begins with UTF-16 LE's).
_BOMS = (
    (codecs.BOM_UTF32_BE, "utf-32-be"),
    (codecs.BOM_UTF32_LE, "utf-32-le"),
    (codecs.BOM_UTF8, "utf-8"),
    (codecs.BOM_UTF16_BE, "utf-16-be"),
    (codecs.BOM_UTF16_LE, "utf-16-le"),
)

#: How ``<?`` or ``<`` begins a document without a mark (XML 1.0, appendix F).
_STARTS = (
    (b"\x00\x00\x00<", "utf-32-be"),
    (b"<\x00\x00\x00", "utf-32-le"),
    (b"\x00<\x00?", "utf-16-be"),
    (b"<\x00?\x00", "utf-16-le"),
)

_DECLARATION = re.compile(r"""\A\s*<\?xml\b[^>]*?\?>""")
_DECLARED = re.compile(r"""encoding\s*=\s*["']([A-Za-z0-9._-]+)["']""")


def _decode(data: bytes, source: str) -> str:
    """The document as text, in the encoding its mark, first bytes or declaration give.

    Everything later (the DOCTYPE refusal, the XML parser) reads this text, so that no
    encoding can hide a declaration from the check that the parser then sees.
    """
    encoding = next((name for mark, name in _BOMS if data.startswith(mark)), None)
    body = data
    if encoding is not None:
        body = data[len(next(mark for mark, name in _BOMS if name == encoding)) :]
    else:
        encoding = next((name for start, name in _STARTS if data.startswith(start)), None)
    if encoding is None:
        # EBCDIC writes "<?xm" as 4C 6F A7 94: its declaration is read in EBCDIC.
        head = data[:200].decode("cp500" if data.startswith(b"\x4c\x6f\xa7\x94") else "latin-1")
        declared = _DECLARATION.match(head)
        named = _DECLARED.search(declared.group(0)) if declared else None
        encoding = named.group(1) if named else "utf-8"
        try:
            codecs.lookup(encoding)
        except LookupError:
            raise _fail(source, "(file)", f"declares an unknown encoding {encoding!r}") from None
    try:
        text = body.decode(encoding)
    except (UnicodeDecodeError, LookupError) as exc:
        reason = getattr(exc, "reason", str(exc))
        raise _fail(source, "(file)", f"is not valid {encoding}: {reason}") from None
    return text.lstrip("\ufeff")


def _load(path: Path) -> tuple[Any, Any]:
    """The file's checked XML tree and the URDF model yourdfpy reads from it."""
    source = str(path)
    text = _decode(_read(path), source)
    if re.search(r"<!\s*(DOCTYPE|ENTITY)", text, re.IGNORECASE):
        # Entities expand (a billion laughs) or reach files (XXE): a robot needs neither.
        raise _fail(source, "(file)", "holds a DOCTYPE or ENTITY declaration, which is refused")
    if text.count("<") > MAX_ELEMENTS:
        raise _fail(source, "(file)", f"more than {MAX_ELEMENTS} XML elements")
    try:
        import yourdfpy  # noqa: PLC0415 - the urdf extra, on use
        from lxml import etree  # noqa: PLC0415 - yourdfpy's own XML library
    except ImportError:
        raise _fail(
            source, "(file)", "reading URDF needs yourdfpy: pip install 'tvopt-codegen[urdf]'"
        ) from None
    # The parser reads the decoded text, its declaration removed, as UTF-8: the bytes it
    # sees are those just checked, whatever the file's own encoding was.
    checked = _DECLARATION.sub("", text, count=1).encode("utf-8", "surrogatepass")
    # Well-formedness first, strictly: yourdfpy falls back to a recovering parser, which
    # would read a broken file as some other robot.
    parser = etree.XMLParser(
        resolve_entities=False, no_network=True, huge_tree=False, load_dtd=False
    )
    try:
        root = etree.fromstring(checked, parser=parser)
    except (etree.XMLSyntaxError, ValueError) as exc:
        raise _fail(source, "(file)", f"not well-formed XML: {exc}") from None
    tree = root.getroottree()
    if tree.docinfo.doctype or any(isinstance(node, etree._Entity) for node in root.iter()):
        raise _fail(source, "(file)", "holds a DOCTYPE or entity reference, which is refused")
    if root.tag != "robot":
        raise _fail(source, "(file)", f"the root element is <{root.tag}>, not <robot>")
    # The spec's nesting limit: a robot is a few levels deep.
    deepest = max((sum(1 for _ in node.iterancestors()) for node in root.iter()), default=0)
    if deepest > MAX_NESTING:
        raise _fail(source, "(file)", f"elements nest {deepest} deep (at most {MAX_NESTING})")
    _check_elements(root, source)
    try:
        # No meshes are read and no scene graph is built: the dynamics need neither. The
        # values are checked above; what yourdfpy or trimesh would warn of is not news.
        with warnings.catch_warnings(), np.errstate(all="ignore"):
            warnings.simplefilter("ignore")
            model = yourdfpy.URDF.load(
                io.BytesIO(checked),
                build_scene_graph=False,
                build_collision_scene_graph=False,
                load_meshes=False,
                load_collision_meshes=False,
            )
    except (ValueError, TypeError, AttributeError, KeyError, IndexError) as exc:
        raise _fail(source, "(file)", f"not a URDF robot: {exc}") from None
    return root, model.robot


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
    for kind, prefix in (("link", "link"), ("joint", "joint")):
        for number, element in enumerate(root.findall(kind), start=1):
            name = element.get("name")
            if name is None:
                raise _fail(source, f"{kind} #{number}", "has no name attribute")
            where = f"{kind} {name!r}"
            if name in seen[kind]:
                raise _fail(source, where, f"two {kind}s are named {name!r}")
            spec_name = _identifier(name, prefix).casefold()
            other = next((o for o, n in seen[kind].items() if n == spec_name), None)
            if other is not None:
                raise _fail(
                    source,
                    where,
                    f"{kind}s {other!r} and {name!r} both become {_identifier(name, prefix)!r} "
                    "in the spec (characters other than ASCII letters, digits and '_' become "
                    "'_', names are cut at 48 and compared ignoring case): rename one",
                )
            seen[kind][name] = spec_name
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


def _chain(
    robot: Any, source: str, tip: str | None
) -> tuple[list[_Body], list[str], dict[str, float]]:
    """The bodies in parent-first order, the driven joints in order, the held ones.

    The driven joints are named in chain order; the held ones map to their position.

    With ``tip``, only the joints between the base and the tip are driven: those beyond
    it or on side branches (a gripper's fingers, mimic joints among them) are held fixed.
    """
    links = {link.name: link for link in robot.links}
    joints = {joint.name: joint for joint in robot.joints}
    children: dict[str, list[Any]] = {}
    parents: dict[str, Any] = {}
    for joint in robot.joints:
        where = f"joint {joint.name!r}"
        if joint.type in ("floating", "planar"):
            raise _fail(
                source,
                where,
                f"a {joint.type} joint (a floating base) is not supported: fixed-base serial "
                "chains only",
            )
        if joint.type not in (*_MOVABLE, "fixed"):
            raise _fail(source, where, f"unknown joint type {joint.type!r}")
        for end in (joint.parent, joint.child):
            if end not in links:
                raise _fail(source, where, f"link {end!r} is not declared")
        if joint.child in parents:
            raise _fail(
                source,
                where,
                f"link {joint.child!r} has a second parent joint: a closed chain is not supported",
            )
        parents[joint.child] = joint
        children.setdefault(joint.parent, []).append(joint)
    roots = [name for name in links if name not in parents]
    if len(roots) != 1:
        found = ", ".join(roots[:4]) or "none: the joints form a loop"
        raise _fail(source, "(robot)", f"expected one root link, found {len(roots)} ({found})")
    driven_path: set[str] | None = None
    if tip is not None:
        if tip not in links or tip == roots[0]:
            raise _fail(source, "--tip", f"no link {tip!r} below the base")
        driven_path = set()
        link = tip
        while link in parents and len(driven_path) <= len(joints):
            driven_path.add(parents[link].name)
            link = parents[link].parent
    held = _held(joints, driven_path, source)
    moves = _moves(roots[0], children, held)
    bodies: list[_Body] = []
    movable: list[str] = []
    order: list[tuple[str, int]] = [(roots[0], -1)]
    seen = {roots[0]}
    while order:
        link_name, parent = order.pop(0)
        below = children.get(link_name, [])
        if sum(1 for j in below if moves[j.name]) > 1:
            raise _fail(
                source,
                f"link {link_name!r}",
                "has more than one moving branch: not a serial chain (with --tip, the "
                "joints off the way to the tip are held fixed)",
            )
        for joint in below:
            if joint.child in seen:
                raise _fail(source, f"joint {joint.name!r}", "closes a loop")
            seen.add(joint.child)
            driven = joint.type in _MOVABLE and joint.name not in held
            if driven and joint.mimic is not None:
                raise _fail(
                    source,
                    f"joint {joint.name!r}",
                    f"mimics {joint.mimic.joint!r}: a mimic joint is not driven on its own; "
                    "give a --tip before it to hold it fixed",
                )
            coordinate = len(movable) if driven else -1
            bodies.append(
                _body(joint, links[joint.child], parent, coordinate, source, held.get(joint.name))
            )
            if driven:
                movable.append(joint.name)
            order.append((joint.child, len(bodies) - 1))
    if len(seen) != len(links):
        raise _fail(source, "(robot)", "some links are not reached from the root: a loop")
    # A driven joint must move some mass (every mass has a positive-definite inertia, so
    # any one does): else its row of M is zero, and M singular everywhere.
    carries = [body.mass != 0 for body in bodies]
    for index in reversed(range(len(bodies))):
        if carries[index] and bodies[index].parent >= 0:
            carries[bodies[index].parent] = True
    for body, moved in zip(bodies, carries, strict=True):
        if body.coordinate >= 0 and not moved:
            raise _fail(
                source,
                f"joint {body.joint!r}",
                "moves no mass (every link beyond it has mass 0): M would be singular",
            )
    if not movable:
        raise _fail(source, "(robot)", "no revolute, continuous or prismatic joint to drive")
    return bodies, movable, held


def _rest(joint: Any) -> float:
    """Where a joint starts or is held: the middle of its limits, else 0.

    A continuous joint's limits are ignored, as the URDF format says.
    """
    limit = joint.limit
    low = getattr(limit, "lower", None)
    high = getattr(limit, "upper", None)
    if joint.type == "continuous" or low is None or high is None:
        return 0.0
    return 0.5 * (float(low) + float(high))


def _held(joints: Mapping[str, Any], path: set[str] | None, source: str) -> dict[str, float]:
    """The movable joints off the way to the tip, by name, at their held position.

    A joint is held at the middle of its limits; a mimic joint where its leader puts it
    (``multiplier * leader + offset``), its leader held too.
    """
    if path is None:
        return {}
    off = [j for j in joints.values() if j.type in _MOVABLE and j.name not in path]
    held = {j.name: _rest(j) for j in off if j.mimic is None}
    waiting = [j for j in off if j.mimic is not None]
    while waiting:
        ready = [j for j in waiting if j.mimic.joint in held]
        if not ready:
            joint = waiting[0]
            leader = joint.mimic.joint
            problem = (
                "a joint the tip needs: it cannot be held fixed"
                if leader in path
                else "no held joint (a mimic loop, or undeclared)"
            )
            raise _fail(source, f"joint {joint.name!r}", f"mimics {leader!r}, {problem}")
        for joint in ready:
            multiplier = 1.0 if joint.mimic.multiplier is None else float(joint.mimic.multiplier)
            offset = 0.0 if joint.mimic.offset is None else float(joint.mimic.offset)
            held[joint.name] = multiplier * held[joint.mimic.joint] + offset
            waiting.remove(joint)
    return held


def _moves(
    root: str, children: Mapping[str, list[Any]], held: Mapping[str, float]
) -> dict[str, bool]:
    """Whether each joint, or any joint below it, is driven, by joint name.

    Walked without recursion: a chain of thousands of fixed links is no deeper for it.
    """
    order: list[Any] = []
    stack = list(children.get(root, []))
    seen: set[str] = set()
    while stack:
        joint = stack.pop()
        if joint.name in seen:  # a loop: refused where the chain is walked
            continue
        seen.add(joint.name)
        order.append(joint)
        stack.extend(children.get(joint.child, []))
    moves: dict[str, bool] = {}
    for joint in reversed(order):  # every joint after the joints above it
        below = children.get(joint.child, [])
        moves[joint.name] = (joint.type in _MOVABLE and joint.name not in held) or any(
            moves.get(j.name, False) for j in below
        )
    return moves


def _turn(axis: np.ndarray, angle: float) -> np.ndarray:
    """The rotation by ``angle`` about the unit ``axis``, numerically."""
    x, y, z = axis
    cross = np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])
    c, s = math.cos(angle), math.sin(angle)
    return np.asarray(c * np.eye(3) + s * cross + (1 - c) * np.outer(axis, axis))


def _body(
    joint: Any, link: Any, parent: int, coordinate: int, source: str, held: float | None = None
) -> _Body:
    """One body: its joint's placement and axis, and its link's inertial parameters.

    A joint ``held`` fixed is a fixed joint whose placement includes its motion there.
    """
    origin = np.asarray(joint.origin if joint.origin is not None else np.eye(4), dtype=float)
    axis = np.asarray(joint.axis if joint.axis is not None else (1.0, 0.0, 0.0), dtype=float)
    if not np.all(np.isfinite(origin)):
        raise _fail(source, f"joint {joint.name!r}", "its origin is not finite")
    kind = {"continuous": "revolute"}.get(joint.type, joint.type)
    if joint.type in _MOVABLE:
        norm = float(np.linalg.norm(axis))
        if not np.isfinite(norm) or norm == 0.0:
            raise _fail(source, f"joint {joint.name!r}", "its axis is zero or not finite")
        axis = axis / norm
        if held is not None:
            origin = origin.copy()
            if kind == "revolute":
                origin[:3, :3] = origin[:3, :3] @ _turn(axis, held)
            else:
                origin[:3, 3] = origin[:3, 3] + origin[:3, :3] @ axis * held
            kind = "fixed"
    name = _identifier(link.name, "link")
    inertial = link.inertial
    mass: sp.Expr = sp.Integer(0)
    com = sp.zeros(3, 1)
    inertia = sp.zeros(3, 3)
    if inertial is not None and inertial.mass is not None and float(inertial.mass) > 0:
        placement = np.asarray(
            inertial.origin if inertial.origin is not None else np.eye(4), dtype=float
        )
        mass = sp.Symbol(f"m_{name}", real=True)
        com = _matrix(placement[:3, 3])
        entries = {
            key: sp.Symbol(f"I{key}_{name}", real=True)
            for key in ("xx", "yy", "zz", "xy", "xz", "yz")
        }
        own = sp.Matrix(
            [
                [entries["xx"], entries["xy"], entries["xz"]],
                [entries["xy"], entries["yy"], entries["yz"]],
                [entries["xz"], entries["yz"], entries["zz"]],
            ]
        )
        turn = _matrix(placement[:3, :3])
        inertia = own if turn == sp.eye(3) else turn * own * turn.T
    return _Body(
        link=link.name,
        joint=joint.name,
        kind=kind,
        parent=parent,
        rotation=_matrix(origin[:3, :3]),
        offset=_matrix(origin[:3, 3]),
        axis=_matrix(axis),
        mass=mass,
        com=com,
        inertia=inertia,
        coordinate=coordinate,
    )


def _inertial_values(robot: Any) -> dict[str, float]:
    """The file's mass and inertia entries, by parameter name."""
    values: dict[str, float] = {}
    where = {"xx": (0, 0), "yy": (1, 1), "zz": (2, 2), "xy": (0, 1), "xz": (0, 2), "yz": (1, 2)}
    for link in robot.links:
        inertial = link.inertial
        if inertial is None or inertial.mass is None or float(inertial.mass) <= 0:
            continue
        name = _identifier(link.name, "link")
        values[f"m_{name}"] = float(inertial.mass)
        matrix = np.asarray(inertial.inertia, dtype=float)
        for key, (i, j) in where.items():
            values[f"I{key}_{name}"] = float(matrix[i, j])
    return values


def _placements(
    bodies: Sequence[_Body],
    q: Sequence[sp.Expr],
    trig: Sequence[tuple[sp.Expr, sp.Expr]] | None = None,
) -> list[tuple[sp.Matrix, sp.Matrix]]:
    """Each body's frame in its parent's: the rotation ``E`` and the origin ``p``.

    ``trig`` gives each coordinate's cosine and sine (names of definitions); by default
    ``cos(q)`` and ``sin(q)`` themselves.
    """
    out = []
    for body in bodies:
        if body.kind == "revolute":
            i = body.coordinate
            c, s = trig[i] if trig is not None else (sp.cos(q[i]), sp.sin(q[i]))
            rotation = body.rotation * _rodrigues(body.axis, c, s)
            offset = body.offset
        elif body.kind == "prismatic":
            rotation = body.rotation
            offset = body.offset + body.rotation * body.axis * q[body.coordinate]
        else:
            rotation, offset = body.rotation, body.offset
        out.append((rotation, offset))
    return out


def _newton_euler(
    bodies: Sequence[_Body],
    placements: Sequence[tuple[sp.Matrix, sp.Matrix]],
    dq: Sequence[sp.Expr],
    ddq: Sequence[sp.Expr],
    gravity: sp.Matrix,
    let: _Lets,
    tag: str,
) -> list[sp.Expr]:
    """The joint forces of the recursive Newton-Euler algorithm, in body frames.

    Every vector it forms is named (``let``; ``tag`` ends each name): angular velocity
    ``om``, angular and linear acceleration ``al`` and ``ac``, and the force and torque
    ``fo`` and ``to`` that each body passes to its parent.
    """
    zero = sp.zeros(3, 1)
    omega: list[sp.Matrix] = []
    alpha: list[sp.Matrix] = []
    accel: list[sp.Matrix] = []
    for number, (body, (E, p)) in enumerate(zip(bodies, placements, strict=True), start=1):
        if body.parent < 0:
            w0, a0, v0 = zero, zero, -gravity
        else:
            w0, a0, v0 = omega[body.parent], alpha[body.parent], accel[body.parent]
        carried = E.T * w0
        linear = E.T * (v0 + a0.cross(p) + w0.cross(w0.cross(p)))
        angular = E.T * a0
        if body.kind == "revolute":
            spin = body.axis * dq[body.coordinate]
            w = carried + spin
            angular = angular + body.axis * ddq[body.coordinate] + carried.cross(spin)
        else:
            w = carried
            if body.kind == "prismatic":
                slide = body.axis * dq[body.coordinate]
                linear = linear + 2 * carried.cross(slide) + body.axis * ddq[body.coordinate]
        # The velocities are those of the bias pass alone (the mass matrix's have none).
        omega.append(let.vector(f"om{number}", w) if any(e != 0 for e in w) else w)
        alpha.append(let.vector(f"al{number}{tag}", angular))
        accel.append(let.vector(f"ac{number}{tag}", linear))
    force: list[sp.Matrix] = []
    torque: list[sp.Matrix] = []
    for body, w, a, v in zip(bodies, omega, alpha, accel, strict=True):
        centre = v + a.cross(body.com) + w.cross(w.cross(body.com))
        f = body.mass * centre
        force.append(f)
        torque.append(body.inertia * a + w.cross(body.inertia * w) + body.com.cross(f))
    for index in reversed(range(len(bodies))):
        force[index] = let.vector(f"fo{index + 1}{tag}", force[index])
        torque[index] = let.vector(f"to{index + 1}{tag}", torque[index])
        parent = bodies[index].parent
        if parent >= 0:
            E, p = placements[index]
            moved = E * force[index]
            force[parent] = force[parent] + moved
            torque[parent] = torque[parent] + E * torque[index] + p.cross(moved)
    out: list[sp.Expr] = [sp.Integer(0)] * len(dq)
    for body, f, n in zip(bodies, force, torque, strict=True):
        if body.kind == "revolute":
            out[body.coordinate] = (body.axis.T * n)[0]
        elif body.kind == "prismatic":
            out[body.coordinate] = (body.axis.T * f)[0]
    return out


def _position(
    bodies: Sequence[_Body], placements: Sequence[tuple[sp.Matrix, sp.Matrix]], link: str
) -> sp.Matrix:
    """The origin of ``link``'s frame in the base frame."""
    index = next(i for i, body in enumerate(bodies) if body.link == link)
    position = sp.zeros(3, 1)
    while index >= 0:
        E, p = placements[index]
        position = E * position + p
        index = bodies[index].parent
    return position


def _text(expr: sp.Expr) -> str:
    """An expression as spec text."""
    return str(sp.sstr(expr))


class _Kinematics:
    """The tip's position and its Jacobian at a configuration, numerically."""

    def __init__(self, bodies: Sequence[_Body], tip: str, n: int) -> None:
        index = next(i for i, body in enumerate(bodies) if body.link == tip)
        path: list[_Body] = []
        while index >= 0:
            path.append(bodies[index])
            index = bodies[index].parent
        self.n = n
        self.parts = [
            (
                np.array(body.rotation.tolist(), dtype=float),
                np.array(body.offset.tolist(), dtype=float).ravel(),
                np.array(body.axis.tolist(), dtype=float).ravel(),
                body.kind,
                body.coordinate,
            )
            for body in reversed(path)
        ]

    def __call__(self, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        turn = np.eye(3)
        at = np.zeros(3)
        axes: list[tuple[int, np.ndarray, np.ndarray | None]] = []
        for rotation, offset, axis, kind, coordinate in self.parts:
            at = at + turn @ offset
            turn = turn @ rotation
            if kind == "revolute":
                axes.append((coordinate, turn @ axis, at))
                turn = turn @ _turn(axis, float(q[coordinate]))
            elif kind == "prismatic":
                direction = turn @ axis
                axes.append((coordinate, direction, None))
                at = at + direction * float(q[coordinate])
        jacobian = np.zeros((3, self.n))
        for coordinate, direction, pivot in axes:
            jacobian[:, coordinate] = (
                direction if pivot is None else np.cross(direction, at - pivot)
            )
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
) -> tuple[float, float]:
    """The tip Jacobian's smallest inverse condition number along a run, and at its start.

    The run is the one the law makes exactly: each output is its target plus the error
    that the poles let decay from the start at rest, so the tip path is known without
    integrating. The three ``solved`` joints (those the tip's position replaces as
    outputs) are solved for along it by Newton's method from the previous point; the
    others are their own outputs. The Jacobian is the tip's with respect to the solved
    joints: the decoupling matrix is singular exactly where it is. An unreachable point,
    or a jump between two points (a change of branch), counts as 0.
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
                margin, first = _circle_margin(kinematics, start, radius, axes, solved)
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


def _owners(
    source: str,
    movable: Sequence[str],
    names: Sequence[str],
    robot: Any,
    values: Mapping[str, float],
) -> dict[str, str]:
    """Every spec name the import makes, casefolded, with the URDF element it comes from.

    Refused, naming both elements, when two elements make the same name: a joint
    ``m_arm`` and a link ``arm``'s mass, say.
    """
    owners: dict[str, str] = {}

    def claim(spec_name: str, owner: str) -> None:
        key = spec_name.casefold()
        if key in owners and owners[key] != owner:
            raise _fail(
                source,
                owner,
                f"its spec name {spec_name!r} is also made by {owners[key]}: rename one",
            )
        owners[key] = owner

    for joint, coordinate in zip(movable, names, strict=True):
        for candidate in (coordinate, f"d{coordinate}", f"tau_{coordinate}"):
            problem = name_problem(candidate)
            if problem:
                raise _fail(source, f"joint {joint!r}", problem)
            claim(candidate, f"joint {joint!r}")
    links = {_identifier(link.name, "link"): link.name for link in robot.links}
    for parameter in values:
        claim(parameter, f"link {links[parameter.split('_', 1)[1]]!r}")
    return owners


def spec_from_urdf(
    path: str | Path,
    *,
    tip: str | None = None,
    gravity: Sequence[float] = (0.0, 0.0, -9.81),
    name: str | None = None,
    initial: Mapping[str, float] | None = None,
    notes: list[str] | None = None,
    stage: Callable[[str], None] | None = None,
) -> dict[str, Any]:
    """The spec of a URDF robot in mass-matrix form (see the module docstring).

    Parameters
    ----------
    path : str or pathlib.Path
        The URDF file.
    tip : str, optional
        A link whose frame origin's position (``px, py, pz``) the objective tracks. The
        joints off the way from the base to it (a gripper's) are held fixed.
    gravity : sequence of 3 floats
        The gravity vector in the base frame.
    name : str, optional
        The spec's name (default: the robot's, made an identifier).
    initial : mapping of str to float, optional
        Initial joint positions by coordinate name (default: the middle of each joint's
        limits, else 0); the targets move about the pose they give.
    notes : list of str, optional
        Receives what the import decided for the user to know: the joints held fixed,
        the default objective's circle and its distance from a singularity.
    stage : callable, optional
        Called with the name of each stage as it starts (the command line names the
        stage a time budget stopped).

    Returns
    -------
    dict
        The spec as a mapping (:func:`tvopt_codegen.mechanics.spec_toml` writes it).

    Raises
    ------
    SpecError
        A file that is not a regular file of at most 1 MB, not well-formed, or holds a
        DOCTYPE; a link or joint whose name, mass, inertia, origin, axis or limits are
        refused (see :func:`_check_elements`); a floating base, a closed chain, a driven
        mimic joint, a branching chain, an unknown ``tip``: one line, naming the file,
        the element, the field and the value.
    BudgetError
        A chain of more than :data:`MAX_JOINTS` driven joints or :data:`MAX_LINKS`
        links, before any algebra.
    """
    path = Path(path)
    source = str(path)
    notes = [] if notes is None else notes
    report = stage or (lambda _stage: None)
    report("reading the URDF")
    _, robot = _load(path)
    report("checking the chain")
    bodies, movable, held = _chain(robot, source, tip)
    joints = {j.name: j for j in robot.joints}
    names = [_identifier(j, "joint") for j in movable]
    gravity = tuple(float(v) for v in gravity)
    if len(gravity) != 3 or not all(np.isfinite(gravity)):
        raise _fail(source, "--gravity", "expected three finite numbers")
    n = len(names)
    if len(bodies) + 1 > MAX_LINKS:
        raise BudgetError(
            source,
            "chain size",
            f"{len(bodies) + 1} links, more than the {MAX_LINKS} the derivation budget allows",
        )
    if n > MAX_JOINTS:
        raise BudgetError(
            source,
            "chain size",
            f"{n} driven joints, more than the {MAX_JOINTS} whose dynamics the derivation "
            "budget allows (give --tip a link nearer the base to hold the rest fixed)",
        )
    if held:
        listed = ", ".join(f"{joint} = {value:.6g}" for joint, value in held.items())
        notes.append(f"held fixed beyond or beside the tip {tip!r}: {listed}")
    values = _inertial_values(robot)
    owners = _owners(source, movable, names, robot, values)
    start: dict[str, float] = {
        coordinate: round(_rest(joints[joint]), 6)
        for coordinate, joint in zip(names, movable, strict=True)
    }
    for key, value in (initial or {}).items():
        if key in {_identifier(joint, "joint") for joint in held}:
            raise _fail(source, "--initial", f"{key!r} is held fixed beyond or beside the tip")
        if key not in start:
            raise _fail(source, "--initial", f"{key!r} is not a joint (joints: {', '.join(names)})")
        if not np.isfinite(value):
            raise _fail(source, "--initial", f"{key} = {value} is not finite")
        start[key] = float(value)
    if tip is not None and n < 3:
        raise _fail(source, "--tip", f"the chain has {n} joints; a tip position needs 3")
    q = [sp.Symbol(c, real=True) for c in names]
    dq = [sp.Symbol(f"d{c}", real=True) for c in names]
    let = _Lets(owners)
    try:
        trig = [
            (let(f"cos_{c}", sp.cos(qc)), let(f"sin_{c}", sp.sin(qc)))
            for c, qc in zip(names, q, strict=True)
        ]
        placements = _placements(bodies, q, trig)
        g = sp.Matrix([_snap(v) for v in gravity])
        report("Newton-Euler: bias forces")
        bias = _newton_euler(bodies, placements, dq, [sp.Integer(0)] * n, g, let, "")
        columns = []
        for j in range(n):
            report(f"Newton-Euler: column {j + 1} of {n} of M")
            columns.append(
                _newton_euler(
                    bodies,
                    placements,
                    [sp.Integer(0)] * n,
                    [sp.Integer(1 if i == j else 0) for i in range(n)],
                    sp.zeros(3, 1),
                    let,
                    f"_m{j + 1}",
                )
            )
    except _NameTakenError as exc:
        owner, problem = exc.args
        raise _fail(source, owner, problem) from None
    # The lower triangle, mirrored: M is symmetric by construction, and one expression per
    # pair keeps it symmetric in the text as well.
    mass = [[columns[min(i, j)][max(i, j)] for j in range(n)] for i in range(n)]
    outputs: dict[str, str] = {}
    signals: dict[str, str] = {}
    terms: list[str] = []
    tracked = names
    if tip is not None:
        report("checking the default objective")
        radius, plane, solved = _tip_circle(
            bodies, tip, np.array(list(start.values())), names, notes
        )
        position = _position(bodies, _placements(bodies, q), tip)
        point = dict(zip(q, start.values(), strict=True))
        first, second = _PLANES[plane]
        motions = ["", "", ""]
        motions[first] = f"{radius!r}*cos({_FREQUENCY!r}*t)"
        motions[second] = f"{radius!r}*sin({_FREQUENCY!r}*t)"
        for axis, expr, motion in zip("xyz", position, motions, strict=True):
            centre = round(float(expr.xreplace(point)), 6)
            outputs[f"p{axis}"] = _text(expr)
            signals[f"o{axis}"] = f"{centre!r} + {motion}" if motion else repr(centre)
            terms.append(f"(p{axis} - o{axis})**2")
        tracked = [c for i, c in enumerate(names) if i not in solved]
    for coordinate in tracked:
        outputs[f"y_{coordinate}"] = coordinate
        signals[f"r_{coordinate}"] = f"{start[coordinate]!r} + {_SWING!r}*sin({_FREQUENCY!r}*t)"
        terms.append(f"(y_{coordinate} - r_{coordinate})**2")
    spec_name = name or _identifier(robot.name or path.stem, "robot").lower()
    fixed = f"; held fixed: {', '.join(held)}" if held else ""
    description = (
        f"Imported from {path.name} by tvopt-codegen import-urdf: {n} joints "
        f"({', '.join(movable)}{fixed}); M(q) and the Coriolis, centrifugal and gravity forces "
        f"by the recursive Newton-Euler algorithm (gravity {list(gravity)}), its vectors "
        "as definitions; the links' masses and inertias as parameters. The objective is "
        "a quadratic tracking objective to edit."
    )
    spec: dict[str, Any] = {"name": spec_name, "description": description}
    spec["system"] = {
        "coordinates": names,
        "inputs": [f"tau_{c}" for c in names],
        "mechanics": {
            "rates": [f"d{c}" for c in names],
            "definitions": {key: _text(expr) for key, expr in let.items},
            "mass_matrix": [[_text(e) for e in row] for row in mass],
            "forces": [_text(-e) for e in bias],
            "input_matrix": [[1 if i == j else 0 for j in range(n)] for i in range(n)],
        },
        "outputs": outputs,
    }
    spec["parameters"] = values
    spec["signals"] = signals
    spec["objective"] = {"f0": " + ".join(terms)}
    spec["error_dynamics"] = {"poles": list(_POLES)}
    spec["simulation"] = {
        "t_final": _T_FINAL,
        "initial_state": {**start, **{f"d{c}": 0.0 for c in names}},
    }
    return spec
