"""Stage 5: print kernels with a backend's printer and render its templates.

The result is ``{file name: text}``; nothing here touches the disk. Every file
carries a stamp (tool and sympy versions, spec file name and SHA-256, template) and a
content hash over the rest of the file, which lets the writer tell an untouched
generated file from one a person edited. The kernels' expressions are either engine's
(:mod:`tvopt_codegen.symbolic`): this stage imports no engine itself.
"""

from __future__ import annotations

import dataclasses
import functools
import math
import re
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from pathlib import Path, PurePath
from typing import Any

import jinja2

from tvopt_codegen import __version__
from tvopt_codegen import symbolic as sx
from tvopt_codegen.backends import BACKENDS, Backend
from tvopt_codegen.contract import CALLER_FAULTS, FUNCTIONS, PIVOT_TOLERANCE, statuses
from tvopt_codegen.cse import symbols_in
from tvopt_codegen.derivation.robust import GRAM_TOLERANCE, STEP_TOLERANCE
from tvopt_codegen.emit.stamp import HASH_PLACEHOLDER, stamp_hash
from tvopt_codegen.errors import TvoptError
from tvopt_codegen.lowering.ir import Kernel, KernelSet
from tvopt_codegen.spec import BUNDLED_SUFFIX
from tvopt_codegen.spec.estimator import FORGETTING_GAP


class CodegenError(TvoptError):
    """A template or printer failed: a bug in tvopt-codegen, not in the spec."""


def template_dir() -> Path:
    """The folder holding the templates: the checkout's ``templates/`` or the wheel's copy.

    A wheel installs ``templates/`` as the data folder ``tvopt_codegen/templates``; a
    source checkout (and an editable install) has it beside the package.
    """
    # This module is tvopt_codegen/renderer/rendering.py: the package is two folders up.
    package = Path(__file__).resolve().parents[1]
    for candidate in (package.parent / "templates", package / "templates"):
        if (candidate / "python").is_dir():
            return candidate
    raise CodegenError(f"templates not found beside {package}: the installation is incomplete")


@functools.lru_cache(maxsize=8)
def environment(root: Path | None = None) -> jinja2.Environment:
    """The jinja environment of a template folder: strict and whitespace-exact.

    ``root`` None is the shipped ``templates/``; a backend from another package brings
    its own folder (which may still import the shipped macros).
    """
    from tvopt_codegen.emit.caches import template_cache  # noqa: PLC0415

    folders = [str(template_dir())] if root is None else [str(root), str(template_dir())]
    env = jinja2.Environment(
        loader=jinja2.FileSystemLoader(folders),
        bytecode_cache=template_cache(),
        undefined=jinja2.StrictUndefined,
        trim_blocks=True,
        lstrip_blocks=True,
        keep_trailing_newline=True,
        autoescape=False,
    )
    env.filters["comment"] = comment_text
    env.filters["docstring"] = docstring_text
    env.filters["md"] = markdown_text
    env.filters["md_code"] = markdown_code
    env.filters["xml"] = xml_text
    env.filters["c_string"] = c_string
    env.filters["pyrepr"] = repr
    env.filters["pytuple"] = lambda values: repr(tuple(values))
    env.filters["pyfloats"] = float_tuple
    env.filters["c_double"] = c_double
    # A macro's text ends with a newline, and so does the line that calls it.
    env.filters["chomp"] = lambda text: str(text).removesuffix("\n")
    # Each backend's own filters (the Python backend's register renaming, ...).
    for backend in BACKENDS.values():
        if backend.filters is not None:
            env.filters.update(backend.filters())
    return env


def float_tuple(values: Iterable[float]) -> str:
    """Floats as a Python tuple, an infinity as ``math.inf`` (``repr`` writes ``inf``)."""
    items = [
        repr(v) if math.isfinite(v) else ("math.inf" if v > 0 else "-math.inf") for v in values
    ]
    return "(" + ", ".join(items) + ("," if len(items) == 1 else "") + ")"


def c_double(value: float) -> str:
    """A double as C source: ``repr``, an infinity as ``INFINITY`` (from math.h)."""
    if math.isfinite(value):
        return repr(value)
    return "INFINITY" if value > 0 else "-INFINITY"


