"""Classical bubble segmenter on shadowgraph-style frames drawn here."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from scipy import ndimage as ndi

from surfphase.masks import classical
from surfphase.masks.params import CLASSICAL_DEFAULTS

SS = 4  # supersampling of the drawn truth


def shadowgraph(
    h, w, bubbles, seed=0, noise=0.01, plate_row=None, plate_edge=None, plate_bottom=None
):
    """Bright uneven backlight, bubbles as dark rings with bright cores.

    ``bubbles``: (u, v, r) pixels. With ``plate_row`` a dim static band (the heated
    plate's top face) fills rows ≥ plate_row and a black band the last rows;
    ``plate_edge`` ((w,) rows, fractional) gives the band's top per column instead,
    area-sampled. With ``plate_bottom`` the plate ends there (its black band the rows
    above it) and the backlight is seen below it.
    Returns the image (float32) and truth labels (pixel-centre coverage ≥ 1/2).
    """
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float64)
    bg = (
        0.75
        + 0.15 * (xx / w)
        - 0.1 * (yy / h)
        - 0.15 * (((xx - w / 2) ** 2 + (yy - h / 2) ** 2) / (w * w / 4 + h * h / 4))
    )
    img = bg.copy()
    if plate_row is not None:
        img[plate_row:] = 0.26 * bg[plate_row:]
    elif plate_edge is not None:
        # Area-sampled: the share of each pixel below the edge (rows ≥ edge covered).
        cover = np.clip(yy + 1 - np.asarray(plate_edge)[None, :], 0.0, 1.0)
        img = (1 - cover) * img + cover * 0.26 * bg
    if plate_row is not None or plate_edge is not None:
        end = h if plate_bottom is None else plate_bottom
        img[end - max(2, h // 16) : end] = 0.03
        img[end:] = bg[end:]
    truth = np.full((h, w), -1, np.int32)
    off = (np.arange(SS) + 0.5) / SS - 0.5
    oy, ox = np.meshgrid(off, off, indexing="ij")
    for k, (cx, cy, r) in enumerate(bubbles):
        d = np.sqrt((xx[..., None, None] + ox - cx) ** 2 + (yy[..., None, None] + oy - cy) ** 2)
        rho = d / r
        trans = np.where(rho < 1, 0.12 + 0.8 * np.exp(-((rho / 0.45) ** 2)), 1.0)
        bright = np.where(rho < 1, bg[..., None, None] * trans, np.nan)
        # A bubble in front of the plate is lit by the backlight, not by the plate.
        px = np.where(np.isnan(bright), img[..., None, None], bright).mean(axis=(2, 3))
        cover = (rho < 1).mean(axis=(2, 3))
        img = np.where(cover > 0, px, img)
        truth[cover >= 0.5] = k
    img = img + np.random.default_rng(seed).normal(0, noise, img.shape)
    return np.clip(img, 0, 1).astype(np.float32), truth


def best_iou(truth, labels, k):
    t = truth == k
    ids, cnt = np.unique(labels[t], return_counts=True)
    j = ids[np.argmax(cnt)]
    if j < 0:
        return 0.0
    p = labels == j
    return (t & p).sum() / (t | p).sum()


BUBBLES_128 = [
    (30, 40, 10),
    (80, 40, 12),
    (101, 40, 10),
    (60, 100, 15),
    (20, 110, 5),
    (100, 95, 8),
    (111, 101, 6),
]


@pytest.mark.parametrize("scale", [1, 4])
def test_segments_every_bubble_and_splits_touching_ones(scale):
    bubbles = [(u * scale, v * scale, r * scale) for u, v, r in BUBBLES_128]
    img, truth = shadowgraph(128 * scale, 128 * scale, bubbles)
    labels, scores = classical.segment_frame(img)
    assert labels.dtype == np.int32 and labels.shape == img.shape
    # (80, 40, 12) and (101, 40, 10) overlap, as do the last two: still 7 instances.
    assert labels.max() + 1 == len(bubbles) == len(scores)
    for k in range(len(bubbles)):
        assert best_iou(truth, labels, k) > 0.9, k
    assert np.all(scores > 0.3)


def test_integer_frames_and_bright_polarity():
    img, truth = shadowgraph(96, 96, [(30, 30, 9), (65, 60, 12)], seed=3)
    ref, _ = classical.segment_frame(img)
    as16 = np.round(img * 65535).astype(np.uint16)
    np.testing.assert_array_equal(classical.segment_frame(as16)[0], ref)
    inv, _ = classical.segment_frame(1.0 - img, {"polarity": "bright"})
    np.testing.assert_array_equal(inv, ref)
    with pytest.raises(ValueError, match="polarity"):
        classical.segment_frame(img, {"polarity": "grey"})


def test_background_fit_follows_backlight_not_bubbles():
    img, truth = shadowgraph(128, 128, BUBBLES_128, noise=0.0)
    yy, xx = np.mgrid[0:128, 0:128].astype(np.float64)
    true_bg = (
        0.75
        + 0.15 * (xx / 128)
        - 0.1 * (yy / 128)
        - 0.15 * (((xx - 64) ** 2 + (yy - 64) ** 2) / (2 * 64 * 64))
    )
    bg = classical.estimate_background(img)
    assert np.max(np.abs(bg - true_bg)[truth < 0]) < 0.01


def test_background_fit_follows_a_vignetted_corner_darker_than_the_plate_test():
    """The synthetic generator's ``gradient`` backlight (vignetting, a diffuser's faint
    waves and a left-to-right fall-off to 60 %) above a dark plate: its top-left
    corner is under 0.6 × the image's 95th percentile, the plate's test. The backlight
    is fitted there too, not extrapolated (which left the corner 29 % darker than the
    fit: an object in every frame), and the plate stays out of the fit."""
    from surfphase.synth.shadowgraph import background

    h, w = 112, 144
    true_bg = background("cam0", h, w, seed=0, pattern="gradient").astype(np.float64)
    img = true_bg.copy()
    img[96:] = 0.26 * true_bg[96:]  # the plate's top face ...
    img[104:] = 0.03  # ... and its black front
    assert img[0, 0] < 0.6 * np.percentile(img, 95)
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float64)
    bubbles = [(60.0, 40.0, 8.0), (110.0, 60.0, 10.0)]
    for cx, cy, r in bubbles:
        img[np.hypot(xx - cx, yy - cy) < r] *= 0.2
    img = np.clip(img + np.random.default_rng(0).normal(0, 0.005, img.shape), 0, 1)
    bg = classical.estimate_background(img.astype(np.float32)).astype(np.float64)
    false_contrast = (bg - true_bg) / bg
    threshold = CLASSICAL_DEFAULTS["threshold_high"]
    assert np.max(false_contrast[:90]) < threshold  # 0.29 in the corner before
    assert np.max(np.abs(false_contrast[20:90, 20:-20])) < 0.05
    labels, _ = classical.segment_frame(img.astype(np.float32))
    found = {int(labels[int(cy), int(cx)]) for cx, cy, _ in bubbles}
    assert min(found) >= 0 and len(found) == 2
    # Nothing else above the plate: no instance in the vignetted corner.
    assert set(np.unique(labels[:90])) <= {-1, *found}


def test_empty_frame_has_no_instance():
    img, _ = shadowgraph(64, 64, [], seed=1)
    labels, scores = classical.segment_frame(img)
    assert (labels == -1).all() and scores.size == 0


def test_bubble_growing_on_the_plate_is_whole():
    """The plate is static; a bubble grows on it in every frame while another rises."""
    h = w = 128
    frames, truths = [], []
    for t in range(12):
        r = 4.0 + 0.6 * t  # grows, its centre 0.6 R above the plate's edge
        sites = [(40.0, 96 - 0.6 * r, r), (90, 60 - 3 * t, 8)]
        img, tr = shadowgraph(h, w, sites, seed=t, plate_row=96)
        frames.append(img)
        truths.append(tr)
    stack = np.stack(frames)
    ref = classical.session_reference(stack)
    bg, static = classical.static_background(ref)
    # The plate and its 2-row rim are static, the backlight above is not (the edge
    # may follow a bubble's dent by up to 3 rows).
    assert static[94:].all() and not static[:91].any()
    for t in (3, 8, 11):
        labels, _ = classical.segment_frame(stack[t], None, (bg, static))
        assert labels.max() + 1 == 2
        assert best_iou(truths[t], labels, 0) > 0.8
        assert best_iou(truths[t], labels, 1) > 0.9


@pytest.mark.parametrize("r", [4.5, 5.5, 6.5, 8.0])
def test_a_small_blurred_bubble_on_the_plate_grows_to_its_outline(r):
    """Blurred (a lens, 1 px), a small bubble's thin dark rim departs from the dim
    plate by less than ``static_edge``: the segmentation keeps little more than its
    bright core. Grown to half its rim's own darkness it is its outline, to within a
    third of the area for the smallest (the blur lowers a thin rim's peak, so that edge
    errs outwards); it loses no pixel and takes none of another instance's."""
    h = w = 96
    frames, truths = [], []
    for t in range(8):
        sites = [(40.0, 72 + 0.3 * r, r), (70.0, 30.0, 6.0)] if t % 2 == 0 else []
        img, tr = shadowgraph(h, w, sites, seed=t, plate_row=64, noise=0.005)
        frames.append(cv2.GaussianBlur(img, (0, 0), 1.0))
        truths.append(tr)
    stack = np.stack(frames)
    bg = classical.static_background(classical.session_reference(stack))
    noise = classical.contrast_noise(stack[1::2], None, bg)  # the frames without bubbles
    labels, _ = classical.segment_frame(stack[0], None, bg, noise)
    assert labels.max() + 1 == 2
    truth = truths[0] == 0
    k = int(np.bincount(labels[truth & (labels >= 0)]).argmax())
    piece = labels == k
    if r < 6:
        assert piece.sum() / truth.sum() < 0.6
    signed = classical.relative_contrast(stack[0], None, bg, signed=True)
    grown = classical.outline_in_front(piece, labels < 0, signed, bg[1], None, noise)
    assert 0.9 < grown.sum() / truth.sum() < 1.35
    assert (grown & truth).sum() / (grown | truth).sum() > 0.75
    assert not (piece & ~grown).any() and not (grown & (labels >= 0) & ~piece).any()


