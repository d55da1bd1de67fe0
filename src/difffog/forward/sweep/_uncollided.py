"""The uncollided sun: a light-aligned transmittance sweep, sheet by sheet.

Sunlight is a delta in direction; putting it into one lattice direction would cause strong ray
effects (docs/design.md).  Instead we march sheets perpendicular to the sweep axis most aligned with
the sun (always z for laterally periodic domains), carrying a 2-D buffer of transmittance — the
splatting paper's shadow buffer.  Moving one sheet along the beam shifts the buffer by the
beam's fractional lateral offset (bilinear resampling) and attenuates it by the half-segments of
the two nodes, exactly like the discrete-ordinates step.  SOLID nodes stop the beam; SURFACE
nodes let it through (they are the surface's shell, not an obstacle), so every shell node facing
the sun receives it.  The result feeds the first-collision source of the sweep and the direct
illumination of surfaces.
"""

from __future__ import annotations

import functools
import math

import jax
import jax.numpy as jnp
import numpy as np

from ..._numerics import linear_source_terms, one_minus_exp_over
from ...geometry._directions import face_plane_axes
from . import _native


def sun_sweep_axis(sun_dir: np.ndarray, periodic_xy: bool) -> tuple[int, int]:
    """(axis, sign) of the sheet order: the light travels along ``-sun_dir``."""
    a = 2 if periodic_xy else int(np.argmax(np.abs(sun_dir)))
    return a, (-1 if sun_dir[a] > 0 else 1)


#: the sun's path (``sun_path``) where no beam reaches (a sun on the horizon of a periodic
#: domain, no face of the fog's box towards the sun): large, so that e^(−σ·path) is 0, and
#: finite, so that differences between nodes are 0 and σ = 0 gives no 0·∞
NO_SUN_PATH = 1e20

#: a quantity changing linearly by Δ across a segment has first moment Δ/12 over it
_MOMENT_TO_CHANGE = 12.0


def beam_frame_key(sun_dir, periodic_xy: bool):
    """What a beam towards ``sun_dir`` fixes in its program: (axis, sign, the offsets' whole
    voxels per sheet), or None for a sun on the horizon of a periodic domain.  With the sun's
    direction traced (``_beam_frame``'s ``vec``) two static directions with the same key give
    the same program."""
    sun_dir = np.asarray(sun_dir, np.float64)
    axis, sign = sun_sweep_axis(sun_dir, periodic_xy)
    along = float(abs(sun_dir[axis]))
    if along < 1e-9:
        return None
    u, v = face_plane_axes(axis)
    # Light moves by -sun_dir; per sheet the lateral displacement is d = -sun_dir[u,v]/along.
    # The light at (u, v) came from (u - du, v - dv) in the previous sheet.
    return axis, sign, tuple(math.floor(float(sun_dir[a]) / along) for a in (u, v))


def _beam_frame(sun_dir: np.ndarray, periodic_xy: bool, vec=None):
    """The sheet order of a beam towards ``sun_dir``: (perm, sign, along, resample), or None
    for a sun on the horizon of a periodic domain.  ``perm`` puts the sweep axis first, the
    sheets run in the light's direction (reversed when ``sign`` < 0), ``along`` = |sun_dir| on
    the axis, and ``resample(t, fill)`` moves a sheet's buffer by the beam's lateral offset per
    sheet (bilinear; ``fill`` enters from outside an open domain, periodic sides wrap).

    ``vec``: a traced direction near ``sun_dir`` (the sun as an unknown): ``along`` and the
    offsets' fractions follow it, the sheet order and the offsets' whole voxels stay
    ``sun_dir``'s (a fraction past [0, 1] extrapolates the bilinear weights linearly)."""
    key = beam_frame_key(sun_dir, periodic_xy)
    if key is None:
        return None
    axis, sign, ipart = key
    along = float(abs(sun_dir[axis]))  # Python floats below: weak-typed, keep σ's dtype
    u, v = face_plane_axes(axis)
    src = [float(sun_dir[u]) / along, float(sun_dir[v]) / along]  # offsets to sample, in voxels
    frac = [x - i for x, i in zip(src, ipart)]
    if vec is not None:
        along = jnp.abs(vec[axis])
        frac = [vec[u] / along - ipart[0], vec[v] / along - ipart[1]]
    lateral_periodic = (periodic_xy and u in (0, 1), periodic_xy and v in (0, 1))

    def resample(t, fill):
        for ax, (i0, f, per) in enumerate(zip(ipart, frac, lateral_periodic)):
            n = t.shape[ax]
            pad_lo, pad_hi = max(0, -i0), max(0, i0 + 1)
            widths = [(0, 0), (0, 0)]
            widths[ax] = (pad_lo, pad_hi)
            if per:
                tp = jnp.pad(t, widths, mode="wrap")
            else:
                tp = jnp.pad(t, widths, constant_values=fill)
            a0 = jax.lax.slice_in_dim(tp, pad_lo + i0, pad_lo + i0 + n, axis=ax)
            a1 = jax.lax.slice_in_dim(tp, pad_lo + i0 + 1, pad_lo + i0 + 1 + n, axis=ax)
            if isinstance(f, float):
                t = a0 if f == 0.0 else (1.0 - f) * a0 + f * a1
            else:
                f = f.astype(t.dtype)
                t = (1.0 - f) * a0 + f * a1
        return t

    return (axis, u, v), sign, along, resample