def comment_text(value: object) -> str:
    """Make text safe inside a one-line ``#``, ``//`` or ``/* */`` comment.

    Line breaks fold to spaces, ``*/`` cannot close a C comment, ``??`` cannot start a
    trigraph (``??/`` is a backslash under -std=c99), and a trailing backslash cannot
    continue the line.
    """
    text = " ".join(str(value).split())
    text = "".join(ch if ch.isprintable() else "?" for ch in text)
    text = text.replace("*/", "* /")
    while "??" in text:  # "???/" would otherwise keep a "??/"
        text = text.replace("??", "? ?")
    return text.rstrip("\\")


def markdown_code(value: object) -> str:
    """``value`` as a Markdown code span that no backtick in it can close.

    The fence is one backtick longer than the longest run inside (CommonMark), padded by
    spaces; characters that are not printable show as ``?``.
    """
    text = "".join(ch if ch.isprintable() else "?" for ch in str(value))
    longest = max((len(run) for run in re.findall("`+", text)), default=0)
    fence = "`" * (longest + 1)
    return f"{fence} {text} {fence}" if longest else f"{fence}{text}{fence}"


def markdown_text(value: object) -> str:
    """Make text safe in Markdown, where many viewers render raw HTML.

    ``<``, ``>`` and ``&`` become entities, which every viewer shows as the characters:
    a description holding ``<script>`` or ``<img onerror=...>`` stays text.
    """
    return str(value).replace("&", "&amp;").replace("<", "&lt;").replace(">", "&gt;")


def c_string(value: object) -> str:
    """``value`` as a C string literal.

    Quotes, backslashes, question marks (trigraphs in C99) and every character outside
    printable ASCII are escaped, so that any text a user wrote compiles as the same bytes.

    Parameters
    ----------
    value : object
        The text.

    Returns
    -------
    str
        A double-quoted C literal.
    """
    out = []
    for byte in str(value).encode():
        char = chr(byte)
        if char in '"\\?':
            out.append("\\" + char)
        elif 32 <= byte < 127:
            out.append(char)
        else:
            # Octal escapes take at most three digits: the next character cannot join it.
            out.append(f"\\{byte:03o}")
    return '"' + "".join(out) + '"'


def xml_text(value: object) -> str:
    """Make text safe in an XML attribute or element (one line)."""
    text = " ".join(str(value).split())
    text = "".join(ch if ch.isprintable() else "?" for ch in text)
    for raw, entity in (("&", "&amp;"), ("<", "&lt;"), (">", "&gt;"), ('"', "&quot;")):
        text = text.replace(raw, entity)
    # Never "--" (an XML comment may not hold it): "---" takes two passes.
    while "--" in text:
        text = text.replace("--", "- -")
    return text


def docstring_text(value: object) -> str:
    """Make text safe inside a triple-quoted Python docstring."""
    lines = str(value).splitlines()
    cleaned = ["".join(ch if ch.isprintable() else "?" for ch in line).rstrip() for line in lines]
    return "\n".join(cleaned).replace("\\", "\\\\").replace('"""', '\\"\\"\\"')


@dataclass(frozen=True)
class PrintedSlot:
    """One unpacked input element: generated name, index, and the user's label."""

    symbol: str
    index: int
    label: str


@dataclass(frozen=True)
class PrintedArg:
    """A kernel argument with the slots the kernel actually reads."""

    name: str
    doc: str
    slots: tuple[PrintedSlot, ...]
    used: bool
    size: int = 0

    @property
    def unpack(self) -> str:
        """The targets of one unpacking of the whole argument (``_`` for unread slots)."""
        names = ["_"] * self.size
        for slot in self.slots:
            names[slot.index] = slot.symbol
        return ", ".join(names) + ("," if self.size == 1 else "")


#: An output with at least this many structurally zero elements, and as many zeros as
#: other elements, is printed as zeros and its nonzero elements (a team's Hessian is
#: almost all zeros: a dense listing is quadratic in the number of agents).
SPARSE_OUTPUT_ZEROS = 16


@dataclass(frozen=True)
class PrintedOutput:
    """An output array: shape and ``(index, flat index, code)`` per element (row-major).

    When :attr:`sparse`, ``elements`` holds the nonzero elements only and the template
    fills the rest with zeros.
    """

    name: str
    doc: str
    shape: tuple[int, ...]
    elements: tuple[tuple[str, int, str], ...]
    sparse: bool = False

    @property
    def size(self) -> int:
        """Number of elements."""
        return math.prod(self.shape)


@dataclass(frozen=True)
class PrintedKernel:
    """A kernel as text fragments for the templates."""

    name: str
    doc: str
    args: tuple[PrintedArg, ...]
    batch_arg: str
    body: tuple[tuple[str, str], ...]
    outputs: tuple[PrintedOutput, ...]
    ops: int
    ops_before_cse: int


