"""Exact and reference cases for the validation ladder (``docs/design.md``), shared by tests and
benchmarks.

* ``slab_problem``: a laterally infinite homogeneous slab under a uniform sky (and optionally a
  sun), as a periodic lattice one node wide, with vacuum margins above and below so that light
  leaving the fog is measured outside it.
* ``slab_reflectance``: total reflectance and transmittance from a converged light field by the
  formal solution along a fine μ quadrature — what a camera integrating over the hemisphere
  would measure, not a count of lattice directions.
* ``slab_exits``: R and T as the lattice itself lets light out (the net flux of its own
  radiance through vacuum planes), the measure of whether the scheme conserves energy.
* ``exact_slab_radiance``: the emergent radiance of an isotropic slab at given μ, exact to a
  fine discretisation of its integral equation: the truth that cameras looking at a slab
  (``benchmarks/slab_cameras.py``) are held against, per angle.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from ..scene._description import Domain, Fog, Scene, Sky, Sun


@dataclass(frozen=True)
class ColumnLattice:
    """A periodic lattice one node wide (laterally homogeneous problems)."""

    node_type: np.ndarray
    normal: np.ndarray
    material: np.ndarray
    density: np.ndarray
    h: float
    M: int
    boundary: str = "periodic-xy"
    origin: np.ndarray = field(default_factory=lambda: np.zeros(3))

    @property
    def shape(self):
        return self.node_type.shape

    @property
    def peak_density(self) -> float:  # no solids in a slab: the densest node (Lattice's rule)
        return float(np.max(self.density, initial=0.0))


def slab_problem(tau: float, albedo: float, n_fog: int, M: int, *, sky: float = 1.0,
                 sun: tuple[float, float] | None = None, g: float = 0.0,
                 margin: int | None = None):
    """(scene, lattice, margin) of a unit-thickness slab of optical thickness ``tau``.

    The fog occupies ``n_fog`` nodes (h = 1/n_fog); ``margin`` vacuum nodes (default M+1) lie
    above and below (``slab_exits`` needs 2M+1).  ``sun`` = (irradiance, zenith_deg) adds a sun.
    """
    margin = M + 1 if margin is None else int(margin)
    nz = n_fog + 2 * margin
    h = 1.0 / n_fog
    density = np.zeros((1, 1, nz), np.float32)
    density[..., margin : margin + n_fog] = 1.0
    lat = ColumnLattice(
        node_type=np.zeros((1, 1, nz), np.int8),
        normal=np.zeros((1, 1, nz, 3), np.float32),
        material=-np.ones((1, 1, nz), np.int16),
        density=density,
        h=h,
        M=M,
    )
    fog = Fog(
        scattering=albedo * tau,
        absorption=(1.0 - albedo) * tau,
        phase="henyey-greenstein" if g else "isotropic",
        g=g,
    )
    scene = Scene(
        title=f"slab tau={tau} a={albedo}",
        domain=Domain((0.0, 0.0, -margin * h), (h, h, 1.0 + margin * h), "periodic-xy"),
        fog=fog,
        sky=Sky(sky) if sky else None,
        sun=Sun(sun[0], sun[1], 0.0) if sun else None,
    )
    return scene, lat, margin


def incident_flux(sky: float, sun: tuple[float, float] | None = None) -> float:
    """The flux a slab receives: π·sky, plus F·μ₀ for a sun (F, zenith in degrees)."""
    flux = math.pi * sky
    if sun is not None:
        flux += sun[0] * math.cos(math.radians(sun[1]))
    return flux


def slab_absorption(sigma_t, light, albedo: float, h: float, *, sky: float,
                    sun: tuple[float, float] | None = None) -> float:
    """A of a slab column from its solve's own fluence, (1 − a)·Σ σ_t·(Λ + the uncollided
    sky and sun)·h over the incident flux; ``sigma_t`` (nz,) the column's extinction."""
    fl = np.asarray(light.fluence + light.sky_fluence + light.sun_fluence, np.float64)[0, 0]
    absorbed = float(np.sum((1.0 - albedo) * np.asarray(sigma_t, np.float64) * fl) * h)
    return absorbed / incident_flux(sky, sun)


