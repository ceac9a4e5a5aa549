"""The fit's bubble table: centroids and track-aware finite-difference velocities."""

from __future__ import annotations

import numpy as np
import pytest

from surfphase.fit.outputs import bubble_table


def _arrays(means: np.ndarray, bubble: np.ndarray, alive: np.ndarray) -> dict:
    F, N = bubble.shape
    return {
        "means": means.astype(np.float32),
        "bubble": bubble.astype(np.int32),
        "alive": alive,
        "opacity": np.ones((F, N), np.float32),
        "log_scales": np.zeros((F, N, 2), np.float32),
    }


def test_velocities_are_one_sided_at_merges_and_births():
    # Two bubbles of two surfels each, 4 frames at dt = 0.1 s. Bubble 1 moves +x at
    # 1 m/s, bubble 2 +y at 2 m/s. They merge into bubble 3 at frame 2; a new bubble
    # (two surfels spawned at frame 2, absent before) appears as bubble 4.
    F, N = 4, 6
    times = 0.1 * np.arange(F)
    x0 = np.array([[0.0, 0, 0], [0.2, 0, 0], [5, 0, 0], [5.2, 0, 0], [9, 9, 0], [9, 9.2, 0]])
    v = np.array([[1.0, 0, 0], [1, 0, 0], [0, 2, 0], [0, 2, 0], [0, 0, 3], [0, 0, 3]])
    means = x0[None] + times[:, None, None] * v[None]
    bubble = np.array(
        [[1, 1, 2, 2, -1, -1], [1, 1, 2, 2, -1, -1], [3, 3, 3, 3, 4, 4]] + [[3, 3, 3, 3, 4, 4]]
    )
    alive = np.ones((F, N), bool)
    alive[:2, 4:] = False
    tab = bubble_table(_arrays(means, bubble, alive), times, np.arange(F)).set_index(
        ["frame", "bubble"]
    )
    vel = lambda f, b: tab.loc[(f, b), ["vx", "vy", "vz"]].to_numpy(np.float64)  # noqa: E731
    # Bubble 1: frame 0 forward, frame 1 backward (its track ends at the merge);
    # the merged surfels' (0, 1)-weighted motion is never mixed in.
    np.testing.assert_allclose(vel(0, 1), [1, 0, 0], atol=1e-5)
    np.testing.assert_allclose(vel(1, 1), [1, 0, 0], atol=1e-5)
    np.testing.assert_allclose(vel(1, 2), [0, 2, 0], atol=1e-5)
    # Bubble 3 starts at the merge: forward at frame 2, backward at frame 3 (last).
    np.testing.assert_allclose(vel(2, 3), [0.5, 1, 0], atol=1e-5)
    np.testing.assert_allclose(vel(3, 3), [0.5, 1, 0], atol=1e-5)
    np.testing.assert_allclose(vel(2, 4), [0, 0, 3], atol=1e-5)  # spawned: forward
    # Centroids: the mean of the bubble's surfels (equal weights).
    np.testing.assert_allclose(tab.loc[(2, 3), ["x", "y", "z"]].to_numpy(float), [2.7, 0.2, 0])
    assert tab.loc[(2, 3), "n_surfels"] == 4


def test_central_difference_inside_a_track_with_an_id_change():
    # One bubble accelerating along y (y = t²), renumbered from 1 to 7 at frame 2.
    F = 5
    times = 0.5 * np.arange(F)
    means = np.zeros((F, 2, 3))
    means[:, :, 1] = times[:, None] ** 2
    means[:, 1, 0] = 0.1
    bubble = np.array([[1, 1], [1, 1], [7, 7], [7, 7], [7, 7]])
    tab = bubble_table(_arrays(means, bubble, np.ones((F, 2), bool)), times, np.arange(F))
    vy = tab.set_index("frame")["vy"].to_numpy()
    # np.gradient of t²: central inside, one-sided at both ends.
    np.testing.assert_allclose(vy, np.gradient(times**2, times), atol=1e-5)


