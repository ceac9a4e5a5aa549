"""The one ``device`` setting: ``auto`` (CUDA when present), ``cpu`` or ``cuda``."""

from __future__ import annotations

from typing import TYPE_CHECKING

if TYPE_CHECKING:  # imported where a device is resolved: platform_record needs none
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
    import torch

    set_kernels = getattr(torch._C, "_set_deterministic_algorithms", None)
    if set_kernels is None:  # a torch without it: the public call, inductor and all
        torch.use_deterministic_algorithms(True, warn_only=True)
    else:
        set_kernels(True, warn_only=True)


#: The libraries whose arithmetic a fit's bits depend on, recorded by
#: :func:`platform_record`.
RECORDED_LIBRARIES = (
    "torch",
    "numpy",
    "scipy",
    "numba",
    "llvmlite",
    "opencv-contrib-python-headless",
)


def platform_record() -> dict[str, object]:
    """What a run's floating-point results depend on beyond its inputs and settings:
    ``{"cpu": the CPU's model name, family, model and stepping (``/proc/cpuinfo``; else
    :func:`platform.processor`),
    "machine": the architecture, "python": its version, "libraries": {distribution:
    version} of :data:`RECORDED_LIBRARIES` installed}``.

    The same code and inputs give the same bits on one machine; the fit's kernels are
    pinned so that CPUs agree (``import surfphase``), but a library release can still
    round differently. The benchmark's draws give every figure that comes from the masks
    identically on an Intel Xeon and on AMD EPYCs, and the held-out PSNR about 0.2 dB
    apart a session on average, up to 1.4 dB, the AMD machines agreeing bit for bit
    (BENCHMARKS.md, determinism): with this record two results say which of these
    differed."""
    import platform
    from importlib import metadata

    info: dict[str, str] = {}
    try:
        with open("/proc/cpuinfo") as fh:
            for ln in fh:  # the first processor's block
                if not ln.strip():
                    break
                key, _, value = ln.partition(":")
                info[key.strip()] = value.strip()
    except OSError:
        pass
    cpu = info.get("model name", "")
    if "model" in info:  # a virtual machine's name can hide the model ("Intel Xeon Processor")
        cpu += f" (family {info.get('cpu family', '?')} model {info['model']}"
        cpu += f" stepping {info.get('stepping', '?')})"
    libs = {}
    for name in RECORDED_LIBRARIES:
        try:
            libs[name] = metadata.version(name)
        except metadata.PackageNotFoundError:
            continue
    return {
        "cpu": cpu or platform.processor(),
        "machine": platform.machine(),
        "python": platform.python_version(),
        "libraries": libs,
    }


def check_setting(setting: str | None) -> str:
    """The ``device`` value, lower-cased (``None`` → ``auto``), if it is ``auto``,
    ``cpu`` or ``cuda[:N]``; else ValueError. Imports no torch (a stage that computes
    on the CPU whatever the setting still refuses a misspelt one)."""
    s = (setting or "auto").lower()
    if s in ("auto", "cpu") or s.startswith("cuda"):
        return s
    raise ValueError(f"device must be auto, cpu or cuda, not {setting!r}")


def _resolve(setting: str | torch.device | None) -> torch.device:
    import torch

    if isinstance(setting, torch.device):
        return setting
    s = check_setting(setting)
    if s == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if s.startswith("cuda") and not torch.cuda.is_available():
        raise RuntimeError("device: cuda was asked for, but no CUDA device is available")
    return torch.device(s)
