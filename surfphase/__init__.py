"""SurfPhase: 3D bubble interfaces and metric velocities from synchronized high-speed videos.

Importing the package sets two threading defaults, before PyTorch or numba start their
thread pools (``os.environ.setdefault``: a value the user exported wins):

* ``OMP_WAIT_POLICY=PASSIVE``: PyTorch's OpenMP workers sleep between parallel regions
  instead of spinning. Spinning workers make a shared CPU (a lab workstation, a cluster
  node, numba's own workers) many times slower — a fit beside one CPU-bound process
  took 20× longer with two spinning threads. The thread count is not changed, so
  results stay bit-for-bit what they are for that count.
* ``NUMBA_THREADING_LAYER=workqueue``: the fused rasterizer's kernels
  (:mod:`surfphase.render.fused`) run on numba's workqueue pool, whose idle workers
  wait on a condition variable (never spin) and which loads no second OpenMP runtime
  beside PyTorch's. It does not allow nested parallel kernels or concurrent calls from
  several Python threads; surfphase makes neither.

On an x86-64 CPU with AVX2 it also pins the instruction set of PyTorch's and numpy's
CPU arithmetic, so that a fit gives the same bits on any such machine (a workstation,
the nodes of a mixed cluster), not only on the one that ran it:

* ``ATEN_CPU_CAPABILITY=avx2``: PyTorch's own kernels (element-wise maths, reductions)
  take their AVX2 build, not the AVX-512 one a newer CPU would pick. The two round
  differently: a 4-frame stage-1 fit run both ways on one machine differs in every
  surfel parameter, and its held-out PSNR by 0.03–0.06 dB (BENCHMARKS.md, determinism).
* ``MKL_CBWR=AVX2``: Intel MKL's conditional numerical reproducibility (its matrix
  products take the AVX2 code path on every CPU that has it); likewise a different fit
  from the default on an AVX-512 machine.
* ``ONEDNN_MAX_CPU_ISA=AVX2``: oneDNN (PyTorch's CPU convolutions: the embedded prior)
  generates no code beyond AVX2.
* ``OPENBLAS_CORETYPE=Haswell``: the OpenBLAS that numpy and scipy bundle takes its
  AVX2 kernels, not the ones it picks for the CPU (``SkylakeX`` on an AVX-512 Xeon;
  on AMD's Zen it takes the Haswell ones by itself), which sum products in another order: on one AVX-512 machine the
  mask stage's ``reproj_px`` of a benchmark session moved by 3e-13 px and the fit's
  scene extent by 6e-18 m between the two (BENCHMARKS.md, determinism).

The masks, centres, velocities and meshes do not depend on the first three (numpy and
OpenCV give the same bits with their AVX-512 paths disabled); OpenBLAS's kernels move
them in the last bits only. ``SURFPHASE_CPU_KERNELS=native`` exported before the run
leaves the four unset (each library then picks the machine's widest paths); a value of
one of them exported before the run wins.

All of these only take effect when ``surfphase`` is imported before ``torch``,
``numpy`` and ``numba`` (``python -m surfphase`` and the workflow's rules always do);
the fit records the kernels it ran and the platform (``summary.json``:
``cpu_capability``, ``platform``: the CPU model and the libraries' versions).
"""

import os


def _has_avx2() -> bool:
    """Whether this is an x86-64 Linux CPU with AVX2 (``/proc/cpuinfo``'s flags)."""
    try:
        with open("/proc/cpuinfo") as fh:
            return any(line.startswith("flags") and "avx2" in line.split() for line in fh)
    except OSError:
        return False


os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
os.environ.setdefault("NUMBA_THREADING_LAYER", "workqueue")
if os.environ.get("SURFPHASE_CPU_KERNELS", "avx2") != "native" and _has_avx2():
    os.environ.setdefault("ATEN_CPU_CAPABILITY", "avx2")
    os.environ.setdefault("MKL_CBWR", "AVX2")
    os.environ.setdefault("ONEDNN_MAX_CPU_ISA", "AVX2")
    os.environ.setdefault("OPENBLAS_CORETYPE", "Haswell")

__version__ = "0.1.0"