def test_records_with_surfel_ids_stack_by_id():
    # Frame 0: surfels 0, 1, 2; frame 1: surfel 1 retired (replaced at a merge) and
    # surfel 3 added. Columns are ids, so surfel 2 keeps column 2 at both frames, and the
    # per-surfel velocities are backward for the retired one at its last frame.
    from surfphase.fit.outputs import stack_records, surfel_velocities

    def rec(ids, xs):
        n = len(ids)
        means = np.zeros((n, 3), np.float32)
        means[:, 0] = xs
        return {
            "ids": np.asarray(ids),
            "means": means,
            "quats": np.tile(np.float32([1, 0, 0, 0]), (n, 1)),
            "log_scales": np.zeros((n, 2), np.float32),
            "colors": np.zeros((n, 1), np.float32),
            "opacity": np.ones(n, np.float32),
            "bubble": np.ones(n, np.int32),
            "gamma": 1.0,
        }

    r0, r1 = rec([0, 1, 2], [0.0, 1.0, 2.0]), rec([0, 2, 3], [0.5, 2.5, 7.0])
    r2 = rec([0, 2, 3], [1.0, 3.0, 7.5])
    a = stack_records([r0, r1, r2], extent=1.0)
    assert a["alive"].tolist() == [[1, 1, 1, 0], [1, 0, 1, 1], [1, 0, 1, 1]]
    np.testing.assert_allclose(a["means"][:, 2, 0], [2.0, 2.5, 3.0])
    np.testing.assert_allclose(a["means"][1:, 3, 0], [7.0, 7.5])
    v = surfel_velocities(a["means"], a["alive"], np.array([0.0, 1.0, 2.0]))
    np.testing.assert_allclose(v[:, 0, 0], [0.5, 0.5, 0.5])  # central inside, one-sided ends
    np.testing.assert_allclose(v[0, 1], 0.0)  # surfel 1 exists at frame 0 only: unknown
    np.testing.assert_allclose(v[1, 3, 0], 0.5)  # born at frame 1: forward


def test_retired_surfel_gets_a_backward_difference():
    from surfphase.fit.outputs import surfel_velocities

    means = np.zeros((3, 1, 3), np.float32)
    means[:, 0, 1] = [0.0, 2.0, 0.0]
    alive = np.array([[True], [True], [False]])
    v = surfel_velocities(means, alive, np.array([0.0, 0.5, 1.0]))
    np.testing.assert_allclose(v[1, 0], [0, 4.0, 0])  # retired after frame 1: backward


def test_track_smoothing_against_analytic_tracks():
    """A bubble rising with constant acceleration (exact for order 2) and a noisy one:
    the smoothed table's velocity is the analytic derivative, and differentiating its
    own centroids gives its velocity column."""
    import pandas as pd

    from surfphase.fit.outputs import smooth_tracks

    fps, n = 2000.0, 25
    t = np.arange(n) / fps
    y = 0.002 + 0.2 * t + 0.5 * 3.0 * t**2  # m; v = 0.2 + 3 t
    rng = np.random.default_rng(0)
    noisy = y + rng.normal(0, 4e-6, n)  # 4 µm centroid jitter
    rows = [{"frame": k, "time_s": t[k], "bubble": b, "x": 0.0, "y": yy[k], "z": 0.0,
             "vx": 0.0, "vy": np.nan, "vz": 0.0, "n_surfels": 10}
            for b, yy in ((1, y), (2, noisy)) for k in range(n)]  # fmt: skip
    table = pd.DataFrame(rows)
    raw_v = np.gradient(noisy, t)
    seg = np.repeat([0, 1], n)
    smooth_tracks(table, seg, window_s=0.0045, order=2)  # 9 frames
    exact = table[table.bubble == 1]
    np.testing.assert_allclose(exact["y"], y, atol=1e-12)
    np.testing.assert_allclose(exact["vy"], np.gradient(y, t), atol=1e-9)  # the truth's
    smooth = table[table.bubble == 2]
    truth = np.gradient(y, t)
    err_raw = np.abs(raw_v - truth).mean()
    err_smooth = np.abs(smooth["vy"].to_numpy() - truth).mean()
    assert err_smooth < 0.4 * err_raw
    # The centroids and velocities agree: d/dt of the reported track is the velocity.
    dydt = np.gradient(smooth["y"].to_numpy(), t)
    assert np.abs(dydt - smooth["vy"]).max() < 1e-12


