"""Rendering: kernels printed by a backend into its templates, and the C run-time library.

Not named ``render``: ``tvopt_codegen.render`` is the stage's function.
"""
