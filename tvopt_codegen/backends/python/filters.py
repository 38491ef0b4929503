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

_NAME = re.compile(r"\b_[A-Za-z]+\d+\b")


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
        # Names read here for the last time free their register before the targets take
        # one: the right-hand side is evaluated before the assignment.
        for name in dict.fromkeys(_NAME.findall(code)):
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

    def rename(code: str) -> str:
        return _NAME.sub(lambda m: mapping.get(m.group(0), m.group(0)), code)

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
