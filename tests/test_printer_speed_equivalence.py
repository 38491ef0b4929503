"""The rendering stage's shortcuts (issue 49) give the texts the plain ways give.

Each shortcut is held against the plain computation it replaces, on a bundled example's
real kernels and C: the printers' memo of a node's arguments, the C source rendered once
for the header's stack bound and for its own file, the stack scanner's bracket matching
and splitting, and the Python backend's register renaming.
"""

from __future__ import annotations

import heapq
import itertools
import re
from typing import Any

import pytest

from tvopt_codegen.backends.c import stack
from tvopt_codegen.backends.python.filters import registers
from tvopt_codegen.backends.python.printer import PythonJointPrinter
from tvopt_codegen.lowering.ir import KernelSet
from tvopt_codegen.renderer.rendering import (
    PrintedArg,
    PrintedKernel,
    PrintedOutput,
    PrintedSlot,
    print_kernel,
    render,
    render_template,
    template_context,
)
from tvopt_codegen.spec import load_spec

#: A bundled example with sums, products, powers, functions and a C pair of many frames.
EXAMPLE = "two_unicycles_barrier"


@pytest.fixture(scope="module")
def kernels() -> KernelSet:
    from tvopt_codegen.derivation import derive
    from tvopt_codegen.lowering.ir import lower

    return lower(derive(load_spec(EXAMPLE)))


def test_one_printer_over_all_kernels_prints_as_a_fresh_printer_per_expression(
    kernels: KernelSet,
) -> None:
    """The memo of nodes, arguments and keys shared across expressions changes no text."""
    shared = PythonJointPrinter()
    expressions = [value for k in kernels.kernels for _, value in k.body]
    expressions += [e for k in kernels.kernels for out in k.outputs for e in out.exprs]
    assert len(expressions) > 100
    for expr in expressions:
        assert shared.doprint(expr) == PythonJointPrinter().doprint(expr)


def test_the_c_source_rendered_for_the_stack_bound_is_the_file(kernels: KernelSet) -> None:
    """``render`` takes the C source from the header's stack pass: the same text, rendered alone."""
    files = render(kernels, "c")
    name = kernels.derivation.spec.name
    alone = render_template("c/controller.c.jinja", template_context(kernels, "c"))
    assert files[f"{name}.c"] == alone
    # The header's bound was computed (its lines are in the header), from that source.
    assert f"{name.upper()}_STACK_BOUND_BYTES" in files[f"{name}.h"]


def _split_plain(tokens: list[str], separator: str) -> list[list[str]]:
    """The scanner's split, token by token (as it was written first)."""
    parts: list[list[str]] = [[]]
    depth = 0
    for token in tokens:
        if token in "([{":
            depth += 1
        elif token in ")]}":
            depth -= 1
        if token == separator and depth == 0:
            parts.append([])
        else:
            parts[-1].append(token)
    return parts


def test_the_stack_scanner_matches_and_splits_as_token_by_token(kernels: KernelSet) -> None:
    files = render(kernels, "c")
    name = kernels.derivation.spec.name
    tokens = stack._tokens(stack._clean(files[f"{name}.c"]))
    assert len(tokens) > 5_000
    closings = stack._closings(tokens)
    openers = [i for i, t in enumerate(tokens) if t in "([{"]
    assert sorted(closings) == openers
    for i in openers:
        assert closings[i] == stack._closing(tokens, i)
    statements = _split_plain(tokens, ";")
    assert stack._split(tokens, ";") == statements
    for statement in statements:
        for separator in (",", "=", ";"):
            assert stack._split(statement, separator) == _split_plain(statement, separator)
    # Unbalanced text: what _closing cannot close, _closings leaves out; extra closers
    # close nothing.
    odd = stack._tokens("f(a[1) ) ] { ( }")  # the ( at 9 is never closed
    assert stack._closings(odd) == {1: 5, 3: 7, 8: 10}
    assert [stack._closing(odd, i) for i in (1, 3, 8)] == [5, 7, 10]
    with pytest.raises(ValueError, match=r"unbalanced \("):
        stack._closing(odd, 9)
    with pytest.raises(ValueError, match=r"unbalanced \{"):
        stack.parse("int f(void) { return 0;", "", 8)


_NAME = re.compile(r"\b_[A-Za-z]+\d+\b")