def sun_path(density, sun_dir, h, periodic_xy):
    """∫ density ds from every node towards the sun, solids ignored (nx, ny, nz): the additive
    twin of :func:`sun_transmittance`'s point value (half of each node's segment, resampled
    sheet by sheet the same way; nothing enters from outside an open domain), so that
    e^(−σ·path) is that transmittance for a uniform extinction σ per unit density.  Linear in
    the density; exact for a uniform one (the cameras interpolate the path, not e^(−σ·path))."""
    sun_dir = np.asarray(sun_dir, dtype=np.float64)
    frame = _beam_frame(sun_dir, periodic_xy)
    if frame is None:
        return jnp.full_like(density, NO_SUN_PATH)  # no direct sun
    perm, sign, along, resample = frame
    half = jnp.transpose(density, perm) * (h / (2.0 * along))
    if sign < 0:
        half = half[::-1]

    def step(p_out_prev, half_k):
        p_arr = resample(p_out_prev, 0.0) + half_k
        return p_arr + half_k, p_arr

    _, out = jax.lax.scan(step, jnp.zeros(half.shape[1:], half.dtype), half)
    if sign < 0:
        out = out[::-1]
    return jnp.transpose(out, np.argsort(perm))


def sun_transmittance(sigma_t, opaque, sun_dir, h, periodic_xy, average=False, slope=False,
                      vec=None):
    """Transmittance of the direct sun beam arriving at every node.

    sigma_t: (nx, ny, nz) extinction per unit length (ζ+γ)·density; opaque: (nx, ny, nz) bool
    (SOLID nodes); sun_dir: unit vector *towards* the sun (static); h: voxel size;
    average: also return the transmittance averaged over each node's segment of the beam.
    Returns (nx, ny, nz) in [0, 1] (the point value at the node), and with ``average`` the pair
    (point, segment average).  The average is what the node's first-collision source needs:
    σ_t·F·average is exactly the power the beam loses in the node's segment, whatever its
    optical depth (the point value is e^(−τ/2) of the segment's entry value: 6e-4 of it at
    τ = 15, where the average is 0.067, and the node's source vanished in thick fog).
    slope: also return h∇T̄ (nx, ny, nz, 3), the segment average's change per lattice spacing
    along the beam, from the first moment of e^(−s) over the node's segment (the linear-source
    scheme's first-collision slope: in a thick node the beam's power is spent near its entry).
    vec: the sun's direction traced (an unknown), near ``sun_dir`` (``_beam_frame``).
    """
    sun_dir = np.asarray(sun_dir, dtype=np.float64)
    frame = _beam_frame(sun_dir, periodic_xy, vec)
    if frame is None:  # sun exactly on the horizon of a periodic domain: no direct light
        return jnp.zeros_like(sigma_t)
    perm, sign, along, resample = frame
    s = jnp.transpose(sigma_t, perm)
    o = jnp.transpose(opaque, perm)
    if sign < 0:
        s, o = s[::-1], o[::-1]

    if not isinstance(along, float):
        along = along.astype(s.dtype)
    tau = s * (h / (2.0 * along))  # half-segment optical depth per node
    half = jnp.exp(-tau)
    mean = one_minus_exp_over(2.0 * tau)  # mean of e^(−s) over the node's whole segment
    # first moment over the segment, as a change per lattice spacing along the beam (segment
    # length h/along)
    # (only with ``slope``: the default program carries no third output)
    factors = (mean,) + ((linear_source_terms(2.0 * tau)[2] * (_MOMENT_TO_CHANGE * along),)
                         if slope else ())

    def step(t_out_prev, sheet):
        opaque_k, half_k, *factor_k = sheet
        t_in = resample(t_out_prev, 1.0)  # no fog outside an open domain
        t_arr = t_in * half_k
        t_out = jnp.where(opaque_k, 0.0, t_arr * half_k)
        return t_out, (t_arr,) + tuple(t_in * f for f in factor_k)

    init = jnp.ones(s.shape[1:], s.dtype)
    _, out = jax.lax.scan(step, init, (o, half) + factors)
    if sign < 0:
        out = jax.tree.map(lambda a: a[::-1], out)
    t_arr, t_avg, *t_first = (jnp.transpose(a, np.argsort(perm)) for a in out)
    if slope:  # along the light's propagation, −sun_dir
        light = -(sun_dir if vec is None else vec)
        grad = t_first[0][..., None] * jnp.asarray(light, t_first[0].dtype)
        return t_arr, t_avg, jnp.where(opaque[..., None], 0.0, grad)
    return (t_arr, t_avg) if average else t_arr


