"""Classical bubble segmenter for shadowgraph-style frames (the embedded default).

In a shadowgraph a bubble is a dark ring (light refracted away from the lens), often
with a bright core, on a bright and slowly varying background. Per frame:

1. background: a grey closing larger than any bubble removes the dark objects, a
   Gaussian blur smooths what remains;
2. contrast ``c = (background − image) / background`` (0 on the background, towards
   1 in a black shadow), thresholded with hysteresis;
3. holes filled (the bright core), specks removed by an opening;
4. touching bubbles split by a watershed on the distance transform; two pieces are
   merged back when the neck between them is nearly as wide as the smaller piece
   (a wobbly bubble, not two);
5. instances smaller than the minimum area dropped.

All sizes are given as fractions of the image's shorter side (or area), so the same
parameters work at 128×128 and 512×512.
"""

from __future__ import annotations

import warnings
from collections.abc import Mapping

import cv2
import numpy as np
from scipy import ndimage as ndi
from skimage.feature import peak_local_max
from skimage.filters import apply_hysteresis_threshold
from skimage.morphology import convex_hull_image
from skimage.segmentation import watershed

from surfphase.folders.frames import unit_grey
from surfphase.masks.params import CLASSICAL_DEFAULTS


def to_unit_float(frame: np.ndarray) -> np.ndarray:
    """A frame (H, W) or (H, W, C) of uint8/uint16/float → float32 grey image in [0, 1]
    (:func:`surfphase.folders.frames.unit_grey`: integers divided by their dtype's
    maximum, floats clipped, colour channels averaged; other dtypes are refused)."""
    return unit_grey(frame)


def _poly_design(x: np.ndarray, y: np.ndarray, degree: int) -> np.ndarray:
    """Columns x^i y^j (i + j ≤ degree) of normalised coordinates in [−1, 1]."""
    cols = [x**i * y**j for i in range(degree + 1) for j in range(degree + 1 - i)]
    return np.stack(cols, axis=-1)


#: A large region darker than this fraction of the backlight is a dark structure (the
#: heated plate), not backlight, for :func:`estimate_background`.
DARK_STRUCTURE = 0.6


def _lstsq(A: np.ndarray, b: np.ndarray, keep: np.ndarray) -> np.ndarray:
    """Least-squares coefficients of (n, k) design ``A`` against (n,) ``b`` over the rows
    ``keep`` (normal equations: a 15-column system, far cheaper than an SVD of A)."""
    Ak = A[keep]
    return np.linalg.solve(Ak.T @ Ak + 1e-9 * np.eye(A.shape[1]), Ak.T @ b[keep])


def estimate_background(image: np.ndarray, degree: int = 4, iterations: int = 3) -> np.ndarray:
    """Smooth background of a (H, W) float image whose objects are darker than it.

    On a ≤64×64 area-downsampled copy, object pixels are those more than 20 % darker
    than a grey closing of 30 % of the shorter side (dark things narrower than that:
    bubbles) or darker than 0.6 × the 95th percentile (the plate); a 2D polynomial of
    total ``degree`` in normalised pixel coordinates is fitted by least squares to the
    others. A region failing the second test that cannot be the plate
    (:func:`plate_components`) is then judged against that polynomial instead (darker
    than 0.6 × it): a vignetted corner is darker than 0.6 × the 95th percentile too, but
    not than the backlight there, and left out it got the polynomial's extrapolation, up
    to 29 % too bright (a static "object" in every frame). The polynomial is then
    refitted without the pixels that stay clearly (2.5 robust σ and 5 %) below it.
    Vignetting and uneven illumination are smooth and broad, so they are followed, not
    rejected.
    Returns (H, W) float32.
    """
    h, w = image.shape
    f = min(1.0, 64.0 / max(h, w))
    small = cv2.resize(
        image.astype(np.float32),
        (max(2, round(w * f)), max(2, round(h * f))),
        interpolation=cv2.INTER_AREA,
    )
    sh, sw = small.shape
    ys, xs = np.mgrid[0:sh, 0:sw]
    A = _poly_design((xs.ravel() + 0.5) / sw * 2 - 1, (ys.ravel() + 0.5) / sh * 2 - 1, degree)
    b = small.ravel().astype(np.float64)
    k = max(3, int(0.3 * min(sh, sw)) | 1)
    closed = cv2.morphologyEx(
        small, cv2.MORPH_CLOSE, np.ones((k, k), np.uint8), borderType=cv2.BORDER_REPLICATE
    )
    # Large dark structures (the plate, dark to the border) fail the second test.
    narrow = (small >= 0.8 * closed).ravel()
    bright = b > DARK_STRUCTURE * np.percentile(b, 95)
    local = narrow & bright
    keep = local.copy()
    if keep.sum() < A.shape[1] * 3:
        keep = np.ones(b.size, bool)
    else:
        # A dark region that cannot be the plate (plate_components) is judged
        # again, against the backlight there rather than the brightest of the image.
        coef = _lstsq(A, b, keep)
        dark, _ = ndi.label(~bright.reshape(sh, sw), np.ones((3, 3)))
        plate = plate_components(dark)
        again = ((dark > 0) & ~np.isin(dark, plate)).ravel() & narrow
        local = keep = local | (again & (b > DARK_STRUCTURE * (A @ coef)))
    coef = np.zeros(A.shape[1])
    for _ in range(iterations):
        coef = _lstsq(A, b, keep)
        r = b - A @ coef
        sigma = 1.4826 * np.median(np.abs(r[keep] - np.median(r[keep]))) + 1e-6
        new_keep = local & (r > -np.maximum(2.5 * sigma, 0.05 * np.abs(A @ coef)))
        if new_keep.sum() < A.shape[1] * 3 or np.array_equal(new_keep, keep):
            break
        keep = new_keep
    # Evaluate at full resolution separably: the design is a sum of x^i y^j products.
    xf = ((np.arange(w) + 0.5) / w * 2 - 1).astype(np.float64)
    yf = ((np.arange(h) + 0.5) / h * 2 - 1).astype(np.float64)
    bg = np.zeros((h, w))
    k = 0
    for i in range(degree + 1):
        for j in range(degree + 1 - i):
            bg += coef[k] * np.outer(yf**j, xf**i)
            k += 1
    return bg.astype(np.float32)


