"""SDEdit scheduling maths: how a refinement ``strength`` becomes a starting noise level.

SDEdit (Meng et al., 2022) refines a video by noising it part of the way towards pure
noise and denoising it back with the prior. ``strength`` s ∈ [0, 1] says how far:

* **Rectified flow, continuous time** (the embedded prior). The noisy video is
  x_t = (1 − t)·x0 + t·ε, ε ~ N(0, I), x0 in [−1, 1]. SDEdit starts at
  **t_start = s** and integrates the learnt velocity with Euler steps on the uniform
  grid t_k = s·(1 − k/n), k = 0 … n, n = max(1, round(s·N)) for an N-step full
  schedule (so a strength-0.35 refinement with N = 24 takes 8 steps).
* **Diffusers' discrete schedules** (the Wan backend, ``WanVideoToVideoPipeline``).
  With N inference steps the pipeline runs the last n = min(⌊N·s⌋, N) steps of the
  schedule, starting at index i0 = N − n; the starting noise level is σ[i0] of the
  scheduler's sigma list. For ``FlowMatchEulerDiscreteScheduler`` (no dynamic
  shifting; ``shift`` a; T training steps) that list is, with
  g(σ) = a·σ / (1 + (a − 1)·σ):
  σ_max = g(1) = 1, σ_min = g(1/T), σ_k = g(σ_max + k·(σ_min − σ_max)/(N − 1)),
  k = 0 … N − 1, then a final 0. (Diffusers applies the shift to the already
  shifted end points; :func:`flow_match_sigmas` reproduces that exactly.) The
  timestep handed to the transformer is T·σ.

Strength 0 means no step at all: both backends then return the input unchanged,
bit for bit, without calling the model.

Long videos are refined in overlapping chunks along time whose results are
cross-faded linearly in the overlaps (:func:`temporal_chunks`, :func:`merge_chunks`).
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np


def check_strength(strength: float) -> float:
    """Return ``strength`` as a float, or raise ValueError outside [0, 1]."""
    s = float(strength)
    if not 0.0 <= s <= 1.0 or not np.isfinite(s):
        raise ValueError(f"SDEdit strength must be in [0, 1], got {strength!r}")
    return s


def flow_sdedit_times(strength: float, num_steps: int) -> np.ndarray:
    """Euler time grid of a rectified-flow SDEdit run, from t_start = ``strength`` to 0.

    Args:
        strength: s in [0, 1]; the starting time (= noise weight) is t_start = s.
        num_steps: N, the number of steps of a full (s = 1) generation.

    Returns:
        (n + 1,) float64 times s·(1 − k/n), k = 0 … n, n = max(1, round(s·N));
        an empty array for s = 0 (nothing to do).
    """
    s = check_strength(strength)
    if num_steps < 1:
        raise ValueError(f"num_steps must be ≥ 1, got {num_steps}")
    if s == 0.0:
        return np.zeros(0)
    n = max(1, int(round(s * num_steps)))
    return s * (1.0 - np.arange(n + 1) / n)


def img2img_steps(strength: float, num_inference_steps: int) -> tuple[int, int]:
    """Diffusers' img2img/video2video convention: (start index i0, steps run n).

    n = min(⌊N·s⌋, N) and i0 = N − n, for N = ``num_inference_steps``.
    """
    s = check_strength(strength)
    n = min(int(num_inference_steps * s), num_inference_steps)
    return num_inference_steps - n, n


def flow_match_sigmas(
    num_inference_steps: int, shift: float = 1.0, num_train_timesteps: int = 1000
) -> np.ndarray:
    """Sigma list of ``FlowMatchEulerDiscreteScheduler.set_timesteps`` (static shift).

    Returns:
        (N + 1,) float64 noise levels σ_0 = 1 > … > σ_{N−1} > σ_N = 0 (see module doc).
    """

    def g(sig):
        return shift * sig / (1.0 + (shift - 1.0) * sig)

    s_max, s_min = g(1.0), g(1.0 / num_train_timesteps)
    base = np.linspace(s_max, s_min, num_inference_steps)
    return np.append(g(base), 0.0)


def flow_match_start_sigma(
    strength: float, num_inference_steps: int, shift: float = 1.0, num_train_timesteps: int = 1000
) -> float:
    """Starting noise level σ[i0] of a diffusers flow-matching SDEdit run (0 if no step)."""
    i0, n = img2img_steps(strength, num_inference_steps)
    if n == 0:
        return 0.0
    return float(flow_match_sigmas(num_inference_steps, shift, num_train_timesteps)[i0])


def temporal_chunks(n_frames: int, chunk: int, overlap: int) -> list[tuple[int, int]]:
    """Split frames 0 … n_frames−1 into windows of ``chunk`` frames overlapping by ≥ ``overlap``.

    Returns (start, stop) pairs covering every frame; the last window ends at
    ``n_frames`` (the stride is shortened there rather than padding). A video no longer
    than ``chunk`` is one window (0, n_frames).
    """
    if chunk < 1 or not 0 <= overlap < chunk:
        raise ValueError(f"need chunk ≥ 1 and 0 ≤ overlap < chunk, got {chunk}, {overlap}")
    if n_frames <= chunk:
        return [(0, n_frames)]
    stride = chunk - overlap
    starts = list(range(0, n_frames - chunk, stride)) + [n_frames - chunk]
    return [(a, a + chunk) for a in starts]


def merge_chunks(
    n_frames: int, windows: list[tuple[int, int]], results: list[np.ndarray]
) -> np.ndarray:
    """Blend per-window results (each (stop − start, H, W)) into one (n_frames, H, W) video.

    In an overlap the earlier window's weight falls linearly to 0 while the later one's
    rises, so the cross-fade has no seam; outside overlaps a frame comes from one window.
    """
    shape = results[0].shape[1:]
    acc = np.zeros((n_frames, *shape), np.float64)
    wsum = np.zeros(n_frames, np.float64)
    for k, ((a, b), r) in enumerate(zip(windows, results, strict=True)):
        w = np.ones(b - a)
        if k > 0:  # ramp up over the overlap with the previous window
            ov = windows[k - 1][1] - a
            if ov > 0:
                w[:ov] = np.arange(1, ov + 1) / (ov + 1)
        if k + 1 < len(windows):  # ramp down over the overlap with the next window
            ov = b - windows[k + 1][0]
            if ov > 0:
                w[-ov:] = np.minimum(w[-ov:], np.arange(ov, 0, -1) / (ov + 1))
        acc[a:b] += w[:, None, None] * r
        wsum[a:b] += w
    return (acc / wsum[:, None, None]).astype(np.float32)


def refine_in_chunks(
    video: np.ndarray,
    chunk: int,
    overlap: int,
    refine_chunk: Callable[[np.ndarray, int], np.ndarray],
) -> np.ndarray:
    """Apply ``refine_chunk(frames, index)`` to overlapping windows and cross-fade them.

    Args:
        video: (T, H, W) float32.
        chunk, overlap: window length and minimum overlap, frames.
        refine_chunk: maps a (t, H, W) window and its index to a (t, H, W) result.

    Returns:
        (T, H, W) float32.
    """
    from surfphase.progress import Progress

    windows = temporal_chunks(video.shape[0], chunk, overlap)
    progress = Progress(len(windows), "refine: window")
    results = []
    for k, (a, b) in enumerate(windows):
        results.append(refine_chunk(video[a:b], k))
        progress.step(f"frames {a}-{b - 1}")
    return merge_chunks(video.shape[0], windows, results)
