"""The views a frame is fitted to: the step's views and their weighted photometric sum."""

from __future__ import annotations

import inspect

import torch

from surfphase.fit import losses
from surfphase.fit.densify import Densify2DGS, NoDensify, Strategy, frame_strategy
from surfphase.fit.params import DEFAULTS
from surfphase.fit.viewset import FrameViews


def _views(V=5, C=2, sampler=None):
    g = torch.Generator().manual_seed(1)
    obs = torch.rand((V, 12, 10, 1), generator=g)
    vm = torch.eye(4).repeat(V, 1, 1) + torch.arange(V)[:, None, None]
    return FrameViews(obs, vm, torch.eye(3).repeat(V, 1, 1), torch.rand((V, 12, 10, 1)), C,
                      sampler)  # fmt: skip


def _terms(rgb, obs):
    """Per-view L1 and D-SSIM in float64 (the reference)."""
    rgb, obs = rgb.double(), obs.double()
    l1_v = (rgb - obs).abs().flatten(1).mean(1)
    return l1_v, 1 - losses.ssim_map(rgb, obs).flatten(1).mean(1)


def test_inputs_only_is_the_plain_sum_over_views():
    fv = _views(V=2)
    step = fv.step(0)
    assert step.viewmats is fv.viewmats and step.inputs(step.observed) is fv.observed
    rgb = torch.rand((2, 12, 10, 1), generator=torch.Generator().manual_seed(2))
    loss, l1, dssim = step.photometric(rgb, 0.2)
    l1_v, dssim_v = _terms(rgb, fv.observed)
    torch.testing.assert_close(loss.double(), (0.8 * l1_v + 0.2 * dssim_v).sum())
    torch.testing.assert_close(l1.double(), l1_v.mean())
    torch.testing.assert_close(dssim.double(), dssim_v.mean())


def test_sampled_views_are_weighted_and_logged_on_the_inputs():
    idx, w = torch.tensor([0, 1, 3, 4]), torch.tensor([1.0, 1.0, 0.5, 0.25])
    fv = _views(sampler=lambda it: (idx, w))
    step = fv.step(7)
    torch.testing.assert_close(step.viewmats, fv.viewmats[idx])
    assert step.inputs(step.observed).shape[0] == 2
    rgb = torch.rand((4, 12, 10, 1), generator=torch.Generator().manual_seed(3))
    loss, l1, _ = step.photometric(rgb, 0.2)
    l1_v, dssim_v = _terms(rgb, fv.observed[idx])
    want = (w.double() * (0.8 * l1_v + 0.2 * dssim_v)).sum()
    torch.testing.assert_close(loss.double(), want)
    torch.testing.assert_close(l1.double(), l1_v[:2].mean())


def test_strategies_share_one_interface_and_the_fit_defaults():
    hooks = ("initialize_state", "before_backward", "after_backward")
    for h in hooks:
        a = inspect.signature(getattr(NoDensify, h))
        b = inspect.signature(getattr(Densify2DGS, h))
        assert list(a.parameters) == list(b.parameters), h
    d = frame_strategy(DEFAULTS, 0, 150)
    assert isinstance(d, Densify2DGS) and isinstance(d, Strategy)
    assert (d.refine_start, d.refine_stop, d.refine_every) == (15, 90, DEFAULTS["densify_every"])
    assert Densify2DGS(0, 10).max_surfels == DEFAULTS["max_surfels"] == d.max_surfels
    assert isinstance(frame_strategy(DEFAULTS, 1, 30), NoDensify)
    assert isinstance(frame_strategy({**DEFAULTS, "densify": False}, 0, 150), NoDensify)