def sky_uncollided(sigma_t, opaque, normal, sky_dirs, sky_wts, h, periodic_xy, harm=None,
                   slope=False, native=None):
    """Uncollided sky light at every node: Σ_k w_k T_k and Σ_k w_k T_k max(0, ω_k·N), and with
    ``harm`` ((n_dirs, K) basis values at each direction's propagation direction) the moments
    Σ_k w_k T̄_k Ỹ(−ω_k) (nx, ny, nz, K) as a third result; with ``slope`` the fluence's
    change per lattice spacing h∇(Σ_k w_k T̄_k) (nx, ny, nz, 3) last (each direction's T̄
    changing along its own beam, as ``sun_transmittance``'s).

    The directions are grouped by their dominant axis and each group is swept sheet by sheet
    along that axis, so the lateral offset per sheet is at most one voxel: marching every
    direction along z let shallow sky light jump over walls a few voxels thick (measured: the
    floor of ring-box's open box got 27% too much sky).  Laterally periodic domains sweep along
    z only (their x, y sweeps would never start).

    native: None (default) takes the values from the native kernel (``_native.sky_pass``, the
    same arithmetic in one pass per sheet; derivatives from this XLA program) on a CPU where
    it is built, for an open domain; False always runs XLA's.
    """
    dirs = np.asarray(sky_dirs, np.float64)
    wts = np.asarray(sky_wts, np.float64)
    if native is not False and not periodic_xy and _native.serves(sigma_t.dtype):
        cfg = (tuple(map(tuple, dirs.tolist())), tuple(wts.tolist()), float(h),
               None if harm is None else tuple(map(tuple, np.asarray(harm, np.float64).tolist())),
               bool(slope))
        return _sky_native(sigma_t, opaque, normal, cfg)
    if periodic_xy:
        groups = {(2, 1): np.arange(len(dirs))}
    else:
        groups = _sky_groups(dirs)
    flu = jnp.zeros_like(sigma_t)
    irr = jnp.zeros_like(sigma_t)
    mom = None if harm is None else jnp.zeros(sigma_t.shape + (harm.shape[1],), sigma_t.dtype)
    grad = jnp.zeros(sigma_t.shape + (3,), sigma_t.dtype) if slope else None
    for (a, sgn), idx in groups.items():
        idx = np.asarray(idx)
        u, v = face_plane_axes(a)
        perm = (u, v, a)  # sweep axis last, as z
        d = dirs[idx][:, perm] * np.array([1.0, 1.0, sgn])
        flip = (lambda x: x[:, :, ::-1]) if sgn < 0 else (lambda x: x)  # noqa: E731
        st = flip(jnp.transpose(sigma_t, perm))
        op = flip(jnp.transpose(opaque, perm))
        nm = normal[..., list(perm)] * jnp.asarray([1.0, 1.0, float(sgn)], normal.dtype)
        nm = flip(jnp.transpose(nm, perm + (3,)))
        out = _sheet_sweep(st, op, nm, d, wts[idx], h, periodic_xy,
                           harm=None if harm is None else np.asarray(harm)[idx], slope=slope)
        inv = np.argsort(perm)
        flu = flu + jnp.transpose(flip(out[0]), inv)
        irr = irr + jnp.transpose(flip(out[1]), inv)
        if harm is not None:
            mom = mom + jnp.transpose(flip(out[2]), tuple(inv) + (3,))
        if slope:  # the sweep frame's (u, v, ±a) components back to the world's
            g = jnp.transpose(flip(out[-1]), tuple(inv) + (3,)) * jnp.asarray(
                [1.0, 1.0, float(sgn)], grad.dtype)
            grad = grad + g[..., np.argsort(perm)]
    res = (flu, irr) if harm is None else (flu, irr, mom)
    return res + (grad,) if slope else res


