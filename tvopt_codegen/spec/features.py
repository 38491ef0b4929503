"""The feature matrix: which features of a spec combine, and why the others do not.

One table, three readers: :func:`refuse` stops a derivation whose spec combines two
features that do not combine (one line naming both and why, exit 3), ``check`` prints the
targets a derived spec cannot run on (:func:`target_notes`), ``docs/features.md`` is
:func:`markdown` of the same data, and ``tests/test_feature_matrix.py`` walks every pair of
feature values through the strength-2 covering cases of :func:`covering_cases`.

A feature is an axis and one of its values (``("plant", "mechanics")``). A pair of values
of two axes either works, is refused (:data:`REFUSALS`: the reason is mathematical or a
missing piece the refusing target names), or is a known failure (:data:`KNOWN_FAILURES`:
a bug with a reproducer, tested as a strict expected failure until its fix lands).
"""

from __future__ import annotations

import itertools
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Protocol

from tvopt_codegen.errors import AssumptionError

if TYPE_CHECKING:
    from tvopt_codegen.spec import Spec


class Chains(Protocol):
    """What the table reads of the closed-loop stage: its padding chains."""

    @property
    def padding(self) -> Sequence[Sequence[str]]:
        """The padding chains' state names, per output (empty where none)."""


class Derived(Protocol):
    """What the table reads of a derivation: its spec and its padding chains.

    A protocol, not ``Derivation``: the derivation refuses pairs through this module,
    which therefore must not import it back (tests/test_architecture.py).
    """

    @property
    def spec(self) -> Spec:
        """The spec derived."""

    @property
    def closed_loop(self) -> Chains:
        """The closed-loop stage (``Derivation.closed_loop``)."""


#: A feature: an axis of the matrix and one of its values.
Feature = tuple[str, str]


@dataclass(frozen=True)
class Axis:
    """One axis of the matrix.

    Attributes
    ----------
    name : str
        Its key (``plant``, ``extension``, ...).
    title : str
        What the documentation calls it.
    values : tuple of (str, str)
        Each value and how a spec (or a user) writes it; the first is the default, the
        value every spec without the feature has.
    """

    name: str
    title: str
    values: tuple[tuple[str, str], ...]

    @property
    def keys(self) -> tuple[str, ...]:
        """The values' keys, default first."""
        return tuple(key for key, _ in self.values)


_OFF = ("no", "not used")

#: The axes, in the order of the documentation. ``target`` is where the law runs; every
#: other axis is read from the spec (padding: from the derivation).
AXES: tuple[Axis, ...] = (
    Axis(
        "plant",
        "plant form",
        (
            ("dynamics", "`[system.dynamics]`: x' = f(x) + G(x) u"),
            ("mechanics", "`[system.mechanics]`: M(q) q'' = F(q, q') + B(q) u"),
        ),
    ),
    Axis(
        "extension",
        "dynamic extension",
        (
            ("none", "no `[extension]`"),
            ("declared", "`[extension] integrate = { u = 1 }`"),
            ("auto", "`[extension] auto = true`, or `--extension auto`"),
        ),
    ),
    Axis(
        "padding",
        "padding chains",
        (_OFF, ("yes", "outputs of unequal relative degree, padded with integrator chains")),
    ),
    Axis("integral", "integral action", (_OFF, ("yes", "`[robust] integral = true`"))),
    Axis("observer", "disturbance observer", (_OFF, ("yes", "`[robust.observer] bandwidth`"))),
    Axis("eso", "extended-state observer", (_OFF, ("yes", "`[robust.eso] bandwidth`"))),
    Axis("limits", "actuator limits", (_OFF, ("yes", "`[limits]`, `[limits.rate]`"))),
    Axis("references", "references", (_OFF, ("yes", "`[references]` (the `*_refs` examples)"))),
    Axis("equality", "equality constraints", (_OFF, ("yes", '`[constraints] a = "lhs == rhs"`'))),
    Axis(
        "inequality",
        "inequality constraints",
        (_OFF, ("yes", '`[constraints] g = "lhs <= rhs"` (or `>=`)')),
    ),
    Axis(
        "target",
        "target",
        (
            ("python", "the Python module (`generate --backend python`)"),
            ("c", "the C library and its Python wrapper (`--backend c`)"),
            ("controller", "the stateful `Controller` (Python and C)"),
            ("fmu", "the co-simulation FMU (`export --fmu`)"),
            ("nlsys", "`tvopt_codegen.interop.to_nlsys` (python-control)"),
            ("sweep", "`sweep` (the compiled closed loop)"),
        ),
    ),
)

