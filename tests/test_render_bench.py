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
