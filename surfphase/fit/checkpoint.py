"""Per-frame checkpoints of a fit, so that a killed job resumes at the last finished
frame with a bit-identical result.

A checkpoint folder holds ``frame_<t:05d>.pt`` (the record of frame t, a dict:
:meth:`surfphase.fit.record.FrameRecord.to_dict`) and two states: ``state.pt`` after the
last finished frame and ``state.prev.pt`` after the one before, so that an unreadable
newest state or record costs one frame, not the run. A state holds the run key
(:func:`run_key`), the next frame, the next surfel id, the surfels, the generator state
and the background images.
"""

from __future__ import annotations

import hashlib
import json
import os
import pickle
import shutil
from pathlib import Path

import torch

from surfphase.fit.session import SessionData
from surfphase.io import atomic_path, code_fingerprint

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


def save_torch(path: Path, obj) -> None:
    with atomic_path(path) as tmp:
        torch.save(obj, tmp)


def save_state(ckpt: Path, state: dict) -> None:
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
    save_torch(cur, state)


def load_checkpoint(ckpt: Path, key: str) -> tuple[dict | None, list[dict]]:
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


def run_key(data: SessionData, p: dict) -> str:
    """What a checkpoint must match to be resumed: parameters, inputs and code.

    A change of the fit's code makes old checkpoints stale, so a rerun triggered by the
    code change refits from the first frame instead of resuming.
    """
    h = hashlib.sha256(json.dumps(p, sort_keys=True, default=str).encode())
    h.update(data.fingerprint().encode())
    h.update(_code_fingerprint().encode())
    return h.hexdigest()


def start_fresh(ckpt: Path) -> None:
    """Make ``ckpt`` an empty checkpoint folder (another run's files are removed)."""
    ckpt.mkdir(parents=True, exist_ok=True)
    for old in ckpt.glob("*.pt"):
        old.unlink()


def save_frame(ckpt: Path, t: int, record: dict, state: dict) -> None:
    """Checkpoint finished frame ``t``: its record first, then the state after it."""
    save_torch(ckpt / f"frame_{t:05d}.pt", record)
    save_state(ckpt, state)
