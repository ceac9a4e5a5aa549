"""The fit benchmark's bubble matching and velocity error, by hand."""

from __future__ import annotations

import numpy as np
import pandas as pd

from surfphase.bench.fit import match_bubbles, velocity_error


def test_match_bubbles_hungarian_with_gate_and_error():
    cols = ["frame", "bubble", "x", "y", "z", "vx", "vy", "vz"]
    gt = pd.DataFrame(
        [
            [0, 10, 0.0, 0.0, 0, 0, 0.2, 0],
            [0, 11, 0.003, 0.0, 0, 0, 0.4, 0],
            [1, 10, 0.0, 0.001, 0, 0, 0.2, 0],
        ],
        columns=cols,
    )
    pred = pd.DataFrame(
        # Predicted ids 2 and 1 swapped in order; id 3 is too far from anything.
        [
            [0, 2, 0.0029, 0.0, 0, 0, 0.3, 0],
            [0, 1, 0.0002, 0.0, 0, 0, 0.25, 0],
            [0, 3, 0.02, 0.0, 0, 0, 1.0, 0],
            [1, 1, 0.0, 0.001, 0, 0.05, 0.2, 0],
        ],
        columns=cols,
    )
    m = match_bubbles(pred, gt, max_dist=0.001)
    assert sorted(zip(m.frame, m.bubble, m.gt_bubble, strict=True)) == [
        (0, 1, 10),
        (0, 2, 11),
        (1, 1, 10),
    ]
    # |dv| = 0.05, 0.1, 0.05 → mean 0.2/3; mean |v_gt| = (0.2 + 0.4 + 0.2)/3.
    assert np.isclose(velocity_error(m), (0.2 / 3) / (0.8 / 3))
