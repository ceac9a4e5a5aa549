"""Every setting of the mask stage and its default (config.yaml ``masks:``), in one
module without heavy imports, so the workflow checks a campaign's ``masks:`` keys when
it builds its DAG. The stage's modules use these dicts (:mod:`surfphase.masks.classical`,
:mod:`~surfphase.masks.amg`, :mod:`~surfphase.masks.associate`,
:mod:`~surfphase.masks.anchors`, :mod:`~surfphase.masks.stage`).
"""

from __future__ import annotations

#: Parameters of :func:`segment_frame` (mirrored in config.yaml under ``masks.classical``).
CLASSICAL_DEFAULTS: dict = {
    # "dark": bubbles darker than the background (shadowgraph); "bright": the opposite.
    "polarity": "dark",
    # Total degree of the robust polynomial background fit.
    "background_degree": 4,
    # Session reference: this per-pixel percentile over (at most max) frames; on the
    # plate, the plate percentile.
    "reference_percentile": 90.0,
    "plate_percentile": 50.0,
    # Second pass: the plate values over the frames where the first pass's objects
    # (grown by this fraction of the shorter side) leave a pixel free, where at least
    # this fraction of the frames do (a slow bubble in front of the plate is otherwise
    # part of its reference). false: one pass.
    "plate_refine": True,
    "plate_grow_frac": 0.02,
    "plate_free_frac": 0.2,
    "reference_max_frames": 64,
    # Static dark structure (the heated plate): darker than the fitted background by
    # this fraction in the reference, touching the border, at least this area fraction.
    "static_dark_frac": 0.35,
    "static_min_area_frac": 0.01,
    # Window along the plate edge, fraction of the image width (more than twice the
    # widest bubble sitting on the plate).
    "static_notch_frac": 0.35,
    # A column of the plate's edge within this many pixels of the robust line of a
    # window (ending at, centred on or starting at it) is the edge; others are dents.
    "static_edge_tol_px": 1.0,
    # On the plate, a reference pixel this far (fraction) from the along-edge median
    # is a bubble persisting at a nucleation site, not the plate.
    "static_outlier_frac": 0.25,
    # Edge of a bubble in front of the static structure, relative contrast.
    "static_edge": 0.25,
    # Radius (pixels) of the closing that joins an object's rim and core in front of
    # the static structure (0: none).
    "static_close_px": 2,
    # In front of the static structure, an object whose convex hull holds another (a
    # dark ring left open around its bright core), or whose ring encloses a core seen
    # against the backlight only together with the plate (its bottom, in front of the
    # plate, too faint to be edge), is one bubble: the hull of its edge.
    "static_ring_hull": True,
    # Where the background itself is darker than this (black plate sides), nothing is seen.
    "background_floor": 0.08,
    # Gaussian smoothing before detection (not for the edge), pixels.
    "smooth_px": 0.7,
    # Hysteresis thresholds on the relative contrast (background − image) / background.
    "threshold_low": 0.08,
    "threshold_high": 0.2,
    # ... and at least this many times the contrast's own noise there (the per-pixel
    # spread of the smoothed contrast between consecutive frames,
    # :func:`contrast_noise`): on a dim plate the relative contrast of camera noise is
    # large, and thresholds meant for the bright backlight would segment it.
    "noise_low": 3.0,
    "noise_high": 5.0,
    # Window (pixels) of the spatial median that steadies the per-pixel noise estimate.
    "noise_window_px": 9,
    # Edge of each object at this fraction of its own peak contrast (half maximum).
    "edge_frac": 0.5,
    # Peaks of the distance transform closer than this (fraction of shorter side) merge.
    "split_min_distance_frac": 0.012,
    # Two touching pieces stay one bubble when neck width / smaller width exceeds this.
    "split_neck_ratio": 0.7,
    # Minimum instance area, fraction of the image area (and never below 6 pixels).
    "min_area_frac": 2.0e-4,
}


#: Automatic-mask-generation parameters (config.yaml ``masks.sam``): the ONNX files
#: (:mod:`surfphase.masks.sam_onnx`) and the generation's thresholds.
SAM_DEFAULTS: dict = {
    "encoder": "resources/sam/sam_encoder.onnx",
    "decoder": "resources/sam/sam_decoder.onnx",
    "points_per_side": 32,
    "points_per_batch": 64,
    "pred_iou_thresh": 0.88,
    "stability_score_thresh": 0.95,
    "stability_score_offset": 1.0,
    "box_nms_thresh": 0.7,
    "min_region_area": 0,
}


