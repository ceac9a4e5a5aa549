"""``surfphase new-campaign``: a campaign folder from a folder of videos.

Finds the videos under ``--videos``, groups them into sessions and cameras, reads the
frame rate from Photron (CIH/CIHX) and Phantom (CINE) headers, and writes
``CAMPAIGN/config/{config.yaml, sessions.tsv, rigs.tsv, board.yaml}``.

Naming rule (the first that matches, per video):

1. Photron's default names ``C001H001S0001.cihx``: camera ``C001H001``, session ``S0001``.
2. Subfolders ``<session>/<camera>.<ext>`` or ``<session>/<camera>/`` (a folder of images).
3. Files ``<session>_<camera>.<ext>`` (the camera is the text after the last ``_``).

A video is a file with a known suffix (``.cih``/``.cihx`` + ``.mraw``, ``.cine``,
``.avi``, ``.mp4``, ``.mov``, ``.mkv``, ``.tif``/``.tiff`` stacks) or a folder of
images. The cameras, sorted by name, become ``cam0``, ``cam1``, ...; the sessions sheet
records which is which in a comment. All sessions share one rig, ``rig01``, whose
calibration images are ``--calib DIR/<camera>/`` (each camera's images, same file name
= same moment); without ``--calib`` the rigs sheet points at ``CAMPAIGN/calib/<cam>/``,
which is created empty for you to fill.
"""

from __future__ import annotations

import argparse
import os
import re
import shlex
from collections import defaultdict
from pathlib import Path

from surfphase.io import atomic_write_text
from surfphase.labformats import open_lab_video

VIDEO_SUFFIXES = {
    ".cih",
    ".cihx",
    ".mraw",
    ".cine",
    ".avi",
    ".mp4",
    ".mov",
    ".mkv",
    ".tif",
    ".tiff",
}
IMAGE_SUFFIXES = {".png", ".tif", ".tiff", ".jpg", ".jpeg", ".bmp"}
PHOTRON_NAME = re.compile(r"^(C\d+H\d+)(S\d+)$", re.IGNORECASE)
ID = re.compile(r"[^A-Za-z0-9_.-]+")

BOARD_YAML = """\
# ChArUco board of the rig (defaults: the reference rig). Lengths in metres.
squares_x: 5
squares_y: 7
square_length: 0.004   # side of a chessboard square
marker_length: 0.003   # side of an ArUco marker
dictionary: DICT_4X4_50
"""

SLURM_BLOCK = """
# For `surfphase run --cluster slurm`: your cluster's account and partitions.
# slurm:
#   account: my_account
#   partition: cpu
#   gpu_partition: gpu
"""


def _is_image_folder(p: Path) -> bool:
    return p.is_dir() and any(
        c.is_file() and c.suffix.lower() in IMAGE_SUFFIXES for c in p.iterdir()
    )


def _clean(name: str) -> str:
    """A session id the sheets accept (letters, digits, '_', '.', '-')."""
    s = ID.sub("-", name).strip("-.")
    return s or "session"


