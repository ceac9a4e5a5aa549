"""``surfphase bench velocity-limits``: where the method's velocity loses to the smoothed
baseline on ``bench accuracy`` runs, the smoothing or the centres
(:mod:`surfphase.bench.velocity_limits`)."""

from __future__ import annotations

import argparse
import json
from pathlib import Path


def register(subparsers) -> None:
    """No top-level command: this module only adds ``surfphase bench velocity-limits``."""


def register_bench(bench_subparsers) -> None:
    p = bench_subparsers.add_parser(
        "velocity-limits",
        help="on bench accuracy runs: would any smoothing of the method's centres win?",
        description=(
            "From the results of `surfphase bench accuracy` runs (nothing is run again): "
            "per session, the method's and the baseline's velocity error at the best "
            "track smoothing of the bench's grid chosen per session with the truth, and "
            "their centres' rms error and frame-to-frame jitter; each session the method "
            "loses is put down to the bubble-frames only it reports, its smoothing (some "
            "setting would win) or its centres (none does); the bubble-frames only the "
            "method reports and how much of those bubbles the views show; and every fixed "
            "smoothing's, and every fit: track_min_visible's, wins over all the runs given."
        ),
    )
    p.add_argument(
        "--work", type=Path, action="append", required=True,
        help="a `bench accuracy` working folder (repeat for several draws)",
    )  # fmt: skip
    p.add_argument("--json", type=Path, help="also write the figures as JSON here")
    p.set_defaults(func=_run)


def _run(args: argparse.Namespace) -> int:
    from surfphase.bench import velocity_limits as vl
    from surfphase.bench.accuracy import _finite

    res = vl.run_velocity_limits(args.work)
    print(res["table"])
    if args.json:
        out = {
            "draws": res["draws"],
            "sweep": res["sweep"].to_dict("records"),
            "visible_sweep": res["visible_sweep"].to_dict("records"),
        }
        args.json.write_text(json.dumps(_finite(out), indent=1))
    return 0
