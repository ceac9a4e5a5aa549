"""``surfphase bench stability`` (see :mod:`surfphase.bench.stability`)."""

from __future__ import annotations


def register(subparsers) -> None:
    """No top-level command: this module only adds a benchmark."""


def register_bench(bench_subparsers) -> None:
    p = bench_subparsers.add_parser(
        "stability",
        help="how far bubble tracks move when the input frames get 1e-4 noise",
        description="For each session of a campaign folder where the workflow ran (e.g. "
        "bench accuracy's WORK/run), rerun masks and the stage-1 fit on its ingested "
        "frames as they are and with Gaussian noise added, and report the changes of "
        "centroid and velocity.",
    )
    p.add_argument("--run", required=True, help="reference campaign working folder")
    p.add_argument("--work", required=True, help="scratch folder for the noisy reruns")
    p.add_argument("--session", action="append", help="only these sessions (repeatable)")
    p.add_argument("--noise", type=float, default=1e-4, help="noise sd, fraction of range")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--margin", type=int, default=3, help="frames left out around events")
    p.add_argument("--cores", type=int, default=2)
    p.add_argument("--json", help="also write the rows to this JSON file")

    def run(args) -> int:
        from surfphase.bench.stability import main

        return main(args)

    p.set_defaults(func=run)
