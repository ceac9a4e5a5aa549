"""Stage-2 fit: restart from stage 1, weighted refined views, per-view backgrounds, resume.

The refined views of these tests are independent of the fit: the toy spheres ray-cast
(numpy, tests/test_fit_toy.py) into two orbit cameras, i.e. a perfect refinement.
"""

from __future__ import annotations

import json
import math
import os
import signal
import subprocess
import sys
import time

import numpy as np
import pytest
import torch
from test_fit_toy import make_toy_session, raycast, toy_spheres

from surfphase.cameras import look_at, save_cameras
from surfphase.fit.outputs import load_surfels
from surfphase.fit.stage import run_fit
from surfphase.fit.stage2 import (
    DEFAULTS,
    ExtraViews,
    initial_model_from_stage1,
    refined_background,
    run_fit_stage2,
    split_params,
    view_weights,
)

SIZE, FRAMES, FPS = 32, 3, 1000.0
FIT = {
    "iters_first": 20,
    "iters_next": 5,
    "n_init": 300,
    "hull_grid": 16,
    "spawn_grid": 10,
    "densify_every": 5,
    "render_frames": 1,
}
#: Stage-2 settings of the tests: few steps, every refined view at every step.
FIT2 = {"iters_first": 6, "iters_next": 4, "views_per_step": 0}


def orbit_view(name: str, az_deg: float):
    target = np.array([0.0, 0.003, 0.0])
    a = math.radians(az_deg)
    eye = target + np.array([0.06 * math.sin(a), 0.002, 0.06 * math.cos(a)])
    return look_at(name, eye, target, fx=1800.0 * SIZE / 512, width=SIZE, height=SIZE)


def write_views(root, names_az):
    """A views folder and a refine folder with the toy spheres ray-cast into the views."""
    views, refine = root / "views", root / "refine"
    views.mkdir(parents=True)
    refine.mkdir(parents=True)
    cams = [orbit_view(n, az) for n, az in names_az]
    save_cameras(views / "cameras.json", cams, session="toy", fps=FPS, frame=list(range(FRAMES)))
    for cam in cams:
        imgs, alphas = [], []
        for f in range(FRAMES):
            im, lab = raycast(cam, toy_spheres(f, FPS))
            imgs.append(im)
            alphas.append((lab >= 0).astype(np.float16))
        np.save(refine / f"{cam.name}.npy", np.round(np.stack(imgs) * 65535).astype(np.uint16))
        np.save(views / f"{cam.name}_alpha.npy", np.stack(alphas))
    return views, refine


@pytest.fixture(scope="module")
def toy(tmp_path_factory):
    torch.set_num_threads(1)
    root = tmp_path_factory.mktemp("toy2")
    ingest, masks = make_toy_session(root, frames=FRAMES, size=SIZE, fps=FPS)
    run_fit(ingest, masks, root / "fit", {**FIT, "frames": FRAMES}, device="cpu")
    views, refine = write_views(root / "two", [("orbit01", 65.0), ("orbit05", 150.0)])
    views1, refine1 = write_views(root / "one", [("orbit01", 65.0)])
    return {
        "ingest": ingest,
        "masks": masks,
        "fit": root / "fit",
        "views": views,
        "refine": refine,
        "views1": views1,
        "refine1": refine1,
    }


def _stage2(toy, out, params, which=""):
    torch.set_num_threads(1)
    return run_fit_stage2(
        toy["ingest"],
        toy["masks"],
        toy["fit"],
        toy["views" + which],
        toy["refine" + which],
        out,
        params=params,
        fit_params=FIT,
        device="cpu",
    )


