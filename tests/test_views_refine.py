"""Refinement of the orbit views through the CLI: files, strength 0, kill and resume, errors."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from test_prior_embedded import bubble_clip
from test_views import make_tiny_session

from surfphase.cli import main
from surfphase.folders.views import read_mp4

ROOT = Path(__file__).resolve().parents[1]
TINY = {"channels": [8, 16], "frames": 4, "overlap": 1, "crop": 16, "batch": 2,
        "steps": 3, "sample_steps": 8, "lr": 5e-3}  # fmt: skip


@pytest.fixture(scope="module")
def session(tmp_path_factory):
    """A tiny fit rendered into its orbit views, and a tiny prior trained for 3 steps."""
    root = tmp_path_factory.mktemp("refine")
    fit, ingest = make_tiny_session(root, n_frames=6)
    assert main(["render-views", "--fit", str(fit), "--ingest", str(ingest), "--out",
                 str(root / "views"), "--device", "cpu", "--threads", "1"]) == 0  # fmt: skip
    clips = root / "clips"
    clips.mkdir()
    for k in range(2):
        np.save(clips / f"clip{k}.npy", bubble_clip(k, frames=6, size=24))
    assert main(["train-prior", "--clips", str(clips), "--out", str(root / "prior"),
                 "--threads", "1", "--samples", "1", "--params-json", json.dumps(TINY)]) == 0  # fmt: skip
    return root


def refine_args(root: Path, view: str, strength: float, out: Path, seed: int = 0) -> list[str]:
    return ["refine", "--prior", str(root / "prior"), "--views", str(root / "views"),
            "--view", view, "--strength", str(strength), "--out", str(out),
            "--seed", str(seed), "--threads", "1"]  # fmt: skip


def test_refine_view_writes_uint16_npy_and_mp4(session):
    out = session / "refined"
    assert main(refine_args(session, "orbit05", 0.35, out, seed=3)) == 0
    view = np.load(session / "views" / "orbit05.npy")
    refined = np.load(out / "orbit05.npy")
    assert refined.dtype == np.uint16 and refined.shape == view.shape == (6, 64, 64)
    assert not np.array_equal(refined, view)
    movie = read_mp4(out / "orbit05.mp4")
    assert movie.shape == refined.shape
    # H.264 is lossy and a 3-step prior leaves noise: compare frame means and correlation
    np.testing.assert_allclose(movie.mean((1, 2)), refined.mean((1, 2)) / 257.0, atol=2.0)
    assert np.corrcoef(movie.ravel(), refined.ravel().astype(float))[0, 1] > 0.8
    info = json.loads((out / "orbit05.json").read_text())
    assert info["strength"] == 0.35 and info["seed"] == 3 and info["fps"] == 1500.0
    # same seed → same result; strength 0 → the view itself, bit for bit
    again = session / "again"
    assert main(refine_args(session, "orbit05", 0.35, again, seed=3)) == 0
    np.testing.assert_array_equal(np.load(again / "orbit05.npy"), refined)
    assert main(refine_args(session, "orbit02", 0.0, out)) == 0
    np.testing.assert_array_equal(np.load(out / "orbit02.npy"), np.load(session / "views" /
                                                                        "orbit02.npy"))  # fmt: skip
    assert not list(out.glob(".*part*"))


def test_refine_killed_mid_run_leaves_nothing_and_resumes_identically(session, tmp_path):
    """SIGKILL during the SDEdit integration, rerun, compare with an uninterrupted run."""
    slow = session / "prior_slow"  # the same network, 120 Euler steps for a full generation
    slow.mkdir(exist_ok=True)
    for f in ("embedded.pt", "train.json"):
        (slow / f).write_bytes((session / "prior" / f).read_bytes())
    meta = json.loads((session / "prior" / "prior.json").read_text())
    meta["params"]["sample_steps"] = 120
    (slow / "prior.json").write_text(json.dumps(meta))
    args = [a if a != str(session / "prior") else str(slow)
            for a in refine_args(session, "orbit06", 0.35, tmp_path / "killed")]  # fmt: skip
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    proc = subprocess.Popen([sys.executable, "-m", "surfphase", *args], cwd=ROOT, env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT)  # fmt: skip
    deadline = time.monotonic() + 120
    while not list((tmp_path / "killed").glob(".orbit06.part-*")):
        assert proc.poll() is None, proc.stdout.read().decode()
        assert time.monotonic() < deadline, "refine did not start"
        time.sleep(0.05)
    time.sleep(0.3)  # the work folder exists: loading the prior, then 2 × 42 Euler steps
    assert proc.poll() is None, "refine finished before it could be killed"
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    killed = tmp_path / "killed"
    assert not [p for p in killed.iterdir() if not p.name.startswith(".")]  # no output
    assert main(args) == 0  # rerun
    assert not list(killed.glob(".orbit06.part-*"))  # the stale work folder is gone
    args_clean = [a if a != str(killed) else str(tmp_path / "clean") for a in args]
    assert main(args_clean) == 0  # uninterrupted
    np.testing.assert_array_equal(np.load(killed / "orbit06.npy"),
                                  np.load(tmp_path / "clean" / "orbit06.npy"))  # fmt: skip
    assert (killed / "orbit06.mp4").is_file()


def test_missing_inputs_give_clear_errors(session, tmp_path, capsys):
    rc = main(["train-prior", "--clips", str(tmp_path / "noclips"), "--out", str(tmp_path / "p")])
    assert rc == 2 and "noclips" in capsys.readouterr().err
    rc = main(["train-prior", "--clips", str(session / "views"), "--out", str(tmp_path / "p"),
               "--backend", "wan", "--params-json", json.dumps({"weights": str(tmp_path / "w")})])  # fmt: skip
    err = capsys.readouterr().err
    assert rc == 2 and str(tmp_path / "w") in err and "cannot be downloaded" in err
    rc = main(refine_args(session, "orbit99", 0.2, tmp_path / "r"))
    assert rc == 2 and "orbit99.npy" in capsys.readouterr().err
    rc = main(["refine", "--prior", str(tmp_path / "noprior"), "--views",
               str(session / "views"), "--view", "orbit01", "--strength", "0.2",
               "--out", str(tmp_path / "r")])  # fmt: skip
    assert rc == 2 and "noprior" in capsys.readouterr().err
    assert not (tmp_path / "p").exists() and not list((tmp_path / "r").glob("*.npy"))