def slab_exits(solver, geom, params, light, margin: int, *, sky: float,
               sun: tuple[float, float] | None = None):
    """(R, T) of a slab column as the lattice itself lets light out: the net flux of the
    lattice's own radiance (``net_flux``) through the vacuum planes above and below the fog,
    averaged over the M interleaved plane chains (a lattice ray steps M planes, so each chain
    carries its own exit flux), divided by the incident flux (π·sky + F·μ₀).  T includes the
    unscattered sun.  Where the scheme conserves energy, R + T + A = 1 with these exactly.

    The planes used lie more than M planes from the fog (no segment of theirs reaches it), so
    the slab needs ``margin`` ≥ 2M + 1 and a solver that keeps Λ in vacuum
    (``SweepSolver(terms="all")``).
    """
    from ..forward.sweep._solver import net_flux

    M = geom.M
    if margin < 2 * M + 1:
        raise ValueError(f"slab_exits needs margin >= 2M+1 = {2 * M + 1}, got {margin}")
    if geom.terms is not None and geom.terms.fog_slabs is not None:
        raise ValueError('slab_exits needs SweepSolver(terms="all") (Λ kept in vacuum)')
    pb = solver.problem(geom, params)
    flux = np.asarray(net_flux(geom, pb, light), np.float64)[0, 0]
    nz = flux.shape[0]
    top = flux[nz - margin + M : nz - margin + 2 * M].mean()  # planes M+1..2M above the fog
    bottom = flux[margin - 2 * M : margin - M].mean()
    incident = incident_flux(sky, sun)
    direct = 0.0
    if sun is not None:
        F, zen = sun
        mu0 = math.cos(math.radians(zen))
        sigma = np.asarray(pb.sigma_t, np.float64)[0, 0]
        direct = F * mu0 * math.exp(-float(sigma.sum() * geom.h) / mu0)
    # the lattice carries the sky (periodic default): net = up − π·sky at the top
    return (top + math.pi * sky) / incident, (direct - bottom) / incident


def sun_scatter_terms(light, albedo: float, tau: float, g: float, density) -> tuple:
    """``slab_reflectance``'s ``sun_scatter`` for a slab of optical depth ``tau`` (per unit
    density) whose solver scatters the sun's first collision with the exact phase: (ζ per cell,
    g, the beam's fluence, the beam's extinction per cell, the kept peak's (c, width)).  The beam
    keeps the forward peak that the lattice's directions cannot resolve (``light.sun_peak``):
    it loses ζ(1 − kept) + γ per unit length, and its light scatters with p·(1 − c·K)."""
    dens = np.asarray(density, np.float64)
    kept, c, width = (0.0, 0.0, 1.0) if light.sun_peak is None else (
        float(x) for x in np.asarray(light.sun_peak, np.float64))
    zeta = albedo * tau * dens
    return (zeta, g, np.asarray(light.sun_fluence, np.float64)[0, 0],
            zeta * (1.0 - kept) + (1.0 - albedo) * tau * dens, (c, width))