def print_kernel(kernel: Kernel, printer: Any) -> PrintedKernel:
    """Print every expression of a kernel with the backend's printer."""
    # Each output's elements as expressions (an output may hold a plain number, a
    # structural zero) and which are zero, asked once per element of the engine's own
    # zero: a comparison with the int 0 converts it each time (4x the comparison).
    nought = sx.ZERO
    columns = []
    for out in kernel.outputs:
        values = [e if isinstance(e, sx.Basic) else sx.sympify(e) for e in out.exprs]
        columns.append((values, [e == nought for e in values]))
    # The zeros read no symbol: a team's Hessian is almost all zeros.
    used = symbols_in(
        [value for _, value in kernel.body]
        + [e for values, zero in columns for e, z in zip(values, zero, strict=True) if not z]
    )
    args = []
    for arg in kernel.inputs:
        slots = tuple(
            PrintedSlot(sym.name, i, label)
            for i, (sym, label) in enumerate(zip(arg.symbols, arg.labels, strict=True))
            if sym in used
        )
        used_arg = bool(slots) or (arg.name == "t" and sx.symbol("t") in used)
        args.append(PrintedArg(arg.name, arg.doc, slots, used_arg, len(arg.symbols)))
    # The argument whose last axis is the batch; none for a kernel of time and
    # parameters alone (jet_time), whose outputs are the same for every state.
    batch = next((arg.name for arg in kernel.inputs if arg.name in ("s", "y", "h", "x")), "")
    body = tuple((sym.name, printer.doprint(value)) for sym, value in kernel.body)
    outputs = []
    for out, (values, zero) in zip(kernel.outputs, columns, strict=True):
        indices = _indices(out.shape)
        zeros = sum(zero)
        sparse = zeros >= SPARSE_OUTPUT_ZEROS and 2 * zeros >= len(values)
        elements = tuple(
            (", ".join(map(str, index)) if index else "...", flat, printer.doprint(e))
            for flat, (index, e) in enumerate(zip(indices, values, strict=True))
            if not (sparse and zero[flat])
        )
        outputs.append(PrintedOutput(out.name, out.doc, out.shape, elements, sparse))
    return PrintedKernel(
        kernel.name,
        kernel.doc,
        tuple(args),
        batch,
        body,
        tuple(outputs),
        kernel.ops,
        kernel.ops_before_cse,
    )


def _indices(shape: tuple[int, ...]) -> list[tuple[int, ...]]:
    if not shape:
        return [()]
    rest = _indices(shape[1:])
    return [(i, *r) for i in range(shape[0]) for r in rest]


#: The context variable through which one controller's templates share what they have
#: rendered already: ``{template name: text before its hash}``. The C header's stack
#: bound renders the C source to parse it (:func:`~tvopt_codegen.backends.c.stack.header_bounds`);
#: the source is then not rendered twice.
RENDERED = "rendered_texts"


def render_template(template_name: str, context: dict[str, Any], root: Path | None = None) -> str:
    """Render one template and fill in its content hash.

    Parameters
    ----------
    template_name : str
        Path under ``templates/``.
    context : dict
        Template variables; ``content_hash`` and ``template_name`` are added.
    root : pathlib.Path, optional
        The backend's template folder (default: the shipped ``templates/``).

    Returns
    -------
    str
        The file text, stamped.
    """
    full = {**context, "content_hash": HASH_PLACEHOLDER, "template_name": template_name}
    try:
        # A text another template of the same controller rendered already (RENDERED).
        text: str | None = context.get(RENDERED, {}).get(template_name)
        if text is None:
            text = environment(root).get_template(template_name).render(full)
    except jinja2.TemplateError as exc:
        raise CodegenError(f"template {template_name}: {exc}") from exc
    return text.replace(HASH_PLACEHOLDER, stamp_hash(text), 1)


def _printings(kernels: KernelSet, backend: Backend) -> dict[str, dict[str, PrintedKernel]]:
    """Every printing of the kernels a backend's templates read: ``""`` and each variant's."""
    printings: dict[str, dict[str, PrintedKernel]] = {}
    if backend.joint is not None:
        joint = backend.joint()
        once = {k.name: print_kernel(k, joint) for k in kernels.kernels}
        for key, text in joint.texts().items():
            printings[key] = {name: _translated(p, text) for name, p in once.items()}
    if "" not in printings:
        printer = backend.printer()
        printings[""] = {k.name: print_kernel(k, printer) for k in kernels.kernels}
    for key, make in backend.variants:
        if key not in printings:
            printings[key] = {k.name: print_kernel(k, make()) for k in kernels.kernels}
    return printings


