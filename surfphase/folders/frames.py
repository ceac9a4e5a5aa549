"""Stored frames ↔ float grey levels in [0, 1]: the one conversion every reader uses.

A stage folder stores frames either as floats already in [0, 1] (the ingest stacks,
``float32``) or as unsigned integers of a declared bit depth (the native stacks, the
orbit views and the refined views: ``uint16``, grey level × 65535; 8-bit sources:
``uint8`` × 255). The scale comes from that declaration — the stored dtype, or the bit
depth a source names (a 12-bit camera in 16-bit words) — never from the values.
"""

from __future__ import annotations

import numpy as np

#: The unsigned integer dtypes a folder may store frames in, and their bit depths.
INTEGER_BITS = {np.dtype(np.uint8): 8, np.dtype(np.uint16): 16}


def check_frame_dtype(dtype: np.dtype, where: str) -> None:
    """Raise ValueError naming ``where`` unless ``dtype`` is one frames are stored in
    (a float, uint8 or uint16)."""
    dtype = np.dtype(dtype)
    if dtype not in INTEGER_BITS and not np.issubdtype(dtype, np.floating):
        raise ValueError(
            f"{where}: frames stored as {dtype}, expected float32 in [0, 1], uint8 or uint16"
        )


def unit_float(stored: np.ndarray, bit_depth: int | None = None) -> np.ndarray:
    """Stored frames (any shape) → float32 grey levels in [0, 1].

    Args:
        stored: floats (clipped to [0, 1]) or uint8/uint16 integers.
        bit_depth: for integers, the declared bit depth of the values (a 12-bit source
            in uint16 words: 12); default the dtype's own (8 or 16). Integers are divided
            by ``2**bit_depth − 1`` in float32.

    Raises:
        ValueError: another dtype, or a bit depth beyond the dtype's.
    """
    a = np.asarray(stored)
    if a.dtype in INTEGER_BITS:
        bits = INTEGER_BITS[a.dtype] if bit_depth is None else int(bit_depth)
        if not 1 <= bits <= INTEGER_BITS[a.dtype]:
            raise ValueError(f"bit depth {bit_depth} does not fit frames stored as {a.dtype}")
        return a.astype(np.float32) / np.float32(2**bits - 1)
    if not np.issubdtype(a.dtype, np.floating):
        raise ValueError(f"frames stored as {a.dtype}: expected floats, uint8 or uint16")
    return np.clip(a.astype(np.float32), 0.0, 1.0)


def to_uint16(frames: np.ndarray) -> np.ndarray:
    """[0, 1] floats → uint16 (value·65535, rounded; the lossless view format)."""
    return np.round(np.clip(frames, 0.0, 1.0) * 65535.0).astype(np.uint16)


def unit_grey(frame: np.ndarray) -> np.ndarray:
    """One stored frame (H, W) or (H, W, C) → (H, W) float32 grey in [0, 1]
    (:func:`unit_float`, colour channels averaged)."""
    out = unit_float(frame)
    if out.ndim == 3:
        out = out.mean(axis=2)
    if out.ndim != 2:
        raise ValueError(f"expected a (H, W) or (H, W, C) frame, got shape {np.shape(frame)}")
    return out