def slab_reflectance(sigma_t, source, sun_fluence, margin: int, h: float, *, sky: float,
                     sun: tuple[float, float] | None = None, n_mu: int = 64, basis=None,
                     n_phi: int = 64, sun_scatter: tuple | None = None, slope=None):
    """(R, T) of a slab column from its converged source radiance (formal solution).

    sigma_t, source: (nz,) extinction and step source Q of the column (emission per unit
    length σ_t·Q, constant over each node's cell); with an anisotropic phase ``source`` is
    (nz, 1 + K) (``_solver.source_field``) and ``basis`` the solver's ``_harmonics.Basis``:
    direction ω's source is Q_0 + Σ_k Ỹ_k(ω) Q_k, averaged over azimuth here (n_phi points).
    Incident flux is π·sky (+ F·μ₀ for a sun); T includes the unscattered sky and sun.
    ``sun_scatter`` = (ζ (scalar or per cell), g, sun (nz,), σ_sun (nz,)[, (c, width)]): add
    the sun's single scattering with the exact Henyey–Greenstein phase (times 1 − c·K(Θ),
    ``forward_peak_kernel``, the forward peak the sun's beam keeps), ζ·p(Θ)·sun per unit length
    (``sun``: the uncollided sun's fluence at each cell; ``source`` then leaves the sun out),
    as the cameras do, and attenuate the sun's beam by σ_sun (where the solver scatters the
    sun's first collision exactly: ``sun_scatter_terms``).
    ``slope``: (nz,) h·∂Q/∂z of the linear-source scheme (``LightField.source_slope``): the
    isotropic source then varies linearly across each cell, q + slope·t for t ∈ [−½, ½].
    """
    s = np.asarray(sigma_t, np.float64)
    mu, wmu = half_range_gauss(n_mu)
    q = np.asarray(source, np.float64)
    if q.ndim == 2:  # anisotropic: the source towards +μ (up) and −μ (down), azimuth-averaged
        phi = 2 * math.pi * (np.arange(n_phi) + 0.5) / n_phi
        sin = np.sqrt(1.0 - mu**2)
        om = np.stack([sin[:, None] * np.cos(phi), sin[:, None] * np.sin(phi),
                       np.broadcast_to(mu[:, None], (n_mu, n_phi))], -1)
        y_up = basis.evaluate(om).mean(1)  # (n_mu, K)
        y_dn = basis.evaluate(om * np.array([1.0, 1.0, -1.0])).mean(1)
        j_up = s[:, None] * (q[:, :1] + q[:, 1:] @ y_up.T)  # (nz, n_mu)
        j_dn = s[:, None] * (q[:, :1] + q[:, 1:] @ y_dn.T)
    else:
        j_up = j_dn = (s * q)[:, None]
    if sun_scatter is not None:
        from ..forward._camera import forward_peak_kernel

        zeta, g, sun_flu = sun_scatter[:3]
        c, width = sun_scatter[4] if len(sun_scatter) > 4 else (0.0, 1.0)
        mu0 = math.cos(math.radians(sun[1]))
        phi = 2 * math.pi * (np.arange(n_phi) + 0.5) / n_phi
        sin, sin0 = np.sqrt(1.0 - mu**2), math.sqrt(max(0.0, 1.0 - mu0**2))
        for sign, name in ((1.0, "up"), (-1.0, "dn")):
            # cos Θ between the sun's light (going down, −μ₀) and light going ±μ
            cos = -mu0 * sign * mu[:, None] + sin0 * sin[:, None] * np.cos(phi)[None]
            p = ((1 - g * g) / (4 * math.pi * (1 + g * g - 2 * g * cos) ** 1.5)
                 * (1.0 - c * forward_peak_kernel(cos, width, np))).mean(1)
            add = (zeta * np.asarray(sun_flu, np.float64))[:, None] * p[None]
            if name == "up":
                j_up = j_up + add
            else:
                j_dn = j_dn + add
    dtau = s * h
    above = np.cumsum(dtau[::-1])[::-1] - dtau  # optical depth above each cell
    below = np.cumsum(dtau) - dtau
    total = dtau.sum()
    # emitted radiance of each cell towards μ, per unit j: (1 - e^{-Δτ/μ})/σ (→ h/μ as σ → 0)
    with np.errstate(divide="ignore", invalid="ignore"):
        cell = np.where(
            s[:, None] > 0,
            -np.expm1(-dtau[:, None] / mu[None]) / np.where(s > 0, s, 1.0)[:, None],
            h / mu[None],
        )
    up_cell, dn_cell = j_up * cell, j_dn * cell
    if slope is not None:
        # ∫₀^T (½ − u/T) e^{−u} du = −T·χ(T) over a cell of slant depth T = Δτ/μ, u measured
        # back from where the ray leaves the cell (up: from its top, down: from its bottom)
        T = dtau[:, None] / mu[None]
        with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
            tchi = np.where(T > 1e-4, ((1 - np.exp(-T) * (1 + T)) / T - (-np.expm1(-T)) / 2),
                            -T * T / 12)
        sl = np.asarray(slope, np.float64)[:, None]
        up_cell = up_cell - sl * tchi
        dn_cell = dn_cell + sl * tchi
    up = (up_cell * np.exp(-above[:, None] / mu[None])).sum(0)
    down = (dn_cell * np.exp(-below[:, None] / mu[None])).sum(0)
    down = down + sky * np.exp(-total / mu)
    flux_up = 2 * math.pi * (wmu * mu * up).sum()
    flux_down = 2 * math.pi * (wmu * mu * down).sum()
    incident = incident_flux(sky, sun)
    if sun is not None:
        F, zen = sun
        mu0 = math.cos(math.radians(zen))
        total_sun = total if sun_scatter is None else float(np.sum(sun_scatter[3]) * h)
        flux_down += F * mu0 * math.exp(-total_sun / mu0)
    return flux_up / incident, flux_down / incident


