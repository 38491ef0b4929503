"""The mathematics the derivation stands on.

Jets and total derivatives, Lie derivatives, exact numbers, the sparse LDL^T program,
Hurwitz certificates and the RK45 tableau. Nothing here reads a spec.
"""
