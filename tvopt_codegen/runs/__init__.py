"""What the verification commands make of a derivation and its runs.

The FMU, the figures (as data) and their drawing, the files a run writes, and the
derivation's summary.
"""
