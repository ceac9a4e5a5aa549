"""`surfphase bench stability`'s measures against hand-made changes."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from surfphase.bench.stability import add_noise, event_bubble_frames, track_changes


def _table(dx: float = 0.0, dv: float = 0.0) -> pd.DataFrame:
    rows = [{"frame": f, "bubble": b, "x": 1e-3 * b + dx, "y": 2e-3 + 1e-4 * f, "z": 0.0,
             "vx": dv, "vy": 0.2, "vz": 0.0} for f in range(10) for b in (0, 1, 2)]  # fmt: skip
    return pd.DataFrame(rows)


def test_changes_are_the_applied_shift_outside_events(tmp_path):
    """A merge of 1 and 2 into 3 at frame 5: bubbles 1 and 2 (3 is not in the table)
    lose frames 4-6; bubble 0 (the nucleation region) is never compared; a split of 7
    elsewhere leaves them alone."""
    (tmp_path / "events.csv").write_text(
        "frame,camera,event,parents,children\n5,cam0,merge,1+2,3\n5,cam1,merge,1+2,3\n"
        "2,cam0,split,7,8\n8,cam0,detach,0,1\n"
    )
    skip = event_bubble_frames(tmp_path / "events.csv", 1)
    assert {(f, b) for f, b in skip if b in (1, 2)} == {(f, b) for f in (4, 5, 6) for b in (1, 2)}
    assert {b for _, b in skip} == {1, 2, 3, 7, 8}  # the detach is no merge or split
    out = track_changes(_table(), _table(dx=20e-6, dv=0.003), skip)
    assert out["matched"] == 2 * 7 and out["unmatched_ref"] == 0  # ids 1, 2: 7 frames each
    assert out["centroid_mean_um"] == pytest.approx(20.0)
    assert out["velocity_worst_mps"] == pytest.approx(0.003)
    assert out["velocity_worst_pct_of_speed"] == pytest.approx(100 * 0.003 / 0.2)


def test_noise_has_the_asked_spread_and_stays_in_range():
    frames = np.full((4, 64, 64), 0.5, np.float32)
    noisy = add_noise(frames, 1e-4, seed=0)
    assert noisy.dtype == np.float32 and np.std(noisy - frames) == pytest.approx(1e-4, rel=0.05)
    assert add_noise(np.ones((1, 8, 8), np.float32), 1e-2, 0).max() <= 1.0
    # The ingest's native uint16 frames get the same spread of their range, as uint16.
    native = np.full((4, 64, 64), 30000, np.uint16)
    n16 = add_noise(native, 1e-4, seed=0)
    assert n16.dtype == np.uint16
    assert np.std(n16.astype(float) - 30000) / 65535 == pytest.approx(1e-4, rel=0.05)


def test_rows_match_on_position_when_the_runs_number_ids_apart():
    """The noisy run calls bubble 1 id 8, and its own merge event at frame 5 covers 8:
    those frames are left out, not counted as unmatched; elsewhere the pairs compare."""
    ref = _table()
    noisy = _table(dx=10e-6)
    noisy.loc[noisy["bubble"] == 1, "bubble"] = 8
    skip_noisy = {(f, 8) for f in (4, 5, 6)}
    out = track_changes(ref, noisy, set(), skip_noisy)
    assert out["unmatched_ref"] == 0
    assert out["matched"] == 10 + 7  # bubble 2 in every frame, bubble 1 outside 4-6
    assert out["centroid_worst_um"] == pytest.approx(10.0)
