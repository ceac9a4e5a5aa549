"""A mesh job killed (SIGKILL) mid-session resumes: finished frames are not meshed again,
the output folder appears only when whole, and the meshes equal an uninterrupted run's."""

from __future__ import annotations

import json
import os
import re
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import torch
from test_mesh import input_cameras, sphere_surfels

from surfphase.cameras import save_cameras
from surfphase.mesh.stage import run_mesh, run_mesh_window

# Coarse and quick (~0.3 s a frame); "session" colours couple every frame of a session.
# The fused surface: these fits come without masks.
PARAMS = {
    "surface": "fused",
    "voxels": 24,
    "n_orbit": 3,
    "orbit_step_deg": 90,
    "render_scale": 1.0,
    "speed_max": "session",
}
FIRST_FRAME = 10
EMPTY_POSITION = 5  # a frame with too few alive surfels: an empty mesh


@pytest.fixture(autouse=True)
def _threads():
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


def write_fit(root: Path, frames: int = 8, session: str = "sphere") -> tuple[Path, Path]:
    """A fit folder (surfels.npz) and an ingest folder (cameras.json, meta.json).

    A 1.5 mm sphere of surfels rising and growing 2 % a frame, its speed growing with
    time (fastest in the last frame); frame numbers start at ``FIRST_FRAME``.
    """
    s = sphere_surfels(n=600)
    n = len(s["means"])
    centre = s["means"].mean(0)
    dt = 1 / 1500
    speed = 0.1 + 0.05 * np.arange(frames)
    means, velocity = [], []
    for t in range(frames):
        v = np.array([0.0, speed[t], 0.0], np.float32)
        means.append(centre + (s["means"] - centre) * (1 + 0.02 * t) + v * dt * t)
        velocity.append(np.broadcast_to(v, (n, 3)))
    alive = np.ones((frames, n), bool)
    if frames > EMPTY_POSITION:
        alive[EMPTY_POSITION, 3:] = False
    arrays = {
        "frame": np.arange(frames, dtype=np.int64) + FIRST_FRAME,
        "time_s": np.arange(frames) * dt,
        "alive": alive,
        "means": np.stack(means).astype(np.float32),
        "quats": np.stack([s["quats"]] * frames),
        "log_scales": np.stack([s["log_scales"]] * frames),
        "opacity": np.stack([s["opacity"]] * frames),
        "velocity": np.stack(velocity).astype(np.float32),
    }
    fit = root / "fit"
    fit.mkdir(parents=True)
    np.savez(fit / "surfels.npz", **arrays)
    ingest = root / "ingest"
    save_cameras(ingest / "cameras.json", input_cameras())
    meta = {"session": session, "frame_indices": list(range(frames))}
    (ingest / "meta.json").write_text(json.dumps(meta))
    return fit, ingest


def assert_same_meshes(a: Path, b: Path) -> None:
    """Same PLY files byte for byte; same mesh.json but for the timings."""
    plys = sorted(p.name for p in a.glob("*.ply"))
    assert plys == sorted(p.name for p in b.glob("*.ply")) and plys
    for name in plys:
        assert (a / name).read_bytes() == (b / name).read_bytes(), name
    ja, jb = (json.loads((d / "mesh.json").read_text()) for d in (a, b))
    for j in (ja, jb):
        for row in j["frames"]:
            assert row.pop("seconds") >= 0
    assert ja == jb
    assert sorted(p.name for p in a.iterdir()) == sorted(p.name for p in b.iterdir())


def mesh_cmd(fit: Path, ingest: Path, out: Path) -> list[str]:
    return [
        sys.executable,
        "-m",
        "surfphase",
        "mesh",
        "--fit",
        str(fit),
        "--ingest",
        str(ingest),
        "--out",
        str(out),
        "--params-json",
        json.dumps(PARAMS),
        "--device",
        "cpu",
        "--threads",
        "1",
    ]


def meshed_frames(log: str) -> list[int]:
    """Frames a mesh job's log says it meshed (computed, not read back)."""
    return [int(m) for m in re.findall(r": frame (\d+) meshed", log)]


def finished_checkpoints(work: Path) -> list[Path]:
    """A job's finished frame checkpoints; a frame being written is a hidden
    ``.<frame>.*.part.npz`` until it is renamed, and a kill can leave one behind."""
    return sorted(p for p in work.glob("*.npz") if p.stem.isdigit())


