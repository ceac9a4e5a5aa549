"""Byte-for-byte comparison of two results folders, timing fields aside.

Used by ``surfphase bench determinism`` (same campaign run twice) and to show that a
restructuring changed no output. Every file under both folders is compared:

* ``.json``: parsed, then equal after dropping the timing keys (:data:`TIMING_KEYS`,
  at any depth);
* ``.npz``: the same array names, each array byte-identical, timing arrays aside;
* ``.csv``/``.tsv``: byte-identical after dropping timing columns;
* ``.pt`` (torch checkpoints): loaded, every tensor and array byte-identical, every other
  value equal, timing keys aside;
* everything else: byte-identical.

Job logs and per-job benchmarks (``logs/``, ``benchmarks/``, ``.snakemake/``) record the
run, not its result, and are not compared.
"""

from __future__ import annotations

import io
import json
from pathlib import Path

import numpy as np

#: Keys (JSON), arrays (NPZ) and columns (CSV) that record how long something took.
#: ``time_s`` is not one of them: it is the frame's physical time.
TIMING_KEYS = frozenset(
    {
        "seconds", "seconds_per_frame", "seconds_first_frame", "seconds_per_later_frame",
        "seconds_per_iter", "seconds_optimise", "seconds_total", "segment_seconds",
        "stage_seconds", "session_background_seconds", "render_s", "calibrate_s",
        "refine_s", "train_s", "sample_s", "elapsed_s", "wall_s",
    }
)  # fmt: skip
SKIP_DIRS = frozenset({"logs", "benchmarks", ".snakemake"})


def _drop(obj, keys: frozenset[str]):
    if isinstance(obj, dict):
        return {k: _drop(v, keys) for k, v in obj.items() if k not in keys}
    if isinstance(obj, list):
        return [_drop(v, keys) for v in obj]
    return obj


def _same_value(a, b, keys: frozenset[str]) -> bool:
    """Recursive equality of checkpoint contents: tensors and arrays byte for byte."""
    import torch

    if isinstance(a, torch.Tensor) or isinstance(b, torch.Tensor):
        return (
            isinstance(a, torch.Tensor)
            and isinstance(b, torch.Tensor)
            and a.dtype == b.dtype
            and a.shape == b.shape
            and a.detach().cpu().contiguous().numpy().tobytes()
            == b.detach().cpu().contiguous().numpy().tobytes()
        )
    if isinstance(a, np.ndarray) or isinstance(b, np.ndarray):
        a, b = np.asarray(a), np.asarray(b)
        return a.dtype == b.dtype and a.shape == b.shape and a.tobytes() == b.tobytes()
    if isinstance(a, dict) and isinstance(b, dict):
        ka, kb = set(a) - keys, set(b) - keys
        return ka == kb and all(_same_value(a[k], b[k], keys) for k in ka)
    if isinstance(a, list | tuple) and isinstance(b, list | tuple):
        return len(a) == len(b) and all(_same_value(x, y, keys) for x, y in zip(a, b, strict=True))
    return type(a) is type(b) and a == b


def _csv_without(data: bytes, keys: frozenset[str]) -> bytes:
    import pandas as pd

    sep = "\t" if data[:4096].count(b"\t") > data[:4096].count(b",") else ","
    df = pd.read_csv(io.BytesIO(data), sep=sep, dtype=str, keep_default_na=False)
    return df.drop(columns=[c for c in df.columns if c in keys]).to_csv(index=False).encode()


def same_file(a: Path, b: Path, keys: frozenset[str] = TIMING_KEYS) -> str | None:
    """``None`` when ``a`` and ``b`` hold the same result, else why not (one line)."""
    ext = a.suffix.lower()
    da, db = a.read_bytes(), b.read_bytes()
    if da == db:
        return None
    if ext == ".json":
        ja, jb = _drop(json.loads(da), keys), _drop(json.loads(db), keys)
        return None if ja == jb else "JSON values differ (timing keys aside)"
    if ext == ".npz":
        with (
            np.load(io.BytesIO(da), allow_pickle=False) as za,
            np.load(io.BytesIO(db), allow_pickle=False) as zb,
        ):
            na, nb = set(za.files) - keys, set(zb.files) - keys
            if na != nb:
                return f"arrays differ: {sorted(na ^ nb)}"
            bad = [n for n in sorted(na) if za[n].dtype != zb[n].dtype
                   or za[n].shape != zb[n].shape or za[n].tobytes() != zb[n].tobytes()]  # fmt: skip
            return f"arrays not byte-identical: {', '.join(bad)}" if bad else None
    if ext == ".pt":
        import torch

        # Checkpoints this project wrote (they hold numpy arrays: not weights-only).
        ta = torch.load(io.BytesIO(da), map_location="cpu", weights_only=False)
        tb = torch.load(io.BytesIO(db), map_location="cpu", weights_only=False)
        return None if _same_value(ta, tb, keys) else "checkpoint values differ"
    if ext in (".csv", ".tsv"):
        return None if _csv_without(da, keys) == _csv_without(db, keys) else "table differs"
    return f"bytes differ ({len(da)} vs {len(db)} bytes)"


def compare_trees(a: Path, b: Path, keys: frozenset[str] = TIMING_KEYS) -> dict:
    """Compare every file of two folders → ``{"same": [...], "differ": {rel: why},
    "only_a": [...], "only_b": [...]}`` (paths relative to the folders)."""
    a, b = Path(a), Path(b)

    def files(root: Path) -> set[str]:
        return {
            str(p.relative_to(root))
            for p in root.rglob("*")
            if p.is_file() and not SKIP_DIRS.intersection(p.relative_to(root).parts)
        }

    fa, fb = files(a), files(b)
    out: dict = {"same": [], "differ": {}, "only_a": sorted(fa - fb), "only_b": sorted(fb - fa)}
    for rel in sorted(fa & fb):
        why = same_file(a / rel, b / rel, keys)
        if why is None:
            out["same"].append(rel)
        else:
            out["differ"][rel] = why
    return out
