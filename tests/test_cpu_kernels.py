"""`import surfphase` pins PyTorch's CPU kernels to AVX2 on x86-64 (surfphase/__init__.py):
the capability PyTorch reports in a fresh process, the switch that turns it off, a
user's export winning, and the numbers being those of an explicit AVX2 run."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import pytest

import surfphase

pytestmark = pytest.mark.skipif(
    not surfphase._has_avx2(), reason="the pin applies to x86-64 CPUs with AVX2 only"
)

PROBE = """
import json, sys
if sys.argv[1] == "surfphase":
    import surfphase  # noqa: F401  (before torch, as python -m surfphase does)
import torch
torch.manual_seed(0)
x = torch.randn(4099, dtype=torch.float32)
print(json.dumps({
    "capability": torch.backends.cpu.get_cpu_capability(),
    "exp_sum": float(torch.exp(x).sum()),
    "norm": float(torch.linalg.vector_norm(x * 1.7 + 0.3)),
}))
"""


def _probe(first: str, probe: str = PROBE, **env: str) -> dict:
    drop = ("ATEN_", "MKL_CBWR", "ONEDNN_", "OPENBLAS_", "SURFPHASE_CPU")
    base = {k: v for k, v in os.environ.items() if not k.startswith(drop)}
    out = subprocess.run(
        [sys.executable, "-c", probe, first],
        env={**base, **env},
        capture_output=True,
        text=True,
        check=True,
    )
    return json.loads(out.stdout)


def test_import_surfphase_pins_avx2_and_an_export_wins():
    pinned = _probe("surfphase")
    assert pinned["capability"] == "AVX2"
    native = _probe("torch")["capability"]  # torch alone: the machine's best
    assert _probe("surfphase", SURFPHASE_CPU_KERNELS="native")["capability"] == native
    assert _probe("surfphase", ATEN_CPU_CAPABILITY="default")["capability"] == "DEFAULT"
    # Pinned, the numbers are those of an explicit AVX2 run (another machine's), with the
    # same three exports surfphase/__init__.py sets (MKL's and oneDNN's too: one run of
    # the suite saw exp_sum differ in the 6th digit with ATEN_CPU_CAPABILITY alone).
    explicit = _probe(
        "torch", ATEN_CPU_CAPABILITY="avx2", MKL_CBWR="AVX2", ONEDNN_MAX_CPU_ISA="AVX2"
    )
    assert pinned == explicit


#: numpy's bundled OpenBLAS: the kernels it loaded (its own report) and a float64
#: product whose bits depend on them.
BLAS_PROBE = """
import ctypes, glob, json, os, sys
if sys.argv[1] == "surfphase":
    import surfphase  # noqa: F401
import numpy as np
libs = glob.glob(os.path.join(os.path.dirname(np.__file__), os.pardir, "numpy.libs", "*openblas*"))
core = ""
if libs:
    lib = ctypes.CDLL(libs[0])
    name = next((n for n in ("scipy_openblas_get_corename64_", "openblas_get_corename64_",
                             "openblas_get_corename") if hasattr(lib, n)), None)
    if name:
        fn = getattr(lib, name)
        fn.restype = ctypes.c_char_p
        core = fn().decode()
rng = np.random.default_rng(0)
a, b = rng.standard_normal((257, 263)), rng.standard_normal((263, 251))
print(json.dumps({"core": core, "product": (a @ b).tobytes().hex()[:4096],
                  "sum": float((a @ b).sum())}))
"""


def test_import_surfphase_pins_numpys_openblas_to_its_avx2_kernels():
    pinned = _probe("surfphase", BLAS_PROBE)
    if not pinned["core"]:
        pytest.skip("numpy here does not bundle an OpenBLAS that reports its kernels")
    assert pinned["core"] == "Haswell"
    # The same bits as an explicit export; the switch leaves OpenBLAS its own choice.
    assert pinned == _probe("numpy", BLAS_PROBE, OPENBLAS_CORETYPE="Haswell")
    own = _probe("numpy", BLAS_PROBE)
    assert _probe("surfphase", BLAS_PROBE, SURFPHASE_CPU_KERNELS="native") == own
