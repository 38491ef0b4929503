"""A differential fuzzer: random plants of known structure, each with random features.

Three kinds of case (``docs/fuzz.md``):

- ``system``: control-affine chains of integrators of random, unequal lengths, in
  strict-feedback form with nonvanishing gains, written in random smooth coordinates, with
  upper-triangular input coupling (so the vector relative degree is the chain lengths and
  R is nonsingular everywhere); with ``unicycle`` a forward-speed input that needs a
  dynamic extension (declared or ``auto``).
- ``arm``: a planar serial arm of 1-3 links with random lengths, masses and inertias,
  built with SymPy mechanics and entering through ``spec_from_sympy``.
- ``urdf``: a random URDF chain (revolute, continuous, prismatic joints, random axes,
  placements and inertials, a fixed link sometimes), entering through ``spec_from_urdf``
  (or the ``import-urdf`` command); its M(q) and bias forces are checked against
  Pinocchio.

Each gets a random strongly convex time-varying objective and a random subset of the
features ``integral``, ``observer``, ``limits``, ``references``, ``inequality``,
``equality`` and ``eso`` (never with ``observer``: that pair is refused). The oracles: the
law (``control``, ``rhs``, ``optimality_error``) against
the independent :class:`tests.oracle.Oracle`; on a sample of cases the C module against
the Python one (functions and the stateful ``Controller``) and the FMU under FMPy against
the Python ``Controller``. A case ends in :data:`AGREES` or a documented refusal
(``SpecError`` or ``AssumptionError`` with a one-line message); anything else is a failure.

A case is a short string, ``kind:size:features:seed`` (``system:2:integral+c:1234``): all
its numbers come from ``numpy.random.default_rng(seed)``, so the string replays it. The
structure (kind, size, features, whether C or the FMU run) is drawn by ``hypothesis``;
``python -m tests.fuzzing --cases N --seed S`` (``make fuzz``) draws N cases with
hypothesis' generator seeded by S, and ``--case STRING`` replays one.
"""

from __future__ import annotations

import argparse
import contextlib
import math
import os
import sys
import tempfile
import time
import traceback
import zlib
from collections import Counter
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from types import ModuleType
from typing import Any

import numpy as np
import sympy as sp

KINDS = ("system", "arm", "urdf")
FEATURES = ("integral", "observer", "limits", "references", "inequality", "equality", "eso")
#: Which implementations a case runs besides the Python module and the oracle.
TARGETS = ("c", "fmu", "cli", "unicycle", "auto")
AGREES = "agrees"


@dataclass(frozen=True)
class Case:
    """One fuzz case; ``str(case)`` is its replayable name."""

    kind: str
    size: int
    features: frozenset[str]
    seed: int

    def __str__(self) -> str:
        flags = "+".join(sorted(self.features)) or "-"
        return f"{self.kind}:{self.size}:{flags}:{self.seed}"

    def rng(self, stream: int = 0) -> np.random.Generator:
        """The case's numbers: from its seed and its structure together.

        Hypothesis draws small seeds often (0 above all); mixed with the structure, two
        cases that share a seed still get different plants.
        """
        shape = zlib.crc32(f"{self.kind}:{self.size}:{sorted(self.features)}".encode())
        return np.random.default_rng([self.seed, shape, stream])

    @classmethod
    def parse(cls, text: str) -> Case:
        """The case a string of :meth:`__str__` names."""
        kind, size, flags, seed = text.strip().split(":")
        features = frozenset() if flags == "-" else frozenset(flags.split("+"))
        unknown = features - set(FEATURES) - set(TARGETS)
        if kind not in KINDS or unknown:
            raise ValueError(f"not a fuzz case: {text!r}")
        return cls(kind, int(size), features, int(seed))


class DisagreementError(AssertionError):
    """Two implementations (or one and the oracle) computed different numbers."""


# --------------------------------------------------------------------------- numbers


def _num(rng: np.random.Generator, low: float, high: float) -> sp.Rational:
    """A two-decimal number in [low, high], exact, so the spec text is short."""
    return sp.Rational(f"{rng.uniform(low, high):.2f}")


def _text(expr: sp.Expr) -> str:
    return str(sp.sympify(expr))


def _signal(rng: np.random.Generator, centre: float = 0.0) -> str:
    """A smooth target in t: a sine about ``centre``, sometimes with a drift."""
    amp, freq, phase = _num(rng, 0.2, 1.0), _num(rng, 0.2, 1.0), _num(rng, -3, 3)
    text = f"{centre:.3f} + {amp}*sin({freq}*t + {phase})"
    if rng.random() < 0.3:
        text += f" + {_num(rng, -0.1, 0.1)}*t"
    return text


def _objective(rng: np.random.Generator, outputs: list[str], targets: list[str]) -> str:
    """A random strongly convex f0: weighted squares, a bounded cross term, maybe a quartic."""
    weights = [float(_num(rng, 0.5, 2.0)) for _ in outputs]
    terms = [f"{w}*({y} - {o})**2" for w, y, o in zip(weights, outputs, targets, strict=True)]
    if len(outputs) >= 2 and rng.random() < 0.5:
        # |c| < sqrt(w0 w1) keeps the quadratic part positive definite (Hessian 2w, c).
        c = 0.8 * math.sqrt(weights[0] * weights[1]) * rng.uniform(-1, 1)
        terms.append(f"{c:.3f}*({outputs[0]} - {targets[0]})*({outputs[1]} - {targets[1]})")
    if rng.random() < 0.3:
        terms.append(f"{_num(rng, 0.05, 0.3)}*({outputs[-1]} - {targets[-1]})**4")
    return " + ".join(terms)


def _poles(rng: np.random.Generator, count: int) -> list[Any]:
    """``count`` stable poles: distinct reals, sometimes one conjugate pair."""
    poles: list[Any] = []
    if count >= 2 and rng.random() < 0.3:
        poles.append([float(_num(rng, -3.0, -0.8)), float(_num(rng, 0.2, 1.5))])
        count -= 2
    taken = {-0.0}
    while count:
        p = float(_num(rng, -4.0, -0.5))
        if p not in taken:
            taken.add(p)
            poles.append(p)
            count -= 1
    return poles


# --------------------------------------------------------------------------- plants