def _polyfit_t(t: np.ndarray, y: np.ndarray) -> tuple[float, float]:
    """numpy's |t| of a parabola's quadratic coefficient (its covariance scaled by
    χ²/(n − 3)) and the lag-1 autocorrelation of its residuals."""
    coef, cov = np.polyfit(t, y, 2, cov=True)
    r = y - np.polyval(coef, t)
    return abs(coef[0]) / np.sqrt(cov[0, 0]), float(np.dot(r[1:], r[:-1]) / np.dot(r, r))


def test_quadratic_t_is_numpys_polyfit_t_statistic_over_the_residuals_correlation():
    """numpy's t statistic, its variance inflated by (1 + ρ)/(1 − ρ) for the residuals'
    lag-1 autocorrelation ρ, clipped to [0, CURVATURE_MAX_RHO]: white noise and a slow
    drift (ρ clipped) in one call."""
    from surfphase.fit.outputs import CURVATURE_MAX_RHO, quadratic_t

    rng = np.random.default_rng(1)
    t = np.arange(24) / 3000.0
    y = np.stack([0.1 * t + 4 * t**2, -0.2 * t], axis=1) + rng.normal(0, 3e-6, (24, 2))
    y[:, 1] += 2e-5 * np.sin(2 * np.pi * (t / t[-1] - 0.5))  # a slow wave: correlated residuals
    ref = []
    for k in range(2):
        tk, rho = _polyfit_t(t, y[:, k])
        rho = min(max(rho, 0.0), CURVATURE_MAX_RHO)
        ref.append(tk / np.sqrt((1 + rho) / (1 - rho)))
        assert quadratic_t(t, y[:, k : k + 1]) == pytest.approx(ref[-1], rel=1e-6)
    assert quadratic_t(t, y) == pytest.approx(max(ref), rel=1e-6)
    assert _polyfit_t(t, y[:, 0])[1] < 0.2  # white: (nearly) as numpy's
    assert _polyfit_t(t, y[:, 1])[1] > CURVATURE_MAX_RHO  # the clip is exercised
    assert quadratic_t(t[:4], y[:4]) == 0.0


def test_quadratic_t_calls_a_slow_drift_curved_less_often_and_a_curve_as_often():
    """Monte Carlo against the statistic's purpose, the end test's threshold 5
    (``track_end_t``): 400 straight tracks of 24 frames whose centres err by AR(1) noise
    (ρ = 0.9, a silhouette's shape-mode error spanning frames at a high frame rate):
    white-noise standard errors call a tenth or more of them curved (white noise: 1 in
    10,000), the correlated ones under half as many. 400 parabolas in white noise, t about 12: found as often
    either way (over 98 %)."""
    from surfphase.fit.outputs import quadratic_t

    rng = np.random.default_rng(7)
    t = np.arange(24) / 8000.0
    plain, corrected = 0, 0
    for _ in range(400):
        e = np.zeros(24)
        e[0] = rng.normal()
        for i in range(1, 24):
            e[i] = 0.9 * e[i - 1] + np.sqrt(1 - 0.81) * rng.normal()
        y = 0.2 * t + 5e-6 * e
        plain += _polyfit_t(t, y)[0] > 5
        corrected += quadratic_t(t, y[:, None]) > 5
    assert plain >= 40 and corrected < 0.5 * plain, (plain, corrected)
    found = 0
    for _ in range(400):
        y = 0.2 * t + 9.0 * t**2 + 1e-6 * rng.normal(size=24)
        found += quadratic_t(t, y[:, None]) > 5
    assert found >= 392, found


