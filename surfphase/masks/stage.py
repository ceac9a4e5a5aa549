"""The ``mask`` stage of one session: segment every frame, associate, write outputs.

Input (the output of ``ingest``), a folder ``INGEST`` with:

* ``<cam>.npy`` — frames × H × W stack (float32 in [0, 1] or uint8/uint16);
* ``cameras.json`` — the cameras of those undistorted frames;
* ``meta.json`` — ``session``, ``fps``, ``frames``, ``cameras`` (camera order).

Outputs in ``OUT``:

* ``<cam>_labels.npy`` — int32 frames × H × W, −1 background, 0 the nucleation
  region at the heated plate (its pieces grown to their outline in front of the plate
  after the association, :func:`grown_nucleation`), ≥ 1 a bubble id shared by all
  views and frames;
* ``instances.csv`` — ``frame, camera, bubble, area, cx, cy, x0, y0, x1, y1, score``
  (pixels; ``score`` is the backend's confidence);
* ``events.csv`` — ``frame, camera, event, parents, children`` (merge, split, detach);
* ``anchors.csv`` — ``frame, bubble, x, y, z, reproj_px, size_ratio, r_m, cut, low,
  visible``: each bubble's centre triangulated from its sub-pixel silhouette centroids
  in the first two views (m, lab frame; :mod:`surfphase.masks.anchors`; ``cut``: a
  view's silhouette was cut by its border and its centre is that of the ellipse fitted
  to the visible outline; ``visible``: the least share of a fitted silhouette inside
  its view), where the views agree. Where they do
  not, the bubble is removed from that frame's masks (``dropped_inconsistent`` in
  ``masks.json``).

With ``INGEST/native/`` (``ingest: native_masks``), the frames before downscaling are
segmented and associated; the label stacks and ``instances.csv`` are then downscaled to
``INGEST``'s frames, and ``anchors.csv`` keeps the native resolution.
* ``overlays/frame_XXXXX.png`` — a few frames, views side by side;
* ``masks.json`` — session, backend, parameters used, counts.

Every file is written under a temporary name and renamed, and the outputs are only
moved into ``OUT`` once all of them are complete. The input is read by
:func:`surfphase.folders.ingest.read_ingest`, the outputs written by
:func:`surfphase.folders.masks.write_masks`.
"""

from __future__ import annotations

import time
import warnings
from collections.abc import Callable, Mapping, Sequence
from functools import partial
from pathlib import Path

import numpy as np
import pandas as pd
from scipy import ndimage as ndi

from surfphase.folders.frames import unit_grey
from surfphase.folders.ingest import read_ingest, stack_path
from surfphase.folders.masks import write_masks
from surfphase.masks import anchors, classical
from surfphase.masks.associate import associate
from surfphase.masks.overlay import overlay_frame
from surfphase.masks.params import DEFAULTS
from surfphase.settings import check_keys

#: The columns of ``anchors.csv``: :func:`frame_anchors`' table less ``consistent``
#: (only consistent rows are written).
ANCHOR_FILE_COLUMNS = [
    *(k for k in anchors.ANCHOR_COLUMNS if k != "consistent"), "low", "visible", "continued"
]  # fmt: skip


def merge_params(params: Mapping | None) -> dict:
    """:data:`DEFAULTS` updated by ``params`` (one level deep for the nested sections).

    Unknown keys are an error, so a typo in config.yaml does not go unnoticed.
    """
    check_keys(DEFAULTS, params, "masks")
    out = {k: (dict(v) if isinstance(v, dict) else v) for k, v in DEFAULTS.items()}
    for k, v in (params or {}).items():
        if isinstance(out[k], dict):
            if not isinstance(v, Mapping):
                raise ValueError(f"masks.{k} must be a mapping, not {v!r}")
            out[k].update(v)
        else:
            out[k] = v
    if out["backend"] not in ("classical", "sam"):
        raise ValueError(f"masks.backend must be classical or sam, not {out['backend']!r}")
    return out


def frame_spans(stack: np.ndarray, max_pixels: int = 65536) -> np.ndarray:
    """(T, 2) 0.1 and 99.9 percentiles of each frame's intensity, in [0, 1] of full scale.

    Computed on an evenly strided subset of about ``max_pixels`` pixels per frame.
    """
    t_n, h, w = stack.shape[:3]
    step = max(1, int(np.ceil(np.sqrt(h * w / max_pixels))))
    out = np.empty((t_n, 2), np.float64)
    for t in range(t_n):
        img = unit_grey(stack[t][::step, ::step])
        out[t] = np.percentile(img, [0.1, 99.9])
    return out


def _where(meta: Mapping, ingest_dir: Path, name: str) -> str:
    """The camera's video and frame stack, for messages."""
    cam = (meta.get("cameras") or {}).get(name) if isinstance(meta.get("cameras"), dict) else None
    stack = stack_path(ingest_dir, name)
    return f"video {cam['source']}, frames {stack}" if cam and cam.get("source") else str(stack)


def _frame_list(frames: np.ndarray, most: int = 10) -> str:
    shown = ", ".join(str(int(t)) for t in frames[:most])
    return shown + (f", … ({len(frames)} frames)" if len(frames) > most else "")


def check_dynamic_range(
    meta: Mapping, ingest_dir: Path, stacks: Mapping[str, np.ndarray], min_range: float
) -> list[str]:
    """Stop on a camera whose every frame is blank; warn about blank frames.

    A frame is blank when its intensities (:func:`frame_spans`) span less than
    ``min_range`` of the full scale. Returns the warnings (also issued with
    :func:`warnings.warn`); raises ValueError naming session, camera and files.
    """
    session = meta.get("session", Path(ingest_dir).name)
    notes = []
    for name, st in stacks.items():
        spans = frame_spans(st)
        blank = np.flatnonzero(spans[:, 1] - spans[:, 0] < min_range)
        if len(blank) == len(st):
            lo, hi = spans[:, 0].min(), spans[:, 1].max()
            kind = "black" if hi < 0.5 else "saturated" if lo > 0.5 else "flat"
            raise ValueError(
                f"session {session}: camera {name}: every one of its {len(st)} frames is blank "
                f"({kind}: intensities {lo:.3f} to {hi:.3f} of full scale, a span below "
                f"masks.min_dynamic_range {min_range}) — check the video, its exposure and "
                f"the lens ({_where(meta, ingest_dir, name)})"
            )
        if len(blank):
            notes.append(
                f"session {session}: camera {name}: {len(blank)} of {len(st)} frames are "
                f"blank (span below {min_range} of full scale), no bubble can be found there: "
                f"frames {_frame_list(blank)} ({_where(meta, ingest_dir, name)})"
            )
    for note in notes:
        warnings.warn(note, stacklevel=2)
    return notes


def check_bubbles_found(meta: Mapping, ingest_dir: Path, instances, cameras: Sequence[str]) -> None:
    """Stop when a camera has no bubble (id >= 1) in any frame of the session: the fit
    needs each bubble in two views. Raises ValueError naming session, camera and files."""
    session = meta.get("session", Path(ingest_dir).name)
    found = set(instances.loc[instances.bubble > 0, "camera"])
    for name in cameras:
        if name not in found:
            raise ValueError(
                f"session {session}: camera {name}: no bubble found in any frame "
                f"(the other cameras: {', '.join(sorted(found)) or 'none either'}) — check "
                f"the video and the masks thresholds ({_where(meta, ingest_dir, name)})"
            )


