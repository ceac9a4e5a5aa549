"""Helpers of track smoothing shared by the fit's tables (:mod:`surfphase.fit.outputs`)
and the classical baseline (:mod:`surfphase.eval.baseline`)."""

from __future__ import annotations

import numpy as np


def savgol_window(frames: float, order: int, n: int) -> int:
    """A Savitzky–Golay window of about ``frames`` samples for a polynomial of ``order``
    on a run of ``n`` samples: rounded, at least ``order + 2``, made odd, and capped at
    the longest odd number ≤ ``n``."""
    win = max(int(round(frames)), order + 2)
    win += 1 - win % 2
    return min(win, n if n % 2 else n - 1)


def moving_polynomial(
    values: np.ndarray, window: int, order: int, weights: np.ndarray | None = None
) -> np.ndarray:
    """(n, D) values smoothed by a moving polynomial of ``order`` over ``window`` samples
    (odd, ``order`` < ``window`` ≤ n), as ``scipy.signal.savgol_filter(values, window,
    order, axis=0, mode="interp")``: each sample is the value there of the polynomial
    fitted to the ``window`` samples centred on it, and the first / last ``window // 2``
    samples take the polynomial of the first / last window.

    With (n,) ``weights`` (> 0) each fit is weighted least squares instead: a sample of
    weight w counts as 1/w times as noisy (variance). Equal weights give the
    Savitzky–Golay result to rounding; without ``weights`` ``savgol_filter`` itself is
    used."""
    from scipy.signal import savgol_filter

    p = np.asarray(values, dtype=np.float64)
    if weights is None:
        return savgol_filter(p, window_length=window, polyorder=order, axis=0, mode="interp")
    n, h = len(p), window // 2
    sw = np.sqrt(np.asarray(weights, dtype=np.float64))
    out = np.empty_like(p)
    k = np.arange(window, dtype=np.float64)
    for i in range(n):
        lo = min(max(i - h, 0), n - window)
        # Powers of the offset from sample i: the fit's constant term is its value at i.
        X = np.vander(k + (lo - i), order + 1, increasing=True) * sw[lo : lo + window, None]
        y = p[lo : lo + window].reshape(window, -1) * sw[lo : lo + window, None]
        out[i] = np.linalg.lstsq(X, y, rcond=None)[0][0].reshape(p.shape[1:])
    return out
