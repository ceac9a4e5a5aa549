"""Densification strategies: clone, split, prune, and the optimiser state that follows."""

from __future__ import annotations

import torch

from surfphase.fit.densify import Densify2DGS, NoDensify, append_surfels, select_surfels
from surfphase.fit.model import SurfelModel
from surfphase.fit.optimise import make_optimizer
from surfphase.fit.stage import DEFAULTS


def _model(n=4, L=0.01):
    means = torch.arange(3 * n, dtype=torch.float32).reshape(n, 3) * 1e-3
    normals = torch.tensor([[0.0, 0.0, 1.0]]).repeat(n, 1)
    m = SurfelModel.from_points(means, normals, torch.rand(n, 1), 1e-5, extent=L, init_sdf=0.1)
    with torch.no_grad():
        m.params["log_scales"][1] = torch.log(torch.tensor([0.005, 0.002]))  # large
    return m


def _step(model, opt):
    loss = sum((v**2).sum() for v in model.params.values())
    opt.zero_grad()
    loss.backward()
    opt.step()


def test_select_and_append_keep_adam_state_aligned():
    m = _model()
    opt = make_optimizer(m, DEFAULTS)
    _step(m, opt)
    avg = opt.state[m.params["means"]]["exp_avg"].clone()
    select_surfels(m, opt, torch.tensor([True, False, True, True]))
    assert m.n == 3
    torch.testing.assert_close(opt.state[m.params["means"]]["exp_avg"], avg[[0, 2, 3]])
    new = {k: v[:2] for k, v in m.state().items() if v.dim() > 0}
    append_surfels(m, opt, new)
    assert m.n == 5
    st = opt.state[m.params["means"]]["exp_avg"]
    assert st.shape == (5, 3) and (st[3:] == 0).all()
    assert opt.param_groups[0]["params"][0] is m.params["means"]
    _step(m, opt)  # the optimiser still works on the new tensors


def test_densify_clones_small_splits_large_and_prunes_transparent():
    m = _model(4)
    opt = make_optimizer(m, DEFAULTS)
    with torch.no_grad():
        m.params["sdf"][3] = 10.0  # opacity ≈ 0: pruned
    strat = Densify2DGS(
        refine_start=0,
        refine_stop=100,
        refine_every=1,
        grow_grad2d=1e-3,
        grow_scale=0.01,
        prune_opacity=0.05,
        prune_scale=10.0,
    )
    state = strat.initialize_state(m.n)
    means2d = torch.zeros(2, 4, 2, requires_grad=True)
    info = {
        "means2d": means2d,
        "radii": torch.ones(2, 4, dtype=torch.int32),
        "width": 20,
        "height": 20,
    }
    strat.before_backward(info)
    # Gradient high for surfels 0 (small) and 1 (large), low for 2.
    (means2d * torch.tensor([1.0, 1.0, 1e-6, 0.0])[None, :, None]).sum().backward()
    before = m.state()
    changed = strat.after_backward(
        m, opt, state, 0, info, generator=torch.Generator().manual_seed(0)
    )
    assert changed
    # Kept: 0, 2 (originals), clone of 0, two children of 1; 1 (split) and 3 (pruned) gone.
    assert m.n == 5
    torch.testing.assert_close(m.means[0], before["means"][0])
    torch.testing.assert_close(m.means[1], before["means"][2])
    torch.testing.assert_close(m.means[2], before["means"][0])
    kids_scale = torch.exp(m.params["log_scales"][3:])
    torch.testing.assert_close(kids_scale, torch.exp(before["log_scales"][1]).repeat(2, 1) / 1.6)
    # Children lie in the parent's tangent plane (normal +z): same z.
    torch.testing.assert_close(m.means[3:, 2], before["means"][1, 2].repeat(2))
    assert state["grad2d"].shape == (5,)
    _step(m, opt)


def test_no_densify_never_changes():
    m = _model()
    assert NoDensify().after_backward(m, None, {}, 0, {}) is False
    assert m.n == 4