def system_spec(case: Case, rng: np.random.Generator) -> dict[str, Any]:
    """Strict-feedback chains of known relative degree, in random smooth coordinates."""
    unicycle = "unicycle" in case.features
    chains = case.size if not unicycle else max(case.size - 2, 0)
    lengths = [int(rng.integers(1, 4)) for _ in range(chains)]
    xi = [[sp.Symbol(f"s{i + 1}_{j + 1}", real=True) for j in range(r)] for i, r in
          enumerate(lengths)]  # fmt: skip
    u = [sp.Symbol(f"u{i + 1}", real=True) for i in range(chains)]
    rhs: dict[sp.Symbol, sp.Expr] = {}
    for i, chain in enumerate(xi):
        for j, s in enumerate(chain):
            lower = chain[: j + 1]
            drift = _num(rng, -0.5, 0.5) * sp.sin(lower[int(rng.integers(len(lower)))])
            if j + 1 < len(chain):
                # A constant gain: a state-dependent one (c0 + c1 cos) puts trigonometry
                # in det R, where the derivation's simplify takes minutes (see
                # tests/test_fuzz_regressions.py); the drift keeps the chain nonlinear.
                rhs[s] = _num(rng, 1.0, 2.0) * chain[j + 1] + drift
            else:
                everything = [x for c in xi for x in c]
                coupling = _num(rng, -0.5, 0.5) * sp.cos(
                    everything[int(rng.integers(len(everything)))]
                )
                # Nonvanishing and rational in the state: c0 + c1 s^2 with c0, c1 > 0.
                gain = _num(rng, 1.0, 2.0) + _num(rng, 0.0, 0.5) * chain[-1] ** 2
                rhs[s] = drift + coupling + gain * u[i]
                for later in u[i + 1 :]:
                    if rng.random() < 0.5:
                        rhs[s] += _num(rng, -1, 1) * chain[0] * later
    # Random smooth coordinates: x_k = xi_k + c sin(xi_j) for some k, each j left as is,
    # so the inverse is one substitution.
    flat = [x for c in xi for x in c]
    names = [sp.Symbol(f"x{k + 1}", real=True) for k in range(len(flat))]
    forward: dict[sp.Symbol, sp.Expr] = dict(zip(flat, flat, strict=True))
    kept = set()
    for k, s in enumerate(flat):
        free = [f for f in flat[:k] if forward[f] == f and f not in kept]
        if free and rng.random() < 0.4:
            j = free[int(rng.integers(len(free)))]
            kept.add(j)
            forward[s] = s + _num(rng, -0.6, 0.6) * sp.sin(j)
    to_x = dict(zip(flat, names, strict=True))
    inverse = {
        s: names[k] - (forward[s] - s).xreplace(to_x) for k, s in enumerate(flat)
    }  # forward[s] - s depends only on unchanged coordinates
    states: list[str] = []
    dynamics: dict[str, str] = {}
    for k, s in enumerate(flat):
        dot = sum(sp.diff(forward[s], v) * rhs[v] for v in flat)
        dynamics[names[k].name] = _text(sp.sympify(dot).xreplace(inverse))
        states.append(names[k].name)
    outputs = {f"y{i + 1}": _text(inverse[c[0]]) for i, c in enumerate(xi)}
    inputs = [x.name for x in u]
    initial = {n: round(float(rng.uniform(-0.5, 0.5)), 2) for n in states}
    spec: dict[str, Any] = {"name": f"fz_system_{case.seed}", "system": {}}
    if unicycle:
        states += ["px", "py", "th"]
        inputs += ["v", "w"]
        dynamics |= {"px": "v*cos(th)", "py": "v*sin(th)", "th": "w"}
        outputs |= {f"y{chains + 1}": "px", f"y{chains + 2}": "py"}
        speed = round(float(rng.uniform(0.5, 1.5) * rng.choice([-1, 1])), 2)
        initial |= {"px": 0.0, "py": 0.0, "th": round(float(rng.uniform(-3, 3)), 2)}
        if "auto" in case.features:
            spec["extension"] = {"auto": True}
            initial["v"] = speed
        else:
            spec["extension"] = {"integrate": {"v": 1}}
            initial["v"] = speed
        lengths += [2, 2]
    spec["relative_degree"] = tuple(lengths)
    spec["system"] = {
        "states": states,
        "inputs": inputs,
        "dynamics": dynamics,
        "outputs": outputs,
    }
    ys = list(outputs)
    spec["signals"] = {f"o{i + 1}": _signal(rng) for i in range(len(ys))}
    spec["objective"] = {"f0": _objective(rng, ys, list(spec["signals"]))}
    spec["error_dynamics"] = {"poles": _poles(rng, max(lengths))}
    spec["simulation"] = {"t_final": 5.0, "initial_state": initial}
    return spec


