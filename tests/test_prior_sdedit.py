"""SDEdit maths: strength → starting noise level, chunking, and strength 0 = identity."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest
import torch

from surfphase.prior import sdedit
from surfphase.prior.embedded import EmbeddedPrior

TINY = {"channels": [8, 8], "frames": 4, "overlap": 1, "sample_steps": 10}


@pytest.fixture(autouse=True)
def one_thread():
    """Tiny tensors: one thread avoids OpenMP spinning on the shared 2-core machine."""
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


@pytest.mark.parametrize("shift", [1.0, 3.0, 7.0])
@pytest.mark.parametrize("n_steps", [4, 10, 30])
def test_flow_match_sigmas_match_diffusers_scheduler(shift, n_steps):
    from diffusers import FlowMatchEulerDiscreteScheduler

    sch = FlowMatchEulerDiscreteScheduler(shift=shift)
    sch.set_timesteps(n_steps)
    ours = sdedit.flow_match_sigmas(n_steps, shift)
    np.testing.assert_allclose(ours, sch.sigmas.numpy(), rtol=0, atol=2e-6)
    np.testing.assert_allclose(1000 * ours[:-1], sch.timesteps.numpy(), rtol=1e-6, atol=1e-3)


@pytest.mark.parametrize("strength", [0.05, 0.2, 0.35, 0.5, 1.0])
def test_wan_start_noise_level_is_what_the_pipeline_uses(strength):
    """The pipeline's own step selection and noising give σ = flow_match_start_sigma."""
    from diffusers import FlowMatchEulerDiscreteScheduler, WanVideoToVideoPipeline

    n = 30
    sch = FlowMatchEulerDiscreteScheduler(shift=7.0)
    sch.set_timesteps(n)
    fake_pipe = SimpleNamespace(scheduler=sch)
    steps, n_run = WanVideoToVideoPipeline.get_timesteps(
        fake_pipe, n, sch.timesteps, strength, "cpu"
    )
    i0, n_ours = sdedit.img2img_steps(strength, n)
    assert n_run == n_ours == len(steps) == int(n * strength)
    sigma = sdedit.flow_match_start_sigma(strength, n, shift=7.0)
    assert float(steps[0]) / 1000 == pytest.approx(sigma, abs=1e-6)
    # the noising the pipeline applies at that timestep: x = σ·ε + (1 − σ)·x0
    x0, eps = (
        torch.full((1, 2, 3), 0.7),
        torch.randn(1, 2, 3, generator=torch.Generator().manual_seed(0)),
    )
    sch.set_begin_index(i0)
    noised = sch.scale_noise(x0, steps[:1], eps)
    torch.testing.assert_close(noised, sigma * eps + (1 - sigma) * x0, atol=1e-6, rtol=0)


def test_strength_zero_runs_no_step():
    assert sdedit.img2img_steps(0.0, 30) == (30, 0)
    assert sdedit.flow_match_start_sigma(0.0, 30, 7.0) == 0.0
    assert sdedit.flow_sdedit_times(0.0, 24).size == 0
    with pytest.raises(ValueError, match="strength"):
        sdedit.check_strength(1.2)
    with pytest.raises(ValueError, match="strength"):
        sdedit.check_strength(float("nan"))


@pytest.mark.parametrize("strength,n", [(0.2, 5), (0.35, 8), (1.0, 24), (0.01, 1)])
def test_flow_times_start_at_strength(strength, n):
    t = sdedit.flow_sdedit_times(strength, 24)
    assert t[0] == strength and t[-1] == 0.0 and len(t) == n + 1
    assert np.all(np.diff(t) < 0)


@pytest.mark.parametrize(
    "T,chunk,overlap", [(24, 8, 2), (25, 9, 4), (5, 9, 4), (33, 33, 8), (10, 4, 3)]
)
def test_temporal_chunks_cover_and_overlap(T, chunk, overlap):
    w = sdedit.temporal_chunks(T, chunk, overlap)
    assert w[0][0] == 0 and w[-1][1] == T
    assert all(b - a == min(chunk, T) for a, b in w)
    for (a0, b0), (a1, _) in zip(w[:-1], w[1:], strict=True):
        assert b0 - a1 >= overlap and a1 > a0