def _registers_plain(kernel: PrintedKernel) -> PrintedKernel:
    """The register renaming by a substitution per code (as it was first written)."""
    statements: list[tuple[list[str], str]] = [
        ([slot.symbol for slot in arg.slots], "") for arg in kernel.args if arg.slots
    ]
    statements += [([name], code) for name, code in kernel.body]
    statements += [([], " ".join(code for _, _, code in out.elements)) for out in kernel.outputs]
    own = {slot.symbol for arg in kernel.args for slot in arg.slots}
    own |= {name for name, _ in kernel.body}
    last: dict[str, int] = {}
    for index, (_, code) in enumerate(statements):
        for name in _NAME.findall(code):
            if name in own:
                last[name] = index
    mapping: dict[str, str] = {}
    free: list[int] = []
    count = 0
    for index, (targets, code) in enumerate(statements):
        for name in dict.fromkeys(_NAME.findall(code)):
            if last.get(name) == index and name in mapping:
                heapq.heappush(free, int(mapping[name][2:]))
        for name in targets:
            if free:
                number = heapq.heappop(free)
            else:
                number, count = count, count + 1
            mapping[name] = f"_r{number}"
            if name not in last:
                heapq.heappush(free, number)

    def rename(code: str) -> str:
        return _NAME.sub(lambda m: mapping.get(m.group(0), m.group(0)), code)

    args = tuple(
        PrintedArg(
            arg.name,
            arg.doc,
            tuple(PrintedSlot(mapping[s.symbol], s.index, s.label) for s in arg.slots),
            arg.used,
            arg.size,
        )
        for arg in kernel.args
    )
    outputs = tuple(
        PrintedOutput(
            out.name,
            out.doc,
            out.shape,
            tuple((index, flat, rename(code)) for index, flat, code in out.elements),
            out.sparse,
        )
        for out in kernel.outputs
    )
    body = tuple((mapping[name], rename(code)) for name, code in kernel.body)
    return PrintedKernel(
        kernel.name,
        kernel.doc,
        args,
        kernel.batch_arg,
        body,
        outputs,
        kernel.ops,
        kernel.ops_before_cse,
    )


def test_register_renaming_splits_once_and_renames_as_a_substitution(kernels: KernelSet) -> None:
    printer: Any = PythonJointPrinter()
    renamed = 0
    for kernel in kernels.kernels:
        printed = print_kernel(kernel, printer)
        fast = registers(printed)
        assert fast == _registers_plain(printed)
        renamed += sum(
            code != old for (_, code), (_, old) in zip(fast.body, printed.body, strict=True)
        )
    assert renamed > 10  # the kernels' temporaries were renamed, not left alone


def test_the_scanners_short_way_for_a_temporary_sizes_it_as_the_general_way(
    kernels: KernelSet,
) -> None:
    """``const <real> tN = ...;`` sized from its first tokens: the size the general path gives."""
    files = render(
        kernels,
        "c",
    )
    name = kernels.derivation.spec.name
    header, source = stack._clean(files[f"{name}.h"]), stack._clean(files[f"{name}.c"])
    defines = dict(stack._DEFINE.findall(header))
    defines.update(stack._DEFINE.findall(source))
    reals = frozenset(re.findall(r"typedef\s+(?:double|float)\s+(\w+)\s*;", header + source))
    sizes = stack._Sizes(8, defines, reals)
    tokens = stack._tokens(stack._DIRECTIVE.sub(" ", source))
    short = 0
    # The statements between semicolons and braces, as _frame cuts a body (a for's
    # header is cut too, and is no declaration either way).
    for ends, group in itertools.groupby(tokens, key=lambda t: t in (";", "{", "}")):
        statement = list(group)
        if ends:
            continue
        size = stack._scalar_declaration(statement, sizes)
        if size is None:
            continue
        short += 1
        assert stack._is_declaration(statement, sizes)
        words, rest = stack._type_words(statement, sizes)
        assert sizes.declarators(sizes.type_size(words), rest) == [(size, size)]
    assert short > 100
    # Not taken where a second declarator, a pointer or an array follows.
    for text in ("const double a = 1, b = 2", "const double *p = q", "const int n[2] = {1, 2}"):
        assert stack._scalar_declaration(stack._tokens(text), sizes) is None
