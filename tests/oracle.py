"""An independent evaluation of the paper's law, for checking generated code.

It shares only the Derivation's Lie derivatives with the generator. The gradient jet
comes from naive repeated total derivatives of the fully substituted f0 (no
straight-line program, no CSE), the law from numpy's dense solves, and everything is
evaluated through ``sympy.lambdify``. With equality constraints, the same for the
Lagrangian ``f0 + sum_j nu_j a_j`` over the outputs and the multipliers, whose jets are
the states ``nu_<name>_0 .. nu_<name>_<k-1>`` by name.
"""

from __future__ import annotations

import collections
import copy
import dataclasses
import math
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np
import pytest
import sympy as sp
from sympy.printing.numpy import NumPyPrinter

from tvopt_codegen import symbolic as sx
from tvopt_codegen.derivation import Derivation
from tvopt_codegen.symbolic.border import to_sympy


def lambdified(args: Sequence[Any], expr: Any) -> Callable[..., Any]:
    """``sympy.lambdify(args, expr, "numpy")``, printing sums and products in their stored
    order, not sorted: the sorting was half of the printing, and the order of the terms
    moves a value by rounding only (the oracle's comparisons allow 1e-12 and more)."""
    printer = NumPyPrinter(
        {
            # lambdify's own settings for "numpy" (sympy.utilities.lambdify), and the order.
            "fully_qualified_modules": False,
            "inline": True,
            "allow_unknown_functions": True,
            "user_functions": {},
            "order": "none",
        }
    )
    return sp.lambdify(args, expr, "numpy", printer=printer)  # type: ignore[no-any-return]


def naive_total_derivative(expr: sp.Expr, t: sp.Symbol, jets: list[list[sp.Symbol]]) -> sp.Expr:
    """D expr = d/dt + sum_j y^(j+1) d/dy^(j), on one expression (swells; tests only)."""
    out = sp.diff(expr, t)
    for chain in jets:
        for j in range(len(chain) - 1):
            out += sp.diff(expr, chain[j]) * chain[j + 1]
    return out


def sympy_twin(d: Any) -> Any:
    """``d`` with every SymEngine expression in it converted to SymPy (as it is on SymPy).

    The oracle computes with SymPy whatever engine derived the law: its inputs cross
    the border once, through one memo, so that a symbol is the same object everywhere.
    Which engine built ``d`` is read off its time symbol, not the engine in use (a test
    may hand a SymEngine derivation to the oracle inside ``sx.using("sympy")``).
    """
    if not type(d.model.t).__module__.startswith("symengine"):
        return d
    with sx.using("symengine"):  # the border converts from the engine in use
        return _to_sympy_twin(d)


def _to_sympy_twin(d: Any) -> Any:
    memo: dict[Any, Any] = {}
    seen: dict[int, Any] = {}

    def convert(value: Any) -> Any:
        if isinstance(value, sx.Basic | sx.MatrixBase):
            return to_sympy(value, memo)
        key = id(value)
        if key in seen:
            return seen[key]
        if dataclasses.is_dataclass(value) and not isinstance(value, type):
            changes = {
                f.name: convert(getattr(value, f.name)) for f in dataclasses.fields(value) if f.init
            }
            out = copy.copy(value)
            for name, new in changes.items():
                object.__setattr__(out, name, new)
        elif isinstance(value, tuple) and type(value) is tuple:
            out = tuple(convert(v) for v in value)
        elif isinstance(value, list):
            out = [convert(v) for v in value]
        elif isinstance(value, dict):
            out = {convert(k): convert(v) for k, v in value.items()}
        elif isinstance(value, frozenset | set):
            out = type(value)(convert(v) for v in value)
        else:
            out = value
        seen[key] = out
        return out

    return convert(d)


#: The oracles last built, by their derivation (kept alive here, so its id stays its own).
_BUILT: collections.OrderedDict[int, tuple[Derivation, Oracle]] = collections.OrderedDict()
#: How many: a run's shared derivations are a few dozen; fuzzed ones come and go.
_KEPT = 48