def test_stage2_starts_from_the_stage1_surfels_of_frame_0(toy, tmp_path):
    s1 = load_surfels(toy["fit"] / "surfels.npz")
    # The checkpoint holds the stage-1 model's own parameters (f in units of L): the
    # conversion from the file's metres must give them back.
    rec = torch.load(toy["fit"].parent / "fit.ckpt" / "frame_00000.pt", weights_only=False)
    model = initial_model_from_stage1(s1, use_sdf=True)
    for k in ("means", "log_scales", "quats", "colors"):
        np.testing.assert_array_equal(model.params[k].detach().numpy(), rec[k], err_msg=k)
    np.testing.assert_allclose(model.params["sdf"].detach().numpy(), rec["sdf"], rtol=1e-5)
    assert math.isclose(float(model.gamma.detach()), rec["gamma"], rel_tol=1e-5)

    assert model.shade is None
    # A stage-1 shading curve is carried over; without one, shade_knots starts a flat one.
    knots = np.array([[0.1], [0.1], [0.3], [0.6]], np.float32)
    shaded = initial_model_from_stage1({**s1, "shade": knots[None]}, use_sdf=True)
    np.testing.assert_allclose(shaded.shade.detach().numpy(), knots, atol=2e-4)
    flat = initial_model_from_stage1(s1, use_sdf=True, shade_knots=5).shade.detach().numpy()
    assert flat.shape == (5, 1) and np.ptp(flat) < 1e-3

    # No step at frame 0: stage 2's first frame is stage 1's.
    _stage2(toy, tmp_path / "f2", {**FIT2, "iters_first": 0, "frames": 1})
    s2 = load_surfels(tmp_path / "f2" / "surfels.npz")
    n = int(s1["alive"][0].sum())
    assert s2["alive"].shape == (1, n)
    for k in ("means", "quats", "log_scales", "colors"):
        np.testing.assert_array_equal(s2[k][0], s1[k][0][s1["alive"][0]], err_msg=k)
    np.testing.assert_allclose(s2["opacity"][0], s1["opacity"][0][:n], atol=1e-5)
    assert (tmp_path / "f2" / "stage2.json").exists()


def test_a_refined_view_of_weight_0_changes_nothing(toy, tmp_path):
    params = {**FIT2, "weight_far": 0.0, "frames": 2}
    a = _stage2(toy, tmp_path / "a", params)  # orbit01 (near) + orbit05 (far, weight 0)
    _stage2(toy, tmp_path / "b", params, which="1")  # orbit01 only
    sa, sb = (
        load_surfels(tmp_path / "a" / "surfels.npz"),
        load_surfels(tmp_path / "b" / "surfels.npz"),
    )
    assert sa.keys() == sb.keys()
    for k in sa:
        np.testing.assert_array_equal(sa[k], sb[k], err_msg=k)
    assert json.loads((tmp_path / "a" / "stage2.json").read_text())["views"] == ["orbit01"]
    # With its weight the far view is used, and the result changes.
    _stage2(toy, tmp_path / "c", {**params, "weight_far": 0.25})
    sc = load_surfels(tmp_path / "c" / "surfels.npz")
    assert not np.array_equal(sa["means"], sc["means"])
    assert a["frames"] == 2


def test_refined_background_on_a_hand_made_view():
    T, H, W = 5, 3, 4
    bg = np.arange(H * W, dtype=np.float32).reshape(H, W) / 20.0
    frames = np.repeat(bg[None], T, axis=0).copy()
    frames[1:3] += 0.01  # the prior brightened two frames a little: the median ignores it
    alpha = np.zeros((T, H, W), np.float32)
    # A dark bubble over pixel (1, 1) in frames 0–3 (alpha 1): background only at frame 4.
    frames[:4, 1, 1] = 0.0
    alpha[:4, 1, 1] = 1.0
    # A bubble always over pixel (2, 3): it takes its nearest neighbour's background.
    frames[:, 2, 3] = 0.0
    alpha[:, 2, 3] = 0.9
    # A faint halo (alpha 0.01 ≤ 0.02) still counts as background.
    alpha[:, 0, 0] = 0.01
    out = refined_background(frames, alpha, alpha_max=0.02)
    expect = bg.copy()
    assert out.shape == (H, W) and out.dtype == np.float32
    assert out[2, 3] in {bg[1, 3], bg[2, 2]}  # a nearest background pixel
    mask = np.ones((H, W), bool)
    mask[2, 3] = False
    np.testing.assert_array_equal(out[mask], expect[mask])
    # Never any background: the fallback image.
    fb = np.full((H, W), 0.5, np.float32)
    np.testing.assert_array_equal(refined_background(frames, np.ones_like(alpha), 0.02, fb), fb)


