"""The one device setting (surfphase.device)."""

from __future__ import annotations

import subprocess
import sys

import pytest


def test_cpu_turns_on_torchs_deterministic_kernels_without_importing_inductor():
    """In a fresh process: after ``resolve_device("cpu")`` torch reports deterministic
    algorithms on (warn only), as ``torch.use_deterministic_algorithms(True,
    warn_only=True)`` would, and torch.compile's inductor was not imported for it."""
    code = (
        "import sys, torch\n"
        "from surfphase.device import resolve_device\n"
        "assert not torch.are_deterministic_algorithms_enabled()\n"
        "print(resolve_device('cpu'))\n"
        "print(torch.are_deterministic_algorithms_enabled(),"
        " torch.is_deterministic_algorithms_warn_only_enabled(),"
        " 'torch._inductor' in sys.modules)\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert out.returncode == 0, out.stderr
    assert out.stdout.split() == ["cpu", "True", "True", "False"]


def test_cuda_without_a_device_is_an_error():
    import torch

    from surfphase.device import resolve_device

    if torch.cuda.is_available():
        pytest.skip("a CUDA device is present")
    with pytest.raises(RuntimeError, match="no CUDA device"):
        resolve_device("cuda")
    with pytest.raises(ValueError, match="auto, cpu or cuda"):
        resolve_device("tpu")
