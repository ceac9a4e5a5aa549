"""The ``surfphase bench render`` command runs and reports what it measured."""

from __future__ import annotations

import argparse
import json

from surfphase.cli import main
from surfphase.commands import render_bench


def test_register_adds_no_stage_command():
    parser = argparse.ArgumentParser()
    sub = parser.add_subparsers()
    render_bench.register(sub)
    assert sub.choices == {}


def test_bench_render_writes_results(tmp_path, capsys):
    out = tmp_path / "bench.json"
    rc = main(
        [
            "bench",
            "render",
            "--runs",
            "32:200",
            "--repeats",
            "2",
            "--warmup",
            "0",
            "--threads",
            "1",
            "--max-pairs-per-chunk",
            "2000",
            "--json",
            str(out),
        ]
    )
    assert rc == 0
    data = json.loads(out.read_text())
    (run,) = data["runs"]
    assert run["size"] == 32 and run["surfels"] == 200
    assert len(run["times_s"]) == 2 and run["median_s"] > 0
    assert run["pairs"] > 1000 and run["visible"] > 100
    assert "32x32" in capsys.readouterr().out


def test_bench_render_compares_backends(tmp_path, capsys):
    out = tmp_path / "bench.json"
    argv = ["bench", "render", "--runs", "24:100,32:200", "--backends", "sparse,fused"]
    argv += ["--repeats", "1", "--warmup", "0", "--threads", "1", "--json", str(out)]
    assert main(argv) == 0
    lines = capsys.readouterr().out.strip().splitlines()
    assert lines[-1].startswith("speedup over sparse: ") and lines[-1].endswith("x at 32:200")
    assert " at 24:100, " in lines[-1]
    data = json.loads(out.read_text())
    runs = data["runs"]
    assert [(r["backend"], r["size"]) for r in runs] == [
        ("sparse", 24),
        ("fused", 24),
        ("sparse", 32),
        ("fused", 32),
    ]
    # Both backends test the same candidate pairs on the same scene.
    assert runs[0]["pairs"] == runs[1]["pairs"] and runs[2]["pairs"] == runs[3]["pairs"]
    assert all(r["median_s"] > 0 and r["cpu_median_s"] > 0 for r in runs)