def arm_spec(case: Case, rng: np.random.Generator) -> dict[str, Any]:
    """A planar arm of ``case.size`` links from SymPy mechanics, through spec_from_sympy."""
    import sympy.physics.mechanics as me

    from tvopt_codegen.mechanics import spec_from_sympy

    links = case.size
    q = me.dynamicsymbols(f"q1:{links + 1}")
    dq = me.dynamicsymbols(f"dq1:{links + 1}")
    tau = me.dynamicsymbols(f"tau1:{links + 1}")
    m = sp.symbols(f"m1:{links + 1}", positive=True)
    lengths = sp.symbols(f"l1:{links + 1}", positive=True)
    inertia = sp.symbols(f"I1:{links + 1}", positive=True)
    centre = sp.symbols(f"c1:{links + 1}", positive=True)
    g = sp.Symbol("g", positive=True)
    world = me.ReferenceFrame("N")
    base = me.Point("O")
    base.set_vel(world, 0)
    bodies, loads = [], []
    parent, joint = world, base
    for i in range(links):
        frame = parent.orientnew(f"L{i + 1}", "Axis", [q[i], parent.z])
        frame.set_ang_vel(parent, dq[i] * parent.z)
        mass_centre = joint.locatenew(f"C{i + 1}", centre[i] * lengths[i] * frame.x)
        mass_centre.v2pt_theory(joint, world, frame)
        tip = joint.locatenew(f"P{i + 1}", lengths[i] * frame.x)
        tip.v2pt_theory(joint, world, frame)
        dyadic = me.inertia(frame, 0, 0, inertia[i])
        bodies.append(me.RigidBody(f"B{i + 1}", mass_centre, frame, m[i], (dyadic, mass_centre)))
        loads.append((mass_centre, -m[i] * g * world.y))
        loads.append((frame, tau[i] * world.z))
        if i > 0:
            loads.append((parent, -tau[i] * world.z))
        parent, joint = frame, tip
    kane = me.KanesMethod(
        world, q_ind=q, u_ind=dq, kd_eqs=[a.diff() - b for a, b in zip(q, dq, strict=True)]
    )
    kane.kanes_equations(bodies, loads)
    values: dict[sp.Symbol, float] = {g: float(_num(rng, 0.0, 9.81))}
    for i in range(links):
        values[m[i]] = float(_num(rng, 0.3, 3.0))
        values[lengths[i]] = float(_num(rng, 0.2, 1.2))
        values[inertia[i]] = float(_num(rng, 0.01, 0.5))
        values[centre[i]] = float(_num(rng, 0.1, 0.9))
    start = [round(float(rng.uniform(-1.5, 1.5)), 2) for _ in range(links)]
    outputs: dict[str, Any] = {}
    centres: list[float] = []
    if links == 2 and rng.random() < 0.5:
        # The tip's position: singular where q2 = 0 or pi, so start well away from them.
        start[1] = round(float(rng.uniform(0.6, 2.5) * rng.choice([-1, 1])), 2)
        l1, l2 = values[lengths[0]], values[lengths[1]]
        outputs = {
            "px": f"{l1}*cos(q1) + {l2}*cos(q1 + q2)",
            "py": f"{l1}*sin(q1) + {l2}*sin(q1 + q2)",
        }
        centres = [
            l1 * math.cos(start[0]) + l2 * math.cos(start[0] + start[1]),
            l1 * math.sin(start[0]) + l2 * math.sin(start[0] + start[1]),
        ]
    else:
        for i in range(links):
            # The absolute angle of link i, or the joint's: both give a triangular J.
            absolute = rng.random() < 0.5
            outputs[f"y{i + 1}"] = (
                "+".join(f"q{j + 1}" for j in range(i + 1)) if absolute else f"q{i + 1}"
            )
            centres.append(sum(start[: i + 1]) if absolute else start[i])
    ys = list(outputs)
    signals = {f"o{i + 1}": _signal(rng, centres[i]) for i in range(len(ys))}
    initial = {f"q{i + 1}": start[i] for i in range(links)}
    spec: dict[str, Any] = spec_from_sympy(
        kane,
        outputs,
        _objective(rng, ys, list(signals)),
        values,
        name=f"fz_arm_{case.seed}",
        signals=signals,
        poles=[-1.0, -2.0],
        t_final=5.0,
        initial_state=initial,
    )
    # spec_from_sympy takes real poles; a conjugate pair goes into the mapping.
    spec["error_dynamics"]["poles"] = _poles(rng, 2)
    return spec


def _rotation(rng: np.random.Generator) -> np.ndarray:
    matrix, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    return np.asarray(matrix * np.sign(np.linalg.det(matrix)), dtype=float)


def _axis(rng: np.random.Generator) -> str:
    if rng.random() < 0.5:
        v = np.zeros(3)
        v[int(rng.integers(3))] = rng.choice([-1.0, 1.0])
    else:
        v = rng.normal(size=3)
        v /= np.linalg.norm(v)
    return " ".join(f"{x:.6f}" for x in v)


def _inertial(rng: np.random.Generator) -> str:
    # Principal moments satisfying the triangle inequality, in a random frame.
    a, b = rng.uniform(0.002, 0.05, 2)
    c = rng.uniform(abs(a - b) + 1e-3, a + b)
    frame = _rotation(rng)
    tensor = frame @ np.diag([a, b, c]) @ frame.T
    tensor = (tensor + tensor.T) / 2
    xyz = " ".join(f"{x:.4f}" for x in rng.uniform(-0.1, 0.1, 3))
    rpy = " ".join(f"{x:.4f}" for x in rng.uniform(-1, 1, 3)) if rng.random() < 0.5 else "0 0 0"
    return (
        f'<inertial><origin xyz="{xyz}" rpy="{rpy}"/><mass value="{rng.uniform(0.2, 3):.4f}"/>'
        f'<inertia ixx="{tensor[0, 0]:.8f}" ixy="{tensor[0, 1]:.8f}" ixz="{tensor[0, 2]:.8f}" '
        f'iyy="{tensor[1, 1]:.8f}" iyz="{tensor[1, 2]:.8f}" izz="{tensor[2, 2]:.8f}"/></inertial>'
    )


def urdf_text(case: Case, rng: np.random.Generator) -> str:
    """A random fixed-base serial chain of ``case.size`` movable joints."""
    parts = ['<?xml version="1.0"?>', f'<robot name="fz_urdf_{case.seed}">', '<link name="base"/>']
    parent = "base"
    for i in range(case.size):
        kind = str(rng.choice(["revolute", "continuous", "prismatic"]))
        child = f"link{i + 1}"
        xyz = " ".join(f"{x:.4f}" for x in rng.uniform(-0.3, 0.3, 3))
        rpy = (
            " ".join(f"{x:.4f}" for x in rng.uniform(-1.5, 1.5, 3))
            if rng.random() < 0.6
            else "0 0 0"
        )
        limit = ""
        if kind == "revolute":
            limit = '<limit lower="-2" upper="2" effort="10" velocity="1"/>'
        elif kind == "prismatic":
            limit = '<limit lower="-0.5" upper="0.5" effort="50" velocity="1"/>'
        parts.append(
            f'<joint name="j{i + 1}" type="{kind}"><parent link="{parent}"/><child link="{child}"/>'
            f'<origin xyz="{xyz}" rpy="{rpy}"/><axis xyz="{_axis(rng)}"/>{limit}</joint>'
        )
        parts.append(f'<link name="{child}">{_inertial(rng)}</link>')
        parent = child
        if rng.random() < (0.25 if i + 1 < case.size else 0.6):
            # A fixed link the chain carries (a sensor, a tool).
            fixed = f"fixed{i + 1}"
            parts.append(
                f'<joint name="f{i + 1}" type="fixed"><parent link="{parent}"/>'
                f'<child link="{fixed}"/><origin xyz="0.05 0 0.1" rpy="0 0.3 0"/></joint>'
            )
            parts.append(f'<link name="{fixed}">{_inertial(rng)}</link>')
    parts.append("</robot>")
    return "\n".join(parts)


