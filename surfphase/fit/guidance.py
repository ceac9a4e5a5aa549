"""Bubble guidance (docs/method.md §5.4): how a later frame's fit starts from the one before.

Before frame ``t`` > 0 is optimised, each bubble's surfels are advected by its velocity
(:func:`advect_velocities`, :func:`surfphase.fit.binding.advect`) and shifted rigidly,
one translation per bubble, to fit the new frame (:func:`advect_and_register`,
:func:`surfphase.fit.register.register_bubbles`); a bubble that a merge formed at ``t``
is dropped (:func:`reseed_merges`) to be seeded afresh from its visual hull. Units:
positions metres (lab frame), time seconds, velocity m/s.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import torch

from surfphase.fit import binding, init, register
from surfphase.fit.densify import select_surfels
from surfphase.fit.model import SurfelModel
from surfphase.fit.record import FrameRecord
from surfphase.fit.session import SessionData


def advect_velocities(
    records: Sequence[FrameRecord], data: SessionData, p: dict
) -> tuple[dict[int, np.ndarray], np.ndarray]:
    """Bubble and per-surfel velocities (m/s) from the last two finished frames.

    Uses the surfels bound to each bubble at the last frame that also existed at the one
    before (matched by surfel id), their positions at both frames. Bubbles whose track
    begins at the last frame (:func:`~surfphase.fit.binding.track_continues`: a merge, a
    split, a new id) have no history: a bubble re-seeded at a merge gets its parents'
    volume-weighted velocity (momentum), any other the configured initial velocity; so
    do surfels without history.
    """
    cur = records[-1]
    bub = cur.bubble
    v_nuc = np.asarray(p["v_init_nucleation"], dtype=np.float64)
    v_bub = np.asarray(p["v_init_bubble"], dtype=np.float64)
    surfel_v = np.where((bub == 0)[:, None], v_nuc, 0.0)
    vb: dict[int, np.ndarray] = {}
    if len(records) >= 2:
        prev = records[-2]
        _, ic, ip = np.intersect1d(cur.ids, prev.ids, assume_unique=True, return_indices=True)
        dt = data.times[len(records) - 1] - data.times[len(records) - 2]
        w = binding.surfel_weights(cur.opacity[ic], np.exp(cur.log_scales[ic]))
        vb = binding.bubble_velocities(prev.means[ip], cur.means[ic], bub[ic], w, dt)
        # A bubble whose track starts at the last frame (merge, split, new id) has no
        # history yet: its surfels' motion across the event is not its velocity.
        w_prev = binding.surfel_weights(prev.opacity[ip], np.exp(prev.log_scales[ip]))
        for b in [b for b in vb if b > 0]:
            if binding.track_continues(bub[ic], prev.bubble[ip], w, w_prev, b) is None:
                del vb[b]
        surfel_v[ic] = (cur.means[ic].astype(np.float64) - prev.means[ip]) / dt
        if p["anchor_centres"]:
            # Where both frames have the bubble's triangulated centre, its motion is the
            # centre's (no surfel re-binding in it).
            c1, c0 = data.anchor_centres(len(records) - 1), data.anchor_centres(len(records) - 2)
            for b in [b for b in vb if b > 0 and b in c1 and b in c0]:
                vb[b] = (c1[b] - c0[b]) / dt
    reseeded = cur.reseeded or {}
    for b in np.unique(bub):
        if b > 0 and int(b) not in vb:
            vb[int(b)] = np.asarray(reseeded.get(int(b), v_bub), dtype=np.float64)
        if b == 0 and 0 not in vb:
            vb[0] = v_nuc
    return vb, surfel_v


def recent_merges(data: SessionData, t: int, frames: int) -> list[int]:
    """Bubbles that a merge formed at one of the ``frames`` frames before ``t``."""
    return sorted({b for f in range(t - frames, t) for b in data.merges.get(f, {})})


def reseed_merges(
    model: SurfelModel,
    data: SessionData,
    t: int,
    velocities: dict[int, np.ndarray],
    p: dict,
) -> tuple[dict[int, np.ndarray], np.ndarray]:
    """Drop the surfels of bubbles that a merge formed at frame ``t``; return their
    parents' velocity and the kept rows.

    The merges are the mask stage's (``events.csv``: the merged bubble's id first shows
    at ``t``). The parents' surfels sit where two spheres were and need many frames to
    become one interface, and their centroid drifts meanwhile, which reads as velocity;
    the merged bubble is therefore seeded afresh from its visual hull
    (:func:`~surfphase.fit.seeding.spawn_bubbles`), like a bubble that appears. Its first advection uses its
    parents' velocities weighted by their volumes (radii of the previous frame's mask
    spheres, cubed: momentum is conserved).

    Returns:
        ``{merged bubble: (3,) m/s}`` and the (N,) bool rows kept; ``model`` is edited.
    """
    merges = data.merges.get(t, {})
    keep = np.ones(model.n, dtype=bool)
    out: dict[int, np.ndarray] = {}
    if not merges:
        return out, keep
    labels = data.labels(t)
    bound = binding.bind_surfels_to_bubbles(
        model.means.detach().double().cpu().numpy(), data.cameras, labels
    )
    spheres = init.bubble_spheres(data.cameras, data.labels(t - 1))
    v_bub = np.asarray(p["v_init_bubble"], np.float64)
    for b, parents in sorted(merges.items()):
        parents = sorted(q for q in parents if q >= 1 and q in spheres)
        if not (bound == b).any():
            continue
        if parents:
            vols = np.array([spheres[q][1] ** 3 for q in parents])
            vel = np.array([velocities.get(q, v_bub) for q in parents], np.float64)
            out[int(b)] = (vols[:, None] * vel).sum(0) / vols.sum()
        else:
            out[int(b)] = v_bub
        keep &= bound != b
    if out:
        select_surfels(model, None, torch.as_tensor(keep, device=model.means.device))
    return out, keep


def advect_and_register(
    model: SurfelModel,
    records: Sequence[FrameRecord],
    data: SessionData,
    t: int,
    p: dict,
    viewmats: torch.Tensor,
    Ks: torch.Tensor,
    backgrounds: torch.Tensor,
) -> tuple[dict[int, np.ndarray], dict[int, np.ndarray]]:
    """Move the surfels of the last finished frame to frame ``t``: advect each bubble's
    by its velocity, then fit one rigid translation per bubble to the input views
    (``viewmats`` (C, 4, 4), ``Ks`` (C, 3, 3), ``backgrounds`` (C, H, W, D)).

    Returns:
        The bubble velocities ``{bubble: (3,) m/s}`` used, and the translations
        ``{bubble: (3,) m}`` fitted; ``model``'s means are set in place.
    """
    dev, dtype = viewmats.device, viewmats.dtype
    labels = data.labels(t)
    vb, vs = advect_velocities(records, data, p)
    dt = data.times[t] - data.times[t - 1]
    new_means = binding.advect(
        records[-1].means, records[-1].bubble, vb, vs, dt, per_surfel_ids=(0,)
    )
    with torch.no_grad():
        model.params["means"].data.copy_(torch.as_tensor(new_means, dtype=dtype))
    registered = register.register_bubbles(
        model,
        records[-1].bubble,
        torch.as_tensor(data.images(t), device=dev),
        viewmats,
        Ks,
        backgrounds,
        steps=int(p["register_steps"]),
        lr=p["lr_register"] * model.extent,
        foreground=(
            torch.as_tensor(np.stack(labels) >= 0, dtype=dtype, device=dev)
            if p["register_silhouette_all"]
            else None
        ),
        w_silhouette=float(p["register_silhouette"]),
        silhouettes={
            b: torch.as_tensor(np.stack(labels) == b, dtype=dtype, device=dev)
            for b in recent_merges(data, t, int(p["register_silhouette_frames"]))
        },
    )
    return vb, registered
