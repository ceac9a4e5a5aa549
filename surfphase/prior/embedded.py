"""The embedded video prior: a small (2+1)D U-Net trained from scratch by rectified flow.

Pixel space, grayscale, values mapped from [0, 1] to [−1, 1]. The network predicts the
velocity v = ε − x0 of the straight path x_t = (1 − t)·x0 + t·ε (t ∈ [0, 1], t = 1 is
pure noise); sampling and SDEdit integrate dx/dt = v from t_start to 0 with Euler steps
(:mod:`surfphase.prior.sdedit`).

Sized for two CPU cores: spatial 3×3 convolutions run per frame (``Conv2d`` on frames
folded into the batch, much faster on CPUs than ``Conv3d``), temporal mixing is a
3-tap convolution along time, and training uses random ``crop × crop`` windows of
``frames`` consecutive frames at the clips' native pixel scale. The network is fully
convolutional, so it refines whole frames of any size (padded to a multiple of
``patch``·2^(levels−1)); along time, videos longer than ``frames`` are refined in
overlapping chunks that share one noise draw and are cross-faded.

What makes its samples look like a boiling video rather than a texture of dark blobs
(measured in BENCHMARKS.md, "prior"):

* ``position``: the network sees each row's height in the frame (an extra input
  channel, −1 at the top, 1 at the bottom; a crop sees its own rows' heights), so it
  learns that the dark heated surface lies at the bottom and bubbles above it. Without
  it, a network trained on crops spreads the plate's dark texture everywhere.
* ``patch`` = 2: the U-Net runs on 2×2 space-to-depth frames (pixel-unshuffle), which
  doubles its receptive field in pixels and lets it be twice as wide for less compute.
* ``time_dist`` = ``tilted``: training times with density 0.5 + t, more of them at high
  noise, where a generation from noise decides where the bubbles are.
* ``crop_focus`` = 0.75 with ``focus_label``: three training windows in four are centred
  on moving content (the bubbles, a few percent of the pixels) and the network is told
  which kind each window is; sampling and refinement ask for the uniform kind. The
  focused windows teach the dark ring with its bright centre; the label keeps the
  clips' bubble density (focused windows alone give 3–4× too many bubbles; importance
  weights instead, ``focus_weighted``, learn the ring as slowly as uniform windows).
* ``frames`` = 4 and 1600 steps: twice the steps of 8-frame windows for the same CPU time.
"""

from __future__ import annotations

import copy
import json
import math
import time
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from surfphase.io import atomic_path, atomic_write_json
from surfphase.prior.interface import check_video
from surfphase.prior.sdedit import check_strength, flow_sdedit_times, refine_in_chunks
from surfphase.progress import Progress

WEIGHTS = "embedded.pt"
#: Smallest t in the velocity of a clean-video prediction (``predict: x``).
X_PRED_T_MIN = 0.05

DEFAULT_PARAMS: dict = {
    "frames": 4,  # frames per training window and refinement chunk
    "overlap": 2,  # frames shared by consecutive refinement chunks
    "crop": 32,  # training crop, pixels (native scale)
    "channels": [32, 64, 96],  # U-Net widths per level (each level halves H and W)
    "patch": 2,  # pixel-unshuffle factor at the input (2: the U-Net runs at half resolution)
    "position": True,  # an input channel with each row's height in the frame, −1 … 1
    "steps": 1600,  # optimiser steps
    "batch": 8,  # windows per step
    "lr": 1e-3,  # AdamW learning rate (cosine decay to 5 %, 20-step warm-up)
    "time_dist": "tilted",  # training times: uniform | logit_normal | tilted (density 0.5 + t)
    "predict": "v",  # network output: v (velocity) | x (clean video; v = (x_t − x)/max(t, 0.05))
    "crop_focus": 0.75,  # fraction of training windows centred on moving content (bubbles)
    "focus_weighted": False,  # weight focused windows' losses by p_uniform/q (unbiased density)
    "focus_label": True,  # tell the network focused from uniform windows; generate uniform
    "ema": 0.995,  # decay of the weight average used for sampling
    "sample_steps": 24,  # Euler steps of a full (strength 1) generation
    "sampler": "euler",  # euler | heun (2nd order: two network calls per step but the last)
    "seed": 0,
}


