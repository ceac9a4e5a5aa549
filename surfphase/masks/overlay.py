"""Overlay pictures of bubble masks on frames, for the report."""

from __future__ import annotations

import os

import cv2
import numpy as np

from surfphase.io import atomic_path

#: Colour of the nucleation region (bubble 0), RGB.
NUCLEATION_RGB = (255, 140, 0)


def bubble_colour(bubble: int) -> tuple[int, int, int]:
    """A stable, distinct RGB colour for a bubble id (golden-angle hues)."""
    if bubble == 0:
        return NUCLEATION_RGB
    hue = (bubble * 0.618033988749895) % 1.0
    hsv = np.uint8([[[int(hue * 179), 200, 255]]])
    r, g, b = cv2.cvtColor(hsv, cv2.COLOR_HSV2RGB)[0, 0]
    return int(r), int(g), int(b)


def overlay_frame(
    image: np.ndarray, labels: np.ndarray, alpha: float = 0.35, min_size: int = 256
) -> np.ndarray:
    """Colour each bubble of a frame, outline it and write its id.

    Args:
        image: (H, W) grey frame in [0, 1].
        labels: (H, W) int bubble ids, −1 background.
        alpha: opacity of the fill.
        min_size: small frames are enlarged (nearest neighbour) to at least this side.

    Returns:
        (H', W', 3) uint8 RGB picture.
    """
    scale = max(1, int(np.ceil(min_size / max(1, min(image.shape)))))
    img = np.repeat(np.repeat(np.clip(image, 0, 1), scale, 0), scale, 1)
    lab = np.repeat(np.repeat(labels, scale, 0), scale, 1)
    rgb = np.repeat((img * 255).astype(np.uint8)[..., None], 3, axis=2)
    out = rgb.astype(np.float32)
    for b in np.unique(lab[lab >= 0]):
        m = lab == b
        col = np.array(bubble_colour(int(b)), np.float32)
        out[m] = (1 - alpha) * out[m] + alpha * col
    out = out.astype(np.uint8)
    for b in np.unique(lab[lab >= 0]):
        m = (lab == b).astype(np.uint8)
        contours, _ = cv2.findContours(m, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
        col = bubble_colour(int(b))
        cv2.drawContours(out, contours, -1, col, 1)
        ys, xs = np.nonzero(m)
        cv2.putText(
            out,
            str(int(b)),
            (int(xs.mean()) - 4, int(ys.mean()) + 4),
            cv2.FONT_HERSHEY_SIMPLEX,
            0.4,
            (255, 255, 255),
            1,
            cv2.LINE_AA,
        )
    return out


def save_png(path: str | os.PathLike, rgb: np.ndarray) -> None:
    """Write an (H, W, 3) uint8 RGB picture as PNG, whole or not at all."""
    ok, buf = cv2.imencode(".png", cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
    if not ok:
        raise ValueError(f"{path}: PNG encoding failed")
    with atomic_path(path) as tmp:
        tmp.write_bytes(buf.tobytes())
