"""Mesh stage: TSDF fusion of rendered surfel depth → marching cubes → PLY with velocity."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pandas as pd
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
        "bubble": np.ones((frames, n), np.int64),
    }
    fit = tmp_path / "fit"
    fit.mkdir()
    np.savez(fit / "surfels.npz", **arrays)
    ingest = tmp_path / "ingest"
    save_cameras(ingest / "cameras.json", input_cameras())
    (ingest / "meta.json").write_text(json.dumps({"session": "sphere"}))
    return fit, ingest


def _read_vtp(path) -> dict:
    """A .vtp read by VTK's own XML reader (an independent reader of our writer)."""
    from vtkmodules.util.numpy_support import vtk_to_numpy
    from vtkmodules.vtkIOXML import vtkXMLPolyDataReader

    reader = vtkXMLPolyDataReader()
    reader.SetFileName(str(path))
    reader.Update()
    assert reader.GetErrorCode() == 0, path
    poly = reader.GetOutput()
    polys = poly.GetPolys()
    offsets = vtk_to_numpy(polys.GetOffsetsArray())
    assert (np.diff(offsets) == 3).all()  # triangles only
    n = poly.GetNumberOfPoints()
    pd, fd = poly.GetPointData(), poly.GetFieldData()
    return {
        "points": vtk_to_numpy(poly.GetPoints().GetData()) if n else np.zeros((0, 3)),
        "polys": vtk_to_numpy(polys.GetConnectivityArray()).reshape(-1, 3),
        "velocity": vtk_to_numpy(pd.GetArray("velocity")).reshape(-1, 3),
        "speed": vtk_to_numpy(pd.GetArray("speed")),
        "active": (pd.GetScalars().GetName(), pd.GetVectors().GetName()),
        "frame": int(vtk_to_numpy(fd.GetArray("frame"))[0]),
        "time_s": float(vtk_to_numpy(fd.GetArray("TimeValue"))[0]),
    }


def _read_pvd(path) -> list[tuple[float, str]]:
    """(timestep, file) of a .pvd collection, parsed by VTK's XML parser (the python
    ``vtk`` package has no vtkPVDReader: that is ParaView's, built on this parser); each
    file it names must exist."""
    from vtkmodules.vtkIOXMLParser import vtkXMLDataParser

    parser = vtkXMLDataParser()
    parser.SetFileName(str(path))
    assert parser.Parse() == 1, path
    root = parser.GetRootElement()
    assert (root.GetName(), root.GetAttribute("type")) == ("VTKFile", "Collection")
    coll = root.GetNestedElement(0)
    assert coll.GetName() == "Collection"
    out = []
    for k in range(coll.GetNumberOfNestedElements()):
        ds = coll.GetNestedElement(k)
        assert ds.GetName() == "DataSet" and (path.parent / ds.GetAttribute("file")).is_file()
        out.append((float(ds.GetAttribute("timestep")), ds.GetAttribute("file")))
    return out


def test_vtp_writer_read_back_by_vtk(tmp_path):
    from surfphase.mesh.vtkxml import write_polydata, write_pvd

    rng = np.random.default_rng(3)
    verts = rng.normal(0.0, 2e-3, (50, 3))
    faces = rng.integers(0, 50, (80, 3))
    vel = rng.normal(0.0, 0.3, (50, 3))
    write_polydata(tmp_path / "a.vtp", verts, faces, vel, frame=12, time_s=12 / 3000)
    got = _read_vtp(tmp_path / "a.vtp")
    np.testing.assert_array_equal(got["points"], verts.astype(np.float32))
    np.testing.assert_array_equal(got["polys"], faces)
    np.testing.assert_array_equal(got["velocity"], vel.astype(np.float32))
    np.testing.assert_allclose(got["speed"], np.linalg.norm(vel, axis=1), rtol=1e-6)
    assert got["active"] == ("speed", "velocity")
    assert (got["frame"], got["time_s"]) == (12, 12 / 3000)
    # A frame without a mesh (no alive surfels) is still a valid, empty file.
    write_polydata(
        tmp_path / "b.vtp", np.zeros((0, 3)), np.zeros((0, 3)), np.zeros((0, 3)), 13, 0.1
    )
    empty = _read_vtp(tmp_path / "b.vtp")
    assert len(empty["points"]) == 0 and len(empty["polys"]) == 0 and empty["frame"] == 13
    write_pvd(tmp_path / "s.pvd", [(12 / 3000, "a.vtp"), (0.1, "b.vtp")])
    assert _read_pvd(tmp_path / "s.pvd") == [(12 / 3000, "a.vtp"), (0.1, "b.vtp")]
    with pytest.raises(ValueError, match="face indices"):
        write_polydata(tmp_path / "c.vtp", verts, faces + 50, vel, 0, 0.0)