def find_videos(root: Path) -> dict[str, dict[str, Path]]:
    """``{session: {camera label: video path}}`` of the videos under ``root``."""
    root = Path(root)
    if not root.is_dir():
        raise FileNotFoundError(f"{root}: videos folder not found")
    found: dict[str, dict[str, Path]] = defaultdict(dict)

    def add(session: str, camera: str, path: Path) -> None:
        session = _clean(session)
        if camera in found[session]:
            raise ValueError(
                f"session {session}: two videos for camera '{camera}': "
                f"{found[session][camera]} and {path}"
            )
        found[session][camera] = path

    def videos_in(folder: Path) -> list[Path]:
        out = []
        for p in sorted(folder.iterdir()):
            if p.name.startswith(".") or p.name.lower() == "calib":
                continue
            if p.is_file() and p.suffix.lower() in VIDEO_SUFFIXES:
                # A Photron recording is its header; its .mraw is the data.
                if p.suffix.lower() == ".mraw" and any(
                    p.with_suffix(s).exists() for s in (".cih", ".cihx", ".CIH", ".CIHX")
                ):
                    continue
                if p.suffix.lower() == ".cih" and p.with_suffix(".cihx").exists():
                    continue
                out.append(p)
        return out

    for p in videos_in(root):
        m = PHOTRON_NAME.match(p.stem)
        if m:
            add(m.group(2), m.group(1), p)
        elif "_" in p.stem:
            session, camera = p.stem.rsplit("_", 1)
            add(session, camera, p)
        else:
            raise ValueError(
                f"{p}: cannot tell session and camera; name it <session>_<camera>{p.suffix} "
                "or put it in a folder <session>/<camera>" + p.suffix
            )
    for sub in sorted(q for q in root.iterdir() if q.is_dir() and not q.name.startswith(".")):
        if sub.name.lower() == "calib" or _is_image_folder(sub):
            continue
        for p in videos_in(sub):
            m = PHOTRON_NAME.match(p.stem)
            add(sub.name, m.group(1) if m else p.stem, p)
        for cam in sorted(q for q in sub.iterdir() if _is_image_folder(q)):
            add(sub.name, cam.name, cam)
    if not found:
        raise ValueError(
            f"{root}: no videos found (suffixes {', '.join(sorted(VIDEO_SUFFIXES))}, "
            "or folders of images)"
        )
    return dict(found)


def header_fps(path: Path) -> float | None:
    """Frame rate from a lab recording's header (CIH/CIHX/CINE), else ``None``."""
    if path.is_file() and path.suffix.lower() in {".cih", ".cihx", ".cine", ".mraw"}:
        return open_lab_video(path).fps
    return None


def _sheet_path(path: Path, sheet_dir: Path, camp: Path) -> str:
    """Relative to the sheet's folder when inside the campaign, else absolute."""
    path = path.resolve()
    if path.is_relative_to(camp):
        return os.path.relpath(path, sheet_dir)
    return str(path)


def native_sizes(found: dict[str, dict[str, Path]]) -> dict[str, tuple[int, int] | str]:
    """``{session: (width, height)}`` of each session's first camera, native pixels.

    A recording that cannot be read yet gets the reason instead of a size (the ingest
    of that session will stop with it, naming the file).
    """
    from surfphase.video import open_video

    sizes: dict[str, tuple[int, int] | str] = {}
    for session, cams in sorted(found.items()):
        path = cams[sorted(cams)[0]]
        try:
            h, w = open_video(path).shape
            sizes[session] = (int(w), int(h))
        except Exception as e:  # noqa: BLE001 - any reader error is reported, not raised
            sizes[session] = f"{path} not readable now ({e})"
    return sizes


def _ingest_comment(sizes: dict[str, tuple[int, int] | str], fit_size: int) -> str:
    """Comment lines saying what ``scale: auto`` does to each session's frames."""
    from surfphase.ingest import auto_scale

    lines = [
        f"# scale: auto fits each session at fit_size = {fit_size} px on the longer side",
        "# (about 3 s per frame for stage 1 on 2 CPU cores; raise it on a GPU):",
    ]
    for session, size in sizes.items():
        if isinstance(size, str):
            lines.append(f"#   {session}: {size}")
            continue
        w, h = size
        k = auto_scale(w, h, fit_size)
        fw, fh = max(1, round(w * k)), max(1, round(h * k))
        lines.append(f"#   {session}: native {w}x{h} -> fitted {fw}x{fh} (scale {k:.4g})")
    return "\n".join(lines) + "\n"