def test_track_ends_take_a_parabola_only_where_the_track_curves():
    """An order-1 smoothing lags an accelerating bubble over a track's last window; with
    ``end_window_s`` the ends of a clearly curved track take a moving parabola (end
    velocity error several times lower), and a straight noisy track is left exactly as
    without it (its curvature is not significant)."""
    import pandas as pd

    from surfphase.fit.outputs import smooth_tracks

    fps, n = 2000.0, 25
    t = np.arange(n) / fps
    rng = np.random.default_rng(0)
    jitter = rng.normal(0, 3e-6, n)
    curved = 0.002 + 0.06 * t + 0.5 * 15.0 * t**2 + jitter  # detaching: 15 m/s²
    straight = 0.002 + 0.2 * t + jitter

    def table_of(y):
        return pd.DataFrame({"frame": np.arange(n), "time_s": t, "bubble": 1, "x": 0.0,
                             "y": y, "z": 0.0, "vx": 0.0, "vy": np.nan, "vz": 0.0})  # fmt: skip

    out = {}
    for name, y in (("curved", curved), ("straight", straight)):
        for ends in ((0.0, 0.0), (0.005, 5.0)):
            tab = table_of(y)
            smooth_tracks(tab, np.zeros(n, int), 0.003, 1, *ends)
            out[name, ends[0]] = tab["vy"].to_numpy()
    true_v = 0.06 + 15.0 * t
    end = np.r_[0:3, n - 3 : n]  # the half windows at the two ends (7-frame window)
    lag = np.abs(out["curved", 0.0][end] - true_v[end]).mean()
    fixed = np.abs(out["curved", 0.005][end] - true_v[end]).mean()
    assert fixed < 0.3 * lag, (fixed, lag)
    # Inside (beyond the central differences next to the ends) nothing changes.
    np.testing.assert_array_equal(out["curved", 0.0][4:-4], out["curved", 0.005][4:-4])
    np.testing.assert_array_equal(out["straight", 0.0], out["straight", 0.005])
    # A track shorter than the end window (9 frames, 4.5 ms) has no end apart from its
    # middle: left as the line gives it, however it curves; 10 frames (5 ms) is tested.
    for k, same in ((9, True), (10, False)):
        short = [table_of(curved)[:k] for _ in range(2)]
        smooth_tracks(short[0], np.zeros(k, int), 0.003, 1)
        smooth_tracks(short[1], np.zeros(k, int), 0.003, 1, 0.005, 5.0)
        assert np.array_equal(short[0]["vy"], short[1]["vy"]) == same


def test_blended_track_is_the_mean_of_two_savitzky_golay_fits():
    """With ``blend_window_s`` the track is the mean of the two moving polynomials, each
    scipy's own ``savgol_filter`` over its window (odd frames, ``mode="interp"``), and
    the velocity column is still the track's own derivative; a track too short for the
    second polynomial keeps the first alone."""
    import pandas as pd
    from scipy.signal import savgol_filter

    from surfphase.fit.outputs import smooth_tracks

    fps, n = 2000.0, 25
    t = np.arange(n) / fps
    rng = np.random.default_rng(2)
    y = 0.002 + 0.2 * t + 0.5 * 3.0 * t**2 + rng.normal(0, 4e-6, n)

    def table_of(y, n):
        return pd.DataFrame({"frame": np.arange(n), "time_s": t[:n], "bubble": 1, "x": 0.0,
                             "y": y[:n], "z": 0.0, "vx": 0.0, "vy": np.nan, "vz": 0.0})  # fmt: skip

    tab = table_of(y, n)
    smooth_tracks(tab, np.zeros(n, int), 0.003, 1, 0.0, 0.0, 0.008, 2)
    short = savgol_filter(y, 7, 1, mode="interp")  # 3 ms: 6 frames, made odd
    long = savgol_filter(y, 17, 2, mode="interp")  # 8 ms: 16 frames, made odd
    np.testing.assert_allclose(tab["y"], 0.5 * (short + long), rtol=0, atol=1e-15)
    np.testing.assert_allclose(tab["vy"], np.gradient(0.5 * (short + long), t), atol=1e-12)
    tiny = table_of(y, 3)  # 3 frames: no parabola of a window > 2 fits
    smooth_tracks(tiny, np.zeros(3, int), 0.003, 1, 0.0, 0.0, 0.008, 2)
    np.testing.assert_allclose(tiny["y"], savgol_filter(y[:3], 3, 1, mode="interp"), atol=1e-15)


