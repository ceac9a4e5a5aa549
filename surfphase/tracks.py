"""Helpers of track smoothing shared by the fit's tables (:mod:`surfphase.fit.outputs`)
and the classical baseline (:mod:`surfphase.eval.baseline`)."""

from __future__ import annotations


def savgol_window(frames: float, order: int, n: int) -> int:
    """A Savitzky–Golay window of about ``frames`` samples for a polynomial of ``order``
    on a run of ``n`` samples: rounded, at least ``order + 2``, made odd, and capped at
    the longest odd number ≤ ``n``."""
    win = max(int(round(frames)), order + 2)
    win += 1 - win % 2
    return min(win, n if n % 2 else n - 1)