def _sheet_sweep(sigma_t, opaque, normal, sky_dirs, sky_wts, h, periodic_xy, by_shift=None,
                 harm=None, slope=False):
    """Batched light-aligned sheet sweep along −z (the frame of :func:`sky_uncollided`).

    For each quadrature direction ω_k (towards the sky) the transmittance T_k(x) from the top
    of the domain (or from its open sides) to x is carried sheet by sheet from the top down,
    with bilinear resampling at the direction's lateral offset per sheet.  Returns per node
      fluence: Σ_k w_k T̄_k(x), T̄ averaged over the node's segment (×sky = the source's 4π·J)
      irradiance: Σ_k w_k T_k(x) max(0, ω_k·N(x))   (× sky = direct sky on a surface node).
    sigma_t, opaque: (nx, ny, nz); normal: (nx, ny, nz, 3); sky_dirs (K, 3) static.
    by_shift: resample by whole-sheet shifts (open domains whose offsets per sheet are within
    one voxel; None: whenever they are) or by gathers (False).
    harm: (K_dirs, K) basis values per direction: also return the moments Σ_k w_k T̄_k harm_k
    (nx, ny, nz, K), T̄ averaged like the fluence's.
    slope: also return the fluence's change per lattice spacing, Σ_k w_k h∂T̄_k along each
    direction's propagation (nx, ny, nz, 3), last.
    """
    nx, ny, nz = sigma_t.shape
    dirs = np.asarray(sky_dirs, np.float64)
    K = dirs.shape[0]
    off = dirs[:, :2] / dirs[:, 2:3]  # sample offset in the sheet above, in voxels
    i0 = np.floor(off).astype(np.int64)
    f = (off - i0).astype(np.float64)
    n_lat = (nx, ny)
    idx = []
    for ax in range(2):
        base = np.arange(n_lat[ax])[None, :] + i0[:, ax : ax + 1]  # (K, n)
        idx.append((base, base + 1))
    if periodic_xy:
        gidx = [tuple(b % n_lat[ax] for b in pair) for ax, pair in enumerate(idx)]
        pad = (0, 0)
    else:
        pad = tuple(int(max(np.abs(i0[:, ax]).max() + 2, 2)) for ax in range(2))
        gidx = [tuple(b + pad[ax] for b in pair) for ax, pair in enumerate(idx)]
    dt = sigma_t.dtype
    fx = jnp.asarray(f[:, 0], dt)[:, None, None]
    fy = jnp.asarray(f[:, 1], dt)[:, None, None]
    kk = np.arange(K)[:, None, None]
    (x0, x1), (y0, y1) = gidx
    x0, x1 = x0[:, :, None], x1[:, :, None]
    y0, y1 = y0[:, None, :], y1[:, None, :]
    path = jnp.asarray(h / (2.0 * dirs[:, 2]), dt)[:, None, None]  # half-sheet path length
    w = jnp.asarray(sky_wts, dt)
    wd = jnp.asarray(dirs, dt)
    wh = None if harm is None else jnp.asarray(np.asarray(sky_wts)[:, None] * harm, dt)
    # w_k · 12 ω_z · (−ω_k): a direction's first moment → its fluence's change per spacing
    wgrad = jnp.asarray(-np.asarray(sky_wts)[:, None] * _MOMENT_TO_CHANGE * dirs[:, 2:3] * dirs,
                        dt)

    # Each direction's lateral offset per sheet lies in [−1, 1] voxels when the directions are
    # grouped by dominant axis (open domains): then the bilinear resampling is a combination of
    # the same few whole-sheet shifts for every direction, with per-direction coefficients —
    # elementwise work XLA fuses, instead of four (K, nx, ny) gathers per sheet (fog-balls at
    # N = 128, M = 5: 3.4 → 2.6 s per pass, measured under load).  Shallow directions of a
    # periodic domain (offsets of many voxels) keep the gathers.
    shifts = [list(range(int(i0[:, ax].min()), int(i0[:, ax].max()) + 2)) for ax in range(2)]
    if by_shift is None:  # (False: the gathers, which the tests compare against)
        by_shift = max(len(sh) for sh in shifts) <= 4 and not periodic_xy
    coef = []
    for ax in range(2):
        c = np.zeros((len(shifts[ax]), K))
        for j, sh in enumerate(shifts[ax]):
            c[j] = np.where(i0[:, ax] == sh, 1.0 - f[:, ax], 0.0) + np.where(i0[:, ax] + 1 == sh,
                                                                          f[:, ax], 0.0)
        coef.append(jnp.asarray(c, dt)[:, :, None, None])

    def resample(t):
        if not periodic_xy:
            t = jnp.pad(t, ((0, 0), (pad[0], pad[0]), (pad[1], pad[1])), constant_values=1.0)
        if by_shift:
            for ax in range(2):  # x, then y (the y axis keeps its padding until its turn)
                n = n_lat[ax]
                parts = [jax.lax.slice_in_dim(t, pad[ax] + sh, pad[ax] + sh + n, axis=ax + 1)
                         for sh in shifts[ax]]
                t = sum(coef[ax][j] * part for j, part in enumerate(parts))
            return t
        a = t[kk, x0, y0] * (1 - fx) + t[kk, x1, y0] * fx
        b = t[kk, x0, y1] * (1 - fx) + t[kk, x1, y1] * fx
        return a * (1 - fy) + b * fy

    def step(t_prev, sheet):
        s_k, o_k, n_k = sheet  # (nx, ny), (nx, ny), (nx, ny, 3)
        tau = s_k[None] * path
        half = jnp.exp(-tau)
        t_in = resample(t_prev)
        t_arr = t_in * half
        t_out = jnp.where(o_k[None], 0.0, t_arr * half)
        # the source's fluence: averaged over the node's segment (see sun_transmittance)
        t_avg = t_in * one_minus_exp_over(2.0 * tau)
        flu = jnp.einsum("kij,k->ij", t_avg, w)
        cos = jnp.maximum(jnp.einsum("ijc,kc->kij", n_k, wd), 0.0)
        irr = jnp.einsum("kij,k->ij", t_arr * cos, w)
        res = (flu, irr)
        if wh is not None:
            res = res + (jnp.einsum("kij,kc->ijc", t_avg, wh),)
        if slope:  # first moment → change per spacing along −ω_k (segment length h/ω_z)
            first = t_in * linear_source_terms(2.0 * tau)[2]
            res = res + (jnp.where(o_k[..., None], 0.0,
                                   jnp.einsum("kij,kc->ijc", first, wgrad)),)
        return t_out, res

    # sheets from the top (z = nz-1) down
    xs = (jnp.moveaxis(sigma_t, 2, 0)[::-1], jnp.moveaxis(opaque, 2, 0)[::-1],
          jnp.moveaxis(normal.astype(dt), 2, 0)[::-1])
    init = jnp.ones((K, nx, ny), dt)
    _, out = jax.lax.scan(step, init, xs)
    return tuple(jnp.moveaxis(a[::-1], 0, 2) for a in out)