def test_merge_chunks_crossfades_without_seams():
    rng = np.random.default_rng(0)
    video = rng.random((20, 3, 4)).astype(np.float32)
    # identity per window → the input back
    same = sdedit.refine_in_chunks(video, 8, 3, lambda v, k: v)
    np.testing.assert_allclose(same, video, atol=1e-6)
    # window k returns the constant k: in an overlap the blend moves monotonically
    w = sdedit.temporal_chunks(20, 8, 3)
    out = sdedit.merge_chunks(
        20, w, [np.full((b - a, 1, 1), float(k)) for k, (a, b) in enumerate(w)]
    )
    assert out[0, 0, 0] == 0.0 and out[-1, 0, 0] == len(w) - 1
    assert np.all(np.diff(out[:, 0, 0]) >= 0)


def test_embedded_strength_zero_returns_input_exactly():
    prior = EmbeddedPrior(TINY)
    video = np.random.default_rng(1).random((6, 12, 12)).astype(np.float32)
    out = prior.refine(video, 0.0, seed=3)
    assert out.dtype == np.float32 and np.array_equal(out, video)


@pytest.mark.parametrize("strength", [0.2, 0.35, 0.8])
def test_embedded_starts_at_documented_noise_level(strength):
    """First model call: t = strength and x = (1 − s)·x0 + s·ε (checked by statistics)."""
    prior = EmbeddedPrior(TINY)
    calls = []

    def hook(_mod, args):
        calls.append((args[0].detach().clone(), args[1].detach().clone()))

    prior.ema.register_forward_pre_hook(hook)
    c = 0.8  # constant video: x0 = 2c − 1 in model units
    prior.refine(np.full((4, 32, 32), c, np.float32), strength, seed=0)
    x, t = calls[0]
    assert torch.all(t == strength)
    assert len(calls) == len(sdedit.flow_sdedit_times(strength, TINY["sample_steps"])) - 1
    assert float(x.mean()) == pytest.approx((1 - strength) * (2 * c - 1), abs=0.02)
    assert float(x.std()) == pytest.approx(strength, rel=0.03)


def test_embedded_refine_deterministic_per_seed():
    prior = EmbeddedPrior(TINY)
    video = np.random.default_rng(2).random((9, 8, 12)).astype(np.float32)
    a = prior.refine(video, 0.35, seed=5)
    b = prior.refine(video, 0.35, seed=5)
    c = prior.refine(video, 0.35, seed=6)
    assert a.shape == video.shape and np.array_equal(a, b) and not np.array_equal(a, c)
    assert a.min() >= 0.0 and a.max() <= 1.0


class _LinearField(torch.nn.Module):
    """v(x, t) = x: dx/dt = x has the closed-form flow x(0) = x(s)·e^{−s}."""

    multiple = 1

    def forward(self, x, t, rows=None, label=None):
        return x


@pytest.mark.parametrize("sampler", ["euler", "heun"])
def test_samplers_match_their_closed_form_steps(sampler):
    """Euler multiplies by (1 + Δ) per step; Heun by (1 + Δ + Δ²/2) (its last step Euler);
    Heun is the closer of the two to the exact flow e^{−s}."""
    prior = EmbeddedPrior({**TINY, "sampler": sampler})
    prior.ema = _LinearField()
    times = sdedit.flow_sdedit_times(0.8, 10)
    x = torch.ones(1, 1, 2, 3, 3, dtype=torch.float64)
    got = float(prior._integrate(x, times).mean())
    factors = []
    for k, dt in enumerate(np.diff(times)):
        last = k == len(times) - 2
        factors.append(1 + dt if sampler == "euler" or last else 1 + dt + dt * dt / 2)
    assert got == pytest.approx(float(np.prod(factors)), rel=1e-12)
    if sampler == "heun":
        euler = float(np.prod(1 + np.diff(times)))
        assert abs(got - np.exp(-0.8)) < abs(euler - np.exp(-0.8)) / 3
