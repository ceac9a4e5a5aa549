"""A bubble that does not move is a static feature of the scene: its speed and its
removal from the masks (surfphase.masks.anchors.track_speeds, stage.drop_static)."""

from __future__ import annotations

import numpy as np
import pandas as pd

from surfphase.masks import anchors
from surfphase.masks.stage import drop_static


def _track(bubble: int, frames: np.ndarray, x0: np.ndarray, v: np.ndarray, noise: float, seed=0):
    rng = np.random.default_rng(seed)
    t = frames / 1000.0
    X = x0[None] + t[:, None] * v[None] + rng.normal(0, noise, (len(frames), 3))
    return pd.DataFrame(
        {"frame": frames, "bubble": bubble, "x": X[:, 0], "y": X[:, 1], "z": X[:, 2]}
    )


def test_track_speeds_is_the_least_squares_slope():
    """Against numpy's polyfit per axis; too-short tracks and id 0 get no speed."""
    f = np.array([3, 4, 5, 7, 8, 9, 10])
    a = _track(2, f, np.array([1e-3, 2e-3, 0.0]), np.array([0.01, 0.2, -0.03]), 2e-6, seed=1)
    b = _track(5, f[:2], np.zeros(3), np.ones(3), 0.0)
    c = _track(0, f, np.zeros(3), np.ones(3), 0.0)
    speeds = anchors.track_speeds(pd.concat([a, b, c]), fps=1000.0)
    assert set(speeds) == {2}
    slope = [np.polyfit(f / 1000.0, a[k], 1)[0] for k in ("x", "y", "z")]
    assert abs(speeds[2] - np.linalg.norm(slope)) < 1e-12


def test_a_still_speck_is_dropped_and_a_rising_bubble_kept():
    """A speck still to 1 µm beside a bubble rising at 0.2 m/s: the speck leaves the
    labels of both views and the instance table, the bubble stays."""
    f = np.arange(6)
    speck = _track(3, f, np.array([3e-3, 5e-4, -1e-3]), np.zeros(3), 1e-6, seed=2)
    rise = _track(4, f, np.array([0.0, 2e-3, 0.0]), np.array([0.0, 0.2, 0.0]), 1e-6, seed=3)
    table = pd.concat([speck, rise]).assign(consistent=True)
    labels = {c: np.full((6, 8, 8), -1, np.int32) for c in ("cam0", "cam1")}
    for lab in labels.values():
        lab[:, 1:3, 1:3] = 3
        lab[:, 5:7, 5:7] = 4
    inst = pd.DataFrame({"frame": np.repeat(f, 2), "bubble": np.tile([3, 4], 6)})
    dropped = drop_static(labels, inst, table, fps=1000.0, min_speed_mps=0.005)
    assert dropped == [3]
    for lab in labels.values():
        assert not (lab == 3).any() and (lab == 4).sum() == 6 * 4
    assert (inst["bubble"] == -1).sum() == 6 and (inst["bubble"] == 4).sum() == 6
    # 0 keeps every bubble.
    assert drop_static(labels, inst, table, fps=1000.0, min_speed_mps=0.0) == []


def test_a_merged_bubble_both_views_saw_stays_where_its_views_disagree():
    """Bubble 8 is born of a merge both views record, 9 of one only one view records:
    where their centres disagree, 9 leaves the masks and 8 stays."""
    from surfphase.masks.stage import drop_inconsistent, merged_in_every_view

    events = pd.DataFrame(
        {
            "frame": [4, 4, 6],
            "camera": ["cam0", "cam1", "cam0"],
            "event": ["merge", "merge", "merge"],
            "parents": ["2+3", "3+2", "5+6"],
            "children": ["8", "8", "9"],
        }
    )
    keep = merged_in_every_view(events, ["cam0", "cam1"])
    assert keep == {8}
    labels = {c: np.full((2, 6, 6), -1, np.int32) for c in ("cam0", "cam1")}
    for lab in labels.values():
        lab[:, :2, :2] = 8
        lab[:, 4:, 4:] = 9
    table = pd.DataFrame({"position": [0, 0], "bubble": [8, 9], "consistent": [False, False]})
    inst = pd.DataFrame({"frame": [0, 0], "bubble": [8, 9]})
    assert drop_inconsistent(labels, inst, table, keep) == 1
    for lab in labels.values():
        assert (lab[0] == 8).sum() == 4 and not (lab[0] == 9).any() and (lab[1] == 9).sum() == 4
