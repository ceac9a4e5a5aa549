"""Calibration outputs: ``cameras.json``, ``report.json`` and a picture of the corners."""

from __future__ import annotations

import colorsys
from pathlib import Path

import cv2
import numpy as np

from surfphase.calib.solve import Calibration
from surfphase.cameras import save_cameras
from surfphase.io import atomic_path, atomic_write_json


def corners_picture(cal: Calibration, error_gain: float = 50.0) -> np.ndarray:
    """(H, W·n_cams, 3) BGR picture: per camera, its reference image with every corner used.

    Corners of each image get their own colour (so coverage of the field is visible);
    a line from each corner shows its reprojection error magnified ``error_gain`` times.
    Corners found but not used (rejected views) are drawn as grey crosses.
    """
    panels = []
    reference = cal.report["reference_image"]
    for name, source in cal.sources.items():
        view = reference if reference in source.frame_of else source.names[0]
        gray = source.read(view)
        panel = cv2.cvtColor((gray * 0.5 + 64).astype(np.uint8), cv2.COLOR_GRAY2BGR)
        used = cal.residuals.get(name, {})
        images = sorted(cal.detections.get(name, {}))
        for k, image in enumerate(images):
            det = cal.detections[name][image]
            if image not in used:
                for u, v in det.image_points:
                    p = (int(round(u)), int(round(v)))
                    cv2.drawMarker(panel, p, (160, 160, 160), cv2.MARKER_TILTED_CROSS, 7, 1)
                continue
            r, g, b = colorsys.hsv_to_rgb(k / max(len(images), 1), 0.9, 1.0)
            colour = (int(b * 255), int(g * 255), int(r * 255))
            for (u, v), (du, dv) in zip(det.image_points, used[image], strict=True):
                p = (int(round(u)), int(round(v)))
                q = (int(round(u + error_gain * du)), int(round(v + error_gain * dv)))
                cv2.circle(panel, p, 3, colour, 1, cv2.LINE_AA)
                cv2.line(panel, p, q, colour, 1, cv2.LINE_AA)
        info = cal.report["cameras"][name]
        text = f"{name}: {info['images_used']} images, RMS {info['rms_px']:.3f} px"
        cv2.putText(panel, text, (6, 18), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (255, 255, 255), 1)
        cv2.putText(
            panel,
            f"errors x{error_gain:g}",
            (6, 36),
            cv2.FONT_HERSHEY_SIMPLEX,
            0.45,
            (255, 255, 255),
            1,
        )
        panels.append(panel)
    height = max(p.shape[0] for p in panels)
    panels = [
        cv2.copyMakeBorder(p, 0, height - p.shape[0], 0, 4, cv2.BORDER_CONSTANT) for p in panels
    ]
    return np.hstack(panels)


def write_calibration(out_dir: str | Path, cal: Calibration) -> None:
    """Write ``out_dir/cameras.json``, ``out_dir/report.json`` and ``out_dir/corners.png``.

    Each file is written whole or not at all.
    """
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    picture = corners_picture(cal)
    with atomic_path(out_dir / "corners.png") as tmp:
        if not cv2.imwrite(str(tmp), picture):
            raise OSError(f"could not write {out_dir / 'corners.png'}")
    atomic_write_json(out_dir / "report.json", cal.report)
    meta = {"rig": cal.report["rig"]} if cal.report.get("rig") else {}
    save_cameras(out_dir / "cameras.json", cal.cameras, **meta)