def test_a_plate_seen_with_backlight_below_it_is_the_plate():
    """A camera level with the plate sees backlight under it too: the plate's band
    spans the width without reaching the bottom border. It is still the static
    structure, and a bubble rising in front of its top edge is its own instance, not
    part of a plate-sized one."""
    h = w = 128
    frames, truths = [], []
    for t in range(12):
        sites = [(40.0, 84 - 0.5 * t, 6.0), (90, 60 - 3 * t, 8)]
        img, tr = shadowgraph(h, w, sites, seed=t, plate_row=80, plate_bottom=112)
        frames.append(img)
        truths.append(tr)
    stack = np.stack(frames)
    ref = classical.session_reference(stack)
    bg, static = classical.static_background(ref)
    assert static[80:112].all() and not static[:76].any()
    for t in (0, 5, 11):
        labels, _ = classical.segment_frame(stack[t], None, (bg, static))
        assert labels.max() + 1 == 2
        assert best_iou(truths[t], labels, 0) > 0.8
        assert best_iou(truths[t], labels, 1) > 0.9
    # A dark band across the top of the view is no plate; one across its lower half,
    # or one reaching the bottom border, can be.
    comp = np.zeros((40, 30), int)
    comp[30:36] = 1
    comp[2:8] = 2
    comp[20:, 10:14] = 3
    assert classical.plate_components(comp).tolist() == [1, 3]


