"""The heated plate is found at any resolution: on a bench-preset session whose plate
is seen level (a grey front face over a black top, filling the bottom third), the
static structure of the native frames and of the frames downscaled for the fit agree,
and no bubble instance is the plate."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from surfphase.masks import classical
from surfphase.synth.campaign import write_campaign
from surfphase.video import open_video


@pytest.fixture(scope="module")
def plate_session(tmp_path_factory):
    root = tmp_path_factory.mktemp("bench3")
    # 24 frames: with 3 the reference happens to keep the plate findable.
    write_campaign(root, preset="bench", seed=0, sessions=3, frames=24)
    src = open_video(root / "session03" / "cam0.cih")
    full = float(2**src.bit_depth - 1)
    return np.stack([f.astype(np.float32) / full for f in src.read(np.arange(src.count))])


def test_plate_found_at_native_and_fit_resolution(plate_session):
    native = plate_session
    t, h, w = native.shape
    half = np.stack([cv2.resize(f, (w // 2, h // 2), interpolation=cv2.INTER_AREA) for f in native])
    fracs = []
    for stack in (native, half):
        bg, static = classical.session_background(stack)
        fracs.append(static.mean())
        labels, _ = classical.segment_frame(stack[0], None, (bg, static))
        ids, counts = np.unique(labels[labels >= 0], return_counts=True)
        # The biggest instance is a bubble (under 2 % of the frame), not the plate.
        assert counts.max() < 0.02 * labels.size, dict(zip(ids, counts, strict=True))
    # The plate fills about the bottom third in both, whatever the resolution.
    assert 0.2 < fracs[0] < 0.45 and abs(fracs[0] - fracs[1]) < 0.03, fracs
