"""Rendered surfels composited over a background: ``I = C + (1 − α)·B``.

``C`` is the renderer's premultiplied colour (Σ w·colour), ``α`` its accumulated opacity
and ``B`` the image behind the surfels. The one implementation of this formula serves
the rasterizer's ``backgrounds`` argument, the fit's per-view background images, the
per-bubble registration and the orbit views.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, TypeVar

if TYPE_CHECKING:
    import numpy as np
    import torch

Image = TypeVar("Image", "np.ndarray", "torch.Tensor")


def over_background(colors: Image, alpha: Image, background: Image) -> Image:
    """``colors + (1 − alpha)·background``, evaluated in that order.

    Args:
        colors: premultiplied colour, e.g. (C, H, W, D), in image units ([0, 1]).
        alpha: accumulated opacity in [0, 1], broadcastable against ``colors``, e.g.
            (C, H, W, 1) beside (C, H, W, D) colours or (C, H, W) beside grey ones.
        background: the image behind, broadcastable likewise: (C, H, W, D),
            (C, 1, 1, D) or (H, W).

    Returns:
        The composited image, the broadcast shape of the three (numpy arrays or torch
        tensors alike: the same three operations, so the same bits as the formula
        written out; autograd flows through all three inputs).
    """
    return colors + (1 - alpha) * background