@pytest.mark.parametrize("v0, r", [(-2.0, 10.0), (0.0, 7.0), (2.0, 7.0)])
def test_a_bubble_leaving_the_frame_keeps_the_core_the_border_cuts_open(v0, r):
    """A bubble whose centre is at the top border: its bright core is open to the
    border, not a hole, yet it is the bubble's (the mask is the visible disc, one
    instance). Left open, the mask was the ring's arms (IoU 0.76–0.93 here), which the
    watershed may split in two."""
    img, truth = shadowgraph(96, 96, [(40.0, v0, r), (70.0, 60.0, 8.0)], seed=1)
    labels, _ = classical.segment_frame(img, None)
    ids = np.unique(labels[truth == 0])
    assert len(ids[ids >= 0]) == 1
    assert best_iou(truth, labels, 0) > 0.94


def test_polyline_edge_keeps_corners_and_drops_dents():
    """A plate's far edge seen in perspective: two straight pieces meeting in a corner,
    dented up and down by bubbles sitting on it; against the analytic polyline."""
    x = np.arange(200.0)
    truth = np.where(x < 90, 120 + 0.15 * (90 - x), 120 + 0.5 * (x - 90))

    def arc(c: float, r: float) -> np.ndarray:
        return np.sqrt(np.clip(r * r - (x - c) ** 2, 0, None))

    # Dark rings of bubbles above the edge (arcs up to 2 r above it), one just left of
    # the corner; a bright core hiding the edge's top rows; columns where no plate is
    # seen.
    core = np.minimum(arc(120, 7), 4)
    edge = np.round(truth - 2 * arc(39, 9) - 2 * arc(80, 6) + core - 2 * arc(166, 6))
    edge[150:158] = 200
    clean, on = classical.polyline_edge(edge, 71, CLASSICAL_DEFAULTS["static_edge_tol_px"])
    dents = (arc(39, 9) > 0.5) | (arc(80, 6) > 0.5) | (core > 1.5) | (arc(166, 6) > 0.5)
    assert not on[dents].any()
    assert on[86:95].all()  # the corner and its neighbours are the edge itself
    keep = (x < 150) | (x >= 172)
    assert np.abs(clean - truth)[keep].max() <= 1.0
    # A running median of the same width (the former cleaning) cuts the corner.
    assert np.abs(ndi.median_filter(edge, 71, mode="nearest") - truth)[88:93].min() >= 3