def _config_text(
    project_config: Path | None,
    clips: Path | None = None,
    sizes: dict[str, tuple[int, int] | str] | None = None,
    fit_size: int = 160,
) -> str:
    """The project's config/config.yaml with the sheet paths of a campaign.

    Refinement (prior, SDEdit, stage 2) is on only with ``clips`` (the monocular clips
    of the video prior); the ingest scale is ``auto`` (per session, from its native
    ``sizes``), with a comment saying what it gives.
    """
    if project_config and project_config.is_file():
        text = project_config.read_text()
        lines = [ln for ln in text.splitlines() if not ln.startswith("#")]
        text = "\n".join(lines).lstrip("\n") + "\n"
        text = re.sub(r"(?m)^sessions:.*$", "sessions: config/sessions.tsv", text)
        text = re.sub(r"(?m)^rigs:.*$", "rigs: config/rigs.tsv", text)
    else:
        text = "sessions: config/sessions.tsv\nrigs: config/rigs.tsv\nresults: results\n"
    scale = f"  scale: auto          # per session, see above\n  fit_size: {fit_size}\n"
    comment = _ingest_comment(sizes or {}, fit_size)
    if re.search(r"(?m)^ingest:", text):
        text = re.sub(r"(?m)^  (scale|fit_size):.*\n", "", text)
        text = re.sub(r"(?m)^ingest:.*\n", lambda m: comment + m.group(0) + scale, text, count=1)
    else:
        text += comment + "ingest:\n" + scale
    on = clips is not None
    clip_line = f"  clips: {clips}" if on else "  clips: null       # monocular clips (--clips)"
    if re.search(r"(?m)^  clips:", text):
        text = re.sub(r"(?m)^  clips:.*$", lambda _m: clip_line, text, count=1)
    else:
        text += f"prior:\n{clip_line}\n"
    enabled = (
        "  enabled: true       # refinement runs: monocular clips were given (--clips)"
        if on
        else "  enabled: false      # no monocular clips (--clips): stage 1 is the final fit"
    )
    if re.search(r"(?m)^refine:", text):
        text = re.sub(
            r"(?ms)^(refine:.*?\n)  enabled:[^\n]*", lambda m: m.group(1) + enabled, text, count=1
        )
    else:
        text += f"refine:\n{enabled}\n"
    head = (
        "# SurfPhase campaign, written by `surfphase new-campaign`. Paths are relative to the\n"
        "# campaign folder; every key is documented in workflow/schemas/config.schema.yaml.\n"
    )
    return head + text + SLURM_BLOCK


def _session_rates(found: dict, labels: list[str], fps: float | None) -> dict[str, float]:
    """``{session: frames/s}``: ``fps`` when given, else the videos' headers (which must
    agree); every session needs a video of every camera."""
    rates: dict[str, float] = {}
    for session, cams in sorted(found.items()):
        missing = [c for c in labels if c not in cams]
        if missing:
            raise ValueError(f"session {session}: no video for camera(s) {', '.join(missing)}")
        heads = {c: header_fps(p) for c, p in cams.items()}
        known = {c: r for c, r in heads.items() if r}
        if fps:
            rates[session] = float(fps)
        elif known:
            values = set(known.values())
            if len(values) > 1:
                raise ValueError(
                    f"session {session}: cameras disagree on the frame rate "
                    + ", ".join(f"{cams[c]}: {r:g} fps" for c, r in known.items())
                )
            rates[session] = values.pop()
        else:
            raise ValueError(
                f"session {session}: no frame rate in the files ({', '.join(map(str, cams.values()))}); "
                "give --fps"
            )
    return rates


def _calibration_folders(
    calib: Path | None, videos: Path, out: Path, cam_of: dict[str, str]
) -> dict[str, Path]:
    """``{camN: folder}``: ``calib/<camera label or camN>/``, else ``videos/calib/…``,
    else an empty ``OUT/calib/<camN>/`` to fill."""
    calib_dirs: dict[str, Path] = {}
    calib = Path(calib).resolve() if calib else None
    if calib is None and (videos / "calib").is_dir():
        calib = videos / "calib"
    for label, cam in cam_of.items():
        if calib is not None:
            cands = [calib / label, calib / cam]
            hit = next((c for c in cands if c.is_dir()), None)
            if hit is None:
                raise FileNotFoundError(
                    f"{calib}: no calibration folder for camera {label} ({cands[0].name}/ or {cam}/)"
                )
            calib_dirs[cam] = hit
        else:
            calib_dirs[cam] = out / "calib" / cam
            calib_dirs[cam].mkdir(parents=True, exist_ok=True)
    return calib_dirs


