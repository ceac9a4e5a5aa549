"""Synthetic campaign generator: the ground truth agrees with itself and with the images.

References are independent of the generator's own bookkeeping: analytic sphere and
cap volumes, ``np.gradient`` for finite differences, pymeshlab for mesh volumes,
brute-force ray marching for the masks.
"""

from __future__ import annotations

import json

import cv2
import numpy as np
import pandas as pd
import pymeshlab
import pytest
import yaml

from surfphase.cameras import load_cameras
from surfphase.cli import main as cli_main
from surfphase.synth.bubbles import BubbleScene
from surfphase.synth.campaign import campaign_settings, session_scene, write_campaign
from surfphase.synth.field import FrameState
from surfphase.synth.groundtruth import frame_truth, mesh_volume, write_ply
from surfphase.synth.shadowgraph import PLATE_MAX, PLATE_MIN

SEED = 3


def _sphere_state(center, radius) -> FrameState:
    return FrameState(
        t=0.0,
        ids=np.array([1]),
        centers=np.asarray([center], dtype=float),
        radii=np.array([radius]),
        lobe_bubble=np.array([0]),
        axes=np.eye(3)[None],
        amps=np.zeros((1, 3)),
        k_internal=np.zeros(1),
    )


def test_sphere_field_is_exact_distance_cut_by_plate():
    st = _sphere_state([0.001, 0.004, -0.002], 1e-3)
    rng = np.random.default_rng(0)
    p = rng.uniform(-0.004, 0.008, size=(500, 3))
    want = np.maximum(np.linalg.norm(p - st.centers[0], axis=1) - 1e-3, -p[:, 1])
    np.testing.assert_allclose(st.sdf(p), want, atol=1e-15)


@pytest.mark.parametrize("height", [0.005, 0.0006])
def test_truth_volume_of_free_and_plate_cut_sphere(height):
    r = 1e-3
    tr = frame_truth(_sphere_state([0.0, height, 0.0], r), spacing=5e-5)
    if height > r:
        v_true, cy = 4 / 3 * np.pi * r**3, height
    else:  # sphere minus the cap below y = 0 (cap height r − height)
        hc = r - height
        v_cap = np.pi * hc**2 * (3 * r - hc) / 3
        v_true = 4 / 3 * np.pi * r**3 - v_cap
        # centroid of the part above the plate, by slicing (independent quadrature)
        y = np.linspace(0.0, height + r, 20001)
        area = np.pi * np.clip(r**2 - (y - height) ** 2, 0, None)
        cy = np.trapezoid(area * y, y) / np.trapezoid(area, y)
    assert tr.volumes[0] == pytest.approx(v_true, rel=2e-3)
    assert tr.centroids[0, 1] == pytest.approx(cy, abs=2e-6)
    assert mesh_volume(tr.verts, tr.faces) == pytest.approx(v_true, rel=5e-3)


def test_ply_is_read_back_by_pymeshlab(tmp_path):
    tr = frame_truth(_sphere_state([0.0, 0.005, 0.0], 1e-3), spacing=1e-4)
    write_ply(tmp_path / "s.ply", tr.verts, tr.faces)
    ms = pymeshlab.MeshSet()
    ms.load_new_mesh(str(tmp_path / "s.ply"))
    m = ms.current_mesh()
    assert (m.vertex_number(), m.face_number()) == (len(tr.verts), len(tr.faces))
    v = ms.get_geometric_measures()["mesh_volume"]
    assert v == pytest.approx(mesh_volume(tr.verts, tr.faces), rel=1e-5)


