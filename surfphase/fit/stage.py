"""The stage-1 fit of one session: sequential per-frame optimisation of SDF surfels with
bubble-guided tracking, checkpointed after every frame (docs/method.md §5).

Per frame ``t`` (in order):

1. initialise — frame 0: surfels on the visual hull of the masks
   (:mod:`surfphase.fit.init`); later frames: the previous frame's surfels, each
   bubble's surfels advected by its velocity (:mod:`surfphase.fit.binding`) and then
   shifted rigidly, one translation per bubble, to fit the new frame
   (:mod:`surfphase.fit.register`), plus new surfels for bubbles that appear;
2. optimise ``λ_app Σ_c (L1 + D-SSIM) + λ_geo (w_n L_normal + w_γ L_γ + w_p L_proj)``
   with Adam (ε = 1e-15); densify and prune at frame 0 only (a strategy object);
3. bind every surfel to a bubble through the masks, and compute the bubble velocities
   that advect the next frame;
4. checkpoint (the frame's record, then the state), so a killed job resumes at the last
   finished frame with a bit-identical result.

Units: positions metres (lab frame), time seconds, velocity m/s. The SDF value ``f`` and
the sharpness ``γ`` are optimised in units of the scene extent ``L`` (m,
:func:`surfphase.fit.init.scene_extent`: the radius of the sphere holding every bubble
triangulated from the first frame's masks); see :mod:`surfphase.fit.model`.

Only the bubbles are reconstructed. The rest of each input view (backlight, heated
plate) is a per-view background image, the per-pixel temporal median of the pixels the
masks call background, composited behind the surfels: ``I = C + (1 − α)·B_c``.

Determinism: one seeded ``torch.Generator`` drives every random choice; each frame starts
a fresh Adam, so a checkpoint holds the surfels, the generator state and the per-frame
records, and a resumed run reproduces an uninterrupted one bit for bit (CPU, same
thread count).
"""

from __future__ import annotations

import copy
import hashlib
import json
import os
import pickle
import shutil
import time
import warnings
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from functools import partial
from pathlib import Path

import numpy as np
import torch

from surfphase.cameras import Camera, load_cameras
from surfphase.device import resolve_device
from surfphase.fit import binding, init, losses, register
from surfphase.fit.densify import Densify2DGS, NoDensify, append_surfels
from surfphase.fit.model import HALF_OPACITY_GF, SurfelModel, per_surfel
from surfphase.fit.params import DEFAULTS  # every hyperparameter, with its default
from surfphase.io import atomic_path, code_fingerprint, stack_frame_indices
from surfphase.progress import Progress
from surfphase.render.shading import monotone_raw
from surfphase.settings import check_keys


def merge_params(params: Mapping | None) -> dict:
    """``DEFAULTS`` updated with ``params``; unknown keys are an error."""
    check_keys(DEFAULTS, params, "fit", see="surfphase.fit.stage.DEFAULTS")
    out = copy.deepcopy(DEFAULTS)
    out.update(params or {})
    if not out["surfel_colors"] and not out["shading"]:
        raise ValueError("fit: surfel_colors false needs shading true (nothing else colours)")
    return out


# -- inputs ------------------------------------------------------------------------------
def read_merges(path: Path) -> dict[int, dict[int, set[int]]]:
    """``{frame position: {merged bubble: parent bubbles}}`` from the mask stage's
    ``events.csv`` (``merge`` rows of any camera; parents and children are ``+``-joined
    bubble ids). A missing file (masks from elsewhere) means no merges are known."""
    import pandas as pd

    out: dict[int, dict[int, set[int]]] = {}
    if not path.exists():
        return out
    try:
        ev = pd.read_csv(path, dtype=str, keep_default_na=False)
        rows = ev[ev["event"] == "merge"]
        for f, par, chi in zip(rows["frame"], rows["parents"], rows["children"], strict=True):
            if not par.strip():
                continue  # no parent bubble known: nothing to take a history from
            for c in str(chi).split("+"):
                d = out.setdefault(int(f), {}).setdefault(int(c), set())
                d.update(int(q) for q in str(par).split("+"))
    except (KeyError, ValueError, pd.errors.ParserError) as e:
        raise ValueError(f"{path}: not a merge/split event table of the mask stage ({e})") from e
    return out