def test_polyline_edge_gives_back_a_corner_a_bubble_hides():
    """A ring sitting on the corner itself: the corner is under the dent, and the two
    pieces' lines extended under it meet there (the chord cuts it by 2.5 rows)."""
    x = np.arange(200.0)
    truth = np.where(x < 90, 120 + 0.15 * (90 - x), 120 + 0.5 * (x - 90))
    ring = 2 * np.sqrt(np.clip(64 - (x - 90) ** 2, 0, None))
    edge = np.round(truth - ring)
    clean, on = classical.polyline_edge(edge, 71, CLASSICAL_DEFAULTS["static_edge_tol_px"])
    assert not on[ring > 0.5].any()
    assert np.abs(clean - truth).max() <= 0.5
    chord = np.interp(x, x[on], edge[on])
    assert (chord - truth)[90] > 2


def test_plate_corner_stays_plate_beside_a_bubble_sitting_there():
    """A trapezoid plate's corner, a bubble resting on its edge beside it in every frame:
    the static region follows the corner, and the bubble's mask takes no plate."""
    h, w = 128, 160
    x = np.arange(w) + 0.5
    plate = np.where(x < 70, 80 + 0.12 * (70 - x), 80 + 0.4 * (x - 70))
    frames, truths = [], []
    for t in range(12):
        img, tr = shadowgraph(
            h, w, [(63.0, 76.0, 6.0), (120, 50 - 3 * t, 7)], seed=t, plate_edge=plate
        )
        frames.append(img)
        truths.append(tr)
    stack = np.stack(frames)
    bg, static = classical.static_background(classical.session_reference(stack))
    top = np.argmax(static, axis=0)
    want = np.ceil(plate - 0.5) - 2  # first row whose centre is on the plate, less the rim
    assert np.abs(top - want).max() <= 1
    for t in (0, 6, 11):
        labels, _ = classical.segment_frame(stack[t], None, (bg, static))
        assert best_iou(truths[t], labels, 0) > 0.75
        k = np.bincount(labels[truths[t] == 0][labels[truths[t] == 0] >= 0]).argmax()
        cols = np.flatnonzero((labels == k).any(axis=0))
        assert cols.max() <= 63 + 6 + 1


def test_plate_under_a_bubble_sitting_on_a_slanted_edge_is_the_plate():
    """Where a bubble hides a slanted, blurred plate edge in every frame, the background
    there is the plate's own, rim included (against the same plate drawn without the
    bubble): the along-edge medians follow the edge's sub-pixel position, not its
    staircase of whole rows."""
    h, w = 96, 192
    x = np.arange(w) + 0.5
    plate = 60 + 0.3 * (x - 96)
    sites = [(96.0, 57.0, 5.0)]  # its lower part in front of the plate, in every frame
    img, truth = shadowgraph(h, w, sites, noise=0.0, plate_edge=plate)
    clean, _ = shadowgraph(h, w, [], noise=0.0, plate_edge=plate)
    img = cv2.GaussianBlur(img, (0, 0), 1.0)
    clean = cv2.GaussianBlur(clean, (0, 0), 1.0)
    bg, static = classical.static_background(img)
    under = ndi.binary_dilation(truth == 0, iterations=2) & static
    assert under.sum() > 20
    err = np.abs(bg - clean)[under] / clean[under]
    # A pixel is replaced when it departs from the along-edge median by more than
    # static_outlier_frac, so that bounds what is left; rows of the band that
    # followed the staircase left 0.32 here.
    assert err.max() < CLASSICAL_DEFAULTS["static_outlier_frac"], err.max()


def _rising_stack(n: int, noise: float, sites=()) -> np.ndarray:
    """(n, 128, 128) frames over a plate (rows ≥ 96): one bubble rising, plus ``sites``
    (u, v, r) that stay put in every frame."""
    frames = []
    for t in range(n):
        img, _ = shadowgraph(
            128, 128, [(90, 70 - 3 * t, 8), *sites], seed=t, noise=noise, plate_row=96
        )
        frames.append(img)
    return np.stack(frames)