def test_short_track_takes_the_blend_parabola_only_where_it_curves():
    """A track shorter than ``blend_window_s`` (24 frames at 10,000 fps: 2.4 ms) gets the
    blend's parabola, one fit over all of it, only where its curvature is significant
    (``end_t``; ``end_t`` 0: always, as before the test): a bubble at constant speed
    with 3 µm noise keeps the line alone (scipy's ``savgol_filter``), and its velocity
    error against the analytic truth, over 40 noise draws, is a third below that of the
    blended track, whose parabola turns the noise into a drifting velocity; a bubble
    accelerating at 400 m/s² (t far above 5) is blended exactly as a long track is."""
    import pandas as pd
    from scipy.signal import savgol_filter

    from surfphase.fit.outputs import smooth_tracks

    fps, n = 10000.0, 24
    t = np.arange(n) / fps

    def smoothed(y, end_t):
        tab = pd.DataFrame({"frame": np.arange(n), "time_s": t, "bubble": 1, "x": 0.0,
                            "y": y, "z": 0.0, "vx": 0.0, "vy": np.nan, "vz": 0.0})  # fmt: skip
        smooth_tracks(tab, np.zeros(n, int), 0.003, 1, 0.005, end_t, 0.008, 2)
        return tab

    rng = np.random.default_rng(5)
    err = {5.0: [], 0.0: []}
    for _ in range(40):
        y = 0.002 + 0.2 * t + rng.normal(0, 3e-6, n)
        for end_t in err:
            err[end_t].append(np.abs(smoothed(y, end_t)["vy"].to_numpy() - 0.2).mean())
    line = savgol_filter(y, 23, 1, mode="interp")  # 3 ms: 30 frames, capped at 23
    np.testing.assert_allclose(smoothed(y, 5.0)["y"], line, rtol=0, atol=1e-15)
    assert np.mean(err[5.0]) < 0.8 * np.mean(err[0.0]), (np.mean(err[5.0]), np.mean(err[0.0]))
    y = 0.002 + 0.2 * t + 0.5 * 400.0 * t**2 + rng.normal(0, 3e-6, n)
    both = 0.5 * (savgol_filter(y, 23, 1, mode="interp") + savgol_filter(y, 23, 2, mode="interp"))
    np.testing.assert_allclose(smoothed(y, 5.0)["y"], both, rtol=0, atol=1e-15)


def test_one_gross_outlier_does_not_bend_the_track():
    """With ``outlier_k`` a centre 0.3 mm off a noisy track (a frame a view damaged) is
    replaced by the track smoothed without it: the velocities near it are those of the
    same track with that frame's true centre (analytic truth plus the same noise),
    while without the pass they are off by several times that; a track with no such
    frame is smoothed exactly as without the pass, and one of fewer than
    OUTLIER_MIN_ROWS frames is left to the plain smoothing."""
    import pandas as pd

    from surfphase.fit.outputs import OUTLIER_MIN_ROWS, smooth_tracks

    fps, n = 3000.0, 18
    t = np.arange(n) / fps
    rng = np.random.default_rng(4)
    z = -5e-4 + 0.01 * t + rng.normal(0, 1e-5, n)  # 10 µm noise in depth
    bad = z.copy()
    bad[9] += 3e-4
    rules = (0.005, 5.0, 0.008, 2)

    def smoothed(z, k, m=n):
        tab = pd.DataFrame({"frame": np.arange(m), "time_s": t[:m], "bubble": 1, "x": 0.0,
                            "y": 0.0, "z": z[:m], "vx": 0.0, "vy": 0.0, "vz": np.nan})  # fmt: skip
        smooth_tracks(tab, np.zeros(m, int), 0.003, 1, *rules, outlier_k=k)
        return tab["vz"].to_numpy()

    clean = smoothed(z, 0.0)
    near = slice(5, 14)
    plain = np.abs(smoothed(bad, 0.0)[near] - clean[near]).max()
    robust = np.abs(smoothed(bad, 6.0)[near] - clean[near]).max()
    assert plain > 0.02 and robust < 0.2 * plain, (plain, robust)  # m/s
    np.testing.assert_array_equal(smoothed(z, 6.0), clean)
    m = OUTLIER_MIN_ROWS - 1
    np.testing.assert_array_equal(smoothed(bad, 6.0, m), smoothed(bad, 0.0, m))


