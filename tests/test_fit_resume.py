"""A fit killed mid-run (SIGKILL) resumes from its checkpoint to the uninterrupted result."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time

import numpy as np
import pytest
import torch
from test_fit_stage import SMALL
from test_fit_toy import make_toy_session

from surfphase.fit.outputs import load_surfels


@pytest.fixture(scope="module")
def toy(tmp_path_factory):
    return make_toy_session(tmp_path_factory.mktemp("toy"), frames=3, size=40)


def _fit_cmd(ingest, masks, out, cfg, ckpt):
    return [
        sys.executable,
        "-m",
        "surfphase",
        "fit",
        "--ingest",
        str(ingest),
        "--masks",
        str(masks),
        "--out",
        str(out),
        "--config",
        str(cfg),
        "--checkpoint",
        str(ckpt),
        "--device",
        "cpu",
        "--threads",
        "1",
    ]


def test_killed_fit_resumes_to_the_same_result(toy, tmp_path):
    ingest, masks = toy
    cfg = tmp_path / "config.yaml"
    # 30 steps a frame (about 1 s here): the kill, 50 ms after frame 1's record appears,
    # lands well before frame 2's state (with 6 steps, 0.1 s, it once came after it).
    params = {**SMALL, "iters_first": 20, "iters_next": 30, "frames": 3, "densify_every": 5}
    cfg.write_text(json.dumps({"fit": params}))  # JSON is YAML
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    ref, ref_ckpt = tmp_path / "ref", tmp_path / "ref.ckpt"
    subprocess.run(_fit_cmd(ingest, masks, ref, cfg, ref_ckpt), check=True, env=env)

    out, ckpt = tmp_path / "run", tmp_path / "run.ckpt"
    proc = subprocess.Popen(_fit_cmd(ingest, masks, out, cfg, ckpt), env=env)
    deadline = time.time() + 120
    while not (ckpt / "frame_00001.pt").exists():
        assert proc.poll() is None, "fit finished before it could be killed"
        assert time.time() < deadline
        time.sleep(0.05)
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait()
    assert not (out / "surfels.npz").exists()
    # Killed after frame 1's record: the state says 1 or 2 frames are done (the record is
    # written before the state), never all 3.
    done = torch.load(ckpt / "state.pt", weights_only=False)["next_frame"]
    assert 1 <= done < 3
    subprocess.run(_fit_cmd(ingest, masks, out, cfg, ckpt), check=True, env=env)

    a, b = load_surfels(ref / "surfels.npz"), load_surfels(out / "surfels.npz")
    assert a.keys() == b.keys()
    for k in a:
        np.testing.assert_array_equal(a[k], b[k], err_msg=k)
    assert (ref / "bubbles.csv").read_text() == (out / "bubbles.csv").read_text()
    assert (ref / "curves.csv").read_text() == (out / "curves.csv").read_text()