def test_killed_mesh_job_resumes_without_redoing_frames(tmp_path):
    fit, ingest = write_fit(tmp_path, frames=8)
    ref = tmp_path / "ref"
    run_mesh(fit, ingest, ref, PARAMS, device="cpu")
    assert not (tmp_path / "ref.partial").exists()

    out = tmp_path / "mesh"
    partial = tmp_path / "mesh.partial"
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    first = tmp_path / "first.log"
    with open(first, "w") as fh:
        proc = subprocess.Popen(mesh_cmd(fit, ingest, out), env=env, stdout=fh, stderr=fh)
        deadline = time.time() + 120
        while not finished_checkpoints(partial):
            assert proc.poll() is None, "mesh finished before it could be killed"
            assert time.time() < deadline
            time.sleep(0.02)
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait()
    assert not out.exists()  # whole or not at all
    done = [int(p.stem) for p in finished_checkpoints(partial)]
    assert 1 <= len(done) < 8
    assert set(meshed_frames(first.read_text())) <= set(done)
    # What a kill in the middle of np.savez leaves: a truncated hidden temporary.
    (partial / f".{FIRST_FRAME + 7:06d}.killed.part.npz").write_bytes(b"PK\x03\x04")

    r = subprocess.run(mesh_cmd(fit, ingest, out), env=env, capture_output=True, text=True)
    assert r.returncode == 0, r.stdout + r.stderr
    resumed = re.search(r"(\d+) of 8 frames already meshed .*frames ([\d, -]+)", r.stdout)
    assert resumed, r.stdout
    assert int(resumed.group(1)) == len(done)
    runs = [[int(x) for x in run.split("-")] for run in resumed.group(2).split(", ")]
    assert [f for run in runs for f in range(run[0], run[-1] + 1)] == done
    redone = meshed_frames(r.stdout)
    assert not set(redone) & set(done), r.stdout
    assert sorted(redone + done) == list(range(FIRST_FRAME, FIRST_FRAME + 8))
    assert_same_meshes(ref, out)
    assert not partial.exists()


def test_checkpoints_are_reused_only_for_the_same_mesh(tmp_path, capsys):
    fit, ingest = write_fit(tmp_path, frames=2)
    # A window folder holds the same per-frame checkpoints a killed job leaves behind.
    run_mesh_window(fit, ingest, tmp_path / "w", 0, 2, PARAMS, device="cpu")
    ckpts = sorted((tmp_path / "w").glob("*.npz"))
    assert [p.stem for p in ckpts] == [f"{FIRST_FRAME:06d}", f"{FIRST_FRAME + 1:06d}"]

    def rerun(name: str, params: dict) -> str:
        (tmp_path / f"{name}.partial").mkdir()
        for p in ckpts:
            shutil.copy(p, tmp_path / f"{name}.partial" / p.name)
        capsys.readouterr()
        run_mesh(fit, ingest, tmp_path / name, params, device="cpu")
        assert not (tmp_path / f"{name}.partial").exists()
        return capsys.readouterr().out

    log = rerun("same", PARAMS)
    assert "2 of 2 frames already meshed" in log and meshed_frames(log) == []
    # Colours are not part of a frame's mesh: other colours reuse the frames ...
    log = rerun("colours", {**PARAMS, "speed_max": 0.4})
    assert "2 of 2 frames already meshed" in log and meshed_frames(log) == []
    # ... other mesh parameters do not.
    log = rerun("coarser", {**PARAMS, "voxels": 20})
    assert "already meshed" not in log
    assert meshed_frames(log) == [FIRST_FRAME, FIRST_FRAME + 1]
    fresh = tmp_path / "fresh"
    run_mesh(fit, ingest, fresh, {**PARAMS, "voxels": 20}, device="cpu")
    assert_same_meshes(fresh, tmp_path / "coarser")


def test_rerun_replaces_a_finished_output_whole(tmp_path):
    fit, ingest = write_fit(tmp_path, frames=1)
    out = tmp_path / "mesh"
    out.mkdir()
    (out / "stale.txt").write_text("from an older run")
    run_mesh(fit, ingest, out, PARAMS, device="cpu")
    names = sorted(p.name for p in out.iterdir())
    assert names == [f"{FIRST_FRAME:06d}.ply", "bubble_sizes.csv", "mesh.json", "sphere.pvd", "vtk"]
    assert [p.name for p in (out / "vtk").iterdir()] == [f"{FIRST_FRAME:06d}.vtp"]
    assert [p.name for p in tmp_path.iterdir() if p.name.startswith(".")] == []