class SessionData:
    """The frames, masks and cameras of one session (memory-mapped stacks).

    ``images(t)`` → (C, H, W, D) float32 in [0, 1]; ``labels(t)`` → C × (H, W) int32.
    """

    def __init__(self, ingest_dir: str | os.PathLike, masks_dir: str | os.PathLike):
        ingest_dir, masks_dir = Path(ingest_dir), Path(masks_dir)
        cam_path = ingest_dir / "cameras.json"
        if not cam_path.exists():
            raise FileNotFoundError(f"{cam_path}: no cameras.json in the ingest folder")
        cams = load_cameras(cam_path)
        meta_path = ingest_dir / "meta.json"
        if not meta_path.exists():
            raise FileNotFoundError(f"{meta_path}: no meta.json in the ingest folder")
        try:
            self.meta = json.loads(meta_path.read_text())
        except ValueError as e:
            raise ValueError(f"{meta_path}: not valid JSON ({e})") from e
        self.session = str(self.meta.get("session", ingest_dir.name))
        self.fps = float(self.meta.get("fps", 0) or 0)
        if not self.fps > 0:
            raise ValueError(f"{meta_path}: session {self.session}: fps must be positive")
        self.cameras: list[Camera] = []
        self.stacks: list[np.ndarray] = []
        self.label_stacks: list[np.ndarray] = []
        for name, cam in cams.items():
            p = ingest_dir / f"{name}.npy"
            if not p.exists():
                continue
            m = masks_dir / f"{name}_labels.npy"
            if not m.exists():
                raise FileNotFoundError(f"{m}: session {self.session}: no masks for {name}")
            stack = np.load(p, mmap_mode="r")
            labs = np.load(m, mmap_mode="r")
            if stack.shape[1:3] != (cam.height, cam.width):
                raise ValueError(
                    f"{p}: session {self.session}: frames are {stack.shape[1:3]}, "
                    f"cameras.json says {(cam.height, cam.width)}"
                )
            if labs.shape[:3] != stack.shape[:3]:
                raise ValueError(
                    f"{m}: session {self.session}: masks {labs.shape} do not match "
                    f"frames {stack.shape}"
                )
            self.cameras.append(cam.undistorted())
            self.stacks.append(stack)
            self.label_stacks.append(labs)
        if len(self.cameras) < 2:
            raise ValueError(
                f"{ingest_dir}: session {self.session}: need frame stacks of ≥ 2 cameras "
                f"listed in cameras.json, found {len(self.cameras)}"
            )
        self.n_frames = min(s.shape[0] for s in self.stacks)
        self.merges = read_merges(masks_dir / "events.csv")
        from surfphase.fit.outputs import read_anchors

        self.anchors = read_anchors(masks_dir / "anchors.csv", self.session)
        self.frame_indices = stack_frame_indices(self.meta, self.n_frames, meta_path)
        self.times = self.frame_indices / self.fps
        self.height, self.width = self.stacks[0].shape[1:3]

    def images(self, t: int) -> np.ndarray:
        out = []
        for s in self.stacks:
            a = np.asarray(s[t])
            if a.dtype == np.uint16:
                a = a.astype(np.float32) / 65535.0
            elif a.dtype == np.uint8:
                a = a.astype(np.float32) / 255.0
            else:
                a = a.astype(np.float32)
            if a.ndim == 2:
                a = a[..., None]
            out.append(np.clip(a, 0.0, 1.0))
        return np.stack(out)

    def labels(self, t: int) -> list[np.ndarray]:
        return [np.asarray(s[t]).astype(np.int32) for s in self.label_stacks]

    def anchor_centres(self, t: int) -> dict[int, np.ndarray]:
        """``{bubble: (3,) triangulated centre (m)}`` at frame position ``t`` (the mask
        stage's ``anchors.csv``; empty without it)."""
        if self.anchors is None:
            return {}
        rows = self.anchors[self.anchors["frame"] == int(self.frame_indices[t])]
        xyz = rows[["x", "y", "z"]].to_numpy(np.float64)
        return {int(b): xyz[i] for i, b in enumerate(rows["bubble"])}

    def nucleation_frames(self) -> set[int]:
        """Session frame indices where every view's masks show the nucleation region."""
        from surfphase.fit.outputs import nucleation_frames

        return nucleation_frames(self.label_stacks, self.frame_indices[: self.n_frames])

    def fingerprint(self) -> str:
        h = hashlib.sha256(json.dumps(self.meta, sort_keys=True).encode())
        for s, lab in zip(self.stacks, self.label_stacks, strict=True):
            h.update(str((s.shape, str(s.dtype), lab.shape)).encode())
            h.update(np.ascontiguousarray(s[0]).tobytes())
            h.update(np.ascontiguousarray(lab[-1]).tobytes())
        for c in self.cameras:
            h.update(json.dumps(c.to_dict(), sort_keys=True).encode())
        return h.hexdigest()


# -- optimisation ------------------------------------------------------------------------
def make_optimizer(model: SurfelModel, p: dict) -> torch.optim.Adam:
    """One Adam over named groups; the position rate is ``lr_means·L`` metres per step."""
    lrs = {
        "means": p["lr_means"] * model.extent,
        "log_scales": p["lr_log_scales"],
        "quats": p["lr_quats"],
        "colors": p["lr_colors"] if p["surfel_colors"] or model.shade is None else 0.0,
        "sdf": p["lr_sdf"],
        "log_gamma": p["lr_log_gamma"],
        "opacity_logit": p["lr_opacity"],
        "shade": p["lr_shade"],
    }
    groups = [{"params": [v], "lr": lrs[k], "name": k} for k, v in model.params.items()]
    return torch.optim.Adam(groups, lr=0.0, eps=p["adam_eps"])


def _render(model: SurfelModel, viewmats, Ks, width, height, backgrounds: torch.Tensor):
    """Render the model over per-view background images (C, H, W, D)."""
    from surfphase.render import over_background, rasterize_surfels

    rgb, alpha, meta = rasterize_surfels(
        model.means,
        model.quats,
        model.scales,
        model.opacities(),
        model.view_colors(viewmats),
        viewmats,
        Ks,
        width,
        height,
    )
    return over_background(rgb, alpha, backgrounds), alpha, meta


