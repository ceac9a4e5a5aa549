"""The views a session is fitted to: its input views, optionally followed by refined views
with their photometric weights and a per-frame sampler (stage 2).

* :class:`ViewSet` — a session's views: the C input cameras and background images, and
  the refined views (:class:`RefinedViews`, e.g. :class:`surfphase.fit.stage2.ExtraViews`)
  or none (stage 1);
* :class:`FrameViews` — the views of one frame with their observed images;
* :class:`StepViews` — the views rendered at one optimisation step and the weighted
  photometric loss over them. Without refined views every input view is rendered at
  every step with weight 1; with them, the C input views and the refined views the
  sampler draws, with their weights; the geometry losses and the logged L1, D-SSIM and
  PSNR use the input views only.

Images are (·, H, W, D) float32 in [0, 1]; cameras as ``viewmats`` (·, 4, 4)
world-to-camera and ``Ks`` (·, 3, 3) pixels.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Protocol

import numpy as np
import torch

from surfphase.cameras import Camera
from surfphase.fit import losses

#: Step ``it`` → (view indices (K,) long into inputs + refined views, weights (K,)).
Sampler = Callable[[int], tuple[torch.Tensor, torch.Tensor]]


class RefinedViews(Protocol):
    """Refined views as extra supervision (:class:`surfphase.fit.stage2.ExtraViews`)."""

    cameras: list[Camera]  # V undistorted cameras of the input views' size
    backgrounds: np.ndarray  # (V, H, W, D) float32

    @property
    def n_frames(self) -> int: ...

    def images(self, t: int) -> np.ndarray:
        """(V, H, W, D) refined images of frame ``t``."""

    def schedule(self, t: int, n_inputs: int) -> Sampler:
        """The sampler of frame ``t``: every input view, then the refined views drawn."""


@dataclass
class StepViews:
    """The K views rendered at one step; the first ``n_inputs`` are input views."""

    viewmats: torch.Tensor  # (K, 4, 4)
    Ks: torch.Tensor  # (K, 3, 3)
    backgrounds: torch.Tensor  # (K, H, W, D)
    observed: torch.Tensor  # (K, H, W, D)
    weights: torch.Tensor | None  # (K,) photometric weights; None: all inputs, weight 1
    n_inputs: int

    def photometric(
        self, rgb: torch.Tensor, lambda_dssim: float
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """``(Σ_k w_k ((1−λ)·L1 + λ·D-SSIM)_k, mean L1, mean D-SSIM)`` of the (K, H, W, D)
        render ``rgb``; the means (logged) are over the input views."""
        loss_v, l1_v, dssim_v = losses.photometric_terms(rgb, self.observed, lambda_dssim)
        if self.weights is None:
            C = rgb.shape[0]
            return loss_v.sum(), l1_v.sum() / C, dssim_v.sum() / C
        ng = self.n_inputs
        return (self.weights.to(loss_v) * loss_v).sum(), l1_v[:ng].mean(), dssim_v[:ng].mean()

    def inputs(self, x: torch.Tensor) -> torch.Tensor:
        """The input views' rows of a per-view tensor (K, ...)."""
        return x if self.weights is None else x[: self.n_inputs]


@dataclass
class FrameViews:
    """The V views of one frame: inputs first, then refined views drawn by ``sampler``."""

    observed: torch.Tensor  # (V, H, W, D)
    viewmats: torch.Tensor  # (V, 4, 4)
    Ks: torch.Tensor  # (V, 3, 3)
    backgrounds: torch.Tensor  # (V, H, W, D)
    n_inputs: int
    sampler: Sampler | None  # None: every view (the inputs only) at every step

    def step(self, it: int) -> StepViews:
        """The views rendered at step ``it``."""
        if self.sampler is None:
            return StepViews(
                self.viewmats, self.Ks, self.backgrounds, self.observed, None, self.n_inputs
            )
        idx, w = self.sampler(it)
        return StepViews(
            self.viewmats[idx], self.Ks[idx], self.backgrounds[idx], self.observed[idx], w,
            self.n_inputs,
        )  # fmt: skip


class ViewSet:
    """A session's views: C input views and, for stage 2, refined views.

    Args:
        cameras: the C undistorted input cameras.
        backgrounds: (C, H, W, D) background images of the input views.
        refined: the refined views with their weights and sampler, or None.
        device, dtype: where and in what the tensors live.
    """

    def __init__(
        self,
        cameras: Sequence[Camera],
        backgrounds: np.ndarray,
        refined: RefinedViews | None = None,
        device: torch.device | str = "cpu",
        dtype: torch.dtype = torch.float32,
    ):
        from surfphase.render import camera_tensors

        self.n_inputs = len(cameras)
        self.refined = refined
        # The input views alone: bubble registration and the per-frame PSNR.
        self.viewmats, self.Ks = camera_tensors(list(cameras), device, dtype)
        self.backgrounds = torch.as_tensor(backgrounds, dtype=dtype, device=device)
        self.device = device
        self._all = (self.viewmats, self.Ks, self.backgrounds)
        if refined is not None:
            rv, rk = camera_tensors(refined.cameras, device, dtype)
            rbg = torch.as_tensor(refined.backgrounds, dtype=dtype, device=device)
            self._all = (
                torch.cat([self.viewmats, rv]),
                torch.cat([self.Ks, rk]),
                torch.cat([self.backgrounds, rbg]),
            )

    def frame(self, t: int, observed: torch.Tensor) -> FrameViews:
        """The views of frame ``t``, ``observed`` (C, H, W, D) its input images."""
        vm, ks, bg = self._all
        if self.refined is None:
            return FrameViews(observed, vm, ks, bg, self.n_inputs, None)
        ref = torch.as_tensor(self.refined.images(t), device=self.device)
        return FrameViews(
            torch.cat([observed, ref]), vm, ks, bg, self.n_inputs,
            self.refined.schedule(t, self.n_inputs),
        )  # fmt: skip