def new_campaign(
    videos: Path,
    out: Path,
    fps: float | None = None,
    calib: Path | None = None,
    project_config: Path | None = None,
    force: bool = False,
    clips: Path | None = None,
) -> dict:
    """Write a campaign's config and sheets for the videos under ``videos``.

    Returns ``{"sessions": {...}, "cameras": {label: camN}, "fps": {session: fps}}``.
    ``fps`` (frames per second) overrides the headers; it is required when a session
    has no lab-format video. ``clips``: the video prior's monocular clips; refinement is
    on only with them (they are checked here). Raises ValueError/FileNotFoundError naming
    the file or session.
    """
    videos, out = Path(videos).resolve(), Path(out).resolve()
    config_dir = out / "config"
    if not force and any((config_dir / n).exists() for n in ("config.yaml", "sessions.tsv")):
        raise ValueError(f"{config_dir}: already holds a campaign (use --force to overwrite)")
    if clips is not None:
        from surfphase.prior.clips import find_clips

        clips = Path(clips).resolve()
        find_clips(clips)  # raises, naming the folder, when it holds no clips
    found = find_videos(videos)
    labels = sorted({c for cams in found.values() for c in cams})
    if len(labels) < 2:
        raise ValueError(
            f"{videos}: found only camera {labels} (sessions {', '.join(found)}); SurfPhase "
            "needs two synchronized cameras per session"
        )
    cam_of = {label: f"cam{i}" for i, label in enumerate(labels)}
    rates = _session_rates(found, labels, fps)
    calib_dirs = _calibration_folders(calib, videos, out, cam_of)
    cams = [cam_of[label] for label in labels]
    mapping = ", ".join(f"{cam_of[label]} = {label}" for label in labels)
    rows = [
        "# Written by `surfphase new-campaign` from " + str(videos),
        f"# cameras: {mapping}",
        "\t".join(["session", "rig", "fps", "frames", *cams]),
    ]
    for session in sorted(found):
        paths = [_sheet_path(found[session][label], config_dir, out) for label in labels]
        rows.append("\t".join([session, "rig01", f"{rates[session]:g}", "", *paths]))
    rig_rows = [
        f"# cameras: {mapping}; calibration images: same file name across cameras = same moment",
        "\t".join(["rig", "board", *cams]),
        "\t".join(
            ["rig01", "board.yaml", *(_sheet_path(calib_dirs[c], config_dir, out) for c in cams)]
        ),
    ]
    atomic_write_text(config_dir / "board.yaml", BOARD_YAML)
    atomic_write_text(config_dir / "rigs.tsv", "\n".join(rig_rows) + "\n")
    atomic_write_text(config_dir / "sessions.tsv", "\n".join(rows) + "\n")
    sizes = native_sizes(found)
    clip_path = _sheet_path(clips, out, out) if clips is not None else None
    atomic_write_text(config_dir / "config.yaml", _config_text(project_config, clip_path, sizes))
    return {
        "sessions": {s: {cam_of[c]: str(p) for c, p in v.items()} for s, v in found.items()},
        "cameras": cam_of,
        "fps": rates,
        "calib": {c: str(p) for c, p in calib_dirs.items()},
        "native_sizes": sizes,
        "refine": clips is not None,
    }


