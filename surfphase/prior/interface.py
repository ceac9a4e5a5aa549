"""One interface for the video priors: refine (SDEdit), train, sample, save and load.

A prior folder holds ``prior.json`` (``{"backend": "embedded" | "wan", "params": …}``)
next to the backend's weights; :func:`load_prior` reads any of them.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Protocol, runtime_checkable

import numpy as np

BACKENDS = ("embedded", "wan")


@runtime_checkable
class VideoPrior(Protocol):
    """A video diffusion prior over grayscale videos in [0, 1]."""

    backend: str
    params: dict

    def refine(self, video: np.ndarray, strength: float, seed: int = 0) -> np.ndarray:
        """SDEdit ``video`` (T, H, W) float32 in [0, 1] at ``strength``; returns (T, H, W).

        Strength 0 returns the input unchanged (see :mod:`surfphase.prior.sdedit`).
        """
        ...

    def train(self, clips: list[np.ndarray], params: dict | None = None, log=print) -> dict:
        """Train (or fine-tune) on clips, each (T_i, H_i, W_i) float32 in [0, 1]; returns a log."""
        ...

    def sample(self, n: int, frames: int, size: int, seed: int = 0) -> np.ndarray:
        """Generate (n, frames, size, size) float32 videos in [0, 1] from pure noise."""
        ...

    def save(self, folder: str | Path) -> None:
        """Write the prior (``prior.json`` and weights) into ``folder``."""
        ...


def check_video(video: np.ndarray, name: str = "video") -> None:
    """Raise ValueError unless ``video`` is a finite (T, H, W) array with T, H, W ≥ 1."""
    v = np.asarray(video)
    if v.ndim != 3 or min(v.shape) < 1:
        raise ValueError(f"{name}: expected a (T, H, W) grayscale video, got shape {v.shape}")
    if not np.all(np.isfinite(v)):
        raise ValueError(f"{name}: contains non-finite values")


def new_prior(backend: str = "embedded", params: dict | None = None, device="cpu") -> VideoPrior:
    """An untrained prior of ``backend`` (``wan`` needs ``params['weights']``, a local folder)."""
    if backend == "embedded":
        from surfphase.prior.embedded import EmbeddedPrior

        return EmbeddedPrior(params, device=device)
    if backend == "wan":
        from surfphase.prior.wan import WanPrior

        return WanPrior(params, device=device)
    raise ValueError(f"unknown prior backend {backend!r}; choose from {BACKENDS}")


def load_prior(folder: str | Path, device="cpu") -> VideoPrior:
    """Read a prior folder written by a backend's ``save``."""
    folder = Path(folder)
    meta_path = folder / "prior.json"
    if not meta_path.is_file():
        raise FileNotFoundError(f"no prior found: {meta_path} does not exist")
    try:
        backend = json.loads(meta_path.read_text())["backend"]
    except (json.JSONDecodeError, KeyError) as e:
        raise ValueError(f"{meta_path}: not a prior description ({e})") from e
    if backend == "embedded":
        from surfphase.prior.embedded import EmbeddedPrior

        return EmbeddedPrior.load(folder, device=device)
    if backend == "wan":
        from surfphase.prior.wan import WanPrior

        return WanPrior.load(folder, device=device)
    raise ValueError(f"{meta_path}: unknown prior backend {backend!r}")
