"""Synthetic ChArUco calibration images of the reference rig.

The rig's board (5×7 squares of 4 mm, 3 mm markers, ``DICT_4X4_50``) is drawn with
OpenCV's own board image (``cv2.aruco.CharucoBoard.generateImage``) and ray-cast
through the *true* cameras, lens distortion included: every output pixel is split
into 3×3 sub-pixels, each sub-pixel's ray (``Camera.pixel_rays(distorted=True)`` at
pixel centres, interpolated bilinearly in between) is intersected with the board plane and the board image is sampled there; the
sub-pixels are averaged (anti-aliasing), then the image is lightly blurred and noised.

Board frame (OpenCV's ``CharucoBoard.getChessboardCorners`` frame): origin at the
top-left corner of the square grid, x along the columns (right in the board image),
y along the rows (down in the board image), z = x × y (into the board, away from a
viewer who reads it).

Lab frame from the reference image (keys of :func:`board_yaml_dict`): in the image
``reference_image`` (``pose000.png``) the board stands upright on the heated plate,
facing cam0: board +x is lab +x, board +y (rows going down) is lab −y, board +z is
lab −z, and the board point ``lab_origin_in_board`` (metres, board frame; by default
the centre of the grid's bottom edge) is the lab origin. So
``x_lab = diag(1, −1, −1) · (x_board − [ox, oy, 0])``.

The synthetic generator uses no reconstruction code: only the true cameras and
OpenCV's board drawing.
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path

import cv2
import numpy as np

from surfphase.cameras import Camera
from surfphase.io import atomic_path
from surfphase.synth.rig import SCENE_CENTER

#: Rotation taking board-frame axes to lab axes in the reference pose.
BOARD_TO_LAB_AXES = np.diag([1.0, -1.0, -1.0])

_PX_PER_SQUARE = 200  # board texture: 0.02 mm per texel for 4 mm squares
_SUPERSAMPLE = 3  # sub-pixels per image pixel along each axis
_PAPER_MARGIN = 0.5  # white paper around the grid, in squares
_BOARD_BLACK, _BOARD_WHITE, _BACKGROUND = 25.0, 225.0, 165.0  # 8-bit grey levels


def board_yaml_dict() -> dict:
    """The rig's board description (what ``board.yaml`` holds), metres.

    Keys: ``squares_x``, ``squares_y`` (squares along board x and y),
    ``square_length``, ``marker_length`` (m), ``dictionary`` (an OpenCV ``DICT_*``
    name), and the lab-frame definition: ``reference_image`` (file name of the
    image in which the board stands upright on the heated plate facing cam0),
    ``lab_origin_in_board`` ([x, y] in the board frame, metres: the lab origin;
    here the centre of the grid's bottom edge).
    """
    sx, sy, sq = 5, 7, 0.004
    return {
        "squares_x": sx,
        "squares_y": sy,
        "square_length": sq,
        "marker_length": 0.003,
        "dictionary": "DICT_4X4_50",
        "reference_image": "pose000.png",
        "lab_origin_in_board": [sx * sq / 2, sy * sq],
    }


def _board_texture(board: dict) -> tuple[np.ndarray, float, int]:
    """Board image as float32 grey levels with a white paper margin.

    Returns (texture (H, W), metres per texel, margin in texels).
    """
    dictionary = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, board["dictionary"]))
    cb = cv2.aruco.CharucoBoard(
        (board["squares_x"], board["squares_y"]),
        board["square_length"],
        board["marker_length"],
        dictionary,
    )
    w, h = board["squares_x"] * _PX_PER_SQUARE, board["squares_y"] * _PX_PER_SQUARE
    img = cb.generateImage((w, h), marginSize=0, borderBits=1)
    margin = int(round(_PAPER_MARGIN * _PX_PER_SQUARE))
    img = cv2.copyMakeBorder(img, margin, margin, margin, margin, cv2.BORDER_CONSTANT, value=255)
    tex = _BOARD_BLACK + (img.astype(np.float32) / 255.0) * (_BOARD_WHITE - _BOARD_BLACK)
    return tex, board["square_length"] / _PX_PER_SQUARE, margin


def _rotation(axis: np.ndarray, angle: float) -> np.ndarray:
    """(3, 3) rotation by ``angle`` radians about ``axis``."""
    rvec = np.asarray(axis, dtype=np.float64)
    rvec = rvec / np.linalg.norm(rvec) * angle
    R, _ = cv2.Rodrigues(rvec)
    return R


def reference_pose(board: dict) -> tuple[np.ndarray, np.ndarray]:
    """Board pose of the reference image: ``x_lab = R @ x_board + t`` (m)."""
    ox, oy = board["lab_origin_in_board"]
    R = BOARD_TO_LAB_AXES.copy()
    t = -R @ np.array([ox, oy, 0.0])
    return R, t


def _visible_corners(
    cam: Camera, R: np.ndarray, t: np.ndarray, board: dict, max_obliquity_deg: float = 70.0
) -> int:
    """How many inner corners of a board at pose (R, t) ``cam`` can detect.

    A ChArUco corner is detectable when the four squares around it (so both of its
    markers) lie inside the image, on the printed side of the board, and the board is
    seen less obliquely than ``max_obliquity_deg`` (angle between its normal and the
    line of sight to its centre).
    """
    sq = board["square_length"]
    nx, ny = board["squares_x"], board["squares_y"]
    ii, jj = np.meshgrid(np.arange(nx + 1), np.arange(ny + 1), indexing="xy")
    Xb = np.stack([ii.ravel() * sq, jj.ravel() * sq, np.zeros(ii.size)], axis=1)
    Xw = Xb @ R.T + t
    normal = R[:, 2]  # board +z (away from the printed side) in world
    sight = cam.center - Xw.mean(axis=0)
    cos_obl = -(normal @ sight) / np.linalg.norm(sight)
    if cos_obl <= np.cos(np.deg2rad(max_obliquity_deg)):  # too oblique, or seen from behind
        return 0
    if np.any(cam.world_to_camera(Xw)[:, 2] <= 0):
        return 0
    uv = cam.project(Xw).reshape(ny + 1, nx + 1, 2)
    pad = 4.0
    inside = (
        (uv[..., 0] > pad)
        & (uv[..., 0] < cam.width - 1 - pad)
        & (uv[..., 1] > pad)
        & (uv[..., 1] < cam.height - 1 - pad)
    )
    ok = (
        inside[:-2, :-2]
        & inside[:-2, 1:-1]
        & inside[:-2, 2:]
        & inside[1:-1, :-2]
        & inside[1:-1, 2:]
        & inside[2:, :-2]
        & inside[2:, 1:-1]
        & inside[2:, 2:]
    )
    return int(ok.sum())


def _facing_rotation(towards: np.ndarray) -> np.ndarray:
    """Board axes (columns, lab frame) for a board facing ``towards``, rows going down."""
    z = -np.asarray(towards, dtype=np.float64)
    z /= np.linalg.norm(z)
    x = np.cross(np.array([0.0, 1.0, 0.0]), z)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    return np.stack([x, y, z], axis=1)


def calibration_poses(
    cameras: Mapping[str, Camera], board: dict, seed: int = 0, n_poses: int = 40
) -> list[tuple[np.ndarray, np.ndarray]]:
    """Board poses ``(R, t)`` (``x_lab = R x_board + t``, metres) for the calibration images.

    Pose 0 is the reference pose (board upright on the plate, facing cam0). The others
    cycle through

    * a *shared* pose: the board near the scene centre, tilted 25–50° from the cameras'
      mean direction, seen by every camera (at least 6 corners each): it ties the
      extrinsics together;
    * for each camera, an *oblique* pose: the board 60–100 mm in front of that camera,
      tilted 40–60° from its line of sight with much of it in view (at least 14
      corners). In a narrow field of view only strong perspective separates the focal
      length from the board's distance; the tilt axis alternates between horizontal,
      vertical and the diagonals.

    Each pose is also rolled in-plane by up to 30°. Deterministic in ``seed``.
    """
    rng = np.random.default_rng(seed)
    cams = list(cameras.values())
    poses = [reference_pose(board)]
    sq = board["square_length"]
    size = np.array([board["squares_x"] * sq, board["squares_y"] * sq])
    towards = np.mean([c.center - SCENE_CENTER for c in cams], axis=0)
    towards /= np.linalg.norm(towards)
    kinds = [None, *cams]  # None: shared pose; a camera: oblique pose for it alone
    count = {id(k): 0 for k in kinds}
    attempts = 0
    while len(poses) < n_poses:
        attempts += 1
        if attempts > 2000 * n_poses:
            raise RuntimeError("calibration_poses: could not place the board in view")
        i = len(poses)
        target = kinds[(i - 1) % len(kinds)]
        j = count[id(target)]
        phi = np.deg2rad(45.0 * (j % 4) + rng.uniform(-10.0, 10.0)) + np.pi * (j // 4 % 2)
        axis = np.array([np.cos(phi), np.sin(phi), 0.0])
        roll = _rotation([0.0, 0.0, 1.0], np.deg2rad(rng.uniform(-30.0, 30.0)))
        anchor = np.array([*(rng.uniform(0.3, 0.7, size=2) * size), 0.0])
        if target is None:
            R = _facing_rotation(towards) @ _rotation(axis, np.deg2rad(rng.uniform(25, 50))) @ roll
            aim = (
                SCENE_CENTER
                + rng.uniform(-0.003, 0.003, size=3)
                - towards * rng.uniform(-0.005, 0.015)
            )
            need = {c.name: 6 for c in cams}
        else:
            tilt = np.deg2rad(rng.uniform(40.0, 60.0))
            R = _facing_rotation(-target.view_dir) @ _rotation(axis, tilt) @ roll
            aim = (
                target.center
                + target.view_dir * rng.uniform(0.06, 0.10)
                + rng.uniform(-0.002, 0.002, size=3)
            )
            need = {target.name: 14}
        t = aim - R @ anchor
        if all(_visible_corners(c, R, t, board) >= need.get(c.name, 0) for c in cams):
            poses.append((R, t))
            count[id(target)] += 1
    return poses


def _camera_rays(cam: Camera, ss: int) -> tuple[np.ndarray, np.ndarray]:
    """Normalised camera-frame ray coordinates ``(x, y)`` (ray ∝ (x, y, 1)) of sub-pixels.

    Returns two (H, W·ss·ss) float32 arrays; sub-pixel ``k = i·ss + j`` of pixel
    ``(u, v)`` is at ``(u + o_j, v + o_i)`` with ``o = (k + 0.5)/ss − 0.5``. The rays
    through pixel centres (and a one-pixel ring around the image) come from
    ``Camera.pixel_rays(distorted=True)``; sub-pixels are interpolated bilinearly
    between them, which is exact to ~1e-5 px for a smooth lens.
    """
    w, h = cam.width, cam.height
    uu, vv = np.meshgrid(np.arange(-1, w + 1), np.arange(-1, h + 1), indexing="xy")
    uv = np.stack([uu.ravel(), vv.ravel()], axis=1).astype(np.float64)
    d = cam.pixel_rays(uv, distorted=True) @ cam.R.T  # camera frame
    grid = (d[:, :2] / d[:, 2:3]).reshape(h + 2, w + 2, 2)
    off = (np.arange(ss) + 0.5) / ss - 0.5
    out = np.empty((h, w, ss, ss, 2))
    for i, ov in enumerate(off):
        for j, ou in enumerate(off):
            # Bilinear weights towards the neighbour on the side of the offset.
            sv, su = int(np.sign(ov)), int(np.sign(ou))
            av, au = abs(ov), abs(ou)
            c00 = grid[1 : h + 1, 1 : w + 1]
            c01 = grid[1 : h + 1, 1 + su : w + 1 + su]
            c10 = grid[1 + sv : h + 1 + sv, 1 : w + 1]
            c11 = grid[1 + sv : h + 1 + sv, 1 + su : w + 1 + su]
            out[:, :, i, j] = (1 - av) * ((1 - au) * c00 + au * c01) + av * (
                (1 - au) * c10 + au * c11
            )
    out = out.reshape(h, w * ss * ss, 2).astype(np.float32)
    return out[..., 0].copy(), out[..., 1].copy()


def render_board_view(
    cam: Camera,
    R_board: np.ndarray,
    t_board: np.ndarray,
    board: dict,
    rng: np.random.Generator,
    rays: tuple[np.ndarray, np.ndarray] | None = None,
    blur_sigma: float = 0.6,
    noise_sigma: float = 1.5,
) -> np.ndarray:
    """Raw (distorted) 8-bit image (H, W) of the board at ``x_lab = R_board x_board + t_board``.

    ``rays`` are the cached output of ``_camera_rays`` for ``cam`` (computed if None).
    ``blur_sigma`` (px) and ``noise_sigma`` (grey levels) set the optics and sensor noise.
    """
    ss = _SUPERSAMPLE
    if rays is None:
        rays = _camera_rays(cam, ss)
    x, y = rays
    tex, metres_per_texel, margin = _board_texture(board)
    # Board pose in the camera frame: x_cam = Rc x_board + tc. A ray s·(x, y, 1) meets
    # the board plane n·(X − tc) = 0 at s = n·tc / n·(x, y, 1).
    Rc = (cam.R @ R_board).astype(np.float64)
    tc = cam.R @ t_board + cam.t
    n = Rc[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        s = np.float32(n @ tc) / (np.float32(n[0]) * x + np.float32(n[1]) * y + np.float32(n[2]))
        coords = []
        for axis in (0, 1):
            r = Rc[:, axis]
            a = np.float32(r[0]) * x + np.float32(r[1]) * y + np.float32(r[2])
            board_m = s * a - np.float32(r @ tc)  # board coordinate along ``axis``, metres
            coords.append(board_m / np.float32(metres_per_texel) + np.float32(margin - 0.5))
    valid = np.isfinite(s) & (s > 0)
    mx = np.where(valid, coords[0], np.float32(-1e6))
    my = np.where(valid, coords[1], np.float32(-1e6))
    h, w = cam.height, cam.width
    sampled = cv2.remap(
        tex,
        mx,
        my,
        interpolation=cv2.INTER_LINEAR,
        borderMode=cv2.BORDER_CONSTANT,
        borderValue=_BACKGROUND,
    )
    img = sampled.reshape(h, w, ss * ss).mean(axis=2, dtype=np.float64)
    # A gentle illumination fall-off, as under a real lamp.
    yy, xx = np.mgrid[0:h, 0:w]
    img = img * (0.92 + 0.08 * (1.0 - ((xx - w / 2) ** 2 + (yy - h / 2) ** 2) / (w * w / 2)))
    if blur_sigma > 0:
        img = cv2.GaussianBlur(img, (0, 0), blur_sigma)
    img = img + rng.normal(0.0, noise_sigma, img.shape)
    return np.clip(np.round(img), 0, 255).astype(np.uint8)


def write_calibration_images(
    cameras: dict[str, Camera], out_dir: Path, seed: int = 0, n_poses: int = 40
) -> None:
    """Write synchronized ChArUco images ``out_dir/<cam>/poseNNN.png`` for the input cameras.

    Only cameras whose ``role`` is ``"input"`` are imaged, at their native resolution,
    through their true distortion. ``pose000.png`` is the reference pose that defines
    the lab frame (see the module docstring and :func:`board_yaml_dict`); the same file
    name across cameras is the same moment. 8-bit grayscale PNG; deterministic in ``seed``.
    """
    out_dir = Path(out_dir)
    inputs = {n: c for n, c in cameras.items() if c.role == "input"}
    if not inputs:
        raise ValueError("write_calibration_images: no camera with role 'input'")
    board = board_yaml_dict()
    poses = calibration_poses(inputs, board, seed=seed, n_poses=n_poses)
    for ci, (name, cam) in enumerate(inputs.items()):
        rng = np.random.default_rng([seed, ci])
        rays = _camera_rays(cam, _SUPERSAMPLE)
        cam_dir = out_dir / name
        cam_dir.mkdir(parents=True, exist_ok=True)
        for pi, (R, t) in enumerate(poses):
            img = render_board_view(cam, R, t, board, rng, rays=rays)
            path = cam_dir / f"pose{pi:03d}.png"
            with atomic_path(path) as tmp:
                if not cv2.imwrite(str(tmp), img):
                    raise OSError(f"could not write {path}")
