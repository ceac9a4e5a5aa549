"""Frame windows: a long session's meshes computed by several independent jobs.

Meshing is per-frame independent (unlike the fit and the mask association, which carry
state from frame to frame), so the frames of a session can be split into windows of
``size`` consecutive fitted frames, each meshed by its own job, then gathered.
"""

from __future__ import annotations

import math
from collections.abc import Sequence


def sheet_frame_count(spec: str | None) -> int | None:
    """Number of frames a sessions-sheet range ``start:stop[:step]`` selects.

    Returns None when the count depends on the video (no range, or no ``stop``). Raises
    ValueError for a malformed or empty range (as the ingest stage would).
    """
    if spec is None or str(spec).strip() == "":
        return None
    parts = str(spec).strip().split(":")
    if len(parts) not in (2, 3):
        raise ValueError(f"frame range {spec!r} is not start:stop[:step]")
    if parts[1] == "":
        return None
    try:
        start = int(parts[0]) if parts[0] else 0
        stop = int(parts[1])
        step = int(parts[2]) if len(parts) == 3 and parts[2] else 1
    except ValueError as e:
        raise ValueError(f"frame range {spec!r} is not start:stop[:step]") from e
    if start < 0 or stop < 0 or step <= 0:
        raise ValueError(f"frame range {spec!r}: need start, stop >= 0 and step > 0")
    n = len(range(start, stop, step))
    if n == 0:
        raise ValueError(f"frame range {spec!r} is empty")
    return n


def fitted_frame_count(n_ingested: int, fit_frames: int | None) -> int:
    """Frames in the fit's output: the ingested ones, or the first ``fit_frames``."""
    return n_ingested if fit_frames is None else min(int(fit_frames), n_ingested)


def window_count(n_frames: int, size: int) -> int:
    """Number of windows of ``size`` frames covering ``n_frames`` (at least one)."""
    if size <= 0:
        raise ValueError(f"mesh window size must be positive, got {size}")
    return max(1, math.ceil(n_frames / size))


def window_positions(positions: Sequence[int], index: int, size: int) -> list[int]:
    """The ``index``-th window (0-based) of ``size`` consecutive entries of ``positions``."""
    if size <= 0:
        raise ValueError(f"mesh window size must be positive, got {size}")
    if index < 0:
        raise ValueError(f"mesh window index must be >= 0, got {index}")
    return [int(t) for t in positions[index * size : (index + 1) * size]]
