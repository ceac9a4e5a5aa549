"""The report stage: velocity series and plots, mask overlays, the campaign page.

The inputs are small tables built here with known tracks (true ids deliberately
different from the fit's), so the expected pairing and series are known by construction.
"""

from __future__ import annotations

import base64
import json
import re

import numpy as np
import pandas as pd
import pytest

from surfphase.cli import main
from surfphase.report.plots import (
    campaign_page,
    copy_overlays,
    pair_truth,
    session_metrics_table,
    velocity_plots,
    velocity_series,
)

FPS = 1000.0


def track(bubble: int, frames, x0: float, v: tuple[float, float, float]) -> pd.DataFrame:
    """A bubble moving at constant velocity ``v`` (m/s) from ``(x0, 0, 0)`` at frame 0."""
    f = np.asarray(list(frames))
    t = f / FPS
    return pd.DataFrame(
        {
            "frame": f,
            "time_s": t,
            "bubble": bubble,
            "x": x0 + v[0] * t,
            "y": v[1] * t,
            "z": v[2] * t,
            "vx": v[0],
            "vy": v[1],
            "vz": v[2],
        }
    )


@pytest.fixture
def tables():
    """Fit bubbles 0 (nucleation), 1, 2; truth ids 7 and 9 under 1 and 2 (+ a decoy 5)."""
    fit = pd.concat(
        [
            track(0, range(10), 0.0, (0.0, 0.01, 0.0)),
            track(1, range(10), -2e-3, (0.01, 0.30, 0.0)),
            track(2, range(3, 10), 2e-3, (-0.02, 0.25, 0.0)),
        ]
    )
    gt = pd.concat(
        [
            track(9, range(12), -2e-3 + 1e-4, (0.0, 0.28, 0.0)),
            track(7, range(12), 2e-3 - 1e-4, (-0.01, 0.26, 0.0)),
            # seen at one frame only, on top of bubble 2: must not be paired with it
            track(5, [5], 2e-3, (-0.02, 0.25, 0.0)),
            # far from everything
            track(3, range(12), 20e-3, (0.0, 0.3, 0.0)),
        ]
    )
    baseline = pd.concat(
        [
            track(1, range(1, 9), -2e-3, (0.02, 0.31, 0.0)),
            track(4, range(10), 5e-3, (0.0, 0.2, 0.0)),
        ]
    )
    return fit, baseline, gt


def test_pair_truth_by_mean_distance(tables):
    fit, _, gt = tables
    assert pair_truth(fit[fit["bubble"] != 0], gt) == {1: 9, 2: 7}
    # a tighter gate than the 0.1 mm offset of the truth pairs nothing
    assert pair_truth(fit, gt, max_dist=5e-5) == {}


def test_velocity_series(tables):
    fit, baseline, gt = tables
    s = velocity_series(fit, baseline, gt, FPS)
    assert sorted(s) == [1, 2]  # nucleation region left out
    assert sorted(s[1]) == ["baseline", "method", "truth"]
    assert sorted(s[2]) == ["method", "truth"]  # baseline bubble 4 is no fit bubble
    np.testing.assert_allclose(s[2]["method"]["t_s"], np.arange(3, 10) / FPS)
    np.testing.assert_allclose(s[1]["baseline"]["vx"], 0.02)
    # truth on the fit's frames only, with the true bubble's velocity
    np.testing.assert_allclose(s[2]["truth"]["t_s"], np.arange(3, 10) / FPS)
    np.testing.assert_allclose(s[2]["truth"]["vx"], -0.01)
    np.testing.assert_allclose(s[1]["truth"]["vy"], 0.28)
    assert 0 in velocity_series(fit, None, None, FPS, include_nucleation=True)
    with pytest.raises(ValueError, match="fps"):
        velocity_series(fit, None, None, 0.0)


def test_velocity_plots_png(tables, tmp_path):
    import matplotlib.image as mpimg

    fit, baseline, gt = tables
    paths = {}
    for name, df in (("fit", fit), ("baseline", baseline), ("gt", gt)):
        paths[name] = tmp_path / f"{name}.csv"
        df.to_csv(paths[name], index=False)
    out = tmp_path / "out" / "velocity.png"
    shown = velocity_plots(paths["fit"], paths["baseline"], paths["gt"], FPS, out, "s1")
    assert sorted(shown) == [1, 2]
    img = mpimg.imread(out)
    assert img.shape[0] > 300 and img.shape[1] == 900  # 9 in at 100 dpi
    assert img[..., :3].std() > 0.05  # something was drawn
    # one bubble only
    velocity_plots(paths["fit"], None, None, FPS, out, max_bubbles=1)
    assert mpimg.imread(out).shape[0] < img.shape[0]
    with pytest.raises(FileNotFoundError, match="missing.csv"):
        velocity_plots(tmp_path / "missing.csv", None, None, FPS, out)
    fit.drop(columns="vy").to_csv(paths["fit"], index=False)
    with pytest.raises(ValueError, match="vy"):
        velocity_plots(paths["fit"], None, None, FPS, out)


def test_copy_overlays(tmp_path):
    src = tmp_path / "masks" / "overlays"
    src.mkdir(parents=True)
    for i in range(10):
        (src / f"frame_{i:05d}.png").write_bytes(bytes([i]))
    out = tmp_path / "report"
    out.mkdir()
    (out / "stale.png").write_bytes(b"x")
    copies = copy_overlays(tmp_path / "masks", out, max_count=4)
    assert [p.name for p in copies] == [f"frame_{i:05d}.png" for i in (0, 3, 6, 9)]
    assert sorted(p.name for p in out.glob("*.png")) == [p.name for p in copies]
    assert (out / "frame_00006.png").read_bytes() == bytes([6])
    with pytest.raises(FileNotFoundError, match="overlays"):
        copy_overlays(tmp_path / "nowhere", out)


