"""The typed per-frame record: the checkpointed dict, key for key, and back."""

from __future__ import annotations

import numpy as np
import torch

from surfphase.fit.model import SurfelModel
from surfphase.fit.params import DEFAULTS
from surfphase.fit.record import FrameRecord, SurfelIds

#: The keys of a checkpointed frame record (frame_<t>.pt), in order, as stage 1 wrote them.
RECORD_KEYS = [
    "means", "log_scales", "quats", "colors", "sdf", "opacity", "gamma", "bubble", "ids",
    "reseeded", "frame", "curves", "psnr", "iters", "spawned", "registered", "seconds",
    "seconds_optimise",
]  # fmt: skip


def _model(n=5):
    g = torch.Generator().manual_seed(0)
    means = torch.rand((n, 3), generator=g) * 1e-3
    normals = torch.nn.functional.normalize(torch.rand((n, 3), generator=g), dim=1)
    return SurfelModel.from_points(means, normals, torch.rand((n, 1), generator=g), 1e-5,
                                   extent=0.004, init_sdf=0.1)  # fmt: skip


def test_record_dict_has_the_checkpoint_keys_and_the_model_values():
    m = _model()
    bubble = np.array([0, 1, 1, -1, 2])
    rec = FrameRecord.of_model(
        m, bubble, ids=np.arange(3, 8, dtype=np.int64), frame=2, iters=30,
        psnr=[30.0, 31.0], reseeded={2: np.zeros(3)}, seconds=1.5, seconds_optimise=1.0,
    )  # fmt: skip
    d = rec.to_dict()
    assert list(d) == RECORD_KEYS
    np.testing.assert_array_equal(d["means"], m.means.detach().numpy())
    np.testing.assert_array_equal(d["opacity"], m.opacities().detach().numpy())
    assert d["bubble"].dtype == np.int32 and d["ids"].dtype == np.int64
    assert d["gamma"] == float(m.gamma.detach()) and d["frame"] == 2 and d["iters"] == 30
    back = FrameRecord.from_dict(d).to_dict()
    assert list(back) == RECORD_KEYS
    for k in RECORD_KEYS:
        a, b = d[k], back[k]
        assert np.array_equal(a, b) if isinstance(a, np.ndarray) else a == b, k


def test_shading_curve_is_recorded_after_the_parameters():
    p = _model().state()
    p["shade"] = torch.zeros((int(DEFAULTS["shade_knots"]), 1))
    d = FrameRecord.of_model(SurfelModel(p, 0.004), np.zeros(5, int), ids=np.arange(5),
                             frame=0, iters=1).to_dict()  # fmt: skip
    assert list(d)[:6] == ["means", "log_scales", "quats", "colors", "sdf", "shade"]
    assert d["shade"].shape == (DEFAULTS["shade_knots"], 1)


def test_surfel_ids_keep_extend_renumber():
    ids = SurfelIds(np.array([0, 1, 2, 5], dtype=np.int64), 6)
    ids.keep(np.array([True, False, True, True]))
    ids.extend(2)
    assert ids.ids.tolist() == [0, 2, 5, 6, 7] and ids.next_id == 8
    ids.renumber(3)
    assert ids.ids.tolist() == [0, 1, 2] and ids.next_id == 3