def estimate_backgrounds(data: SessionData, n_frames: int, max_frames: int = 64) -> np.ndarray:
    """Per-view background images (C, H, W, D) in [0, 1]: the per-pixel median over time of
    the pixels the masks call background (backlight, plate, static dirt); pixels that are
    never background take the nearest background pixel's value."""
    from scipy import ndimage

    idx = np.unique(np.linspace(0, n_frames - 1, min(n_frames, max_frames)).round().astype(int))
    imgs = np.stack([data.images(t) for t in idx])  # (K, C, H, W, D)
    labs = np.stack([np.stack(data.labels(t)) for t in idx])  # (K, C, H, W)
    out = np.empty(imgs.shape[1:], dtype=np.float32)
    for c in range(imgs.shape[1]):
        x = np.where((labs[:, c] < 0)[..., None], imgs[:, c], np.nan)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN pixels: filled below
            med = np.nanmedian(x, axis=0)
        missing = np.isnan(med[..., 0])
        if missing.all():
            med = np.broadcast_to(np.median(imgs[:, c], axis=(0, 1, 2)), med.shape).copy()
        elif missing.any():
            _, (ri, ci) = ndimage.distance_transform_edt(missing, return_indices=True)
            med = med[ri, ci]
        out[c] = med
    return out


@dataclass
class DepthBounds:
    """Bubble spheres of one frame and the poorly seen axis (``depth_bound``)."""

    centres: torch.Tensor  # (B, 3) metres
    limits: torch.Tensor  # (B,) metres: k·r, inf for the nucleation region
    radii: torch.Tensor  # (B,) metres
    axis: torch.Tensor  # (3,) unit vector

    def apply(self, means: torch.Tensor) -> None:
        """Move (N, 3) ``means`` (metres, in place) back within the limits along the axis."""
        c, lim, r, u = (t.to(means) for t in (self.centres, self.limits, self.radii, self.axis))
        near = (torch.cdist(means, c) / r).argmin(dim=1)
        d = (means - c[near]) @ u
        excess = (d.abs() - lim[near]).clamp_min(0.0)
        means.sub_((excess * torch.sign(d))[:, None] * u)


def depth_bounds(
    cameras: Sequence[Camera],
    labels: Sequence[np.ndarray],
    k: float | None,
    centres: dict[int, np.ndarray] | None = None,
) -> DepthBounds | None:
    """The ``depth_bound`` of one frame's masks (see ``DEFAULTS``), or None when off or
    no bubble is seen in two views. ``centres`` (m, by bubble id), where given, replace
    the triangulated centroids of the frame's binary masks (the mask stage's sub-pixel
    anchors)."""
    if k is None:
        return None
    spheres = init.bubble_spheres(cameras, labels, radius="max")
    if not spheres:
        return None
    for b, c in (centres or {}).items():
        if b in spheres:
            spheres[b] = (np.asarray(c, dtype=np.float64), *spheres[b][1:])
    ids = sorted(spheres)
    axis = np.mean([c.view_dir for c in cameras], axis=0)
    axis /= np.linalg.norm(axis)
    radii = np.array([spheres[b][1] for b in ids])
    limits = np.where(np.array(ids) >= 1, float(k) * radii, np.inf)
    as_t = partial(torch.as_tensor, dtype=torch.float64)
    return DepthBounds(
        as_t(np.stack([spheres[b][0] for b in ids])), as_t(limits), as_t(radii), as_t(axis)
    )


