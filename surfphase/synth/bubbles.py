"""Synthetic pool-boiling scene: bubble life cycles as one signed distance field.

Units: metres, seconds, m/s. Lab frame (docs/conventions.md §1): +y up, heated plate at y = 0.
Time ``t = 0`` is frame 0 of the clip; frame ``f`` is at ``t = f / fps``. The scene
is simulated from :data:`WARMUP` seconds before frame 0 so the clip starts in a
steady state (bubbles already spread over the rising column).

Life cycle of a bubble (one :class:`Bubble`):

* **nucleation and growth** at a site ``(x, 0, z)`` on the plate, from ``t_birth``
  to ``t_detach``: radius ``R(t) = sqrt(r0² + (r_d² − r0²)·(t − t_birth)/t_grow)``
  (diffusion-controlled growth, R ∝ √t); the centre sits ``CONTACT·R`` above the
  plate and the sphere is cut by the plate (a truncated sphere on its foot);
* **rise** after ``t_detach``: the centre accelerates from ``v0`` towards the
  terminal velocity ``u_term`` (vertical 0.12–0.3 m/s for 1–3 mm bubbles, plus a
  small sideways drift) with relaxation time ``tau_acc = U/(2g)`` (the added-mass
  acceleration of 2g from rest), plus a growing zig-zag wobble (18–35 Hz);
* **deformation**: three low-order shape modes ``r = R·(1 + Σ a_m(t)·P_l(cos γ_m))``
  (Legendre P2 about the vertical — elongated while attached, oblate while rising —
  P2 about a tilted axis, and P3), oscillating at the Lamb frequency of mode ``l``
  of a bubble in saturated water (≈ 150 Hz for l = 2, R = 1 mm: 10 frames at 1500 fps);
* **merge**: when two bubbles' surfaces touch at ``t_m`` (:func:`surface_gap`, shape
  modes included: two oblate bubbles one above the other touch later than their
  nominal spheres would), both end and a
  new bubble is born there with their summed nominal volume and their
  volume-weighted centre and velocity; for :data:`COALESCE` seconds it is the smooth
  union of two lobes sliding into one sphere, then it oscillates strongly.
  ``force_merge`` arranges one inside the clip by wake capture: a follower from the
  same site grows twice as fast and rises 1.4× faster than its leader (up to
  ≈ 0.4 m/s) until they touch.

The field: each lobe is ``ρ − R(1 + δ(u))`` (ρ distance to the lobe centre); a
bubble's lobes are joined by a polynomial smooth minimum, and the scene is the
polynomial smooth minimum (:data:`K_SCENE`: thin films bridge just before contact)
of the two smallest bubble fields at each point, cut by the plate:
``scene = max(smin(d_(1), d_(2)), −y)``. It is a distance *bound* with slope ≤
~1.1 (the shape modes), so sphere tracing steps by 0.9 of it.

Bubble identity in the truth: a point belongs to the bubble whose own field is
smallest there (:meth:`FrameState.sdf_and_label`), which partitions the vapour
exactly, so per-bubble volumes add up to the volume of ``scene < 0``. Ids are
1, 2, … in order of birth among the bubbles alive during the clip; a merged bubble
gets a new id and its parents' ids end at the merge, so no id's centroid jumps.
The field at one time is :mod:`surfphase.synth.field`.
Id 0 is not used: the method's "bubble 0" (the nucleation region) is not an
entity here — attached, growing bubbles are ordinary bubbles with their own ids.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

from surfphase.synth.field import K_SCENE, MODE_DEGREES, FrameState, mode_delta

#: Surface tension (N/m) and liquid density (kg/m³) of saturated water at 100 °C.
SIGMA, RHO_L, G = 0.0589, 958.4, 9.81
#: Height of an attached bubble's centre above the plate, in radii (contact angle).
CONTACT = 0.6
#: Duration of coalescence (two lobes sliding into one sphere), seconds.
COALESCE = 1.5e-3
#: Relaxation time of shape-mode means and amplitudes after detachment, seconds.
RELAX = 2.0e-3
#: Simulated time before frame 0, seconds.
WARMUP = 0.16
#: A bubble leaves the scene when its bottom passes this height, metres.
Y_EXIT = 0.0175
#: Time step of the merge (contact) search, seconds.
CONTACT_DT = 1.0e-4
#: The contact search looks where two bubbles' nominal spheres are less than this
#: fraction of their summed radii apart.
CONTACT_SEARCH = 0.5
#: Shapes of :class:`BubbleScene` (see its ``shape`` argument).
SHAPES = ("default", "sphere", "spheroid", "tilted")
#: Range of the tilt (degrees off the vertical) of a ``"tilted"`` bubble's axis.
TILT_DEG = (20.0, 40.0)


def lamb_frequency(degree: int, radius: float) -> float:
    """Natural frequency (Hz) of shape mode ``degree`` of a bubble of ``radius`` m."""
    n = degree
    w2 = (n - 1) * (n + 1) * (n + 2) * SIGMA / (RHO_L * radius**3)
    return float(np.sqrt(w2) / (2 * np.pi))


def terminal_speed(radius: float) -> float:
    """Terminal rise speed (m/s) of a bubble of equivalent ``radius`` m (0.12–0.3 m/s)."""
    return float(min(0.30, 0.12 + 0.06 * (2 * radius * 1e3)))


@dataclass(frozen=True)
class Mode:
    """One shape mode ``a(t)·P_degree(cos γ)`` about ``axis`` (unit, lab frame).

    ``a(t) = mean(t) + amp(t)·sin(2π·freq·(t − t0) + phase)``; ``mean`` and ``amp``
    ramp up to ``mean_att``/``amp_att`` while attached and relax to ``*_free``
    after detachment (time constant :data:`RELAX`).
    """

    degree: int
    axis: np.ndarray
    mean_att: float
    amp_att: float
    mean_free: float
    amp_free: float
    freq: float
    phase: float


@dataclass
class Bubble:
    """A bubble's whole life (see the module docstring). Times in s, lengths in m."""

    key: int
    t_birth: float
    t_detach: float
    r0: float
    r_detach: float
    site: np.ndarray  # (3,) foot on the plate (y = 0)
    v0: np.ndarray  # (3,) centre velocity at detachment, m/s
    c0: np.ndarray  # (3,) centre at detachment
    u_term: np.ndarray  # (3,) terminal velocity (drift x, rise, drift z)
    tau_acc: float
    wobble_amp: np.ndarray  # (2,) x and z zig-zag amplitudes, m
    wobble_freq: float
    wobble_phase: np.ndarray  # (2,)
    modes: tuple[Mode, ...]
    t_end: float = np.inf
    parents: tuple[Bubble, ...] = ()
    mode_t0: float | None = None  # mode clock start (merged: end of coalescence)
    extra: dict = field(default_factory=dict)

    def alive(self, t: float) -> bool:
        return self.t_birth <= t < self.t_end

    def radius(self, t: np.ndarray | float) -> np.ndarray:
        """Nominal radius (m) at times ``t`` (s)."""
        t = np.asarray(t, dtype=np.float64)
        if self.t_detach <= self.t_birth:
            return np.full(t.shape, self.r_detach)
        s = np.clip((t - self.t_birth) / (self.t_detach - self.t_birth), 0.0, 1.0)
        return np.sqrt(self.r0**2 + (self.r_detach**2 - self.r0**2) * s)

    def center(self, t: np.ndarray | float) -> np.ndarray:
        """Nominal centre (…, 3) in metres at times ``t`` (s), attached or rising."""
        t = np.asarray(t, dtype=np.float64)
        tau = np.maximum(t - self.t_detach, 0.0)[..., None]
        e = np.exp(-tau / self.tau_acc)
        free = self.c0 + self.u_term * tau + (self.v0 - self.u_term) * self.tau_acc * (1 - e)
        env = 1.0 - np.exp(-tau[..., 0] / 4e-3)
        ph = 2 * np.pi * self.wobble_freq * tau[..., 0]
        free[..., 0] += env * self.wobble_amp[0] * np.sin(ph + self.wobble_phase[0])
        free[..., 2] += env * self.wobble_amp[1] * np.sin(ph + self.wobble_phase[1])
        att = np.broadcast_to(self.site, free.shape).copy()
        att[..., 1] = CONTACT * self.radius(t)
        return np.where((t < self.t_detach)[..., None], att, free)

    def velocity(self, t: float, dt: float = 1e-6) -> np.ndarray:
        """Nominal centre velocity (3,) m/s (numerical derivative of :meth:`center`)."""
        return (self.center(t + dt) - self.center(t - dt)) / (2 * dt)

    def mode_amplitudes(self, t: float) -> np.ndarray:
        """(len(modes),) mode amplitudes at time ``t`` (s)."""
        t0 = self.t_birth if self.mode_t0 is None else self.mode_t0
        out = np.zeros(len(self.modes))
        if t < t0:
            return out
        for i, m in enumerate(self.modes):
            osc = np.sin(2 * np.pi * m.freq * (t - t0) + m.phase)
            if t < self.t_detach:
                prog = (t - self.t_birth) / max(self.t_detach - self.t_birth, 1e-9)
                out[i] = m.mean_att * prog + m.amp_att * osc
            else:
                e = np.exp(-(t - max(self.t_detach, t0)) / RELAX)
                mean = m.mean_free + (m.mean_att - m.mean_free) * e
                amp = m.amp_free + (m.amp_att - m.amp_free) * e
                out[i] = mean + amp * osc
        return out

    def lobes(
        self, t: float
    ) -> tuple[list[tuple[np.ndarray, float, np.ndarray, np.ndarray]], float]:
        """Lobes at ``t``: ``[(centre (3,), radius m, mode axes (3, 3), amplitudes (3,))]``
        and the smooth-union width (m) joining them (0 for a single lobe)."""
        if self.parents and t < self.t_birth + COALESCE:
            s = (t - self.t_birth) / COALESCE
            w = s * s * (3 - 2 * s)
            cm = self.center(t)
            lobes = []
            for p in self.parents:
                cp = p.center(self.t_birth)
                rp = float(p.radius(self.t_birth))
                axes = np.stack([m.axis for m in p.modes])
                amps = p.mode_amplitudes(t) * (1 - w)
                lobes.append(
                    (cm + (cp - self.c0) * (1 - w), rp + (self.r_detach - rp) * w, axes, amps)
                )
            return lobes, K_SCENE * (1 - w)
        axes = np.stack([m.axis for m in self.modes])
        return [(self.center(t), float(self.radius(t)), axes, self.mode_amplitudes(t))], 0.0


