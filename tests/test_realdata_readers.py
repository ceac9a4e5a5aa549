"""Our Photron and Phantom readers against independent readers, on real camera files.

The files are third-party recordings in ``../shared/realdata`` (see its README): Photron
MRAW from pyMRAW's test data, read here also by ``pyMRAW.load_video``; Phantom CINE from
PIMS's test data, read here also by ``pims.open``. Absent files skip these tests (fail
them with ``SURFPHASE_REQUIRE_REALDATA=1``, as in CI): see ``tests/realdata.py``.
"""

from __future__ import annotations

import warnings

import numpy as np
import pytest
from realdata import REQUIRE_ENV, realdata

from surfphase.labformats import open_lab_video
from surfphase.video import open_video

PHOTRON = {  # name: (frames, (H, W), significant bits, fps), from the README
    "beam": (4, (80, 1024), 12, 50_000.0),
    "ball_12bit": (15, (384, 384), 12, 30_000.0),
}
PHANTOM = {
    "cine_781": (15, (256, 256), 12, 90_000.0),
    "cine_legacy": (97, (128, 128), 14, 35_087.0),
}


@pytest.mark.parametrize("name", sorted(PHOTRON))
@pytest.mark.parametrize("given", [".cihx", ".mraw"])
def test_photron_equals_pymraw(name, given):
    import pyMRAW

    head = realdata("photron", f"{name}.cihx")
    ref, cih = pyMRAW.load_video(str(head))
    ref = np.asarray(ref)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # the header says monochrome: no colour warning
        src = open_video(head.with_suffix(given))
    assert src.header["colour"] == "mono"  # ball_12bit: "Raw" data of a -M (mono) model
    n, shape, bits, fps = PHOTRON[name]
    assert (src.kind, src.count, src.shape, src.bit_depth, src.fps) == ("mraw", n, shape, bits, fps)
    assert ref.shape == (n, *shape) and cih["Total Frame"] == n
    ours = np.stack(list(src.read(range(src.count))))
    assert ours.dtype == np.uint16
    np.testing.assert_array_equal(ours, ref)
    assert int(ours.max()) < 2**bits
    # Out of order and repeated, as the ingest may ask.
    np.testing.assert_array_equal(np.stack(list(src.read([n - 1, 0, n - 1]))), ref[[n - 1, 0, -1]])


@pytest.mark.parametrize("name", sorted(PHANTOM))
def test_phantom_equals_pims(name):
    import pims

    path = realdata("phantom", f"{name}.cine")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # pims's deprecation notices
        cine = pims.open(str(path))
        ref = np.stack([np.asarray(f) for f in cine])
        ref_fps = float(cine.frame_rate)
        cine.close()
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        src = open_video(path)
    assert src.header["colour"] == "mono" and src.header["cfa"] == cine.cfa == 0
    n, shape, bits, fps = PHANTOM[name]
    assert (src.kind, src.count, src.shape, src.bit_depth, src.fps) == ("cine", n, shape, bits, fps)
    assert ref.shape == (n, *shape) and ref_fps == fps
    ours = np.stack(list(src.read(range(src.count))))
    assert ours.dtype == ref.dtype == np.uint16
    np.testing.assert_array_equal(ours, ref)
    assert int(ours.max()) < 2**bits


def test_lab_reader_and_open_video_agree():
    head = realdata("photron", "ball_12bit.cihx")
    a = open_lab_video(head)
    b = open_video(head.with_suffix(".mraw"))
    np.testing.assert_array_equal(next(a.read([7])), next(b.read([7])))


def test_absent_data_skips_or_fails_when_required(tmp_path, monkeypatch):
    import realdata as module

    monkeypatch.setattr(module, "REALDATA", tmp_path / "nowhere")
    monkeypatch.delenv(REQUIRE_ENV, raising=False)
    with pytest.raises(pytest.skip.Exception, match="nowhere"):
        realdata("photron", "beam.cihx")
    monkeypatch.setenv(REQUIRE_ENV, "1")
    with pytest.raises(pytest.fail.Exception, match=f"{REQUIRE_ENV}=1 requires it"):
        realdata("photron", "beam.cihx")


@pytest.mark.parametrize("name", ["photron/ball_12bit", "photron/beam", "phantom/cine_781"])
def test_cut_copy_of_a_real_recording_is_truncated(tmp_path, name):
    folder, stem = name.split("/")
    if folder == "photron":
        head = realdata(folder, f"{stem}.cihx")
        (tmp_path / head.name).write_bytes(head.read_bytes())
        data = head.with_suffix(".mraw")
    else:
        data = realdata(folder, f"{stem}.cine")
    cut = tmp_path / data.name
    cut.write_bytes(data.read_bytes()[: int(data.stat().st_size * 0.8)])
    with pytest.raises(ValueError, match="truncated recording") as e:
        open_video(cut)
    assert str(cut) in str(e.value)
