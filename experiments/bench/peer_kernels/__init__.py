"""Peer implementations a researcher would otherwise write, for benchmarks and cross-checks.

Not used by the Dr.Jit kernels; the benchmark measures our kernels against them.
"""