def _sky_groups(dirs: np.ndarray) -> dict:
    """The sky directions of an open domain by the axis their sheets run along, {(axis, sign
    of ω on it): indices}, in the order :func:`sky_uncollided` adds their sums."""
    axis = np.argmax(np.abs(dirs), axis=1)
    sign = np.where(dirs[np.arange(len(dirs)), axis] > 0, 1, -1)
    groups: dict = {}
    for k, key in enumerate(zip(axis.tolist(), sign.tolist())):
        groups.setdefault(key, []).append(k)
    return groups


def _sky_table(cfg, dt) -> tuple[np.ndarray, np.ndarray | None]:
    """The native sky pass's per-direction tables (``_native.sky_pass``) from ``_sky_native``'s
    static configuration (directions, weights, h, harm, slope), grouped as
    :func:`sky_uncollided` groups them: (K, 12) each group's axis and sign, the offsets' whole
    voxels and fractions per sheet along its two other axes (computed in float64 as
    ``_sheet_sweep`` does, then cast), the half-segment path, the weight and ω; and the
    channels' weights (K, NH + 3) or None: the moments' w_k·harm_k, the slope's −12 w_k
    |ω_axis| ω_k (``_sheet_sweep``'s wgrad, back in the world's axes)."""
    dirs, wts, h = np.asarray(cfg[0], np.float64), np.asarray(cfg[1], np.float64), cfg[2]
    harm, slope = (None if cfg[3] is None else np.asarray(cfg[3], np.float64)), cfg[4]
    rows, chans = [], []
    for (a, sgn), idx in _sky_groups(dirs).items():
        u, v = face_plane_axes(a)
        d = dirs[idx][:, (u, v, a)] * np.array([1.0, 1.0, float(sgn)])
        off = d[:, :2] / d[:, 2:3]
        i0 = np.floor(off)
        n = len(idx)
        rows.append(np.concatenate([np.full((n, 1), a), np.full((n, 1), sgn), i0, off - i0,
                                    (h / (2.0 * d[:, 2]))[:, None], wts[idx][:, None],
                                    dirs[idx], np.zeros((n, 1))], 1))
        ch = [wts[idx][:, None] * harm[idx]] if harm is not None else []
        if slope:
            ch.append(-wts[idx][:, None] * _MOMENT_TO_CHANGE * d[:, 2:3] * dirs[idx])
        chans.append(np.concatenate(ch, 1) if ch else np.zeros((n, 0)))
    chan = np.concatenate(chans)
    return np.concatenate(rows).astype(dt), (chan.astype(dt) if chan.shape[1] else None)


