"""Lowering: the derivation's law as kernels, straight-line programs a backend prints.

The lowering table (``ir``), the IR's types (``kernel``), the execution plan (``plan``)
and the printers' shared canonical order (``printers``); ``cse/`` numbers and assembles
the kernels.
"""
