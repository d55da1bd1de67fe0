"""Constants and NaN-free numerical helpers shared by the solvers, the cameras and the fit.

Each helper is written so that both its value and its gradient stay finite where the naive
formula divides by zero (zero optical depth, zero weight): the "double ``where``" pattern.
"""

from __future__ import annotations

import math

import jax.numpy as jnp

#: the solid angle of the whole sphere (sr): Λ/4π is the mean radiance of a fluence Λ
FOUR_PI = 4.0 * math.pi


def safe_div(a, b):
    """a / b, and 0 where b == 0; NaN-free in value and gradient (double ``where``)."""
    ok = b != 0
    return jnp.where(ok, a / jnp.where(ok, b, 1.0), 0.0)


def one_minus_exp_over(tau):
    """(1 − e^{−τ})/τ: the mean transmittance over a segment of optical depth τ.

    Finite with finite derivatives at τ = 0 (a series below |τ| = 1e-3).  Used by every
    step-characteristic update: a constant source S over a segment of length ℓ and
    extinction σ contributes S·ℓ·(1 − e^{−σℓ})/(σℓ).
    """
    small = jnp.abs(tau) < 1e-3
    ts = jnp.where(small, 1.0, tau)
    series = 1.0 - tau / 2.0 + tau * tau / 6.0 - tau * tau * tau / 24.0
    return jnp.where(small, series, -jnp.expm1(-ts) / ts)


def linear_source_terms(tau):
    """(φ, ψ, χ, χ₂) of a segment of optical depth τ whose source is linear in optical depth:

    φ = (1 − e^{−τ})/τ,  ψ = (1 − φ)/τ,  χ = (1/τ)∫₀^τ e^{−u}(u/τ − ½) du,  χ₂ = 1/12 + χ/τ.

    Over such a segment, entered with radiance R_a by a source going from Q_a to Q_b, the exit
    radiance is Q_b + e^{−τ}(R_a − Q_a) − φ(Q_b − Q_a), the mean radiance Q̄ + φ(R_a − Q_a) −
    ψ(Q_b − Q_a), and its first moment (1/τ)∫R(u/τ − ½)du is χ(R_a − Q_a) + χ₂(Q_b − Q_a)
    (the linear-characteristic sweep, ``forward/sweep/_kernel.py``).  Below τ = 0.5 each is
    its Taylor series (the closed forms cancel there); value and gradient finite at τ = 0.
    """
    small = jnp.abs(tau) < 0.5
    t = jnp.where(small, 1.0, tau)
    em = jnp.expm1(-t)
    phi_c = -em / t
    psi_c = (t + em) / (t * t)
    chi_c = (((-em) - t * (1.0 + em)) / t + em / 2.0) / t
    chi2_c = 1.0 / 12.0 + chi_c / t
    # series: e^{−u} = Σ (−u)^n/n!; each term integrated exactly
    phi_s = psi_s = chi_s = chi2_s = 0.0
    fact = 1.0
    for n in range(11):
        if n:
            fact *= n
        a = (-1.0) ** n / fact  # coefficient of u^n in e^{-u}
        phi_s = phi_s + a / (n + 1) * tau**n  # (1/τ)∫₀^τ u^n du = τ^n/(n+1)
        if n >= 1:  # ψ = (1 − φ)/τ: φ's series without its leading 1, over τ
            psi_s = psi_s - a / (n + 1) * tau ** (n - 1)
        c = a * n / (2.0 * (n + 1) * (n + 2))  # ∫₀^τ u^n (u/τ − ½) du / τ = τ^n · n/(2(n+1)(n+2))
        chi_s = chi_s + c * tau**n
        if n >= 2:  # χ₂ = 1/12 + χ/τ: the n = 1 term of χ/τ is −1/12
            chi2_s = chi2_s + c * tau ** (n - 1)
    return (jnp.where(small, phi_s, phi_c), jnp.where(small, psi_s, psi_c),
            jnp.where(small, chi_s, chi_c), jnp.where(small, chi2_s, chi2_c))


def bilinear(buf, u, v, xp=jnp):
    """Bilinear lookup of ``buf[..., H, W]`` at continuous index coordinates (u, v) (any
    matching shapes), clamped to the buffer: a point outside reads the nearest edge value.

    ``xp``: ``jax.numpy`` (traced, differentiable in ``buf``) or ``numpy`` (host).
    """
    hs, ws = buf.shape[-2:]
    u = xp.clip(u, 0.0, hs - 1.0)
    v = xp.clip(v, 0.0, ws - 1.0)
    i0 = xp.clip(xp.floor(u), 0, max(hs - 2, 0)).astype(xp.int32 if xp is jnp else "int64")
    j0 = xp.clip(xp.floor(v), 0, max(ws - 2, 0)).astype(xp.int32 if xp is jnp else "int64")
    i1 = xp.minimum(i0 + 1, hs - 1)
    j1 = xp.minimum(j0 + 1, ws - 1)
    fu, fv = u - i0, v - j0
    return ((1 - fu) * (1 - fv) * buf[..., i0, j0] + fu * (1 - fv) * buf[..., i1, j0]
            + (1 - fu) * fv * buf[..., i0, j1] + fu * fv * buf[..., i1, j1])


def trilinear(vol, origin, h: float, pts):
    """Trilinear sample of a node-centred (nx, ny, nz) field (node (i, j, k) at
    ``origin + (idx + 0.5)·h``) at points (..., 3); 0 outside the nodes' hull."""
    c = (pts - jnp.asarray(origin, pts.dtype)) / h - 0.5
    shape = vol.shape
    i0 = jnp.floor(c)
    f = c - i0
    i0 = i0.astype(jnp.int32)
    out = jnp.zeros(pts.shape[:-1], vol.dtype)
    for dx in (0, 1):
        for dy in (0, 1):
            for dz in (0, 1):
                ix, iy, iz = i0[..., 0] + dx, i0[..., 1] + dy, i0[..., 2] + dz
                w = ((f[..., 0] if dx else 1 - f[..., 0]) * (f[..., 1] if dy else 1 - f[..., 1])
                     * (f[..., 2] if dz else 1 - f[..., 2]))
                ok = ((ix >= 0) & (ix < shape[0]) & (iy >= 0) & (iy < shape[1])
                      & (iz >= 0) & (iz < shape[2]))
                v = vol[jnp.clip(ix, 0, shape[0] - 1), jnp.clip(iy, 0, shape[1] - 1),
                        jnp.clip(iz, 0, shape[2] - 1)]
                out = out + jnp.where(ok, w * v, 0.0)
    return out
