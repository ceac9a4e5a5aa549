"""End-to-end stage-1 fit on the ray-cast toy session."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import torch
from test_fit_toy import make_toy_session, toy_spheres

from surfphase.fit.outputs import load_surfels
from surfphase.fit.stage import run_fit

SMALL = {
    "iters_first": 60,
    "iters_next": 20,
    "n_init": 600,
    "hull_grid": 24,
    "spawn_grid": 12,
    "densify_every": 15,
    "render_frames": 2,
    # The toy's masks are written by hand, without anchors.csv: bubbles.csv holds the
    # surfels' own centroids, here checked frame by frame (no track smoothing).
    "track_window_s": 0.0,
}


@pytest.fixture(scope="module")
def toy(tmp_path_factory):
    return make_toy_session(tmp_path_factory.mktemp("toy"), frames=4, size=40)


def test_fit_reconstructs_and_tracks_the_rising_bubble(toy, tmp_path, capsys):
    torch.set_num_threads(2)
    ingest, masks = toy
    out = tmp_path / "fit"
    summary = run_fit(ingest, masks, out, SMALL, device="cpu")
    log = [ln for ln in capsys.readouterr().out.splitlines() if ": frame " in ln]
    assert log[0].startswith(f"session {summary['session']}: frame 1/{summary['frames']}")
    assert "ETA" in log[0] and "elapsed" in log[-1]  # progress with an ETA per frame
    for name in ("surfels.npz", "bubbles.csv", "curves.csv", "summary.json"):
        assert (out / name).exists()
    assert len(list((out / "renders").glob("*.png"))) == 4
    assert summary["frames"] == 4 and min(np.mean(p) for p in summary["psnr_per_frame"]) > 30
    # summary.json names the CPU kernels the fit ran: this process's (the pin itself is
    # tested in fresh interpreters, test_cpu_kernels.py).
    assert summary["cpu_capability"] == torch.backends.cpu.get_cpu_capability()
    # ... and the platform its bits depend on: the libraries' own version strings.
    import numba
    import scipy

    libs = summary["platform"]["libraries"]
    assert libs["torch"] == torch.__version__ and libs["numpy"] == np.__version__
    assert libs["scipy"] == scipy.__version__ and libs["numba"] == numba.__version__
    assert summary["platform"]["machine"] and summary["platform"]["python"].count(".") == 2
    cpuinfo = Path("/proc/cpuinfo")
    model = (
        re.search(r"^model\s*:\s*(\d+)$", cpuinfo.read_text(), re.M) if cpuinfo.is_file() else None
    )
    if model:  # the CPU model number, which a virtual machine's model name can hide
        assert f"model {model.group(1)} " in summary["platform"]["cpu"]
    s = load_surfels(out / "surfels.npz")
    F, N = s["alive"].shape
    assert s["means"].shape == (F, N, 3) and s["velocity"].shape == (F, N, 3)
    assert s["quats"].shape == (F, N, 4) and s["gamma"].shape == (F,)
    assert np.all(s["opacity"][s["alive"]] <= 1) and np.isfinite(s["sdf"][s["alive"]]).all()
    # The heated surface (y = 0) is solid: no surfel centre below it, although the
    # nucleation bubble's sphere reaches 0.1 mm under it (and the hull further).
    assert s["means"][s["alive"]][:, 1].min() >= 0.0
    # Bubble 1 rises at (0.02, 0.25, 0) m/s; its centroid sits inside the true sphere.
    table = pd.read_csv(out / "bubbles.csv")
    b1 = table[table.bubble == 1].set_index("frame")
    for f in range(4):
        _, c, r = toy_spheres(f, 1000.0)[1]
        assert np.linalg.norm(b1.loc[f, ["x", "y", "z"]].to_numpy() - c) < r
    v = b1.loc[1:2, ["vx", "vy", "vz"]].to_numpy()
    err = np.linalg.norm(v - [0.02, 0.25, 0.0], axis=1).mean() / 0.25
    assert err < 0.25, (v, err)


def test_bad_inputs_name_the_file(tmp_path, toy):
    ingest, masks = toy
    with pytest.raises(FileNotFoundError, match="cameras.json"):
        run_fit(tmp_path, masks, tmp_path / "o", SMALL, device="cpu")
    with pytest.raises(ValueError, match="unknown parameter"):
        run_fit(ingest, masks, tmp_path / "o", {"nope": 1}, device="cpu")
    empty = tmp_path / "m"
    empty.mkdir()
    with pytest.raises(FileNotFoundError, match="cam0_labels.npy"):
        run_fit(ingest, empty, tmp_path / "o", SMALL, device="cpu")
    assert not Path(tmp_path / "o" / "surfels.npz").exists()


def test_without_the_floor_surfels_go_below_the_plate(toy, tmp_path):
    """The check above is not vacuous: with ``floor_y: None`` the same fit leaves surfel
    centres under y = 0 (the nucleation bubble's visual hull reaches below it)."""
    torch.set_num_threads(2)
    ingest, masks = toy
    # (The depth bound, on by default, also keeps the hull's long corners in: off here,
    # so that only the floor is tested.)
    params = {**SMALL, "iters_first": 30, "iters_next": 5, "floor_y": None, "depth_bound": None}
    run_fit(ingest, masks, tmp_path / "fit", params, device="cpu")
    s = load_surfels(tmp_path / "fit" / "surfels.npz")
    assert s["means"][s["alive"]][:, 1].min() < -1e-5


def test_depth_bounds_pull_surfels_back_along_the_bisector(tmp_path):
    """Two views 35° apart (the toy rig): a surfel 3 r behind its bubble's centre along
    the views' mean direction comes back to k·r, one inside stays, and surfels of the
    nucleation region (bubble 0) are left where they are. The sphere's centre and
    radius come from the masks (centroid triangulation, equivalent radius)."""
    from surfphase.fit.bounds import depth_bounds
    from surfphase.fit.session import SessionData

    ingest, masks = make_toy_session(tmp_path, frames=1, size=40)
    data = SessionData(ingest, masks)
    cams, labels = data.cameras, data.labels(0)
    assert depth_bounds(cams, labels, None) is None
    b = depth_bounds(cams, labels, 1.2)
    axis = np.mean([c.view_dir for c in cams], axis=0)
    axis /= np.linalg.norm(axis)
    assert np.allclose(b.axis.numpy(), axis)
    _, c1, r1 = toy_spheres(0, 1000.0)[1]
    i1 = int(np.argmin(np.linalg.norm(b.centres.numpy() - c1, axis=1)))
    c, r = b.centres[i1].numpy(), float(b.radii[i1])
    assert np.linalg.norm(c - c1) < 0.3 * r1 and r == pytest.approx(r1, rel=0.25)
    i0 = int(np.argmax(np.isinf(b.limits.numpy())))  # the nucleation region
    c0 = b.centres[i0].numpy()
    pts = torch.tensor(
        np.stack([c + 3 * r * axis, c - 0.5 * r * axis, c0 + 1.5 * r * axis]), dtype=torch.float64
    )
    before = pts.clone()
    b.apply(pts)
    assert (pts[0].numpy() - c) @ axis == pytest.approx(1.2 * r, rel=1e-9)
    assert torch.equal(pts[1:], before[1:])


def test_checkpoint_fingerprint_sees_every_frames_masks_and_the_anchors(tmp_path):
    """A fit's checkpoint resumes only the same inputs: the session fingerprint changes
    when one middle frame's labels change (the first and last untouched), when the
    anchors change and when the merges change, and is the same when nothing does."""
    import shutil

    import pandas as pd

    from surfphase.fit.session import SessionData

    ingest, masks = make_toy_session(tmp_path, frames=3, size=40)
    pd.DataFrame(
        [(t, 1, 0.001 * t, 0.002, 0.0) for t in range(3)],
        columns=["frame", "bubble", "x", "y", "z"],
    ).to_csv(masks / "anchors.csv", index=False)
    first = SessionData(ingest, masks).fingerprint()
    assert SessionData(ingest, masks).fingerprint() == first

    def changed(edit) -> str:
        other = tmp_path / f"masks_{edit.__name__}"
        shutil.copytree(masks, other)
        edit(other)
        return SessionData(ingest, other).fingerprint()

    def middle_labels(folder):
        path = sorted(folder.glob("*_labels.npy"))[0]
        lab = np.load(path)
        ys, xs = np.nonzero(lab[1] >= 1)
        lab[1, ys[0], xs[0]] = -1  # one pixel of one bubble, frame 1 of 3
        np.save(path, lab)

    def anchors(folder):
        a = pd.read_csv(folder / "anchors.csv")
        a.loc[a.index[0], "x"] += 1e-6
        a.to_csv(folder / "anchors.csv", index=False)

    def merges(folder):
        pd.DataFrame(
            [(1, "cam0", "merge", "1+2", "3")],
            columns=["frame", "camera", "event", "parents", "children"],
        ).to_csv(folder / "events.csv", index=False)

    got = [changed(f) for f in (middle_labels, anchors, merges)]
    assert first not in got and len(set(got)) == 3