_AXIS = {axis.name: axis for axis in AXES}
#: The axes a spec (and its derivation) decides; ``target`` is chosen by the command.
SPEC_AXES: tuple[str, ...] = tuple(axis.name for axis in AXES if axis.name != "target")

_LABELS: dict[Feature, str] = {
    ("plant", "dynamics"): "[system.dynamics]",
    ("plant", "mechanics"): "[system.mechanics]",
    ("extension", "none"): "no extension",
    ("extension", "declared"): "[extension] integrate",
    ("extension", "auto"): "[extension] auto",
    ("padding", "yes"): "padding chains",
    ("integral", "yes"): "[robust] integral",
    ("observer", "yes"): "[robust.observer]",
    ("eso", "yes"): "[robust.eso]",
    ("limits", "yes"): "[limits]",
    ("references", "yes"): "[references]",
    ("equality", "yes"): "equality constraints",
    ("inequality", "yes"): "inequality constraints",
    ("target", "python"): "the Python module",
    ("target", "c"): "the C backend",
    ("target", "controller"): "the stateful Controller",
    ("target", "fmu"): "the FMU",
    ("target", "nlsys"): "to_nlsys",
    ("target", "sweep"): "sweep",
}


def label(feature: Feature) -> str:
    """How messages and the documentation name a feature (``[system.mechanics]``)."""
    return _LABELS.get(feature, f"{feature[0]} {feature[1]}")


@dataclass(frozen=True)
class Refusal:
    """Two features that do not combine, and why.

    Attributes
    ----------
    first, second : Feature
        The two features (``first``'s axis comes first in :data:`AXES`).
    reason : str
        Why, in one clause: the mathematics, or the piece that is missing.
    field : str
        The spec field the refusal is attributed to in the error.
    """

    first: Feature
    second: Feature
    reason: str
    field: str

    @property
    def line(self) -> str:
        """The one line ``check`` and the commands print: both features, then why."""
        return f"{label(self.first)} with {label(self.second)}: {self.reason}"


@dataclass(frozen=True)
class KnownFailure:
    """A pair that should work and does not yet: a bug, with where it is being fixed.

    Attributes
    ----------
    first, second : Feature
        The two features.
    symptom : str
        What goes wrong, measured.
    where : str
        The files the fix belongs in.
    """

    first: Feature
    second: Feature
    symptom: str
    where: str


#: Every pair that does not combine. The mathematics decides the first three (two
#: observers of one mismatch; a mass-matrix plant's prolonged inputs and padding); the
#: last is a piece the sweep lacks (its compiled loop has no source of reference samples).
REFUSALS: tuple[Refusal, ...] = (
    Refusal(
        ("observer", "yes"),
        ("eso", "yes"),
        "both estimate the plant's mismatch and cancel it, one on the inputs and one at the "
        "outputs' top derivatives: each would see the other's cancellation as a disturbance "
        "to cancel; keep one (docs/robust.md says which suits a plant)",
        "robust.eso",
    ),
    Refusal(
        ("plant", "mechanics"),
        ("extension", "declared"),
        "a prolonged input raises the outputs' relative degree to 3, and their third "
        "derivative holds d/dt (M(q)^-1 (F + B u)), a derivative of M^-1 that the "
        "mass-matrix form never forms (M is factored at run time); write the plant in "
        "[system.dynamics] to prolong an input",
        "extension.integrate",
    ),
    Refusal(
        ("plant", "mechanics"),
        ("padding", "yes"),
        "padding chains need outputs of unequal relative degree, and outputs h(q) of a "
        "mass-matrix plant have relative degree 2 or need the derivative of M^-1, which is "
        "factored at run time and never differentiated; write the plant in "
        "[system.dynamics] for outputs of higher relative degree",
        "system.outputs",
    ),
    Refusal(
        ("references", "yes"),
        ("target", "sweep"),
        "the sweep's compiled closed loop has no source of reference samples; sweep the "
        "spec with the references' nominal closed forms as [signals]",
        "references",
    ),
)

