"""Backlit shadowgraph images of the synthetic scene, by sphere tracing in numpy.

Independent of the reconstruction's renderer (docs/method.md §1.1): rays come from the true
cameras (``Camera.pixel_rays``, lens distortion included for raw input views),
and are marched through the scene field of :mod:`surfphase.synth.scene`.

Look of a backlit shadowgraph (grey levels as fractions of full scale):

* background: bright (≈0.8), slightly uneven (vignetting and a faint diffuser
  pattern, different per camera);
* bubble: light that meets the interface obliquely is refracted out of the
  aperture, so the bubble is dark (≈0.1 of the background) with a bright core
  where the surface faces the camera (``|n·d| > 0.8``, smooth step to ≈0.85);
* heated plate: an opaque block under y = 0 (x ±12 mm, z ±6 mm, 4 mm thick) —
  its top face seen at grazing incidence is dim grey, its sides are black;
* optics and sensor: Gaussian blur, shot noise (Poisson, full well
  ``full_well`` electrons) and read noise, quantised to 8 or 16 bits.

Pixels follow the project's convention (origin at the centre of the top-left pixel).
"""

from __future__ import annotations

import zlib
from dataclasses import dataclass

import cv2
import numpy as np

from surfphase.cameras import Camera
from surfphase.synth.field import FrameState

#: Heated plate block, lab frame, metres: (min corner, max corner).
PLATE_MIN = np.array([-0.012, -0.004, -0.006])
PLATE_MAX = np.array([0.012, 0.0, 0.006])
#: Sphere tracing: convergence floor (m), step factor (field slope ≤ ~1.1), max steps.
HIT_EPS, STEP, MAX_STEPS = 5e-7, 0.9, 90


@dataclass(frozen=True)
class Rays:
    """Rays through every pixel centre of a camera image, row-major.

    Attributes:
        origin: (3,) camera centre, m.
        dirs: (H·W, 3) unit directions, lab frame.
        height, width: image size in pixels.
        camera: the camera the rays belong to.
        t_plate: (H·W,) distance (m) at which each ray enters the plate block (inf: never).
        plate_top: (H·W,) whether that entry is through the plate's top face.
        distorted: whether the pixels are those of the raw (distorted) image.
    """

    origin: np.ndarray
    dirs: np.ndarray
    height: int
    width: int
    camera: Camera
    t_plate: np.ndarray
    plate_top: np.ndarray
    distorted: bool


def camera_rays(cam: Camera, distorted: bool = True) -> Rays:
    """Rays through all pixel centres of ``cam`` (raw, distorted pixels if ``distorted``)."""
    v, u = np.mgrid[0 : cam.height, 0 : cam.width]
    uv = np.stack([u.ravel(), v.ravel()], axis=1).astype(np.float64)
    dirs = cam.pixel_rays(uv, distorted=distorted)
    t_plate, top = _ray_box(cam.center, dirs, PLATE_MIN, PLATE_MAX)
    return Rays(cam.center, dirs, cam.height, cam.width, cam, t_plate, top, distorted)


def _candidate_pixels(state: FrameState, rays: Rays) -> np.ndarray:
    """Flat indices of pixels whose ray may meet a lobe's bounding sphere.

    Each bounding sphere is projected to a square pixel box (15 % + 3 px margin for
    lens distortion and perspective); the exact ray–sphere test follows.
    """
    cam = rays.camera
    depth = cam.world_to_camera(state.centers)[:, 2]
    uv = cam.project(state.centers, distort=rays.distorted)
    mask = np.zeros((rays.height, rays.width), dtype=bool)
    for (u, v), z, rb in zip(uv, depth, state.bound_radii, strict=True):
        if z <= rb:
            mask[:] = True  # sphere around the camera: no useful box
            break
        r = cam.K[0, 0] * rb / np.sqrt(z * z - rb * rb) * 1.15 + 3
        u0, u1 = int(max(np.floor(u - r), 0)), int(min(np.ceil(u + r), rays.width - 1))
        v0, v1 = int(max(np.floor(v - r), 0)), int(min(np.ceil(v + r), rays.height - 1))
        if u0 <= u1 and v0 <= v1:
            mask[v0 : v1 + 1, u0 : u1 + 1] = True
    return np.flatnonzero(mask.ravel())