def check_centres_found(
    meta: Mapping, ingest_dir: Path, instances: pd.DataFrame, table: pd.DataFrame,
    cameras: Sequence[str],
) -> list[str]:  # fmt: skip
    """Warn about the bubbles both views see that get no centre in any frame: the two
    views never agree on them (``table``: the consistent anchors), so ``bubbles.csv``
    will not report them. ``instances``: the association's, before any was dropped.
    Returns the warnings (also issued with :func:`warnings.warn`)."""
    session = meta.get("session", Path(ingest_dir).name)
    seen = [set(instances.loc[(instances.camera == c) & (instances.bubble > 0), "bubble"])
            for c in cameras[:2]]  # fmt: skip
    if len(seen) < 2:
        return []
    lost = sorted((seen[0] & seen[1]) - set(table["bubble"].astype(int)))
    if not lost:
        return []
    what = "no bubble will be reported" if table.empty else "bubbles.csv leaves it out"
    if len(lost) > 1 and not table.empty:
        what = "bubbles.csv leaves them out"
    note = (
        f"session {session}: {'bubbles' if len(lost) > 1 else 'bubble'} "
        f"{', '.join(map(str, lost))} {'are' if len(lost) > 1 else 'is'} seen by cameras "
        f"{cameras[0]} and {cameras[1]} but in no frame do the two views agree on their "
        f"centre (sizes or positions differ: one view may see two bubbles as one, or a "
        f"bubble the other does not); {what} — see the mask overlays "
        f"({_where(meta, ingest_dir, cameras[0])})"
    )
    warnings.warn(note, stacklevel=2)
    return [note]


def segment_stack(
    stack: np.ndarray, params: Mapping, backend=None
) -> tuple[np.ndarray, list, tuple[np.ndarray, np.ndarray]]:
    """Segment every frame of a (T, H, W) stack; with the classical backend and
    ``classical: plate_refine``, a second time on the plate's background from the frames
    the first pass leaves free, when a first-pass object reaches the plate.

    Returns (T, H, W) int32 labels, per-frame scores, and the session's background
    model ``(background, static)`` (:func:`surfphase.masks.classical.session_background`;
    ``static`` is the (H, W) bool image of the heated plate).
    """
    t_n, h, w = stack.shape[:3]
    labels = np.full((t_n, h, w), -1, np.int32)
    scores = []
    cp = params["classical"]
    refs = classical.session_references(stack, cp)
    bg = classical.session_background(stack, cp, references=refs)
    if params["backend"] == "classical":

        def segment_all(bg: tuple[np.ndarray, np.ndarray]) -> list:
            noise = classical.contrast_noise(stack, cp, bg)
            out = []
            for t in range(t_n):
                labels[t], s = classical.segment_frame(stack[t], cp, bg, noise)
                out.append(s)
            return out

        scores = segment_all(bg)
        cov = labels >= 0
        if cp["plate_refine"] and classical.plate_touched(cov, bg[1], cp):
            # Second pass: the plate's values from the frames the first leaves it free.
            bg = classical.session_background(stack, cp, covered=cov, references=refs)
            scores = segment_all(bg)
    else:
        for t in range(t_n):
            labels[t], s = backend.generate(unit_grey(stack[t]), params["sam"])
            scores.append(s)
    return labels, scores, bg


def frame_anchors(
    stacks: Mapping[str, np.ndarray],
    labels: Mapping[str, np.ndarray],
    backgrounds: Mapping[str, tuple],
    cameras: Mapping[str, object],
    frames: np.ndarray,
    params: Mapping,
    young: Mapping[int, set[int]] | None = None,
    related: set[frozenset[int]] = frozenset(),
    fps: float | None = None,
) -> pd.DataFrame:
    """The triangulated centres (:func:`surfphase.masks.anchors.anchor_table`) of the
    first two views' bubbles, from their sub-pixel silhouette centroids; a silhouette
    that touches a view's border has its centre and full area from the ellipse fitted to
    its visible outline (:func:`surfphase.masks.anchors.cut_centres`) when at least
    ``anchors: min_visible`` of it is in the frame, else from the shape its track shows
    whole in another frame (:func:`surfphase.masks.anchors.tracked_cut_centres`,
    ``min_visible_tracked``), else from the sphere both views' outlines agree on
    (:func:`sphere_cut_centres`), and none in that frame otherwise. Bubbles one view
    sees apart and the other fuses into one silhouette, or into touching ones with one in
    front, get their circles there from its outline (:func:`occluded_centres`; not two that a merge joins, ``related``:
    :func:`merge_relatives`), and that silhouette is split between them. The ids of
    ``young`` (frame position → young merged bubbles, :func:`young_merged`) take the
    centroid of their silhouette's solid of revolution
    (:func:`surfphase.masks.anchors.lobe_centroids`). A bubble leaving or entering the
    frame past its last or first centre has it continued along its track
    (:func:`surfphase.masks.anchors.continued_centres`, ``continue_s``; with ``fps``),
    and one the border cuts where it still has none gets the centre of the moving sphere
    of its outlines (:func:`surfphase.masks.anchors.sphere_track_centres`,
    ``sphere_track``): those rows have ``continued`` True."""
    names = list(stacks)[:2]
    cp, ap = params["classical"], params["anchors"]
    cents, cuts = [], []
    for c in names:
        plate = backgrounds[c][1]  # the plate's image: its own edge darkness
        per, per_cut = [], []
        missing: dict[int, set[int]] = {}
        for t in range(stacks[c].shape[0]):
            con = classical.relative_contrast(stacks[c][t], cp, backgrounds[c])
            cen = anchors.coverage_centroids(con, labels[c][t], int(ap["ring_px"]), plate)
            if young and young.get(t):
                cen.update(
                    anchors.lobe_centroids(con, labels[c][t], young[t], int(ap["ring_px"]), plate)
                )
            cut = anchors.border_ids(labels[c][t])  # silhouettes the frame may cut
            fits = anchors.cut_centres(
                con, labels[c][t], cut - {0}, int(ap["ring_px"]),
                min_visible=float(ap["min_visible"]),
                max_aspect=float(ap["max_cut_aspect"]),
                max_area_error=float(ap["max_cut_area_error"]),
            )  # fmt: skip
            per.append({**{b: v for b, v in cen.items() if b not in cut}, **fits})
            per_cut.append(set(fits))
            missing[t] = cut - {0} - set(fits)
        if float(ap["min_visible_tracked"]) <= 1.0 and any(missing.values()):

            def contrast_at(t: int, c: str = c) -> np.ndarray:
                return classical.relative_contrast(stacks[c][t], cp, backgrounds[c])

            tracked = anchors.tracked_cut_centres(
                contrast_at, labels[c], {t: m for t, m in missing.items() if m},
                int(ap["ring_px"]), float(ap["min_visible_tracked"]),
                float(ap["max_shape_rms"]),
            )  # fmt: skip
            for t, fits in tracked.items():
                per[t].update(fits)
                per_cut[t] |= set(fits)
        cents.append(per)
        cuts.append(per_cut)
    cams = [cameras[c].undistorted() for c in names]
    split: list[tuple[str, int]] = []
    attached: list = []
    if ap["occlusion"] and len(names) == 2:
        split = occluded_centres(
            stacks, labels, backgrounds, cams, cents, cuts, params, related, attached
        )
    if float(ap["min_visible_sphere"]) <= 1.0 and len(names) == 2:
        sphere_cut_centres(stacks, labels, backgrounds, cams, cents, cuts, params)
    table = anchors.anchor_table(cams, cents, frames, ap, cuts, young)
    table["low"] = anchors.low_bottoms(
        table,
        cams,
        [labels[c] for c in names],
        frames,
        float(params["associate"]["nucleation_height"]),
    )
    table["visible"] = anchors.visible_shares(
        table, cents, cuts, [labels[c] for c in names], frames
    )
    table["continued"] = False
    if fps and float(ap["continue_s"]) > 0 and len(names) == 2:
        more = anchors.continued_centres(
            table, cams, [labels[c] for c in names], frames, float(fps), float(ap["continue_s"])
        )
        table = _with_continued(table, more)
    if fps and ap["sphere_track"] and len(names) == 2:
        outline = _outline_reader(stacks, labels, backgrounds, params)
        more = anchors.sphere_track_centres(
            table, cams, [labels[c] for c in names], outline, frames, float(fps),
            float(ap["continue_s"]), float(ap["max_sphere_rms"]), float(ap["min_visible_sphere"]),
        )  # fmt: skip
        table = _with_continued(table, more)
    table.attrs["split"] = split
    table.attrs["attached"] = [
        {"frame": int(frames[k]), "camera": c, "x": float(X[0]), "y": float(X[1]),
         "z": float(X[2]), "r_m": r}
        for c, k, X, r in attached
    ]  # fmt: skip
    return table


