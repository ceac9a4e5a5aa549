"""Benchmarks behind ``surfphase bench ...`` (accuracy, determinism, comparisons)."""