def half_range_gauss(n: int) -> tuple[np.ndarray, np.ndarray]:
    """(μ, w): the ``n``-point Gauss–Legendre rule on (0, 1), weights summing to 1."""
    x, w = np.polynomial.legendre.leggauss(n)
    return 0.5 * (x + 1.0), 0.5 * w


def sun_cosine(light: str) -> float | None:
    """μ₀ of the sun a slab ``light`` names ("collZ": zenith Z degrees), None for "diffuse"."""
    return None if light == "diffuse" else math.cos(math.radians(float(light[4:])))


def _e3(x):
    from scipy.special import expn

    x = np.asarray(x, np.float64)
    return np.where(x > 0, expn(3, np.maximum(x, 1e-300)), 0.5)


def exact_slab_collided(tau: float, albedo: float, light: str, *,
                        cells_per_tau: float = 64.0, min_cells: int = 400):
    """(t, J) of a homogeneous isotropic slab: the cell edges in optical depth from the top
    (n + 1) and each cell's collided mean intensity J (n), solving J = a·Λ[J + J₀] (Λ the E₁
    kernel averaged over each pair of cells exactly, by differences of E₃; J₀ the uncollided
    light, cell-averaged) directly on cells of 1/``cells_per_tau`` mean free path, at least
    ``min_cells``.  ``light``: "diffuse" (a sky of radiance 1) or "collZ" (a sun of irradiance
    1 at zenith Z degrees)."""
    n = max(int(min_cells), int(math.ceil(tau * cells_per_tau)))
    d = tau / n
    t = np.arange(n + 1) * d
    m = np.arange(n)
    col = np.empty(n)
    col[0] = (2 * d - 1 + 2 * _e3(d)) / (2 * d)
    col[1:] = (_e3((m[1:] + 1) * d) + _e3((m[1:] - 1) * d) - 2 * _e3(m[1:] * d)) / (2 * d)
    K = col[np.abs(m[:, None] - m[None, :])]
    sun = sun_cosine(light)
    if sun is None:  # J₀ of a downward isotropic radiance 1: E₂(t)/2, cell-averaged
        j0 = 0.5 * (_e3(t[:-1]) - _e3(t[1:])) / d
    else:  # F e^(−t/μ₀)/4π, cell-averaged
        j0 = sun * (np.exp(-t[:-1] / sun) - np.exp(-t[1:] / sun)) / d / (4 * math.pi)
    return t, np.linalg.solve(np.eye(n) - albedo * K, albedo * K @ j0)


def exact_slab_radiance(tau: float, albedo: float, light: str, mus, *,
                        cells_per_tau: float = 64.0, min_cells: int = 400):
    """(I_top(μ), I_bottom(μ), incident flux, direct) of a homogeneous isotropic slab.

    ``light``: "diffuse" (a sky of radiance 1 from above) or "collZ" (a sun of irradiance 1 at
    zenith Z degrees).  I_top is the radiance leaving the top towards +μ, I_bottom the one
    leaving the bottom towards −μ (with the sky seen through the slab); ``direct`` is the
    sun's unscattered flux through the bottom (0 for the sky), so that R = 2π∫I_top μ dμ /
    incident and T = (2π∫I_bottom μ dμ + direct) / incident.

    The collided light is ``exact_slab_collided``'s; the single scattering of the sun and of
    the sky is integrated in closed form (the sky's over a 400-point μ' quadrature).  R and T
    agree with the adding-doubling table within 0.04% on its isotropic rows with τ ≤ 64
    (tests/test_slab_cameras.py).
    """
    t, J = exact_slab_collided(tau, albedo, light, cells_per_tau=cells_per_tau,
                               min_cells=min_cells)
    sun = sun_cosine(light)
    mus = np.asarray(mus, np.float64)
    et = np.exp(-t[None, :] / mus[:, None])
    eb = np.exp(-(tau - t[None, :]) / mus[:, None])
    top = (albedo * J[None] * (et[:, :-1] - et[:, 1:])).sum(1)
    bot = (albedo * J[None] * (eb[:, 1:] - eb[:, :-1])).sum(1)

    def through(inv_in):  # ∫₀^τ e^(−t·inv_in) e^(−(τ−t)/μ) dt/μ, stable for any sign
        b = inv_in - 1 / mus[:, None]
        with np.errstate(divide="ignore", invalid="ignore"):
            return np.where(np.abs(b) > 1e-6,
                            (np.exp(-tau / mus[:, None]) - np.exp(-tau * inv_in))
                            / (b * mus[:, None]),
                            tau / mus[:, None] * np.exp(-tau / mus[:, None]))

    if sun is None:
        mp, wp = half_range_gauss(400)
        a_ = 1 / mp[None, :] + 1 / mus[:, None]
        top += albedo / 2 * (wp[None] * (1 - np.exp(-tau * a_)) / (mus[:, None] * a_)).sum(1)
        bot += albedo / 2 * (wp[None] * through(1 / mp[None, :])).sum(1)
        bot += np.exp(-tau / mus)  # the sky seen through the slab
        return top, bot, math.pi, 0.0
    c = albedo / (4 * math.pi)
    top += c * sun / (sun + mus) * (1 - np.exp(-tau * (1 / sun + 1 / mus)))
    bot += c * through(np.array([[1 / sun]]))[:, 0]
    return top, bot, sun, sun * math.exp(-tau / sun)