def _translated(printed: PrintedKernel, text: Callable[[str], str]) -> PrintedKernel:
    """A printed kernel with every code fragment passed through ``text``."""
    outputs = tuple(
        dataclasses.replace(out, elements=tuple((i, f, text(c)) for i, f, c in out.elements))
        for out in printed.outputs
    )
    body = tuple((name, text(code)) for name, code in printed.body)
    return dataclasses.replace(printed, body=body, outputs=outputs)


def template_context(kernels: KernelSet, backend: Backend | str) -> dict[str, Any]:
    """The variables every template of ``backend`` sees (docs/backends.md lists them).

    Parameters
    ----------
    kernels : KernelSet
        The lowered controller.
    backend : Backend or str
        The backend (its printers print the kernels) or its name.

    Returns
    -------
    dict
        Template variables.
    """
    if isinstance(backend, str):
        backend = BACKENDS[backend]
    d = kernels.derivation
    printings = _printings(kernels, backend)
    printed = printings[""]
    variants = {f"kernels_{key}": printings[key] for key, _ in backend.variants}
    return {
        "d": d,
        "backend": backend.name,
        "spec": d.spec,
        "kernels": printed,
        **variants,
        "tool_version": __version__,
        # The engine that derived the law, and its version (read without importing SymPy).
        "engine": sx.engine_version(),
        "spec_file": PurePath(d.spec.source.removesuffix(BUNDLED_SUFFIX)).name,
        "extension_counts": dict(d.linearization.extension.counts),
        "parameters": dict(d.spec.parameters),
        "relative_degree": dict(zip(d.spec.outputs, d.linearization.relative_degree, strict=True)),
        "prefix": d.spec.name,
        "guard": d.spec.name.upper(),
        "r_blocks": kernels.r_blocks,
        "plan": kernels.plan,
        "robust": d.robustness,
        "gram_tolerance": GRAM_TOLERANCE,
        "step_tolerance": STEP_TOLERANCE,
        **contract_context(kernels),
        "estimator_gains": d.estimator.gains if d.estimator is not None else (),
        "estimator_order": d.estimator.order if d.estimator is not None else 0,
        "estimator_gap": FORGETTING_GAP,
        **(backend.context(kernels) if backend.context is not None else {}),
    }


def contract_context(kernels: KernelSet) -> dict[str, Any]:
    """The contract's tables as every template reads them (:mod:`tvopt_codegen.contract`).

    Parameters
    ----------
    kernels : KernelSet
        The lowered controller.

    Returns
    -------
    dict
        ``statuses``, ``status_details`` (a spec's own words on where a status happens,
        by status name), ``caller_faults``, ``functions``, ``sizes`` (the sizes that
        :attr:`~tvopt_codegen.contract.Function.shape` names) and
        ``pivot_tolerance``.
    """
    d = kernels.derivation
    dependent = (
        "it is where " + "; ".join(d.decoupling.dependent_set) if d.decoupling.dependent_set else ""
    )
    return {
        "statuses": statuses(),
        "status_details": {
            "SINGULAR_DECOUPLING": d.decoupling.singular_text,
            "DEPENDENT_CONSTRAINTS": dependent,
        },
        "caller_faults": CALLER_FAULTS,
        "functions": FUNCTIONS,
        "sizes": {
            "n_inputs": len(d.spec.inputs),
            "n_states": len(d.closed_loop.state_names),
            "n_outputs": len(d.spec.outputs),
            "n_plant_states": len(d.spec.states),
            "n_kkt": d.jet.n_kkt,
            "k": d.dynamics.k,
        },
        "pivot_tolerance": PIVOT_TOLERANCE,
    }


def render(kernels: KernelSet, backend: Backend | str) -> dict[str, str]:
    """Render all files of one backend for one controller.

    Parameters
    ----------
    kernels : KernelSet
        The lowered controller.
    backend : Backend or str
        The backend or its name.

    Returns
    -------
    dict of str to str
        File name (relative to the output folder) to file text, in template order.
    """
    if isinstance(backend, str):
        backend = BACKENDS[backend]
    context = {**template_context(kernels, backend), RENDERED: {}}
    name = kernels.derivation.spec.name
    return {
        pattern.format(name=name): render_template(template_name, context, backend.template_root)
        for template_name, pattern in backend.templates
    }
