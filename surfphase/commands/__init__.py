"""Subcommands of ``surfphase``; each module defines ``register(subparsers)``.

Optionally also ``register_bench(bench_subparsers)`` for ``surfphase bench NAME``.
"""
