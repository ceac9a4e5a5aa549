"""A contact sheet of a synthetic session: a few frames from each camera, tiled."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from surfphase.synth.monoclips import write_png


def contact_sheet(
    campaign: Path,
    session: str = "session01",
    frames: tuple[int, ...] = (0, 8, 16, 23),
    cameras: tuple[str, ...] = ("cam0", "cam1", "mid", "orbit03", "orbit06", "orbit09"),
    tile: int = 256,
) -> np.ndarray:
    """(rows·tile, cols·tile) uint8 sheet: one row per camera, one column per frame.

    Input cameras come from ``<session>/<cam>/``, the others from
    ``<session>/gt/views/<cam>/``; every frame is resized to ``tile`` pixels
    (area-averaged down, nearest-neighbour up) and labelled ``camera f<frame>``.
    """
    campaign = Path(campaign)
    rows = []
    for cam in cameras:
        folder = campaign / session / cam
        if not folder.is_dir():
            folder = campaign / session / "gt" / "views" / cam
        row = []
        for f in frames:
            path = folder / f"{f:06d}.png"
            img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
            if img is None:
                raise FileNotFoundError(f"{path}: no such frame (session {session})")
            if img.dtype == np.uint16:
                img = (img >> 8).astype(np.uint8)
            interp = cv2.INTER_AREA if img.shape[0] > tile else cv2.INTER_NEAREST
            img = cv2.resize(img, (tile, tile), interpolation=interp)
            cv2.putText(
                img, f"{cam} f{f}", (6, 18), cv2.FONT_HERSHEY_SIMPLEX, 0.5, 255, 1, cv2.LINE_AA
            )
            row.append(np.pad(img, 1, constant_values=0))
        rows.append(np.hstack(row))
    return np.vstack(rows)


def write_contact_sheet(campaign: Path, out: Path, **kwargs) -> None:
    """Write :func:`contact_sheet` of ``campaign`` as a PNG at ``out``."""
    write_png(Path(out), contact_sheet(campaign, **kwargs))
