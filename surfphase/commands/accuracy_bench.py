"""``surfphase bench accuracy``: the workflow on the varied synthetic preset against the
truth, beside the classical two-view baseline (:mod:`surfphase.bench.accuracy`)."""

from __future__ import annotations

import argparse
import json
from pathlib import Path


def register(subparsers) -> None:
    """No top-level command: this module only adds ``surfphase bench accuracy``."""


def register_bench(bench_subparsers) -> None:
    p = bench_subparsers.add_parser(
        "accuracy",
        help="the default workflow on the varied synthetic preset vs the classical baseline",
        description=(
            "Generate `surfphase synth --preset bench` (or use --campaign), run the workflow "
            "with the project's config plus ingest scale 0.5 and refinement off (the "
            "config `surfphase new-campaign` writes for clip-less campaigns, at a fixed "
            "scale) through evaluate, compute the two-view centroid baseline from masks at the "
            "native resolution (raw and track-smoothed, window and order chosen on a grid), "
            "and print one table: per session, mean and worst."
        ),
    )
    p.add_argument(
        "--work", type=Path, default=Path("bench-accuracy"), help="working folder (kept)"
    )
    p.add_argument("--campaign", type=Path, help="an existing `synth --preset bench` campaign")
    p.add_argument("--sessions", type=int, help="only the first N sessions")
    p.add_argument("--frames", type=int, help="frames per session (when generating)")
    p.add_argument("--seed", type=int, default=0, help="synth seed (when generating)")
    p.add_argument(
        "--preset", default="bench", choices=["bench", "bench-mixed", "bench-drawn"],
        help="synth preset (when generating): bench, bench-mixed (its sessions' settings "
        "recombined by the seed) or bench-drawn (settings drawn by the seed from the "
        "ranges the bench spans)",
    )  # fmt: skip
    p.add_argument(
        "--cores", type=int, default=2,
        help="CPU cores for the workflow (this many sessions run at once, one thread per job)",
    )  # fmt: skip
    p.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="change the config, e.g. fit.iters_first=20 (stated in the table's notes)",
    )
    p.add_argument(
        "--skip-run", action="store_true", help="score the existing results, run nothing"
    )
    p.add_argument("--samples", type=int, help="surface samples per mesh and frame")
    p.add_argument("--json", type=Path, help="also write the result as JSON here")
    p.set_defaults(func=_run)


def _run(args: argparse.Namespace) -> int:
    from surfphase.bench import accuracy

    res = accuracy.run_accuracy_bench(
        args.work,
        campaign=args.campaign,
        sessions=args.sessions,
        frames=args.frames,
        seed=args.seed,
        preset=args.preset,
        cores=args.cores,
        set_values=args.set,
        skip_run=args.skip_run,
        samples=args.samples or accuracy.SAMPLES,
    )
    print(res["table"])
    print()
    print(res["notes"])
    print()
    print(accuracy.grid_table(_grid(res)))
    if args.json:
        args.json.write_text((Path(args.work) / "accuracy.json").read_text())
    print(
        f"\nfull results: {Path(args.work) / 'accuracy.json'}; timings {json.dumps(res['timings'])}"
    )
    return 0


def _grid(res: dict):
    import pandas as pd

    return pd.DataFrame(res["smoothing"]["grid"])