#: Working pairs whose meaning is narrower than either feature alone.
NOTES: tuple[tuple[Feature, Feature, str], ...] = (
    (
        ("plant", "mechanics"),
        ("extension", "auto"),
        "the search has one candidate, no prolongation (a prolonged input would need the "
        "derivative of M^-1): a fully actuated robot takes it, and outputs that need more "
        "are refused with the padding line",
    ),
    (
        ("observer", "yes"),
        ("target", "sweep"),
        "the observer runs in the stateful controller, so the sweep needs `--sample-time`",
    ),
)

#: Pairs that fail today where they should work, each with its reproducer in
#: ``tests/test_feature_matrix.py`` (a strict expected failure: it fails loudly once fixed).
KNOWN_FAILURES: tuple[KnownFailure, ...] = ()


def _key(a: Feature, b: Feature) -> frozenset[Feature]:
    return frozenset((a, b))


_REFUSED = {_key(r.first, r.second): r for r in REFUSALS}
_KNOWN = {_key(k.first, k.second): k for k in KNOWN_FAILURES}


def refusal(a: Feature, b: Feature) -> Refusal | None:
    """The refusal of the pair ``a``, ``b`` (in either order), or None."""
    return _REFUSED.get(_key(a, b))


def known_failure(a: Feature, b: Feature) -> KnownFailure | None:
    """The known failure of the pair ``a``, ``b`` (in either order), or None."""
    return _KNOWN.get(_key(a, b))


def pairs() -> list[tuple[Feature, Feature]]:
    """Every pair of values of two different axes, in the order of :data:`AXES`."""
    out = []
    for i, first in enumerate(AXES):
        for second in AXES[i + 1 :]:
            out += [((first.name, a), (second.name, b)) for a in first.keys for b in second.keys]
    return out


def status(a: Feature, b: Feature) -> str:
    """``works``, ``refused`` or ``known failure``."""
    if refusal(a, b) is not None:
        return "refused"
    return "known failure" if known_failure(a, b) is not None else "works"


# ------------------------------------------------------------------ what a spec uses


def spec_features(spec: Spec) -> dict[str, str]:
    """The value of every axis a spec decides before its derivation (not padding, target)."""
    constraints = (*spec.constraints, *spec.equalities)
    if spec.extension_auto:
        extension = "auto"
    elif any(count > 0 for _, count in spec.extension):
        extension = "declared"
    else:
        extension = "none"

    def used(flag: bool) -> str:
        return "yes" if flag else "no"

    return {
        "plant": "mechanics" if spec.mechanics is not None else "dynamics",
        "extension": extension,
        "integral": used(spec.robust.integral),
        "observer": used(spec.robust.observer is not None),
        "eso": used(spec.robust.eso is not None),
        "limits": used(bool(spec.limits)),
        "references": used(bool(spec.references)),
        "equality": used(any(c.op == "==" for c in constraints)),
        "inequality": used(any(c.op != "==" for c in constraints)),
    }


def derivation_features(derivation: Derived) -> dict[str, str]:
    """Every axis but the target, padding included (from the derivation's chains)."""
    found = spec_features(derivation.spec)
    found["padding"] = "yes" if any(derivation.closed_loop.padding) else "no"
    return found


def refusals(features: Mapping[str, str]) -> list[Refusal]:
    """The refusals whose two features are both in ``features`` (axis to value)."""
    return [
        r
        for r in REFUSALS
        if features.get(r.first[0]) == r.first[1] and features.get(r.second[0]) == r.second[1]
    ]


def refuse(spec: Spec) -> None:
    """Stop a spec that combines two features that do not combine, before deriving it.

    Raises
    ------
    AssumptionError
        For the first refusal that applies: the line names both features and why.
    """
    for found in refusals(spec_features(spec)):
        raise AssumptionError(spec.source, found.field, found.line)