#: Parameters of :func:`associate` (config.yaml ``masks.associate``).
ASSOCIATE_DEFAULTS: dict = {
    # Gate of the cross-view pair cost, fraction of the image height.
    "view_gate_frac": 0.04,
    # An attached bubble's silhouette bottom is within this height of the plate, metres
    # (about two pixels of a typical recording: the bottom's triangulation error).
    "nucleation_height": 1.0e-4,
    # A bubble rising out of the nucleation region is free from the moment the line
    # through its triangulated bottom heights over its first frames (this many seconds,
    # at least detach_fit_min_frames) reaches the plate: frames before it left the
    # nucleation height become its own (surfphase.masks.detach).
    "detach_fit_s": 0.002,
    "detach_fit_min_frames": 4,
    # Without cameras: attached when the bottom is within this many rows (fraction of
    # the height) of the lowest silhouette bottom seen in the session.
    "nucleation_margin_frac": 0.02,
    # Frame-to-frame: minimum IoU of a track's predicted mask with the next instance.
    "track_iou_min": 0.2,
    # A track unseen for up to this many frames (hidden behind another) may come back.
    "coast_frames": 8,
    # Merge/split: an overlap counts when it covers this fraction of the smaller mask.
    "event_overlap_frac": 0.25,
    # Cross-view link: paired in at least this fraction of the common frames.
    "link_frac": 0.3,
    # A merge is dated back over up to this many seconds (at least one frame) in which
    # the parents touch in every view: a young merged bubble is two lobes the segmenter
    # may still cut apart for about the coalescence time (~1 ms for mm bubbles in water),
    # however many frames that is. Seconds, so one setting holds across frame rates.
    "merge_lobe_s": 0.001,
    # ... but not before the frame before the parents' approach speeds up. Bubbles
    # about to touch show as touching lobes too (the film between them is dark), and
    # approach steadily; once merged, the lobes slide together faster. The frame that
    # departs from a straight line through the previous merge_trend_frames frames of
    # the lobes' centroid distance, by more than merge_departure x their summed radii
    # (and 3 residual SDs), is the first seen merged; contact is dated one frame
    # before it (a merge dated a frame early reports one wrong bubble, a frame late two)
    # and merge_onset_s earlier still: the lobes need about that long to slide together
    # by a measurable amount, however many frames that is. Dated as early as that lag
    # allows (floor of merge_onset_s x fps frames, 0 below 1 / merge_onset_s fps).
    "merge_trend_frames": 5,
    "merge_departure": 0.02,
    "merge_onset_s": 0.00015,
}