class BubbleScene:
    """A deterministic pool-boiling scene (see the module docstring).

    Args:
        seed: random seed.
        duration: clip length, s (frames / fps); the scene is defined on [0, duration).
        bubbles: target mean number of bubbles in the rising column (≥ 1).
        force_merge: arrange a wake-capture merge inside the clip (``forced_merge``
            tells whether it could be arranged).
        region: (x, z) half-widths (m) of the plate area holding nucleation sites.
        radius_range: (min, max) detachment radius, m; each site's mean radius is drawn
            from the middle half of the range (default 0.75–1.25 mm).
        shape: ``"default"`` (the three modes of the module docstring), ``"sphere"``
            (no shape modes), ``"spheroid"`` (P2 about the vertical only: an oblate
            spheroid while rising, oscillating), ``"tilted"`` (a spheroid whose axis is
            tilted :data:`TILT_DEG` off the vertical, with its P2 and P3 oscillations
            about that tilted axis — a bubble an axisymmetric-about-vertical prior does
            not fit).
    """

    def __init__(
        self,
        seed: int,
        duration: float,
        bubbles: int = 5,
        force_merge: bool = False,
        region: tuple[float, float] = (0.0035, 0.0015),
        radius_range: tuple[float, float] = (0.5e-3, 1.5e-3),
        shape: str = "default",
    ):
        if duration <= 0:
            raise ValueError(f"scene duration must be positive, got {duration}")
        if bubbles < 1:
            raise ValueError(f"bubble count must be at least 1, got {bubbles}")
        if shape not in SHAPES:
            raise ValueError(f"unknown bubble shape {shape!r}; choose from {SHAPES}")
        if not 0 < radius_range[0] <= radius_range[1]:
            raise ValueError(f"radius range must be 0 < min <= max (m), got {radius_range}")
        self.shape = shape
        self.radius_range = (float(radius_range[0]), float(radius_range[1]))
        self.seed = int(seed)
        self.duration = float(duration)
        self.rng = np.random.default_rng([self.seed, 7101])
        self._key = 0
        n_sites = max(1, int(np.ceil(bubbles / 2.5)))
        self.sites = self._place_sites(n_sites, region)
        per_site = bubbles / n_sites
        self.bubbles: list[Bubble] = []
        self._site_lists: list[list[Bubble]] = []
        for site in self.sites:
            lst = self._schedule_site(site, per_site)
            self._site_lists.append(lst)
            self.bubbles.extend(lst)
        self.forced_merge = bool(force_merge) and self._force_merge()
        self._resolve_merges()
        self._assign_ids()

    # -- construction -------------------------------------------------------------
    def _next_key(self) -> int:
        self._key += 1
        return self._key

    def _place_sites(self, n: int, region: tuple[float, float]) -> list[np.ndarray]:
        sites: list[np.ndarray] = []
        min_gap = 0.0032
        for attempt in range(3000):
            if len(sites) == n:
                break
            p = np.array(
                [
                    self.rng.uniform(-region[0], region[0]),
                    0.0,
                    self.rng.uniform(-region[1], region[1]),
                ]
            )
            if all(np.linalg.norm(p - s) >= min_gap for s in sites):
                sites.append(p)
            elif attempt > 500:
                min_gap *= 0.99
        return sites

    def _random_modes(self, r: float, merged: bool = False) -> tuple[Mode, ...]:
        rng = self.rng
        tilt = rng.normal(size=3)
        tilt[1] = abs(tilt[1]) + 1.0
        tilt /= np.linalg.norm(tilt)
        ax3 = np.array([rng.normal(0, 0.2), 1.0, rng.normal(0, 0.2)])
        ax3 /= np.linalg.norm(ax3)
        up = np.array([0.0, 1.0, 0.0])
        f2, f3 = lamb_frequency(2, r), lamb_frequency(3, r)
        k = 2.5 if merged else 1.0  # coalescence excites strong oscillations
        att = 0.0 if merged else 1.0
        modes = (
            Mode(2, up, att * rng.uniform(0.04, 0.08), att * 0.015, -rng.uniform(0.04, 0.07),
                 k * rng.uniform(0.02, 0.035), f2 * rng.uniform(0.95, 1.05), rng.uniform(0, 2 * np.pi)),
            Mode(2, tilt, 0.0, att * 0.01, 0.0, k * rng.uniform(0.015, 0.03),
                 f2 * rng.uniform(0.9, 1.1), rng.uniform(0, 2 * np.pi)),
            Mode(3, ax3, 0.0, att * 0.008, 0.0, k * rng.uniform(0.008, 0.018),
                 f3 * rng.uniform(0.95, 1.05), rng.uniform(0, 2 * np.pi)),
        )  # fmt: skip
        if self.shape == "default":
            return modes
        off = Mode(2, up, 0.0, 0.0, 0.0, 0.0, f2, 0.0)
        if self.shape == "sphere":
            return (off, replace(off, axis=tilt), replace(off, degree=3, axis=ax3, freq=f3))
        p2 = modes[0]
        if self.shape == "spheroid":
            # Stronger flattening than the default (rising mm bubbles: aspect 1.1–1.4).
            spheroid = replace(p2, mean_free=-rng.uniform(0.06, 0.12))
            return (spheroid, replace(off, axis=tilt), replace(off, degree=3, axis=ax3, freq=f3))
        # "tilted": the spheroid's axis and both oscillations about a tilted axis.
        az = rng.uniform(0, 2 * np.pi)
        tl = np.deg2rad(rng.uniform(*TILT_DEG))
        axis = np.array([np.sin(tl) * np.cos(az), np.cos(tl), np.sin(tl) * np.sin(az)])
        return (
            replace(p2, axis=axis, mean_att=p2.mean_att, mean_free=-rng.uniform(0.06, 0.12)),
            replace(modes[1], axis=axis),
            replace(modes[2], axis=axis),
        )

    def _new_bubble(self, site: np.ndarray, t_birth: float, r_mean: float) -> Bubble:
        rng = self.rng
        rd = float(np.clip(r_mean * rng.uniform(0.85, 1.15), *self.radius_range))
        t_grow = 0.012 * (rd / 1e-3) ** 2 * rng.uniform(0.8, 1.2)
        r0 = 0.15e-3
        u = terminal_speed(rd)
        drift = rng.normal(0, 0.008, size=2)
        b = Bubble(
            key=self._next_key(),
            t_birth=t_birth,
            t_detach=t_birth + t_grow,
            r0=r0,
            r_detach=rd,
            site=site.copy(),
            v0=np.zeros(3),
            c0=np.array([site[0], CONTACT * rd, site[2]]),
            u_term=np.array([drift[0], u, drift[1]]),
            tau_acc=u / (2 * G),
            wobble_amp=rng.uniform(0.05e-3, 0.25e-3, size=2) * (rd / 1e-3),
            wobble_freq=rng.uniform(18, 35),
            wobble_phase=rng.uniform(0, 2 * np.pi, size=2),
            modes=self._random_modes(rd),
        )
        _set_detach_velocity(b)
        return b

    def _schedule_site(self, site: np.ndarray, per_site: float) -> list[Bubble]:
        lo, hi = self.radius_range
        r_mean = self.rng.uniform(lo + 0.25 * (hi - lo), hi - 0.25 * (hi - lo))
        # A bubble is in the column for about (growth + crossing) seconds.
        in_view = 0.012 * (r_mean / 1e-3) ** 2 + Y_EXIT / terminal_speed(r_mean)
        period = in_view / max(per_site, 0.3)
        t = -WARMUP - self.rng.uniform(0, period)
        out = []
        while t < self.duration:
            b = self._new_bubble(site, t, r_mean)
            out.append(b)
            wait = max(period - (b.t_detach - b.t_birth), 0.004) * self.rng.uniform(0.8, 1.2)
            t = b.t_detach + wait
        return out

    def _times(self) -> np.ndarray:
        return np.arange(-WARMUP - 0.05, self.duration + CONTACT_DT, CONTACT_DT)

    def _contact_time(self, a: Bubble, b: Bubble, times: np.ndarray) -> float:
        """First sampled time (s) at which the surfaces of ``a`` and ``b`` touch
        (:func:`surface_gap` ≤ 0), searched where their nominal spheres are less than
        :data:`CONTACT_SEARCH` of their summed radii apart (the shape modes change a
        radius by less than that)."""
        lo, hi = max(a.t_birth, b.t_birth), min(a.t_end, b.t_end, self.duration)
        ts = times[(times >= lo) & (times < hi)]
        if ts.size == 0:
            return np.inf
        ra, rb = a.radius(ts), b.radius(ts)
        gap = np.linalg.norm(a.center(ts) - b.center(ts), axis=1) - ra - rb
        for i in np.flatnonzero(gap <= CONTACT_SEARCH * (ra + rb)):
            if surface_gap(a, b, float(ts[i])) <= 0:
                return float(ts[i])
        return np.inf

    def _exit_time(self, b: Bubble, times: np.ndarray) -> float:
        ts = times[times >= b.t_birth]
        if ts.size == 0:
            return np.inf
        out = np.flatnonzero(b.center(ts)[:, 1] - b.radius(ts) > Y_EXIT)
        return float(ts[out[0]]) if out.size else np.inf

    def _force_merge(self) -> bool:
        """Make a trailing bubble rise in its leader's wake and catch it inside the clip.

        The follower grows twice as fast, accelerates sooner and rises 1.4× faster
        (wake entrainment); its birth time is chosen so that their surfaces touch at a
        time in the middle of the clip, after the follower has detached.
        Returns False (scene unchanged) when no leader/follower pair allows it.
        """
        times = self._times()
        rng = self.rng
        for _attempt in range(8):
            tm = self.duration * rng.uniform(0.3, 0.7)
            for lst in self._site_lists:
                for i in range(len(lst) - 1):
                    a, b = lst[i], lst[i + 1]
                    if not (tm - 0.06 < a.t_detach < tm - 0.004):
                        continue
                    saved = [(x.t_birth, x.t_detach) for x in lst[i + 1 :]]
                    saved_b = (b.u_term, b.tau_acc, b.wobble_amp)
                    t_grow = 0.5 * (b.t_detach - b.t_birth)
                    b.u_term = a.u_term.copy()
                    b.u_term[1] = 1.4 * a.u_term[1]
                    b.tau_acc = 0.4 * a.tau_acc
                    b.wobble_amp = a.wobble_amp * 0.2

                    def shift(tb: float, _lst=lst, _i=i, _saved=saved, _tg=t_grow) -> None:
                        dt = tb - _saved[0][0]
                        for j, (x, (tb0, td0)) in enumerate(
                            zip(_lst[_i + 1 :], _saved, strict=True)
                        ):
                            x.t_birth = tb0 + dt
                            x.t_detach = (tb + _tg) if j == 0 else td0 + dt
                            _set_detach_velocity(x)

                    # Contact time is not monotonic in the birth time (an early follower
                    # touches its leader at the plate), so scan, then bisect a crossing.
                    grid = np.linspace(a.t_detach + 0.003, tm, 48)
                    tcs = []
                    for tb in grid:
                        shift(tb)
                        tc = self._contact_time(a, b, times)
                        tcs.append(tc if tc > b.t_detach + 0.001 else -np.inf)
                    ok = False
                    for j in range(len(grid) - 1, 0, -1):
                        if np.isfinite(tcs[j - 1]) and tcs[j - 1] <= tm < tcs[j]:
                            lo, hi = grid[j - 1], grid[j]
                            for _ in range(25):
                                mid = 0.5 * (lo + hi)
                                shift(mid)
                                if self._contact_time(a, b, times) <= tm:
                                    lo = mid
                                else:
                                    hi = mid
                            shift(lo)
                            tc = self._contact_time(a, b, times)
                            ok = b.t_detach + 0.001 < tc <= tm
                            break
                    if ok:
                        b.extra["wake_of"] = a.key
                        return True
                    for x, (tb0, td0) in zip(lst[i + 1 :], saved, strict=True):
                        x.t_birth, x.t_detach = tb0, td0
                        _set_detach_velocity(x)
                    b.u_term, b.tau_acc, b.wobble_amp = saved_b
        return False

    def _merge(self, a: Bubble, b: Bubble, tm: float) -> Bubble:
        va, vb = float(a.radius(tm)) ** 3, float(b.radius(tm)) ** 3
        wa, wb = va / (va + vb), vb / (va + vb)
        rm = (va + vb) ** (1 / 3)
        c0 = wa * a.center(tm) + wb * b.center(tm)
        v0 = wa * a.velocity(tm - 1e-5) + wb * b.velocity(tm - 1e-5)
        u = terminal_speed(rm)
        rng = self.rng
        drift = wa * a.u_term + wb * b.u_term
        a.t_end = b.t_end = tm
        return Bubble(
            key=self._next_key(),
            t_birth=tm,
            t_detach=tm,
            r0=rm,
            r_detach=rm,
            site=np.array([c0[0], 0.0, c0[2]]),
            v0=v0,
            c0=c0,
            u_term=np.array([drift[0], u, drift[2]]),
            tau_acc=u / (2 * G),
            wobble_amp=rng.uniform(0.05e-3, 0.2e-3, size=2) * (rm / 1e-3),
            wobble_freq=rng.uniform(18, 35),
            wobble_phase=rng.uniform(0, 2 * np.pi, size=2),
            modes=self._random_modes(rm, merged=True),
            parents=(a, b),
            mode_t0=tm + COALESCE,
        )

    def _resolve_merges(self) -> None:
        times = self._times()
        for b in self.bubbles:
            b.t_end = min(b.t_end, self._exit_time(b, times))
        for _ in range(500):
            best: tuple[float, Bubble | None, Bubble | None] = (np.inf, None, None)
            alive = [b for b in self.bubbles if b.t_end > -WARMUP]
            for i, a in enumerate(alive):
                for b in alive[i + 1 :]:
                    if a.t_birth >= b.t_end or b.t_birth >= a.t_end:
                        continue
                    tc = self._contact_time(a, b, times)
                    if tc < best[0]:
                        best = (tc, a, b)
            tm, a, b = best
            if a is None or b is None:
                return
            m = self._merge(a, b, tm)
            m.t_end = self._exit_time(m, times)
            self.bubbles.append(m)
        raise ValueError(f"scene seed {self.seed}: the merge cascade did not settle")

    def _assign_ids(self) -> None:
        shown = [b for b in self.bubbles if b.t_end > 0 and b.t_birth < self.duration]
        shown.sort(key=lambda b: (b.t_birth, b.key))
        self.id_of = {b.key: i + 1 for i, b in enumerate(shown)}
        self.by_id = {i + 1: b for i, b in enumerate(shown)}

    # -- queries ------------------------------------------------------------------
    def merges(self) -> list[tuple[float, int, int, int]]:
        """Merges inside the clip: ``(t_m s, parent id, parent id, merged id)``."""
        out = []
        for b in self.bubbles:
            if b.parents and 0 <= b.t_birth < self.duration and b.key in self.id_of:
                pa, pb = (self.id_of.get(p.key, -1) for p in b.parents)
                out.append((b.t_birth, pa, pb, self.id_of[b.key]))
        return out

    def state(self, t: float) -> FrameState:
        """The scene at time ``t`` (s) as a :class:`FrameState`."""
        ids, centers, radii, lobe_b, axes, amps, kint = [], [], [], [], [], [], []
        for bid, b in self.by_id.items():
            if not b.alive(t):
                continue
            lobes, k = b.lobes(t)
            bi = len(ids)
            ids.append(bid)
            kint.append(k)
            for c, r, ax, am in lobes:
                centers.append(c)
                radii.append(r)
                lobe_b.append(bi)
                axes.append(ax)
                amps.append(am)
        m = len(MODE_DEGREES)
        return FrameState(
            t=float(t),
            ids=np.asarray(ids, dtype=np.int64),
            centers=np.asarray(centers, dtype=np.float64).reshape(-1, 3),
            radii=np.asarray(radii, dtype=np.float64),
            lobe_bubble=np.asarray(lobe_b, dtype=np.int64),
            axes=np.asarray(axes, dtype=np.float64).reshape(-1, m, 3),
            amps=np.asarray(amps, dtype=np.float64).reshape(-1, m),
            k_internal=np.asarray(kint, dtype=np.float64),
        )

    def scene_sdf(self, points: np.ndarray, t: float) -> np.ndarray:
        """(N, 3) points (m) at time ``t`` (s) → (N,) signed distance bound (m)."""
        return self.state(t).sdf(points)


