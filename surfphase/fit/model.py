"""The stage-1 scene model: 2D Gaussian surfels carrying a signed-distance value.

Every surfel ``i`` has a centre ``μ_i`` (metres, lab frame), two tangent scales
``s_i = exp(log_scales_i)`` (metres, standard deviations along the first two columns
of its rotation), a rotation quaternion ``q_i`` (w, x, y, z; normalised when used), a
colour ``c_i`` (D channels in [0, 1]) and a signed-distance value ``f_i``. Opacity is
not free (docs/method.md §5.1): ``o_i = 4 e^{−γ f_i} / (1 + e^{−γ f_i})²`` with one global
sharpness ``γ``.

Units of ``f`` and ``γ``: the optimised ``f`` is expressed in units of the scene extent
``L`` (metres; see :func:`surfphase.fit.init.scene_extent`), so that the method's
normalised-scene learning rate (0.05) and thresholds carry over to a metric scene. The
metric SDF value is ``f·L`` metres and the metric sharpness ``γ/L`` per metre; the
opacity ``o(γ f)`` is the same in either unit system.

With ``use_sdf=False`` (the "no SDF" ablation) the opacity is a free parameter,
``o = sigmoid(opacity_logit)``, as in plain 2D Gaussian splatting.

Optionally the model carries a shading curve ``shade`` (K, D): one function of the
facing angle for all surfels, added to their colours in each view
(:mod:`surfphase.render.shading`).
"""

from __future__ import annotations

import math

import torch

from surfphase.render.projection import quat_to_rotmat

#: ``−ln(3 − 2√2)``: the value of ``γ|f|`` at which ``o(γ f) = 1/2``.
HALF_OPACITY_GF = -math.log(3.0 - 2.0 * math.sqrt(2.0))


def sdf_to_opacity(sdf: torch.Tensor, gamma: torch.Tensor | float) -> torch.Tensor:
    """Opacity ``o = 4 e^{−γ f} / (1 + e^{−γ f})²`` of surfels with SDF values ``f``.

    Args:
        sdf: (N,) signed distances ``f`` (any unit, as long as ``gamma`` is its inverse).
        gamma: scalar sharpness ``γ`` (> 0).

    Returns:
        (N,) opacities in (0, 1]; 1 on the zero level set, 1/2 where
        ``γ|f| = −ln(3 − 2√2)``.
    """
    # 4 e^{-x}/(1+e^{-x})^2 = 4 σ(x) σ(-x): symmetric in x, and stable for large |x|.
    x = gamma * sdf
    return 4.0 * torch.sigmoid(x) * torch.sigmoid(-x)


def surfel_normals(quats: torch.Tensor) -> torch.Tensor:
    """(N, 4) quaternions → (N, 3) unit surfel normals (third rotation column)."""
    return quat_to_rotmat(quats)[..., :, 2]


def normal_to_quat(normals: torch.Tensor) -> torch.Tensor:
    """(N, 3) unit normals → (N, 4) quaternions (w, x, y, z) whose third column is the normal.

    The rotation is the shortest arc taking +z to ``n``; for ``n ≈ −z`` a half turn
    about +x is used.
    """
    n = normals / normals.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    z = torch.zeros_like(n)
    z[:, 2] = 1.0
    axis = torch.cross(z, n, dim=-1)
    w = 1.0 + n[:, 2]
    q = torch.cat([w[:, None], axis], dim=-1)
    flip = w < 1e-6
    if flip.any():
        q[flip] = torch.tensor([0.0, 1.0, 0.0, 0.0], dtype=n.dtype, device=n.device)
    return q / q.norm(dim=-1, keepdim=True)


#: Names of the optimised tensors, in a fixed order (optimizer groups, checkpoints).
PARAM_NAMES_SDF = ("means", "log_scales", "quats", "colors", "sdf", "log_gamma")
PARAM_NAMES_FREE = ("means", "log_scales", "quats", "colors", "opacity_logit")
#: Parameters that belong to the whole model, not to one surfel (never indexed per
#: surfel by densification, pruning or appending).
GLOBAL_PARAMS = frozenset({"log_gamma", "shade"})


def per_surfel(name: str) -> bool:
    """Whether parameter ``name`` has one row per surfel."""
    return name not in GLOBAL_PARAMS


