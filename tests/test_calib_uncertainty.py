"""The calibration's stated sd against true errors on synthetic rigs (a small run of
``surfphase bench calib-uncertainty``, which does 20 rigs at 512 px)."""

from __future__ import annotations

import json

from surfphase.calib.uncertainty import MAX_SD_OVER_SPREAD, MIN_COVERAGE_3SD, run, summarise
from surfphase.cli import main


def test_stated_sd_cover_true_errors_and_no_check_warns():
    out = run(5, n_poses=16, native=256)
    s = out["summary"]
    kinds = {"fx", "fy", "cx", "cy", "rvec", "tvec", "baseline"}
    assert kinds <= set(s)
    assert s["all"]["n"] == 5 * (2 * 4 + 7)
    assert s["all"]["coverage_3sd"] >= MIN_COVERAGE_3SD
    for k in kinds:
        assert s[k]["sd_over_spread"] <= MAX_SD_OVER_SPREAD, (k, s[k])
    assert s["honest"]
    # The checks against the single-camera calibrations and the per-view extrinsics
    # raise no warning on rigs that are what they claim to be.
    assert s["warnings"] == 0


def test_summary_flags_dishonest_sd():
    """Errors ten times the stated sd fail coverage; sd ten times the errors fail the
    spread target."""
    rows = [
        {"kind": "fx", "error": e, "sd": 0.1, "seed": k, "warnings": 0}
        for k, e in enumerate([1.0, -1.0, 1.0])
    ]
    assert summarise(rows)["all"]["coverage_3sd"] == 0 and not summarise(rows)["honest"]
    rows = [dict(r, sd=10.0) for r in rows]
    s = summarise(rows)
    assert s["all"]["coverage_3sd"] == 1 and s["fx"]["sd_over_spread"] == 10
    assert not s["honest"]


def test_bench_command(tmp_path, capsys):
    rows = tmp_path / "rows.json"
    args = ["bench", "calib-uncertainty", "--rigs", "1", "--poses", "16", "--native", "256"]
    assert main([*args, "--rows", str(rows)]) in (0, 1)
    summary = json.loads(capsys.readouterr().out)
    assert summary["rigs"] == 1 and summary["all"]["n"] == 15
    assert len(json.loads(rows.read_text())) == 15
