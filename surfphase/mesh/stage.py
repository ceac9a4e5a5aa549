"""The mesh stage: one PLY mesh per fitted frame, with per-vertex velocity.

``OUT/<frame:06d>.ply`` — binary PLY, vertex ``x y z`` (float32, metres, lab frame),
``vx vy vz`` (float32, m/s: the velocity of the nearest alive surfel) and ``red green
blue`` (uchar: viridis over [0, ``speed_max``] m/s); triangle faces.
``OUT/vtk/<frame:06d>.vtp`` — the same mesh as VTK XML PolyData for ParaView (VTK's
PLY reader drops ``vx vy vz``): point arrays ``velocity`` (3 components, m/s) and
``speed`` (m/s), field data ``frame`` and ``TimeValue`` (s); see :mod:`surfphase.mesh.vtkxml`.
``OUT/<session>.pvd`` (``OUT/mesh.pvd`` when the session is unknown) — the frames as one
ParaView time series, each at its time in seconds (``time_s`` of ``surfels.npz``).
``OUT/mesh.json`` — the parameters used, ``pvd`` (the series' file name) and, per frame,
``frame``, ``time_s``, ``vertices``, ``faces``, ``components``, ``watertight``, ``seconds``.

Method (:mod:`surfphase.mesh.surfaces`, config ``mesh: surface``): ``hull`` (the
default) meshes each bubble's elliptic hull from the masks on its own grid
(:mod:`surfphase.mesh.hull`), each vertex taking the velocity of the nearest surfel of
its bubble; ``fused`` renders the frame's alive surfels (median depth where alpha > 0.5)
into the input cameras and ``n_orbit`` orbit views about the surfels' mean, fuses the
depth maps into a truncated signed distance volume (:mod:`surfphase.mesh.fuse`) and
carves it by the masks' hulls. Both are cut at the heated surface (``floor_y``: nothing
lies below it), meshed by marching cubes and cleaned with pymeshlab
(:mod:`surfphase.mesh.cleanup`).

Resuming and windows: every finished frame is saved at once (``<frame:06d>.npz``:
vertices, faces, velocities, keyed by :func:`mesh_key`) in a side folder,
``OUT.partial/``; a killed job, rerun, reads those back instead of meshing them again,
and ``OUT/`` is written into a temporary folder and renamed, so it appears whole or not
at all. A long session can be meshed by independent jobs, one per window of frames
(:func:`run_mesh_window`, :mod:`surfphase.mesh.windows`); :func:`gather_mesh` then
writes the same ``OUT/`` as a single job (speed colours need the whole session).
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import time
import zipfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd

from surfphase.cameras import Camera
from surfphase.folders.fit import BUBBLES, SURFELS, read_fit_bubbles, read_fit_surfels
from surfphase.folders.ingest import read_ingest
from surfphase.folders.masks import ANCHORS as MASKS_ANCHORS
from surfphase.folders.masks import INFO as MASKS_INFO
from surfphase.folders.masks import INSTANCES as MASKS_INSTANCES
from surfphase.folders.masks import labels_path, read_anchors, read_masks
from surfphase.io import atomic_path, atomic_write_json, atomic_write_text, part_dir, replace_dir
from surfphase.masks.params import ANCHOR_DEFAULTS
from surfphase.mesh.cleanup import mesh_stats
from surfphase.mesh.cut import completed_view, cut_shapes, nucleation_cut_shapes
from surfphase.mesh.measure import bubble_sizes, vertex_bubbles
from surfphase.mesh.params import DEFAULTS  # every setting, with its default
from surfphase.mesh.ply import speed_colors, write_mesh_ply
from surfphase.mesh.surfaces import (  # noqa: F401  (re-exported: the stage's per-frame functions)
    bubble_vertex_velocities,
    cut_below,
    hull_mesh_frame,
    mesh_frame,
    silhouette_distance,
    surfel_spheres,
    vertex_velocities,
    view_cameras,
)
from surfphase.mesh.vtkxml import write_polydata, write_pvd
from surfphase.mesh.windows import window_positions
from surfphase.progress import Progress
from surfphase.settings import check_keys


def mesh_params(params: dict | None) -> dict:
    """Defaults updated with ``params``; unknown keys are an error."""
    check_keys(DEFAULTS, params, "mesh")
    return {**DEFAULTS, **(params or {})}


#: The sources a frame's mesh depends on (:func:`surfphase.io.code_fingerprint`).
CODE_SOURCES = ("cameras.py", "mesh", "render")


def _code_fingerprint() -> str:
    """Hash of the sources a frame's mesh depends on (mesh and renderer, cameras)."""
    from surfphase.io import code_fingerprint

    return code_fingerprint(CODE_SOURCES)