def new_campaign_cmd(args: argparse.Namespace) -> int:
    from surfphase.commands.run import project_root

    out = Path(args.out)
    info = new_campaign(
        Path(args.videos),
        out,
        fps=args.fps,
        calib=Path(args.calib) if args.calib else None,
        project_config=project_root() / "config" / "config.yaml",
        force=args.force,
        clips=Path(args.clips) if args.clips else None,
    )
    print(f"Campaign written to {out / 'config'}:")
    print(f"  {len(info['sessions'])} session(s): " + ", ".join(sorted(info["sessions"])))
    print("  cameras: " + ", ".join(f"{v} = {k}" for k, v in info["cameras"].items()))
    print("  fps: " + ", ".join(f"{s} {r:g}" for s, r in sorted(info["fps"].items())))
    empty = [c for c, p in info["calib"].items() if not any(Path(p).iterdir())]
    if empty:
        print(
            "  calibration: put each camera's ChArUco images in "
            + ", ".join(info["calib"][c] for c in empty)
        )
    print(
        "  refinement: "
        + ("on (video prior trained on --clips)" if info["refine"] else "off (no --clips)")
    )
    print(f"  check the board in {out / 'config' / 'board.yaml'}")
    q = shlex.quote(str(out))
    print("Next:")
    print(f"  surfphase status --campaign {q}")
    print(f"  surfphase run --campaign {q} --cores 8        # or --cluster slurm")
    return 0


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "new-campaign",
        help="write a campaign's config and sheets from a folder of videos",
        description=(
            "Find the videos under --videos (named <session>_<camera>.<ext>, "
            "<session>/<camera>.<ext>, <session>/<camera>/ image folders, or Photron's "
            "C001H001S0001), read fps from MRAW/CINE headers, and write "
            "CAMPAIGN/config/{config.yaml,sessions.tsv,rigs.tsv,board.yaml}."
        ),
    )
    p.add_argument("--videos", required=True, metavar="DIR", help="folder of the videos")
    p.add_argument("--out", required=True, metavar="CAMPAIGN", help="campaign folder to write")
    p.add_argument("--fps", type=float, help="frame rate (fps); overrides the headers")
    p.add_argument(
        "--calib",
        metavar="DIR",
        help="calibration images, one subfolder per camera (default: VIDEOS/calib)",
    )
    p.add_argument(
        "--clips",
        metavar="DIR",
        help="monocular clips for the video prior: turns refinement (stage 2) on",
    )
    p.add_argument("--force", action="store_true", help="overwrite an existing config")
    p.set_defaults(func=new_campaign_cmd)


def bench_labformats_cmd(args: argparse.Namespace) -> int:
    """Read speed of the lab-format readers (frames/s), every frame checked."""
    import tempfile
    import time

    import numpy as np

    from surfphase.labformats import write_cine, write_mraw

    n, size = args.frames, args.size
    rng = np.random.default_rng(0)
    cases = [("mraw", 8), ("mraw", 12), ("mraw", 16), ("cine", 8), ("cine", 12)]
    print(f"{n} frames of {size}x{size}, read one at a time (after a 1-frame warm-up)")
    with tempfile.TemporaryDirectory(dir=args.work) as tmp:
        for kind, bits in cases:
            data = rng.integers(
                0, 2**bits, (n, size, size), dtype=np.uint8 if bits == 8 else np.uint16
            )
            if kind == "mraw":
                path = write_mraw(Path(tmp) / f"m{bits}.cih", data, bits, fps=10000)
            else:
                path = write_cine(Path(tmp) / f"c{bits}.cine", data, bits, fps=10000)
            t0 = time.perf_counter()
            video = open_lab_video(path)
            t_open = time.perf_counter() - t0
            next(video.read([0]))
            t0 = time.perf_counter()
            for i, frame in enumerate(video.read()):
                if not np.array_equal(frame, data[i]):
                    raise ValueError(f"{path}: frame {i} read back wrong")
            dt = time.perf_counter() - t0
            print(
                f"{kind} {bits:>2}-bit: open {t_open * 1e3:6.1f} ms, read {n / dt:7.0f} frames/s "
                f"({n * size * size / dt / 1e6:6.1f} Mpixel/s)"
            )
    return 0


def register_bench(bench_subparsers) -> None:
    p = bench_subparsers.add_parser(
        "labformats",
        help="read speed of the MRAW and CINE readers",
        description="Write MRAW (8/12/16-bit) and CINE (8/12-bit) recordings of random "
        "frames to a scratch folder, then time reading every frame back (and check it).",
    )
    p.add_argument("--frames", type=int, default=200)
    p.add_argument("--size", type=int, default=512, help="frame width and height, pixels")
    p.add_argument("--work", help="scratch folder (default: the system's temporary folder)")
    p.set_defaults(func=bench_labformats_cmd)
