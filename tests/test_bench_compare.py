"""The results-folder comparison behind `surfphase bench determinism`: equal results with
different timings compare equal; any other difference is found and named."""

from __future__ import annotations

import json

import numpy as np

from surfphase.bench.compare import compare_trees


def _tree(root, seconds: float, z: float, extra: bool = False):
    (root / "s1" / "fit").mkdir(parents=True)
    (root / "logs").mkdir()
    (root / "logs" / "fit.log").write_text(f"took {seconds} s")  # logs are not results
    summary = {"psnr": [30.5, 31.0], "seconds_per_frame": [seconds], "nested": {"seconds": 1}}
    (root / "s1" / "fit" / "summary.json").write_text(json.dumps(summary))
    np.savez(root / "s1" / "fit" / "surfels.npz", means=np.array([[0.0, 1.0, z]]),
             seconds=np.array([seconds]))  # fmt: skip
    (root / "s1" / "fit" / "bubbles.csv").write_text(f"frame,z,seconds\n0,{z},{seconds}\n")
    (root / "s1" / "a.png").write_bytes(b"\x89PNG" + bytes([int(z)]))
    if extra:
        (root / "s1" / "extra.txt").write_text("x")


def test_same_results_with_other_timings_are_identical(tmp_path):
    _tree(tmp_path / "a", 1.5, 2.0)
    _tree(tmp_path / "b", 9.25, 2.0)
    out = compare_trees(tmp_path / "a", tmp_path / "b")
    assert out["differ"] == {} and out["only_a"] == out["only_b"] == []
    assert sorted(out["same"]) == [
        "s1/a.png", "s1/fit/bubbles.csv", "s1/fit/summary.json", "s1/fit/surfels.npz"
    ]  # fmt: skip


def test_a_last_bit_difference_is_found(tmp_path):
    _tree(tmp_path / "a", 1.5, 2.0)
    _tree(tmp_path / "b", 1.5, np.nextafter(2.0, 3.0), extra=True)
    out = compare_trees(tmp_path / "a", tmp_path / "b")
    assert set(out["differ"]) == {"s1/fit/bubbles.csv", "s1/fit/surfels.npz"}
    assert "means" in out["differ"]["s1/fit/surfels.npz"]
    assert out["only_b"] == ["s1/extra.txt"]
