"""The Python backend's template filters: register renaming and NumPy aliases.

Its one-point law writes several kernels into one function body; these filters make their
names few and reused (:func:`registers`) and list the NumPy functions it aliases
(:func:`numpy_aliases`).
"""

from __future__ import annotations

import heapq
import re
from typing import Any

from tvopt_codegen.renderer.rendering import PrintedArg, PrintedKernel, PrintedOutput, PrintedSlot

#: A slot's or temporary's name, captured: ``split`` puts the names at odd places.
_NAME = re.compile(r"\b(_[A-Za-z]+\d+)\b")


_ALIAS = re.compile(r"\b_np_([A-Za-z_][A-Za-z0-9_]*)\(")


def numpy_aliases(kernels: Any) -> list[str]:
    """The NumPy functions the one-point kernels call through ``_np_<name>`` aliases."""
    names: set[str] = set()
    for kernel in kernels:
        codes = [code for _, code in kernel.body]
        codes += [code for out in kernel.outputs for _, _, code in out.elements]
        for code in codes:
            names.update(_ALIAS.findall(code))
    return sorted(names)


def registers(kernel: PrintedKernel) -> PrintedKernel:
    """The kernel with its slots and temporaries renamed ``_r0, _r1, ...``, reusing dead ones.

    A backend that writes several kernels into one function body (the Python backend's
    one-point law) needs their names apart, and few of them: CPython addresses a
    function's first 256 locals with one instruction and every later one with two. A name
    is reused once its value has been read for the last time (linear scan in evaluation
    order: the inputs' unpacking, the body, the outputs), so the kernel needs as many
    names as values live at once; each kernel's names are dead when its outputs are built,
    so consecutive kernels share them.
    """
    # Each code split once at the names it reads (text, name, text, ...): read for the
    # names' last reads and joined again renamed.
    body_pieces = [_NAME.split(code) for _, code in kernel.body]
    output_pieces = [[_NAME.split(code) for _, _, code in out.elements] for out in kernel.outputs]
    statements: list[tuple[list[str], list[str]]] = [
        ([slot.symbol for slot in arg.slots], []) for arg in kernel.args if arg.slots
    ]
    statements += [
        ([name], pieces[1::2]) for (name, _), pieces in zip(kernel.body, body_pieces, strict=True)
    ]
    statements += [([], [n for p in out for n in p[1::2]]) for out in output_pieces]
    own = {slot.symbol for arg in kernel.args for slot in arg.slots}
    own |= {name for name, _ in kernel.body}
    last: dict[str, int] = {}
    for index, (_, reads) in enumerate(statements):
        for name in reads:
            if name in own:
                last[name] = index
    mapping: dict[str, str] = {}
    free: list[int] = []
    count = 0
    for index, (targets, reads) in enumerate(statements):
        # Names read here for the last time free their register before the targets take
        # one: the right-hand side is evaluated before the assignment.
        for name in dict.fromkeys(reads):
            if last.get(name) == index and name in mapping:
                heapq.heappush(free, int(mapping[name][2:]))
        for name in targets:
            if free:
                number = heapq.heappop(free)
            else:
                number, count = count, count + 1
            mapping[name] = f"_r{number}"
            if name not in last:  # never read: its register is free again at once
                heapq.heappush(free, number)

    def rename(pieces: list[str]) -> str:
        pieces[1::2] = [mapping.get(name, name) for name in pieces[1::2]]
        return "".join(pieces)

    # Every name is assigned once (the kernels are in SSA form), so one renaming holds
    # for the whole kernel: a register is reused only after its name's last read.
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
            tuple(
                (index, flat, rename(pieces))
                for (index, flat, _), pieces in zip(out.elements, split, strict=True)
            ),
            out.sparse,
        )
        for out, split in zip(kernel.outputs, output_pieces, strict=True)
    )
    body = tuple(
        (mapping[name], rename(pieces))
        for (name, _), pieces in zip(kernel.body, body_pieces, strict=True)
    )
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
