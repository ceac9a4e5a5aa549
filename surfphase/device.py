"""The one ``device`` setting: ``auto`` (CUDA when present), ``cpu`` or ``cuda``."""

from __future__ import annotations

import torch


def resolve_device(setting: str | torch.device | None = "auto") -> torch.device:
    """Map the config's ``device`` value to a ``torch.device``.

    ``auto`` picks CUDA when available, else the CPU. Asking for ``cuda`` on a machine
    without it is an error rather than a silent fallback. On the CPU this also turns on
    :func:`bit_for_bit` (same inputs, seed and thread count → the same bytes).
    """
    dev = _resolve(setting)
    if dev.type == "cpu":
        bit_for_bit()
    return dev


def bit_for_bit() -> None:
    """Make torch's CPU kernels reproducible run to run.

    ``torch.use_deterministic_algorithms(True)``: ops with a run-dependent summation
    order (the threaded ``index_put_(accumulate=True)`` behind the backward of ``x[idx]``
    with repeated indices, measured to differ on every run from ~10k elements on 2
    threads) take their deterministic kernels. The project's own code avoids those ops
    (``index_select``/``index_add_``); this guards what it does not know of. It is not
    set on CUDA, whose deterministic mode needs cuBLAS settings of its own.

    The flag is set on torch's kernels directly: ``torch.use_deterministic_algorithms``
    also sets ``torch.compile``'s (inductor's) flag, and importing inductor for it costs
    every process about 1.7 s on the development machine (a fifth of a small fit job);
    nothing here uses ``torch.compile``.
    """
    set_kernels = getattr(torch._C, "_set_deterministic_algorithms", None)
    if set_kernels is None:  # a torch without it: the public call, inductor and all
        torch.use_deterministic_algorithms(True, warn_only=True)
    else:
        set_kernels(True, warn_only=True)


def _resolve(setting: str | torch.device | None) -> torch.device:
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