def urdf_spec(
    case: Case, rng: np.random.Generator, folder: Path
) -> tuple[dict[str, Any], Path, tuple[float, float, float]]:
    """The URDF file of the case, written to ``folder``, and the spec imported from it."""
    from tvopt_codegen.urdf import spec_from_urdf

    path = folder / f"fz_urdf_{case.seed}.urdf"
    path.write_text(urdf_text(case, rng), encoding="utf-8")
    gravity = (float(rng.uniform(-1, 1)), float(rng.uniform(-1, 1)), float(rng.uniform(-9.81, 0)))
    # The tip's position as the outputs, on a chain of 3, at a fixed link off the last
    # joint's axis: the last link's own origin lies on its joint's axis, which then does
    # not move it (R singular everywhere, a refusal that would test nothing).
    tip: list[str] = []
    if case.size == 3 and f'link name="fixed{case.size}"' in path.read_text(encoding="utf-8"):
        tip = ["--tip", f"fixed{case.size}"] if rng.random() < 0.7 else []
    if "cli" in case.features:
        import io

        from tvopt_codegen.cli import main as cli_main

        # The command line as the shell hands it to the CLI's parser, in this process: what
        # the case checks is the arguments' meaning (a negative gravity's first component
        # must not read as an option) and the file written. A fresh interpreter's start-up
        # is test_cli's and test_rough_edges' subject (import-urdf's: test_urdf_door's FIFO
        # refusal); a subprocess here cost a second of imports the caller has paid.
        out = folder / "imported.toml"
        err = io.StringIO()
        with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(err):
            try:
                code = cli_main(
                    ["import-urdf", str(path), "--out", str(out),
                     "--gravity=" + ",".join(repr(v) for v in gravity), *tip]
                )  # fmt: skip
            except SystemExit as stop:  # argparse's usage errors end so
                code = stop.code if isinstance(stop.code, int) else int(stop.code is not None)
        if code != 0:
            raise RuntimeError(f"import-urdf exit {code}: {err.getvalue().strip()}")
        import tomllib

        spec = tomllib.loads(out.read_text(encoding="utf-8"))
    else:
        spec = spec_from_urdf(
            path, gravity=gravity, name=f"fz_urdf_{case.seed}", tip=tip[1] if tip else None
        )
    spec["name"] = f"fz_urdf_{case.seed}"
    spec.setdefault("simulation", {})["t_final"] = 5.0
    return spec, path, gravity


# --------------------------------------------------------------------------- features


def add_features(spec: dict[str, Any], case: Case, rng: np.random.Generator) -> None:
    """Add the case's features to a spec mapping, in place."""
    ys = list(spec["system"]["outputs"])
    # The targets each output tracks, by position: the signals f0 reads.
    signals = spec.setdefault("signals", {})
    targets = list(signals)
    if "references" in case.features:
        # A reference in place of a closed-form target: the law takes its jets.
        chosen = [s for s in targets if rng.random() < 0.7] or targets[:1]
        spec["references"] = {
            "names": chosen,
            "nominal": {s: signals.pop(s) for s in chosen},
        }
        if rng.random() < 0.3:
            spec["references"]["estimator"] = {"kind": "levant", "lipschitz": 2.0}
        if not signals:
            del spec["signals"]
    constraints: dict[str, Any] = {}
    if "inequality" in case.features:
        i = int(rng.integers(len(ys)))
        side = "<=" if rng.random() < 0.5 else ">="
        margin = float(_num(rng, 0.1, 1.0)) * (1 if side == "<=" else -1)
        constraints["keep"] = f"{ys[i]} {side} {targets[i]} + {margin}"
    if "equality" in case.features and len(ys) >= 2:
        c = float(_num(rng, 0.2, 1.5))
        constraints["line"] = f"{ys[0]} + {c}*{ys[1]} == {targets[0]} + {c}*{targets[1]}"
    if constraints:
        spec["constraints"] = constraints
    robust: dict[str, Any] = {}
    if "integral" in case.features:
        robust["integral"] = True
        spec["error_dynamics"]["poles"].append(float(_num(rng, -4.0, -0.3)) - 0.001)
    if "observer" in case.features:
        robust["observer"] = {"bandwidth": float(_num(rng, 2.0, 60.0))}
    if "eso" in case.features:
        robust["eso"] = {"bandwidth": float(_num(rng, 5.0, 60.0))}
    if robust:
        spec["robust"] = robust
    if "limits" in case.features:
        limits: dict[str, Any] = {}
        for name in spec["system"]["inputs"]:
            if rng.random() < 0.5:
                limits[name] = float(_num(rng, 0.5, 20.0))
            else:
                low = float(_num(rng, -20.0, 0.0))
                limits[name] = [low, low + float(_num(rng, 0.5, 30.0))]
        if rng.random() < 0.4:
            limits["rate"] = {spec["system"]["inputs"][0]: float(_num(rng, 5.0, 200.0))}
        spec["limits"] = limits


# --------------------------------------------------------------------------- oracles


@dataclass
class Report:
    """What a case did: its outcome and how long each part took."""

    case: Case
    outcome: str = AGREES
    seconds: dict[str, float] = field(default_factory=dict)

    @contextlib.contextmanager
    def timed(self, part: str) -> Iterator[None]:
        start = time.perf_counter()
        try:
            yield
        finally:
            self.seconds[part] = self.seconds.get(part, 0.0) + time.perf_counter() - start


def _close(name: str, ours: np.ndarray, ref: np.ndarray, tolerance: float) -> None:
    ours, ref = np.asarray(ours, dtype=float), np.asarray(ref, dtype=float)
    scale = float(np.abs(ref).max()) if ref.size else 0.0
    if ours.shape != ref.shape or not np.allclose(
        ours, ref, rtol=tolerance, atol=tolerance * scale
    ):
        worst = float(np.abs(ours - ref).max()) if ours.shape == ref.shape else math.nan
        raise DisagreementError(
            f"{name}: shapes {ours.shape} vs {ref.shape}, largest difference {worst:.3g} "
            f"(scale {scale:.3g})"
        )


