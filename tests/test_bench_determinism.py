"""CI-sized `surfphase bench determinism`: a session with 10,000 surfels run twice through
the workflow up to its fit (calibration, ingest, masks, stage-1 fit), the second time
beside a CPU-bound process; every output must be byte-identical, timing fields aside.
The benchmark itself also runs the evaluation (and, with --stage2, stage 2)."""

from __future__ import annotations

from surfphase.bench.determinism import report, run_twice

SMALL = {
    "frames": 2, "native": 160, "scale": 0.5, "n_init": 10000, "hull_grid": 96, "iters_first": 8,
    "iters_next": 3, "voxels": 20, "n_orbit": 3, "threads": 2, "seed": 0,
    "load_processes": 1, "stage2": False, "target": "fit",
}  # fmt: skip


def test_two_runs_under_different_load_are_identical(tmp_path):
    summary = run_twice(tmp_path, SMALL, log=lambda _line: None)
    assert summary["max_surfels"] >= 10000, report(summary)
    assert summary["files_compared"] > 15
    assert summary["identical"], report(summary)
