"""Recal's calibration core: pure numpy, SI units inside, batched over a leading N axis.

Nothing here does I/O or imports the rest of Recal. Models are immutable; algorithms are free
functions that return arrays (``fk(model, q)``).
"""