def _with_continued(table: pd.DataFrame, more: pd.DataFrame) -> pd.DataFrame:
    """``table`` with the rows ``more`` (continued centres: ``low`` False, ``continued``
    True), in frame then bubble order."""
    if not len(more):
        return table
    more = more.assign(low=False, continued=True)
    table = pd.concat([table, more[table.columns]], ignore_index=True)
    return table.sort_values(["frame", "bubble"], kind="stable").reset_index(drop=True)


def _epipolar_hits(cam_u, cam_v, centre: tuple, lab: np.ndarray, reach: float = 4.0) -> set[int]:
    """Region ids (≥ 1) of the view's (H, W) labels ``lab`` that the ray of ``centre``
    ((u, v, …) pixels of ``cam_u``) crosses, seen by ``cam_v``: its points from 1/reach to
    reach times the distance of the lab origin, projected."""
    d = cam_u.R.T @ np.linalg.solve(cam_u.K, np.array([centre[0], centre[1], 1.0]))
    d /= np.linalg.norm(d)
    s0 = float(np.linalg.norm(cam_u.center))
    X = cam_u.center[None] + np.geomspace(s0 / reach, s0 * reach, 4000)[:, None] * d[None]
    X = X[cam_v.world_to_camera(X)[:, 2] > 0]
    uv = np.rint(cam_v.project(X, distort=False)).astype(int)
    h, w = lab.shape
    ok = (uv[:, 0] >= 0) & (uv[:, 0] < w) & (uv[:, 1] >= 0) & (uv[:, 1] < h)
    hit = lab[uv[ok, 1], uv[ok, 0]]
    return {int(b) for b in np.unique(hit) if b >= 1}


def occluded_centres(
    stacks: Mapping[str, np.ndarray],
    labels: Mapping[str, np.ndarray],
    backgrounds: Mapping[str, tuple],
    cams: Sequence,
    cents: list[list[dict]],
    cuts: list[list[set[int]]],
    params: Mapping,
    related: set[frozenset[int]] = frozenset(),
    attached: list | None = None,
) -> list[tuple[str, int]]:
    """Fill in place, in ``cents`` and ``cuts`` (as :func:`frame_anchors` builds them),
    the centres of bubbles that one view sees apart and whole and the other sees one in
    front of another (``anchors: occlusion``).

    In a frame, a bubble with a whole silhouette in one view whose entry in the other
    view is missing or disagrees with it (:func:`surfphase.masks.anchors.pair_agreement`
    beyond the limits of :func:`surfphase.masks.anchors.views_agree`) is hidden there in
    the silhouette its ray crosses (its own piece aside) (:func:`_fused_hosts`). Bubbles
    whose whole silhouettes touch in the other view and not in the first
    (:func:`_touching_groups`) may be one in front of another there too, split into two
    silhouettes. That
    silhouette, or those touching ones joined, with the pieces of the bubbles hidden in
    it, is fitted by their circles
    (:func:`surfphase.masks.anchors.occluded_centres`), kept where each circle lies on
    silhouettes (:func:`_discs_on_silhouettes`); the circles of the bubbles of which at
    least ``min_visible_sphere`` shows (:func:`_visible_shares`: a bubble nearly hidden
    has its depth from a short arc) become their entries there, marked fitted, as a
    border-cut bubble's (touching ones only where a circle hides at least
    :data:`MIN_HIDDEN_SHARE` of another's disc), and the silhouette's
    pixels are relabelled in ``labels``, in place: each to the circle nearest the
    camera that holds it, else to the circle whose edge is nearest (background when
    further than :data:`SPLIT_REACH_PX` from all). Bubbles that a merge joins
    (``related``, pairs of ids: :func:`merge_relatives`) are not fitted together: one
    view may see them merged, or as touching lobes, a frame before the other. A
    nucleation piece that the first view shows whole and the other hides in one free
    bubble's silhouette (:func:`_nucleation_guests`) is fitted with that bubble as a
    free circle, out of the rms test (an attached bubble is no sphere: ``loose``), gets no
    entry, and its pixels go back
    to the nucleation region; its circle there, as a sphere ``(camera, frame position,
    (3,) centre m, radius m)`` (:func:`_guest_sphere`), is appended to ``attached``:
    the mesh adds to the attached bubble the part of it the free bubble hides. Returns
    the (camera, frame position) of the labels relabelled.
    """
    names = list(stacks)[:2]
    cp, ap = params["classical"], params["anchors"]
    ring, rms_max = int(ap["ring_px"]), float(ap["max_sphere_rms"])
    low = float(params["associate"]["nucleation_height"])
    split: list[tuple[str, int]] = []
    for k in range(stacks[names[0]].shape[0]):
        for v in (0, 1):
            u = 1 - v
            whole = {b: e for b, e in cents[u][k].items() if b >= 1 and b not in cuts[u][k]}
            lab = np.asarray(labels[names[v]][k])
            groups = [(host, sorted(hidden | ({host} if host in whole else set())), False)
                      for host, hidden in _fused_hosts(cams, u, v, whole, cents[v][k],
                                                       cuts[v][k], lab, ap).items()]  # fmt: skip
            # A bubble alone in its host (its ray crosses its own silhouette only) is
            # no fused group: it may still touch, in front of or behind, another.
            taken = set().union(*(g for _, g, _ in groups if len(g) >= 2))
            lab_u = np.asarray(labels[names[u]][k])
            for group in _touching_groups(
                lab, lab_u, set(whole) - taken, cents[v][k], cuts[v][k], related
            ):
                groups.append((group[0], group, True))
            taken |= set().union(*(g for _, g, touching in groups if touching))
            guests = _nucleation_guests(
                cams, u, v, whole, lab_u, lab, taken,
                partial(classical.relative_contrast, stacks[names[u]][k], cp, backgrounds[names[u]]),
                backgrounds[names[u]][1], ring,
            )  # fmt: skip
            for host, (g, e) in guests.items():
                whole[g] = e
                groups.append((host, [host, g], False))
            for host, group, touching in groups:
                if not 2 <= len(group) <= 3 or any(g not in whole for g in group):
                    continue
                if any(frozenset((a, b)) in related for a in group for b in group if a < b):
                    continue
                joined = np.where(np.isin(lab, group), host, lab)
                con = classical.relative_contrast(stacks[names[v]][k], cp, backgrounds[names[v]])
                vis = anchors.visible_outline(
                    con, joined, anchors.region_owners(joined, ring), host, ring
                )
                if vis is None:
                    continue
                fit = anchors.occluded_centres(
                    cams, v, vis[0], {g: whole[g] for g in group}, rms_max,
                    loose=[g for g in group if g >= GUEST_BASE],
                )  # fmt: skip
                if fit is None or not _discs_on_silhouettes(lab, fit):
                    continue
                spheres = {g: _guest_sphere(cams, u, v, whole[g], fit[g], low)
                           for g in group if g >= GUEST_BASE}  # fmt: skip
                if any(sp is None for sp in spheres.values()):
                    continue
                shown = _visible_shares(fit)
                if touching and min(shown.values()) > 1.0 - MIN_HIDDEN_SHARE:
                    continue  # touching, none in front of another: the centroids hold
                for g, (cu_, cv_, area, _z) in fit.items():
                    if g < GUEST_BASE and shown[g] >= float(ap["min_visible_sphere"]):
                        cents[v][k][g] = (cu_, cv_, area)
                        cuts[v][k].add(g)
                _split_fused(labels[names[v]], k, joined == host, fit)
                if any(g >= GUEST_BASE for g in group):
                    if attached is not None:
                        attached += [(names[v], k, *sp) for sp in spheres.values()]
                    frame = np.asarray(labels[names[v]][k]).copy()
                    frame[frame >= GUEST_BASE] = anchors.NUCLEATION_ID
                    labels[names[v]][k] = frame
                split.append((names[v], k))
    return split


