"""The settings of the mesh stage and their defaults (config ``mesh:``), kept apart from
the stage so that they import without torch: the workflow checks the config's keys
against them while it builds the DAG (``workflow/rules/common.smk``).
:mod:`surfphase.mesh.stage` holds them as its ``DEFAULTS``.
"""

from __future__ import annotations

DEFAULTS: dict = {
    "voxels": 64,  # voxels along the longest side of the surfels' bounding box
    "voxel_m": None,  # or an explicit voxel edge, metres (overrides "voxels")
    "trunc_voxels": 3.0,  # truncation τ, in voxels
    "margin_voxels": 4.0,  # grid margin around the surfels' bounding box, in voxels
    "render_scale": 2.0,  # depth maps rendered at this multiple of the input size
    "opacity_min": 0.1,  # surfels below this are left out of the depth maps ...
    "solid": True,  # ... the others rendered opaque, so thin shells block the view
    "scale_factor": 1.5,  # surfel sizes ×this for the depth maps (closes pinholes)
    "alpha_min": 0.5,  # pixels with more accumulated alpha get the median depth
    "silhouette_alpha": 0.05,  # silhouette (holes filled) threshold; see render_depths
    "n_orbit": 11,
    "orbit_step_deg": 30.0,
    "min_component_m": 3.0e-4,  # components with a smaller bounding-box diagonal go
    # ... and, in each bubble's mesh, components whose bounding-box diagonal is less than
    # this fraction of its largest component's (a bubble is one body: these are slivers
    # of the hull's end slices, misplaced in depth where the views meet at a small
    # angle; 0: keep all).
    "min_piece_frac": 0.3,
    "smooth_steps": 5,  # Taubin steps
    "max_hole_edges": 30,
    "speed_max": 0.4,  # m/s, top of the colour map; "session" = max vertex speed seen
    # The heated surface (y = 0, docs/conventions.md §1): the volume below it is solid plate, so
    # the fused volume is cut there and bubbles sitting on it get a flat base; None = off.
    "floor_y": 0.0,  # metres, lab frame
    # With the session's masks: the fused volume is intersected with the masks' visual
    # hull (every input view's silhouettes, grown by this many pixels), so nothing is
    # meshed where an input view sees no bubble (carve_px: None = off).
    "carve_px": 1.0,
    # ... and, per bubble, with its elliptic hull: each horizontal cross-section the
    # ellipse closest to a circle that both views' silhouettes bound (surfphase.mesh.hull;
    # a shape prior: a rising bubble is close to axisymmetric about the vertical).
    "ellipse_hull": True,
    # What the surface is: "fused", the surfels' depth maps fused (TSDF) and carved by
    # the hulls above; or "hull", each bubble's elliptic hull alone, on its own grid of
    # hull_voxels_per_radius voxels per (silhouette-equivalent) radius, the surfels
    # giving only the vertices' velocities (surfphase.mesh.hull.bubble_hull_volume).
    "surface": "hull",
    "hull_voxels_per_radius": 8.0,
    # ... and each slice's ellipse centre a straight-line fit over this many slices on
    # either side (surfphase.mesh.hull.smooth_centres; 0: each slice's own)
    "hull_centre_slices": 4,
    # ... and each slice's two half-widths taken as known to this many pixels of their
    # views: the ellipse is the one closest to a circle within that (0: exactly; views at
    # a small angle turn a pixel's difference between the widths into an elongated
    # section, surfphase.mesh.hull.closest_widths)
    "hull_width_tol_px": 0.5,
    # ... and each bubble's hull moved so that its centroid is the bubble's centre in the
    # fit's bubbles.csv (the triangulated sub-pixel silhouette centres, smoothed along
    # its track), where the fit reports it (surfphase.mesh.surfaces.hull_mesh_frame).
    "hull_at_centres": True,
    # ... and an id (>= 1) that the fit's bubbles.csv never reports meshed only in frames
    # where its two silhouettes are one object (their centroids' point reprojects within
    # 0.25 of each one's equivalent radius, their sizes there within 1.5x: the nucleation
    # region's rule, surfphase.mesh.hull.bubble_pieces): an id the two views' masks give
    # to different things (a strip along the plate's edge in one view, a border speck in
    # the other) otherwise gets a hull where their rays happen to cross, millimetres from
    # any bubble. A reported bubble is meshed in every frame both views show it, and so is
    # one the border cuts in both views (cut, they disagree; surfphase.mesh.stage.
    # spared_ids). False: every id both views show.
    "hull_agreeing": True,
    # ... and each bubble's mesh scaled about its centre so that its images have the
    # areas of its silhouettes at the recording's native resolution (the masks'
    # instances.csv), the labels the hull is made from being the fit's: a bubble a few of
    # their pixels across loses volume to them; only a factor within hull_area_limits
    # (otherwise the masks and the hull disagree on more than a size) and only where no
    # view's border cuts the bubble (surfphase.mesh.surfaces.scale_to_silhouettes); each
    # hull of the nucleation region likewise, to the areas of the region's whole pieces
    # whose centroids fall on its silhouettes (a bubble growing on the plate).
    "hull_native_area": True,
    "hull_area_limits": [0.8, 1.25],
    # ... and each bubble the image border cuts in a view drawn whole beyond the border
    # before its hull is made: the shape its track shows whole in the nearest frame of
    # that view, moved onto its visible outline, by the rules the mask stage's centres
    # use (masks: anchors: min_visible_tracked, max_shape_rms; surfphase.mesh.cut);
    # otherwise its hull, and its mesh, stop at the border.
    "complete_cut": True,
    # ... and one whose track shows no whole shape, the circle fitted to its visible
    # outline, by the same rules (a prior: a bubble of a millimetre is near-spherical);
    # so too each piece of the nucleation region the bottom border cuts (a bubble growing
    # on a plate just below the frame), filled as if the border closed it.
    "complete_cut_circles": True,
    # ... and one less of which is inside than min_visible_tracked, the circle of the
    # radius its track's nearest frame gave it so, placed on its visible outline.
    "complete_cut_tracked_circles": True,
    # ... and one whose track shows no whole shape, before any fitted circle, the image
    # of the sphere the mask stage fitted to it (anchors.csv: its centre x, y, z and
    # radius r_m in the frame; a bubble never seen whole has its centre from its
    # outlines in both views), where its visible part fits inside that circle.
    "complete_cut_spheres": True,
    "frames": None,  # positions (0-based) in surfels.npz; None = all
}
