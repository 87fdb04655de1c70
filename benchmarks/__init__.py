"""Benchmarks of torch_interreflect: scripts that print and save tables and plots under ``benchmarks/results/``.

Run each from the repository root as a module (``python -m benchmarks.accuracy --quick``; the Makefile's
``bench-*`` targets do); the shared helpers are in :mod:`benchmarks._common`.
"""