class SurfelModel:
    """A set of surfels as leaf tensors, plus the global SDF sharpness.

    Attributes (leaf tensors with ``requires_grad``):
        means: (N, 3) centres, metres.
        log_scales: (N, 2) log of the tangent standard deviations (metres).
        quats: (N, 4) rotations (w, x, y, z), unnormalised.
        colors: (N, D) colours in [0, 1] (clamped when rendered).
        sdf: (N,) SDF values in units of ``extent`` (``use_sdf`` only).
        log_gamma: () log of ``γ`` in 1/``extent`` units (``use_sdf`` only).
        opacity_logit: (N,) free opacities before the sigmoid (``use_sdf=False`` only).
        shade: (K, D) shading curve added to the colours per view, stored as
            :func:`surfphase.render.shading.monotone_raw` of its knot values (optional;
            absent = view-independent colour).
        extent: scene extent ``L`` in metres (a constant, not optimised).
    """

    def __init__(self, params: dict[str, torch.Tensor], extent: float, use_sdf: bool = True):
        self.use_sdf = bool(use_sdf)
        self.extent = float(extent)
        names = PARAM_NAMES_SDF if self.use_sdf else PARAM_NAMES_FREE
        if "shade" in params:
            names = (*names, "shade")
        missing = [k for k in names if k not in params]
        if missing:
            raise ValueError(f"SurfelModel: missing parameters {missing}")
        self.params: dict[str, torch.Tensor] = {
            k: params[k].detach().clone().requires_grad_(True) for k in names
        }

    # -- construction -------------------------------------------------------------------
    @classmethod
    def from_points(
        cls,
        means: torch.Tensor,
        normals: torch.Tensor,
        colors: torch.Tensor,
        scale: torch.Tensor | float,
        extent: float,
        init_sdf: float,
        use_sdf: bool = True,
        init_opacity: float = 0.5,
    ) -> SurfelModel:
        """Surfels at ``means`` (N, 3) m, facing ``normals`` (N, 3), with colours (N, D).

        ``scale`` (metres, scalar or (N,)) sets both tangent standard deviations.
        With ``use_sdf``, every surfel starts at ``f = init_sdf`` (extent units) and
        ``γ = −ln(3−2√2)/init_sdf``, i.e. opacity 1/2, and the hinge target ``γ_m``
        equals ``γ``. Without, opacity starts at ``init_opacity``.
        """
        n = means.shape[0]
        dt = means.dtype
        s = torch.as_tensor(scale, dtype=dt, device=means.device).expand(n)
        params = {
            "means": means,
            "log_scales": torch.log(s)[:, None].repeat(1, 2),
            "quats": normal_to_quat(normals),
            "colors": colors,
        }
        if use_sdf:
            params["sdf"] = torch.full((n,), float(init_sdf), dtype=dt, device=means.device)
            params["log_gamma"] = torch.tensor(
                math.log(HALF_OPACITY_GF / init_sdf), dtype=dt, device=means.device
            )
        else:
            p = min(max(init_opacity, 1e-4), 1 - 1e-4)
            params["opacity_logit"] = torch.full(
                (n,), math.log(p / (1 - p)), dtype=dt, device=means.device
            )
        return cls(params, extent=extent, use_sdf=use_sdf)

    # -- derived quantities -------------------------------------------------------------
    @property
    def n(self) -> int:
        return int(self.params["means"].shape[0])

    @property
    def means(self) -> torch.Tensor:
        return self.params["means"]

    @property
    def scales(self) -> torch.Tensor:
        """(N, 2) tangent standard deviations, metres."""
        return torch.exp(self.params["log_scales"])

    @property
    def quats(self) -> torch.Tensor:
        return self.params["quats"]

    @property
    def colors(self) -> torch.Tensor:
        return self.params["colors"]

    @property
    def gamma(self) -> torch.Tensor:
        """Scalar sharpness ``γ`` in 1/extent units (NaN without SDF)."""
        if not self.use_sdf:
            return torch.tensor(float("nan"))
        return torch.exp(self.params["log_gamma"])

    @property
    def shade(self) -> torch.Tensor | None:
        """(K, D) knot values of the shading curve (never decreasing with the facing
        cosine), or None (view-independent colour). The parameter ``shade`` holds them
        through :func:`surfphase.render.shading.monotone_raw`."""
        from surfphase.render.shading import monotone_knots

        raw = self.params.get("shade")
        return None if raw is None else monotone_knots(raw)

    def view_colors(self, viewmats: torch.Tensor) -> torch.Tensor:
        """Colours to render with, for C cameras (``viewmats`` (C, 4, 4) world-to-camera):
        (C, N, D) with a shading curve; without one ``colors`` (N, D) itself, the same in
        every camera (the renderer takes either)."""
        from surfphase.render.shading import view_colors

        shade = self.shade
        if shade is None:
            return self.colors
        return view_colors(self.colors, self.means, self.quats, shade, viewmats)

    def opacities(self) -> torch.Tensor:
        """(N,) opacities: from the SDF, or the free parameter in the ablation."""
        if self.use_sdf:
            return sdf_to_opacity(self.params["sdf"], self.gamma)
        return torch.sigmoid(self.params["opacity_logit"])

    def normals(self) -> torch.Tensor:
        """(N, 3) unit normals (third column of each surfel's rotation)."""
        return surfel_normals(self.params["quats"])

    def zero_level_points(self) -> torch.Tensor:
        """(N, 3) ``μ − f·n`` in metres: each centre moved onto the SDF's zero level set."""
        if not self.use_sdf:
            return self.means
        return self.means - (self.params["sdf"] * self.extent)[:, None] * self.normals()

    # -- bookkeeping --------------------------------------------------------------------
    def state(self) -> dict[str, torch.Tensor]:
        """Detached copies of all parameters (for checkpoints and outputs)."""
        return {k: v.detach().clone() for k, v in self.params.items()}

    def replace_params(self, params: dict[str, torch.Tensor]) -> None:
        """Swap in new parameter values (new leaf tensors; optimizer must follow)."""
        self.params = {k: params[k].detach().clone().requires_grad_(True) for k in self.params}

    def append(self, other: SurfelModel) -> None:
        """Concatenate ``other``'s surfels after this model's (global γ kept)."""
        new = {}
        for k, v in self.params.items():
            if not per_surfel(k):
                new[k] = v.detach()
            else:
                new[k] = torch.cat([v.detach(), other.params[k].detach().to(v)], dim=0)
        self.replace_params(new)