def test_scene_is_deterministic_and_physical():
    a = BubbleScene(11, 24 / 1500, bubbles=5, force_merge=True)
    b = BubbleScene(11, 24 / 1500, bubbles=5, force_merge=True)
    sa, sb = a.state(0.007), b.state(0.007)
    np.testing.assert_array_equal(sa.centers, sb.centers)
    np.testing.assert_array_equal(sa.amps, sb.amps)
    assert a.merges() == b.merges()
    for bub in a.by_id.values():
        assert 0.5e-3 <= bub.r_detach <= 2.0e-3  # 1–4 mm diameter
        if not bub.extra.get("wake_of"):
            assert 0.1 <= bub.u_term[1] <= 0.3  # terminal rise speed, m/s


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    out = tmp_path_factory.mktemp("synth") / "campaign"
    write_campaign(out, preset="tiny", seed=SEED)
    return out


def test_layout_and_sheets(tiny):
    cfg = yaml.safe_load((tiny / "config.yaml").read_text())
    assert cfg == {
        "sessions": "sessions.tsv",
        "rigs": "rigs.tsv",
        "prior_clips": "clips",
        "seed": SEED,
    }
    sessions = pd.read_csv(tiny / "sessions.tsv", sep="\t", keep_default_na=False)
    assert list(sessions.columns) == ["session", "rig", "fps", "frames", "cam0", "cam1", "gt"]
    rigs = pd.read_csv(tiny / "rigs.tsv", sep="\t")
    assert list(rigs.columns) == ["rig", "board", "cam0", "cam1"]
    board = yaml.safe_load((tiny / rigs.board[0]).read_text())
    assert board["squares_x"] == 5 and board["squares_y"] == 7
    assert board["square_length"] == 0.004 and board["marker_length"] == 0.003
    assert board["dictionary"] == "DICT_4X4_50"
    for cam in ("cam0", "cam1"):
        assert len(list((tiny / rigs[cam][0]).glob("*.png"))) >= 6
    settings = campaign_settings("tiny")
    row = sessions.iloc[0]
    assert row.session == "session01" and row.rig == "rig01" and row["frames"] == ""
    cams = load_cameras(tiny / row["gt"] / "cameras.json")
    meta = json.loads((tiny / row["gt"] / "cameras.json").read_text())
    assert meta["fps"] == float(row["fps"]) == settings["fps"] and meta["fit_scale"] == 0.25
    names = ["cam0", "cam1", "mid"] + [f"orbit{k:02d}" for k in range(1, 12)]
    assert sorted(cams) == sorted(names)
    native, fit = settings["native"], settings["native"] // 4
    for n in names:
        c = cams[n]
        if n in ("cam0", "cam1"):
            assert (c.width, c.height, c.role) == (native, native, "input")
            assert np.any(c.dist != 0)
            frames = sorted((tiny / row[n]).glob("*.png"))
            assert len(frames) == settings["frames"]
            img = cv2.imread(str(frames[0]), cv2.IMREAD_UNCHANGED)
            assert img.shape == (native, native) and img.dtype == np.uint8
            m = np.load(tiny / row["gt"] / "masks" / f"{n}.npy")
            assert m.shape == (settings["frames"], native, native) and m.dtype == np.int32
        else:
            assert (c.width, c.height) == (fit, fit) and not np.any(c.dist)
            views = sorted((tiny / row["gt"] / "views" / n).glob("*.png"))
            assert len(views) == settings["frames"]
            assert cv2.imread(str(views[0]), cv2.IMREAD_UNCHANGED).shape == (fit, fit)
    assert len(sorted((tiny / row["gt"] / "meshes").glob("*.ply"))) == settings["frames"]
    clips = sorted((tiny / cfg["prior_clips"]).iterdir())
    assert len(clips) == settings["clips"]
    img = cv2.imread(str(sorted(clips[0].glob("*.png"))[0]), cv2.IMREAD_UNCHANGED)
    assert img.shape == (fit, fit)