def _file_hash(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def mesh_key(surfels_path: Path, cameras_path: Path, p: dict, device: str) -> str:
    """What a finished frame's checkpoint must match to be reused: the fit and camera
    files (content), the parameters that shape a frame's mesh, the device and the code.

    ``speed_max`` and ``frames`` are left out: they choose colours and frames, not the
    mesh of a frame, so changing them reuses the frames already meshed.
    """
    shape = {k: v for k, v in p.items() if k not in ("speed_max", "frames")}
    h = hashlib.sha256(json.dumps(shape, sort_keys=True, default=str).encode())
    for part in (device, _file_hash(surfels_path), _file_hash(cameras_path), _code_fingerprint()):
        h.update(part.encode())
    return h.hexdigest()


@dataclass
class _Session:
    """One session's fitted surfels and cameras, ready to mesh."""

    surfels: dict
    inputs: list[Camera]
    session: str | None
    p: dict
    device: str
    key: str
    picks: list[int]  # positions (0-based) in surfels.npz to mesh, in order
    masks: list[np.ndarray] | None = None  # per input camera, (T, H, W) labels (carve_px)
    centres: dict[int, dict[int, np.ndarray]] | None = None  # frame → bubble → (3,) m
    cut_rules: dict | None = None  # masks: anchors: rules of the cut silhouettes (complete_cut)
    areas: dict[int, dict[int, list[float]]] | None = None  # frame → bubble → per view px
    pieces: dict[int, list[np.ndarray]] | None = None  # frame → per view (N, 3) u, v, px
    spheres: dict[int, dict[int, tuple]] | None = None  # frame → bubble → ((3,) m, r m)
    attached: dict[int, dict[int, list]] | None = None  # frame → view → [((3,) m, r m)]


def _open_session(
    fit_dir: Path,
    ingest_dir: Path,
    params: dict | None,
    device: str,
    masks_dir: Path | None = None,
) -> _Session:
    p = mesh_params(params)
    if p["surface"] == "fused":  # it renders, with torch
        from surfphase.device import resolve_device

        dev = str(resolve_device(device))
    else:  # the hulls are numpy on the CPU: no torch to import (2-4 s a job)
        from surfphase.device import check_setting

        check_setting(device)
        dev = "cpu"
    surfels_path = fit_dir / SURFELS
    surfels = read_fit_surfels(fit_dir)
    ingest = read_ingest(ingest_dir, stacks=False, min_cameras=0)
    cam_path, cams, session = ingest.cameras_path, ingest.cameras, ingest.session
    names = [str(c) for c in np.atleast_1d(surfels.get("cameras", []))]
    inputs = [cams[n] for n in names if n in cams] or [
        c for c in cams.values() if c.role == "input"
    ]
    if not inputs:
        raise ValueError(f"{cam_path}: no input cameras")
    n_frames = surfels["alive"].shape[0]
    picks = list(range(n_frames)) if p["frames"] is None else [int(t) for t in p["frames"]]
    for t in picks:
        if not 0 <= t < n_frames:
            raise ValueError(f"{fit_dir}: frame position {t} outside 0..{n_frames - 1}")
    if "time_s" not in surfels or np.shape(surfels["time_s"]) != (n_frames,):
        raise ValueError(f"{surfels_path}: no time_s per frame (seconds), needed for the .pvd")
    masks, mask_paths = None, []
    if p["surface"] not in ("fused", "hull"):
        raise ValueError(f"mesh: surface must be 'fused' or 'hull', got {p['surface']!r}")
    if p["surface"] == "hull" and masks_dir is None:
        raise ValueError(
            f"session {session}: mesh: surface: hull meshes the masks' elliptic hulls, "
            "and no masks folder was given (--masks)"
        )
    if masks_dir is not None and (p["carve_px"] is not None or p["surface"] == "hull"):
        labels = read_masks(masks_dir, inputs, session, min_frames=n_frames).labels
        masks = list(labels.values())
        mask_paths = [labels_path(masks_dir, n) for n in labels]
    centres, hashed = None, list(mask_paths)  # the carve depends on the masks' content too
    if p["surface"] == "hull" and p["hull_at_centres"] and (fit_dir / BUBBLES).is_file():
        centres = bubble_centres(read_fit_bubbles(fit_dir, f"session {session}"))
        hashed.append(fit_dir / BUBBLES)
    cut_rules = None
    if p["surface"] == "hull" and p["complete_cut"] and masks_dir is not None:
        cut_rules = masks_anchor_rules(masks_dir)
        hashed += [f for f in [masks_dir / MASKS_INFO] if f.is_file()]
    spheres = attached = None
    if cut_rules is not None and p["complete_cut_spheres"]:
        anchors_tab = read_anchors(masks_dir, f"session {session}")
        if anchors_tab is not None and "r_m" in anchors_tab.columns:
            spheres = anchor_spheres(anchors_tab)
            hashed.append(Path(masks_dir) / MASKS_ANCHORS)
        attached = attached_spheres(masks_dir, inputs)
    areas = pieces = None
    if p["surface"] == "hull" and p["hull_native_area"] and masks_dir is not None:
        inst = Path(masks_dir) / MASKS_INSTANCES
        if inst.is_file():
            table = pd.read_csv(inst)
            areas = silhouette_areas(table, inputs)
            pieces = nucleation_areas(table, inputs)
            hashed.append(inst)
    key = mesh_key(surfels_path, cam_path, p, dev)
    if hashed:
        key = hashlib.sha256("".join([key, *map(_file_hash, hashed)]).encode()).hexdigest()
    found = (masks, centres, cut_rules, areas, pieces, spheres, attached)
    return _Session(surfels, inputs, session, p, dev, key, picks, *found)


def anchor_spheres(anchors_tab: pd.DataFrame) -> dict[int, dict[int, tuple]]:
    """``{frame: {bubble: ((3,) centre m, radius m)}}`` of a masks folder's
    ``anchors.csv`` rows with ids ≥ 1 and a finite centre and radius ``r_m``."""
    out: dict[int, dict[int, tuple]] = {}
    rows = anchors_tab[anchors_tab["bubble"] >= 1]
    xyz = rows[["x", "y", "z"]].to_numpy(np.float64)
    r = rows["r_m"].to_numpy(np.float64)
    for f, b, c, rr in zip(rows["frame"], rows["bubble"], xyz, r, strict=True):
        if np.isfinite(c).all() and np.isfinite(rr) and rr > 0:
            out.setdefault(int(f), {})[int(b)] = (c, float(rr))
    return out


def attached_spheres(masks_dir: Path, cameras: list[Camera]) -> dict[int, dict[int, list]]:
    """``{frame: {view index: [((3,) centre m, radius m)]}}`` of a masks folder's
    ``masks.json`` ``attached_hidden`` entries: the circles, as spheres, of attached
    bubbles that a free bubble hides in part in one view (``masks: anchors:
    occlusion``), per input camera of ``cameras`` (entries of other cameras left out)."""
    info = Path(masks_dir) / MASKS_INFO
    if not info.is_file():
        return {}
    index = {c.name: k for k, c in enumerate(cameras)}
    out: dict[int, dict[int, list]] = {}
    for e in json.loads(info.read_text()).get("attached_hidden") or []:
        k = index.get(str(e["camera"]))
        if k is not None:
            X = np.array([e["x"], e["y"], e["z"]], np.float64)
            out.setdefault(int(e["frame"]), {}).setdefault(k, []).append((X, float(e["r_m"])))
    return out


def silhouette_areas(
    instances: pd.DataFrame, cameras: list[Camera]
) -> dict[int, dict[int, list[float]]]:
    """``{frame: {bubble: [area per camera]}}`` (pixels of ``cameras``) of the bubbles
    (ids ≥ 1) that every camera's silhouettes show whole, from a masks folder's
    ``instances.csv`` (areas counted at the recording's native resolution, in the fit
    frame's pixels; an id's pieces summed); a bubble whose box reaches a view's image
    border is left out (its silhouette there is cut)."""
    out: dict[int, dict[int, list[float]]] = {}
    need = {"frame", "camera", "bubble", "area", "x0", "y0", "x1", "y1"}
    if not need <= set(instances.columns):
        return out
    rows = instances[instances["bubble"] >= 1]
    per_view = []
    for cam in cameras:
        g = rows[rows["camera"] == cam.name]
        edge = (
            (g["x0"] <= 0) | (g["y0"] <= 0) | (g["x1"] >= cam.width - 1)
            | (g["y1"] >= cam.height - 1)
        )  # fmt: skip
        area = g.groupby(["frame", "bubble"])["area"].sum()
        cut = edge.groupby([g["frame"], g["bubble"]]).any()
        per_view.append(area[~cut.reindex(area.index, fill_value=False)])
    both = pd.concat(per_view, axis=1, join="inner")
    for (frame, bubble), vals in both.iterrows():
        out.setdefault(int(frame), {})[int(bubble)] = [float(v) for v in vals]
    return out


def nucleation_areas(instances: pd.DataFrame, cameras: list[Camera]) -> dict[int, list[np.ndarray]]:
    """``{frame: [per camera (N, 3) centroid column, row and area]}`` (pixels of
    ``cameras``) of the nucleation region's pieces (id 0) in ``instances.csv`` (areas
    counted at the recording's native resolution, in the fit frame's pixels), a piece
    whose box reaches its view's image border left out (its silhouette is cut)."""
    need = {"frame", "camera", "bubble", "area", "cx", "cy", "x0", "y0", "x1", "y1"}
    if not need <= set(instances.columns):
        return {}
    rows = instances[instances["bubble"] == 0]
    out: dict[int, list[np.ndarray]] = {}
    for f in sorted(set(rows["frame"].astype(int))):
        per_view = []
        for cam in cameras:
            g = rows[(rows["frame"] == f) & (rows["camera"] == cam.name)]
            whole = (
                (g["x0"] > 0) & (g["y0"] > 0) & (g["x1"] < cam.width - 1)
                & (g["y1"] < cam.height - 1)
            )  # fmt: skip
            per_view.append(g.loc[whole, ["cx", "cy", "area"]].to_numpy(np.float64))
        out[f] = per_view
    return out


def masks_anchor_rules(masks_dir: Path) -> dict:
    """The ``masks: anchors:`` settings the masks folder's centres were made with
    (``masks.json``'s parameters; the defaults where it has none)."""
    rules = dict(ANCHOR_DEFAULTS)
    info = Path(masks_dir) / MASKS_INFO
    if info.is_file():
        rules.update((json.loads(info.read_text()).get("params") or {}).get("anchors") or {})
    return rules


def frame_views(s: _Session, t: int, cache: list[dict]) -> tuple[list[Camera], list[np.ndarray]]:
    """The input cameras and (H, W) labels the hull of position ``t`` is made from: with
    ``complete_cut``, each view's silhouettes the border cuts drawn whole beyond it, on a
    grown grid (:mod:`surfphase.mesh.cut`; with ``complete_cut_spheres`` those whose
    track shows no whole shape as the image of the mask stage's sphere,
    :func:`sphere_shapes`, before any fitted circle; with ``complete_cut_circles`` the
    nucleation region's pieces the bottom border cuts as their circles, :func:`nucleation_cut_shapes`);
    ``cache``: per view, its whole shapes."""
    labels = [np.asarray(m[t]) for m in s.masks]
    if s.cut_rules is None:
        return list(s.inputs), labels
    spheres = s.spheres.get(int(s.surfels["frame"][t]), {}) if s.spheres else {}
    views = []
    for cam, lab, m, c in zip(s.inputs, labels, s.masks, cache, strict=True):
        # The mask stage's sphere comes before a circle fitted to the visible arc (of an
        # oblate bubble's lower arc: too large, its centre beyond the bubble's).
        sph = sphere_shapes(cam.undistorted(), lab, spheres, set())
        shapes = cut_shapes(
            m, t, s.cut_rules, c, bool(s.p["complete_cut_circles"]),
            bool(s.p["complete_cut_tracked_circles"]), sph,
        )  # fmt: skip
        shapes.update({b: e for b, e in sph.items() if b not in shapes})
        pieces = nucleation_cut_shapes(lab, s.cut_rules) if s.p["complete_cut_circles"] else []
        views.append(completed_view(cam, lab, shapes, pieces))
    return [v[0] for v in views], [v[1] for v in views]


#: Least share of a bubble's sphere image that other bubbles' silhouettes cover for it
#: to count as hidden behind them in that view (:func:`hidden_parts`).
HIDDEN_MIN_SHARE = 0.1


def hidden_parts(
    s: _Session, t: int, views: list[Camera], labels: list[np.ndarray]
) -> dict[int, list[np.ndarray | None]] | None:
    """Per bubble hidden behind others in some view, per view, the (H, W) bool pixels of
    ``labels`` (:func:`frame_views`' grids, cameras ``views``) it covers there behind
    them: where the image of its anchors' sphere (``complete_cut_spheres``; centre's
    projection, radius f·r / depth) lies on other bubbles' silhouettes, when that is at
    least :data:`HIDDEN_MIN_SHARE` of the image and its own silhouette fits inside it
    (at most 10 % of its pixels more than a pixel outside: the labels were split at the
    recording's resolution, and a stray piece may lie apart); None in the other views. The mask stage splits
    a fused silhouette between the bubbles in it (``masks: anchors: occlusion``): the
    one behind keeps only what shows of it. The nucleation region (id 0) has an entry
    where an attached bubble's circle (``masks.json``'s ``attached_hidden``,
    :func:`attached_spheres`) lies so on bubbles' silhouettes and its image holds
    nucleation pixels: the pixels of those silhouettes in its image."""
    if not s.spheres and not s.attached:
        return None
    spheres = (s.spheres or {}).get(int(s.surfels["frame"][t]), {})
    attached = (s.attached or {}).get(int(s.surfels["frame"][t]), {})
    out: dict[int, list[np.ndarray | None]] = {}
    from surfphase.masks.anchors import NUCLEATION_ID, sphere_image

    for k, (cam, lab) in enumerate(zip(views, labels, strict=True)):
        cam = cam.undistorted()
        vv, uu = np.mgrid[0 : lab.shape[0], 0 : lab.shape[1]]
        for X, r in attached.get(k, []):
            circle = sphere_image(cam, X, r)
            if circle is None:
                continue
            u, v, rho = circle
            disc = np.hypot(uu - u, vv - v) <= rho
            behind = disc & (lab >= 1)
            if behind.sum() < HIDDEN_MIN_SHARE * np.pi * rho * rho:
                continue
            if not (disc & (lab == NUCLEATION_ID)).any():
                continue
            views_b = out.setdefault(NUCLEATION_ID, [None] * len(views))
            views_b[k] = behind if views_b[k] is None else views_b[k] | behind
        for b, (X, r) in spheres.items():
            circle = sphere_image(cam, X, r)
            if b < 1 or circle is None or not (lab == b).any():
                continue
            u, v, rho = circle
            disc = np.hypot(uu - u, vv - v) <= rho
            behind = disc & (lab >= 1) & (lab != b)
            own = lab == b
            if behind.sum() < HIDDEN_MIN_SHARE * np.pi * rho * rho:
                continue
            if np.mean(np.hypot(uu - u, vv - v)[own] > rho + 1.0) > 0.1:
                continue
            out.setdefault(b, [None] * len(views))[k] = behind
    return out or None


def sphere_shapes(
    cam: Camera, lab: np.ndarray, spheres: dict[int, tuple], done: set[int]
) -> dict[int, tuple]:
    """Circles ``(u, v, ρ, ρ, 0)`` (pixels of ``lab``'s grid) of the bubbles the border
    cuts in one view's (H, W) labels, not in ``done``, that have a sphere in ``spheres``
    (``{id: ((3,) centre m, radius m)}``): its image in the undistorted ``cam``
    (centre's projection, radius f·r / depth), where the visible part fits inside it
    (at most 2 % of its pixels outside); and of those with a sphere that have no pixels
    in ``lab`` while their circle overlaps the frame (a bubble leaving it, whose
    sliver the view's labels no longer hold: ``masks: anchors: continue_s``,
    ``sphere_track``; :func:`surfphase.masks.anchors.circle_meets_frame`: the mask
    stage found it at the recording's resolution, whose pixel centres a coarser grid
    may not have)."""
    from surfphase.masks.anchors import border_ids, circle_meets_frame, sphere_image

    out: dict[int, tuple] = {}
    absent = set(spheres) - set(np.unique(lab).tolist())
    for b in sorted((border_ids(lab) | absent) - set(done)):
        if b < 1 or b not in spheres:
            continue
        circle = sphere_image(cam, *spheres[b])
        if circle is None:
            continue
        u, v, rho = circle
        if b in absent:
            if circle_meets_frame(u, v, rho, lab.shape):
                out[b] = (float(u), float(v), rho, rho, 0.0)
            continue
        ys, xs = np.nonzero(lab == b)
        if np.mean(np.hypot(xs - u, ys - v) > rho + 0.5) <= 0.02:
            out[b] = (float(u), float(v), rho, rho, 0.0)
    return out


def spared_ids(s: _Session, t: int) -> set[int]:
    """Ids meshed at position ``t`` whether or not their two silhouettes are one object
    (``mesh: hull_agreeing``): the bubbles the fit reports in some frame, and those the
    border cuts in both input views there (their cut silhouettes' centroids are not one
    point's images; a bubble leaving the frame that the views never agree on)."""
    from surfphase.masks.anchors import border_ids

    out = set().union(*s.centres.values()) if s.centres else set()
    if s.masks is not None and len(s.masks) >= 2:
        out |= set.intersection(*(border_ids(np.asarray(m[t])) for m in s.masks[:2]))
    return out


def bubble_centres(table: pd.DataFrame) -> dict[int, dict[int, np.ndarray]]:
    """``{frame: {bubble: (3,) centre m}}`` of a fit's ``bubbles.csv`` rows with ids ≥ 1
    and a finite centre."""
    out: dict[int, dict[int, np.ndarray]] = {}
    rows = table[table["bubble"] >= 1]
    xyz = rows[["x", "y", "z"]].to_numpy(np.float64)
    for f, b, c in zip(rows["frame"].to_numpy(), rows["bubble"].to_numpy(), xyz, strict=True):
        if np.isfinite(c).all():
            out.setdefault(int(f), {})[int(b)] = c
    return out


def _frame_file(work: Path, frame: int) -> Path:
    return work / f"{frame:06d}.npz"


def _load_frame(path: Path, key: str) -> dict | None:
    """A finished frame's checkpoint, or None if absent, unreadable or from another run."""
    if not path.exists():
        return None
    try:
        with np.load(path) as z:
            if str(z["key"]) != key:
                return None
            return {k: z[k] for k in z.files}
    except (OSError, ValueError, KeyError, EOFError, zipfile.BadZipFile):
        return None


def _frame_ranges(frames: list[int]) -> str:
    """Sorted frame numbers as runs, e.g. ``[3, 4, 5, 9]`` → ``"3-5, 9"`` (short logs)."""
    runs: list[list[int]] = []
    for f in frames:
        if runs and f == runs[-1][1] + 1:
            runs[-1][1] = f
        else:
            runs.append([f, f])
    return ", ".join(str(a) if a == b else f"{a}-{b}" for a, b in runs)


def _mesh_positions(s: _Session, positions: list[int], work: Path) -> list[dict]:
    """Mesh the fitted frames at ``positions``, one checkpoint per frame in ``work``.

    A frame whose checkpoint matches the session's key is read back, not recomputed, so
    a killed job resumes where it stopped. Returns the frames' records in order: frame,
    position, verts (V, 3) m, faces (F, 3), velocity (V, 3) m/s, seconds.
    """
    work.mkdir(parents=True, exist_ok=True)
    surf = s.surfels
    frames = [int(surf["frame"][t]) for t in positions]
    records: dict[int, dict] = {}
    for t, frame in zip(positions, frames, strict=True):
        rec = _load_frame(_frame_file(work, frame), s.key)
        if rec is not None:
            records[t] = rec
    if records:
        done = sorted(int(r["frame"]) for r in records.values())
        print(
            f"mesh {s.session}: {len(records)} of {len(positions)} frames already meshed "
            f"in {work}, resuming: frames {_frame_ranges(done)}",
            flush=True,
        )
    todo = [t for t in positions if t not in records]
    progress = Progress(len(todo), "mesh: frames to do")
    shape_cache: list[dict] = [{} for _ in s.inputs]
    for t in todo:
        t0 = time.perf_counter()
        a = surf["alive"][t]
        verts, faces = np.zeros((0, 3)), np.zeros((0, 3), np.int64)
        vel, vbub = np.zeros((0, 3)), np.zeros(0, np.int64)
        if s.p["surface"] == "hull":
            sb = surf["bubble"][t][a] if "bubble" in surf else np.full(int(a.sum()), -9)
            views, labs = frame_views(s, t, shape_cache)
            verts, faces, vbub = hull_mesh_frame(
                views,
                labs,
                s.p,
                surfel_spheres(surf["means"][t][a], sb),
                None if s.centres is None else s.centres.get(int(surf["frame"][t])),
                None if s.areas is None else s.areas.get(int(surf["frame"][t])),
                hidden_parts(s, t, views, labs),
                spared_ids(s, t),
                None if s.pieces is None else s.pieces.get(int(surf["frame"][t])),
            )
            vel = bubble_vertex_velocities(
                verts, vbub, surf["means"][t][a], sb, surf["velocity"][t][a]
            )
        elif a.sum() >= 4:
            verts, faces = mesh_frame(
                surf["means"][t][a],
                surf["quats"][t][a],
                surf["log_scales"][t][a],
                surf["opacity"][t][a],
                s.inputs,
                s.p,
                s.device,
                None if s.masks is None else [np.asarray(m[t]) for m in s.masks],
            )
            if len(verts):
                vel = vertex_velocities(verts, surf["means"][t][a], surf["velocity"][t][a])
                if "bubble" in surf:  # (a surfels.npz made by hand may have no ids)
                    vbub = vertex_bubbles(verts, surf["means"][t][a], surf["bubble"][t][a])
                else:
                    vbub = np.full(len(verts), -1, np.int64)
        frame = int(surf["frame"][t])
        rec = {
            "key": np.array(s.key),
            "frame": np.int64(frame),
            "time_s": np.float64(surf["time_s"][t]),
            "position": np.int64(t),
            "verts": np.asarray(verts, np.float64),
            "faces": np.asarray(faces, np.int64).reshape(-1, 3),
            "velocity": np.asarray(vel, np.float64).reshape(-1, 3),
            "vertex_bubble": np.asarray(vbub, np.int64).reshape(-1),
            "seconds": np.float64(time.perf_counter() - t0),
        }
        with atomic_path(_frame_file(work, frame)) as tmp, open(tmp, "wb") as fh:
            np.savez(fh, **rec)
        records[t] = rec
        progress.step(f"{s.session}: frame {frame} meshed, {len(verts)} vertices")
    return [records[t] for t in positions]


def _write_meshes(records: list[dict], out: Path, session, device: str, p: dict) -> dict:
    """Write ``OUT/<frame>.ply``, ``OUT/vtk/<frame>.vtp``, ``OUT/<session>.pvd`` and
    ``OUT/mesh.json`` of ``records``, whole or not at all."""
    if p["speed_max"] == "session":
        speeds = [
            np.nanmax(np.linalg.norm(r["velocity"], axis=1))
            for r in records
            if np.isfinite(r["velocity"]).any()
        ]
        vmax = float(max(speeds)) if speeds and max(speeds) > 0 else 1.0
    else:
        vmax = float(p["speed_max"])
    tmp = part_dir(out)
    pvd = f"{session or 'mesh'}.pvd"
    try:
        rows, series, sizes = [], [], []
        (tmp / "vtk").mkdir()
        for r in records:
            frame, verts, faces, vel = int(r["frame"]), r["verts"], r["faces"], r["velocity"]
            time_s = float(r["time_s"])
            colors = speed_colors(np.linalg.norm(vel, axis=1), vmax)
            write_mesh_ply(tmp / f"{frame:06d}.ply", verts, faces, vel, colors)
            write_polydata(tmp / "vtk" / f"{frame:06d}.vtp", verts, faces, vel, frame, time_s)
            series.append((time_s, f"vtk/{frame:06d}.vtp"))
            for b in bubble_sizes(verts, faces, r["vertex_bubble"]):
                sizes.append({"frame": frame, "time_s": time_s, **b})
            rows.append(
                {
                    "frame": frame,
                    "time_s": time_s,
                    "vertices": len(verts),
                    "faces": len(faces),
                    **mesh_stats(faces, len(verts)),
                    "seconds": float(r["seconds"]),
                }
            )
        write_pvd(tmp / pvd, series)
        cols = ["frame", "time_s", "bubble", "volume_m3", "d_eq_m", "components", "closed"]
        atomic_write_text(
            tmp / "bubble_sizes.csv", pd.DataFrame(sizes, columns=cols).to_csv(index=False)
        )
        summary = {
            "session": session,
            "units": "metres, m/s, seconds",
            "pvd": pvd,
            "speed_max": vmax,
            "device": device,
            "params": p,
            "frames": rows,
        }
        atomic_write_json(tmp / "mesh.json", summary)
        replace_dir(tmp, out)
    finally:
        if tmp.exists():
            shutil.rmtree(tmp)
    return summary


def run_mesh(
    fit_dir: str | os.PathLike,
    ingest_dir: str | os.PathLike,
    out_dir: str | os.PathLike,
    params: dict | None = None,
    device: str = "auto",
    work_dir: str | os.PathLike | None = None,
    masks_dir: str | os.PathLike | None = None,
) -> dict:
    """Mesh every fitted frame of a session; write ``OUT/<frame:06d>.ply`` and
    ``OUT/mesh.json`` (see the module docstring); return the mesh.json content.

    Each finished frame is checkpointed in ``work_dir`` (default ``<out_dir>.partial``,
    removed at the end): a killed run, rerun, meshes only the frames not yet finished.
    ``out_dir`` appears whole (renamed from a temporary folder) or not at all.
    ``masks_dir``: the session's masks (``<cam>_labels.npy``), for ``carve_px``.
    """
    out_dir = Path(out_dir)
    work = Path(work_dir) if work_dir else out_dir.parent / (out_dir.name + ".partial")
    masks = Path(masks_dir) if masks_dir else None
    s = _open_session(Path(fit_dir), Path(ingest_dir), params, device, masks)
    records = _mesh_positions(s, s.picks, work)
    summary = _write_meshes(records, out_dir, s.session, s.device, s.p)
    shutil.rmtree(work, ignore_errors=True)
    return summary


def run_mesh_window(
    fit_dir: str | os.PathLike,
    ingest_dir: str | os.PathLike,
    out_dir: str | os.PathLike,
    index: int,
    size: int,
    params: dict | None = None,
    device: str = "auto",
    masks_dir: str | os.PathLike | None = None,
) -> dict:
    """Mesh window ``index`` (0-based) of ``size`` consecutive fitted frames.

    Writes ``OUT/<frame:06d>.npz`` (the raw meshes: verts, faces, velocity) and
    ``OUT/window.json`` (key, session, device, parameters, the session's frame count,
    the window's positions and frames), for :func:`gather_mesh`. Frames are checkpointed
    in ``<out_dir>.partial``, which becomes ``out_dir`` by a rename when the window is
    done. A window past the last frame is empty. Returns the window.json content.
    """
    out_dir = Path(out_dir)
    work = out_dir.parent / (out_dir.name + ".partial")
    masks = Path(masks_dir) if masks_dir else None
    s = _open_session(Path(fit_dir), Path(ingest_dir), params, device, masks)
    positions = window_positions(s.picks, index, size)
    records = _mesh_positions(s, positions, work)
    keep = {_frame_file(work, int(r["frame"])).name for r in records}
    for f in work.glob("*.npz"):
        if f.name not in keep:  # a frame of another window size or run
            f.unlink()
    info = {
        "key": s.key,
        "session": s.session,
        "device": s.device,
        "params": s.p,
        "n_fitted": int(s.surfels["alive"].shape[0]),
        "window": int(index),
        "size": int(size),
        "positions": positions,
        "frames": [int(r["frame"]) for r in records],
    }
    atomic_write_json(work / "window.json", info)
    replace_dir(work, out_dir)
    return info


def gather_mesh(window_dirs: list[str | os.PathLike], out_dir: str | os.PathLike) -> dict:
    """Gather window folders (:func:`run_mesh_window`) into ``OUT/<frame:06d>.ply`` and
    ``OUT/mesh.json``: the same files a single :func:`run_mesh` job writes.

    Raises ValueError (naming the folder) when the windows come from different runs or do
    not cover every fitted frame exactly once.
    """
    infos = []
    for d in map(Path, window_dirs):
        path = d / "window.json"
        if not path.exists():
            raise FileNotFoundError(f"{path}: not a mesh window folder (no window.json)")
        infos.append((d, json.loads(path.read_text())))
    if not infos:
        raise ValueError("mesh gather: no window folders given")
    ref_dir, ref = infos[0]
    for d, info in infos[1:]:
        for k in ("key", "params", "n_fitted", "device"):
            if info[k] != ref[k]:
                raise ValueError(
                    f"{d / 'window.json'}: {k} differs from {ref_dir / 'window.json'} "
                    "(windows of different runs)"
                )
    p = mesh_params(ref["params"])
    picks = list(range(ref["n_fitted"])) if p["frames"] is None else [int(t) for t in p["frames"]]
    by_pos: dict[int, tuple[Path, int]] = {}
    for d, info in infos:
        for t, frame in zip(info["positions"], info["frames"], strict=True):
            if t in by_pos:
                raise ValueError(f"{d}: frame position {t} is also in window {by_pos[t][0]}")
            by_pos[t] = (d, frame)
    missing = [t for t in picks if t not in by_pos]
    if missing or len(by_pos) != len(picks):
        raise ValueError(
            f"mesh gather for session {ref['session']}: the windows cover {len(by_pos)} of "
            f"{len(picks)} fitted frames (missing positions {missing[:10]}); the window "
            "count comes from the sessions sheet's frames column or the ingest's meta.json"
        )
    records = []
    for t in picks:
        d, frame = by_pos[t]
        rec = _load_frame(_frame_file(d, frame), ref["key"])
        if rec is None:
            raise ValueError(f"{_frame_file(d, frame)}: missing or from another run")
        records.append(rec)
    return _write_meshes(records, Path(out_dir), ref["session"], ref["device"], p)
