"""The code fingerprint of checkpoints: one helper, the same bytes hashed as before."""

from __future__ import annotations

import hashlib
from pathlib import Path

import surfphase
from surfphase.fit import checkpoint as fit_checkpoint
from surfphase.io import PACKAGE_ROOT, code_fingerprint, source_files
from surfphase.mesh import stage as mesh_stage

ROOT = Path(surfphase.__file__).resolve().parent


def _hash(files: list[Path]) -> str:
    h = hashlib.sha256()
    for f in files:
        h.update(f.name.encode())
        h.update(f.read_bytes())
    return h.hexdigest()


def test_fit_fingerprint_is_the_one_computed_before():
    # As surfphase/fit/stage.py (now fit/checkpoint.py) hashed the sources before the
    # shared helper.
    h = hashlib.sha256()
    for pkg in ("fit", "render"):
        for f in sorted((ROOT / pkg).rglob("*.py")):
            h.update(f.name.encode())
            h.update(f.read_bytes())
    assert fit_checkpoint._code_fingerprint() == h.hexdigest()


def test_mesh_fingerprint_is_the_one_computed_before():
    # As surfphase/mesh/stage.py hashed the sources before the shared helper.
    files = [ROOT / "cameras.py"]
    for pkg in ("mesh", "render"):
        files += sorted((ROOT / pkg).rglob("*.py"))
    h = hashlib.sha256()
    for f in files:
        h.update(f.name.encode())
        h.update(f.read_bytes())
    assert mesh_stage._code_fingerprint() == h.hexdigest()


def test_package_root_is_the_installed_package():
    assert PACKAGE_ROOT == ROOT
    assert source_files(["cameras.py"]) == [ROOT / "cameras.py"]


def test_parts_keep_their_order_and_folders_are_sorted(tmp_path):
    (tmp_path / "b").mkdir()
    (tmp_path / "b" / "sub").mkdir()
    for rel in ("b/z.py", "b/a.py", "b/sub/m.py", "b/notes.txt", "top.py"):
        (tmp_path / rel).write_text(f"# {rel}\n")
    files = source_files(["top.py", "b"], tmp_path)
    names = [str(f.relative_to(tmp_path)) for f in files]
    assert names == ["top.py", "b/a.py", "b/sub/m.py", "b/z.py"]
    fingerprint = code_fingerprint(["top.py", "b"], tmp_path)
    assert fingerprint == _hash(files)
    assert code_fingerprint(["b", "top.py"], tmp_path) != fingerprint


def test_fingerprint_changes_with_a_source(tmp_path):
    (tmp_path / "p").mkdir()
    (tmp_path / "p" / "x.py").write_text("a = 1\n")
    before = code_fingerprint(["p"], tmp_path)
    (tmp_path / "p" / "x.py").write_text("a = 2\n")
    assert code_fingerprint(["p"], tmp_path) != before
