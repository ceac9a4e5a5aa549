"""``surfphase bench determinism`` (see :mod:`surfphase.bench.determinism`)."""

from __future__ import annotations


def register(subparsers) -> None:
    """No top-level command: this module only adds a benchmark."""


def register_bench(bench_subparsers) -> None:
    p = bench_subparsers.add_parser(
        "determinism",
        help="run one campaign twice (idle, then beside a CPU-bound process) and compare",
        description="Generate a synthetic session, run the workflow on it twice (fit, "
        "mesh, evaluation; --stage2 adds the prior, refinement and stage 2), the second "
        "time beside CPU-bound processes, and compare every output byte for byte, "
        "timing fields aside. Exit status 1 if anything differs.",
    )
    p.add_argument("--work", required=True, help="scratch folder (kept, for inspection)")
    p.add_argument("--frames", type=int, default=12, help="frames of the session")
    p.add_argument("--native", type=int, default=320, help="native frame size, pixels")
    p.add_argument("--scale", type=float, default=0.5, help="ingest scale")
    p.add_argument("--n-init", type=int, default=12000, help="fit: n_init (surfels)")
    p.add_argument("--hull-grid", type=int, default=96, help="fit: hull_grid (finer: more surfels)")
    p.add_argument("--iters-first", type=int, default=60, help="fit: iters_first")
    p.add_argument("--iters-next", type=int, default=20, help="fit: iters_next")
    p.add_argument("--voxels", type=int, default=48, help="mesh: voxels")
    p.add_argument("--n-orbit", type=int, default=5, help="mesh: n_orbit")
    p.add_argument("--threads", type=int, default=2, help="threads (cores) of each run")
    p.add_argument("--seed", type=int, default=0, help="synthetic campaign seed")
    p.add_argument("--load-processes", type=int, default=1, help="CPU-bound processes")
    p.add_argument("--stage2", action="store_true", help="also prior, refinement, stage 2")
    p.add_argument(
        "--target",
        choices=["evaluate", "mesh", "fit"],
        default="evaluate",
        help="the last stage run (evaluate: fit, mesh and evaluation)",
    )
    p.add_argument("--json", help="also write the summary to this JSON file")

    def run(args) -> int:
        from surfphase.bench.determinism import main

        return main(args)

    p.set_defaults(func=run)