class Oracle:
    """Numerical functions of the law for one derivation, vectorized over states.

    Built once per derivation object: its functions are pure (nothing is assigned after
    ``__init__``), and building one (SymPy's derivatives and lambdify) costs a second on
    a team, for every file that checks a module against the same shared derivation.
    """

    def __new__(cls, d: Derivation) -> Oracle:
        hit = _BUILT.get(id(d))
        if hit is not None and hit[0] is d:
            _BUILT.move_to_end(id(d))
            return hit[1]
        return super().__new__(cls)

    def __init__(self, d: Derivation) -> None:
        if "d" in vars(self):
            return  # the memo's: built already
        self._build(d)
        _BUILT[id(d)] = (d, self)
        while len(_BUILT) > _KEPT:
            _BUILT.popitem(last=False)

    def _build(self, d: Derivation) -> None:
        d = sympy_twin(d)
        self.d = d
        model = d.model
        t, k, m = model.t, d.dynamics.k, len(model.y)
        q = len(model.equalities)
        n = m + q
        self.k, self.m, self.n = k, m, n
        lagrangian = model.f0 + sum(
            (sp.Symbol(f"nu_{c.name}", real=True) * (c.lhs - c.rhs) for c in model.equalities),
            sp.Integer(0),
        )
        variables = [*model.y, *(sp.Symbol(f"nu_{c.name}", real=True) for c in model.equalities)]
        f0 = lagrangian.xreplace(dict(model.signals)).xreplace(dict(model.signals))
        jets = [[sp.Symbol(f"Y{i}_{j}", real=True) for j in range(k + 1)] for i in range(n)]
        f0 = f0.xreplace({variables[i]: jets[i][0] for i in range(n)})
        grads = [[sp.diff(f0, jets[i][0]) for i in range(n)]]
        for _ in range(k):
            grads.append([naive_total_derivative(g, t, jets) for g in grads[-1]])
        hess = [sp.diff(g, jets[j][0]) for g in grads[0] for j in range(n)]
        rest = [g.xreplace({jets[i][k]: 0 for i in range(n)}) for g in grads[k]]
        state_jet = {jets[i][j]: d.jet.y_jet_values[i][j] for i in range(m) for j in range(k)}
        states = dict(zip(d.closed_loop.state_names, d.closed_loop.states, strict=True))
        # With [robust.eso], y^(j), 1 <= j < r_i, is the observer's estimate, the state
        # eso_<output>_<j>, by name (y itself is measured); its d_hat is eso_<output>_d.
        self.eso = d.spec.robust.eso
        degrees = d.linearization.relative_degree
        outputs = d.spec.outputs
        if self.eso is not None:
            state_jet |= {
                jets[i][j]: states[f"eso_{outputs[i]}_{j}"]
                for i in range(m)
                for j in range(1, degrees[i])
            }
            self.eso_rows = [
                [d.closed_loop.state_names.index(f"eso_{o}_{j}") for j in range(degrees[i])]
                + [d.closed_loop.state_names.index(f"eso_{o}_d")]
                for i, o in enumerate(outputs)
            ]
        state_jet |= {
            jets[m + i][j]: states[f"nu_{c.name}_{j}"]
            for i, c in enumerate(model.equalities)
            for j in range(k)
        }
        self.multipliers = [
            [d.closed_loop.state_names.index(f"nu_{c.name}_{j}") for j in range(k)]
            for c in model.equalities
        ]
        self.integral = [
            d.closed_loop.state_names.index(name) for name in d.closed_loop.integral_states
        ]
        w = sp.symbols(f"W0:{m}", real=True)
        args = [t, *d.closed_loop.states, *model.params, *w]
        ext = d.linearization.extension
        field = list(ext.f + ext.G * sp.Matrix(w))

        def lam(exprs: Sequence[sp.Expr]) -> Callable[..., list[object]]:
            return lambdified(args, [sp.sympify(e).xreplace(state_jet) for e in exprs])

        self.E = lam([g for j in range(k) for g in grads[j]])
        # The barrier's domain: s(t) - g_i(y, t) > 0 for each inequality, y from the state.
        outputs = {yi: d.jet.y_jet_values[i][0] for i, yi in enumerate(model.y)}
        self.margin = lam(
            [
                (model.slack - sp.sympify(c.g))
                .xreplace(dict(model.signals))
                .xreplace(dict(model.signals))
                .xreplace(outputs)
                for c in model.constraints
            ]
        )
        self.h = lam(list(model.h))
        self.hess = lam(hess)
        self.rest = lam(rest)
        self.R = lam(list(d.linearization.R))
        self.p = lam(list(d.decoupling.p))
        self.field = lam(field)
        self.mechanics = model.mechanics
        if model.mechanics is not None:
            # The mass-matrix form, independently of the derivation's Lie derivatives:
            # y'' = J (M^-1 (F + B u)) + (dJ/dt) q', with numpy's dense solves of M.
            mech = model.mechanics
            q = [sp.Symbol(c, real=True) for c in mech.coordinates]
            dq = [sp.Symbol(r, real=True) for r in mech.rates]
            J = [[sp.diff(h, qk) for qk in q] for h in model.h]
            curvature = [
                sp.Add(
                    *(
                        sp.diff(row[kk], ql) * dq[ll] * dq[kk]
                        for kk in range(len(q))
                        for ll, ql in enumerate(q)
                    )
                )
                for row in J
            ]
            self.coordinates = len(q)
            # The spec's definitions one by one, each from those before it: M, F and B
            # read them (a URDF robot's link velocities), substituted they would swell.
            # Each is a function of the arguments and earlier definitions it reads, by
            # position: lambdify's cost grows with its argument list, and a robot's few
            # hundred definitions each given all before it took most of its oracle.
            defined = [s for s, _ in mech.definitions]
            position = {a: i for i, a in enumerate(args)}
            earlier: dict[sp.Symbol, int] = {}
            self.definitions = []
            for i, (sym, expr) in enumerate(mech.definitions):
                free = sp.sympify(expr).free_symbols
                read = [a for a in args if a in free]
                before = [s for s in defined[:i] if s in free]
                function = lambdified([*read, *before], expr)
                self.definitions.append(
                    (
                        sym,
                        tuple(position[a] for a in read),
                        tuple(earlier[s] for s in before),
                        function,
                    )
                )
                earlier[sym] = i
            self.mass = lambdified([*args, *defined], [e for row in mech.mass_matrix for e in row])
            self.forces = lambdified([*args, *defined], list(mech.forces))
            self.gain = lambdified([*args, *defined], [e for row in mech.input_matrix for e in row])
            self.jacobian = lam([e for row in J for e in row])
            self.curvature = lam(curvature)

    @staticmethod
    def _eval(
        func: Callable[..., list[object]], args: list[object], shape: tuple[int, ...], n: int
    ) -> np.ndarray:
        values = func(*args)
        return np.array(
            [np.broadcast_to(np.asarray(v, dtype=float), (n,)) for v in values]
        ).reshape(*shape, n)

    def law(self, t: float, s: np.ndarray, p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Return (u, ds) for states ``s`` of shape (n, N) and parameters ``p``."""
        d, k, m, size, n = self.d, self.k, self.m, self.n, s.shape[1]
        args: list[object] = [t, *s, *p, *np.zeros(m)]
        E = self._eval(self.E, args, (k, size), n)
        hess = self._eval(self.hess, args, (size, size), n)
        rest = self._eval(self.rest, args, (size,), n)
        # Integral action: k + 1 coefficients, the first on the integrals of grad f0.
        shift = 1 if self.integral else 0
        c = sum(d.dynamics.coefficients[j + shift] * E[j] for j in range(k)) - rest
        if self.integral:
            c = c + d.dynamics.coefficients[0] * s[self.integral]
        z = np.linalg.solve(np.moveaxis(hess, -1, 0), np.moveaxis(c, -1, 0)[..., None])[..., 0].T
        v = np.array(
            [
                s[d.closed_loop.state_names.index(d.closed_loop.padding[i][0])]
                if d.closed_loop.padding[i]
                else z[i]
                for i in range(m)
            ]
        )
        if self.mechanics is None:
            R = self._eval(self.R, args, (m, m), n)
            pv = self._eval(self.p, args, (m,), n)
        else:
            nq = self.coordinates
            values: list[object] = []
            for _, read, before, function in self.definitions:
                value = function(*(args[i] for i in read), *(values[i] for i in before))
                values.append(np.broadcast_to(np.asarray(value, dtype=float), (n,)))
            full = [*args, *values]
            M = np.moveaxis(self._eval(self.mass, full, (nq, nq), n), -1, 0)
            F = self._eval(self.forces, full, (nq,), n)
            B = self._eval(self.gain, full, (nq, m), n)
            J = np.moveaxis(self._eval(self.jacobian, args, (m, nq), n), -1, 0)
            acc = np.linalg.solve(M, np.moveaxis(F, -1, 0)[..., None])[..., 0]
            W = np.linalg.solve(M, np.moveaxis(B, -1, 0))
            R = np.moveaxis(J @ W, 0, -1)
            pv = (J @ acc[..., None])[..., 0].T + self._eval(self.curvature, args, (m,), n)
        b = v - pv
        if self.eso is not None:
            b = b - np.array([s[rows[-1]] for rows in self.eso_rows])
        w = np.linalg.solve(np.moveaxis(R, -1, 0), np.moveaxis(b, -1, 0)[..., None])[..., 0].T
        if self.mechanics is None:
            field = self._eval(self.field, [t, *s, *p, *w], (len(d.linearization.extension.x),), n)
        else:
            accel = acc + (W @ w.T[..., None])[..., 0]
            field = np.vstack([s[nq : 2 * nq], accel.T])
        pad = []
        for i, chain in enumerate(d.closed_loop.padding):
            for j in range(len(chain)):
                pad.append(
                    s[d.closed_loop.state_names.index(chain[j + 1])] if j + 1 < len(chain) else z[i]
                )
        for i, chain in enumerate(self.multipliers):
            for j in range(k):
                pad.append(s[chain[j + 1]] if j + 1 < k else z[m + i])
        if self.eso is not None:
            # The observer: (s + omega)^(r+1) by the binomial gains, on e = h(x) - eta_0.
            y = self._eval(self.h, args, (m,), n)
            for i, rows in enumerate(self.eso_rows):
                r = len(rows) - 1
                e = y[i] - s[rows[0]]
                for j in range(r + 1):
                    gain = math.comb(r + 1, j + 1) * self.eso ** (j + 1)
                    above = s[rows[j + 1]] if j + 1 < r else (v[i] if j + 1 == r else 0.0)
                    pad.append(above + gain * e)
        pad += list(E[0][: len(self.integral)])
        ds = np.vstack([field, *pad]) if pad else field
        u = np.array(
            [
                s[d.closed_loop.state_names.index(uj.name)]
                if uj.name in d.linearization.extension.states
                else w[j]
                for j, uj in enumerate(d.model.u)
            ]
        )
        return u, ds

    def margins(self, t: float, s: np.ndarray, p: np.ndarray) -> np.ndarray:
        """Each inequality's margin ``s(t) - g_i(y, t)`` (q, N): the law is defined where all
        are positive (no rows without inequalities)."""
        count = len(self.d.model.constraints)
        args: list[object] = [t, *s, *p, *np.zeros(self.m)]
        return self._eval(self.margin, args, (count,), s.shape[1])

    def domain(
        self, t: float, s: np.ndarray, p: np.ndarray, rounding: float = 1e-9
    ) -> tuple[np.ndarray, np.ndarray]:
        """The columns of ``s`` inside every barrier, and those past one (boolean masks).

        A margin within ``rounding`` of 0 is in neither: the generated code may round it
        to either side.
        """
        margins = self.margins(t, s, p)
        return np.all(margins > rounding, axis=0), np.any(margins < -rounding, axis=0)

    def optimality_error(self, t: float, s: np.ndarray, p: np.ndarray) -> np.ndarray:
        """E of shape (k, m + q, N)."""
        args: list[object] = [t, *s, *p, *np.zeros(self.m)]
        return self._eval(self.E, args, (self.k, self.n), s.shape[1])


def assert_matches_oracle(
    oracle: Oracle,
    modules: Sequence[object],
    states: np.ndarray,
    times: Sequence[float],
    tolerance: float = 1e-9,
) -> None:
    """Every module's ``control`` and ``rhs`` equal the oracle's at ``states`` and ``times``.

    Relative to the largest entry of the oracle's values, so that near-zero entries of a
    batch do not set the scale.
    """
    p = np.array(list(modules[0].PARAMETERS.values()))  # type: ignore[attr-defined]
    for t in times:
        inside, outside = oracle.domain(t, states, p)
        for mod in modules:
            if outside.any():
                # Past a barrier the law refuses, in every backend alike.
                with pytest.raises(mod.OutsideBarrierError):  # type: ignore[attr-defined]
                    mod.control(t, states[:, outside])  # type: ignore[attr-defined]
        if not inside.any():
            continue
        within = states[:, inside]
        u_ref, ds_ref = oracle.law(t, within, p)
        for mod in modules:
            u, ds = mod.control(t, within), mod.rhs(t, within)  # type: ignore[attr-defined]
            scale_u, scale_ds = np.abs(u_ref).max(), np.abs(ds_ref).max()
            np.testing.assert_allclose(u, u_ref, rtol=tolerance, atol=tolerance * scale_u)
            np.testing.assert_allclose(ds, ds_ref, rtol=tolerance, atol=tolerance * scale_ds)
