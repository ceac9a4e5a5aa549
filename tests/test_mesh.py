"""Mesh stage: TSDF fusion of rendered surfel depth → marching cubes → PLY with velocity."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from surfphase.cameras import look_at, save_cameras
from surfphase.cli import main
from surfphase.eval.geometry import chamfer, read_ply, sample_surface
from surfphase.mesh.ply import read_vertex_properties, speed_colors
from surfphase.mesh.stage import mesh_frame, mesh_params, vertex_velocities

R_SPHERE = 1.5e-3
CENTRE = np.array([0.0, 0.006, 0.0])


@pytest.fixture(autouse=True)
def _threads():
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


def sphere_surfels(n: int = 1500, radius: float = R_SPHERE, centre=CENTRE) -> dict:
    """Surfels tangent to a sphere on a Fibonacci lattice, overlapping, nearly opaque."""
    k = np.arange(n) + 0.5
    phi = np.arccos(1 - 2 * k / n)
    theta = np.pi * (1 + 5**0.5) * k
    d = np.stack([np.cos(theta) * np.sin(phi), np.cos(phi), np.sin(theta) * np.sin(phi)], 1)
    a = np.where(np.abs(d[:, :1]) < 0.9, [[1.0, 0, 0]], [[0, 1.0, 0]])
    tu = np.cross(d, a)
    tu /= np.linalg.norm(tu, axis=1, keepdims=True)
    tv = np.cross(d, tu)
    R = np.stack([tu, tv, d], -1)
    w = np.sqrt(np.clip(1 + R[:, 0, 0] + R[:, 1, 1] + R[:, 2, 2], 1e-12, None)) / 2
    q = np.stack(
        [
            w,
            (R[:, 2, 1] - R[:, 1, 2]) / (4 * w),
            (R[:, 0, 2] - R[:, 2, 0]) / (4 * w),
            (R[:, 1, 0] - R[:, 0, 1]) / (4 * w),
        ],
        1,
    )
    spacing = np.sqrt(4 * np.pi * radius**2 / n)
    return {
        "means": (np.asarray(centre) + radius * d).astype(np.float32),
        "quats": q.astype(np.float32),
        "log_scales": np.full((n, 2), np.log(0.7 * spacing), np.float32),
        "opacity": np.full(n, 0.95, np.float32),
    }


def input_cameras():
    """Two 128-px cameras 35° apart, 30 mm from the scene, like the demo's ingest."""
    cams = []
    for k, az in enumerate((0.0, 35.0)):
        a = np.deg2rad(az)
        eye = CENTRE + 0.03 * np.array([np.sin(a), 0.0, np.cos(a)])
        cams.append(look_at(f"cam{k}", eye, CENTRE, fx=225.0, width=128, height=128))
    return cams


def test_sphere_mesh_matches_analytic_sphere():
    s = sphere_surfels()
    verts, faces = mesh_frame(**s, inputs=input_cameras(), p=mesh_params({}))
    assert len(faces) > 500
    pts = sample_surface(verts, faces, 20000, seed=0)
    # Independent reference: points uniform on the analytic sphere.
    g = np.random.default_rng(1).normal(size=(20000, 3))
    ref = CENTRE + R_SPHERE * g / np.linalg.norm(g, axis=1, keepdims=True)
    cd = chamfer(pts, ref)["mean_mm"]
    assert cd < 0.04 * R_SPHERE * 1e3, cd
    radial = np.abs(np.linalg.norm(verts - CENTRE, axis=1) - R_SPHERE)
    assert np.median(radial) < 0.03 * R_SPHERE
    # Outward winding: the signed volume is positive and close to the sphere's.
    a, b, c = verts[faces[:, 0]], verts[faces[:, 1]], verts[faces[:, 2]]
    vol = np.einsum("ij,ij->i", a - CENTRE, np.cross(b - CENTRE, c - CENTRE)).sum() / 6
    assert vol == pytest.approx(4 / 3 * np.pi * R_SPHERE**3, rel=0.1)


def test_mesh_is_cut_at_the_heated_surface():
    """A sphere whose centre is 0.5 mm above the plate (y = 0): with ``floor_y = 0`` the
    mesh stops at the plate with a flat, closed base, and its volume is the sphere's
    less the cap below the plane (π h² (3r − h) / 3, h = r − 0.5 mm)."""
    centre = np.array([0.0, 0.5e-3, 0.0])
    s = sphere_surfels(centre=centre)
    cams = []
    for k, az in enumerate((0.0, 35.0)):
        a = np.deg2rad(az)
        eye = centre + 0.03 * np.array([np.sin(a), 0.0, np.cos(a)])
        cams.append(look_at(f"cam{k}", eye, centre, fx=225.0, width=128, height=128))
    free, _ = mesh_frame(**s, inputs=cams, p=mesh_params({"floor_y": None}))
    assert free[:, 1].min() < -0.9e-3  # the whole sphere, down to y = −1 mm
    verts, faces = mesh_frame(**s, inputs=cams, p=mesh_params({}))
    voxel = 2 * (R_SPHERE + 1e-3) / 64  # about: the surfels' box over 64 voxels
    assert verts[:, 1].min() > -voxel
    a, b, c = verts[faces[:, 0]], verts[faces[:, 1]], verts[faces[:, 2]]
    vol = np.einsum("ij,ij->i", a, np.cross(b, c)).sum() / 6
    h = R_SPHERE - 0.5e-3
    cut = 4 / 3 * np.pi * R_SPHERE**3 - np.pi * h**2 * (3 * R_SPHERE - h) / 3
    assert vol == pytest.approx(cut, rel=0.1)
    base = np.abs(verts[:, 1]) < 0.5 * voxel  # flat base: a disc of radius √(r² − c²)
    rim = np.sqrt(R_SPHERE**2 - 0.5e-3**2)
    assert np.hypot(verts[base, 0], verts[base, 2]).max() == pytest.approx(rim, rel=0.1)