def test_velocities_are_finite_differences_of_centroids(tiny):
    df = pd.read_csv(tiny / "session01" / "gt" / "bubbles.csv")
    fps = campaign_settings("tiny")["fps"]
    n_checked = 0
    for _, g in df.groupby("bubble"):
        g = g.sort_values("frame")
        assert np.all(np.diff(g.frame) == 1), "a bubble's frames are contiguous"
        if len(g) < 2:
            assert g[["vx", "vy", "vz"]].isna().all(axis=None)
            continue
        for c, v in zip("xyz", ("vx", "vy", "vz"), strict=True):
            want = np.gradient(g[c].to_numpy(), 1.0 / fps)
            np.testing.assert_allclose(g[v].to_numpy(), want, rtol=1e-6, atol=1e-8)
        n_checked += 1
    assert n_checked >= 2
    rising = df[(df.y > 0.004)]
    assert 0.08 < rising.vy.median() < 0.35  # plausible rise speeds, m/s


def test_mesh_volume_matches_equivalent_radii(tiny):
    df = pd.read_csv(tiny / "session01" / "gt" / "bubbles.csv")
    for f, g in df.groupby("frame"):
        ms = pymeshlab.MeshSet()
        ms.load_new_mesh(str(tiny / "session01" / "gt" / "meshes" / f"{f:06d}.ply"))
        v_mesh = ms.get_geometric_measures()["mesh_volume"]
        v_eq = (4 / 3 * np.pi * g.r_eq.to_numpy() ** 3).sum()
        assert v_mesh == pytest.approx(v_eq, rel=0.02), f"frame {f}"


def test_merge_ids(tiny):
    """Parents end and the merged bubble starts at the merge's frame; there its vapour
    is one body: its truth mask is one connected region in every view (a merge dated at
    the nominal spheres' contact left two oblate lobes apart in the images)."""
    from scipy import ndimage as ndi

    gt = tiny / "session01" / "gt"
    merges = pd.read_csv(gt / "merges.csv")
    assert len(merges) >= 1
    df = pd.read_csv(gt / "bubbles.csv")
    for m in merges.itertuples():
        for parent in (m.parent_a, m.parent_b):
            assert df[(df.bubble == parent) & (df.frame >= m.frame)].empty
        assert df[df.bubble == m.merged].frame.min() == m.frame
        for path in sorted((gt / "masks").glob("*.npy")):
            mask = np.load(path, mmap_mode="r")[int(m.frame)] == m.merged
            if mask.any():
                assert ndi.label(mask, np.ones((3, 3), bool))[1] == 1, (path.name, m.frame)


@pytest.mark.parametrize("seed", [11, 3])
def test_merges_happen_when_the_surfaces_touch(seed):
    """At each merge time the two lobes of the merged bubble (the parents, shape modes
    and all) are one body: the scene's field (the renderer's, an independent
    evaluation) is negative all along the segment between their centres; one contact
    step earlier the parents' surfaces were apart (``surface_gap`` > 0)."""
    from surfphase.synth.bubbles import CONTACT_DT, surface_gap

    scene = BubbleScene(seed, 24 / 1500, bubbles=5, force_merge=True)
    merges = scene.merges()
    assert merges
    for tm, pa, pb, child in merges:
        lobes, _ = scene.by_id[child].lobes(tm)
        (c0, *_), (c1, *_) = lobes
        line = c0[None] + np.linspace(0, 1, 201)[:, None] * (c1 - c0)[None]
        assert scene.state(tm).sdf(line).max() < 0, (tm, pa, pb)
        assert surface_gap(scene.by_id[pa], scene.by_id[pb], tm - CONTACT_DT) > 0


