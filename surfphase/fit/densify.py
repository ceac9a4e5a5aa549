"""Densification strategies (swappable objects, after gsplat's ``Strategy`` design).

Every strategy implements :class:`Strategy`; the fit calls, at every step of a frame::

    state = strategy.initialize_state(model.n, device)   # once per frame
    strategy.before_backward(info)                        # e.g. keep the 2D-mean gradient
    loss.backward()
    if strategy.after_backward(model, optimizer, state, step, info, generator):
        ...  # the surfel set changed: the gradients belong to replaced tensors

``info`` is the renderer's ``meta`` dict (``means2d`` (C, N, 2) pixels, ``radii``
(C, N)) with ``width`` and ``height`` added by the fit. The first frame uses
:class:`Densify2DGS` (``fit: densify``); later frames :class:`NoDensify`, so the
surfels, and with them the correspondences, stay the same (:func:`frame_strategy`).
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Callable

import torch

from surfphase.fit.model import SurfelModel, per_surfel, quat_to_rotmat
from surfphase.fit.params import DEFAULTS

Edit = Callable[[str, torch.Tensor, bool], torch.Tensor]


def _edit_params_and_state(
    model: SurfelModel, optimizer: torch.optim.Optimizer | None, edit: Edit
) -> None:
    """Apply ``edit(name, tensor, is_state)`` to every per-surfel parameter and its Adam
    moments (``is_state=True``; new rows must get zeros). Global parameters (γ, the shading
    curve) are left alone."""
    old = dict(model.params)
    model.replace_params(
        {k: (edit(k, v.detach(), False) if per_surfel(k) else v.detach()) for k, v in old.items()}
    )
    if optimizer is None:
        return
    for group in optimizer.param_groups:
        name = group["name"]
        p_new = model.params[name]
        st = optimizer.state.pop(old[name], None)
        group["params"] = [p_new]
        if st is None:
            continue
        if per_surfel(name):
            st = {
                k: (edit(name, v, True) if torch.is_tensor(v) and v.dim() > 0 else v)
                for k, v in st.items()
            }
        optimizer.state[p_new] = st


def select_surfels(
    model: SurfelModel, optimizer: torch.optim.Optimizer | None, keep: torch.Tensor
) -> None:
    """Keep only the surfels where the (N,) bool ``keep`` is true (params and Adam state)."""
    _edit_params_and_state(model, optimizer, lambda _k, t, _s: t[keep])


def append_surfels(
    model: SurfelModel, optimizer: torch.optim.Optimizer | None, new: dict[str, torch.Tensor]
) -> None:
    """Append surfels with values ``new[name]`` (M, ...) per parameter; Adam moments of the
    new rows start at zero."""

    def edit(name: str, t: torch.Tensor, is_state: bool) -> torch.Tensor:
        add = new[name].to(t)
        if is_state:
            add = torch.zeros_like(add)
        return torch.cat([t, add], dim=0)

    _edit_params_and_state(model, optimizer, edit)


class Strategy(ABC):
    """The hooks a densification strategy implements (the same arguments for all)."""

    @abstractmethod
    def initialize_state(self, n: int, device: torch.device | str = "cpu") -> dict:
        """The strategy's running state for a model of ``n`` surfels (one per frame)."""

    @abstractmethod
    def before_backward(self, info: dict) -> None:
        """Called after the render, before ``loss.backward()``."""

    @abstractmethod
    def after_backward(
        self,
        model: SurfelModel,
        optimizer: torch.optim.Optimizer | None,
        state: dict,
        step: int,
        info: dict,
        generator: torch.Generator | None = None,
    ) -> bool:
        """Called after ``loss.backward()``, before the optimiser step; may add or remove
        surfels (``model`` and ``optimizer`` edited in place, random draws from
        ``generator``). Returns whether the surfel set changed: the fit then skips the
        optimiser step, whose gradients belong to the replaced tensors."""


class NoDensify(Strategy):
    """The strategy of every frame after the first: the surfel set never changes."""

    def initialize_state(self, n: int, device: torch.device | str = "cpu") -> dict:
        return {}

    def before_backward(self, info: dict) -> None:
        pass

    def after_backward(
        self,
        model: SurfelModel,
        optimizer: torch.optim.Optimizer | None,
        state: dict,
        step: int,
        info: dict,
        generator: torch.Generator | None = None,
    ) -> bool:
        return False