def _guest_sphere(
    cams: Sequence, u: int, v: int, entry: tuple, circle: tuple, low: float
) -> tuple[np.ndarray, float] | None:
    """The sphere ((3,) centre m, radius m) of a nucleation piece's ``entry`` ``(u, v,
    area)`` in view ``u`` and its fitted free ``circle`` ``(u, v, area, depth)`` in view
    ``v``, where the two are one attached bubble; None where they are not.

    One object by the rule of the nucleation region's pieces
    (:func:`surfphase.masks.anchors.pieces_agree`), and attached: the sphere meets
    the plate (y = 0; its bottom at most ``low``, ``associate: nucleation_height``, above
    it, its top above it). A free circle can fit a stretch of the host's own outline on
    the ray of a speck of the plate's edge whose ray crosses a bubble; such a circle is off
    the ray, of another size, or under the plate. The centre returned lies on the
    circle's ray in view ``v`` at the triangulated depth, the radius that of the circle
    there: its image in ``v`` is the fitted circle."""
    sp = anchors.pair_sphere(
        (cams[u], cams[v]),
        [np.asarray(entry[:2], np.float64), np.asarray(circle[:2], np.float64)],
        [float(entry[2]), float(circle[2])],
    )
    if not anchors.pieces_agree(sp):
        return None
    X, r = sp[0], sp[1]
    if not (X[1] - r <= low and X[1] + r > 0.0):
        return None
    depth = float(cams[v].world_to_camera(np.asarray(X, np.float64)[None])[0, 2])
    return anchors.circle_sphere(cams[v], circle[0], circle[1], circle[2], depth)


#: Ids from this one up stand, within :func:`occluded_centres`, for the nucleation
#: region's pieces that one view sees apart and the other hides in a free bubble's
#: silhouette (:func:`_nucleation_guests`); none is left in the labels.
GUEST_BASE = 1 << 24


def _nucleation_guests(
    cams: Sequence, u: int, v: int, whole: Mapping, lab_u: np.ndarray, lab_v: np.ndarray,
    taken: set[int], contrast_u: Callable[[], np.ndarray], plate_u: np.ndarray, ring: int,
) -> dict[int, tuple[int, tuple[float, float, float]]]:  # fmt: skip
    """``{host: (guest id, (u, v, area))}`` of one frame: the nucleation region's pieces
    (an attached bubble each) that view ``u``'s (H, W) labels ``lab_u`` show whole and
    apart from a free bubble (``host``, one of ``whole``, view ``u``'s whole entries, not
    in ``taken``), and that view ``v``'s labels ``lab_v`` show in that bubble's
    silhouette: no nucleation piece of ``v`` agrees with the piece
    (:func:`surfphase.masks.anchors.agreeing_pieces`' rule) and its centroid's ray
    crosses the host's silhouette only (the host's own ray crossing it too). A
    bubble just off the plate is in front of, or behind, the next bubble growing at
    another site, in a view that sees both sites in line. Each piece's entry is its
    sub-pixel centroid and weighted area
    (:func:`surfphase.masks.anchors.coverage_centroids`, ``contrast_u`` the view's
    relative darkness, made when first needed, ``plate_u`` its plate), under a guest id
    from :data:`GUEST_BASE`; one piece per host, the largest."""
    pieces_u = anchors.silhouette_pieces(lab_u, anchors.NUCLEATION_ID)
    if not pieces_u:
        return {}
    pieces_v = anchors.silhouette_pieces(lab_v, anchors.NUCLEATION_ID)
    h, w = lab_u.shape
    found: dict[int, tuple[float, np.ndarray]] = {}
    for uv, area, m in pieces_u:
        rr, cc = np.nonzero(m)
        if rr.min() == 0 or cc.min() == 0 or rr.max() == h - 1 or cc.max() == w - 1:
            continue  # cut by the frame: its centroid is not its centre's image
        if any(
            anchors.pieces_agree(anchors.pair_sphere((cams[u], cams[v]), [uv, uv_v], [area, a_v]))
            for uv_v, a_v, _ in pieces_v
        ):
            continue  # the other view shows it too
        hits = _epipolar_hits(cams[u], cams[v], (uv[0], uv[1]), lab_v)
        if len(hits) != 1:
            continue
        host = next(iter(hits))
        if host not in whole or host in taken:
            continue
        if _epipolar_hits(cams[u], cams[v], whole[host], lab_v) != {host}:
            continue
        if host not in found or area > found[host][0]:
            found[host] = (area, m)
    out: dict[int, tuple[int, tuple[float, float, float]]] = {}
    con = contrast_u() if found else None
    for i, (host, (_a, m)) in enumerate(sorted(found.items())):
        g = GUEST_BASE + i
        cen = anchors.coverage_centroids(con, np.where(m, g, lab_u), ring, plate_u)
        out[host] = (g, cen[g])
    return out


def _fused_hosts(
    cams: Sequence, u: int, v: int, whole: Mapping, cents_v: Mapping, cuts_v: set,
    lab: np.ndarray, ap: Mapping,
) -> dict[int, set[int]]:  # fmt: skip
    """``{host: hidden}`` of one frame: the bubbles of ``whole`` (view ``u``'s whole
    entries) whose entry in view ``v`` is missing or disagrees with it, grouped by the one
    silhouette of ``v``'s (H, W) labels ``lab`` that their ray crosses (their own aside)."""
    hosts: dict[int, set[int]] = {}
    for b, e in whole.items():
        if b in cents_v and b not in cuts_v:
            _X, rep, ratio, r_px = anchors.pair_agreement((cams[u], cams[v]), e, cents_v[b])
            if anchors.views_agree(rep, ratio, r_px, ap):
                continue
        hits = _epipolar_hits(cams[u], cams[v], e, lab)
        others = hits - {b}
        host = next(iter(others)) if len(others) == 1 else b if hits == {b} else None
        if host is not None:
            hosts.setdefault(host, set()).add(b)
    return hosts


def _neighbours(lab: np.ndarray, ids: set[int]) -> dict[int, set[int]]:
    """Per id of ``ids``, the ids (≥ 1) whose silhouettes in the (H, W) labels ``lab``
    share an edge with its own (8-connected)."""
    out: dict[int, set[int]] = {}
    for b in ids:
        m = lab == b
        if not m.any():
            continue
        ring = ndi.binary_dilation(m, structure=np.ones((3, 3), bool)) & ~m
        out[b] = {int(c) for c in np.unique(lab[ring]) if c >= 1}
    return out


