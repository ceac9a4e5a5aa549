"""The embedded prior: training, save/load, chunked refinement, and the two commands."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest
import torch

from surfphase.cli import main
from surfphase.prior import load_prior
from surfphase.prior.clips import find_clips, read_video
from surfphase.prior.embedded import EmbeddedPrior

SMALL = {"channels": [8, 16], "frames": 4, "overlap": 1, "crop": 16, "batch": 2,
         "steps": 30, "sample_steps": 4, "lr": 5e-3}  # fmt: skip


def bubble_clip(seed: int, frames: int = 10, size: int = 24) -> np.ndarray:
    """(frames, size, size) [0, 1]: dark rings rising over a bright background."""
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[:size, :size].astype(np.float32)
    centres = rng.uniform(4, size - 4, (3, 2))
    radii = rng.uniform(2.0, 4.0, 3)
    video = np.full((frames, size, size), 0.8, np.float32)
    for f in range(frames):
        for (cy, cx), r in zip(centres, radii, strict=True):
            d = np.hypot(yy - (cy - 0.7 * f) % size, xx - cx)
            video[f] -= 0.6 * np.exp(-(((d - r) / 0.8) ** 2))
    return np.clip(video, 0, 1)


def write_png_clip(folder, video: np.ndarray) -> None:
    folder.mkdir(parents=True)
    for k, frame in enumerate(video):
        cv2.imwrite(str(folder / f"{k:06d}.png"), np.round(frame * 255).astype(np.uint8))


def flow_loss(model, clips, seed=0) -> float:
    """Mean ‖v(x_t, t) − (ε − x0)‖² over fixed windows, noise and times (an independent check)."""
    g = torch.Generator().manual_seed(seed)
    x0 = torch.stack([torch.from_numpy(c[:4, :16, :16]) * 2 - 1 for c in clips])[:, None]
    eps = torch.randn(x0.shape, generator=g)
    t = torch.linspace(0.1, 0.9, len(clips))
    tt = t[:, None, None, None, None]
    rows = torch.linspace(-1, 1, 24)[:16].expand(len(clips), -1)  # the crops' rows in 24
    with torch.no_grad():
        v = model((1 - tt) * x0 + tt * eps, t, rows=rows if model.position else None)
    return float(((v - (eps - x0)) ** 2).mean())


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    torch.set_num_threads(1)
    prior = EmbeddedPrior(SMALL)
    clips = [bubble_clip(0), bubble_clip(1)]
    held_out = [bubble_clip(k) for k in range(20, 26)]
    before = flow_loss(prior.model, held_out)
    log = prior.train(clips, log=None)
    log["held_out_before"], log["held_out_after"] = before, flow_loss(prior.model, held_out)
    folder = tmp_path_factory.mktemp("prior")
    prior.save(folder)
    return prior, log, folder


def test_training_lowers_the_flow_matching_loss(trained):
    _, log, _ = trained
    assert len(log["losses"]) == SMALL["steps"]
    assert log["held_out_after"] < 0.85 * log["held_out_before"]


def test_save_load_round_trip_gives_identical_refinement(trained):
    prior, _, folder = trained
    again = load_prior(folder)
    assert isinstance(again, EmbeddedPrior) and again.params == prior.params
    video = bubble_clip(5, frames=11)
    a, b = prior.refine(video, 0.35, seed=2), again.refine(video, 0.35, seed=2)
    assert a.shape == video.shape and np.array_equal(a, b)
    assert 0.0 <= a.min() and a.max() <= 1.0
    # SDEdit keeps the input's structure at low strength: closer to it than to another clip
    assert np.abs(a - video).mean() < np.abs(a - bubble_clip(9, frames=11)).mean()


def test_sample_shape_and_determinism(trained):
    prior, _, _ = trained
    s1, s2 = prior.sample(2, 4, 16, seed=1), prior.sample(2, 4, 16, seed=1)
    assert s1.shape == (2, 4, 16, 16) and np.array_equal(s1, s2)


def test_refine_pads_odd_sizes_and_short_videos(trained):
    prior, _, _ = trained
    video = bubble_clip(3, frames=3, size=24)[:, :23, :21]
    out = prior.refine(video, 0.2, seed=0)
    assert out.shape == video.shape and np.isfinite(out).all()


def test_bad_inputs_raise_clear_errors(tmp_path):
    prior = EmbeddedPrior(SMALL)
    with pytest.raises(ValueError, match="frames"):
        prior.train([bubble_clip(0, frames=2)], log=None)
    with pytest.raises(ValueError, match="unknown parameters"):
        EmbeddedPrior({"stepz": 3})
    with pytest.raises(ValueError, match=r"\(T, H, W\)"):
        prior.refine(np.zeros((4, 4)), 0.2)
    with pytest.raises(FileNotFoundError, match="nowhere"):
        find_clips(tmp_path / "nowhere")
    with pytest.raises(FileNotFoundError, match="no prior"):
        load_prior(tmp_path)


def test_train_prior_refuses_no_samples_before_training(tmp_path, capsys):
    """``--samples 0`` once failed in the sample grid after the whole training."""
    with pytest.raises(SystemExit):
        main(["train-prior", "--clips", str(tmp_path), "--out", str(tmp_path / "p"),
              "--samples", "0"])  # fmt: skip
    assert "--samples: must be at least 1, got 0" in capsys.readouterr().err
    assert not (tmp_path / "p").exists()


def test_commands_train_prior_and_refine(tmp_path, capsys):
    clips = tmp_path / "clips"
    for k in range(2):
        write_png_clip(clips / f"clip{k:03d}", bubble_clip(10 + k, frames=8, size=16))
    params = dict(SMALL, steps=3, crop=16)
    out = tmp_path / "prior"
    assert main(["train-prior", "--clips", str(clips), "--out", str(out), "--threads", "1",
                 "--params-json", json.dumps(params), "--samples", "2"]) == 0  # fmt: skip
    assert {p.name for p in out.iterdir()} == {
        "prior.json",
        "embedded.pt",
        "samples.png",
        "train.json",
    }
    grid = cv2.imread(str(out / "samples.png"), cv2.IMREAD_GRAYSCALE)
    assert grid.shape == (4 * 16 + 3 * 2 + 6, 4 * 16 + 3 * 2)  # 2 clips, band, 2 samples
    log = json.loads((out / "train.json").read_text())
    assert log["steps"] == 3 and log["backend"] == "embedded"

    view = clips / "clip001"
    for strength, name in ((0.35, "near"), (0.0, "zero")):
        assert main(["refine", "--prior", str(out), "--video", str(view), "--strength",
                     str(strength), "--out", str(tmp_path / f"{name}.npy"), "--seed", "4"]) == 0  # fmt: skip
        stack = np.load(tmp_path / f"{name}.npy")
        assert stack.shape == (8, 16, 16)
        assert len(list((tmp_path / name).glob("*.png"))) == 8
        np.testing.assert_allclose(read_video(tmp_path / name), stack, atol=0.5 / 255 + 1e-6)
    np.testing.assert_array_equal(np.load(tmp_path / "zero.npy"), read_video(view))
    assert json.loads((tmp_path / "near" / "refine.json").read_text())["strength"] == 0.35
    rc = main(["refine", "--prior", str(out), "--video", str(view), "--strength", "1.5",
               "--out", str(tmp_path / "bad")])  # fmt: skip
    assert rc == 2 and "strength" in capsys.readouterr().err
    assert not (tmp_path / "bad.npy").exists()


def test_patch_two_unet_is_pixel_unshuffled_and_refines_any_size():
    """patch = 2: the U-Net runs on 2×2 space-to-depth frames (torch's pixel_unshuffle per
    frame, undone by pixel_shuffle); sizes are padded to its multiple (2·2^levels−1)."""
    import torch.nn.functional as F

    from surfphase.prior.embedded import _per_frame

    x = torch.randn(2, 1, 3, 8, 12)
    y = _per_frame(F.pixel_unshuffle, x, 2)
    assert y.shape == (2, 4, 3, 4, 6)
    assert torch.equal(y[:, 1, :, 2, 3], x[:, 0, :, 4, 7])  # channel 1 = (row 0, column 1)
    assert torch.equal(_per_frame(F.pixel_shuffle, y, 2), x)
    torch.set_num_threads(1)
    prior = EmbeddedPrior({**SMALL, "patch": 2, "steps": 3})
    assert prior.model.multiple == 4
    prior.train([bubble_clip(0)], log=None)
    video = bubble_clip(4, frames=5)[:, :23, :21]
    out = prior.refine(video, 0.35, seed=1)
    assert out.shape == video.shape and np.isfinite(out).all()


def test_training_windows_carry_their_rows_heights_in_the_frame():
    """``position``: a crop's rows get their heights in the whole frame, −1 top … 1 bottom."""
    from surfphase.prior.embedded import VideoUNet, row_heights

    np.testing.assert_allclose(row_heights(5).numpy(), np.linspace(-1, 1, 5), atol=1e-7)
    np.testing.assert_allclose(row_heights(5, 7)[5:].numpy(), [1.5, 2.0], atol=1e-7)
    H = 20
    clip = torch.arange(H, dtype=torch.float32)[None, :, None].expand(6, H, 9)  # value = row
    rng = np.random.default_rng(0)
    for _ in range(5):
        w, rows, weight, focused = EmbeddedPrior._window([clip], rng, 4, 8)
        assert weight == 1.0 and not focused
        first = int(w[0, 0, 0])
        np.testing.assert_allclose(
            rows.numpy(), np.linspace(-1, 1, H)[first : first + 8], atol=1e-6
        )
    with pytest.raises(ValueError, match="rows"):
        VideoUNet([8], position=True)(torch.zeros(1, 1, 2, 4, 4), torch.zeros(1))


