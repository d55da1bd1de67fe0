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
