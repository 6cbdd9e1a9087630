"""Slow, obvious float64 NumPy references for the kernels (never imported by the package)."""