def _ray_box(origin: np.ndarray, dirs: np.ndarray, lo: np.ndarray, hi: np.ndarray):
    """Slab test: entry distance (N,) (inf where missed) and whether entry is the top face."""
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = 1.0 / dirs
        t1 = (lo - origin) * inv
        t2 = (hi - origin) * inv
    tmin = np.minimum(t1, t2)
    tmax = np.maximum(t1, t2)
    t_in = np.nanmax(tmin, axis=1)
    t_out = np.nanmin(tmax, axis=1)
    hit = (t_out >= np.maximum(t_in, 0.0)) & (t_in > 0)
    top = np.argmax(tmin, axis=1) == 1
    return np.where(hit, t_in, np.inf), top & hit


def _ray_sphere_candidates(state: FrameState, rays: Rays):
    """Rays of ``rays`` crossing a lobe's bounding sphere: (indices, t_enter, t_exit)."""
    pix = _candidate_pixels(state, rays)
    oc = rays.origin[None] - state.centers  # (L, 3)
    b = rays.dirs[pix] @ oc.T  # (P, L)
    c = (oc * oc).sum(axis=1) - state.bound_radii**2
    disc = b * b - c[None]
    cross = disc > 0
    root = np.sqrt(np.where(cross, disc, 0.0))
    t_in = np.where(cross, -b - root, np.inf)
    t_out = np.where(cross, -b + root, -np.inf)
    sel = cross.any(axis=1) & (t_out.max(axis=1) > 0)
    return pix[sel], np.maximum(t_in[sel].min(axis=1), 0.0), t_out[sel].max(axis=1)


def trace_many(state: FrameState, rays_list: list[Rays]) -> list[dict[str, np.ndarray]]:
    """Sphere-trace the scene field along the rays of several cameras at once.

    For each :class:`Rays`, returns ``{"t": (N,) hit distance m (inf = miss),
    "normal": (N, 3) unit outward normal (0 where missed), "label": (N,) bubble id
    hit (-1 = none)}``. Only rays crossing a lobe's bounding sphere are marched; a
    ray has converged when the field is below 3 % of its pixel footprint.
    """
    outs = []
    for rays in rays_list:
        n = rays.dirs.shape[0]
        outs.append({"t": np.full(n, np.inf), "normal": np.zeros((n, 3)), "label": np.full(n, -1)})
    if len(state.ids) == 0:
        return outs
    parts = [_ray_sphere_candidates(state, r) for r in rays_list]
    idx = np.concatenate([p[0] for p in parts])
    if idx.size == 0:
        return outs
    owner = np.concatenate([np.full(p[0].size, i) for i, p in enumerate(parts)])
    t = np.concatenate([p[1] for p in parts])
    t_far = np.concatenate([p[2] for p in parts])
    o = np.concatenate(
        [np.broadcast_to(r.origin, (p[0].size, 3)) for r, p in zip(rays_list, parts, strict=True)]
    )
    d = np.concatenate([r.dirs[p[0]] for r, p in zip(rays_list, parts, strict=True)])
    footprint = np.concatenate(
        [np.full(p[0].size, 1.0 / r.camera.K[0, 0]) for r, p in zip(rays_list, parts, strict=True)]
    )
    active = np.arange(idx.size)
    done_t = np.full(idx.size, np.inf)
    done_lab = np.full(idx.size, -1)
    for _ in range(MAX_STEPS):
        if active.size == 0:
            break
        ta = t[active]
        f, lab = state.sdf_and_label(o[active] + ta[:, None] * d[active])
        hit = f < np.maximum(HIT_EPS, 0.03 * ta * footprint[active])
        done_t[active[hit]] = ta[hit]
        done_lab[active[hit]] = lab[hit]
        t[active] = ta + STEP * np.maximum(f, HIT_EPS)
        active = active[~hit & (t[active] < t_far[active])]
    got = np.flatnonzero(np.isfinite(done_t))
    p = o[got] + done_t[got, None] * d[got]
    # Normal from four tetrahedral samples: Σ_k e_k·f(p + h·e_k) ∝ ∇f.
    tet = np.array([[1.0, -1.0, -1.0], [-1.0, -1.0, 1.0], [-1.0, 1.0, -1.0], [1.0, 1.0, 1.0]])
    f4 = state.sdf((p[:, None, :] + 1e-6 * tet[None]).reshape(-1, 3)).reshape(-1, 4)
    g = f4 @ tet
    g /= np.maximum(np.linalg.norm(g, axis=1, keepdims=True), 1e-12)
    lab = done_lab[got]
    for i, out in enumerate(outs):
        mine = owner[got] == i
        k = idx[got[mine]]
        out["t"][k] = done_t[got[mine]]
        out["normal"][k] = g[mine]
        out["label"][k] = lab[mine]
    return outs