def test_track_segments_end_at_a_merge():
    import pandas as pd

    from surfphase.fit.outputs import track_segments

    # Frames 0-1: bubbles 1 and 2 (surfels 0-3 and 4-7); frame 2: they merged into 3.
    bub = np.array([[1, 1, 1, 1, 2, 2, 2, 2], [1, 1, 1, 1, 2, 2, 2, 2], [3] * 8])
    w = np.ones_like(bub, dtype=float)
    table = pd.DataFrame({"frame": [0, 0, 1, 1, 2], "bubble": [1, 2, 1, 2, 3]})
    seg = track_segments(table, [0, 0, 1, 1, 2], bub, w)
    assert seg[0] == seg[2] and seg[1] == seg[3] and seg[0] != seg[1]
    assert seg[4] not in (seg[0], seg[1])  # the merged bubble starts a new track


def test_low_centres_whose_views_disagree_on_size_lead_their_track():
    """Low rows whose two views agree on the centre's position but not on its size (a
    silhouette grown by the plate's image in one view) lead the track as damaged ones
    do; a size disagreement within the track's own, or within 5 %, does not."""
    from surfphase.fit.outputs import lead_rows

    fps, n = 6000.0, 16
    t = np.arange(n) / fps
    low = np.zeros(n, bool)
    low[:3] = True
    reproj = np.full(n, 0.5)  # positions agree as well in the low rows as after them
    seg = np.zeros(n, np.int64)
    ratio = np.r_[1.23, 1.23, 1.01, np.full(n - 3, 1.02)]
    assert not lead_rows(low, reproj, t, seg, 0.002).any()  # by position alone: none
    lead = lead_rows(low, reproj, t, seg, 0.002, ratio)
    assert lead.tolist() == [True] * 2 + [False] * (n - 2)
    # 4 % off where the next rows are 2 % off: more than twice as much, but under 5 %.
    assert not lead_rows(low, reproj, t, seg, 0.002, np.r_[1.04, 1.04, np.full(n - 2, 1.02)]).any()
    # As far off as the track's next rows are: not damaged.
    same = np.r_[1.2, 1.2, np.full(n - 2, 1.12)]
    assert not lead_rows(low, reproj, t, seg, 0.002, same).any()


def test_a_track_led_by_damaged_low_centres_starts_on_its_parabola():
    """Rows just off the plate whose views agree worse than the track's next ones take
    the parabola of the clean rows (analytic truth); a low row that agrees as well is
    kept as measured."""
    import pandas as pd

    from surfphase.fit.outputs import extrapolate_leads, lead_rows

    fps, n = 5000.0, 20
    t = np.arange(n) / fps
    truth = np.stack([0.01 * t, 0.1 * t + 20.0 * t**2, -0.02 * t + 3.0 * t**2], axis=1)
    low = np.zeros(n, bool)
    low[:4] = True
    reproj = np.full(n, 0.1)
    reproj[:3] = 0.8  # the first three: a silhouette cut by the plate's image
    seg = np.zeros(n, np.int64)
    lead = lead_rows(low, reproj, t, seg, 0.002)
    assert lead.tolist() == [True] * 3 + [False] * (n - 3)
    # A track whose low rows agree as well as its next ones: nothing leads it.
    assert not lead_rows(low, np.full(n, 0.1), t, seg, 0.002).any()
    tab = pd.DataFrame({"time_s": t})
    tab[["x", "y", "z"]] = truth + np.where(lead[:, None], 7e-5, 0.0)  # biased up
    tab[["vx", "vy", "vz"]] = 0.0
    extrapolate_leads(tab, seg, lead, 0.002)
    np.testing.assert_allclose(tab[["x", "y", "z"]].to_numpy(), truth, atol=1e-12)
    vel = np.stack([0.01 + 0 * t, 0.1 + 40.0 * t, -0.02 + 6.0 * t], axis=1)
    # Central differences of a parabola are exact inside the track.
    np.testing.assert_allclose(tab[["vx", "vy", "vz"]].to_numpy()[1:-1], vel[1:-1], atol=1e-9)