def sample_states(d: Any, rng: np.random.Generator, count: int) -> np.ndarray:
    """States near the initial one; prolonged speeds kept away from zero."""
    base = np.array(d.closed_loop.initial_state, dtype=float)
    states = base[:, None] + rng.uniform(-0.2, 0.2, size=(len(base), count))
    for name in d.linearization.extension.states:
        i = d.closed_loop.state_names.index(name)
        states[i] = base[i] * rng.uniform(0.7, 1.3, size=count)
    return states


def pinocchio_check(
    spec: dict[str, Any], path: Path, gravity: Any, rng: np.random.Generator
) -> None:
    """M(q) and the bias forces of an imported URDF spec against Pinocchio's."""
    import pinocchio as pin

    from tvopt_codegen.spec import spec_from_dict

    from .pinocchio_check import both_at

    mech = spec_from_dict(spec).mechanics
    assert mech is not None
    model = pin.buildModelFromUrdf(str(path))
    model.gravity.linear = np.array(gravity)
    data = model.createData()
    if model.nv != len(mech.coordinates):
        raise DisagreementError(
            f"Pinocchio has {model.nv} joints, the spec {len(mech.coordinates)}"
        )
    params = {sp.Symbol(n, real=True): v for n, v in spec_from_dict(spec).parameters}
    for _ in range(5):
        q = rng.uniform(-np.pi, np.pi, model.nv)
        v = rng.uniform(-2.0, 2.0, model.nv)
        ours, theirs, our_bias, bias = both_at(mech, params, model, data, q, v)
        _close("M against Pinocchio", ours, theirs, 1e-9)
        _close("bias forces against Pinocchio", our_bias, bias, 1e-9)


def _twin(spec: dict[str, Any]) -> dict[str, Any]:
    """The spec with its references written back as closed-form signals."""
    twin = {k: v for k, v in spec.items() if k != "references"}
    twin["signals"] = {**spec.get("signals", {}), **spec["references"]["nominal"]}
    return twin


def _same_answer(
    name: str, python: Any, c: Any, t: float, states: np.ndarray, kwargs: dict[str, Any]
) -> None:
    """A public function in Python and C: the same values, or the same documented error."""
    try:
        expected = python(t, states, **kwargs)
    except ArithmeticError as exc:  # ControllerError: the law refused (past a barrier)
        try:
            c(t, states, **kwargs)
        except ArithmeticError as other:
            if type(other).__name__ != type(exc).__name__ or str(other) != str(exc):
                raise DisagreementError(
                    f"C {name} at t={t}: {type(other).__name__}: {other}; "
                    f"Python: {type(exc).__name__}: {exc}"
                ) from other
            return
        raise DisagreementError(f"C {name} at t={t} answered; Python: {exc}") from exc
    _close(f"C {name}", c(t, states, **kwargs), expected, 1e-10)


def _controller_run(
    mod: ModuleType, x0: np.ndarray, plants: np.ndarray, times: np.ndarray, jets: Any
) -> tuple[np.ndarray, str]:
    """Inputs and controller states of ``Controller.step`` along given plant states.

    Returns the rows of the steps that succeeded and the class of the documented run-time
    error (``ControllerError``) that stopped the run, or ``"none"``.
    """
    kwargs = {"refs": jets(times[0])} if jets else {}
    controller = mod.Controller(x0, **kwargs)
    rows = [np.concatenate([controller.u, controller.state])]
    for k in range(1, len(times)):
        kwargs = {"refs": jets(times[k])} if jets else {}
        try:
            u = controller.step(float(times[k]), plants[:, k], **kwargs)
        except mod.ControllerError as exc:
            return np.array(rows), type(exc).__name__
        rows.append(np.concatenate([u, controller.state]))
    return np.array(rows), "none"


@dataclass
class ClosedLoop:
    """A sampled closed loop of the Python ``Controller`` and the plant it was derived for.

    ``plants[:, k]`` is what the controller measured at ``times[k]``; ``rows[k]`` its
    input and states after that step. ``stopped`` is the documented run-time error that
    ended the run early (``""`` when every step succeeded), ``at`` the step it came at.
    """

    plants: np.ndarray
    times: np.ndarray
    rows: np.ndarray
    stopped: str = ""
    at: int = 0


def _closed_loop(
    mod: ModuleType, x0: np.ndarray, times: np.ndarray, disturbance: np.ndarray, jets: Any
) -> ClosedLoop:
    """The controller stepped at ``times`` on its plant plus a constant ``disturbance``.

    The plant is integrated by RK4 under the held input, so that the controller meets the
    states its own inputs produce (a path that ignores them winds the integrals and the
    observer up until the law leaves its domain, which says nothing about the tool); the
    disturbance gives the observer and the integrals something to act on.
    """
    kwargs = {"refs": jets(times[0])} if jets else {}
    controller = mod.Controller(x0, **kwargs)
    rows = [np.concatenate([controller.u, controller.state])]
    x, u = x0.copy(), np.asarray(controller.u, dtype=float)

    def f(t: float, state: np.ndarray) -> np.ndarray:
        return np.asarray(mod.plant(t, state, u), dtype=float).ravel() + disturbance

    plants = [x0.copy()]
    for k in range(1, len(times)):
        t, h = float(times[k - 1]), float(times[k] - times[k - 1])
        k1 = f(t, x)
        k2 = f(t + h / 2, x + h / 2 * k1)
        k3 = f(t + h / 2, x + h / 2 * k2)
        k4 = f(t + h, x + h * k3)
        x = x + h / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
        plants.append(x.copy())
        kwargs = {"refs": jets(times[k])} if jets else {}
        try:
            u = np.asarray(controller.step(float(times[k]), x, **kwargs), dtype=float)
        except mod.ControllerError as exc:
            message = " ".join(str(exc).split())
            return ClosedLoop(np.array(plants).T, times[: k + 1], np.array(rows),
                              f"{type(exc).__name__}: {message}", k)  # fmt: skip
        rows.append(np.concatenate([u, controller.state]))
    return ClosedLoop(np.array(plants).T, times, np.array(rows))