def _touching_groups(
    lab_v: np.ndarray,
    lab_u: np.ndarray,
    ids: set[int],
    cents_v: Mapping,
    cuts_v: set,
    related: set[frozenset[int]] = frozenset(),
) -> list[list[int]]:
    """Groups (2 or 3 ids, sorted) of ``ids``, each with a whole entry in one view (in
    ``cents_v``, not in ``cuts_v``), joined by pairs whose silhouettes share an edge in
    that view's (H, W) labels ``lab_v`` and not in the other view's ``lab_u``: one of the
    pair may be in front of the other in the first view. (Two that touch in both views
    are side by side, or about to merge; nor are two that a merge joins, ``related``,
    paired: one view may see them touch a frame before the other.)"""
    ok = {b for b in ids if b in cents_v and b not in cuts_v}
    nu = _neighbours(lab_u, ok)
    edges = {
        b: {c for c in n & ok if c not in nu.get(b, set()) and frozenset((b, c)) not in related}
        for b, n in _neighbours(lab_v, ok).items()
    }
    groups, seen = [], set()
    for b in sorted(edges):
        if b in seen or not edges[b]:
            continue
        comp, todo = set(), [b]
        while todo:
            c = todo.pop()
            if c not in comp:
                comp.add(c)
                todo.extend(edges.get(c, set()) - comp)
        seen |= comp
        if 2 <= len(comp) <= 3:
            groups.append(sorted(comp))
    return groups


def refreshed_instances(
    instances: pd.DataFrame, lab_stack: np.ndarray, camera: str, k: int
) -> pd.DataFrame:
    """``instances`` with the rows of ``camera`` at frame position ``k`` remade from its
    (T, H, W) labels (area, centroid and inclusive box of each id ≥ 0; each keeps the
    score of the row it replaces, the largest of the frame's where it had none)."""
    lab = np.asarray(lab_stack[k])
    mine = (instances["camera"] == camera) & (instances["frame"] == k)
    old = instances[mine]
    score = old.groupby("bubble")["score"].max().to_dict()
    rows = []
    for b in np.unique(lab[lab >= 0]):
        sc = score.get(int(b), max(score.values()) if score else float("nan"))
        rows.append(_instance_row(k, camera, int(b), lab == b, float(sc)))
    return _with_rows(instances, mine, rows)


def _instance_row(k: int, camera: str, b: int, mask: np.ndarray, score: float) -> tuple:
    """One row of ``instances.csv`` for the (H, W) bool ``mask`` of id ``b``."""
    ys, xs = np.nonzero(mask)
    return (k, camera, b, ys.size, xs.mean(), ys.mean(), xs.min(), ys.min(), xs.max(),
            ys.max(), score)  # fmt: skip


def _with_rows(instances: pd.DataFrame, mine: pd.Series, rows: list[tuple]) -> pd.DataFrame:
    """``instances`` with its rows ``mine`` replaced by ``rows`` (:func:`_instance_row`),
    sorted by frame, camera and id."""
    new = pd.DataFrame(rows, columns=["frame", "camera", "bubble", "area", "cx", "cy", "x0",
                                      "y0", "x1", "y1", "score"])  # fmt: skip
    out = pd.concat([instances[~mine], new.astype(instances.dtypes.to_dict())],
                    ignore_index=True)  # fmt: skip
    return out.sort_values(["frame", "camera", "bubble"], kind="stable").reset_index(drop=True)


#: 8-connectivity: a piece's pixels touching at a corner are one piece.
EIGHT = np.ones((3, 3), bool)


def refreshed_pieces(
    instances: pd.DataFrame, lab_stack: np.ndarray, camera: str, k: int, bubble: int = 0
) -> pd.DataFrame:
    """``instances`` with the rows of id ``bubble`` of ``camera`` at frame position ``k``
    remade from its (T, H, W) labels, one per 8-connected piece (area, centroid and
    inclusive box; each the score of the id's best row there)."""
    mine = (
        (instances["camera"] == camera) & (instances["frame"] == k)
        & (instances["bubble"] == bubble)
    )  # fmt: skip
    if not mine.any():
        return instances
    score = float(instances.loc[mine, "score"].max())
    comp, n = ndi.label(np.asarray(lab_stack[k]) == bubble, EIGHT)
    rows = [_instance_row(k, camera, bubble, comp == j, score) for j in range(1, n + 1)]
    return _with_rows(instances, mine, rows)


def grown_nucleation(
    labels: dict[str, np.ndarray],
    instances: pd.DataFrame,
    stacks: Mapping[str, np.ndarray],
    backgrounds: Mapping[str, tuple],
    params: Mapping,
    gap_px: int = 1,
) -> pd.DataFrame:
    """The nucleation region's pieces (id 0 of each camera's (T, H, W) ``labels``, at the
    segmented resolution) grown in place to their outline in front of the plate
    (:func:`surfphase.masks.classical.outline_in_front`; classical backend), each kept
    ``gap_px`` pixels apart from the others (so that downscaled they stay apart), and
    their rows of ``instances`` remade. After the association: it reads the silhouettes'
    bottoms, which date a detachment, from the edge every instance has (a lower edge
    keeps a just-detached bubble's silhouette on the plate's image longer)."""
    if params["backend"] != "classical":
        return instances
    cp = params["classical"]
    for name, lab in labels.items():
        frames = np.flatnonzero((lab == 0).any(axis=(1, 2)))
        if not frames.size:
            continue
        bg = backgrounds[name]
        noise = classical.contrast_noise(stacks[name], cp, bg)
        for t in frames:
            signed = classical.relative_contrast(stacks[name][t], cp, bg, signed=True)
            comp, n = ndi.label(lab[t] == 0, EIGHT)
            for j in range(1, n + 1):
                piece = comp == j
                # Pieces stay apart: the mesh matches each view's pieces by centroid.
                others = ndi.binary_dilation((lab[t] == 0) & ~piece, EIGHT, gap_px)
                free = (lab[t] < 0) & ~others
                new = classical.outline_in_front(piece, free, signed, bg[1], cp, noise)
                lab[t][new & free] = 0
            instances = refreshed_pieces(instances, lab, name, int(t))
    return instances


#: Bubbles whose silhouettes merely touch in a view, none in front of another, keep
#: their silhouettes' centroids: their fitted circles count as overlapping when one
#: hides at least this share of another's disc. Hiding a share h of a disc's edge moves
#: its silhouette's centroid by about 0.8 h r / (1 − h), 0.016 r at 2 %: the error of a
#: fitted circle's centre (:func:`occluded_centres`).
MIN_HIDDEN_SHARE = 0.02

#: Least share of a fitted circle's inner disc (its radius less a pixel) that must be
#: silhouette pixels in its view: whatever hides a bubble is a bubble too, so its
#: whole image is dark (:func:`_discs_on_silhouettes`).
MIN_DISC_ON_SILHOUETTE = 0.9


def _visible_shares(fit: Mapping) -> dict[int, float]:
    """Per circle of ``fit`` (``{bubble: (u, v, area, depth)}``), the share of its disc
    that no circle nearer the camera covers (on a 0.25 px grid)."""
    ids = list(fit)
    c = np.array([fit[b][:2] for b in ids], np.float64)
    r = np.sqrt(np.array([fit[b][2] for b in ids], np.float64) / np.pi)
    z = np.array([fit[b][3] for b in ids], np.float64)
    out = {}
    for i, b in enumerate(ids):
        g = np.arange(-r[i], r[i] + 1e-9, 0.25)
        xx, yy = np.meshgrid(c[i, 0] + g, c[i, 1] + g)
        disc = np.hypot(xx - c[i, 0], yy - c[i, 1]) <= r[i]
        hidden = np.zeros_like(disc)
        for j in range(len(ids)):
            if j != i and z[j] < z[i]:
                hidden |= np.hypot(xx - c[j, 0], yy - c[j, 1]) <= r[j]
        out[b] = float((disc & ~hidden).sum() / max(disc.sum(), 1))
    return out