def fit_frame(
    model: SurfelModel,
    observed: torch.Tensor,
    viewmats: torch.Tensor,
    Ks: torch.Tensor,
    background: torch.Tensor,
    p: dict,
    iters: int,
    strategy,
    frame: int,
    generator: torch.Generator,
    geo_from: int = 0,
    view_schedule=None,
    geo_views: int | None = None,
    bounds: DepthBounds | None = None,
    foreground: torch.Tensor | None = None,
) -> list[dict]:
    """Optimise ``model`` on one frame's (C, H, W, D) ``observed`` images. Returns the
    logged curve rows.

    Stage 2 (:mod:`surfphase.fit.stage2`) passes ``view_schedule(it) → (idx, weights)``:
    the views rendered at step ``it`` ((K,) long, the first ``geo_views`` of them the
    input views) and their photometric weights ((K,)); the geometry losses and the
    logged L1/D-SSIM/PSNR then use those first ``geo_views`` views only. Without a
    schedule every view is rendered with weight 1 (stage 1). ``bounds`` (see
    :func:`depth_bounds`) limits the surfels' depth extent after every step. With
    ``foreground`` ((C_in, H, W) floats, 1 inside any bubble's mask of an input view)
    and ``w_mask`` > 0, ``w_mask · mean|α − foreground|`` over the input views is added:
    a bubble is opaque inside its mask.
    """
    C, H, W, D = observed.shape
    opt = make_optimizer(model, p)
    state = strategy.initialize_state(model.n, model.means.device)
    rows = []
    base_lr = p["lr_means"] * model.extent
    for it in range(iters):
        frac = it / max(iters - 1, 1)
        for g in opt.param_groups:
            if g["name"] == "means":
                g["lr"] = base_lr * p["lr_means_decay"] ** frac
        if view_schedule is None:
            vm, ks, obs = viewmats, Ks, observed
            rgb, alpha, meta = _render(model, viewmats, Ks, W, H, background)
            strategy.before_backward(meta)
            app, l1v, dssim = losses.photometric_loss(rgb, observed, p["lambda_dssim"])
            geo = meta
        else:
            idx, w = view_schedule(it)
            vm, ks, obs = viewmats[idx], Ks[idx], observed[idx]
            rgb, alpha, meta = _render(model, vm, ks, W, H, background[idx])
            strategy.before_backward(meta)
            lv, l1_v, dssim_v = losses.photometric_terms(rgb, obs, p["lambda_dssim"])
            app = (w.to(lv) * lv).sum()
            ng = int(geo_views)
            l1v, dssim = l1_v[:ng].mean(), dssim_v[:ng].mean()
            vm, ks, obs, rgb, alpha = vm[:ng], ks[:ng], obs[:ng], rgb[:ng], alpha[:ng]
            geo = {k: meta[k][:ng] for k in ("normals_camera", "normals_from_depth")}
            geo["depth_expected"] = meta["depth_expected"][:ng]
        loss = p["lambda_app"] * app
        if foreground is not None and p["w_mask"] > 0:
            loss = loss + p["w_mask"] * (alpha[..., 0] - foreground).abs().mean()
        geo_on = it >= geo_from
        ln = lg = lp = torch.zeros(())
        if geo_on:
            ln = losses.normal_consistency(geo["normals_camera"], geo["normals_from_depth"], alpha)
            pts = model.zero_level_points()
            lp = losses.projection_loss(
                pts, geo["depth_expected"], vm, ks, model.extent, p["proj_threshold"]
            )
            if model.use_sdf:
                sdf = model.params["sdf"]
                lg = losses.gamma_hinge(model.gamma, sdf) / losses.gamma_target(sdf)
            loss = loss + p["lambda_geo"] * (
                p["w_normal"] * ln + p["w_gamma"] * lg + p["w_proj"] * lp
            )
        opt.zero_grad(set_to_none=True)
        loss.backward()
        meta["width"], meta["height"] = W, H
        if isinstance(strategy, Densify2DGS):
            strategy.after_backward(model, opt, state, it, meta, generator=generator)
            # Gradients belong to replaced tensors after a refinement: skip that step.
            if any(p_.grad is None for g in opt.param_groups for p_ in g["params"]):
                opt.zero_grad(set_to_none=True)
                continue
        opt.step()
        with torch.no_grad():
            model.params["quats"].data /= (
                model.params["quats"].data.norm(dim=-1, keepdim=True).clamp_min(1e-12)
            )
            if p["floor_y"] is not None:
                model.params["means"].data[:, 1].clamp_(min=float(p["floor_y"]))
            if bounds is not None:
                bounds.apply(model.params["means"].data)
        if it % p["log_every"] == 0 or it == iters - 1:
            rows.append(
                {
                    "frame": frame,
                    "iter": it,
                    "loss": float(loss.detach()),
                    "l1": float(l1v.detach()),
                    "dssim": float(dssim.detach()),
                    "normal": float(ln.detach()),
                    "gamma": float(lg.detach()),
                    "proj": float(lp.detach()),
                    "psnr": losses.psnr(rgb, obs),
                    "n_surfels": model.n,
                }
            )
    return rows


# -- checkpoints -------------------------------------------------------------------------
# A checkpoint folder holds ``frame_<t:05d>.pt`` (the record of frame t) and two states:
# ``state.pt`` after the last finished frame and ``state.prev.pt`` after the one before,
# so that an unreadable newest state or record costs one frame, not the run.
STATE, PREV_STATE = "state.pt", "state.prev.pt"
#: What torch.load raises on a damaged, truncated or foreign file.
_UNREADABLE = (
    OSError,
    RuntimeError,
    EOFError,
    KeyError,
    AttributeError,
    TypeError,
    ValueError,
    IndexError,
    ImportError,
    pickle.UnpicklingError,
)


def _save_torch(path: Path, obj) -> None:
    with atomic_path(path) as tmp:
        torch.save(obj, tmp)


def _save_state(ckpt: Path, state: dict) -> None:
    """Write ``state.pt``, keeping the one it replaces as ``state.prev.pt``.

    ``state.pt`` always exists once written: the previous one is linked (or copied) to
    ``state.prev.pt`` first, then the new one is renamed over it.
    """
    cur, prev = ckpt / STATE, ckpt / PREV_STATE
    if cur.exists():
        tmp = ckpt / (PREV_STATE + ".tmp")
        tmp.unlink(missing_ok=True)
        try:
            os.link(cur, tmp)
        except OSError:  # a file system without hard links
            shutil.copy2(cur, tmp)
        os.replace(tmp, prev)
    _save_torch(cur, state)