def _crossed_a_barrier(oracle: Any, loop: ClosedLoop, d: Any, p: np.ndarray) -> bool:
    """Whether a loop that stopped with ``OutsideBarrierError`` stopped where the plant's
    outputs are past a barrier by the oracle's own margins (raises if they are inside)."""
    if not loop.stopped.startswith("OutsideBarrierError"):
        return False
    state = np.zeros(len(d.closed_loop.state_names))
    plant = loop.plants[:, loop.at]
    state[: len(plant)] = plant  # the margins read y = h(x): the plant's states alone
    margins = oracle.margins(float(loop.times[loop.at]), state[:, None], p)[:, 0]
    if np.all(margins > 1e-9):
        raise DisagreementError(
            f"Controller.step refused at t = {loop.times[loop.at]:g} s as past a barrier, "
            f"where the oracle's margins are {margins.tolist()}"
        )
    return True


def _fmu_check(kernels: Any, mod: ModuleType, x0: np.ndarray, plants: np.ndarray,
               times: np.ndarray, jets: Any, folder: Path) -> None:  # fmt: skip
    """The FMU under FMPy against the Python ``Controller`` along the same plant states."""
    import fmpy

    from tvopt_codegen.runs.fmu import build_fmu

    path = folder / "case.fmu"
    path.write_bytes(build_fmu(kernels, 2))
    columns = [(n, plants[i]) for i, n in enumerate(mod.PLANT_STATE_NAMES)]
    if jets:
        values = np.array([jets(t) for t in times])  # (T, n_refs, q + 1)
        for r, name in enumerate(mod.REFERENCE_NAMES):
            for j in range(values.shape[2]):
                columns.append((f"reference.{name}.d{j}", values[:, r, j]))
    table = np.array(
        [(t, *(c[k] for _, c in columns)) for k, t in enumerate(times)],
        dtype=[("time", float)] + [(n, float) for n, _ in columns],
    )
    names = [*mod.INPUT_NAMES, *(f"controller.{n}" for n in mod.CONTROLLER_STATE_NAMES)]
    h = float(times[1] - times[0])
    result = fmpy.simulate_fmu(
        str(path), start_time=0.0, stop_time=float(times[-1]), output_interval=h, input=table,
        output=names, fmi_type="CoSimulation",
    )  # fmt: skip
    got = np.array([[row[n] for n in names] for row in result])
    # The FMU shows at t_{k+1} what doStep(t_k) computed from x(t_k).
    kwargs = {"refs": jets(times[0])} if jets else {}
    controller = mod.Controller(x0, **kwargs)
    expected = [np.concatenate([controller.u, controller.state])]
    for k in range(len(times) - 1):
        kwargs = {"refs": jets(times[k])} if jets else {}
        u = controller.step(float(times[k]), plants[:, k], **kwargs)
        expected.append(np.concatenate([u, controller.state]))
    _close("FMU against Controller.step", got, np.array(expected), 1e-9)


def _error_of(call: Any) -> str:
    try:
        call()
    except Exception as exc:  # noqa: BLE001 - the class is what is compared
        return type(exc).__name__
    return "none"


def _same_errors(py: ModuleType, cmod: ModuleType, d: Any, state: np.ndarray, jets: Any) -> None:
    """Python and C raise the same error class at a non-finite and a singular state."""
    kwargs = {"refs": jets(1.0)} if jets else {}
    bad = {"a NaN state": state.copy()}
    bad["a NaN state"][0] = np.nan
    if "v" in d.closed_loop.state_names:  # the unicycle's prolonged speed: R is singular at v = 0
        bad["v = 0"] = state.copy()
        bad["v = 0"][d.closed_loop.state_names.index("v")] = 0.0
    for what, s in bad.items():
        for name in ("control", "rhs"):
            ours = _error_of(lambda n=name, s=s: getattr(cmod, n)(1.0, s, **kwargs))
            theirs = _error_of(lambda n=name, s=s: getattr(py, n)(1.0, s, **kwargs))
            if ours != theirs or ours == "none":
                raise DisagreementError(f"{name} at {what}: C raises {ours}, Python {theirs}")
    # The stateful controller, measuring a NaN after a good start.
    plant = len(py.PLANT_STATE_NAMES)
    x0 = np.array(py.DEFAULT_STATE[:plant], dtype=float)
    nan = x0.copy()
    nan[0] = np.nan
    classes = [
        _error_of(lambda m=m: m.Controller(x0, **kwargs).step(1.01, nan, **kwargs))
        for m in (cmod, py)
    ]
    if classes[0] != classes[1] or classes[0] == "none":
        raise DisagreementError(
            f"Controller.step at a NaN: C raises {classes[0]}, Python {classes[1]}"
        )


def build_spec(case: Case, folder: Path) -> tuple[dict[str, Any], dict[str, Any]]:
    """The case's spec mapping, and what its plant is known to be.

    ``relative_degree`` for a ``system`` (the chains' lengths, 2 for a unicycle's
    outputs once extended), ``urdf`` (the file and gravity Pinocchio needs) for a URDF.
    """
    rng = case.rng()
    extra: dict[str, Any] = {}
    if case.kind == "system":
        spec = system_spec(case, rng)
        extra = {"relative_degree": spec.pop("relative_degree")}
    elif case.kind == "arm":
        spec = arm_spec(case, rng)
    else:
        spec, path, gravity = urdf_spec(case, rng, folder)
        extra = {"urdf": (path, gravity)}
    add_features(spec, case, rng)
    return spec, extra


