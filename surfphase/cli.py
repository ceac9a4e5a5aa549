"""The ``surfphase`` command: one subcommand per stage, plus benchmarks.

Each module in :mod:`surfphase.commands` defines ``register(subparsers)``, adding its
subcommand(s) with ``set_defaults(func=...)``. The stages never import this module.
"""

from __future__ import annotations

import argparse
import importlib
import pkgutil
import sys

from surfphase import __version__, commands


class UserError(Exception):
    """An error caused by the user's input: printed without a traceback, exit code 2."""


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="surfphase",
        description="Reconstruct 3D bubble interfaces and velocities from synchronized videos.",
    )
    parser.add_argument("--version", action="version", version=f"surfphase {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    bench = sub.add_parser("bench", help="benchmarks (timings and accuracy)")
    bench_sub = bench.add_subparsers(dest="bench", metavar="BENCH")
    bench.set_defaults(func=lambda a: bench.print_help() or 1)
    for info in sorted(pkgutil.iter_modules(commands.__path__), key=lambda m: m.name):
        mod = importlib.import_module(f"surfphase.commands.{info.name}")
        mod.register(sub)
        if hasattr(mod, "register_bench"):
            mod.register_bench(bench_sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if not getattr(args, "func", None):
        parser.print_help()
        return 1
    try:
        rc = args.func(args)
    except (UserError, FileNotFoundError, ValueError) as e:
        print(f"surfphase {args.command}: error: {e}", file=sys.stderr)
        return 2
    return int(rc or 0)


if __name__ == "__main__":
    sys.exit(main())
