"""The record of one fitted frame (:class:`FrameRecord`) and the persistent surfel ids.

A record is checkpointed after every frame (``frame_<t:05d>.pt``) as the plain dict of
:meth:`FrameRecord.to_dict`, which :mod:`surfphase.fit.outputs` reads (one dict per
frame: ``surfels.npz``, ``curves.csv``, ``summary.json``). Units: metres, seconds;
``sdf`` and ``gamma`` in units of the scene extent ``L`` as the model holds them.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from surfphase.fit.model import SurfelModel, per_surfel

#: The record's keys besides the per-surfel parameters, in the order of its dict.
_FIELDS = (
    "shade", "opacity", "gamma", "bubble", "ids", "reseeded", "frame", "curves", "psnr",
    "iters", "spawned", "registered", "seconds", "seconds_optimise",
)  # fmt: skip


@dataclass
class FrameRecord:
    """The surfels after frame ``frame`` was fitted, and how the fit went.

    Attributes:
        params: per-surfel parameters as the model holds them, (N, ...) float32:
            ``means`` (m), ``log_scales``, ``quats``, ``colors``, and ``sdf`` (units of
            L) or ``opacity_logit`` (the "no SDF" ablation).
        shade: (K, D) float32 shading-curve knots, or None (no shading).
        opacity: (N,) float32 opacities.
        gamma: SDF sharpness γ in 1/L (NaN without SDF).
        bubble: (N,) int32 bubble bound to each surfel (−1 none, 0 nucleation).
        ids: (N,) int64 persistent surfel ids of the rows (columns of surfels.npz).
        reseeded: ``{merged bubble: (3,) m/s}`` seeded afresh at this frame.
        frame: frame position in the session (0-based).
        curves: the logged optimisation rows (``curves.csv``).
        psnr: input-view PSNR after the fit, dB, one per input view.
        iters: optimisation steps.
        spawned: bubbles that got new surfels at this frame.
        registered: ``{bubble: (3,) rigid shift applied before the fit, m}``.
        seconds: wall time of the whole frame.
        seconds_optimise: wall time of its optimisation steps.
    """

    params: dict[str, np.ndarray]
    opacity: np.ndarray
    gamma: float
    bubble: np.ndarray
    ids: np.ndarray
    frame: int
    iters: int
    shade: np.ndarray | None = None
    curves: list[dict] = field(default_factory=list)
    psnr: list[float] = field(default_factory=list)
    reseeded: dict[int, np.ndarray] = field(default_factory=dict)
    spawned: list[int] = field(default_factory=list)
    registered: dict[int, np.ndarray] = field(default_factory=dict)
    seconds: float = 0.0
    seconds_optimise: float = 0.0

    @classmethod
    def of_model(cls, model: SurfelModel, bubble: np.ndarray, **kw) -> FrameRecord:
        """The record of ``model``'s surfels (any device) bound to ``bubble`` (N,);
        ``kw``: the other fields."""
        st = model.state()
        params = {k: v.cpu().numpy().astype(np.float32) for k, v in st.items() if per_surfel(k)}
        shade = None
        if model.shade is not None:
            shade = model.shade.detach().cpu().numpy().astype(np.float32)
        return cls(
            params=params,
            shade=shade,
            opacity=model.opacities().detach().cpu().numpy().astype(np.float32),
            gamma=float(model.gamma.detach()),
            bubble=bubble.astype(np.int32),
            **kw,
        )

    @property
    def means(self) -> np.ndarray:
        """(N, 3) float32 surfel centres, metres."""
        return self.params["means"]

    @property
    def log_scales(self) -> np.ndarray:
        """(N, 2) float32 ln of the tangent standard deviations (m)."""
        return self.params["log_scales"]

    def to_dict(self) -> dict:
        """The checkpointed dict: the parameters, then the fields (``shade`` only with
        shading)."""
        out = dict(self.params)
        for k in _FIELDS:
            if k == "shade" and self.shade is None:
                continue
            out[k] = getattr(self, k)
        return out

    @classmethod
    def from_dict(cls, d: dict) -> FrameRecord:
        """The record of a checkpointed dict (:meth:`to_dict`)."""
        params = {k: v for k, v in d.items() if k not in _FIELDS}
        kw = {k: d[k] for k in _FIELDS if k in d}
        kw.setdefault("ids", np.arange(params["means"].shape[0], dtype=np.int64))
        return cls(params=params, **kw)


@dataclass
class SurfelIds:
    """Persistent ids of the model's rows: surfels keep theirs across frames, new ones
    get the next unused id."""

    ids: np.ndarray  # (N,) int64
    next_id: int

    def keep(self, rows: np.ndarray) -> None:
        """Keep the ids of the (N,) bool ``rows`` (the surfels kept)."""
        self.ids = self.ids[rows]

    def extend(self, n: int) -> None:
        """Give ``n`` surfels appended to the model the next ids."""
        self.ids = np.concatenate([self.ids, np.arange(self.next_id, self.next_id + n)])
        self.next_id += n

    def renumber(self, n: int) -> None:
        """Ids ``0 … n−1`` (the first frame, once densification has settled it)."""
        self.ids, self.next_id = np.arange(n, dtype=np.int64), n