def _load_checkpoint(ckpt: Path, key: str) -> tuple[dict | None, list[dict]]:
    """The newest resumable state in ``ckpt`` for a run with this ``key``, and the
    records of the frames before it; ``(None, [])`` when there is none.

    A file that cannot be read (damaged, truncated, from another version) is reported,
    naming it, and deleted; the previous state is tried next, so the run resumes from
    the last good checkpoint and recomputes the frames after it.
    """
    records: dict[int, dict | None] = {}

    def load(path: Path):
        try:
            return torch.load(path, weights_only=False)
        except _UNREADABLE as e:
            why = f"{type(e).__name__}: {e}".strip()
            print(f"fit: checkpoint file {path} is unreadable ({why[:200]}); discarded it")
            path.unlink(missing_ok=True)
            return None

    def record(t: int) -> dict | None:
        if t not in records:
            path = ckpt / f"frame_{t:05d}.pt"
            rec = load(path) if path.exists() else None
            if rec is not None and not (isinstance(rec, dict) and rec.get("frame") == t):
                print(f"fit: checkpoint file {path} does not hold frame {t}; discarded it")
                path.unlink(missing_ok=True)
                rec = None
            records[t] = rec
        return records[t]

    for name in (STATE, PREV_STATE):
        path = ckpt / name
        state = load(path) if path.exists() else None
        if state is None:
            continue
        if not isinstance(state, dict) or state.get("key") != key:
            return None, []  # another run's checkpoint (other inputs, parameters, code)
        n = state.get("next_frame")
        if not isinstance(n, int) or n < 0:
            print(f"fit: checkpoint file {path} has no frame count; discarded it")
            path.unlink(missing_ok=True)
            continue
        recs = [record(t) for t in range(n)]
        if all(r is not None for r in recs):
            if name != STATE:
                print(f"fit: resuming from {path} (frame {n}): the later frames are recomputed")
            return state, recs
        missing = next(t for t, r in enumerate(recs) if r is None)
        print(f"fit: {path} needs the record of frame {missing}, which is gone")
    return None, []


#: The sources the fit's results depend on (:func:`surfphase.io.code_fingerprint`).
CODE_SOURCES = ("fit", "render")


def _code_fingerprint() -> str:
    """Hash of the sources the fit's results depend on (fit and renderer packages)."""
    return code_fingerprint(CODE_SOURCES)


def _run_key(data: SessionData, p: dict) -> str:
    """What a checkpoint must match to be resumed: parameters, inputs and code.

    A change of the fit's code makes old checkpoints stale, so a rerun triggered by the
    code change refits from the first frame instead of resuming.
    """
    h = hashlib.sha256(json.dumps(p, sort_keys=True, default=str).encode())
    h.update(data.fingerprint().encode())
    h.update(_code_fingerprint().encode())
    return h.hexdigest()


# -- the frame loop ----------------------------------------------------------------------
def _initial_model(data: SessionData, p: dict, gen: torch.Generator, dtype) -> SurfelModel:
    labels = data.labels(0)
    images = data.images(0)
    spheres = init.bubble_spheres(data.cameras, labels)
    if not spheres:
        raise ValueError(f"session {data.session}: no bubble mask at frame 0 is seen in 2 views")
    extent = init.scene_extent(spheres)
    hull = init.visual_hull_surfels(
        data.cameras, labels, list(images), spheres=spheres, grid=p["hull_grid"]
    )
    if hull.points.shape[0] == 0:
        raise ValueError(f"session {data.session}: the visual hull of frame 0 is empty")
    n = hull.points.shape[0]
    if n > p["n_init"]:
        idx = torch.randperm(n, generator=gen)[: p["n_init"]].sort().values.numpy()
    else:
        idx = np.arange(n)
    t = lambda a: torch.as_tensor(a[idx], dtype=dtype)  # noqa: E731
    model = SurfelModel.from_points(
        t(hull.points),
        t(hull.normals),
        t(hull.colors),
        hull.spacing * p["init_scale"],
        extent=extent,
        init_sdf=p["init_sdf"],
        use_sdf=p["use_sdf"],
    )
    if p["shading"]:
        params = model.state()
        D = model.colors.shape[1]
        knots = torch.zeros((int(p["shade_knots"]), D), dtype=dtype)
        if not p["surfel_colors"]:
            knots += params["colors"].mean(0)
            params["colors"] = torch.zeros_like(params["colors"])
        params["shade"] = monotone_raw(knots)
        model = SurfelModel(params, extent=extent, use_sdf=p["use_sdf"])
    return model