def _march_first_label(state, origin, dirs, step=4e-6):
    """Brute force: first sample along each ray inside the vapour, its label (-1: none)."""
    dist = np.linalg.norm(state.centers - origin, axis=1)
    ts = np.arange(
        max((dist - state.bound_radii).min(), 0.0), (dist + state.bound_radii).max(), step
    )
    out = np.full(len(dirs), -1)
    t_first = np.full(len(dirs), np.inf)
    for i, d in enumerate(dirs):
        pts = origin + ts[:, None] * d
        # keep the samples near a bubble to save time (lobe bounding spheres)
        near = np.zeros(len(ts), dtype=bool)
        for c, rb in zip(state.centers, state.bound_radii, strict=True):
            near |= np.linalg.norm(pts - c, axis=1) < rb
        if not near.any():
            continue
        f, lab = state.sdf_and_label(pts[near])
        inside = np.flatnonzero(f < 0)
        if inside.size:
            out[i] = lab[inside[0]]
            t_first[i] = ts[near][inside[0]]
    return out, t_first


def _plate_entry(origin, dirs):
    with np.errstate(divide="ignore"):
        t1 = (PLATE_MIN - origin) / dirs
        t2 = (PLATE_MAX - origin) / dirs
    tin = np.minimum(t1, t2).max(axis=1)
    tout = np.maximum(t1, t2).min(axis=1)
    return np.where((tout >= tin) & (tin > 0), tin, np.inf)


def test_masks_are_projections_of_the_true_field(tiny):
    cfg = campaign_settings("tiny")
    scene = session_scene(SEED, 0, cfg)
    gt = tiny / "session01" / "gt"
    cams = load_cameras(gt / "cameras.json")
    rng = np.random.default_rng(0)
    frame = cfg["frames"] // 2
    state = scene.state(frame / cfg["fps"])
    for name in ("cam0", "cam1"):
        cam = cams[name]
        mask = np.load(gt / "masks" / f"{name}.npy")[frame]
        fg = np.argwhere(mask >= 0)
        ring = np.argwhere(cv2.dilate((mask >= 0).astype(np.uint8), np.ones((7, 7))) & (mask < 0))
        pick = np.concatenate(
            [
                fg[rng.choice(len(fg), 60, replace=False)],
                ring[rng.choice(len(ring), 40, replace=False)],
            ]
        )
        uv = pick[:, ::-1].astype(float)  # (row, col) -> (u, v)
        dirs = cam.pixel_rays(uv, distorted=True)
        lab, t_first = _march_first_label(state, cam.center, dirs)
        lab = np.where(t_first < _plate_entry(cam.center, dirs), lab, -1)
        agree = lab == mask[pick[:, 0], pick[:, 1]]
        assert agree.mean() >= 0.97, f"{name}: {agree.mean():.3f} of sampled pixels agree"