def run_case(case: Case, report: Report | None = None) -> str:
    """Run one case through every oracle; return :data:`AGREES` or the refusal's message.

    Raises
    ------
    DisagreementError
        Two implementations disagree.
    Exception
        Anything else that went wrong: an internal error of the tool or of the harness.
    """
    from tvopt_codegen.derivation import derive
    from tvopt_codegen.errors import AssumptionError, SpecError
    from tvopt_codegen.lowering.ir import lower
    from tvopt_codegen.simulation import load_controller
    from tvopt_codegen.simulation.references import exact_jets
    from tvopt_codegen.spec import spec_from_dict

    from .oracle import Oracle

    report = report or Report(case)
    rng = case.rng(1)
    with tempfile.TemporaryDirectory(prefix="tvopt-fuzz-") as tmp:
        folder = Path(tmp)
        with report.timed("build"):
            spec, extra = build_spec(case, folder)
        if "urdf" in extra:
            with report.timed("pinocchio"):
                urdf, gravity = extra["urdf"]
                pinocchio_check(spec, urdf, gravity, rng)
        try:
            with report.timed("derive"):
                d = derive(spec_from_dict(spec))
                kernels = lower(d)
        except (SpecError, AssumptionError) as exc:
            message = str(exc)
            if "\n" in message or not message.strip():
                raise AssertionError(f"a refusal of more than one line: {message!r}") from exc
            return f"refused: {type(exc).__name__}: {message}"
        # A start where the law is undefined (a random chain stretched straight) is the
        # derivation's documented warning, and simulate's exit 3: the law cannot start.
        stuck = [w for w in d.warnings if "the law is undefined at the initial state" in w]
        if stuck:
            return f"refused: warning: {stuck[0]}"
        if (
            "relative_degree" in extra
            and d.linearization.relative_degree != extra["relative_degree"]
        ):
            raise DisagreementError(
                f"relative degree {d.linearization.relative_degree}, "
                f"built as {extra['relative_degree']}"
            )
        with report.timed("python"):
            py = load_controller(kernels, "python")
        with report.timed("oracle"):
            twin = derive(spec_from_dict(_twin(spec))) if "references" in spec else d
            oracle = Oracle(twin)
            jets = exact_jets(d, {}) if "references" in spec else None
            states = sample_states(d, rng, 40)
            p = np.array(list(py.PARAMETERS.values()), dtype=float)
            for t in np.round(rng.uniform(0, 5, 2), 3):
                kwargs = {"refs": jets(t)} if jets else {}
                # Past a barrier (the slack shrinks while the samples stay near the start)
                # the law must refuse; inside it must agree. A margin within rounding of 0
                # is neither.
                inside, outside = oracle.domain(float(t), states, p)
                for name in ("control", "rhs", "optimality_error") if outside.any() else ():
                    try:
                        getattr(py, name)(t, states[:, outside], **kwargs)
                    except py.OutsideBarrierError:
                        pass
                    else:
                        raise DisagreementError(f"{name} at t={t} past a barrier: no error")
                if inside.any():
                    u_ref, ds_ref = oracle.law(float(t), states[:, inside], p)
                    within = states[:, inside]
                    _close(f"control at t={t}", py.control(t, within, **kwargs), u_ref, 1e-8)
                    _close(f"rhs at t={t}", py.rhs(t, within, **kwargs), ds_ref, 1e-8)
                    _close(
                        f"optimality_error at t={t}",
                        py.optimality_error(t, within, **kwargs),
                        oracle.optimality_error(float(t), within, p),
                        1e-8,
                    )
        # The stateful controller along a plant trajectory near the start: it runs the
        # observer, the limits and the integrals, which the law alone does not.
        x0 = np.array(py.DEFAULT_STATE[: len(py.PLANT_STATE_NAMES)], dtype=float)
        times = np.round(np.arange(0, 11) * 0.01, 6)
        disturbance = rng.uniform(-0.5, 0.5, size=len(x0))
        with report.timed("controller"):
            loop = _closed_loop(py, x0, times, disturbance, jets)
            if not np.all(np.isfinite(loop.rows)):
                raise DisagreementError(
                    "Controller.step returned a non-finite value without an error"
                )
            crossed = _crossed_a_barrier(oracle, loop, d, p)
            # The first step from a start the derivation calls regular must succeed: an
            # error there is the "undefined everywhere" kind of seam, unless the plant has
            # really crossed a barrier (a start millimetres inside one, pushed out by the
            # disturbance while limits hold the input). Later, a sampled loop (10 ms, stiff
            # barriers, limits that exclude the nominal input) may leave the law's domain,
            # and the documented error class is the right end.
            if loop.stopped and loop.at == 1 and not crossed:
                raise DisagreementError(f"Controller.step failed at the first step: {loop.stopped}")
        if "c" in case.features:
            with report.timed("c"):
                cmod = load_controller(kernels, "c")
                for t in (0.0, 1.3):
                    kwargs = {"refs": jets(t)} if jets else {}
                    for name in ("control", "rhs", "optimality_error"):
                        _same_answer(name, getattr(py, name), getattr(cmod, name), t, states,
                                     kwargs)  # fmt: skip
                rows, stopped = _controller_run(cmod, x0, loop.plants, loop.times, jets)
                if stopped != (loop.stopped.split(":")[0] or "none"):
                    raise DisagreementError(
                        f"Controller.step stopped with {stopped} in C, "
                        f"{loop.stopped or 'none'} in Python"
                    )
                _close("C Controller.step", rows, loop.rows, 1e-9)
                _same_errors(py, cmod, d, states[:, 0], jets)
        if "fmu" in case.features:
            with report.timed("fmu"):
                # Up to the step before a documented error: the FMU reports it by failing.
                good = len(loop.rows)
                _fmu_check(kernels, py, x0, loop.plants[:, :good], loop.times[:good], jets,
                           folder)  # fmt: skip
        if loop.stopped:
            return (
                f"refused: run-time: the sampled closed loop left the law's domain at "
                f"t = {loop.times[loop.at]:g} s: {loop.stopped}"
            )
    return AGREES


# --------------------------------------------------------------------------- hypothesis


def cases_strategy(c_rate: float = 0.1, fmu_rate: float = 0.03, max_size: int = 3) -> Any:
    """Hypothesis strategy of :class:`Case`; C and the FMU run on the given shares.

    ``max_size`` bounds the chains, links and joints (a 3-joint URDF chain costs five
    times a small plant).
    """
    from hypothesis import strategies as st

    @st.composite
    def draw_case(draw: Any) -> Case:
        kind = draw(st.sampled_from(KINDS))
        size = draw(st.integers(1, max_size))
        features = {f for f in FEATURES if draw(st.booleans())}
        if {"observer", "eso"} <= features:
            # Refused up front (docs/features.md): a case keeps one of the two observers.
            features.discard(draw(st.sampled_from(("observer", "eso"))))
        if kind == "system" and draw(st.booleans()):
            features.add("unicycle")
            size = draw(st.integers(2, max_size + 1))
            if draw(st.booleans()):
                features.add("auto")
        if kind == "urdf" and draw(st.integers(0, 9)) == 0:
            features.add("cli")
        # Compared from above: hypothesis starts from small draws, which would mean
        # "always" for the first cases.
        if draw(st.integers(0, 999)) >= 1000 - c_rate * 1000:
            features.add("c")
        if draw(st.integers(0, 999)) >= 1000 - fmu_rate * 1000:
            features.add("fmu")
        seed = draw(st.integers(0, 2**32 - 1))
        return Case(kind, size, frozenset(features), seed)

    return draw_case()