def _spawn_bubbles(
    model: SurfelModel,
    data: SessionData,
    t: int,
    p: dict,
    gen: torch.Generator,
    sizes: Mapping[int, tuple[int, int]] | None = None,
) -> list[int]:
    """Add surfels for bubbles that the masks of frame ``t`` show but no surfel covers.

    ``sizes``: ``{bubble: (hull grid, most surfels)}`` overriding ``spawn_grid`` and
    ``spawn_max_surfels`` (bubbles re-seeded at a merge).
    """
    sizes = sizes or {}
    labels = data.labels(t)
    spheres = init.bubble_spheres(data.cameras, labels)
    bound = binding.bind_surfels_to_bubbles(
        model.means.detach().double().numpy(), data.cameras, labels
    )
    images = None
    added = []
    for b in sorted(spheres):
        if int((bound == b).sum()) >= p["spawn_min_surfels"]:
            continue
        if images is None:
            images = list(data.images(t))
        grid, most = sizes.get(b, (p["spawn_grid"], p["spawn_max_surfels"]))
        hull = init.visual_hull_surfels(
            data.cameras,
            labels,
            images,
            bubble=b,
            spheres=spheres,
            grid=grid,
            occlusion=bool(p["hull_occlusion"]),
            occlusion_ratio=float(p["hull_occlusion_ratio"]),
        )
        n = hull.points.shape[0]
        if n == 0:
            continue
        idx = np.arange(n)
        if n > most:
            idx = torch.randperm(n, generator=gen)[:most].sort().values.numpy()
        dt = model.means.dtype
        new = SurfelModel.from_points(
            torch.as_tensor(hull.points[idx], dtype=dt),
            torch.as_tensor(hull.normals[idx], dtype=dt),
            torch.as_tensor(hull.colors[idx], dtype=dt) * (1.0 if p["surfel_colors"] else 0.0),
            hull.spacing * p["init_scale"],
            extent=model.extent,
            init_sdf=p["init_sdf"],
            use_sdf=model.use_sdf,
        )
        vals = new.state()
        if model.use_sdf:
            # New surfels start at opacity 1/2 under the current γ.
            vals["sdf"] = torch.full_like(
                vals["sdf"], HALF_OPACITY_GF / float(model.gamma.detach())
            )
        append_surfels(model, None, {k: v for k, v in vals.items() if per_surfel(k)})
        added.append(b)
    return added


def _record(model: SurfelModel, bubble: np.ndarray) -> dict:
    st = model.state()
    rec = {k: v.cpu().numpy().astype(np.float32) for k, v in st.items() if per_surfel(k)}
    if model.shade is not None:
        rec["shade"] = model.shade.detach().cpu().numpy().astype(np.float32)
    rec["opacity"] = model.opacities().detach().cpu().numpy().astype(np.float32)
    rec["gamma"] = float(model.gamma.detach())
    rec["bubble"] = bubble.astype(np.int32)
    return rec


def _backgrounds(data: SessionData, n_frames: int, p: dict) -> np.ndarray:
    """(C, H, W, D) float32 background images for the fit (see ``background`` in DEFAULTS)."""
    bg = p["background"]
    C, H, W = len(data.cameras), data.height, data.width
    D = data.images(0).shape[-1]
    if isinstance(bg, str):
        if bg not in ("images", "constant"):
            raise ValueError(
                f"fit: background must be 'images', 'constant' or a number, not {bg!r}"
            )
        imgs = estimate_backgrounds(data, n_frames)
        if bg == "constant":
            imgs = np.broadcast_to(np.median(imgs, axis=(0, 1, 2)), imgs.shape).copy()
        return imgs.astype(np.float32)
    return np.full((C, H, W, D), float(bg), dtype=np.float32)


def _advect_velocities(
    records: list[dict], data: SessionData, p: dict
) -> tuple[dict[int, np.ndarray], np.ndarray]:
    """Bubble and per-surfel velocities (m/s) from the last two finished frames.

    Uses the surfels bound to each bubble at the last frame that also existed at the one
    before (matched by surfel id), their positions at both frames. Bubbles whose track
    begins at the last frame (:func:`~surfphase.fit.binding.track_continues`: a merge, a
    split, a new id) have no history: a bubble re-seeded at a merge gets its parents'
    volume-weighted velocity (momentum), any other the configured initial velocity; so
    do surfels without history.
    """
    from surfphase.fit.outputs import record_ids

    cur = records[-1]
    bub = cur["bubble"]
    v_nuc = np.asarray(p["v_init_nucleation"], dtype=np.float64)
    v_bub = np.asarray(p["v_init_bubble"], dtype=np.float64)
    surfel_v = np.where((bub == 0)[:, None], v_nuc, 0.0)
    vb: dict[int, np.ndarray] = {}
    if len(records) >= 2:
        prev = records[-2]
        _, ic, ip = np.intersect1d(
            record_ids(cur), record_ids(prev), assume_unique=True, return_indices=True
        )
        dt = data.times[len(records) - 1] - data.times[len(records) - 2]
        w = binding.surfel_weights(cur["opacity"][ic], np.exp(cur["log_scales"][ic]))
        vb = binding.bubble_velocities(prev["means"][ip], cur["means"][ic], bub[ic], w, dt)
        # A bubble whose track starts at the last frame (merge, split, new id) has no
        # history yet: its surfels' motion across the event is not its velocity.
        w_prev = binding.surfel_weights(prev["opacity"][ip], np.exp(prev["log_scales"][ip]))
        for b in [b for b in vb if b > 0]:
            if binding.track_continues(bub[ic], prev["bubble"][ip], w, w_prev, b) is None:
                del vb[b]
        surfel_v[ic] = (cur["means"][ic].astype(np.float64) - prev["means"][ip]) / dt
        if p["anchor_centres"]:
            # Where both frames have the bubble's triangulated centre, its motion is the
            # centre's (no surfel re-binding in it).
            c1, c0 = data.anchor_centres(len(records) - 1), data.anchor_centres(len(records) - 2)
            for b in [b for b in vb if b > 0 and b in c1 and b in c0]:
                vb[b] = (c1[b] - c0[b]) / dt
    reseeded = cur.get("reseeded") or {}
    for b in np.unique(bub):
        if b > 0 and int(b) not in vb:
            vb[int(b)] = np.asarray(reseeded.get(int(b), v_bub), dtype=np.float64)
        if b == 0 and 0 not in vb:
            vb[0] = v_nuc
    return vb, surfel_v


