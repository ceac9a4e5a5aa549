"""The settings of the stage-1 and stage-2 fits and their defaults (config ``fit:`` and
``fit2:``), kept apart from the fits themselves so that they import without torch: the
workflow checks the config's keys against them while it builds the DAG
(``workflow/rules/common.smk``). :mod:`surfphase.fit.stage` and
:mod:`surfphase.fit.stage2` hold them as their ``DEFAULTS`` (and ``FIT_OVERRIDES``).
"""

from __future__ import annotations

from surfphase.views_params import REFINE_DEFAULTS

#: Every hyperparameter of the fit, with its default (mirrored in config.yaml ``fit:``).
#: Units are given per entry; ``L`` is the scene extent in metres.
DEFAULTS: dict = {
    "seed": 0,  # torch generator seed (densification splits, subsampling)
    "frames": None,  # fit only the first N frames of the session (None: all)
    "use_sdf": True,  # False: "no SDF" ablation, opacity optimised directly
    "guidance": True,  # False: "no bubble guidance" ablation, plain per-frame refit
    # -- iterations -------------------------------------------------------------------
    "iters_first": 150,  # Adam steps at frame 0 (with densification)
    "iters_next": 30,  # Adam steps at every later frame
    "iters_reseed": 90,  # Adam steps at a frame where a merged bubble was re-seeded
    # -- initialisation ---------------------------------------------------------------
    "n_init": 1500,  # at most this many surfels seeded on the visual hull
    "hull_grid": 48,  # hull voxels along the longest bounding-box side
    "init_scale": 0.8,  # initial surfel std, in hull-voxel spacings
    "init_sdf": 0.1,  # initial |f|, units of L (opacity 1/2 at the initial γ)
    "spawn_min_surfels": 30,  # a mask bubble with fewer bound surfels gets new ones
    "spawn_max_surfels": 400,  # at most this many surfels per newly appearing bubble
    "spawn_grid": 24,  # hull voxels per newly appearing bubble
    # True: a new or merged bubble's hull is not carved by another bubble's pixels where
    # that bubble can hide it (init.visual_hull_surfels, occlusion) ...
    "hull_occlusion": True,
    # ... only in views where the bubble's mask has fewer than this fraction of the
    # pixels of its largest mask (a part is hidden there). On session01 it seeds the
    # half-hidden merged bubble 0.08 mm from its centroid instead of 0.53 mm; with this
    # gate, the five other synthetic sessions fit as with it off (BENCHMARKS.md, fit).
    "hull_occlusion_ratio": 0.75,
    # A bubble formed by a merge (the mask stage's events.csv) is seeded afresh from its
    # visual hull; see surfphase.fit.guidance.reseed_merges.
    "reseed_merges": True,
    "reseed_grid": 32,  # hull voxels per merged bubble
    "reseed_max_surfels": 800,
    # -- learning rates (2DGS's, f: 0.05) ---------------------------------------------
    # Position: lr_means·L metres per step. 2DGS uses 1.6e-4 × its camera extent (1.1 ×
    # the largest camera-centre distance from their mean: ≈ 2 cm for the reference rig);
    # L here is the bubbles' extent (≈ 3.7 mm on the demo), so 1e-3·L ≈ 3.7 µm per
    # step is about 2DGS's metric rate (3.2 µm) for this rig.
    "lr_means": 1e-3,
    "lr_means_decay": 0.1,  # exponential decay of lr_means over each frame's steps
    "lr_log_scales": 5e-3,
    "lr_quats": 1e-3,
    "lr_colors": 2.5e-3,
    "lr_sdf": 0.05,  # f in units of L
    "lr_log_gamma": 0.01,  # on ln γ
    "lr_opacity": 0.05,  # opacity logit, "no SDF" ablation only
    "adam_eps": 1e-15,
    # -- loss weights -----------------------------------------------------------------
    "lambda_app": 1.0,
    "lambda_dssim": 0.2,  # L1/D-SSIM mix: (1-λ)·L1 + λ·(1-SSIM)
    "lambda_geo": 1.0,
    "w_normal": 0.05,
    "w_gamma": 0.01,  # on L_γ/γ_m (relative hinge, dimensionless)
    "w_proj": 0.1,  # on L_proj (units of L)
    "w_mask": 0.0,  # on mean |α − masks| over the input views (0: off)
    "geo_from": 0.3,  # fraction of frame 0's steps before geometry losses start
    # L_proj ignores (point, view) pairs whose depth error exceeds proj_threshold·L
    # metres: the paper's 0.1 in normalised scene units, here units of L.
    "proj_threshold": 0.1,
    # -- densification (frame 0 only) -------------------------------------------------
    "densify": True,
    "densify_start": 0.1,  # fractions of iters_first
    "densify_stop": 0.6,
    "densify_every": 50,
    "grow_grad2d": 2e-4,  # NDC units, as 3DGS/2DGS/gsplat
    "grow_scale": 0.01,  # units of L
    "prune_opacity": 0.05,
    "prune_scale": 0.1,  # units of L
    "max_surfels": 3000,
    # -- bubble guidance --------------------------------------------------------------
    "v_init_nucleation": [0.03, 0.03, 0.0],  # m/s, lab frame: bubble 0 before history
    "v_init_bubble": [0.07, 0.3, 0.0],  # m/s, lab frame: other bubbles before history
    # After the advection, one rigid translation per bubble (ids ≥ 1) is fitted to the
    # new frame photometrically (surfphase.fit.register) before the per-surfel steps.
    "register_steps": 15,  # Adam steps of that translation fit (0: off)
    "lr_register": 0.01,  # its step size, units of L (decays to 1/10 over the steps)
    "register_silhouette": 3.0,  # weight of |α − masks| in that fit (0: photometric only)
    "register_silhouette_all": False,  # True: every bubble; False: merged bubbles only
    "register_silhouette_frames": 3,  # ... for this many frames after their merge
    # The heated surface (y = 0, docs/conventions.md §1) is solid plate: after every step the
    # surfel centres are put back on or above it (a projected gradient step); None = off.
    "floor_y": 0.0,  # metres, lab frame
    # -- reported tracks (bubbles.csv) ---------------------------------------------------
    # True: a bubble's (id >= 1) reported centre is its triangulated silhouette centre
    # (the mask stage's anchors.csv), reported only in frames where both input views see
    # it and agree; False: the centroid of its surfels, in every frame it has surfels.
    "anchor_centres": True,
    "min_track_frames": 3,  # ... in runs of at least this many consecutive frames
    # ... and where less than this share (0-1) of its silhouette is inside a view (the
    # anchors' ``visible``: a bubble mostly outside the frame, its centre fitted to a short
    # arc), it is reported without a velocity (empty), left out of its track's smoothing
    # and placed on the parabola through the track's nearest other centres (a track with
    # fewer than 3 others: as measured, and no velocity anywhere on it). Such a centre
    # moves with the bubble's shape modes as well as its centre (0.05 r_eq off on the
    # bench's leaving bubbles 5-15 % inside; velocities from centres 5-25 % inside 10 %
    # off, from 25-60 % inside 4-5 %, whole 2.6 %), so a track through it would differ
    # from the velocities beside it. 0: every centre counts.
    "track_min_visible": 0.25,
    # Up to this many consecutive frames missing between two centres of one bubble (a
    # frame where its two views disagreed, so the mask stage gave it no centre) are
    # reported all the same, placed like those centres (no velocity), and the track runs
    # through them: one bad frame no longer cuts a track in two, nor drops its short end
    # (min_track_frames). 0: a gap ends the track.
    "track_gap_frames": 1,
    "track_window_s": 0.003,  # > 0: centroids and velocities of each bubble track from a
    # moving polynomial over this many seconds (Savitzky-Golay; 0: per-frame values)
    "track_order": 1,  # polynomial order of that fit
    # ... and at each end of a track whose centre curves significantly over its first /
    # last track_end_window_s seconds (the quadratic coefficient of a parabola more than
    # track_end_t standard errors from 0, the residuals' serial correlation allowed for:
    # surfphase.fit.outputs.quadratic_t), a moving parabola over that window there: a
    # straight line over a track's last window lags an accelerating bubble (0: off);
    # not on a track shorter than that window (its ends are all of it).
    "track_end_window_s": 0.005,
    "track_end_t": 5.0,
    # ... and, with a window > 0 (seconds), the track is the mean of that and a second
    # moving polynomial of order track_blend_order over this window (0: off): a short
    # line that follows a bubble's changes and a long parabola that averages more noise;
    # on a track shorter than this window, only where the track's whole curvature is
    # significant (track_end_t's test): else that parabola is mostly the centres' bias.
    "track_blend_window_s": 0.008,
    "track_blend_order": 2,
    # ... and on a track of at least 7 frames, a centre farther from that smoothed track
    # than this many times the track's median distance is replaced by its smoothed value
    # and the track smoothed again: one damaged frame does not bend its neighbours (0: off).
    "track_outlier_k": 6.0,
    # ... and, > 0 (pixels), every moving polynomial of that smoothing weights each centre
    # by how well its two views agree (the anchors' reproj_px, e): 1 / (1 + (e / this)²).
    # A view's silhouette damaged by the plate or a neighbour puts its centroid off, and
    # the views then disagree; 0: every centre weighs the same.
    "track_reproj_px": 0.2,
    # Two views leave a bubble's extent along their bisector (the mean viewing direction)
    # unseen: surfels may sit anywhere in the visual hull's long corners. With a number k,
    # after every step a surfel farther than k·r along that axis from its bubble's centre
    # is put back at k·r (centre and r from the frame's masks: triangulated centroids, the
    # largest equivalent radius over the views; nearest bubble ≥ 1 by distance / r; the
    # nucleation region is left free). None = off.
    "depth_bound": 1.2,
    # -- appearance -------------------------------------------------------------------
    # A backlit bubble is bright where the interface faces the camera and dark where it
    # is oblique, so one interface point looks different from each camera. True: every
    # view's surfel colours get one learned curve of |normal · view direction| added
    # (surfphase.render.shading; shade_knots values per channel, starting at zero).
    "shading": False,
    "shade_knots": 11,
    "lr_shade": 0.01,
    # With shading, False: no per-surfel colour at all (every surfel's is 0 and the curve,
    # started at the mean colour inside the masks, carries the whole bubble's look), so
    # the look can only be explained by where the surfels face.
    "surfel_colors": True,
    # -- outputs ----------------------------------------------------------------------
    "background": "images",  # "images": per-view temporal median of background pixels;
    # "constant": one colour, the median of those; or a number in [0, 1]
    "render_frames": 3,  # frames with observed-vs-rendered PNGs
    "log_every": 10,  # curves.csv row every N steps (and the last)
}


#: Stage-2 settings (config ``fit2:``), with their defaults. Keys of the stage-1 fit
#: (:data:`DEFAULTS`) may be given in ``fit2:`` too; they override
#: the stage-1 settings and :data:`FIT_OVERRIDES` for stage 2.
STAGE2_DEFAULTS: dict = {
    "weight_inputs": 1.0,  # photometric weight of each input view
    "weight_near": 0.5,  # ... of each refined orbit view not in far_views
    "weight_far": 0.25,  # ... of each refined orbit view in far_views
    # orbit view numbers (orbitNN) that count as far: those the refinement calls far
    "far_views": list(REFINE_DEFAULTS["far_views"]),
    "views_per_step": 4,  # refined views rendered per step (0: all of them)
    "bg_alpha_max": 0.02,  # stage-1 alpha below which a refined pixel is background
}

#: Stage-1 settings that stage 2 changes by default: it starts from converged surfels,
#: so frame 0 needs fewer steps and no densification.
FIT_OVERRIDES: dict = {"iters_first": 60, "densify": False, "geo_from": 0.0}
