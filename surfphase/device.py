"""The one ``device`` setting: ``auto`` (CUDA when present), ``cpu`` or ``cuda``."""

from __future__ import annotations

import torch


def resolve_device(setting: str | torch.device | None = "auto") -> torch.device:
    """Map the config's ``device`` value to a ``torch.device``.

    ``auto`` picks CUDA when available, else the CPU. Asking for ``cuda`` on a machine
    without it is an error rather than a silent fallback.
    """
    if isinstance(setting, torch.device):
        return setting
    s = (setting or "auto").lower()
    if s == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if s.startswith("cuda") and not torch.cuda.is_available():
        raise RuntimeError("device: cuda was asked for, but no CUDA device is available")
    if s == "cpu" or s.startswith("cuda"):
        return torch.device(s)
    raise ValueError(f"device must be auto, cpu or cuda, not {setting!r}")