def plate_components(comp: np.ndarray) -> np.ndarray:
    """The labels of (H, W) int ``comp`` (0: none) that can be the plate: a region
    reaching the bottom border, where the plate enters the view, or spanning the view
    from its left border to its right in its lower half (the plate seen from level or
    below, with backlight under it too; a dark band across the top of the view is not
    the plate, under the bubbles). Returns the sorted labels (int array)."""
    bottom = np.unique(comp[-1][comp[-1] > 0])
    left, right = comp[:, 0][comp[:, 0] > 0], comp[:, -1][comp[:, -1] > 0]
    across = np.intersect1d(left, right)
    if across.size:
        rows = ndi.mean(
            np.broadcast_to(np.arange(comp.shape[0])[:, None], comp.shape), comp, across
        )
        across = across[np.asarray(rows) >= 0.5 * (comp.shape[0] - 1)]
    return np.union1d(bottom, across)


def _fill_along_rows(band: np.ndarray, unknown: np.ndarray) -> np.ndarray:
    """``band`` (R, W) with its ``unknown`` ((R, W) bool) entries linearly interpolated
    along each row from the row's other finite entries (the nearest one beyond the
    last); a row with none keeps them."""
    out = np.array(band, np.float64)
    for r in np.flatnonzero(unknown.any(axis=1)):
        known = np.isfinite(out[r]) & ~unknown[r]
        if known.any():
            u = np.flatnonzero(known)
            out[r, unknown[r]] = np.interp(np.flatnonzero(unknown[r]), u, out[r, u])
    return out


def reference_frames(n: int, max_frames: int) -> np.ndarray:
    """Indices of the at most ``max_frames`` evenly spaced frames of ``n`` that the
    session's references are made of."""
    return np.unique(np.linspace(0, n - 1, min(n, int(max_frames))).round().astype(int))


def session_reference(
    frames: np.ndarray, percentile: float = 90.0, max_frames: int = 64
) -> np.ndarray:
    """(H, W) float32 reference image of a (T, H, W) frame stack: what stays put.

    The per-pixel ``percentile`` over at most ``max_frames`` evenly spaced frames:
    moving (dark) bubbles fall below it, the bright backlight and static structures
    such as the heated plate remain.
    """
    n = frames.shape[0]
    if n == 0:
        raise ValueError("empty frame stack")
    idx = reference_frames(n, max_frames)
    stack = np.stack([to_unit_float(frames[i]) for i in idx])
    return np.percentile(stack, percentile, axis=0).astype(np.float32)