def _recent_merges(data: SessionData, t: int, frames: int) -> list[int]:
    """Bubbles that a merge formed at one of the ``frames`` frames before ``t``."""
    return sorted({b for f in range(t - frames, t) for b in data.merges.get(f, {})})


def _reseed_merges(
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
    (:func:`_spawn_bubbles`), like a bubble that appears. Its first advection uses its
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
        from surfphase.fit.densify import select_surfels

        select_surfels(model, None, torch.as_tensor(keep, device=model.means.device))
    return out, keep


def run_fit(
    ingest_dir: str | os.PathLike,
    masks_dir: str | os.PathLike,
    out_dir: str | os.PathLike,
    params: Mapping | None = None,
    device: str = "auto",
    checkpoint_dir: str | os.PathLike | None = None,
    initial_model: SurfelModel | None = None,
    extra_views=None,
    key_extra: str = "",
) -> dict:
    """Fit one session; write ``out_dir`` (see :mod:`surfphase.fit.outputs`).

    Args:
        ingest_dir: ``<cam>.npy`` frame stacks, ``cameras.json``, ``meta.json``.
        masks_dir: ``<cam>_labels.npy`` instance masks.
        out_dir: output folder.
        params: overrides of :data:`DEFAULTS`.
        device: ``auto``, ``cpu`` or ``cuda``.
        checkpoint_dir: where per-frame checkpoints go (default ``<out_dir>.ckpt``);
            an existing checkpoint of the same inputs and parameters is resumed.
        initial_model: frame 0 starts from these surfels instead of the visual hull
            (stage 2: the stage-1 surfels of frame 0).
        extra_views: stage 2's supervision beside the input views
            (:class:`surfphase.fit.stage2.ExtraViews`: ``cameras``, ``backgrounds``,
            ``n_frames``, ``images(t)``, ``schedule(t, n_inputs)``).
        key_extra: what else a checkpoint must match (stage 2: a hash of its inputs).

    Returns:
        The summary dict (also written to ``out_dir/summary.json``).
    """
    from surfphase.fit import outputs
    from surfphase.render import camera_tensors

    p = merge_params(params)
    out_dir = Path(out_dir)
    ckpt = Path(checkpoint_dir) if checkpoint_dir else out_dir.parent / (out_dir.name + ".ckpt")
    dev = resolve_device(device)
    dtype = torch.float32
    data = SessionData(ingest_dir, masks_dir)
    n_frames = data.n_frames if p["frames"] is None else min(int(p["frames"]), data.n_frames)
    if n_frames < 1:
        raise ValueError(f"session {data.session}: no frames to fit")
    if extra_views is not None:
        n_frames = min(n_frames, int(extra_views.n_frames))
    key = _run_key(data, {**p, "frames": n_frames})
    if key_extra:
        key = hashlib.sha256((key + key_extra).encode()).hexdigest()
    viewmats, Ks = camera_tensors(data.cameras, dev, dtype)

    state, records = _load_checkpoint(ckpt, key)
    gen = torch.Generator().manual_seed(int(p["seed"]))
    if state is None:
        ckpt.mkdir(parents=True, exist_ok=True)
        for old in ckpt.glob("*.pt"):
            old.unlink()
        if initial_model is None:
            model = _initial_model(data, p, gen, dtype)
        else:
            model = SurfelModel(initial_model.state(), initial_model.extent, p["use_sdf"])
        background = _backgrounds(data, n_frames, p)
        start = 0
    else:
        model = SurfelModel(state["params"], extent=state["extent"], use_sdf=p["use_sdf"])
        gen.set_state(state["generator"])
        background = state["background"]
        start = state["next_frame"]
    model.params = {k: v.detach().to(dev).requires_grad_(True) for k, v in model.params.items()}
    bg_t = torch.as_tensor(background, dtype=dtype, device=dev)
    fit_vm, fit_Ks, fit_bg = viewmats, Ks, bg_t
    if extra_views is not None:
        ev, ek = camera_tensors(extra_views.cameras, dev, dtype)
        fit_vm, fit_Ks = torch.cat([viewmats, ev]), torch.cat([Ks, ek])
        ebg = torch.as_tensor(extra_views.backgrounds, dtype=dtype, device=dev)
        fit_bg = torch.cat([bg_t, ebg])

    from surfphase.fit.outputs import record_ids

    # Persistent surfel ids of the model's rows (columns of surfels.npz).
    next_id = int(state.get("next_id", model.n)) if state is not None else 0
    ids = record_ids(records[-1]) if records else np.zeros(0, dtype=np.int64)
    # One line per frame with elapsed time and ETA (a resumed run counts what is left).
    progress = Progress(n_frames - start, f"session {data.session}: frame", offset=start)
    for t in range(start, n_frames):
        t0 = time.perf_counter()
        labels = data.labels(t)
        spawned: list[int] = []
        registered: dict[int, np.ndarray] = {}
        reseeded: dict[int, np.ndarray] = {}
        if t > 0:
            if p["guidance"]:
                vb, vs = _advect_velocities(records, data, p)
                dt = data.times[t] - data.times[t - 1]
                new_means = binding.advect(
                    records[-1]["means"], records[-1]["bubble"], vb, vs, dt, per_surfel_ids=(0,)
                )
                with torch.no_grad():
                    model.params["means"].data.copy_(torch.as_tensor(new_means, dtype=dtype))
                registered = register.register_bubbles(
                    model,
                    records[-1]["bubble"],
                    torch.as_tensor(data.images(t), device=dev),
                    viewmats,
                    Ks,
                    bg_t,
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
                        for b in _recent_merges(data, t, int(p["register_silhouette_frames"]))
                    },
                )
            model.params = {k: v.detach().cpu() for k, v in model.params.items()}
            if p["guidance"] and p["reseed_merges"]:
                reseeded, keep = _reseed_merges(model, data, t, vb, p)
                ids = ids[keep]
            n_before = model.n
            grid = (int(p["reseed_grid"]), int(p["reseed_max_surfels"]))
            spawned = _spawn_bubbles(model, data, t, p, gen, {b: grid for b in reseeded})
            ids = np.concatenate([ids, np.arange(next_id, next_id + model.n - n_before)])
            next_id += model.n - n_before
            model.params = {
                k: v.detach().to(dev).requires_grad_(True) for k, v in model.params.items()
            }
        observed = torch.as_tensor(data.images(t), device=dev)
        if t == 0:
            iters = int(p["iters_first"])
            strategy = (
                Densify2DGS(
                    refine_start=int(p["densify_start"] * iters),
                    refine_stop=int(p["densify_stop"] * iters),
                    refine_every=int(p["densify_every"]),
                    grow_grad2d=p["grow_grad2d"],
                    grow_scale=p["grow_scale"],
                    prune_opacity=p["prune_opacity"],
                    prune_scale=p["prune_scale"],
                    max_surfels=int(p["max_surfels"]),
                )
                if p["densify"]
                else NoDensify()
            )
            geo_from = int(p["geo_from"] * iters)
        else:
            iters = int(p["iters_reseed"] if reseeded else p["iters_next"])
            strategy, geo_from = NoDensify(), 0
        t_opt = time.perf_counter()
        centres = data.anchor_centres(t) if p["anchor_centres"] else None
        bounds = depth_bounds(data.cameras, labels, p["depth_bound"], centres)
        fg = torch.as_tensor(np.stack(labels) >= 0, dtype=dtype, device=dev)
        if extra_views is None:
            rows = fit_frame(
                model, observed, viewmats, Ks, bg_t, p, iters, strategy, t, gen,
                geo_from=geo_from, bounds=bounds, foreground=fg,
            )  # fmt: skip
        else:
            nc = len(data.cameras)
            obs_all = torch.cat([observed, torch.as_tensor(extra_views.images(t), device=dev)])
            rows = fit_frame(
                model, obs_all, fit_vm, fit_Ks, fit_bg, p, iters, strategy, t, gen,
                geo_from=geo_from, view_schedule=extra_views.schedule(t, nc), geo_views=nc,
                bounds=bounds, foreground=fg,
            )  # fmt: skip
        t_done = time.perf_counter()
        with torch.no_grad():
            rgb, _, _ = _render(model, viewmats, Ks, data.width, data.height, bg_t)
        view_psnr = [losses.psnr(rgb[c], observed[c]) for c in range(observed.shape[0])]
        model_cpu = SurfelModel(
            {k: v.detach().cpu() for k, v in model.params.items()},
            extent=model.extent,
            use_sdf=model.use_sdf,
        )
        bubble = binding.bind_surfels_to_bubbles(
            model_cpu.means.detach().double().numpy(), data.cameras, labels
        )
        if t == 0:  # densification has settled the first frame's surfels
            ids, next_id = np.arange(model.n, dtype=np.int64), model.n
        rec = _record(model_cpu, bubble)
        rec.update(
            {
                "ids": ids.astype(np.int64),
                "reseeded": reseeded,
                "frame": t,
                "curves": rows,
                "psnr": view_psnr,
                "iters": iters,
                "spawned": spawned,
                "registered": registered,
                "seconds": time.perf_counter() - t0,
                "seconds_optimise": t_done - t_opt,
            }
        )
        records.append(rec)
        _save_torch(ckpt / f"frame_{t:05d}.pt", rec)
        _save_state(
            ckpt,
            {
                "key": key,
                "next_frame": t + 1,
                "next_id": next_id,
                "params": model_cpu.state(),
                "extent": model.extent,
                "generator": gen.get_state(),
                "background": background,
            },
        )
        progress.step(
            f"{iters} steps, "
            f"input-view PSNR {', '.join(f'{v:.1f}' for v in view_psnr)} dB, "
            f"{rec['seconds']:.1f} s"
        )

    return outputs.write_outputs(
        out_dir, records, data, p, background, extent=model.extent, device=dev
    )