def surface_gap(a: Bubble, b: Bubble, t: float) -> float:
    """Gap (m; < 0: they overlap) between the surfaces of ``a`` and ``b`` at time ``t``
    (s), along the line between each pair of their lobes' centres: the centres'
    distance less each lobe's radius ``R·(1 + δ)`` towards the other (shape modes
    included), the least over the lobe pairs. Exact for spheres; for the near-spherical
    lobes here the nearest points lie close to that line."""
    out = np.inf
    lobes_b = b.lobes(t)[0]
    for ca, ra, axa, ama in a.lobes(t)[0]:
        for cb, rb, axb, amb in lobes_b:
            d = np.asarray(cb, np.float64) - np.asarray(ca, np.float64)
            dist = float(np.linalg.norm(d))
            u = d / max(dist, 1e-12)
            reach_a = ra * (1 + float(mode_delta(axa @ u, ama)))
            reach_b = rb * (1 + float(mode_delta(axb @ -u, amb)))
            out = min(out, dist - reach_a - reach_b)
    return out


def _set_detach_velocity(b: Bubble) -> None:
    """Velocity of the attached centre at detachment, ``d(CONTACT·R)/dt`` (m/s)."""
    t_grow = b.t_detach - b.t_birth
    vy = CONTACT * (b.r_detach**2 - b.r0**2) / (2 * b.r_detach * t_grow)
    b.v0 = np.array([0.0, vy, 0.0])