def test_view_weights_and_the_per_step_draw():
    s2, fit = split_params({"views_per_step": 2, "iters_next": 7}, {"iters_next": 30})
    assert fit["iters_next"] == 7 and fit["densify"] is False
    names = [f"orbit{k:02d}" for k in range(1, 12)]
    w = view_weights(names, s2)
    assert list(w) == [0.5] * 3 + [0.25] * 5 + [0.5] * 3
    with pytest.raises(ValueError, match="unknown parameter"):
        split_params({"nope": 1})
    ev = ExtraViews(
        names=names,
        cameras=[],
        frames=np.zeros((11, 1, 2, 2), np.float32),
        backgrounds=np.zeros((11, 2, 2, 1), np.float32),
        weights=w,
        weight_inputs=DEFAULTS["weight_inputs"],
        views_per_step=2,
        seed=3,
    )
    pick = ev.schedule(t=4, n_inputs=2)
    draws = [pick(i) for i in range(200)]
    again = ev.schedule(t=4, n_inputs=2)
    for idx, wt in draws[:5]:
        assert idx[:2].tolist() == [0, 1] and wt[:2].tolist() == [1.0, 1.0]
        ref = idx[2:] - 2
        assert len(set(ref.tolist())) == 2
        np.testing.assert_allclose(wt[2:].numpy(), w[ref.numpy()] * 11 / 2, rtol=1e-6)
    # Same frame → same draws (a resumed run draws the same views).
    for i in range(5):
        assert torch.equal(again(i)[0], draws[i][0])
    # Every view is drawn, about equally often: each step's loss is unbiased.
    counts = np.bincount(torch.cat([d[0][2:] - 2 for d in draws]).numpy(), minlength=11)
    assert counts.min() > 0.5 * 400 / 11 and counts.sum() == 400


def _fit2_cmd(toy, out, ckpt, cfg):
    return [
        sys.executable, "-m", "surfphase", "fit2",
        "--ingest", str(toy["ingest"]), "--masks", str(toy["masks"]),
        "--stage1", str(toy["fit"]), "--views", str(toy["views"]),
        "--refine", str(toy["refine"]), "--out", str(out), "--config", str(cfg),
        "--checkpoint", str(ckpt), "--device", "cpu", "--threads", "1",
    ]  # fmt: skip


def test_killed_stage2_fit_resumes_to_the_same_result(toy, tmp_path):
    cfg = tmp_path / "config.yaml"
    fit2 = {**FIT2, "iters_next": 12, "views_per_step": 1, "frames": FRAMES}
    cfg.write_text(json.dumps({"fit": FIT, "fit2": fit2}))  # JSON is YAML
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    ref, ref_ckpt = tmp_path / "ref", tmp_path / "ref.ckpt"
    subprocess.run(_fit2_cmd(toy, ref, ref_ckpt, cfg), check=True, env=env)

    out, ckpt = tmp_path / "run", tmp_path / "run.ckpt"
    proc = subprocess.Popen(_fit2_cmd(toy, out, ckpt, cfg), env=env)
    deadline = time.time() + 120
    while not (ckpt / "frame_00001.pt").exists():
        assert proc.poll() is None, "fit2 finished before it could be killed"
        assert time.time() < deadline
        time.sleep(0.02)
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait()
    assert not (out / "surfels.npz").exists()
    done = torch.load(ckpt / "state.pt", weights_only=False)["next_frame"]
    assert 1 <= done < FRAMES
    subprocess.run(_fit2_cmd(toy, out, ckpt, cfg), check=True, env=env)

    a, b = load_surfels(ref / "surfels.npz"), load_surfels(out / "surfels.npz")
    assert a.keys() == b.keys()
    for k in a:
        np.testing.assert_array_equal(a[k], b[k], err_msg=k)
    assert (ref / "bubbles.csv").read_text() == (out / "bubbles.csv").read_text()
    assert (ref / "curves.csv").read_text() == (out / "curves.csv").read_text()