def _hg_modes(g: float, mu_out, mu_in, modes: int, n_phi: int = 2048):
    """(modes, n_out, n_in): the Henyey–Greenstein phase (mean 1 over the sphere) between
    propagation cosines ``mu_out`` and ``mu_in`` (signed), its azimuthal Fourier coefficients
    p_m = (1/2π)∫ p(cos Θ(ψ)) cos(mψ) dψ, m < ``modes`` (midpoint rule in ψ, spectral for
    this smooth periodic integrand)."""
    psi = (np.arange(n_phi) + 0.5) * (math.pi / n_phi)
    mo, mi = np.asarray(mu_out)[:, None, None], np.asarray(mu_in)[None, :, None]
    c = mo * mi + np.sqrt(np.clip(1 - mo * mo, 0, None) * np.clip(1 - mi * mi, 0, None)) \
        * np.cos(psi)
    p = (1 - g * g) / (1 + g * g - 2 * g * c) ** 1.5
    return np.stack([(p * np.cos(m * psi)).mean(axis=2) for m in range(modes)])


def adding_doubling_radiance(tau: float, albedo: float, g: float, light: str, mus,
                             azimuths=None, *, n_quad: int = 64, modes: int = 96,
                             delta: float = 1e-7):
    """(I_top, I_bottom, incident flux, direct) of a homogeneous Henyey–Greenstein slab (any
    g; g = 0 is isotropic) at the cosines ``mus``, by adding-doubling on an ``n_quad``-point
    Gauss–Legendre rule per hemisphere: a layer of optical depth ``delta`` or less (single
    scattering, exact within it for every pair of directions) doubled up to τ.  ``light`` as
    ``exact_slab_radiance`` names it.  The cameras' cosines (and the sun's) join the rule
    with a vanishing weight, so the radiance is the adding-doubling's own at exactly those
    angles, not interpolated.  Under a sun off the zenith the radiance depends on the azimuth:
    ``azimuths`` (degrees, each camera's azimuth from the sun's: 0 on the sun's side) gives
    I_top, I_bottom of shape (len(mus), len(azimuths)) from ``modes`` azimuthal Fourier
    modes; without it, their azimuthal mean.  Against ``exact_slab_radiance`` (g = 0): within
    0.2% at μ = 0.034 and 0.05% elsewhere; its R and T against the adding-doubling table's
    g = 0.85 rows (iadpython) within 0.001% (tests/test_slab_cameras.py)."""
    mq, wq = half_range_gauss(n_quad)
    mus = np.asarray(mus, np.float64)
    sun = sun_cosine(light)
    eps = 1e-40  # the extra cosines' weight: they read the field without feeding it
    mu = np.concatenate([mq, mus, [] if sun is None else [sun]])
    wt = np.concatenate([wq, np.full(mu.size - n_quad, eps)])
    n = mu.size
    n_modes = modes if (azimuths is not None and sun is not None and sun < 1.0) else 1
    pf = _hg_modes(g, mu, mu, n_modes)  # both directions into the slab (transmission)
    pb = _hg_modes(g, mu, -mu, n_modes)  # one out of it (reflection)
    norm = 0.5 * ((pf[0, :, :n_quad] + pb[0, :, :n_quad]) * wq).sum(1)  # each row scatters a
    pf, pb = pf / norm[None, :, None], pb / norm[None, :, None]
    k = max(0, int(math.ceil(math.log2(tau / delta))))
    d = tau / 2 ** k
    mi, mj = mu[:, None], mu[None, :]
    refl = mj / (mi + mj) * -np.expm1(-d * (1 / mi + 1 / mj)) * wt[None]
    with np.errstate(divide="ignore", invalid="ignore"):
        trans = np.where(np.abs(mi - mj) < 1e-14, d / mi * np.exp(-d / mi),
                         mj / (mj - mi) * (np.exp(-d / mj) - np.exp(-d / mi))) * wt[None]
    E = np.diag(np.exp(-d / mu))
    cam = slice(n_quad, n_quad + mus.size)
    out_top, out_bot = [], []
    for m in range(n_modes):
        R = albedo / 2 * pb[m] * refl
        T = E + albedo / 2 * pf[m] * trans  # (every mode's radiance is attenuated alike)
        for _ in range(k):  # the layer on itself: R + T(1 − RR)⁻¹RT, T(1 − RR)⁻¹T
            TG = T @ np.linalg.inv(np.eye(n) - R @ R)
            R, T = R + TG @ R @ T, TG @ T
        if sun is None:
            out_top.append(R[cam] @ np.ones(n))
            out_bot.append(T[cam] @ np.ones(n))
        else:  # a beam of irradiance 1: per mode a radiance density 1/2π at μ₀
            out_top.append(R[cam, -1] / (2 * math.pi * eps))
            out_bot.append(T[cam, -1] / (2 * math.pi * eps))
    if sun is None:
        return out_top[0], out_bot[0], math.pi, 0.0
    top, bot = np.array(out_top), np.array(out_bot)
    if n_modes > 1:  # the light's propagation azimuth is the sun's + 180°
        dpsi = np.radians(np.asarray(azimuths, np.float64)) - math.pi
        c = np.cos(np.arange(n_modes)[:, None] * dpsi[None, :])
        c[1:] *= 2.0
        top, bot = np.einsum("mk,ma->ka", top, c), np.einsum("mk,ma->ka", bot, c)
    elif azimuths is not None:
        top = np.repeat(top[0][:, None], len(azimuths), axis=1)
        bot = np.repeat(bot[0][:, None], len(azimuths), axis=1)
    else:
        top, bot = top[0], bot[0]
    return top, bot, sun, sun * math.exp(-tau / sun)


