"""The uncollided sun: a light-aligned transmittance sweep, sheet by sheet.

Sunlight is a delta in direction; putting it into one lattice direction would cause strong ray
effects (DESIGN.md).  Instead we march sheets perpendicular to the sweep axis most aligned with
the sun (always z for laterally periodic domains), carrying a 2-D buffer of transmittance — the
splatting paper's shadow buffer.  Moving one sheet along the beam shifts the buffer by the
beam's fractional lateral offset (bilinear resampling) and attenuates it by the half-segments of
the two nodes, exactly like the discrete-ordinates step.  SOLID nodes stop the beam; SURFACE
nodes let it through (they are the surface's shell, not an obstacle), so every shell node facing
the sun receives it.  The result feeds the first-collision source of the sweep and the direct
illumination of surfaces.
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np

from ._directions import face_plane_axes


def sun_sweep_axis(sun_dir: np.ndarray, periodic_xy: bool) -> tuple[int, int]:
    """(axis, sign) of the sheet order: the light travels along ``-sun_dir``."""
    a = 2 if periodic_xy else int(np.argmax(np.abs(sun_dir)))
    return a, (-1 if sun_dir[a] > 0 else 1)


def sun_transmittance(sigma_t, opaque, sun_dir, h, periodic_xy):
    """Transmittance of the direct sun beam arriving at every node.

    sigma_t: (nx, ny, nz) extinction per unit length (ζ+γ)·density; opaque: (nx, ny, nz) bool
    (SOLID nodes); sun_dir: unit vector *towards* the sun (static); h: voxel size.
    Returns (nx, ny, nz) in [0, 1].
    """
    sun_dir = np.asarray(sun_dir, dtype=np.float64)
    axis, sign = sun_sweep_axis(sun_dir, periodic_xy)
    along = abs(sun_dir[axis])
    if along < 1e-9:  # sun exactly on the horizon of a periodic domain: no direct light
        return jnp.zeros_like(sigma_t)
    u, v = face_plane_axes(axis)
    perm = (axis, u, v)
    s = jnp.transpose(sigma_t, perm)
    o = jnp.transpose(opaque, perm)
    if sign < 0:
        s, o = s[::-1], o[::-1]
    # Light moves by -sun_dir; per sheet the lateral displacement is d = -sun_dir[u,v]/along.
    # The light at (u, v) came from (u - du, v - dv) in the previous sheet.
    src = [-(-sun_dir[u] / along), -(-sun_dir[v] / along)]  # offsets to sample, in voxels
    ipart = [math.floor(x) for x in src]
    frac = [x - i for x, i in zip(src, ipart)]
    lateral_periodic = (periodic_xy and u in (0, 1), periodic_xy and v in (0, 1))
    half = jnp.exp(-s * (h / (2.0 * along)))  # half-segment transmittance per node

    def resample(t):
        for ax, (i0, f, per) in enumerate(zip(ipart, frac, lateral_periodic)):
            n = t.shape[ax]
            pad_lo, pad_hi = max(0, -i0), max(0, i0 + 1)
            widths = [(0, 0), (0, 0)]
            widths[ax] = (pad_lo, pad_hi)
            if per:
                tp = jnp.pad(t, widths, mode="wrap")
            else:
                tp = jnp.pad(t, widths, constant_values=1.0)  # no fog outside an open domain
            a0 = jax.lax.slice_in_dim(tp, pad_lo + i0, pad_lo + i0 + n, axis=ax)
            a1 = jax.lax.slice_in_dim(tp, pad_lo + i0 + 1, pad_lo + i0 + 1 + n, axis=ax)
            t = a0 if f == 0.0 else (1.0 - f) * a0 + f * a1
        return t

    def step(t_out_prev, sheet):
        half_k, opaque_k = sheet
        t_arr = resample(t_out_prev) * half_k
        t_out = jnp.where(opaque_k, 0.0, t_arr * half_k)
        return t_out, t_arr

    init = jnp.ones(s.shape[1:], s.dtype)
    _, t_arr = jax.lax.scan(step, init, (half, o))
    if sign < 0:
        t_arr = t_arr[::-1]
    return jnp.transpose(t_arr, np.argsort(perm))