def test_images_look_backlit(tiny):
    gt = tiny / "session01" / "gt"
    mask = np.load(gt / "masks" / "cam0.npy")[0]
    img = cv2.imread(str(tiny / "session01" / "cam0" / "000000.png"), cv2.IMREAD_UNCHANGED)
    upper = img[: img.shape[0] // 2]
    bg = upper[mask[: img.shape[0] // 2] < 0]
    assert bg.mean() > 150  # bright backlight
    fg = img[cv2.erode((mask >= 0).astype(np.uint8), np.ones((3, 3))) > 0]
    assert fg.size > 0 and np.median(fg) < 0.5 * bg.mean()  # dark bubbles (bright cores are small)
    assert fg.max() > 0.5 * bg.mean()  # ... with a bright core


def test_heldout_clean_views_and_reference_frames(tiny):
    """The noiseless held-out views differ from the recorded ones by sensor noise alone
    (zero mean, σ near √(I/full_well) ≈ 0.018 at the backlight), and the reference frame
    equals the noiseless view wherever no bubble is near."""
    gt = tiny / "session01" / "gt"
    for name in ("mid", "orbit05"):
        ref = cv2.imread(str(gt / "views_background" / f"{name}.png"), cv2.IMREAD_UNCHANGED)
        assert ref.dtype == np.uint16
        ref = ref / 65535.0
        for f in (0, 3):
            rec = cv2.imread(str(gt / "views" / name / f"{f:06d}.png"), cv2.IMREAD_UNCHANGED)
            clean = cv2.imread(str(gt / "views_clean" / name / f"{f:06d}.png"), -1)
            assert clean.dtype == np.uint16 and clean.shape == rec.shape == ref.shape
            noise = rec / 255.0 - clean / 65535.0
            bright = clean / 65535.0 > 0.6
            assert abs(noise[bright].mean()) < 0.004
            assert 0.012 < noise[bright].std() < 0.026
            # Away from bubbles (where the noiseless view equals the reference to 16-bit
            # rounding), and those pixels are most of the image.
            same = np.abs(clean / 65535.0 - ref) < 2e-5
            assert same.mean() > 0.5
            assert (np.abs(clean / 65535.0 - ref) > 0.05).any()  # the bubbles are not in it


def test_write_campaign_refuses_non_empty_folder(tmp_path):
    (tmp_path / "x").mkdir()
    (tmp_path / "x" / "keep.txt").write_text("mine")
    with pytest.raises(ValueError, match="not empty"):
        write_campaign(tmp_path / "x", preset="tiny")
    with pytest.raises(ValueError, match="preset"):
        write_campaign(tmp_path / "y", preset="huge")


def test_cli_small_campaign_is_deterministic(tmp_path):
    out = tmp_path / "c"
    rc = cli_main(
        ["synth", "--preset", "tiny", "--out", str(out), "--seed", "5", "--frames", "2",
         "--native", "128", "--clips", "1", "--clip-frames", "2", "--bit-depth", "16"]
    )  # fmt: skip
    assert rc == 0
    img = cv2.imread(str(out / "session01" / "cam1" / "000001.png"), cv2.IMREAD_UNCHANGED)
    assert img.dtype == np.uint16 and img.shape == (128, 128)
    assert len(pd.read_csv(out / "session01" / "gt" / "bubbles.csv")) > 0
    # Same seed and settings through the Python API: byte-identical outputs.
    again = write_campaign(
        tmp_path / "d", preset="tiny", seed=5, frames=2, native=128, clips=1, clip_frames=2,
        bit_depth=16,
    )  # fmt: skip
    for rel in ("session01/gt/bubbles.csv", "session01/cam1/000001.png",
                "session01/gt/masks/cam0.npy", "session01/gt/meshes/000001.ply",
                "session01/gt/views/orbit05/000000.png", "clips/clip000/000001.png",
                "rig01/calib/cam0/pose001.png"):  # fmt: skip
        assert (out / rel).read_bytes() == (again / rel).read_bytes(), rel


# --- the bench preset ---------------------------------------------------------------------


def test_bench_preset_spans_what_labs_vary():
    from surfphase.synth.campaign import BENCH_SESSIONS, CONTAINERS

    s = BENCH_SESSIONS
    assert len(s) >= 8
    angles = [x["angle"] for x in s]
    elev = [x["elevation"] for x in s]
    assert min(angles) <= 25 and max(angles) >= 60 and min(elev) == 0 and max(elev) >= 10
    assert any(w == h for w, h in (x["size"] for x in s))
    assert any(w != h for w, h in (x["size"] for x in s))
    fps = [x["fps"] for x in s]
    assert min(fps) <= 1000 and max(fps) >= 10000
    radii = [r for x in s for r in x["radius_mm"]]
    assert min(radii) <= 0.3 and max(radii) >= 1.5
    assert {x["shape"] for x in s} >= {"sphere", "spheroid", "tilted"}
    assert {x["merge"] for x in s} == {True, False}
    assert {x["bit_depth"] for x in s} == {8, 12, 16}
    assert len({x["backlight"] for x in s}) >= 4 and len({x["noise"] for x in s}) == 3
    assert {x["container"] for x in s} >= set(CONTAINERS) - {"png"}
    assert all(x["bit_depth"] == 8 for x in s if x["container"] in ("mp4", "avi"))
    assert all(x["bit_depth"] != 12 or x["container"] == "mraw" for x in s)
    with pytest.raises(ValueError, match="per session"):
        campaign_settings("bench", fps=500.0)


def test_bench_mixed_recombines_the_bench_settings():
    """``bench-mixed`` keeps every value the bench preset has, each group of settings
    permuted across the sessions on its own (a container with its bit depth), in
    combinations the bench preset does not have; deterministic in the seed."""
    from surfphase.synth.campaign import BENCH_SESSIONS, MIX_GROUPS, bench_specs

    assert bench_specs("bench", 3) is BENCH_SESSIONS
    mixed = bench_specs("bench-mixed", 3)
    assert mixed == bench_specs("bench-mixed", 3) != bench_specs("bench-mixed", 4)
    assert len(mixed) == len(BENCH_SESSIONS)
    for group in MIX_GROUPS:
        values = [[tuple(x[k] for k in group) for x in s] for s in (mixed, BENCH_SESSIONS)]
        assert sorted(values[0]) == sorted(values[1]), group
    assert {k for g in MIX_GROUPS for k in g} == set(BENCH_SESSIONS[0])
    pairs = {(x["bit_depth"], x["container"]) for x in BENCH_SESSIONS}
    assert all((x["bit_depth"], x["container"]) in pairs for x in mixed)
    assert any(x not in BENCH_SESSIONS for x in mixed)
    with pytest.raises(ValueError, match="per session"):
        campaign_settings("bench-mixed", bubbles=2)
    with pytest.raises(ValueError, match="not a bench preset"):
        bench_specs("demo", 0)


def test_tilted_bubbles_are_spheroids_off_the_vertical():
    from surfphase.synth.bubbles import TILT_DEG

    scene = BubbleScene(5, 0.01, bubbles=3, shape="tilted", radius_range=(0.6e-3, 1.0e-3))
    for b in scene.by_id.values():
        ax = b.modes[0].axis
        tilt = np.degrees(np.arccos(abs(ax[1]) / np.linalg.norm(ax)))
        assert TILT_DEG[0] - 1e-9 <= tilt <= TILT_DEG[1] + 1e-9
        assert b.modes[0].mean_free < -0.05  # oblate about the tilted axis
        assert all(np.allclose(m.axis, ax) for m in b.modes)  # modes about that axis too
        if not b.parents:
            assert 0.6e-3 <= b.r_detach <= 1.0e-3
    sphere = BubbleScene(5, 0.01, bubbles=3, shape="sphere")
    assert all(not np.any(b.mode_amplitudes(0.005)) for b in sphere.by_id.values())


def test_bench_drawn_draws_every_setting_within_its_ranges(tmp_path):
    """``bench-drawn`` draws each session's settings from :data:`DRAWN`'s ranges,
    deterministic in the seed, with values the bench preset never has; its campaign is
    written with the drawn frame size and rate."""
    from surfphase.synth.bubbles import SHAPES
    from surfphase.synth.campaign import BENCH_SESSIONS, DRAWN, NOISE, bench_specs
    from surfphase.synth.shadowgraph import BACKLIGHTS

    specs = [x for seed in range(6) for x in bench_specs("bench-drawn", seed)]
    assert bench_specs("bench-drawn", 2) == bench_specs("bench-drawn", 2)
    assert bench_specs("bench-drawn", 2) != bench_specs("bench-drawn", 3)
    for x in specs:
        assert set(x) == set(BENCH_SESSIONS[0])
        for k in ("angle", "elevation", "fps", "bubbles", "blur"):
            assert DRAWN[k][0] <= x[k] <= DRAWN[k][1], (k, x)
        assert all(DRAWN["size"][0] <= v <= DRAWN["size"][1] and v % 16 == 0 for v in x["size"])
        lo, hi = x["radius_mm"]
        assert DRAWN["radius_lo_mm"][0] <= lo < hi <= DRAWN["radius_max_mm"]
        assert x["shape"] in SHAPES and x["backlight"] in BACKLIGHTS and x["noise"] in NOISE
        assert (x["bit_depth"], x["container"]) in DRAWN["pairs"]
    for k in ("angle", "fps", "blur"):
        assert {x[k] for x in specs} - {x[k] for x in BENCH_SESSIONS}, k
    assert {x["merge"] for x in specs} == {True, False}
    assert len({x["size"][0] == x["size"][1] for x in specs}) == 2

    out = tmp_path / "drawn"
    write_campaign(out, preset="bench-drawn", seed=1, sessions=2, frames=2)
    info = json.loads((out / "synth.json").read_text())
    for i, want in enumerate(bench_specs("bench-drawn", 1)[:2]):
        name = f"session{i + 1:02d}"
        got = info["sessions"][name]["spec"]
        assert got["fps"] == want["fps"] and tuple(got["size"]) == tuple(want["size"])
        masks = np.load(out / name / "gt" / "masks" / "cam0.npy")
        assert masks.shape == (2, want["size"][1], want["size"][0])


@pytest.fixture(scope="module")
def bench2(tmp_path_factory):
    out = tmp_path_factory.mktemp("synth") / "bench"
    write_campaign(out, preset="bench", seed=SEED, sessions=3, frames=3)
    return out


def test_bench_campaign_containers_read_back_independently(bench2):
    """Every container read by another reader than the project's: tifffile (LZW tag),
    pyMRAW (12-bit packed), OpenCV for the MPEG-4 video; pixels match the project's
    readers, and each rig has its lab-frame reference image."""
    import pyMRAW
    import tifffile

    from surfphase.synth.campaign import BENCH_SESSIONS
    from surfphase.video import open_video

    sessions = pd.read_csv(bench2 / "sessions.tsv", sep="\t", keep_default_na=False)
    rigs = pd.read_csv(bench2 / "rigs.tsv", sep="\t")
    assert list(sessions.rig) == list(rigs.rig) == ["rig01", "rig02", "rig03"]
    board = yaml.safe_load((bench2 / "board.yaml").read_text())
    for r in rigs.itertuples():
        for cam in (r.cam0, r.cam1):
            assert (bench2 / cam / board["reference_image"]).is_file()
    for row, spec in zip(sessions.itertuples(), BENCH_SESSIONS, strict=False):
        w, h = spec["size"]
        assert float(row.fps) == spec["fps"]
        path = bench2 / row.cam0
        ours = np.stack(list(open_video(path).read(range(3))))
        assert ours.shape == (3, h, w)
        masks = np.load(bench2 / row.gt / "masks" / "cam0.npy")
        assert masks.shape == (3, h, w)
        if spec["container"] == "tiff-lzw":
            with tifffile.TiffFile(path) as tif:
                assert tif.pages[0].compression == tifffile.COMPRESSION.LZW
                assert np.array_equal(tif.asarray(), ours) and ours.dtype == np.uint16
        elif spec["container"] == "mraw":
            data, info = pyMRAW.load_video(str(path))
            assert int(info["Color Bit"]) == spec["bit_depth"] == 12
            assert np.array_equal(np.asarray(data), ours) and ours.max() < 4096
            assert ours.max() > 2000  # the backlight uses the 12-bit range
        elif spec["container"] == "mp4":
            cap = cv2.VideoCapture(str(path))
            ok, frame = cap.read()
            cap.release()
            assert ok and np.array_equal(cv2.cvtColor(frame, cv2.COLOR_BGR2GRAY), ours[0])
        # The images are backlit shadowgraphs: bubbles (true mask) darker than the rest.
        full = 2.0 ** spec["bit_depth"] - 1
        lit = ours[masks < 0].mean() / full
        dark = ours[masks >= 0].mean() / full
        assert lit > 0.3 and dark < 0.6 * lit