def isotropic_slab_rows(g: float = 0.0) -> dict[tuple[float, float, str], tuple[float, float]]:
    """{(τ, albedo, light): (R_total, T_total)} of the adding-doubling table's rows of
    anisotropy ``g`` (0: isotropic), light named as ``exact_slab_radiance`` names it
    ("diffuse", "coll0", "coll60")."""
    from .references import slab_table

    rows = {}
    for r in slab_table():
        if r["g"] != g:
            continue
        light = "diffuse" if r["illumination"] == "diffuse" else f"coll{int(r['zenith_deg'])}"
        rows[(r["tau"], r["albedo"], light)] = (r["R_total"], r["T_total"])
    return rows


def exact_slab_rt(tau: float, albedo: float, light: str, n_mu: int = 48,
                  cells_per_tau: float = 64.0, g: float = 0.0) -> tuple[float, float]:
    """R, T of the exact slab by an ``n_mu``-point Gauss–Legendre μ rule over its radiance:
    ``exact_slab_radiance``'s (isotropic), or ``adding_doubling_radiance``'s azimuthal mean
    for a Henyey–Greenstein ``g`` ≠ 0."""
    mu, wmu = half_range_gauss(n_mu)
    top, bot, inc, direct = (adding_doubling_radiance(tau, albedo, g, light, mu) if g else
                             exact_slab_radiance(tau, albedo, light, mu,
                                                 cells_per_tau=cells_per_tau))
    return (2 * math.pi * float(np.sum(wmu * mu * top)) / inc,
            (2 * math.pi * float(np.sum(wmu * mu * bot)) + direct) / inc)
