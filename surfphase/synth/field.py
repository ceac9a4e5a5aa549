"""The synthetic scene frozen at one time: its signed distance field and bubble labels.

:class:`FrameState` holds the alive bubbles' lobes as flat arrays (built by
:meth:`surfphase.synth.bubbles.BubbleScene.state`); the field and the bubble identity of a
point are defined in :mod:`surfphase.synth.bubbles`' docstring. Units: metres.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

#: Smooth-union width between bubbles, metres.
K_SCENE = 1.5e-4
#: Legendre degrees of the three shape-mode slots of every lobe.
MODE_DEGREES = (2, 2, 3)


def mode_delta(cos: np.ndarray, amps: np.ndarray) -> np.ndarray:
    """Relative radius change ``Σ a_m P_l(cos γ_m)`` of a lobe's shape modes.

    Args:
        cos: (..., 3) cosine of the angle between the direction and each mode's axis.
        amps: (..., 3) the modes' amplitudes (degrees :data:`MODE_DEGREES`).

    Returns:
        (...,) δ: the lobe's radius in that direction is ``R·(1 + δ)``.
    """
    c, a = np.asarray(cos), np.asarray(amps)
    c2 = c * c
    out = (1.5 * c2[..., 0] - 0.5) * a[..., 0] + (1.5 * c2[..., 1] - 0.5) * a[..., 1]
    return out + (2.5 * c2[..., 2] - 1.5) * c[..., 2] * a[..., 2]


def smin(a: np.ndarray, b: np.ndarray, k: float) -> np.ndarray:
    """Polynomial smooth minimum of width ``k`` (m); exactly ``min`` when ``k = 0``."""
    if k <= 0:
        return np.minimum(a, b)
    h = np.maximum(k - np.abs(a - b), 0.0) / k
    return np.minimum(a, b) - h * h * k * 0.25


@dataclass
class FrameState:
    """The scene frozen at one time: flat arrays of lobes, ready for vectorised queries.

    Attributes:
        t: time, s.
        ids: (E,) ids of the alive bubbles.
        centers: (L, 3) lobe centres, m; radii: (L,) nominal lobe radii, m.
        lobe_bubble: (L,) index into ``ids`` of each lobe's bubble.
        axes: (L, 3, 3) mode axes; amps: (L, 3) mode amplitudes (degrees MODE_DEGREES).
        k_internal: (E,) smooth-union width between a bubble's own lobes, m.
    """

    t: float
    ids: np.ndarray
    centers: np.ndarray
    radii: np.ndarray
    lobe_bubble: np.ndarray
    axes: np.ndarray
    amps: np.ndarray
    k_internal: np.ndarray

    @property
    def bound_radii(self) -> np.ndarray:
        """(L,) radius (m) of a sphere about each lobe centre that contains the lobe."""
        # smin lowers a field by at most k/4 (between bubbles and between lobes).
        k_int = self.k_internal[self.lobe_bubble] if len(self.radii) else 0.0
        return self.radii * (1 + np.abs(self.amps).sum(axis=1)) + 0.25 * (K_SCENE + k_int)

    def subset(self, bubble_index: np.ndarray) -> FrameState:
        """The same frame restricted to the bubbles ``ids[bubble_index]``."""
        bubble_index = np.asarray(bubble_index, dtype=int)
        keep = np.isin(self.lobe_bubble, bubble_index)
        remap = np.full(len(self.ids), -1)
        remap[bubble_index] = np.arange(len(bubble_index))
        return replace(
            self,
            ids=self.ids[bubble_index],
            centers=self.centers[keep],
            radii=self.radii[keep],
            lobe_bubble=remap[self.lobe_bubble[keep]],
            axes=self.axes[keep],
            amps=self.amps[keep],
            k_internal=self.k_internal[bubble_index],
        )

    def bubble_sdf(self, points: np.ndarray) -> np.ndarray:
        """(N, 3) points, m → (N, E) each bubble's own field, m (plate cut not applied)."""
        p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        n, nb, nl = p.shape[0], len(self.ids), len(self.radii)
        if nb == 0:
            return np.full((n, 0), np.inf)
        # Distances to all lobe centres via |p|² − 2p·c + |c|² (one matrix product);
        # exact distances are recomputed below wherever the shape matters.
        rho = np.sqrt(
            np.maximum(
                (p * p).sum(axis=1)[:, None]
                - 2 * (p @ self.centers.T)
                + (self.centers**2).sum(axis=1),
                0.0,
            )
        )  # (N, L)
        spread = self.radii * np.abs(self.amps).sum(axis=1)  # (L,) max |R·δ|
        d_lobe = rho - (self.radii + spread)  # lower bound of each lobe's field
        if nl > 1:
            # Lobes far above the smallest upper bound cannot change the smooth union
            # or the label: keep their lower bound and skip their shape modes.
            upper = (rho - (self.radii - spread)).min(axis=1)
            need = (d_lobe <= upper[:, None] + 3 * K_SCENE).T
        else:
            need = np.ones((1, n), dtype=bool)
        for li in range(nl):
            sel = np.flatnonzero(need[li]) if nl > 1 else slice(None)
            dl = p[sel] - self.centers[li]  # (S, 3)
            r = np.sqrt((dl * dl).sum(axis=1))
            c = (dl @ self.axes[li].T) / np.maximum(r, 1e-12)[:, None]  # (S, 3) cos γ
            d_lobe[sel, li] = r - self.radii[li] * (1 + mode_delta(c, self.amps[li]))
        if nl == nb and np.array_equal(self.lobe_bubble, np.arange(nb)):  # one lobe each
            return d_lobe
        out = np.full((n, nb), np.inf)
        seen: set[int] = set()
        for li, b in enumerate(self.lobe_bubble.tolist()):
            if b in seen:
                out[:, b] = smin(out[:, b], d_lobe[:, li], float(self.k_internal[b]))
            else:
                out[:, b] = d_lobe[:, li]
                seen.add(b)
        return out

    def sdf_and_label(
        self, points: np.ndarray, chunk: int = 32768
    ) -> tuple[np.ndarray, np.ndarray]:
        """Scene field (N,) m and bubble label (N,) int64 at (N, 3) points, m.

        The field is the smooth minimum (width :data:`K_SCENE`) of the two smallest
        bubble fields at each point, cut by the plate. The label is the id of the
        bubble whose own field is smallest (defined outside the vapour too; mask it
        with ``sdf < 0``); ``-1`` when no bubble is alive.
        """
        p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        sdf = np.empty(p.shape[0])
        lab = np.full(p.shape[0], -1, dtype=np.int64)
        for s in range(0, p.shape[0], chunk):
            q = p[s : s + chunk]
            d = self.bubble_sdf(q)
            if d.shape[1] == 0:
                sdf[s : s + chunk] = np.inf
                continue
            if d.shape[1] == 1:
                acc = d[:, 0]
            else:
                two = np.partition(d, 1, axis=1)
                acc = smin(two[:, 0], two[:, 1], K_SCENE)
            sdf[s : s + chunk] = np.maximum(acc, -q[:, 1])
            lab[s : s + chunk] = self.ids[np.argmin(d, axis=1)]
        return sdf, lab

    def sdf(self, points: np.ndarray) -> np.ndarray:
        """(N, 3) points, m → (N,) scene signed distance bound, m; negative = vapour."""
        return self.sdf_and_label(points)[0]