def test_moving_polynomial_is_savgol_and_its_weighted_fit_is_numpys():
    """``moving_polynomial`` with equal weights is scipy's ``savgol_filter`` (``mode=
    "interp"``), and with weights each sample is the value there of numpy's weighted
    ``polyfit`` over the window centred on it (the first / last window at the ends)."""
    from scipy.signal import savgol_filter

    from surfphase.tracks import moving_polynomial

    rng = np.random.default_rng(7)
    for n, win, order in ((24, 19, 1), (24, 23, 2), (9, 5, 1), (30, 7, 3), (7, 7, 2)):
        p = rng.normal(size=(n, 3))
        ref = savgol_filter(p, win, order, axis=0, mode="interp")
        np.testing.assert_allclose(moving_polynomial(p, win, order), ref, rtol=0, atol=1e-14)
        np.testing.assert_allclose(
            moving_polynomial(p, win, order, np.full(n, 0.3)), ref, rtol=0, atol=1e-12
        )
        w = rng.uniform(0.05, 1.0, n)
        got = moving_polynomial(p, win, order, w)
        for i in range(n):
            lo = min(max(i - win // 2, 0), n - win)
            x = np.arange(lo, lo + win, dtype=float)
            for d in range(3):
                c = np.polyfit(x, p[lo : lo + win, d], order, w=np.sqrt(w[lo : lo + win]))
                assert abs(np.polyval(c, i) - got[i, d]) < 1e-11


def test_centres_whose_views_disagree_weigh_less_in_the_track():
    """A bubble at constant velocity whose centre is pushed 0.15 mm off in a third of its
    frames (a view's silhouette damaged: there the two views disagree, ``reproj_px``
    0.4 against 0.05): with ``reproj_px`` the track's velocity error against the
    analytic truth is several times lower than with every centre weighed the same, and
    with no ``reproj_px`` column, or ``reproj_px`` 0, the smoothing is the unweighted
    one exactly."""
    import pandas as pd

    from surfphase.fit.outputs import smooth_tracks

    fps, n = 6250.0, 24
    t = np.arange(n) / fps
    rng = np.random.default_rng(3)
    z = 1e-3 + 0.017 * t + rng.normal(0, 5e-6, n)
    hit = rng.permutation(n)[: n // 3]
    z[hit] += 1.5e-4
    reproj = np.full(n, 0.05)
    reproj[hit] = 0.4
    rules = (0.005, 5.0, 0.008, 2, 6.0)

    def smoothed(weigh_px, column=True):
        tab = pd.DataFrame({"frame": np.arange(n), "time_s": t, "bubble": 1, "x": 0.0,
                            "y": 0.0, "z": z, "vx": 0.0, "vy": 0.0, "vz": np.nan})  # fmt: skip
        if column:
            tab["reproj_px"] = reproj
        smooth_tracks(tab, np.zeros(n, int), 0.003, 1, *rules, reproj_px=weigh_px)
        return tab["vz"].to_numpy()

    plain = np.abs(smoothed(0.0) - 0.017).mean()
    weighed = np.abs(smoothed(0.1) - 0.017).mean()
    assert weighed < 0.3 * plain, (weighed, plain)
    np.testing.assert_array_equal(smoothed(0.1, column=False), smoothed(0.0))
    with pytest.raises(ValueError, match="track_reproj_px"):
        smoothed(-0.1)