def _discs_on_silhouettes(lab: np.ndarray, fit: Mapping) -> bool:
    """Whether each circle of ``fit`` (``{bubble: (u, v, area, depth)}``) lies on the
    silhouettes of the (H, W) labels ``lab`` (ids ≥ 0): at least
    :data:`MIN_DISC_ON_SILHOUETTE` of the pixels of its disc shrunk by a pixel that lie
    in the image. A circle whose arc fits a stretch of the outline but that lies over
    the background is not a bubble there."""
    h, w = lab.shape
    for u, v, area, _z in fit.values():
        r = float(np.sqrt(area / np.pi)) - 1.0
        if r <= 0:
            continue
        y0, y1 = max(int(np.floor(v - r)), 0), min(int(np.ceil(v + r)) + 1, h)
        x0, x1 = max(int(np.floor(u - r)), 0), min(int(np.ceil(u + r)) + 1, w)
        if y0 >= y1 or x0 >= x1:
            return False
        yy, xx = np.mgrid[y0:y1, x0:x1]
        disc = np.hypot(xx - u, yy - v) <= r
        if not disc.any() or np.mean(lab[y0:y1, x0:x1][disc] >= 0) < MIN_DISC_ON_SILHOUETTE:
            return False
    return True


#: Pixels of a fused silhouette further than this outside every fitted circle are
#: none of its bubbles' (a stray piece of a mask): background (:func:`_split_fused`).
SPLIT_REACH_PX = 1.5


def _split_fused(lab_stack: np.ndarray, k: int, region: np.ndarray, fit: Mapping) -> None:
    """Relabel, in place, the pixels of ``region`` ((H, W) bool) in frame ``k`` of a
    (T, H, W) label stack by the circles of ``fit`` (``{bubble: (u, v, area, depth)}``):
    each pixel to the nearest-to-camera circle holding it, else to the circle whose
    edge is nearest, within :data:`SPLIT_REACH_PX`; background beyond."""
    rows, cols = np.nonzero(region)
    ids = list(fit)
    c = np.array([fit[b][:2] for b in ids])
    r = np.sqrt(np.array([fit[b][2] for b in ids]) / np.pi)
    z = np.array([fit[b][3] for b in ids])
    d = np.hypot(cols[:, None] - c[None, :, 0], rows[:, None] - c[None, :, 1]) - r[None]
    inside = d <= 0
    front = np.where(inside, z[None], np.inf).argmin(1)
    pick = np.where(inside.any(1), front, d.argmin(1))
    frame = np.asarray(lab_stack[k]).copy()
    frame[rows, cols] = np.where(d.min(1) <= SPLIT_REACH_PX, np.asarray(ids)[pick], -1)
    lab_stack[k] = frame


def sphere_cut_centres(
    stacks: Mapping[str, np.ndarray],
    labels: Mapping[str, np.ndarray],
    backgrounds: Mapping[str, tuple],
    cams: Sequence,
    cents: list[list[dict]],
    cuts: list[list[set[int]]],
    params: Mapping,
) -> None:
    """Fill in place, in ``cents`` and ``cuts`` (per view, per frame position, as
    :func:`frame_anchors` builds them), the centres of the bubbles that both first two
    views see but at least one of them cut by its border without a centre
    (``anchors: min_visible_sphere``, ``max_sphere_rms``, ``sphere_both_cut``); a
    view's existing centre is kept.

    * Where the view has the bubble's centre in another frame, its visible outline is
      laid onto that frame's outline by a translation
      (:func:`surfphase.masks.anchors.register_outline`; the nearest such frame) and
      that centre moved with it: a shape fitted anew to each frame's shrinking arc
      drifts with the bubble's departure from a sphere (0.1 r as it goes from 50 to
      30 % inside); a moved arc does not, and it continues the centres without a jump.
    * Else, where the other view has a centre, the sphere on that centre's ray that the
      cut view's visible outline lies on (:func:`surfphase.masks.anchors.sphere_centres`),
      in the frame where most of it is inside, moved to the other frames as above.
    * Else (neither view ever has one), the sphere fitted to both views' outlines in the
      frame where most of it is inside (the lesser visible share of the two views), its
      circles moved to the other frames as above.
    """
    names = list(stacks)[:2]
    ap = params["anchors"]
    lo, rms_max = float(ap["min_visible_sphere"]), float(ap["max_sphere_rms"])
    n = stacks[names[0]].shape[0]
    outline = _outline_reader(stacks, labels, backgrounds, params)

    # What each view misses: bubble -> frame positions (seen by both, cut in this view).
    missing: list[dict[int, list[int]]] = [{}, {}]
    for t in range(n):
        labs = [np.asarray(labels[c][t]) for c in names]
        ids = set(np.unique(labs[0]).tolist()) & set(np.unique(labs[1]).tolist())
        for k in (0, 1):
            cut = anchors.border_ids(labs[k])
            for b in sorted(i for i in ids if i >= 1 and i in cut and i not in cents[k][t]):
                missing[k].setdefault(b, []).append(t)
    for k in (0, 1):
        for b, ts in missing[k].items():
            have = [t for t in range(n) if b in cents[k][t]]
            _register_frames(k, b, ts, have, cents, cuts, outline, lo, rms_max)
    for k in (0, 1):
        for b, ts in missing[k].items():
            ts = [t for t in ts if b not in cents[k][t] and b in cents[1 - k][t]]
            vis = {t: outline(t, k, b) for t in ts}
            vis = {t: v for t, v in vis.items() if v is not None}
            for t in sorted(vis, key=lambda t: (-vis[t][1], t))[:3]:  # most visible first
                known = [cents[j][t][b] if j != k else None for j in (0, 1)]
                pts = [vis[t][0] if j == k else None for j in (0, 1)]
                cov = [vis[t][1] if j == k else 0.0 for j in (0, 1)]
                fit = anchors.sphere_centres(cams, pts, cov, known, lo, rms_max)
                if fit is not None:
                    _set_centres(cents, cuts, t, b, fit, known)
                    rest = [f for f in ts if f != t]
                    _register_frames(k, b, rest, [t], cents, cuts, outline, lo, rms_max)
                    break
    both: dict[int, list[int]] = {}
    for k in (0, 1):
        for b, ts in missing[k].items():
            for t in ts:
                if b not in cents[0][t] and b not in cents[1][t]:
                    both.setdefault(b, [])
                    if t not in both[b]:
                        both[b].append(t)
    if not ap["sphere_both_cut"]:
        return
    for b, ts in sorted(both.items()):
        vis = {t: [outline(t, k, b) for k in (0, 1)] for t in ts}
        vis = {t: v for t, v in vis.items() if all(x is not None for x in v)}
        order = sorted(vis, key=lambda t: (-min(x[1] for x in vis[t]), t))
        for t in order[:3]:  # the most visible frames first
            pts, cov = [x[0] for x in vis[t]], [x[1] for x in vis[t]]
            fit = anchors.sphere_centres(cams, pts, cov, (None, None), lo, rms_max)
            if fit is not None:
                _set_centres(cents, cuts, t, b, fit, (None, None))
                for k in (0, 1):
                    rest = [f for f in ts if b not in cents[k][f]]
                    _register_frames(k, b, rest, [t], cents, cuts, outline, lo, rms_max)
                break


def _outline_reader(
    stacks: Mapping[str, np.ndarray],
    labels: Mapping[str, np.ndarray],
    backgrounds: Mapping[str, tuple],
    params: Mapping,
) -> Callable[[int, int, int], tuple[np.ndarray, float] | None]:
    """``outline(t, k, b)``: the visible outline of id ``b`` in the first two views'
    view ``k`` at frame position ``t``
    (:func:`surfphase.masks.anchors.visible_outline`: ``(points, cover)`` or None),
    each frame's contrast and region owners computed once for the last few frames."""
    names = list(stacks)[:2]
    cp, ring = params["classical"], int(params["anchors"]["ring_px"])
    cache: dict[int, tuple] = {}

    def outline(t: int, k: int, b: int):
        if t not in cache:
            if len(cache) > 8:
                cache.clear()
            labs = [np.asarray(labels[c][t]) for c in names]
            cons = [classical.relative_contrast(stacks[c][t], cp, backgrounds[c]) for c in names]
            cache[t] = (labs, cons, [anchors.region_owners(lab, ring) for lab in labs])
        labs, cons, owners = cache[t]
        return anchors.visible_outline(cons[k], labs[k], owners[k], b, ring)

    return outline