def test_session_metrics_table():
    m = {"session": "s1", "fps": 1500.0, "cameras": ["cam0", "cam1"]}
    m["velocity"] = {"method": {"relative_error": 0.15, "matched": 56}}
    m["chamfer_mm"] = {"mean_mm": 0.2, "per_frame": {"0": {"mean_mm": 0.2}}}
    t = session_metrics_table(m)
    assert dict(zip(t["metric"], t["value"], strict=True)) == {
        "session": "s1",
        "fps": 1500.0,
        "velocity.method.relative_error": 0.15,
        "velocity.method.matched": 56,
        "chamfer_mm.mean_mm": 0.2,
    }


def test_campaign_page(tmp_path):
    csv = tmp_path / "metrics.csv"
    pd.DataFrame(
        {
            "session": ["s1", "s2"],
            "velocity.method.relative_error": [0.148, 0.169],
            "heldout.mean.psnr": [18.06, np.nan],
            "extra.metric": [1.0, 2.0],
        }
    ).to_csv(csv, index=False)
    png = tmp_path / "velocity.png"
    png.write_bytes(b"\x89PNG\r\n\x1a\nfake-bytes")
    out = tmp_path / "campaign" / "index.html"
    summary = campaign_page(csv, out, {"s1": [png]}, {"s2": [png]})
    assert list(summary.columns) == ["session", "velocity rel. error (method)", "held-out PSNR dB"]
    page = out.read_text()
    assert "0.148" in page and "18.06" in page and "extra.metric" in page
    assert '<h2 id="s1">' in page and '<h2 id="s2">' in page
    datas = re.findall(r'src="data:image/png;base64,([^"]+)"', page)
    assert [base64.b64decode(d) for d in datas] == [png.read_bytes()] * 2
    with pytest.raises(ValueError, match="s3"):
        campaign_page(csv, out, {"s3": [png]})
    with pytest.raises(FileNotFoundError, match="nope.png"):
        campaign_page(csv, out, {"s1": [tmp_path / "nope.png"]})
    with pytest.raises(FileNotFoundError, match="absent.csv"):
        campaign_page(tmp_path / "absent.csv", out)
    grid = tmp_path / "samples.png"
    grid.write_bytes(b"\x89PNG\r\n\x1a\nprior-grid")
    campaign_page(csv, out, prior_samples=grid)
    page = out.read_text()
    assert "Video prior" in page
    datas = re.findall(r'src="data:image/png;base64,([^"]+)"', page)
    assert [base64.b64decode(d) for d in datas] == [grid.read_bytes()]
    with pytest.raises(FileNotFoundError, match="prior sample grid"):
        campaign_page(csv, out, prior_samples=tmp_path / "none.png")


def test_commands(tables, tmp_path, capsys):
    fit, baseline, gt = tables
    for sub, df, name in (
        ("fit", fit, "bubbles.csv"),
        ("evaluate", baseline, "baseline_bubbles.csv"),
        ("gt", gt, "bubbles.csv"),
    ):
        (tmp_path / sub).mkdir()
        df.to_csv(tmp_path / sub / name, index=False)
    metrics = {"session": "s1", "fps": FPS, "velocity": {"method": {"relative_error": 0.1}}}
    (tmp_path / "evaluate" / "metrics.json").write_text(json.dumps(metrics))
    overlays = tmp_path / "masks" / "overlays"
    overlays.mkdir(parents=True)
    for i in range(3):
        (overlays / f"f{i}.png").write_bytes(b"\x89PNG" + bytes([i]))
    rep = tmp_path / "report"
    argv = ["plots", "--session", "s1", "--fit", str(tmp_path / "fit")]
    argv += ["--evaluate", str(tmp_path / "evaluate"), "--gt", str(tmp_path / "gt")]
    argv += ["--masks", str(tmp_path / "masks"), "--out", str(rep)]
    assert main(argv) == 0
    assert "2 bubbles (2 paired with the truth)" in capsys.readouterr().out
    assert (rep / "velocity.png").stat().st_size > 1000
    page = (rep / "metrics.html").read_text()
    assert "velocity.method.relative_error" in page
    assert "the fits compared" in page and "method (final fit)" in page
    assert len(list((rep / "masks").glob("*.png"))) == 3

    pd.DataFrame([{"session": "s1", "velocity.method.relative_error": 0.1}]).to_csv(
        tmp_path / "campaign.csv", index=False
    )
    page = tmp_path / "index.html"
    argv = ["campaign-page", "--metrics", str(tmp_path / "campaign.csv"), "--out", str(page)]
    assert main(argv + ["--session-report", f"s1={rep}"]) == 0
    assert page.read_text().count("data:image/png;base64,") == 4  # velocity + 3 overlays
    assert main(argv + ["--session-report", "s1"]) == 2
    assert "SESSION=FOLDER" in capsys.readouterr().err
    # no metrics.json: a clear error naming the file and session
    (tmp_path / "evaluate" / "metrics.json").unlink()
    assert main(["plots", "--session", "s1", "--fit", str(tmp_path / "fit"), "--evaluate",
                 str(tmp_path / "evaluate"), "--out", str(rep)]) == 2  # fmt: skip
    assert "metrics.json: session s1" in capsys.readouterr().err