def test_contrast_noise_is_the_drawn_noise():
    """Frames with Gaussian noise σ = 0.01: the smoothed contrast's noise is σ over the
    background times the Gaussian kernel's noise gain √Σk² per axis (cv2's own kernel),
    above the plate and, 1/0.26 times larger, on its dim face."""
    sigma = 0.01
    stack = _rising_stack(16, sigma)
    ref = classical.session_reference(stack)
    bg, static = classical.static_background(ref)
    est = classical.contrast_noise(stack, None, (bg, static))
    k = cv2.getGaussianKernel(7, classical.CLASSICAL_DEFAULTS["smooth_px"])[:, 0]
    gain = float((k**2).sum())  # 2D separable: (√Σk²)² = Σk²
    truth = sigma / np.maximum(bg, 1e-3) * gain
    free = ~static
    free[:, 80:100] = False  # the rising bubble's path
    on_plate = static.copy()
    on_plate[:100] = False
    on_plate[118:] = False  # the black band, where nothing is seen
    for region in (free, on_plate):
        ratio = np.median(est[region] / truth[region])
        assert 0.85 < ratio < 1.15, ratio


def test_noise_raises_the_thresholds_where_the_plate_is_dim():
    """On a noisy dim plate the fixed thresholds segment noise; thresholds raised to the
    measured noise find no object away from the two bubbles (one rising, one sitting in
    front of the plate's face in every frame, which the plate's background must not
    absorb), and find both in every frame."""
    from scipy import ndimage as ndi

    stack = _rising_stack(12, 0.02, sites=[(40.0, 108.0, 7.0)])
    ref = classical.session_reference(stack)
    plate = classical.session_reference(stack, 50.0)
    bgs = classical.static_background(ref, None, plate)
    noise = classical.contrast_noise(stack, None, bgs)
    # The sitting bubble is in every frame's plate reference; its background is the plate.
    yy, xx = np.mgrid[0:128, 0:128].astype(np.float64)
    light = 0.75 + 0.15 * xx / 128 - 0.1 * yy / 128
    light -= 0.15 * ((xx - 64) ** 2 + (yy - 64) ** 2) / (2 * 64**2)
    disc = np.hypot(xx - 40, yy - 108) < 8
    err = np.abs(bgs[0][disc] / (0.26 * light[disc]) - 1)
    assert np.percentile(err, 95) < 0.15, np.percentile(err, 95)

    def away(labels, t):
        """Instances whose centroid is more than 3 px outside both bubbles."""
        true = [(70 - 3 * t, 90, 8), (108, 40, 7)]
        n = 0
        for i in range(labels.max() + 1):
            cy, cx = ndi.center_of_mass(labels == i)
            n += min(np.hypot(cy - v, cx - u) - r for v, u, r in true) > 3
        return n

    fixed = sum(away(classical.segment_frame(f, None, bgs)[0], t) for t, f in enumerate(stack))
    assert fixed > 0  # noise specks with the fixed thresholds
    for t, f in enumerate(stack):
        labels = classical.segment_frame(f, None, bgs, noise)[0]
        assert away(labels, t) == 0
        assert labels[70 - 3 * t, 90] >= 0 and labels[108, 40] >= 0


def test_outline_in_front_grows_by_a_dark_rim_only():
    """A bubble's piece in front of the plate (its bright core) grows through its dark
    rim to the rim's outer edge, no farther than its own radius; a speck brighter than
    the plate all round (a piece of the plate's edge) has no rim and does not grow."""
    h = w = 40
    yy, xx = np.mgrid[0:h, 0:w]
    rho = np.hypot(yy - 20, xx - 20)
    static = np.ones((h, w), bool)
    core = rho <= 2.5
    for halo, grows in ((0.15, True), (-0.15, False)):
        signed = np.where(core, -0.8, np.where(rho <= 5.5, halo, 0.0)).astype(np.float32)
        # The contrast's zero crossing between the core and the rim: a 1-px ring.
        signed[(rho > 2.5) & (rho <= 3.5)] = 0.0
        out = classical.outline_in_front(core, np.ones((h, w), bool), signed, static)
        assert not (core & ~out).any()
        if grows:
            disc = rho <= 5.5
            assert (out == disc).mean() > 0.99 and (out & ~disc).sum() == 0
        else:
            assert (out == core).all()