def _set_centres(cents, cuts, t: int, b: int, fit, known) -> None:
    """Enter ``fit``'s entries of the views without a ``known`` centre."""
    for k in (0, 1):
        if known[k] is None:
            cents[k][t][b] = tuple(map(float, fit[k]))
            cuts[k][t].add(b)


def _register_frames(
    k: int,
    b: int,
    frames: Sequence[int],
    have: Sequence[int],
    cents,
    cuts,
    outline: Callable,
    lo: float,
    rms_max: float,
) -> None:
    """View ``k``'s centres of bubble ``b`` at the positions ``frames``, each from the
    nearest position of ``have`` (where the view has its centre and area): the visible
    outline laid onto that position's outline by a translation
    (:func:`surfphase.masks.anchors.register_outline`, starting from the translation
    of the nearest frame done), the centre moved with it, the area kept; where the
    outline lies within ``rms_max`` of the centre's equivalent radius (rms) and its
    visible cover is at least ``lo`` of that area. ``outline(t, k, b)``: the view's
    ``(points, cover)`` at position t, or None."""
    if not have:
        return
    refs: dict[int, tuple] = {}
    moved: dict[int, dict[int, np.ndarray]] = {}  # reference -> frame -> motion (px)
    for t in sorted(frames, key=lambda t: (min(abs(t - h) for h in have), t)):
        t0 = min(have, key=lambda h: (abs(t - h), h))
        if t0 not in refs:
            refs[t0] = outline(t0, k, b)
            moved[t0] = {t0: np.zeros(2)}
        vis, ref = outline(t, k, b), refs[t0]
        if vis is None or ref is None or len(vis[0]) < 3:
            continue
        done = moved[t0]
        near = min((f for f in done if (f - t0) * (t - t0) >= 0), key=lambda f: abs(f - t))
        reg = anchors.register_outline(vis[0], ref[0], -done[near])
        u, v, area = cents[k][t0][b]
        r = float(np.sqrt(area / np.pi))
        if reg is None or reg[1] > rms_max * r or vis[1] < lo * area:
            continue
        done[t] = -reg[0]
        cents[k][t][b] = (u - float(reg[0][0]), v - float(reg[0][1]), float(area))
        cuts[k][t].add(b)


def young_merged(
    events: pd.DataFrame, views: Sequence[str], n_frames: int, fps: float | None, span_s: float
) -> dict[int, set[int]]:
    """``{frame position: ids}`` of the bubbles born of a merge that every one of
    ``views`` records in ``events`` (``events.csv``'s rows, frames as positions), in the
    positions less than ``span_s`` seconds (at least one frame) from the merge's first
    frame, below ``n_frames``; empty without fps or with ``span_s`` ≤ 0."""
    if not fps or span_s <= 0 or len(events) == 0:
        return {}
    n = max(1, int(round(float(span_s) * float(fps))))
    rows = events[events["event"] == "merge"]
    born: dict[int, int] = {}
    for f, ch in zip(rows["frame"].astype(int), rows["children"], strict=True):
        for c in str(ch).split("+"):
            born[int(c)] = min(born.get(int(c), f), f)
    out: dict[int, set[int]] = {}
    for b in merged_in_every_view(events, views):
        for k in range(born[b], min(born[b] + n, int(n_frames))):
            out.setdefault(k, set()).add(b)
    return out


def merge_relatives(events: pd.DataFrame) -> set[frozenset[int]]:
    """Pairs of bubble ids that one merge of ``events`` (``events.csv``'s rows) joins:
    its parents with each other and with its child, in any view."""
    out: set[frozenset[int]] = set()
    if len(events) == 0:
        return out
    for par, ch in events.loc[events["event"] == "merge", ["parents", "children"]].itertuples(
        index=False
    ):
        ids = sorted({int(x) for x in f"{par}+{ch}".split("+") if x.strip()})
        out |= {frozenset((a, b)) for i, a in enumerate(ids) for b in ids[i + 1 :]}
    return out


def merged_in_every_view(events: pd.DataFrame, views: Sequence[str]) -> set[int]:
    """Bubble ids born of a merge that every one of ``views`` records in ``events``
    (``events.csv``'s rows: ``camera``, ``event``, ``children``)."""
    if len(events) == 0:
        return set()
    rows = events[events["event"] == "merge"]
    per = [
        {int(c) for ch in rows.loc[rows["camera"] == v, "children"] for c in str(ch).split("+")}
        for v in views
    ]
    return set.intersection(*per) if per else set()


def drop_inconsistent(
    labels: dict[str, np.ndarray],
    instances: pd.DataFrame,
    table: pd.DataFrame,
    keep: set[int] = frozenset(),
) -> int:
    """Remove, in place, each (frame position, bubble) whose two views disagree
    (``consistent`` false in :func:`frame_anchors`' table, frames as positions) from every
    view's labels; return how many. ``instances`` gets ``bubble = -1`` there. A pair
    with a centre fitted to a border-cut outline (``cut``) that disagrees only loses
    its centre: the fit, not the pairing, is the likelier fault. So do the bubbles of
    ``keep``: a young merged bubble both views saw merge has its lobes fused differently
    in each view, so its silhouettes' centres disagree, but it is a bubble."""
    cut = table["cut"].astype(bool) if "cut" in table else False
    bad = table[~table["consistent"].astype(bool) & ~cut & ~table["bubble"].isin(sorted(keep))]
    for t, b in bad[["position", "bubble"]].itertuples(index=False):
        for lab in labels.values():
            lab[int(t)][lab[int(t)] == int(b)] = -1
        sel = (instances["frame"] == int(t)) & (instances["bubble"] == int(b))
        instances.loc[sel, "bubble"] = -1
    return len(bad)


def drop_static(
    labels: dict[str, np.ndarray],
    instances: pd.DataFrame,
    table: pd.DataFrame,
    fps: float,
    min_speed_mps: float,
) -> list[int]:
    """Remove, in place, every bubble whose consistent centres in ``table`` move slower
    than ``min_speed_mps`` (:func:`surfphase.masks.anchors.track_speeds`) from every
    view's labels and from ``instances`` (``bubble = -1``); return their ids."""
    if min_speed_mps <= 0 or not fps:
        return []
    ok = table[table["consistent"].astype(bool)]
    speeds = anchors.track_speeds(ok, fps)
    static = sorted(b for b, v in speeds.items() if v < min_speed_mps)
    for b in static:
        for lab in labels.values():
            lab[lab == b] = -1
        instances.loc[instances["bubble"] == b, "bubble"] = -1
    return static


def scaled_instances(instances: pd.DataFrame, sx: float, sy: float) -> pd.DataFrame:
    """The instance table of labels downscaled by ``(sx, sy)`` (pixel-centre
    convention ``u' = (u + 0.5)·s − 0.5``; areas × sx·sy; boxes rounded outwards)."""
    out = instances.copy()
    out["cx"] = (out["cx"] + 0.5) * sx - 0.5
    out["cy"] = (out["cy"] + 0.5) * sy - 0.5
    out["area"] = (out["area"] * sx * sy).round().astype(int)
    out["x0"] = np.floor(out["x0"] * sx).astype(int)
    out["y0"] = np.floor(out["y0"] * sy).astype(int)
    out["x1"] = np.floor((out["x1"] + 1) * sx - 1e-9).astype(int)
    out["y1"] = np.floor((out["y1"] + 1) * sy - 1e-9).astype(int)
    return out