def trace(state: FrameState, rays: Rays) -> dict[str, np.ndarray]:
    """Sphere-trace one camera's rays; see :func:`trace_many`."""
    return trace_many(state, [rays])[0]


#: Backlight patterns of :func:`background`.
BACKLIGHTS = ("smooth", "gradient", "stripes", "speckle", "dim")


def background(
    cam_name: str, height: int, width: int, seed: int = 0, pattern: str = "smooth"
) -> np.ndarray:
    """(H, W) backlight level in [0, 1] for camera ``cam_name``: bright, slightly uneven.

    Defined on normalised image coordinates, so the same camera at another
    resolution sees the same pattern. ``pattern`` (:data:`BACKLIGHTS`): ``smooth``
    (vignetting and a faint diffuser pattern), ``gradient`` (plus a strong left-to-right
    fall-off, to 60 %), ``stripes`` (plus a diffuser's stripes, ±6 %), ``speckle``
    (plus a blotchy diffuser texture, ±5 %), ``dim`` (the smooth pattern at half level).
    """
    if pattern not in BACKLIGHTS:
        raise ValueError(f"unknown backlight pattern {pattern!r}; choose from {BACKLIGHTS}")
    bg = _smooth_background(cam_name, height, width, seed)
    if pattern == "smooth":
        return bg
    rng = np.random.default_rng([seed, zlib.crc32(cam_name.encode()), 77])
    y = (np.arange(height) + 0.5) / height - 0.5
    x = (np.arange(width) + 0.5) / width - 0.5
    X, Y = np.meshgrid(x, y)
    if pattern == "gradient":
        side = rng.choice([-1.0, 1.0])
        return bg * (0.8 + 0.4 * side * X)
    if pattern == "stripes":
        ang = rng.uniform(0, np.pi)
        k = rng.uniform(8, 14)
        return bg * (1 + 0.06 * np.sin(2 * np.pi * k * (np.cos(ang) * X + np.sin(ang) * Y)))
    if pattern == "speckle":
        tex = rng.normal(size=(24, 24))
        tex = cv2.resize(tex, (width, height), interpolation=cv2.INTER_CUBIC)
        tex = cv2.GaussianBlur(tex, (0, 0), max(width, height) / 40)
        return bg * (1 + 0.05 * tex / max(np.abs(tex).max(), 1e-9))
    return 0.5 * bg  # dim