class _SpatialConv(nn.Module):
    """3×3 convolution applied to each frame: (B, C, T, H, W) → (B, C', T, H, W)."""

    def __init__(self, cin: int, cout: int, kernel: int = 3, stride: int = 1):
        super().__init__()
        self.conv = nn.Conv2d(cin, cout, kernel, stride=stride, padding=(kernel - 1) // 2)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        b, c, t, h, w = x.shape
        y = self.conv(x.transpose(1, 2).reshape(b * t, c, h, w))
        return y.reshape(b, t, *y.shape[1:]).transpose(1, 2)


class _TemporalConv(nn.Module):
    """3-tap convolution along time (zero padded): (B, C, T, H, W) → (B, C', T, H, W)."""

    def __init__(self, cin: int, cout: int):
        super().__init__()
        self.conv = nn.Conv2d(cin, cout, (3, 1), padding=(1, 0))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        b, c, t, h, w = x.shape
        return self.conv(x.reshape(b, c, t, h * w)).reshape(b, -1, t, h, w)


def _per_frame(op, x: torch.Tensor, *args) -> torch.Tensor:
    """Apply a 2D image op to every frame: (B, C, T, H, W) → (B, C', T, H', W')."""
    b, c, t, h, w = x.shape
    y = op(x.transpose(1, 2).reshape(b * t, c, h, w), *args)
    return y.reshape(b, t, *y.shape[1:]).transpose(1, 2)


class _ResBlock(nn.Module):
    """Residual (2+1)D block with the time embedding applied as scale and shift."""

    def __init__(self, cin: int, cout: int, emb: int):
        super().__init__()
        self.norm1 = nn.GroupNorm(min(8, cin), cin)
        self.space1, self.time1 = _SpatialConv(cin, cout), _TemporalConv(cout, cout)
        self.film = nn.Linear(emb, 2 * cout)
        self.norm2 = nn.GroupNorm(min(8, cout), cout)
        self.space2, self.time2 = _SpatialConv(cout, cout), _TemporalConv(cout, cout)
        nn.init.zeros_(self.time2.conv.weight)  # start as identity: stabler early training
        nn.init.zeros_(self.time2.conv.bias)
        self.skip = nn.Identity() if cin == cout else _SpatialConv(cin, cout, kernel=1)

    def forward(self, x: torch.Tensor, emb: torch.Tensor) -> torch.Tensor:
        h = self.time1(self.space1(F.silu(self.norm1(x))))
        scale, shift = self.film(emb)[:, :, None, None, None].chunk(2, dim=1)
        h = F.silu(self.norm2(h) * (1 + scale) + shift)
        return self.skip(x) + self.time2(self.space2(h))


class VideoUNet(nn.Module):
    """Velocity network v(x_t, t): (B, 1, T, H, W), (B,) → (B, 1, T, H, W).

    H and W must be multiples of 2^(levels − 1); T is free (temporal convolutions).
    """

    def __init__(
        self,
        channels: list[int] | tuple[int, ...] = (16, 32, 64),
        emb: int = 64,
        patch: int = 1,
        position: bool = False,
        labels: int = 0,
    ):
        super().__init__()
        ch = list(channels)
        self.emb_dim = emb
        self.patch = int(patch)
        self.position = bool(position)
        self.emb = nn.Sequential(nn.Linear(emb, 2 * emb), nn.SiLU(), nn.Linear(2 * emb, emb))
        self.label = nn.Embedding(labels, emb) if labels else None
        if self.label is not None:
            nn.init.zeros_(self.label.weight)  # start as the unlabelled network
        self.inp = _SpatialConv((1 + self.position) * self.patch**2, ch[0])
        self.down = nn.ModuleList()
        self.pool = nn.ModuleList()
        c = ch[0]
        for i, co in enumerate(ch):
            self.down.append(_ResBlock(c, co, emb))
            c = co
            if i < len(ch) - 1:
                self.pool.append(_SpatialConv(c, c, kernel=3, stride=2))
        self.mid = _ResBlock(c, c, emb)
        self.up = nn.ModuleList()
        for co in reversed(ch):
            self.up.append(_ResBlock(c + co, co, emb))
            c = co
        self.out_norm = nn.GroupNorm(min(8, c), c)
        self.out = _SpatialConv(c, self.patch**2)
        nn.init.zeros_(self.out.conv.weight)
        nn.init.zeros_(self.out.conv.bias)

    @property
    def multiple(self) -> int:
        """H and W must be multiples of this."""
        return self.patch * 2 ** len(self.pool)

    def forward(
        self,
        x: torch.Tensor,
        t: torch.Tensor,
        rows: torch.Tensor | None = None,
        label: torch.Tensor | None = None,
    ) -> torch.Tensor:
        """``rows``: (B, H) height of each image row in its frame, −1 top … 1 bottom
        (required when the network was built with ``position``); ``label``: (B,) int64
        class of each window when it was built with ``labels`` (default class 0)."""
        half = self.emb_dim // 2
        freqs = torch.exp(-math.log(1000.0) * torch.arange(half, device=x.device) / half)
        ang = 1000.0 * t[:, None].to(x.dtype) * freqs[None]
        e = self.emb(torch.cat([ang.sin(), ang.cos()], dim=1))
        if self.label is not None:
            if label is None:
                label = torch.zeros(x.shape[0], dtype=torch.long, device=x.device)
            e = e + self.label(label)
        if self.position:
            if rows is None or rows.shape != (x.shape[0], x.shape[3]):
                raise ValueError("VideoUNet: position needs rows of shape (B, H)")
            y = rows.to(x.dtype)[:, None, None, :, None].expand(-1, 1, x.shape[2], -1, x.shape[4])
            x = torch.cat([x, y], dim=1)
        if self.patch > 1:  # (B, 1, T, H, W) → (B, p², T, H/p, W/p), lossless
            x = _per_frame(F.pixel_unshuffle, x, self.patch)
        h = self.inp(x)
        skips = []
        for i, block in enumerate(self.down):
            h = block(h, e)
            skips.append(h)
            if i < len(self.pool):
                h = self.pool[i](h)
        h = self.mid(h, e)
        for block in self.up:
            skip = skips.pop()
            if h.shape[-2:] != skip.shape[-2:]:
                h = F.interpolate(h, size=skip.shape[2:], mode="nearest")
            h = block(torch.cat([h, skip], dim=1), e)
        y = self.out(F.silu(self.out_norm(h)))
        if self.patch > 1:  # back to (B, 1, T, H, W)
            y = _per_frame(F.pixel_shuffle, y, self.patch)
        return y


def activity_map(clip: np.ndarray) -> np.ndarray:
    """(T, H, W) float64 weights of moving content in a (T, H, W) clip in [0, 1]: each
    pixel's absolute difference from the clip's per-pixel temporal median (the static
    backlight and plate score ≈ 0, the bubbles high), squared so the bubbles dominate."""
    c = np.asarray(clip, np.float64)
    return (np.abs(c - np.median(c, axis=0)[None])) ** 2


def focus_proposal(activity: np.ndarray, crop: int) -> np.ndarray:
    """(T, H − crop + 1, W − crop + 1) float64: per frame, the probability of each window
    top-left corner when a centre pixel is drawn with probability ∝ ``activity`` (T, H, W)
    and the window is clipped into the frame (as :meth:`EmbeddedPrior._window` does).
    A frame without activity gets all zeros."""
    a = np.asarray(activity, np.float64)
    T, H, W = a.shape
    ny, nx = H - crop + 1, W - crop + 1
    ty = np.clip(np.arange(H) - crop // 2, 0, ny - 1)
    tx = np.clip(np.arange(W) - crop // 2, 0, nx - 1)
    rows = np.zeros((T, ny, W))
    np.add.at(rows, (slice(None), ty), a)  # rows[:, ty[i]] += a[:, i]
    q = np.zeros((T, ny, nx))
    np.add.at(q, (slice(None), slice(None), tx), rows)
    total = q.sum(axis=(1, 2), keepdims=True)
    return np.divide(q, total, out=np.zeros_like(q), where=total > 0)


def row_heights(height: int, n: int | None = None) -> torch.Tensor:
    """(n,) float32 heights of rows 0 … n−1 in a frame of ``height`` rows: −1 at the top
    row, 1 at the bottom one (rows past the bottom, e.g. padding, continue the ramp)."""
    n = height if n is None else n
    return torch.arange(n, dtype=torch.float32) * (2.0 / max(height - 1, 1)) - 1.0


class EmbeddedPrior:
    """Rectified-flow video prior trained from scratch (the default backend).

    Args:
        params: overrides of :data:`DEFAULT_PARAMS`.
        device: torch device for training and inference.
    """

    backend = "embedded"

    def __init__(self, params: dict | None = None, device: str | torch.device = "cpu"):
        unknown = set(params or {}) - set(DEFAULT_PARAMS)
        if unknown:
            raise ValueError(f"embedded prior: unknown parameters {sorted(unknown)}")
        self.params = {**DEFAULT_PARAMS, **(params or {})}
        self.device = torch.device(device)
        torch.manual_seed(int(self.params["seed"]))
        self.model = VideoUNet(
            self.params["channels"],
            patch=int(self.params["patch"]),
            position=bool(self.params["position"]),
            labels=2 if self.params["focus_label"] else 0,
        )
        self.model = self.model.to(self.device)
        self.ema = copy.deepcopy(self.model).eval().requires_grad_(False)

    # ------------------------------------------------------------------ training
    def train(self, clips: list[np.ndarray], params: dict | None = None, log=print) -> dict:
        """Fit the network on monocular clips; returns a log (losses, seconds).

        Args:
            clips: list of (T_i, H_i, W_i) float32 videos in [0, 1]; each needs at least
                ``frames`` frames and ``crop`` pixels per side.
            params: overrides of the training parameters (``steps``, ``batch``, ``lr``…).
            log: called with a progress line every 50 steps (``None`` for silence).
        """
        if params:
            unknown = set(params) - set(DEFAULT_PARAMS)
            if unknown:
                raise ValueError(f"embedded prior: unknown parameters {sorted(unknown)}")
            arch = {"channels", "patch", "position", "focus_label"} & {
                k for k in params if params[k] != self.params[k]
            }
            if arch:
                raise ValueError(f"embedded prior: set {sorted(arch)} when creating the prior")
            self.params.update(params)
        p = self.params
        T, crop = int(p["frames"]), int(p["crop"])
        if not clips:
            raise ValueError("embedded prior: no training clips")
        for k, c in enumerate(clips):
            check_video(c, f"clip {k}")
            if c.shape[0] < T or min(c.shape[1:]) < crop:
                raise ValueError(
                    f"embedded prior: clip {k} has shape {c.shape}; need ≥ {T} frames and "
                    f"≥ {crop} px per side (params 'frames', 'crop')"
                )
        data = [torch.from_numpy(np.ascontiguousarray(c, np.float32)) * 2 - 1 for c in clips]
        focus = (
            [focus_proposal(activity_map(c), crop) for c in clips]
            if float(p["crop_focus"]) > 0
            else None
        )
        rng = np.random.default_rng([int(p["seed"]), 77])
        gen = torch.Generator().manual_seed(int(p["seed"]))
        steps, batch = int(p["steps"]), int(p["batch"])
        opt = torch.optim.AdamW(self.model.parameters(), lr=float(p["lr"]), weight_decay=0.0)

        def lr_at(i: int) -> float:
            warm = min(1.0, (i + 1) / 20)
            return warm * (0.05 + 0.95 * 0.5 * (1 + math.cos(math.pi * i / max(1, steps))))

        sched = torch.optim.lr_scheduler.LambdaLR(opt, lr_at)
        self.model.train()
        losses, t0 = [], time.perf_counter()
        progress = Progress(steps, "prior training: step", log=log)
        for step in range(steps):
            wins = [
                self._window(data, rng, T, crop, focus, float(p["crop_focus"]))
                for _ in range(batch)
            ]
            x0 = torch.stack([w[0] for w in wins])[:, None].to(self.device)  # (B,1,T,c,c)
            rows = torch.stack([w[1] for w in wins]).to(self.device)  # (B, crop)
            if p["focus_weighted"]:
                weight = torch.tensor([w[2] for w in wins], device=self.device)
            else:
                weight = torch.ones(batch, device=self.device)
            label = torch.tensor([int(w[3]) for w in wins], device=self.device)
            noise = torch.randn(x0.shape, generator=gen).to(self.device)
            t = self._train_times(batch, gen).to(self.device)
            xt = (1 - t[:, None, None, None, None]) * x0 + t[:, None, None, None, None] * noise
            v = self._velocity(self.model, xt, t, rows, label)
            err = (v - (noise - x0)).square().mean(dim=(1, 2, 3, 4))
            loss = (weight * err).mean()
            opt.zero_grad(set_to_none=True)
            loss.backward()
            nn.utils.clip_grad_norm_(self.model.parameters(), 1.0)
            opt.step()
            sched.step()
            self._update_ema(min(float(p["ema"]), (1 + step) / (10 + step)))
            losses.append(float(loss.detach()))
            if log and ((step + 1) % 50 == 0 or step + 1 == steps):
                progress.step(f"loss {np.mean(losses[-50:]):.4f}", n=step + 1 - progress.done)
        self.model.eval()
        return {
            "steps": steps,
            "seconds": round(time.perf_counter() - t0, 2),
            "loss_first50": float(np.mean(losses[:50])),
            "loss_last50": float(np.mean(losses[-50:])),
            "losses": [round(v, 5) for v in losses],
        }

    def _velocity(
        self,
        net: VideoUNet,
        xt: torch.Tensor,
        t: torch.Tensor,
        rows: torch.Tensor,
        label: torch.Tensor | None = None,
    ) -> torch.Tensor:
        """v(x_t, t), (B, 1, T, H, W): the network's output, or with ``predict: x`` the
        velocity of its clean-video estimate x̂: (x_t − x̂)/max(t, 0.05). Predicting the
        clean video asks a small network for a smooth image instead of noise (Li & He,
        2025, "Back to basics: let denoising generative models denoise").

        ``label`` (with ``focus_label``): 1 for focused training windows, 0 (the default,
        used for sampling and refinement) for uniform ones."""
        out = net(xt, t, rows=rows, label=label)
        mode = self.params["predict"]
        if mode == "v":
            return out
        if mode == "x":
            return (xt - out) / t.clamp_min(X_PRED_T_MIN)[:, None, None, None, None]
        raise ValueError(f"embedded prior: predict must be 'v' or 'x', not {mode!r}")

    def _train_times(self, n: int, gen: torch.Generator) -> torch.Tensor:
        """(n,) training times in (0, 1): uniform, or logit-normal (more weight mid-path,
        where the layout of the bubbles is decided; Esser et al., 2024)."""
        dist = self.params["time_dist"]
        if dist == "uniform":
            return torch.rand(n, generator=gen)
        if dist == "logit_normal":
            return torch.sigmoid(torch.randn(n, generator=gen))
        if dist == "tilted":  # density 0.5 + t: half uniform, half ∝ t (more high noise)
            u, pick = torch.rand(n, generator=gen), torch.rand(n, generator=gen)
            return torch.where(pick < 0.5, u, u.sqrt())
        raise ValueError(
            f"embedded prior: time_dist must be uniform, logit_normal or tilted, not {dist!r}"
        )

    @staticmethod
    def _window(
        data: list[torch.Tensor],
        rng: np.random.Generator,
        T: int,
        crop: int,
        focus: list[np.ndarray] | None = None,
        focus_frac: float = 0.0,
    ):
        """A random (T, crop, crop) window of a random clip, mirrored left-right at random,
        the (crop,) heights of its rows in the clip's frame (:func:`row_heights`), its
        importance weight, and whether it was centred on moving content.

        With ``focus`` (per clip the (T_i, H_i − crop + 1, W_i − crop + 1)
        :func:`focus_proposal` of its :func:`activity_map`), a fraction ``focus_frac`` of
        the windows is centred on a pixel drawn with probability proportional to the
        activity of the window's first frame, so that the network sees the bubbles, a few
        percent of the pixels, in most windows. The weight p/q (uniform corner density
        over the mixture's; training uses it with ``focus_weighted``) makes the weighted
        loss an unbiased estimate of the loss over uniform windows, so that the network
        keeps the clips' bubble density while seeing more bubble windows (measured in
        BENCHMARKS.md: it then also learns the bubbles as slowly as from uniform windows).
        Without ``focus`` the weight is 1. With ``focus_label`` the network is told
        instead which windows were focused, and generates uniform ones.

        No vertical flips or time reversal: bubbles rise, and the prior should know it.
        """
        k = int(rng.integers(len(data)))
        c = data[k]
        a = int(rng.integers(c.shape[0] - T + 1))
        ny, nx = c.shape[1] - crop + 1, c.shape[2] - crop + 1
        y = int(rng.integers(ny))
        x = int(rng.integers(nx))
        weight, focused = 1.0, False
        if focus is not None and focus[k][a].any():
            q = focus[k][a]
            if rng.random() < focus_frac:
                i = int(rng.choice(q.size, p=q.ravel()))
                y, x = divmod(i, nx)
                focused = True
            uniform = 1.0 / (ny * nx)
            weight = uniform / ((1 - focus_frac) * uniform + focus_frac * float(q[y, x]))
        w = c[a : a + T, y : y + crop, x : x + crop]
        rows = row_heights(c.shape[1])[y : y + crop]
        return (w.flip(-1) if rng.random() < 0.5 else w), rows, weight, focused

    @torch.no_grad()
    def _update_ema(self, decay: float) -> None:
        for pe, pm in zip(self.ema.parameters(), self.model.parameters(), strict=True):
            pe.mul_(decay).add_(pm.detach(), alpha=1 - decay)

    # ----------------------------------------------------------------- sampling
    @torch.no_grad()
    def _integrate(self, x: torch.Tensor, times: np.ndarray) -> torch.Tensor:
        """Euler-integrate dx/dt = v(x, t) along ``times`` (decreasing); x (B, 1, T, H, W)."""
        m = self.ema.multiple
        h, w = x.shape[-2:]
        ph, pw = (-h) % m, (-w) % m
        heun = self.params["sampler"] == "heun"
        rows = row_heights(h, h + ph).to(x.device).expand(x.shape[0], -1)

        def velocity(x: torch.Tensor, t: float) -> torch.Tensor:
            xin = F.pad(x, (0, pw, 0, ph, 0, 0), mode="replicate") if (ph or pw) else x
            tt = torch.full((x.shape[0],), t, device=x.device)
            return self._velocity(self.ema, xin, tt, rows)[..., :h, :w]

        for t_now, t_next in zip(times[:-1], times[1:], strict=True):
            dt = float(t_next - t_now)
            v = velocity(x, float(t_now))
            if heun and t_next > 0:  # trapezoidal correction (the last step stays Euler)
                v = 0.5 * (v + velocity(x + dt * v, float(t_next)))
            x = x + dt * v
        return x

    def refine(self, video: np.ndarray, strength: float, seed: int = 0) -> np.ndarray:
        """SDEdit: noise ``video`` to t = ``strength`` and denoise it with the prior.

        Args:
            video: (T, H, W) float32 in [0, 1].
            strength: SDEdit strength s ∈ [0, 1] (starting time t_start = s).
            seed: seed of the noise draw (one draw for the whole video).

        Returns:
            (T, H, W) float32 in [0, 1]; the input itself (a copy) when s = 0.
        """
        check_video(video, "video")
        times = flow_sdedit_times(check_strength(strength), int(self.params["sample_steps"]))
        video = np.asarray(video, np.float32)
        if times.size == 0:
            return video.copy()
        x0 = torch.from_numpy(np.ascontiguousarray(video)) * 2 - 1
        noise = torch.randn(x0.shape, generator=torch.Generator().manual_seed(int(seed)))
        s = float(times[0])
        xs = ((1 - s) * x0 + s * noise).numpy()

        def run(window: np.ndarray, _k: int) -> np.ndarray:
            x = torch.from_numpy(window)[None, None].to(self.device)
            return self._integrate(x, times)[0, 0].cpu().numpy()

        frames = int(self.params["frames"])
        out = refine_in_chunks(xs, frames, int(self.params["overlap"]), run)
        return np.clip((out + 1) / 2, 0.0, 1.0).astype(np.float32)

    def sample(self, n: int, frames: int, size: int, seed: int = 0) -> np.ndarray:
        """Generate ``n`` videos from pure noise: (n, frames, size, size) float32 in [0, 1]."""
        gen = torch.Generator().manual_seed(int(seed))
        noise = torch.randn((n, 1, frames, size, size), generator=gen).to(self.device)
        times = flow_sdedit_times(1.0, int(self.params["sample_steps"]))
        x = self._integrate(noise, times)
        return np.clip((x[:, 0].cpu().numpy() + 1) / 2, 0.0, 1.0).astype(np.float32)

    # ---------------------------------------------------------------- save/load
    def save(self, folder: str | Path) -> None:
        """Write ``folder/embedded.pt`` (weights and EMA weights) and ``folder/prior.json``."""
        folder = Path(folder)
        folder.mkdir(parents=True, exist_ok=True)
        state = {"model": self.model.state_dict(), "ema": self.ema.state_dict()}
        with atomic_path(folder / WEIGHTS) as tmp:
            torch.save(state, tmp)
        atomic_write_json(folder / "prior.json", {"backend": self.backend, "params": self.params})

    @classmethod
    def load(cls, folder: str | Path, device: str | torch.device = "cpu") -> EmbeddedPrior:
        """Read a prior written by :meth:`save`."""
        folder = Path(folder)
        meta = json.loads((folder / "prior.json").read_text())
        prior = cls(meta["params"], device=device)
        path = folder / WEIGHTS
        if not path.is_file():
            raise FileNotFoundError(f"embedded prior: weights {path} not found")
        state = torch.load(path, map_location=prior.device, weights_only=True)
        prior.model.load_state_dict(state["model"])
        prior.ema.load_state_dict(state["ema"])
        prior.model.eval()
        return prior