def _row_weights(rows: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Linear interpolation between the rows of an n-row table at fractional ``rows``
    (any shape): ``(r0, r1, f)``, value = (1 − f)·T[r0] + f·T[r1], clamped to rows
    0 … n − 1."""
    r0 = np.clip(np.floor(rows).astype(int), 0, n - 1)
    return r0, np.minimum(r0 + 1, n - 1), np.clip(rows - r0, 0.0, 1.0)


def polyline_edge(
    edge: np.ndarray, window: int, tol_px: float, max_points: int = 96
) -> tuple[np.ndarray, np.ndarray]:
    """The static structure's upper edge without the dents of bubbles, corners kept.

    ``edge`` (W,): the edge's row in each column (the image height where a column has
    none). The plate's far edge, seen in perspective, is a polyline (a trapezoid's
    corner); a bubble sitting on it dents it, up or down, over less than half of
    ``window`` columns. A column is *on the edge* when it lies within ``tol_px`` rows
    of Siegel's repeated-median line (``scipy.stats.siegelslopes``, robust to up to
    half the points being outliers) of one of three windows of ``window`` columns:
    ending at it, centred on it, or starting at it, together with one of its
    neighbours. Near a corner one of the one-sided windows lies on one straight
    piece, so the corner is kept, where a running median would cut it; in a dent no
    window's line reaches it. Only windows wholly inside the image count, and only
    those whose line holds more than half of their columns (one across a corner is a
    compromise between two pieces). A column on the edge takes the value of the
    nearest line through it; dented columns take the edge linearly interpolated
    between the nearest columns on the edge (held constant beyond the outermost), or
    the higher of those two columns' lines extended under the dent where that is
    above the chord (a corner the dent hides: the plate's top face is convex).
    Lines are fitted on at most ``max_points`` columns of a window (evenly spaced).

    Returns ``(cleaned, on_edge)``: (W,) float64 rows and (W,) bool.
    """
    from scipy.stats import siegelslopes  # here: scipy.stats takes 0.7 s to import

    y = np.asarray(edge, np.float64)
    w = y.size
    n = max(3, min(int(window), w))
    x = np.arange(w, dtype=np.float64)
    step = max(1, int(np.ceil(n / max_points)))
    # Line of each whole window [s, s + n) inside the image (a window cut by the
    # image's side could be mostly dent); index s + n − 1, so that the windows
    # ending before column 0 or starting after w − n stay NaN.
    lines = np.full((w + n - 1, 2), np.nan)
    for s in range(w - n + 1):
        idx = np.arange(s, s + n)[::step]
        a, b = siegelslopes(y[idx], x[idx])
        # A window across a corner has no line through most of its columns.
        if np.mean(np.abs(a * x[idx] + b - y[idx]) <= tol_px) > 0.5:
            lines[s + n - 1] = a, b
    starts = np.stack([x - n + 1, x - n // 2, x]).astype(int) + n - 1  # (3, W)
    a, b = lines[starts, 0], lines[starts, 1]

    def near(shift: int) -> np.ndarray:
        # Whether column u + shift lies on the line of column u's window (3, W).
        u = np.arange(w) + shift
        inside = (u >= 0) & (u < w)
        u = np.clip(u, 0, w - 1)
        with np.errstate(invalid="ignore"):
            return (np.abs(a * x[u] + b - y[u]) <= tol_px) & inside

    # On a window's line together with a neighbour: a dent's side may cross the line
    # of the other piece, extended past the corner, in one column.
    ok = near(0) & (near(-1) | near(1))
    on = ok.any(axis=0)
    if not on.any():
        return y.copy(), on
    # The value of the nearest line through the column: sub-pixel, where the
    # staircase of a shallow slope or a slight bow steps by a row (near a corner the
    # other piece's line, extended, may pass within the tolerance too).
    best = np.argmin(np.where(ok, np.abs(a * x + b - y), np.inf), axis=0)
    la = np.take_along_axis(a, best[None], axis=0)[0]
    lb = np.take_along_axis(b, best[None], axis=0)[0]
    out = np.interp(x, x[on], (la * x + lb)[on])
    # A dent between two columns on the edge: the plate's top face projects to a convex
    # polygon, whose upper boundary (rows grow downwards) is the maximum of its pieces'
    # lines and lies on or above the chord. So the lines of the columns either side,
    # extended under the dent, give back a corner hidden there; the chord bounds them.
    idx = np.flatnonzero(on)
    for i0, i1 in zip(idx[:-1], idx[1:], strict=True):
        if i1 - i0 > 1:
            u = x[i0 + 1 : i1]
            ext = np.maximum(la[i0] * u + lb[i0], la[i1] * u + lb[i1])
            out[i0 + 1 : i1] = np.minimum(out[i0 + 1 : i1], ext)
    return out, on


def static_background(
    reference: np.ndarray,
    params: Mapping | None = None,
    plate_reference: np.ndarray | None = None,
    plate_unknown: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Background model of a session from its :func:`session_reference`.

    ``plate_reference`` (default: ``reference``) supplies the values on the plate: a
    per-pixel *median* there is not lifted by the bright cores of bubbles that sit
    at a nucleation site in a good part of the frames.

    The backlight is the robust polynomial fit of the reference. A static dark structure
    — the heated plate — is the part of the reference darker than
    ``(1 − static_dark_frac)`` × backlight that can be the plate (reaching the bottom
    border, or spanning the width: :func:`plate_components`) and larger than
    ``static_min_area_frac`` of the image. Its upper edge is taken per column and
    cleaned of the dents of bubbles sitting on it (which stay in the reference when
    nucleation never stops) by :func:`polyline_edge` over windows of
    ``static_notch_frac`` of the width, within ``static_edge_tol_px``.
    Inside the structure (and two rows above its edge, its blurred rim) the
    background is the reference itself, except where the reference departs from its
    running median *along* the edge by more than ``static_outlier_frac``: there a
    bubble sat at a nucleation site all along, and the median replaces it.
    ``plate_unknown`` ((H, W) bool): plate pixels whose value ``plate_reference`` does
    not know (covered in nearly every frame); each is interpolated along the edge from
    the known ones at the same depth below it.

    Returns ``background`` (H, W) float32 (polarity applied) and ``static`` (H, W) bool.
    """
    p = {**CLASSICAL_DEFAULTS, **(params or {})}
    ref = _polarised(reference, p)
    h, w = ref.shape
    light = estimate_background(ref, int(p["background_degree"]))
    static = np.zeros((h, w), bool)
    # Under a large dark structure the backlight is not seen and its polynomial is an
    # extrapolation, which can fall to zero or below there (then nothing is darker than
    # it): the test uses the backlight clamped to half its median.
    floor = 0.5 * float(np.median(light))
    dark = ref < (1.0 - p["static_dark_frac"]) * np.maximum(light, floor)
    comp, n = ndi.label(dark)
    if n == 0:
        return light, static
    sizes = ndi.sum_labels(np.ones_like(comp), comp, np.arange(1, n + 1))
    big = np.flatnonzero(sizes >= p["static_min_area_frac"] * comp.size) + 1
    keep = np.intersect1d(big, plate_components(comp))
    if keep.size == 0:
        return light, static
    s0 = np.isin(comp, keep)
    has = s0.any(axis=0)
    edge = np.where(has, np.argmax(s0, axis=0), h).astype(np.float64)
    win = max(3, (w // 6) | 1)
    # Bubbles on the plate dent its edge over at most their width, upwards (a dark
    # ring above the plate) or downwards (a bright core hiding its top rows): robust
    # lines over windows wider than twice the widest bubble remove both and keep the
    # corners of the plate seen in perspective.
    notch = max(3, int(p["static_notch_frac"] * w) | 1)
    # Two rows above the edge too: the blurred rim of the structure.
    top = np.maximum(polyline_edge(edge, notch, float(p["static_edge_tol_px"]))[0] - 2, 0.0)
    edge = np.round(top).astype(int)
    static = np.arange(h)[:, None] >= edge[None, :]
    # Unroll the structure along its sub-pixel edge: band[r, u] = ref[top(u) + r, u],
    # linear between rows. In the blurred rim one row is a third of the plate's
    # brightness: rows of the band that followed the edge's staircase to the nearest
    # pixel would mix offsets in the along-edge medians below.
    depth = h - int(np.floor(top.min()))
    vf = top[None, :] + np.arange(depth)[:, None]
    valid = vf <= h - 1
    v0, v1, frac = _row_weights(vf, h)
    uu = np.broadcast_to(np.arange(w)[None, :], vf.shape)
    pref = ref if plate_reference is None else _polarised(plate_reference, p)
    sampled = np.where(valid, (1 - frac) * pref[v0, uu] + frac * pref[v1, uu], np.nan)
    band = sampled
    if plate_unknown is not None:
        unknown = plate_unknown[v0, uu] | (plate_unknown[v1, uu] & (frac > 0))
        band = _fill_along_rows(band, valid & unknown)
    padded = np.pad(band, ((0, 0), (win // 2, win // 2)), constant_values=np.nan)
    windows = np.lib.stride_tricks.sliding_window_view(padded, win, axis=1)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        med = np.nanmedian(windows, axis=2)
    med = np.where(np.isfinite(med), med, band)
    # The reference is the background, except where it departs strongly from its
    # along-edge median: bubbles that never left the nucleation sites.
    outlier = np.abs(band - med) > p["static_outlier_frac"] * np.maximum(med, 1e-3)
    # Only departures reaching the edge, or holding a part brighter than the plate:
    # bubbles sit *on* the plate, and one seen in front of the plate's top shows a
    # bright core there, whereas the plate's own lower features (its black sides) are
    # dark and do not follow the edge.
    # A bubble's ring and core are separate departures: pieces within 2 px are one.
    grouped = ndi.binary_dilation(outlier, iterations=2)
    out_lab, n_out = ndi.label(grouped)
    if n_out:
        touching = np.unique(out_lab[:4][out_lab[:4] > 0])
        bright = band - med > p["static_outlier_frac"] * np.maximum(med, 1e-3)
        cored = np.unique(out_lab[bright & outlier & (out_lab > 0)])
        keep = np.isin(out_lab, touching)
        # A bubble in front of the plate: its whole disc, ring, core and what lies between.
        keep |= ndi.binary_fill_holes(np.isin(out_lab, cored)) & ~keep
        outlier = (outlier & np.isin(out_lab, touching)) | (keep & ~np.isin(out_lab, touching))
    outlier = ndi.binary_dilation(outlier, np.ones((3, 3), bool))
    # What the along-edge medians and the fill changed, back on the pixel grid: the
    # background is the reference plus that change, exactly the reference elsewhere.
    change = np.where(valid, np.where(outlier, med, band) - sampled, 0.0)
    r0, r1, s = _row_weights(np.arange(h)[:, None] - top[None, :], depth)
    cols = np.broadcast_to(np.arange(w)[None, :], (h, w))
    moved = (1 - s) * change[r0, cols] + s * change[r1, cols]
    bg = np.where(static, pref + moved, light)
    return bg.astype(np.float32), static


def uncovered_reference(
    frames: np.ndarray,
    covered: np.ndarray,
    percentile: float,
    max_frames: int,
    grow_px: int,
    min_free_frac: float,
) -> np.ndarray:
    """Per-pixel ``percentile`` of a (T, H, W) stack over the frames where no object
    covers the pixel.

    ``covered`` (T, H, W) bool marks the objects of a first segmentation; each frame's
    is grown by ``grow_px`` pixels (their blurred rims). The frames are those of
    :func:`session_reference` (:func:`reference_frames`).

    Returns (H, W) float32, NaN where fewer than ``min_free_frac`` of the frames, and
    fewer than 2, leave the pixel free.
    """
    n = frames.shape[0]
    if covered.shape != frames.shape[:3]:
        raise ValueError(f"covered is {covered.shape}, frames are {frames.shape[:3]}")
    idx = reference_frames(n, max_frames)
    grow = np.ones((3, 3), bool)
    stack = np.empty((len(idx), *frames.shape[1:3]), np.float32)
    for k, i in enumerate(idx):
        cov = np.asarray(covered[i], bool)
        if grow_px > 0 and cov.any():
            cov = ndi.binary_dilation(cov, grow, iterations=int(grow_px))
        stack[k] = np.where(cov, np.nan, to_unit_float(frames[i]))
    free = np.isfinite(stack).sum(axis=0)
    ok = free >= max(2, int(np.ceil(min_free_frac * len(idx))))
    out = np.full(frames.shape[1:3], np.nan, np.float32)
    if ok.any():
        out[ok] = nan_percentile(stack[:, ok], percentile)
    return out


def nan_percentile(values: np.ndarray, percentile: float) -> np.ndarray:
    """``np.nanpercentile(values, percentile, axis=0)`` (linear interpolation) of a
    (T, N) float array whose columns each hold at least one finite value, by one sort
    (NaN last) instead of numpy's per-column loop. Returns (N,) float64."""
    v = np.sort(np.where(np.isfinite(values), values, np.inf).astype(np.float64), axis=0)
    n = np.isfinite(v).sum(axis=0)
    pos = float(percentile) / 100.0 * (n - 1)
    lo = np.floor(pos).astype(np.int64)
    hi = np.minimum(lo + 1, n - 1)
    a = np.take_along_axis(v, lo[None], axis=0)[0]
    b = np.take_along_axis(v, hi[None], axis=0)[0]
    return a + (pos - lo) * (b - a)


def session_references(
    frames: np.ndarray, params: Mapping | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """The session's two (H, W) reference images (:func:`session_reference`): at
    ``reference_percentile`` and at ``plate_percentile``."""
    p = {**CLASSICAL_DEFAULTS, **(params or {})}
    n = int(p["reference_max_frames"])
    return (
        session_reference(frames, p["reference_percentile"], n),
        session_reference(frames, p["plate_percentile"], n),
    )


def plate_grow_px(shape: tuple[int, ...], params: Mapping | None = None) -> int:
    """Pixels the first pass's objects are grown by (``plate_grow_frac`` of the shorter
    side of a (…, H, W) ``shape``)."""
    p = {**CLASSICAL_DEFAULTS, **(params or {})}
    return int(round(float(p["plate_grow_frac"]) * min(shape[-2:])))


def plate_touched(covered: np.ndarray, static: np.ndarray, params: Mapping | None = None) -> bool:
    """Whether an object of ``covered`` ((T, H, W) bool), grown by :func:`plate_grow_px`,
    reaches the static structure ``static`` ((H, W) bool) in a frame the references use
    (:func:`session_reference`'s): only then does :func:`session_background` with
    ``covered`` differ from the one without."""
    p = {**CLASSICAL_DEFAULTS, **(params or {})}
    idx = reference_frames(covered.shape[0], p["reference_max_frames"])
    grow = plate_grow_px(covered.shape, p)
    near = (
        ndi.binary_dilation(static, np.ones((3, 3), bool), iterations=grow) if grow > 0 else static
    )
    return bool(np.any(np.asarray(covered)[idx] & near[None]))


def session_background(
    frames: np.ndarray,
    params: Mapping | None = None,
    covered: np.ndarray | None = None,
    references: tuple[np.ndarray, np.ndarray] | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """``(background, static)`` of a (T, H, W) session: :func:`static_background` of
    its reference (``reference_percentile``), plate values from ``plate_percentile``.

    ``covered`` ((T, H, W) bool, the objects a first segmentation found): the plate
    values are then the ``plate_percentile`` over the frames where no object covers the
    pixel (:func:`uncovered_reference`, ``plate_grow_frac`` of the shorter side around
    each object), where at least ``plate_free_frac`` of the frames do. A bubble that
    rises slowly in front of the plate covers its pixels in most frames, so the plain
    percentile keeps a ghost of it that hides its rim in every frame; where a bubble
    sits all along, the plain percentile and its along-edge test stay. ``references``:
    :func:`session_references` of these frames, when already computed."""
    p = {**CLASSICAL_DEFAULTS, **(params or {})}
    ref, plate = session_references(frames, p) if references is None else references
    if covered is None:
        return static_background(ref, p, plate)
    grow = plate_grow_px(frames.shape[:3], p)
    free_ref = uncovered_reference(
        frames, covered, p["plate_percentile"], p["reference_max_frames"], grow,
        float(p["plate_free_frac"]),
    )  # fmt: skip
    unknown = ~np.isfinite(free_ref)
    plate = np.where(unknown, plate, free_ref).astype(np.float32)
    return static_background(ref, p, plate, unknown)


def _polarised(image: np.ndarray, p: Mapping) -> np.ndarray:
    img = to_unit_float(image)
    if p["polarity"] == "bright":
        return 1.0 - img
    if p["polarity"] != "dark":
        raise ValueError(f"masks.classical.polarity must be dark or bright, not {p['polarity']!r}")
    return img


def relative_contrast(
    image: np.ndarray,
    params: Mapping | None = None,
    background: tuple[np.ndarray, np.ndarray] | None = None,
    signed: bool = False,
) -> np.ndarray:
    """(H, W) float32 relative darkness ``(background − image) / background`` in [0, 1].

    ``background`` is ``(background, static)`` from :func:`static_background`; without
    it the backlight is fitted on this frame alone. A per-frame gain (median ratio
    of image to background off the static structures) follows illumination flicker.
    With ``polarity: bright`` the image is inverted first (bright bubbles on dark).
    ``signed``: the contrast before folding and clipping (negative where brighter than
    the background), zero where the background is below ``background_floor``.
    """
    p = {**CLASSICAL_DEFAULTS, **(params or {})}
    img = _polarised(image, p)
    if background is None:
        bg = estimate_background(img, int(p["background_degree"]))
        static = np.zeros(img.shape, bool)
    else:
        bg, static = background
        if bg.shape != img.shape:
            raise ValueError(f"background is {bg.shape[::-1]} pixels, frame is {img.shape[::-1]}")
        free = ~static
        if free.any():
            bg = bg * float(np.median(img[free] / np.maximum(bg[free], 1e-3)))
    c = (bg - img) / np.maximum(bg, 1e-3)
    c[bg < p["background_floor"]] = 0.0
    c = c.astype(np.float32)
    return c if signed else fold_contrast(c, static)


def fold_contrast(signed: np.ndarray, static: np.ndarray | None) -> np.ndarray:
    """(H, W) float32 contrast in [0, 1] from :func:`relative_contrast`'s signed one: in
    front of a static dark structure (``static`` (H, W) bool) a bubble shows as a dark
    ring *and* a core brighter than the structure, so any departure from the reference
    counts there (its absolute value); elsewhere darkening only."""
    c = np.array(signed, dtype=np.float32)
    if static is not None:
        c[static] = np.abs(c[static])
    return np.clip(c, 0.0, 1.0)


def smoothed(contrast: np.ndarray, params: Mapping | None = None) -> np.ndarray:
    """(H, W) float32 contrast smoothed for detection (Gaussian, ``smooth_px``)."""
    p = {**CLASSICAL_DEFAULTS, **(params or {})}
    if p["smooth_px"] <= 0:
        return np.asarray(contrast, np.float32)
    return cv2.GaussianBlur(contrast, (0, 0), sigmaX=float(p["smooth_px"]))


def detection_contrast(
    signed: np.ndarray, static: np.ndarray | None, params: Mapping | None = None
) -> np.ndarray:
    """(H, W) float32 contrast that objects are detected on: the smoothed signed
    contrast (:func:`relative_contrast` with ``signed``), clipped to [0, 1], and in
    front of the static structure (``static`` (H, W) bool) its absolute value (a
    bubble's dark ring and bright core both depart from the plate). Smoothing before
    folding keeps camera noise, which folds into a positive bias, from adding up."""
    sm = smoothed(signed, params)
    out = np.clip(sm, 0.0, 1.0)
    if static is not None:
        out[static] = np.clip(np.abs(sm[static]), 0.0, 1.0)
    return out.astype(np.float32)


def contrast_noise(
    frames: np.ndarray,
    params: Mapping | None = None,
    background: tuple[np.ndarray, np.ndarray] | None = None,
) -> np.ndarray:
    """(H, W) float32 noise (standard deviation) of the smoothed signed contrast.

    Per pixel, the robust spread (1.4826 × median absolute value / √2) of the smoothed
    signed contrast's change between consecutive frames (at most
    ``reference_max_frames`` pairs, evenly spaced): a bubble crossing a pixel changes it
    in a few pairs only, and one that hardly moves changes it little, so the estimate
    is the camera's noise. A spatial median over ``noise_window_px`` steadies it. Zero
    for fewer than 2 frames.

    Args:
        frames: (T, H, W) session frames (any dtype :func:`to_unit_float` takes).
        params: overrides of :data:`CLASSICAL_DEFAULTS`.
        background: ``(background, static)`` as for :func:`relative_contrast`.
    """
    p = {**CLASSICAL_DEFAULTS, **(params or {})}
    n = frames.shape[0]
    if n < 2:
        return np.zeros(frames.shape[1:3], np.float32)
    starts = np.unique(np.linspace(0, n - 2, min(n - 1, int(p["reference_max_frames"]))).round())

    def sm(t: int) -> np.ndarray:
        return smoothed(relative_contrast(frames[t], p, background, signed=True), p)

    diffs, last, last_t = [], None, -1
    for t in starts.astype(int):
        a = last if last_t == t else sm(t)  # consecutive pairs share a frame
        last, last_t = sm(t + 1), t + 1
        diffs.append(np.abs(last - a))
    sigma = 1.4826 * np.median(np.stack(diffs), axis=0) / np.sqrt(2.0)
    win = int(p["noise_window_px"])
    if win > 1:
        sigma = ndi.median_filter(sigma, size=win, mode="nearest")
    return sigma.astype(np.float32)


def ring_hulls(
    comp: np.ndarray, static: np.ndarray, inside: float = 0.9
) -> tuple[np.ndarray, dict[int, np.ndarray]]:
    """Join each open ring in front of the plate to the core inside it.

    In front of the plate (``static``, (H, W) bool) a bubble is a dark ring around a
    bright core, both departures from the plate, split by the contrast's zero
    crossing. Where the plate's rim or camera noise leaves the ring open, filling its
    holes does not reach the core, and the bubble comes out as a ring and a core, or
    as arcs. A detected object touching the plate whose convex hull holds another
    object (at least ``inside`` of its pixels) takes that object in: it is one bubble,
    its region the hull.

    Args:
        comp: (H, W) int labels of the detected objects (0: none), from ``ndi.label``.
        static: (H, W) bool plate.

    Returns:
        the labels with each joined core relabelled to its ring and the hull given to
        the ring, and ``{ring label: (H, W) bool hull}`` of the rings that took a core.
    """
    comp = comp.copy()
    hulls: dict[int, np.ndarray] = {}
    boxes = ndi.find_objects(comp)
    sizes = np.bincount(comp.ravel(), minlength=len(boxes) + 1)
    # Largest first: a ring is larger than the core it holds.
    for k in sorted(range(1, len(boxes) + 1), key=lambda i: -sizes[i]):
        sl = boxes[k - 1]
        if sl is None or sizes[k] < 3 or not (static[sl] & (comp[sl] == k)).any():
            continue
        hull = np.zeros(comp.shape, bool)
        hull[sl] = convex_hull_image(comp[sl] == k)
        held = np.unique(comp[hull & (comp > 0) & (comp != k)])
        held = [j for j in held if (hull & (comp == j)).sum() >= inside * sizes[j]]
        if not held:
            continue
        comp[np.isin(comp, held) | (hull & (comp == 0))] = k
        hulls[k] = hull
        for j in held:
            boxes[j - 1] = None
            sizes[j] = 0
    return comp, hulls


#: Fewest pixels, and least share of its ring's, of a core that :func:`open_ring_core`
#: finds for :func:`foreground_mask` to take the ring's hull.
OPEN_RING_MIN_PX = 4
OPEN_RING_MIN_SHARE = 0.05


def open_ring_core(
    edge: np.ndarray,
    filled: np.ndarray,
    static: np.ndarray,
    at_border: tuple[bool, bool, bool, bool],
) -> np.ndarray:
    """(h, w) bool: the pixels off the plate that an object's ``edge`` (bool (h, w),
    a crop) encloses together with the plate (``static``, bool (h, w)) but not alone
    (``filled``: ``edge`` with its own holes filled, :func:`fill_holes_to_border`),
    within the edge's convex hull: the core of a bubble in front of the plate's edge
    whose dark ring the plate's low contrast left open (``at_border``: as for
    :func:`fill_holes_to_border`)."""
    core = fill_holes_to_border(edge | static, at_border) & ~filled & ~static
    return core & convex_hull_image(edge) if core.any() else core


def fill_holes_to_border(mask: np.ndarray, at_border: tuple[bool, bool, bool, bool]) -> np.ndarray:
    """``mask`` (bool (h, w), a crop of one object) with its holes filled, the crop's
    sides flagged in ``at_border`` (top, bottom, left, right: the image's border)
    counted as closed: a backlit bubble's bright core that the frame cuts open is filled
    as well, where ``ndi.binary_fill_holes`` leaves it open to the border."""
    pads = [(int(at_border[0]), int(at_border[1])), (int(at_border[2]), int(at_border[3]))]
    big = np.pad(mask, pads, constant_values=True)
    filled = ndi.binary_fill_holes(big)
    return filled[
        pads[0][0] : filled.shape[0] - pads[0][1], pads[1][0] : filled.shape[1] - pads[1][1]
    ]


def outline_in_front(
    piece: np.ndarray,
    free: np.ndarray,
    signed: np.ndarray,
    static: np.ndarray,
    params: Mapping | None = None,
    noise: np.ndarray | None = None,
) -> np.ndarray:
    """(H, W) bool ``piece`` grown, in front of the plate, to its outline.

    :func:`foreground_mask` puts a bubble's edge there at ``static_edge`` of relative
    contrast. A small bubble's dark rim is thin, and the lens's blur lowers it to
    little more than 0.1 above the plate: that edge keeps its bright core and little
    else. Here the edge is ``edge_frac`` of the rim's own darkness (the 95th
    percentile of ``signed`` (H, W), :func:`relative_contrast` with ``signed``, over
    the piece and 2 px about it in front of the plate, ``static`` (H, W) bool), where
    that is lower than ``static_edge``, never below ``threshold_low`` nor
    ``noise_low`` × ``noise`` ((H, W), :func:`contrast_noise`). The piece takes the
    pixels darker than the plate past that edge (its rim; a speck of the plate's edge,
    brighter than the plate, has none), ``free`` ((H, W) bool: no other instance's) and
    no farther from it than its own equivalent radius (at least 2 px: a bubble's bright
    core is at least half its radius), closed by ``static_close_px`` and its holes
    filled as there, where joined to it; it never loses one.
    """
    p = {**CLASSICAL_DEFAULTS, **(params or {})}
    if not piece.any():
        return piece.copy()
    r_close = int(p["static_close_px"])
    # The core is at least half the bubble's radius: the piece grows by at most its own.
    reach = max(2, int(round(np.sqrt(piece.sum() / np.pi))))
    pad = reach + r_close
    ys, xs = np.nonzero(piece)
    sl = (
        slice(max(ys.min() - pad, 0), ys.max() + pad + 1),
        slice(max(xs.min() - pad, 0), xs.max() + pad + 1),
    )
    own, st = piece[sl], static[sl]
    if (own & st).sum() < 4:
        return piece.copy()
    grow = np.ones((3, 3), bool)
    ring = ndi.binary_dilation(own, grow, iterations=2) & st
    region = (ndi.binary_dilation(own, grow, iterations=reach) & free[sl]) | own
    sg = signed[sl]
    rim_peak = float(np.percentile(sg[ring], 95))
    low = np.full(own.shape, max(p["edge_frac"] * rim_peak, p["threshold_low"]), np.float32)
    if noise is not None:
        low = np.maximum(low, p["noise_low"] * noise[sl])
    edge = own | (st & (sg >= np.minimum(low, p["static_edge"])) & region)
    if r_close > 0:
        # The rim and the core meet across the contrast's zero crossing.
        yy, xx = np.mgrid[-r_close : r_close + 1, -r_close : r_close + 1]
        closed = ndi.binary_closing(np.pad(edge, r_close), xx**2 + yy**2 <= r_close**2)
        edge = closed[r_close:-r_close, r_close:-r_close] & region
    whole = ndi.binary_fill_holes(edge) & region
    out = piece.copy()
    out[sl] |= ndi.binary_propagation(own, grow, mask=whole | own)
    return out


def foreground_mask(
    contrast: np.ndarray,
    params: Mapping | None = None,
    static: np.ndarray | None = None,
    return_cores: bool = False,
    noise: np.ndarray | None = None,
    detect: np.ndarray | None = None,
):
    """(H, W) bool bubble pixels from the relative contrast.

    Objects are *detected* by hysteresis on the smoothed contrast; each object's *edge*
    is then placed where the unsmoothed contrast crosses ``edge_frac`` of the object's
    own peak (95th percentile, off the static structure), which follows the true outline
    of a blurred shadow whatever its darkness. In front of the static structure
    (``static``, (H, W) bool), where a bubble's contrast against the dim plate is lower,
    ``static_edge`` is the edge instead, and an object there is closed (a disc of
    ``static_close_px``) before its holes are filled; with ``static_ring_hull`` a ring
    left open there (:func:`ring_hulls`, :func:`open_ring_core`) is the hull of its
    edge. Holes (bright cores) are filled,
    and cores the image's border cuts open (:func:`fill_holes_to_border`); with
    ``return_cores`` the filled holes are returned too, as a second (H, W) bool array:
    one core per bubble that shows one. ``noise`` ((H, W), the detection contrast's
    standard deviation, :func:`contrast_noise`) raises the two hysteresis thresholds to
    ``noise_low`` and ``noise_high`` times it where that is higher. ``detect``: the (H,
    W) image to detect on (:func:`detection_contrast`); default the smoothed
    ``contrast``.
    """
    p = {**CLASSICAL_DEFAULTS, **(params or {})}
    sm = smoothed(contrast, p) if detect is None else detect
    if noise is None:
        det = apply_hysteresis_threshold(sm, p["threshold_low"], p["threshold_high"])
    else:
        low = sm > np.maximum(p["threshold_low"], p["noise_low"] * noise)
        high = sm > np.maximum(p["threshold_high"], p["noise_high"] * noise)
        comp_low, n_low = ndi.label(low)
        seeds = np.zeros(n_low + 1, bool)
        seeds[np.unique(comp_low[high])] = True
        seeds[0] = False
        det = seeds[comp_low]
    det = ndi.binary_fill_holes(det)
    comp, n = ndi.label(det)
    hulls = {}
    if static is not None and p["static_ring_hull"]:
        comp, hulls = ring_hulls(comp, static)
    fg = np.zeros_like(det)
    cores = np.zeros_like(det)
    grow = np.ones((3, 3), bool)
    r_close = int(p["static_close_px"])
    close = None
    if static is not None and r_close > 0:
        yy, xx = np.mgrid[-r_close : r_close + 1, -r_close : r_close + 1]
        close = xx**2 + yy**2 <= r_close**2
    h, w = comp.shape
    for k, sl in enumerate(ndi.find_objects(comp), start=1):
        if sl is None:
            continue
        # Work in the object's box grown by 2 px, so a refined edge may move outwards.
        sl = tuple(slice(max(s.start - 2, 0), s.stop + 2) for s in sl)
        own = comp[sl] == k
        region = ndi.binary_dilation(own, grow, iterations=2) & ((comp[sl] == 0) | own)
        c = contrast[sl]
        st = static[sl] if static is not None else np.zeros(own.shape, bool)
        free = own & ~st
        peak = np.percentile(c[free] if free.sum() >= 4 else c[own], 95)
        edge = ((c >= p["edge_frac"] * peak) | (st & (c >= p["static_edge"]))) & region
        if close is not None and (own & st).any():
            # In front of the plate a bubble's dark rim and bright core are split by
            # the contrast's zero crossing, and its rim is faint where it meets the
            # plate: closed, the rim is one ring around one body.
            closed = ndi.binary_closing(np.pad(edge, r_close), close)
            edge = closed[r_close:-r_close, r_close:-r_close] & region
        # A bubble leaving the frame: its core, open to the border, is filled too (left
        # open, the ring's two arms were split into two bubbles by the watershed).
        at_border = (sl[0].start == 0, sl[0].stop >= h, sl[1].start == 0, sl[1].stop >= w)
        filled = fill_holes_to_border(edge, at_border)
        if k in hulls and (edge & hulls[k][sl]).sum() >= 3:
            # An open ring around its core: the outline is the hull of the ring's edge.
            filled = convex_hull_image(edge & hulls[k][sl])
        elif p["static_ring_hull"] and (own & st).any() and edge.sum() >= 3:
            # A ring left open where it meets the plate, around a core seen against the
            # backlight that nothing detected: the core is a hole of the ring and the
            # plate together, not of the ring; the outline is the hull of the ring.
            core = open_ring_core(edge, filled, st, at_border)
            if core.sum() >= max(OPEN_RING_MIN_PX, OPEN_RING_MIN_SHARE * edge.sum()) and (
                (filled & ~edge).sum() < core.sum()
            ):
                filled = convex_hull_image(edge) | filled
        fg[sl] |= filled
        cores[sl] |= filled & ~edge
    fg = ndi.binary_opening(fg, structure=np.ones((2, 2), bool))
    return (fg, cores & fg) if return_cores else fg


def _neck_widths(labels: np.ndarray, dist: np.ndarray) -> dict[tuple[int, int], float]:
    """Widest distance-transform value along each shared boundary of two labels (> 0)."""
    necks: dict[tuple[int, int], float] = {}
    for a, b, da, db in (
        (labels[:, :-1], labels[:, 1:], dist[:, :-1], dist[:, 1:]),
        (labels[:-1, :], labels[1:, :], dist[:-1, :], dist[1:, :]),
    ):
        sel = (a != b) & (a > 0) & (b > 0)
        if not sel.any():
            continue
        la, lb = a[sel], b[sel]
        w = np.minimum(da[sel], db[sel])
        lo, hi = np.minimum(la, lb), np.maximum(la, lb)
        for x, y, v in zip(lo.tolist(), hi.tolist(), w.tolist(), strict=True):
            key = (x, y)
            if v > necks.get(key, -1.0):
                necks[key] = v
    return necks


def split_touching(
    fg: np.ndarray, params: Mapping | None = None, cores: np.ndarray | None = None
) -> np.ndarray:
    """Split touching bubbles of a (H, W) bool mask → (H, W) int32 labels 1..n, 0 outside.

    Watershed of the negated Euclidean distance transform from its local maxima;
    adjacent pieces whose neck (largest distance on their shared boundary) is wider
    than ``split_neck_ratio`` × the smaller piece's peak distance are merged back.
    A component holding two or more bright ``cores`` (shadowgraph: one per bubble)
    is instead split by a watershed from those cores, however wide the neck.
    """
    p = {**CLASSICAL_DEFAULTS, **(params or {})}
    comp, n = ndi.label(fg)
    if n == 0:
        return comp.astype(np.int32)
    dist = ndi.distance_transform_edt(fg).astype(np.float32)
    min_d = max(1, int(round(p["split_min_distance_frac"] * min(fg.shape))))
    peaks = peak_local_max(dist, min_distance=min_d, labels=comp, exclude_border=False)
    markers = np.zeros(fg.shape, np.int32)
    markers[tuple(peaks.T)] = np.arange(1, len(peaks) + 1)
    # Components without a peak (flat plateaus) still need a seed.
    seeded = np.zeros(n + 1, bool)
    seeded[comp[markers > 0]] = True
    nxt = len(peaks) + 1
    for k in np.flatnonzero(~seeded[1:]) + 1:
        idx = np.unravel_index(np.argmax(np.where(comp == k, dist, -1)), fg.shape)
        markers[idx] = nxt
        nxt += 1
    ws = watershed(-dist, markers, mask=fg).astype(np.int32)
    nlab = int(ws.max())
    peak = ndi.maximum(dist, ws, index=np.arange(1, nlab + 1))
    parent = np.arange(nlab + 1)

    def find(i: int) -> int:
        while parent[i] != i:
            parent[i] = parent[parent[i]]
            i = parent[i]
        return i

    necks = _neck_widths(ws, dist)
    # Merge the widest necks first so chains of wobbly pieces collapse together.
    for (a, b), w in sorted(necks.items(), key=lambda kv: -kv[1]):
        if w > p["split_neck_ratio"] * min(peak[a - 1], peak[b - 1]):
            ra, rb = find(a), find(b)
            if ra != rb:
                parent[max(ra, rb)] = min(ra, rb)
    roots = np.array([find(i) for i in range(nlab + 1)])
    _, relabel = np.unique(roots, return_inverse=True)
    out = relabel[ws].astype(np.int32)
    if cores is not None and cores.any():
        core_lab, n_core = ndi.label(cores & fg)
        sizes = ndi.sum_labels(np.ones_like(core_lab), core_lab, np.arange(1, n_core + 1))
        core_lab[np.isin(core_lab, np.flatnonzero(sizes < 2) + 1)] = 0
        per_comp = ndi.labeled_comprehension(
            core_lab, comp, np.arange(1, n + 1), lambda v: len(np.unique(v[v > 0])), int, 0
        )
        nxt = int(out.max()) + 1
        for k in np.flatnonzero(per_comp >= 2) + 1:
            m = comp == k
            ws_k = watershed(-dist, np.where(m, core_lab, 0), mask=m)
            for j in np.unique(ws_k[m]):
                out[m & (ws_k == j)] = nxt
                nxt += 1
        _, inv = np.unique(out, return_inverse=True)
        out = inv.reshape(out.shape).astype(np.int32)
    return out


def segment_frame(
    image: np.ndarray,
    params: Mapping | None = None,
    background: tuple[np.ndarray, np.ndarray] | None = None,
    noise: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Segment the bubbles of one frame.

    Args:
        image: (H, W) frame, float in [0, 1] or integer.
        params: overrides of :data:`CLASSICAL_DEFAULTS`.
        background: ``(background, static)`` of the session
            (:func:`static_background`); fitted on the frame alone when ``None``.
        noise: (H, W) noise of the smoothed contrast (:func:`contrast_noise`), which
            raises the detection thresholds; ``None``: the fixed thresholds only.

    Returns:
        labels: (H, W) int32, −1 background, 0..n−1 instance index (largest first);
        scores: (n,) float32 confidence, the mean relative contrast inside each instance.
    """
    p = {**CLASSICAL_DEFAULTS, **(params or {})}
    static = None if background is None else background[1]
    signed = relative_contrast(image, p, background, signed=True)
    contrast = fold_contrast(signed, static)
    detect = None if noise is None else detection_contrast(signed, static, p)
    fg, cores = foreground_mask(
        contrast,
        p,
        None if background is None else background[1],
        return_cores=True,
        noise=noise,
        detect=detect,
    )
    if background is not None:
        # In front of the plate a bubble's core is not a clean hole in its ring.
        cores &= ~background[1]
    lab = split_touching(fg, p, cores)
    n = int(lab.max())
    if n == 0:
        return np.full(lab.shape, -1, np.int32), np.zeros(0, np.float32)
    idx = np.arange(1, n + 1)
    area = ndi.sum_labels(np.ones_like(lab), lab, idx)
    min_area = max(6.0, p["min_area_frac"] * lab.size)
    keep = idx[area >= min_area]
    keep = keep[np.argsort(-area[keep - 1], kind="stable")]
    lut = np.full(n + 1, -1, np.int32)
    lut[keep] = np.arange(len(keep), dtype=np.int32)
    labels = lut[lab]
    scores = ndi.mean(contrast, lab, keep).astype(np.float32) if len(keep) else np.zeros(0)
    return labels, np.asarray(scores, np.float32)