def _segment_all(stacks: Mapping[str, np.ndarray], p: Mapping) -> tuple[dict, dict, dict, float]:
    """Every camera's :func:`segment_stack` → (labels, scores, backgrounds, seconds)."""
    backend = None
    if p["backend"] == "sam":
        # Imported here: ONNX Runtime and torch cost a classical run 1–2 s to load.
        from surfphase.masks.sam_onnx import load_sam

        backend = load_sam(p["sam"])
    t0 = time.perf_counter()
    labels, scores, bgs = {}, {}, {}
    for name, st in stacks.items():
        labels[name], scores[name], bgs[name] = segment_stack(st, p, backend)
    return labels, scores, bgs, time.perf_counter() - t0


def _anchor_and_drop(
    stacks: Mapping[str, np.ndarray],
    labels: dict[str, np.ndarray],
    instances: pd.DataFrame,
    events: pd.DataFrame,
    bgs: Mapping[str, tuple],
    cameras: Mapping,
    frames: np.ndarray,
    fps: float | None,
    p: Mapping,
) -> tuple[pd.DataFrame, pd.DataFrame, int, list[int]]:
    """With ≥ 2 views: the anchors (:func:`frame_anchors`), the inconsistent and the
    static bubbles removed from ``labels`` (in place) and ``instances``.

    Returns (instances, consistent anchors, how many pairs dropped, static ids).
    """
    anchor_tab = pd.DataFrame(
        columns=[*anchors.ANCHOR_COLUMNS, "low", "visible", "continued", "position"]
    )
    if len(stacks) < 2:
        return instances, anchor_tab, 0, []
    young = young_merged(
        events, list(stacks)[:2], len(frames), fps, float(p["anchors"]["lobe_centroid_s"])
    )
    anchor_tab = frame_anchors(
        stacks, labels, bgs, cameras, frames, p, young, merge_relatives(events), fps
    )
    pos = {int(f): k for k, f in enumerate(frames)}
    anchor_tab["position"] = [pos[int(f)] for f in anchor_tab["frame"]]
    for cam, k in anchor_tab.attrs.get("split", []):
        instances = refreshed_instances(instances, labels[cam], cam, k)
    merged = merged_in_every_view(events, list(stacks)[:2])
    dropped = drop_inconsistent(labels, instances, anchor_tab, merged)
    static = drop_static(labels, instances, anchor_tab, fps, float(p["anchors"]["min_speed_mps"]))
    instances = instances[instances["bubble"] != -1].reset_index(drop=True)
    attached = anchor_tab.attrs.get("attached", [])
    anchor_tab = anchor_tab[
        anchor_tab["consistent"].astype(bool) & ~anchor_tab["bubble"].isin(static)
    ]
    anchor_tab.attrs["attached"] = attached
    return instances, anchor_tab, dropped, static


def _to_fit_size(
    labels: dict[str, np.ndarray],
    instances: pd.DataFrame,
    seg_stacks: Mapping[str, np.ndarray],
    fit_stacks: Mapping[str, np.ndarray],
) -> tuple[dict[str, np.ndarray], pd.DataFrame]:
    """Native-resolution labels and instances → the fit's frame size."""
    out = {}
    for name, full in labels.items():
        h, w = fit_stacks[name].shape[1:3]
        out[name] = np.stack(
            [anchors.downsample_labels(full[t], (w, h)) for t in range(full.shape[0])]
        )
    parts = []
    for name, g in instances.groupby("camera", sort=False):
        h, w = fit_stacks[name].shape[1:3]
        sx, sy = w / seg_stacks[name].shape[2], h / seg_stacks[name].shape[1]
        parts.append(scaled_instances(g, sx, sy))
    return out, (pd.concat(parts).sort_index() if parts else instances)


def overlay_images(
    stacks: Mapping[str, np.ndarray], labels: Mapping[str, np.ndarray], count: int
) -> dict[str, np.ndarray]:
    """``{"frame_XXXXX.png": RGB}`` of ``count`` frames evenly spaced over the session,
    the views side by side (:func:`surfphase.masks.overlay.overlay_frame`)."""
    n_frames = next(iter(stacks.values())).shape[0]
    k = max(0, min(int(count), n_frames))
    out = {}
    for t in np.unique(np.linspace(0, n_frames - 1, k).round().astype(int)) if k else []:
        pics = [overlay_frame(unit_grey(stacks[c][t]), labels[c][t]) for c in stacks]
        hmax = max(pc.shape[0] for pc in pics)
        pics = [np.pad(pc, ((0, hmax - pc.shape[0]), (0, 4), (0, 0))) for pc in pics]
        out[f"frame_{int(t):05d}.png"] = np.concatenate(pics, axis=1)
    return out


def run_mask_stage(ingest_dir: Path, out_dir: Path, params: Mapping | None = None) -> None:
    """Run the mask stage of one session (see the module docstring for the files).

    Args:
        ingest_dir: the session's ingest folder.
        out_dir: output folder (created; existing outputs are replaced).
        params: the ``masks`` section of the config (defaults: :data:`DEFAULTS`).
    """
    ingest_dir, out_dir = Path(ingest_dir), Path(out_dir)
    p = merge_params(params)
    ingest = read_ingest(ingest_dir)
    meta = ingest.meta
    seg = ingest.native() or ingest
    stacks = seg.stacks
    blank_notes = check_dynamic_range(meta, seg.path, stacks, float(p["min_dynamic_range"]))
    labels, scores, bgs, t_seg = _segment_all(stacks, p)
    plates = {name: bg[1] for name, bg in bgs.items()}
    bubble_labels, instances, events = associate(
        labels, scores, seg.cameras, p["associate"], plates, ingest.fps, p["anchors"]
    )
    check_bubbles_found(meta, ingest_dir, instances, list(stacks))
    associated = instances.copy()
    instances, anchor_tab, dropped, static = _anchor_and_drop(
        stacks, bubble_labels, instances, events, bgs, seg.cameras, ingest.frame_indices,
        ingest.fps, p,
    )  # fmt: skip
    if len(stacks) >= 2:
        blank_notes += check_centres_found(
            meta, ingest_dir, associated[~associated.bubble.isin(static)], anchor_tab,
            list(stacks),
        )  # fmt: skip
    # Kept apart by a whole pixel of the fit's frames, downscaled (2 s − 1 native ones).
    scale = max(
        int(np.ceil(stacks[c].shape[k] / ingest.stacks[c].shape[k])) for c in stacks for k in (1, 2)
    )
    instances = grown_nucleation(bubble_labels, instances, stacks, bgs, p, 2 * scale - 1)
    if seg is not ingest:
        bubble_labels, instances = _to_fit_size(bubble_labels, instances, stacks, ingest.stacks)
    info = {
        "session": ingest.session,
        "backend": p["backend"],
        "params": p,
        "cameras": list(ingest.stacks),
        "frames": ingest.n_frames,
        "instances": len(instances),
        "bubbles": int(instances.loc[instances.bubble > 0, "bubble"].nunique()),
        "events": len(events),
        "native": seg is not ingest,
        "segmented_size": {c: list(st.shape[1:3][::-1]) for c, st in labels.items()},
        "anchors": len(anchor_tab),
        "dropped_inconsistent": dropped,
        "dropped_static": static,
        "segment_seconds": round(t_seg, 3),
        "warnings": blank_notes,
        "attached_hidden": anchor_tab.attrs.get("attached", []),
    }
    write_masks(
        out_dir, bubble_labels, instances, events,
        anchor_tab[ANCHOR_FILE_COLUMNS],
        overlay_images(ingest.stacks, bubble_labels, p["overlay_frames"]), info,
    )  # fmt: skip