#: Parameters (config ``masks: anchors:``).
ANCHOR_DEFAULTS: dict = {
    # Width (pixels) of the band around each mask whose partial darkness counts as
    # partial cover (anti-aliased, blurred edges): 0 = the binary mask's centroid.
    "ring_px": 1,
    # Two views agree on a bubble when its triangulated centre reprojects within this
    # many pixels of both silhouette centroids ...
    "max_reproj_px": 1.0,
    # ... or within this fraction of the silhouettes' mean equivalent radius (pixels),
    # whichever is larger: a deformed bubble's silhouette centroid is off its centre's
    # projection by a share of its size (true pairs over the eight benchmark draws: up
    # to 0.11 of the radius, 1.4 px on a 13.5 px bubble; the pairs of two different
    # things there: 0.18-1.0 where over 1 px); not a bubble just born of a merge (within
    # lobe_centroid_s of it: two lobes, not one deformed bubble) ...
    "max_reproj_r": 0.15,
    # ... and the sizes its two silhouettes give at that centre (equivalent radius ×
    # distance / focal length) differ by at most this factor.
    "max_size_ratio": 1.3,
    # A bubble whose triangulated centre moves slower than this (m/s; the least-squares
    # speed over its frames, at least 3) is a static feature of the scene (a speck on
    # the plate or the window), not a free bubble: buoyancy lifts a free bubble of 0.1 mm
    # diameter in water at about 5 mm/s, larger ones faster. 0 keeps them all.
    "min_speed_mps": 0.005,
    # A silhouette the image border cuts gets its centre and full area from the ellipse
    # fitted to its visible outline (cut_centres) when at least this fraction (0-1) of
    # the fitted ellipse's area is inside the frame; above 1: never (no centre).
    "min_visible": 0.6,
    # ... and when that ellipse's long axis is at most this many times its short axis
    # and its part inside the frame has the visible silhouette's area to within
    # max_cut_area_error: a short arc of a near-circular outline (a bubble mostly
    # outside the frame) is fitted as a flat ellipse that closes just past the border,
    # its centre up to a radius off, its visible share read as 0.6 or more. On four
    # draws of the bench preset the 122 fits within 0.25 radius of the true centre had
    # at most 1.19 and 0.034; the 27 further off were all above one of 1.5 and 0.1. A
    # rejected silhouette gets its centre as one with less inside (below).
    "max_cut_aspect": 1.5,
    "max_cut_area_error": 0.1,
    # One with less inside gets its centre from the shape its own track shows whole in
    # the nearest frame of that view (tracked_cut_centres: the ellipse moved onto the
    # visible outline) when at least this fraction of that ellipse is inside the frame
    # and the outline's rms distance to it is at most max_shape_rms of its equivalent
    # radius; min_visible_tracked above 1: never.
    "min_visible_tracked": 0.25,
    "max_shape_rms": 0.05,
    # A bubble still without a centre in a view (cut by the frame there, and no frame of
    # that view shows it whole: it enters or leaves at the session's start or end) gets
    # one from the sphere fitted to its visible outlines in both views at once
    # (sphere_centres) when at least this fraction of each view's circle is inside the
    # frame and each outline's rms distance to its circle is at most max_sphere_rms of
    # the circle's radius; min_visible_sphere above 1: never. Below 0.15 the centres
    # stay close (on the bench's leaving bubbles, 5-15 % inside: 0.05 r_eq off on
    # average), but the visible cap moves with the bubble's shape modes as well as its
    # centre: velocities from them are 10 % off, so the fit reports them (and those up
    # to 25 % inside) without one (fit: track_min_visible; anchors.csv's ``visible`` is
    # each centre's share inside).
    "min_visible_sphere": 0.05,
    # (max_sphere_rms also bounds the circle of a silhouette that the image's bottom
    # border cuts, whose lowest point is then the bubble's bottom for the nucleation
    # test: masks: associate: nucleation_height.)
    "max_sphere_rms": 0.08,
    # Where the other view has the bubble's centre and area, the sphere lies on that
    # centre's ray with that size and only its depth is fitted; where neither has one,
    # True fits the whole sphere to both views' outlines (its centre drifts with a
    # spheroid's shape as less of it is inside), False leaves the bubble without a centre.
    "sphere_both_cut": True,
    # A bubble leaving the frame whose sliver is too small for any of the fits above
    # (or entering it) has its centre continued along its track past its last (first)
    # centre for up to this many seconds (continued_centres: the line through its
    # centres of the last continue_s, their median radius), while a view still shows
    # part of it, its sphere's image reaches into both frames and holds what shows.
    # Without it such a bubble is neither reported nor meshed in its last frames, though
    # both views see it; a continued centre is reported without a velocity (its
    # ``visible`` share is under fit: track_min_visible). 0: never.
    "continue_s": 0.002,
    # A bubble the border cuts in frames where it still has no centre (one that no
    # frame shows whole in either view, or whose sliver in one view is lost) gets one
    # there from the sphere moving at a constant velocity that its visible outlines in
    # both views lie on over those frames and the cut frames within continue_s of them
    # (sphere_track_centres; each outline within max_sphere_rms of its circle), under
    # continue_s's test, reported without a velocity like a continued centre. False: never.
    "sphere_track": True,
    # Two or three bubbles that one view sees apart, whole, and the other fuses into one
    # silhouette (one in front of another): their spheres on the first view's rays fitted
    # to the fused outline's arcs give their centres there (occluded_centres; rms at most
    # max_sphere_rms of the circles' mean radius), and the fused silhouette's pixels go
    # to the circle in front that holds them. An attached bubble (a nucleation piece one
    # view shows whole) fused so with a free bubble is fitted with it as a free circle,
    # out of the rms test, and its pixels go back to the nucleation region. False: such
    # bubbles get no centre there.
    "occlusion": True,
    # A bubble born of a merge (both views' events), for this many seconds from the
    # merge frame (the coalescence time, as associate: merge_lobe_s), has as its
    # silhouette's centre the centroid of the solid of revolution about its long axis
    # (lobe_centroids): a young merged bubble is two lobes, whose vapour weighs each
    # by its volume, not its area; 0: never.
    "lobe_centroid_s": 0.001,
}


#: Parameters of the stage (config.yaml ``masks:``); nested sections are merged key by key.
DEFAULTS: dict = {
    # classical (embedded, default) or sam (ONNX models from masks.sam.encoder/decoder).
    "backend": "classical",
    "classical": dict(CLASSICAL_DEFAULTS),
    "sam": dict(SAM_DEFAULTS),
    "associate": dict(ASSOCIATE_DEFAULTS),
    # Triangulated centres and the two views' agreement (surfphase.masks.anchors).
    "anchors": dict(ANCHOR_DEFAULTS),
    # Number of overlay pictures (evenly spaced frames).
    "overlay_frames": 4,
    # A frame whose intensities (0.1 to 99.9 percentile) span less than this fraction of
    # the full scale is blank (black, saturated, a lens cap); a camera whose every frame
    # is blank stops the stage, naming the session, camera and video.
    "min_dynamic_range": 0.01,
}