def classify(case: Case, report: Report) -> tuple[str, str]:
    """(kind of end, detail): ``agrees``, ``refused`` or ``FAILED``, never raising."""
    try:
        outcome = run_case(case, report)
    except Exception as exc:  # noqa: BLE001 - every other end is a finding to record
        last = traceback.format_exception_only(type(exc), exc)[-1].strip()
        return "FAILED", " ".join(last.split())[:400]
    if outcome == AGREES:
        return "agrees", ""
    return "refused", outcome


def _run_one(text: str) -> tuple[str, str, str, dict[str, float], float, float]:
    """One case by its string, in this process or a worker's: (case, end, detail, seconds
    by part, wall seconds, CPU seconds)."""
    case = Case.parse(text)
    report = Report(case)
    begin, cpu = time.perf_counter(), time.process_time()
    end, detail = classify(case, report)
    return text, end, detail, report.seconds, time.perf_counter() - begin, time.process_time() - cpu


def drawn_cases(count: int, seed: int, c_rate: float, fmu_rate: float) -> list[str]:
    """The ``count`` distinct cases hypothesis draws from ``seed``, in its order.

    Drawing is cheap and does not depend on how a case ends, so the list is the one a
    run that executes each case as it is drawn would meet.
    """
    from hypothesis import HealthCheck, Phase, assume, given, settings
    from hypothesis import seed as hypothesis_seed

    cases: list[str] = []

    @hypothesis_seed(seed)
    @settings(
        max_examples=count, database=None, deadline=None, phases=[Phase.generate],
        suppress_health_check=list(HealthCheck),
    )  # fmt: skip
    @given(cases_strategy(c_rate, fmu_rate))
    def collect(case: Case) -> None:
        # Hypothesis mutates earlier examples and sometimes meets one again: keep each
        # case once (a rejected draw does not count towards the budget).
        assume(str(case) not in cases)
        cases.append(str(case))

    collect()
    return cases


def main(argv: list[str] | None = None) -> int:
    """``make fuzz``: run N cases from a seed (or replay one); exit 1 on any failure."""
    parser = argparse.ArgumentParser(
        prog="python -m tests.fuzzing", description=__doc__.split("\n")[0]
    )
    parser.add_argument("--cases", type=int, default=100)
    parser.add_argument("--seed", type=int, default=None)
    parser.add_argument("--case", action="append", default=[], help="replay this case (repeatable)")
    parser.add_argument("--c-rate", type=float, default=0.1)
    parser.add_argument("--fmu-rate", type=float, default=0.03)
    parser.add_argument("--log", type=Path, default=None, help="append one line per case here")
    parser.add_argument(
        "--workers", type=int, default=1, help="processes that run cases (the cases are the same)"
    )
    args = parser.parse_args(argv)
    if args.workers < 1:
        parser.error(f"--workers: {args.workers} is not a positive count")
    os.environ.setdefault("TVOPT_CODEGEN_CACHE", tempfile.mkdtemp(prefix="tvopt-fuzz-cache-"))
    seed = args.seed if args.seed is not None else int.from_bytes(os.urandom(4), "little")
    tally: Counter[str] = Counter()
    failures: list[tuple[str, str]] = []
    parts: Counter[str] = Counter()
    cpu_seconds = [0.0]
    log = args.log.open("a", encoding="utf-8") if args.log else None
    started = time.perf_counter()

    def record(result: tuple[str, str, str, dict[str, float], float, float]) -> None:
        text, end, detail, seconds, wall, cpu = result
        tally[end] += 1
        parts.update(seconds)
        cpu_seconds[0] += cpu
        # Wall and CPU time: on a shared machine the wall time says little.
        line = f"{end:8s} {wall:6.2f}s {cpu:6.2f}cpu {text} {detail}"
        print(line, flush=True)
        if log:
            print(line, file=log, flush=True)
        if end == "FAILED":
            failures.append((text, detail))

    if args.case:
        texts = [str(Case.parse(text)) for text in args.case]
        print(f"replaying {len(texts)} case(s)", flush=True)
    else:
        print(f"fuzz: {args.cases} cases, seed {seed} (replay the run: --seed {seed})", flush=True)
        texts = drawn_cases(args.cases, seed, args.c_rate, args.fmu_rate)
    if args.workers == 1:
        for text in texts:
            record(_run_one(text))
    else:
        # Each case is a pure function of its string: workers change the order in which
        # lines are printed, never what a case does.
        from concurrent.futures import ProcessPoolExecutor

        with ProcessPoolExecutor(args.workers) as pool:
            for result in pool.map(_run_one, texts, chunksize=1):
                record(result)
    elapsed = time.perf_counter() - started
    total = sum(tally.values())
    print(
        f"fuzz: {total} cases in {elapsed:.0f} s with {args.workers} worker(s) "
        f"({total / max(elapsed, 1e-9):.2f} cases/s; {cpu_seconds[0]:.0f} s of CPU in the "
        f"fuzzing processes, {total / max(cpu_seconds[0], 1e-9):.2f} cases per CPU-second, "
        "compilers and subprocesses not counted): "
        + ", ".join(f"{k} {v}" for k, v in sorted(tally.items())),
        flush=True,
    )
    print(
        "time by part: " + ", ".join(f"{k} {v:.0f} s" for k, v in parts.most_common()), flush=True
    )
    for text, detail in failures:
        print(f"FAILED {text}: {detail}\n  replay: make fuzz CASE={text}", flush=True)
    if args.seed is None and not args.case:
        print(f"seed {seed}", flush=True)
    if log:
        log.close()
    return 1 if failures else 0


if __name__ == "__main__":
    sys.exit(main())