def refusal_line(a: Feature, b: Feature) -> str:
    """The refusal's line for a pair that the table refuses (where the derivation finds it)."""
    found = refusal(a, b)
    assert found is not None, (a, b)
    return found.line


def target_notes(derivation: Derived) -> list[str]:
    """What ``check`` prints: one line per target that refuses this spec."""
    found = derivation_features(derivation)
    return [
        f"not for {label(('target', value))}: {r.line}"
        for value in _AXIS["target"].keys
        for r in refusals({**found, "target": value})
    ]


# ------------------------------------------------------------------ the covering cases


@dataclass(frozen=True)
class Case:
    """One spec of the covering array, and the targets it is run on.

    Attributes
    ----------
    features : tuple of (str, str)
        Each spec axis and its value, in the order of :data:`SPEC_AXES`.
    targets : tuple of str
        The targets the case runs on (the Python module always: it is what the oracle
        checks).
    """

    features: tuple[Feature, ...]
    targets: tuple[str, ...]

    def value(self, axis: str) -> str:
        """The case's value on ``axis``."""
        return dict(self.features)[axis]

    def holds(self, a: Feature, b: Feature) -> bool:
        """Whether the case combines ``a`` and ``b`` (a target counts when the case runs it)."""
        values = dict(self.features)
        return all(
            f[1] in self.targets if f[0] == "target" else values[f[0]] == f[1] for f in (a, b)
        )


def _allowed(a: Feature, b: Feature) -> bool:
    return status(a, b) == "works"


#: Targets run on every case: the Python module (the oracle's reference) and its stateful
#: Controller, which only wraps it.
EVERY_CASE_TARGETS = ("python", "controller")


def covering_cases() -> tuple[Case, ...]:
    """A strength-2 covering array of every working pair, computed deterministically.

    The spec axes are covered greedily (each new case starts from the first pair not yet
    covered and takes, axis by axis, the value that covers most new pairs with the values
    already chosen, never a pair that does not work). Then each target is given the fewest
    cases, greedily, in which every working value of every spec axis meets it.
    """
    axes = [_AXIS[name] for name in SPEC_AXES]
    todo = {
        frozenset(p)
        for p in pairs()
        if p[0][0] != "target" and p[1][0] != "target" and _allowed(*p)
    }
    rows: list[dict[str, str]] = []
    while todo:
        start = min(todo, key=lambda p: sorted(_order(f) for f in p))
        row = dict(start)
        for axis in axes:
            if axis.name in row:
                continue
            best, gain = axis.keys[0], -1
            for value in axis.keys:
                feature = (axis.name, value)
                if not all(_allowed(feature, other) for other in row.items()):
                    continue
                new = sum(frozenset((feature, other)) in todo for other in row.items())
                if new > gain:
                    best, gain = value, new
            row[axis.name] = best
        todo -= {frozenset(p) for p in itertools.combinations(row.items(), 2)}
        rows.append(row)
    targets: list[set[str]] = [set(EVERY_CASE_TARGETS) for _ in rows]
    for target in _AXIS["target"].keys:
        if target in EVERY_CASE_TARGETS:
            continue
        feature = ("target", target)
        need = {
            (axis.name, v) for axis in axes for v in axis.keys if _allowed(feature, (axis.name, v))
        }
        usable = [i for i, row in enumerate(rows) if all(_allowed(feature, f) for f in row.items())]
        while need:
            pick = max(usable, key=lambda i: (len(need & set(rows[i].items())), -i))
            if not need & set(rows[pick].items()):
                raise AssertionError(f"no case holds {sorted(need)} with {target}")
            need -= set(rows[pick].items())
            targets[pick].add(target)
    order = _AXIS["target"].keys
    return tuple(
        Case(
            tuple((name, row[name]) for name in SPEC_AXES),
            tuple(t for t in order if t in chosen),
        )
        for row, chosen in zip(rows, targets, strict=True)
    )


def _order(feature: Feature) -> tuple[int, int]:
    """Where a feature stands in :data:`AXES` (axis, then value)."""
    names = [axis.name for axis in AXES]
    axis = names.index(feature[0])
    return axis, AXES[axis].keys.index(feature[1])