def test_focused_windows_contain_the_moving_content():
    from surfphase.prior.embedded import activity_map, focus_proposal

    clip = np.full((10, 64, 64), 0.8, np.float32)
    for t in range(10):  # a dark 4×4 square rising through the right half
        clip[t, 50 - 3 * t : 54 - 3 * t, 44:48] = 0.1
    act = activity_map(clip)
    assert act.shape == clip.shape and act[:, :, :32].max() == 0.0
    prop = focus_proposal(act, 16)
    data = [torch.from_numpy(clip) * 2 - 1]
    rng = np.random.default_rng(0)
    for _ in range(20):
        w, _rows, _weight, focused = EmbeddedPrior._window(data, rng, 4, 16, [prop], 1.0)
        assert focused
        assert (w[0] < 0).any()  # the first frame of every window shows the square


def test_focus_proposal_is_the_corner_density_of_clipped_centre_draws():
    """Against a brute-force count: every centre pixel, clipped to a window corner."""
    from surfphase.prior.embedded import focus_proposal

    rng = np.random.default_rng(3)
    act = rng.random((2, 12, 10)) ** 4
    act[1] = 0.0  # a frame without motion
    crop = 5
    q = focus_proposal(act, crop)
    assert q.shape == (2, 8, 6)
    ref = np.zeros((8, 6))
    for cy in range(12):
        for cx in range(10):
            y = min(max(cy - crop // 2, 0), 7)
            x = min(max(cx - crop // 2, 0), 5)
            ref[y, x] += act[0, cy, cx]
    np.testing.assert_allclose(q[0], ref / act[0].sum(), rtol=1e-12)
    assert not q[1].any()


def test_focused_window_weights_are_unbiased():
    """E_q[p/q · g] = E_p[g]: weighted means over focused draws equal uniform means."""
    from surfphase.prior.embedded import activity_map, focus_proposal

    clip = np.full((6, 24, 24), 0.8, np.float32)
    clip[:, 4:8, 15:19] = np.linspace(0.1, 0.5, 6)[:, None, None]  # a changing dark square
    prop = [focus_proposal(activity_map(clip), 8)]
    data = [torch.from_numpy(clip)]
    rng = np.random.default_rng(0)
    draws = [EmbeddedPrior._window(data, rng, 2, 8, prop, 0.75) for _ in range(20000)]
    weights = np.array([d[2] for d in draws])
    dark = np.array([float((d[0] < 0.6).any()) for d in draws])
    assert dark.mean() > 0.6  # most focused windows show the square
    # uniform windows: the exact share of corners whose window overlaps the square
    ys, xs = np.arange(24 - 8 + 1), np.arange(24 - 8 + 1)
    hit_y = (ys + 8 > 4) & (ys < 8)
    hit_x = (xs + 8 > 15) & (xs < 19)
    p_dark = hit_y.mean() * hit_x.mean()
    assert abs(weights.mean() - 1.0) < 0.05
    assert abs(np.mean(weights * dark) - p_dark) < 0.03


def test_clean_video_prediction_lands_on_the_clean_video():
    """``predict: x``: a network that returns the clean video exactly gives the exact
    velocity ε − x0 of the straight path, so SDEdit's Euler steps end on the video."""
    torch.set_num_threads(1)
    prior = EmbeddedPrior({**SMALL, "predict": "x", "sample_steps": 10, "position": False})
    frame = bubble_clip(2, frames=1, size=16)[0]
    video = np.repeat(frame[None], 6, axis=0)  # the same frame: every chunk sees it

    class Oracle(torch.nn.Module):
        multiple = prior.ema.multiple

        def forward(self, x, t, rows=None, label=None):
            return (torch.from_numpy(frame) * 2 - 1).expand(x.shape).to(x.dtype)

    prior.ema = Oracle()
    out = prior.refine(video, 0.5, seed=3)  # times 0.5, 0.4, …, 0.1, 0: all above 0.05
    np.testing.assert_allclose(out, video, atol=2e-6)
    prior.params["predict"] = "eps"
    with pytest.raises(ValueError, match="predict"):
        prior.refine(video, 0.5)


def test_focus_label_trains_both_classes_and_generates_uniform_windows():
    """``focus_label``: the label embedding learns from focused (1) and uniform (0)
    windows; sampling and refinement use class 0 only."""
    torch.set_num_threads(1)
    params = {**SMALL, "steps": 6, "crop_focus": 0.5, "focus_label": True}
    prior = EmbeddedPrior(params)
    assert not prior.model.label.weight.any()  # starts as the unlabelled network
    prior.train([bubble_clip(0), bubble_clip(1)], log=None)
    assert prior.model.label.weight[0].abs().sum() > 0
    assert prior.model.label.weight[1].abs().sum() > 0
    ref = prior.sample(1, 4, 16, seed=2)
    with torch.no_grad():
        prior.ema.label.weight[1] += 1e3  # class 1 is never asked for
    np.testing.assert_array_equal(prior.sample(1, 4, 16, seed=2), ref)
    with torch.no_grad():
        prior.ema.label.weight[0] += 1.0
    assert not np.array_equal(prior.sample(1, 4, 16, seed=2), ref)
