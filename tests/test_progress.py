"""Progress lines: elapsed time and ETA against hand-computed values, and the long
stages (fit, mesh, prior training, refinement) print them."""

from __future__ import annotations

import numpy as np

from surfphase.prior.sdedit import refine_in_chunks
from surfphase.progress import Progress, format_seconds


def test_eta_is_the_recent_mean_times_what_is_left():
    now = [0.0]
    lines: list[str] = []
    p = Progress(10, "fit s1: frame", log=lines.append, clock=lambda: now[0])
    now[0] = 60.0  # frame 0: 60 s (densification)
    p.step()
    assert lines[-1] == "fit s1: frame 1/10, elapsed 1m00s, ETA 9m00s"
    for _ in range(5):  # then 6 s a frame: the first frame drops out of the window
        now[0] += 6.0
        p.step("x")
    assert p.eta() == 6.0 * 4
    assert lines[-1] == "fit s1: frame 6/10, x, elapsed 1m30s, ETA 24s"
    now[0] += 24.0
    p.step(n=4)
    assert lines[-1] == "fit s1: frame 10/10, elapsed 1m54s"  # no ETA when done
    assert format_seconds(7322) == "2h02m"


def test_refinement_reports_each_window(capsys):
    video = np.zeros((10, 4, 4), np.float32)
    out = refine_in_chunks(video, 4, 1, lambda w, k: w + 1)
    assert np.allclose(out, 1)
    lines = [ln for ln in capsys.readouterr().out.splitlines() if ln.startswith("refine")]
    assert len(lines) >= 3 and lines[0].startswith("refine: window 1/")
    assert "ETA" in lines[0] and "ETA" not in lines[-1]