def _smooth_background(cam_name: str, height: int, width: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng([seed, zlib.crc32(cam_name.encode())])
    y = (np.arange(height) + 0.5) / height - 0.5
    x = (np.arange(width) + 0.5) / width - 0.5
    X, Y = np.meshgrid(x, y)
    cx, cy = rng.uniform(-0.15, 0.15, size=2)
    bg = 0.84 * (1.0 - 0.45 * ((X - cx) ** 2 + (Y - cy) ** 2))
    for _ in range(3):
        k = rng.uniform(1.0, 3.0, size=2) * rng.choice([-1, 1], size=2)
        bg += rng.uniform(0.01, 0.025) * np.sin(
            2 * np.pi * (k[0] * X + k[1] * Y) + rng.uniform(0, 6.3)
        )
    bg += rng.uniform(-0.03, 0.03) * Y
    return bg


def _smoothstep(a: float, b: float, x: np.ndarray) -> np.ndarray:
    s = np.clip((x - a) / (b - a), 0.0, 1.0)
    return s * s * (3 - 2 * s)


def shade(rays: Rays, hits: dict[str, np.ndarray], bg: np.ndarray) -> np.ndarray:
    """(H, W) noiseless shadowgraph intensity in [0, 1] from traced ``hits``."""
    bgf = bg.ravel()
    img = bgf.copy()
    t_plate, top = rays.t_plate, rays.plate_top
    bubble = np.isfinite(hits["t"]) & (hits["t"] < t_plate)
    cos = np.abs(np.einsum("nk,nk->n", hits["normal"][bubble], rays.dirs[bubble]))
    core = _smoothstep(0.80, 0.95, cos)
    img[bubble] = bgf[bubble] * (0.09 + 0.12 * cos + 0.64 * core)
    plate = np.isfinite(t_plate) & ~bubble
    # Top face at grazing incidence: dim, with faint machining streaks along x.
    p = rays.origin + t_plate[plate, None] * rays.dirs[plate]
    streak = 1.0 + 0.08 * np.sin(p[:, 2] * 2 * np.pi / 4e-4)
    img[plate] = np.where(top[plate], 0.26 * bgf[plate] * streak, 0.04)
    return img.reshape(rays.height, rays.width)


def sensor(
    img: np.ndarray,
    rng: np.random.Generator,
    blur_sigma: float = 0.8,
    full_well: float = 2500.0,
    read_noise: float = 0.003,
) -> np.ndarray:
    """Blur (σ in pixels), add shot and read noise; returns float image in [0, 1]."""
    if blur_sigma > 0:
        img = cv2.GaussianBlur(img.astype(np.float64), (0, 0), blur_sigma)
    img = rng.poisson(np.clip(img, 0, None) * full_well) / full_well
    img = img + rng.normal(0.0, read_noise, size=img.shape)
    return np.clip(img, 0.0, 1.0)


def quantize(img: np.ndarray, bit_depth: int = 8) -> np.ndarray:
    """[0, 1] float image → uint8 (``bit_depth`` 8) or uint16 grey levels (12: values
    in [0, 4095], as a 12-bit sensor; 16: [0, 65535])."""
    if bit_depth == 8:
        return np.round(img * 255).astype(np.uint8)
    if bit_depth in (12, 16):
        return np.round(img * (2**bit_depth - 1)).astype(np.uint16)
    raise ValueError(f"bit depth must be 8, 12 or 16, got {bit_depth}")


def render_views(
    state: FrameState,
    rays_list: list[Rays],
    bgs: list[np.ndarray],
    rngs: list[np.random.Generator],
    out_sizes: list[tuple[int, int] | None],
    blur_sigmas: list[float],
    noise: tuple[float, float] | None = None,
) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """Several views of one frame: per view a noisy image (H', W') in [0, 1], the
    labels (H, W) int32 of the bubble seen through each ray (-1 = none), and the
    noiseless image (H', W') the noise was drawn around.

    A view's ``rays`` may be supersampled; its ``out_size = (W', H')`` then
    area-averages the image down (labels stay at the ray resolution). Blur σ is in
    output pixels. ``noise = (full_well electrons, read noise fraction)`` of
    :func:`sensor` (default: its defaults).
    """
    fw, rn = noise if noise is not None else (2500.0, 0.003)
    hits_all = trace_many(state, rays_list)
    out = []
    for rays, hits, bg, rng, size, sigma in zip(
        rays_list, hits_all, bgs, rngs, out_sizes, blur_sigmas, strict=True
    ):
        clean = shade(rays, hits, bg)
        visible = np.isfinite(hits["t"]) & (hits["t"] < rays.t_plate)
        labels = np.where(visible, hits["label"], -1).reshape(rays.height, rays.width)
        clean = optics(clean, size, sigma)
        noisy = sensor(clean, rng, blur_sigma=0.0, full_well=fw, read_noise=rn)
        out.append((noisy, labels.astype(np.int32), clean))
    return out


def optics(clean: np.ndarray, out_size: tuple[int, int] | None, blur_sigma: float) -> np.ndarray:
    """Noiseless image at the output size: ``clean`` (H, W) at the ray resolution,
    Gaussian-blurred (σ in output pixels) and, when ``out_size = (W', H')`` differs,
    area-averaged down; float64 (H', W') in [0, 1]."""
    clean = np.asarray(clean, dtype=np.float64)
    height, width = clean.shape
    if out_size is not None and out_size != (width, height):
        clean = cv2.GaussianBlur(clean, (0, 0), blur_sigma * width / out_size[0])
        return cv2.resize(clean, out_size, interpolation=cv2.INTER_AREA)
    if blur_sigma > 0:
        clean = cv2.GaussianBlur(clean, (0, 0), blur_sigma)
    return clean


def empty_view(
    rays: Rays, bg: np.ndarray, out_size: tuple[int, int] | None, blur_sigma: float
) -> np.ndarray:
    """(H', W') noiseless view of the scene without bubbles (backlight and plate): the
    reference frame a lab records before boiling starts, through :func:`optics`."""
    n = rays.height * rays.width
    hits = {"t": np.full(n, np.inf), "normal": np.zeros((n, 3))}
    return optics(shade(rays, hits, bg), out_size, blur_sigma)


def render_frame(
    state: FrameState,
    rays: Rays,
    bg: np.ndarray,
    rng: np.random.Generator,
    out_size: tuple[int, int] | None = None,
    blur_sigma: float = 0.8,
) -> tuple[np.ndarray, np.ndarray]:
    """One view of one frame, (noisy image, labels); see :func:`render_views`."""
    img, labels, _ = render_views(state, [rays], [bg], [rng], [out_size], [blur_sigma])[0]
    return img, labels