def test_cli_writes_ply_per_frame_with_velocity(tmp_path, capsys):
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
            '{"surface": "fused", "voxels": 40, "n_orbit": 5, "orbit_step_deg": 60}',
            "--device",
            "cpu",
        ]
    )
    assert rc == 0
    printed = capsys.readouterr().out
    assert "mesh: frames to do 1/2, sphere: frame 3 meshed" in printed  # progress
    assert "ETA" in printed
    summary = json.loads((out / "mesh.json").read_text())
    assert summary["session"] == "sphere"
    # Per-bubble size: the one bubble, its volume against the true sphere's.
    sizes = pd.read_csv(out / "bubble_sizes.csv")
    assert sizes["frame"].tolist() == [3, 4] and (sizes["bubble"] == 1).all()
    assert sizes["closed"].all()
    np.testing.assert_allclose(sizes["d_eq_m"], 2 * R_SPHERE, rtol=0.05)
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
        # The ParaView copy, read by VTK's own reader: the same mesh, with the velocity.
        poly = _read_vtp(out / "vtk" / f"{r['frame']:06d}.vtp")
        np.testing.assert_array_equal(poly["points"], verts)
        np.testing.assert_array_equal(poly["polys"], faces)
        vel = np.stack([props["vx"], props["vy"], props["vz"]], 1)
        np.testing.assert_array_equal(poly["velocity"], vel)
        np.testing.assert_allclose(poly["speed"], np.linalg.norm(vel, axis=1), rtol=1e-6)
        assert poly["time_s"] == r["time_s"] and poly["frame"] == r["frame"]
    assert summary["pvd"] == "sphere.pvd"
    series = _read_pvd(out / "sphere.pvd")
    assert series == [(k / 1500, f"vtk/{f:06d}.vtp") for k, f in enumerate((3, 4))]


def test_hull_mesh_command_never_imports_torch(tmp_path):
    """`surfphase mesh --threads N` with the hull surface (the default) leaves torch,
    whose import costs 2-4 s a job, unloaded up to the stage's own checks; the fused
    surface imports it and takes the threads."""
    fit, ingest = _write_fit(tmp_path)
    code = (
        "import sys\n"
        "from surfphase.cli import main\n"
        "argv = ['mesh', '--fit', sys.argv[1], '--ingest', sys.argv[2], '--out', sys.argv[3],"
        " '--threads', '1', '--device', 'cpu'] + sys.argv[4:]\n"
        "rc = main(argv)\n"
        "print(rc, 'torch' in sys.modules)\n"
        "if 'torch' in sys.modules: print(sys.modules['torch'].get_num_threads())\n"
    )
    args = [sys.executable, "-c", code, str(fit), str(ingest), str(tmp_path / "out")]
    r = subprocess.run(args, capture_output=True, text=True, check=True)
    assert r.stdout.split() == ["2", "False"]  # stopped by the hull's missing masks
    assert "no masks folder" in r.stderr
    fused = '{"surface": "fused", "voxels": 24, "n_orbit": 2, "orbit_step_deg": 60}'
    r = subprocess.run([*args, "--params-json", fused], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    assert r.stdout.split()[-3:] == ["0", "True", "1"]


def test_bad_inputs_name_the_file(tmp_path):
    with pytest.raises(FileNotFoundError, match="surfels.npz"):
        from surfphase.mesh.stage import run_mesh

        run_mesh(tmp_path, tmp_path, tmp_path / "out")
    with pytest.raises(ValueError, match="unknown parameter"):
        mesh_params({"voxel": 3})


def test_hull_surface_needs_the_masks(tmp_path):
    """`mesh: surface: hull` (the default) meshes the masks' hulls: without a masks
    folder the stage stops and says so; an unknown surface is refused."""
    from surfphase.mesh.stage import run_mesh

    fit, ingest = _write_fit(tmp_path)
    with pytest.raises(ValueError, match="no masks folder"):
        run_mesh(fit, ingest, tmp_path / "out", device="cpu")
    # The hull needs no device, but a misspelt one is still refused.
    with pytest.raises(ValueError, match="device must be auto, cpu or cuda"):
        run_mesh(fit, ingest, tmp_path / "out", device="gpu")
    with pytest.raises(ValueError, match="surface must be"):
        run_mesh(fit, ingest, tmp_path / "out", {"surface": "tsdf"}, device="cpu")