@functools.partial(jax.custom_jvp, nondiff_argnums=(3,))
def _sky_native(sigma_t, opaque, normal, cfg):
    """:func:`sky_uncollided`'s results (fluence, irradiance[, moments][, slope]) from the
    native kernel (an open domain); ``cfg`` = (directions, weights, h, harm or None, slope) as
    tuples (static).  Its derivatives are XLA's program's (the rule below), as the sweep's
    are."""
    dt = sigma_t.dtype
    table, chan = _sky_table(cfg, dt)
    nh = 0 if cfg[3] is None else len(cfg[3][0])
    flu, irr, mom = _native.sky_pass(sigma_t, opaque, normal.astype(dt), table, chan, nh,
                                     cfg[4])
    return ((flu, irr) + ((mom[..., :nh],) if nh else ())
            + ((mom[..., nh:],) if cfg[4] else ()))


@_sky_native.defjvp
def _sky_native_jvp(cfg, primals, tangents):
    dirs, wts, h = np.asarray(cfg[0]), np.asarray(cfg[1]), cfg[2]
    harm = None if cfg[3] is None else np.asarray(cfg[3])
    out = _sky_native(*primals, cfg)

    def xla(sigma_t, opaque, normal):
        return sky_uncollided(sigma_t, opaque, normal, dirs, wts, h, False, harm=harm,
                              slope=cfg[4], native=False)

    _, t_out = jax.jvp(xla, primals, tangents)
    return out, t_out