class Densify2DGS(Strategy):
    """2DGS/gsplat-style adaptive density control: clone, split, prune.

    Every ``refine_every`` steps between ``refine_start`` and ``refine_stop``: surfels
    whose mean 2D-position gradient (in NDC units, as 3DGS: pixels × size/2) exceeds
    ``grow_grad2d`` are cloned when small (largest scale ≤ ``grow_scale`` · L) and split in
    two (scales ÷ 1.6, positions drawn from the surfel) when large; then surfels with
    opacity below ``prune_opacity`` or a scale above ``prune_scale`` · L are removed.
    ``max_surfels`` caps growth (highest gradients first). ``L`` is the scene extent (m).
    The defaults are the fit's (:data:`surfphase.fit.params.DEFAULTS`); the refinement
    window, in steps, has none (:meth:`from_params` makes it from the fractions there).
    """

    def __init__(
        self,
        refine_start: int,
        refine_stop: int,
        refine_every: int = DEFAULTS["densify_every"],
        grow_grad2d: float = DEFAULTS["grow_grad2d"],
        grow_scale: float = DEFAULTS["grow_scale"],
        prune_opacity: float = DEFAULTS["prune_opacity"],
        prune_scale: float = DEFAULTS["prune_scale"],
        max_surfels: int = DEFAULTS["max_surfels"],
    ):
        self.refine_start = refine_start
        self.refine_stop = refine_stop
        self.refine_every = refine_every
        self.grow_grad2d = grow_grad2d
        self.grow_scale = grow_scale
        self.prune_opacity = prune_opacity
        self.prune_scale = prune_scale
        self.max_surfels = max_surfels

    @classmethod
    def from_params(cls, p: dict, iters: int) -> Densify2DGS:
        """The strategy of a frame of ``iters`` steps under the fit settings ``p``."""
        return cls(
            refine_start=int(p["densify_start"] * iters),
            refine_stop=int(p["densify_stop"] * iters),
            refine_every=int(p["densify_every"]),
            grow_grad2d=p["grow_grad2d"],
            grow_scale=p["grow_scale"],
            prune_opacity=p["prune_opacity"],
            prune_scale=p["prune_scale"],
            max_surfels=int(p["max_surfels"]),
        )

    def initialize_state(self, n: int, device: torch.device | str = "cpu") -> dict:
        return {"grad2d": torch.zeros(n, device=device), "count": torch.zeros(n, device=device)}

    def before_backward(self, info: dict) -> None:
        m2d = info["means2d"]
        if m2d.requires_grad:
            m2d.retain_grad()

    def _accumulate(self, state: dict, info: dict) -> None:
        m2d = info["means2d"]
        if m2d.grad is None:
            return
        g = m2d.grad.detach().clone()  # (C, N, 2)
        g[..., 0] *= info["width"] / 2.0
        g[..., 1] *= info["height"] / 2.0
        visible = info["radii"].detach() > 0
        if visible.dim() == 3:
            visible = visible.any(dim=-1)
        norms = g.norm(dim=-1) * visible
        state["grad2d"] += norms.sum(dim=0).to(state["grad2d"])
        state["count"] += visible.sum(dim=0).to(state["count"])

    @torch.no_grad()
    def after_backward(
        self,
        model: SurfelModel,
        optimizer: torch.optim.Optimizer | None,
        state: dict,
        step: int,
        info: dict,
        generator: torch.Generator | None = None,
    ) -> bool:
        """Accumulate gradients; densify and prune on refinement steps. Returns whether
        the surfel set changed."""
        if step >= self.refine_stop:
            return False
        self._accumulate(state, info)
        if step < self.refine_start or step % self.refine_every != 0:
            return False
        L = model.extent
        avg = state["grad2d"] / state["count"].clamp_min(1)
        high = avg > self.grow_grad2d
        smax = model.scales.max(dim=1).values
        small = smax <= self.grow_scale * L
        room = max(self.max_surfels - model.n, 0)
        cand = torch.nonzero(high).squeeze(1)
        if cand.numel() > room:
            order = torch.argsort(avg[cand], descending=True, stable=True)
            cand = cand[order[:room]]
        sel = torch.zeros_like(high)
        sel[cand] = True
        clone = sel & small
        split = sel & ~small
        n_before = model.n
        p = model.state()
        # Clone: an identical copy (the optimiser will pull the two apart).
        new = {k: v[clone] for k, v in p.items() if per_surfel(k)}
        # Split: two children drawn from the parent's disk, scales / 1.6; parent removed.
        if split.any():
            rot = quat_to_rotmat(p["quats"][split])  # (M, 3, 3)
            s = torch.exp(p["log_scales"][split])  # (M, 2)
            kids = {
                k: v[split].repeat(2, *([1] * (v.dim() - 1))) for k, v in p.items() if per_surfel(k)
            }
            z = torch.randn((2 * s.shape[0], 2), generator=generator, dtype=s.dtype).to(s.device)
            off2 = z * s.repeat(2, 1)
            off = torch.einsum("nij,nj->ni", rot.repeat(2, 1, 1)[:, :, :2], off2)
            kids["means"] = p["means"][split].repeat(2, 1) + off
            kids["log_scales"] = p["log_scales"][split].repeat(2, 1) - torch.log(
                torch.tensor(1.6, dtype=s.dtype)
            )
            new = {k: torch.cat([new[k], kids[k]], dim=0) for k in new}
        if new["means"].shape[0]:
            append_surfels(model, optimizer, new)
        keep = torch.ones(model.n, dtype=torch.bool, device=model.means.device)
        keep[:n_before][split] = False
        # Prune what is nearly transparent or far too large.
        op = model.opacities().detach()
        keep &= op >= self.prune_opacity
        keep &= model.scales.detach().max(dim=1).values <= self.prune_scale * L
        if keep.sum() < 1:
            keep[torch.argmax(op)] = True
        select_surfels(model, optimizer, keep)
        state.update(self.initialize_state(model.n, model.means.device))
        return True


def frame_strategy(p: dict, frame: int, iters: int) -> Strategy:
    """The strategy of frame position ``frame`` (``iters`` steps): densification at the
    first frame when ``fit: densify``, none after."""
    if frame == 0 and p["densify"]:
        return Densify2DGS.from_params(p, iters)
    return NoDensify()