def case_of(a: Feature, b: Feature, cases: Sequence[Case] | None = None) -> int:
    """The index of the first covering case that holds the working pair ``a``, ``b``."""
    for index, case in enumerate(covering_cases() if cases is None else cases):
        if case.holds(a, b):
            return index
    raise KeyError((a, b))


# ------------------------------------------------------------------ the documentation


def _cell(a: Feature, b: Feature) -> str:
    found = status(a, b)
    return {"works": "yes", "refused": "**no**", "known failure": "*bug*"}[found]


def markdown() -> str:
    """``docs/features.md``: the axes, the pairwise table, the refusals and known failures."""
    lines = [
        "# Which features combine",
        "",
        "<!-- generated by `python -m tvopt_codegen.spec.features` from "
        "tvopt_codegen/spec/features.py "
        "(`make features-doc`); do not edit -->",
        "",
        "Every pair of the features below either works, or is refused up front: for two "
        "features of the spec, `check`, `generate`, `simulate`, `report`, `export` and "
        "`sweep` (and `derive` in Python) stop with one line naming both features and why "
        "(exit 3), before anything is written; a target that refuses a spec says so itself "
        "(the sweep: exit 2), and `check` lists it (`not for sweep: ...`). The same table "
        "drives the refusals and `tests/test_feature_matrix.py`, which runs a strength-2 "
        "covering array of specs (every working pair of values meets in at least one of "
        "them) through the closed loop and its certificate, the independent oracle of "
        "`tests/oracle.py`, and the targets.",
        "",
        "## The features",
        "",
        "| axis | value | written |",
        "|---|---|---|",
    ]
    for axis in AXES:
        for key, text in axis.values:
            lines.append(f"| {axis.title} | `{key}` | {text} |")
    lines += [
        "",
        "## Pairs",
        "",
        "`yes`: works (a covering case runs it); **no**: refused (below); *bug*: should work "
        "and does not yet (below). Pairs with a default value (`none`, `no`, the "
        "Python module) are left out of the table but not of the tests: the covering "
        "cases hold them too, and a known failure among them is listed below.",
        "",
    ]
    used = [(axis.name, v) for axis in AXES for v in axis.keys[1:]]
    used = [("plant", "mechanics"), *[f for f in used if f[0] != "plant"]]
    header = [label(f) for f in used]
    lines.append("| | " + " | ".join(header) + " |")
    lines.append("|---|" + "---|" * len(used))
    for row in used:
        cells = ["-" if row[0] == col[0] else _cell(row, col) for col in used]
        lines.append(f"| {label(row)} | " + " | ".join(cells) + " |")
    lines += ["", "## Refused, and why", ""]
    for r in REFUSALS:
        lines.append(f"- **{label(r.first)} with {label(r.second)}**: {r.reason}.")
    lines += ["", "## Working, with a note", ""]
    for first, second, note in NOTES:
        lines.append(f"- **{label(first)} with {label(second)}**: {note}.")
    lines += ["", "## Known failures", ""]
    if KNOWN_FAILURES:
        for k in KNOWN_FAILURES:
            lines.append(
                f"- **{label(k.first)} with {label(k.second)}**: {k.symptom} (fix in {k.where})."
            )
    else:
        lines.append("None.")
    cases = covering_cases()
    lines += [
        "",
        "## The covering cases",
        "",
        f"{len(cases)} specs hold every working pair; "
        "`tests/test_feature_matrix.py` builds each and runs it on its targets.",
        "",
        "| case | " + " | ".join(SPEC_AXES) + " | targets |",
        "|---|" + "---|" * (len(SPEC_AXES) + 1),
    ]
    for index, case in enumerate(cases):
        values = " | ".join(v for _, v in case.features)
        lines.append(f"| {index} | {values} | {', '.join(case.targets)} |")
    return "\n".join(lines) + "\n"


def _main(argv: Iterable[str] = ()) -> int:
    """Print :func:`markdown` (``python -m tvopt_codegen.spec.features > docs/features.md``)."""
    del argv
    print(markdown(), end="")
    return 0


if __name__ == "__main__":
    raise SystemExit(_main())
