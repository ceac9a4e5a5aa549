"""Small file helpers shared by every stage: whole-or-nothing writes, frame stacks and their
frame indices, and the code fingerprint of checkpoints.

A stage writes each output to a temporary name in the same folder, then renames it
(``os.replace`` is atomic on POSIX), so a killed job never leaves a half-written file
under the final name.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import os
import shutil
import tempfile
from collections.abc import Iterator, Mapping, Sequence
from pathlib import Path

import numpy as np


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike, suffix: str | None = None) -> Iterator[Path]:
    """Yield a temporary path next to ``path``; rename it onto ``path`` on success.

    The temporary keeps ``path``'s suffix (or ``suffix``) so libraries that choose a
    format from the extension still work. On error the temporary is removed.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    sfx = path.suffix if suffix is None else suffix
    fd, tmp = tempfile.mkstemp(prefix=f".{path.stem}.", suffix=f".part{sfx}", dir=path.parent)
    os.close(fd)
    tmp_path = Path(tmp)
    # mkstemp makes owner-only files; give the result the usual umask permissions.
    umask = os.umask(0)
    os.umask(umask)
    os.chmod(tmp_path, 0o666 & ~umask)
    try:
        yield tmp_path
        os.replace(tmp_path, path)
    finally:
        if tmp_path.exists():
            tmp_path.unlink()


def part_dir(final: str | os.PathLike) -> Path:
    """A fresh temporary folder ``.<name>.part-*`` next to ``final`` (its parent is
    created), with the usual umask permissions (mkdtemp makes owner-only folders)."""
    final = Path(final)
    final.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{final.name}.part-", dir=final.parent))
    umask = os.umask(0)
    os.umask(umask)
    os.chmod(tmp, 0o777 & ~umask)
    return tmp


def replace_dir(tmp: str | os.PathLike, out: str | os.PathLike) -> None:
    """Put the finished folder ``tmp`` at ``out`` by renames, replacing an existing
    ``out`` (moved aside, then removed), so ``out`` is always whole."""
    tmp, out = Path(tmp), Path(out)
    if out.exists() and not (out.is_dir() and not any(out.iterdir())):
        old = out.parent / f".{out.name}.old-{os.getpid()}"
        os.replace(out, old)
        os.replace(tmp, out)
        shutil.rmtree(old)
    else:
        os.replace(tmp, out)


@contextlib.contextmanager
def atomic_dir(out: str | os.PathLike) -> Iterator[Path]:
    """Yield a temporary folder next to ``out`` (:func:`part_dir`); on success it
    replaces ``out`` (:func:`replace_dir`), on error it is removed."""
    tmp = part_dir(out)
    try:
        yield tmp
        replace_dir(tmp, out)
    finally:
        if tmp.exists():
            shutil.rmtree(tmp)


def atomic_write_text(path: str | os.PathLike, text: str) -> None:
    """Write ``text`` to ``path`` whole or not at all."""
    with atomic_path(path) as tmp:
        tmp.write_text(text)


def atomic_write_json(path: str | os.PathLike, obj, indent: int = 1) -> None:
    """Write ``obj`` as JSON to ``path`` whole or not at all."""
    atomic_write_text(path, json.dumps(obj, indent=indent, default=_json_default))


def _json_default(o):
    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, Path):
        return str(o)
    raise TypeError(f"not JSON serialisable: {type(o)}")


def save_npy(path: str | os.PathLike, array: np.ndarray) -> None:
    """Save an array as ``.npy`` whole or not at all (readable with ``mmap_mode='r'``)."""
    with atomic_path(path) as tmp, open(tmp, "wb") as f:
        np.save(f, np.ascontiguousarray(array))


def load_stack(path: str | os.PathLike) -> np.ndarray:
    """Memory-map a frame stack ``.npy`` (frames × H × W[, C]) without reading it all."""
    return np.load(path, mmap_mode="r")


def stack_frame_indices(meta: Mapping, n_frames: int, meta_path: str | os.PathLike) -> np.ndarray:
    """The session frame index of each of a stack's first ``n_frames`` positions.

    Read from an ingest ``meta.json`` (already parsed into ``meta``), whose
    ``frame_indices`` lists one integer per stack position (ingest writes it). Without
    that key (a folder written by hand): ``0 … n_frames − 1``.

    Returns:
        (n_frames,) int64.

    Raises:
        ValueError: naming ``meta_path``, when ``frame_indices`` is not a list of integers
            or lists fewer frames than ``n_frames`` (the times would be wrong).
    """
    idx = meta.get("frame_indices")
    if idx is None:
        return np.arange(n_frames, dtype=np.int64)
    if not isinstance(idx, list) or not all(
        isinstance(i, int) and not isinstance(i, bool) for i in idx
    ):
        raise ValueError(f"{meta_path}: frame_indices must be a list of integers")
    if len(idx) < n_frames:
        raise ValueError(
            f"{meta_path}: frame_indices lists {len(idx)} frames, the stacks hold {n_frames}"
        )
    return np.asarray(idx[:n_frames], dtype=np.int64)


#: The ``surfphase`` package folder, which :func:`code_fingerprint` names sources from.
PACKAGE_ROOT = Path(__file__).resolve().parent


def source_files(parts: Sequence[str], root: Path = PACKAGE_ROOT) -> list[Path]:
    """The source files that ``parts`` name, in hashing order.

    Each part is a path relative to ``root``: a file (``"cameras.py"``) stands for
    itself, a folder (``"fit"``) for every ``*.py`` under it, recursively, sorted by
    path. Parts keep their order: ``["cameras.py", "mesh", "render"]`` gives
    ``cameras.py``, then the sorted ``mesh`` files, then the sorted ``render`` ones.
    """
    files: list[Path] = []
    for part in parts:
        path = root / part
        files += sorted(path.rglob("*.py")) if path.is_dir() else [path]
    return files


def code_fingerprint(parts: Sequence[str], root: Path = PACKAGE_ROOT) -> str:
    """SHA-256 hex digest of the sources a stage's results depend on.

    For each file of :func:`source_files` in turn: its name (without the folder, UTF-8)
    then its bytes. A checkpoint keyed on it is stale once any of those files changes.
    """
    h = hashlib.sha256()
    for f in source_files(parts, root):
        h.update(f.name.encode())
        h.update(f.read_bytes())
    return h.hexdigest()