def test_vertex_velocity_is_nearest_surfels():
    means = np.array([[0.0, 0.0, 0.0], [0.001, 0.0, 0.0]])
    vel = np.array([[0.1, 0.0, 0.0], [0.0, -0.2, 0.3]])
    verts = np.array([[0.0002, 0.0001, 0.0], [0.0009, 0.0, 0.0], [0.0006, 0.0, 0.0]])
    out = vertex_velocities(verts, means, vel)
    np.testing.assert_array_equal(out, vel[[0, 1, 1]])


def test_speed_colors_viridis_ends():
    rgb = speed_colors(np.array([0.0, 0.2, 0.4, 1.0]), 0.4)
    assert rgb.dtype == np.uint8
    np.testing.assert_array_equal(rgb[0], [68, 1, 84])  # viridis(0)
    np.testing.assert_array_equal(rgb[2], [253, 231, 37])  # viridis(1)
    np.testing.assert_array_equal(rgb[3], rgb[2])  # clipped


def _write_fit(tmp_path, frames: int = 2):
    """A two-frame fit folder: the sphere rising at 0.25 m/s, plus ingest cameras."""
    s = sphere_surfels(n=1200)
    n = len(s["means"])
    v = np.array([0.0, 0.25, 0.0], np.float32)
    dt = 1 / 1500
    arrays = {
        "frame": np.arange(frames, dtype=np.int64) + 3,
        "time_s": np.arange(frames) * dt,
        "alive": np.ones((frames, n), bool),
        "means": np.stack([s["means"] + v * dt * t for t in range(frames)]),
        "quats": np.stack([s["quats"]] * frames),
        "log_scales": np.stack([s["log_scales"]] * frames),
        "opacity": np.stack([s["opacity"]] * frames),
        "velocity": np.broadcast_to(v, (frames, n, 3)).copy(),
    }
    fit = tmp_path / "fit"
    fit.mkdir()
    np.savez(fit / "surfels.npz", **arrays)
    ingest = tmp_path / "ingest"
    save_cameras(ingest / "cameras.json", input_cameras())
    (ingest / "meta.json").write_text(json.dumps({"session": "sphere"}))
    return fit, ingest


def test_cli_writes_ply_per_frame_with_velocity(tmp_path):
    import pymeshlab

    fit, ingest = _write_fit(tmp_path)
    out = tmp_path / "mesh"
    rc = main(
        [
            "mesh",
            "--fit",
            str(fit),
            "--ingest",
            str(ingest),
            "--out",
            str(out),
            "--params-json",
            '{"voxels": 40, "n_orbit": 5, "orbit_step_deg": 60}',
            "--device",
            "cpu",
        ]
    )
    assert rc == 0
    summary = json.loads((out / "mesh.json").read_text())
    assert summary["session"] == "sphere"
    assert [r["frame"] for r in summary["frames"]] == [3, 4]
    for r in summary["frames"]:
        assert r["components"] == 1 and r["watertight"]
        path = out / f"{r['frame']:06d}.ply"
        verts, faces = read_ply(path)
        assert len(verts) == r["vertices"] and len(faces) == r["faces"]
        # Metres (not mm, not voxels): the mesh is the 1.5 mm sphere, coarse grid.
        assert np.ptp(verts, axis=0).max() == pytest.approx(2 * R_SPHERE, rel=0.15)
        props = read_vertex_properties(path)
        np.testing.assert_allclose(props["vy"], 0.25, rtol=1e-6)
        np.testing.assert_array_equal(props["vx"], 0.0)
        np.testing.assert_array_equal(
            np.stack([props["red"], props["green"], props["blue"]], 1)[0],
            speed_colors(np.array([0.25]), 0.4)[0],
        )
        ms = pymeshlab.MeshSet()
        ms.load_new_mesh(str(path))
        m = ms.current_mesh()
        assert m.vertex_number() == r["vertices"] and m.face_number() == r["faces"]
        np.testing.assert_allclose(m.vertex_matrix(), verts, atol=1e-9)


def test_bad_inputs_name_the_file(tmp_path):
    with pytest.raises(FileNotFoundError, match="surfels.npz"):
        from surfphase.mesh.stage import run_mesh

        run_mesh(tmp_path, tmp_path, tmp_path / "out")
    with pytest.raises(ValueError, match="unknown parameter"):
        mesh_params({"voxel": 3})
