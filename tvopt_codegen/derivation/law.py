"""The paper's control law as data: the last step of the derivation.

Given the derived quantities (the gradient jet, the Hessian's entries, R, the
extended plant, the padding chains), this module writes the law down, once, as
expressions that lowering only has to slice into kernels (``ir.lower``) and the report
can show:

- ``Hess y_imp^(k) = sum_j a_j grad^(j) f0 - rest`` (eq. (13) of the paper solved for
  the highest derivative): :attr:`Law.jet_rhs`, with the Hessian's pattern
  :attr:`Law.hessian_pattern`; when the Hessian is constant, its exact inverse applied
  at generation time, :attr:`Law.y_imp`;
- the new input ``v``: ``y_imp^(k)`` for an output of full relative degree, the first
  padding state otherwise (the non-uniform theorem);
- ``w = R^-1 (v - p)``, solved at run time over R's diagonal blocks
  (:attr:`Law.r_blocks`);
- the closed-loop field ``f + G w`` with the padding chains, and the map from ``w`` and
  the state to the plant input ``u``.

The unknowns solved for at run time are symbols of their own: ``_w0, ...`` (the input
of the extended plant), ``_z0, ...`` (``y_imp^(k)``) and the Hurwitz coefficients
``_a0, ...``. A leading underscore keeps them apart from every user name.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

from tvopt_codegen import symbolic as sx
from tvopt_codegen.derivation.rejection import Rejection, observer_field
from tvopt_codegen.maths.lie import Extension, connected_groups, control_affine, nonzero_entries


def symbols(prefix: str, count: int) -> tuple[sx.Expr, ...]:
    """``_<prefix>0, _<prefix>1, ...``: real symbols no user name can take."""
    return tuple(sx.symbol(f"_{prefix}{i}") for i in range(count))


@dataclass(frozen=True)
class Law:
    """The implicit trajectory planning law of one spec.

    Attributes
    ----------
    a, w, z : tuple of symbol
        The Hurwitz coefficients ``a_j``, the extended plant's input ``w`` and
        ``z = y_imp^(k)`` (then ``nu^(k)`` with equalities), as they appear in the
        expressions below.
    hessian : tuple of expression
        ``grad_yy f0``, (m, m) row-major, over the derivation's programs; with
        equalities the KKT matrix ``[[grad_yy L, J_a^T], [J_a, 0]]``, (m + q, m + q).
    hessian_pattern : tuple of (int, int)
        The entries ``(i, j), i >= j`` of the Hessian's lower triangle that the
        generated code stores: the structurally nonzero ones and the whole diagonal.
    jet_rhs : tuple of expression
        ``sum_j a_j grad^(j) f0 - rest``, so that ``Hess z = jet_rhs``.
    y_imp : tuple of expression or None
        ``Hess^-1 jet_rhs`` with the exact inverse of a constant Hessian (a quadratic
        f0); None when the Hessian varies and ``z`` is solved for at run time.
    v : tuple of expression
        The new input per output: ``z_i``, or the first padding state of output i.
    r_blocks : tuple of tuple of int
        R's diagonal blocks (output indices, in order): a team of agents has one each.
    r_entries : tuple of expression
        R's entries block by block, each block row by row: the zeros between blocks
        are never stored.
    closed_loop : tuple of expression
        The closed-loop vector field: ``f + G w`` of the extended plant, then the
        padding chains (each state's derivative is the next, the last one's ``z_i``).
    plant_input : tuple of expression
        The plant input ``u``: a prolonged input is a state of the extension, the
        others are entries of ``w``.
    chains : tuple of (int, int)
        The integrator chains among the controller's own states (the closed-loop state
        after the plant's: extension, then padding): ``(first index among them, length)``
        each, extension chains first. A chain's last state is driven by an entry of
        ``w`` (extension) or of ``z`` (padding): its entry of :attr:`closed_loop`. Held
        constant over a sampling interval, the chain moves by a finite Taylor polynomial.
        The extended-state observer's states are no chain: the sampled controller
        moves them by the observer's own discrete step.
    lumped : tuple of expression
        Per output, the lumped disturbance the law cancels, ``R w = v - p - lumped``:
        the extended-state observer's ``d_hat`` state, else 0.
    """

    a: tuple[sx.Expr, ...]
    w: tuple[sx.Expr, ...]
    z: tuple[sx.Expr, ...]
    hessian: tuple[sx.Expr, ...]
    hessian_pattern: tuple[tuple[int, int], ...]
    jet_rhs: tuple[sx.Expr, ...]
    y_imp: tuple[sx.Expr, ...] | None
    v: tuple[sx.Expr, ...]
    r_blocks: tuple[tuple[int, ...], ...]
    r_entries: tuple[sx.Expr, ...]
    closed_loop: tuple[sx.Expr, ...]
    plant_input: tuple[sx.Expr, ...]
    chains: tuple[tuple[int, int], ...]
    lumped: tuple[sx.Expr, ...] = ()

    @property
    def constant_hessian(self) -> bool:
        """Whether the Hessian is a constant matrix (and :attr:`y_imp` is the law)."""
        return self.y_imp is not None


def diagonal_blocks(matrix: sx.Expr) -> tuple[tuple[int, ...], ...]:
    """The finest symmetric block-diagonal partition of a square matrix's pattern.

    Rows ``i`` and ``j`` share a block when ``matrix[i, j]`` or ``matrix[j, i]`` is not
    structurally zero (connected components, found by union-find). Blocks are ordered
    by their first index.
    """
    links = [(i, j) for i, j, _ in nonzero_entries(matrix) if i != j]
    return tuple(tuple(block) for block in connected_groups(range(matrix.shape[0]), links))


def symmetric_dense(
    entries: Sequence[tuple[tuple[int, int], sx.Expr]], n: int
) -> tuple[sx.Expr, ...]:
    """A symmetric (n, n) matrix, row-major, from its lower entries (zero elsewhere).

    Zeros first, then the entries and their mirror images: a team's Hessian is n^2
    entries, almost all zero, and a lookup per entry was a fifth of a second at n = 512.
    """
    dense: list[sx.Expr] = [sx.ZERO] * (n * n)
    for (i, j), entry in entries:
        dense[i * n + j] = dense[j * n + i] = entry
    return tuple(dense)


def _chains(
    extension: Extension, chains: Sequence[Sequence[str]], observer: int, integral: int
) -> tuple[tuple[int, int], ...]:
    """``Law.chains``: each ``(first index among the controller states, length)``.

    The extension's chains, then the padding and multiplier chains, then one per integral.
    The ``observer`` states of the extended-state observer sit between the multipliers'
    and the integrals' and are no chain.
    """
    out: list[tuple[int, int]] = []
    start = 0
    for _, count in extension.counts:
        out.append((start, count))
        start += count
    for chain in chains:
        if chain:
            out.append((start, len(chain)))
            start += len(chain)
    start += observer
    return (*out, *((start + j, 1) for j in range(integral)))


def control_law(
    *,
    hessian_entries: Sequence[tuple[tuple[int, int], sx.Expr]],
    grad_jet: Sequence[Sequence[sx.Expr]],
    rest: Sequence[sx.Expr],
    R: sx.Expr,
    extension: Extension,
    plant_inputs: Sequence[sx.Expr],
    padding: Sequence[Sequence[str]],
    states: Sequence[sx.Expr],
    state_names: Sequence[str],
    multipliers: Sequence[Sequence[str]] = (),
    integral: Sequence[str] = (),
    eso: Rejection | None = None,
    outputs: Sequence[sx.Expr] = (),
) -> Law:
    """Write the law down from the derived quantities.

    Parameters
    ----------
    hessian_entries : sequence of ((int, int), expression)
        The nonzero entries ``(i, j), i >= j`` of the Hessian's lower triangle.
    grad_jet : sequence of sequence of expression
        ``grad^(j) f0`` for ``j = 0 .. k-1``.
    rest : sequence of expression
        ``grad^(k) f0`` with ``y^(k) = 0``.
    R : matrix
        The decoupling matrix (m, m).
    extension : Extension
        The extended plant.
    plant_inputs : sequence of symbol
        The plant's inputs ``u``.
    padding : sequence of sequence of str
        The padding states of each output, in chain order.
    states, state_names : sequence
        The closed-loop state: symbols and names, in order.
    multipliers : sequence of sequence of str, optional
        With equalities, each multiplier's chain of states ``nu, nu', ..., nu^(k-1)``:
        the jet, the Hessian and ``rest`` are then the KKT system's, over the outputs
        and the multipliers, and ``z`` holds ``nu^(k)`` after ``y_imp^(k)``.
    integral : sequence of str, optional
        With integral action, the states ``z_I`` holding the integral of each entry of
        ``grad f0``: there are then k + 1 coefficients, ``a_0`` multiplies ``z_I`` and
        ``a_{j+1}`` multiplies ``grad^(j) f0``, so that ``col(z_I, E)' = H_I col(z_I, E)``.
    eso : Rejection, optional
        The extended-state observer: its states' rows join the field (after the
        multipliers', before the integrals') and its ``d_hat`` is cancelled.
    outputs : sequence of expression, optional
        With ``eso``, ``h(x)``: what the observer measures.

    Returns
    -------
    Law
        The law.
    """
    m, k = len(plant_inputs), len(grad_jet)
    # n = m + q unknowns: y^(k), then nu^(k) of each equality.
    n = len(grad_jet[0])
    shift = 1 if integral else 0
    a, w, z = symbols("a", k + shift), symbols("w", m), symbols("z", n)
    state_of = dict(zip(state_names, states, strict=True))
    value = dict(hessian_entries)
    hessian = symmetric_dense(hessian_entries, n)
    pattern = sorted(value)
    if not any(i == j for i, j in pattern):
        pattern = sorted({*pattern, *((i, i) for i in range(n))})
    jet_rhs = tuple(
        sum((a[j + shift] * grad_jet[j][i] for j in range(k)), sx.Integer(0)) - rest[i]
        for i in range(n)
    )
    if integral:
        jet_rhs = tuple(
            a[0] * state_of[name] + entry for name, entry in zip(integral, jet_rhs, strict=True)
        )
    y_imp = None
    if all(sx.sympify(e).is_Number for e in value.values()):
        # A constant Hessian (quadratic f0) is inverted once, exactly, at generation time:
        # a constant, not a symbolic inverse of a function, and no run-time Cholesky.
        # (The derivation has checked it is nonsingular.)
        inverse = sx.Matrix(n, n, list(hessian)).inv()
        y_imp = tuple(inverse * sx.Matrix(list(jet_rhs)))
    v = tuple(state_of[padding[i][0]] if padding[i] else z[i] for i in range(m))
    r_blocks = diagonal_blocks(R)
    r_entries = tuple(R[i, j] for block in r_blocks for i in block for j in block)
    ext = extension
    field = control_affine(ext.f, ext.G, w)
    for i, chain in enumerate(padding):
        for j in range(len(chain)):
            field.append(state_of[chain[j + 1]] if j + 1 < len(chain) else z[i])
    for index, chain in enumerate(multipliers):
        for j in range(len(chain)):
            field.append(state_of[chain[j + 1]] if j + 1 < len(chain) else z[m + index])
    lumped: tuple[sx.Expr, ...] = tuple(sx.Integer(0) for _ in range(m))
    if eso is not None:
        estimates = [[state_of[name] for name in chain] for chain in eso.states]
        field += observer_field(eso, estimates, outputs, v)
        lumped = tuple(chain[-1] for chain in estimates)
    # The integral states last: each integrates its entry of grad f0 (of the KKT map).
    field += [grad_jet[0][i] for i in range(len(integral))]
    plant_input = tuple(u if u.name in ext.states else w[j] for j, u in enumerate(plant_inputs))
    chains = _chains(ext, (*padding, *multipliers), len(eso.names) if eso else 0, len(integral))
    return Law(
        a=a,
        w=w,
        z=z,
        hessian=hessian,
        hessian_pattern=tuple(pattern),
        jet_rhs=jet_rhs,
        y_imp=y_imp,
        v=v,
        r_blocks=r_blocks,
        r_entries=r_entries,
        closed_loop=tuple(field),
        plant_input=plant_input,
        chains=chains,
        lumped=lumped,
    )
