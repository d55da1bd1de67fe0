"""The splat's set-up (host, once per scene and camera): the sheets, their density
footprints, the shadow-buffer frame, the polygons' eye and light rasterization, and the
scattering kernels' static binning.  See ``_pass.py`` for the method and the paper.
"""

from __future__ import annotations

import math
import time
from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ..._errors import SceneError
from ..._numerics import trilinear
from ...geometry._hits import first_hits
from ...geometry._rays import cast_rays
from ...scene._description import Scene
from .._camera import camera_basis, camera_rays
from ...geometry._directions import sky_quadrature


# --------------------------------------------------------------------------------------------
# small helpers
# --------------------------------------------------------------------------------------------
def _unit(v):
    v = np.asarray(v, np.float64)
    return v / np.linalg.norm(v)


def _plane_basis(s):
    ref = np.array([0.0, 0.0, 1.0]) if abs(s[2]) < 0.9 else np.array([0.0, 1.0, 0.0])
    a = _unit(np.cross(ref, s))
    return a, np.cross(s, a)


_trilinear_jit = jax.jit(trilinear)


@jax.jit
def _segment_integrals(vol, dup, origin, h, o, d, t0, t1, gl_x, gl_w):
    """∫ density over [t0, t1] of rays o + t·d (Gauss–Legendre), and the upward column density
    at the segment midpoint.  o, d: (P, 3); t0, t1: (P,)."""
    ln = jnp.maximum(t1 - t0, 0.0)
    tq = t0[None] + ln[None] * gl_x[:, None]  # (Q, P)
    pts = o[None] + tq[..., None] * d[None]
    dens = trilinear(vol, origin, h, pts)  # (Q, P)
    mid = o + (0.5 * (t0 + t1))[:, None] * d
    return ln * (gl_w[:, None] * dens).sum(0), trilinear(dup, origin, h, mid), mid


# --------------------------------------------------------------------------------------------
# the static sheets of one camera
# --------------------------------------------------------------------------------------------
class SheetFrame(NamedTuple):
    """Where one camera's sheets lie (static): sheet k spans s·x ∈ z_lo + [k, k+1]·dz; the
    shadow buffer's texel (i, j) is the light ray through the point (u_min + (i + ½)·texel)·a
    + (v_min + (j + ½)·texel)·b of the plane s·x = 0, travelling along L (= −sun_dir)."""

    s: tuple[float, float, float]
    a: tuple[float, float, float]
    b: tuple[float, float, float]
    L: tuple[float, float, float]
    z_lo: float
    dz: float
    u_min: float
    v_min: float
    texel: float


class SheetGeometry(eqx.Module):
    """Everything about one camera's splat pass that does not depend on Params.

    K sheets of thickness ``dz`` along ``s`` from ``z_lo``; a shadow buffer of (hs, ws) texels of
    size ``texel``; P = H·W·S eye samples.  Arrays: ``light_D`` (K + W + 1, hs, ws) density
    footprints of the light rays per slab (zero past K); ``occ_first``/``occ_sheets`` (hs, ws):
    slab of the first polygon along each light ray and how many slabs it stays opaque;
    ``eye_D``/``eye_up`` (K, P): eye footprints and upward column density at the segment
    midpoints; ``eye_uv`` (K, P, 2): shadow-buffer coordinates of the midpoints; per-sample
    polygon data ``hit_*`` (P,); kernels' static binning matrices.
    """

    light_D: jax.Array
    occ_first: jax.Array
    occ_sheets: jax.Array
    eye_D: jax.Array
    eye_up: jax.Array
    eye_uv: jax.Array
    eye_dir: jax.Array  # (P, 3)
    hit_sheet: jax.Array  # (P,) int: slab of the polygon hit, -1 before the scan, K after, K+1: none
    hit_frac: jax.Array  # (P,) fraction of its slab the light crossed to reach the hit
    hit_uv: jax.Array  # (P, 2)
    hit_shape: jax.Array  # (P,) int
    hit_cos_sun: jax.Array  # (P,) max(0, n·sun_dir)
    hit_cos_back: jax.Array  # (P,) max(0, −n·sun_dir)
    hit_sky: jax.Array  # (P,) (1 + n_z)/2: the sky's share of a Lambertian surface's hemisphere
    hit_vis: jax.Array  # (P,) 1 where the shadow ray to the sun misses every polygon
    hit_up: jax.Array  # (P,) upward column density above the hit
    sky_escape: jax.Array  # (P,) 1 where the ray hits nothing and points up
    fwd_bins: jax.Array  # (Nq, nk²) forward-hemisphere directions → kernel texels
    fwd_mu: jax.Array  # (Nq,) cos angle to L;  fwd_w: solid-angle weights
    fwd_w: jax.Array
    back_bins: jax.Array
    back_mu: jax.Array
    back_w: jax.Array
    pen_kernel: jax.Array  # (nk, nk) sun-disk footprint over one sheet (sums to 1)
    sky_dirs: jax.Array  # (Nsky, 3) and weights for the in-scattered sky
    sky_w: jax.Array
    K: int = eqx.field(static=True)
    W: int = eqx.field(static=True)
    radius: int = eqx.field(static=True)
    front_to_back: bool = eqx.field(static=True)
    image_hw: tuple[int, int] = eqx.field(static=True)
    samples: int = eqx.field(static=True)
    buffer_hw: tuple[int, int] = eqx.field(static=True)
    sun_dir: tuple[float, float, float] = eqx.field(static=True)
    forward: bool = eqx.field(static=True)
    soft: bool = eqx.field(static=True)
    frame: SheetFrame = eqx.field(static=True)


def _hemisphere_bins(s, L, a, b, step, texel, radius, sign, n_mu=32, n_phi=32):
    """Directions of one hemisphere about L (sign +1 forward, −1 backward) and where each lands
    on the next (previous) sheet relative to the light ray it left, as bilinear weights on the
    (2R+1)² kernel texels.  Returns (bins (Nq, nk²), mu (Nq,), weights (Nq,))."""
    x, w = np.polynomial.legendre.leggauss(n_mu)
    mu = 0.5 * (x + 1.0)  # cos angle to ±L in (0, 1)
    wmu = 0.5 * w
    phi = (np.arange(n_phi) + 0.5) * 2 * np.pi / n_phi
    m, p = np.meshgrid(mu, phi, indexing="ij")
    sn = np.sqrt(1 - m**2)
    axis = sign * L
    u1, u2 = _plane_basis(axis)
    dirs = (m[..., None] * axis + sn[..., None] * (np.cos(p)[..., None] * u1
                                                   + np.sin(p)[..., None] * u2)).reshape(-1, 3)
    wts = np.repeat(wmu * 2 * np.pi / n_phi, n_phi)
    sd = dirs @ s
    sL = float(s @ L)
    # from sheet k to k + sign: plane distance sign·step along s
    with np.errstate(divide="ignore", invalid="ignore"):
        t = sign * step / sd
        off = t[:, None] * dirs - (sign * step / sL) * L[None]
    bad = ~(t > 0) | ~np.isfinite(t)
    ou, ov = off @ a / texel, off @ b / texel
    r = np.hypot(ou, ov)
    lim = radius + 0.0
    scale = np.where(r > lim, lim / np.maximum(r, 1e-300), 1.0)
    ou, ov = np.where(bad, 0, ou * scale), np.where(bad, 0, ov * scale)
    # bad directions (never reach the neighbouring sheet, s·ω of the wrong sign) go to the rim
    # in their own direction: they still leave the ray's texel
    nk = 2 * radius + 1
    bins = np.zeros((len(dirs), nk * nk))
    iu0, iv0 = np.floor(ou).astype(int), np.floor(ov).astype(int)
    fu, fv = ou - iu0, ov - iv0
    for du in (0, 1):
        for dv in (0, 1):
            wgt = (fu if du else 1 - fu) * (fv if dv else 1 - fv)
            iu = np.clip(iu0 + du + radius, 0, nk - 1)
            iv = np.clip(iv0 + dv + radius, 0, nk - 1)
            np.add.at(bins, (np.arange(len(dirs)), iu * nk + iv), wgt)
    return bins, m.reshape(-1), wts


def _penumbra_kernel(s, L, a, b, step, texel, radius, angular_radius_deg, n=24):
    """Uniform sun disk of the given angular radius, projected over one sheet spacing onto the
    buffer, bilinear-binned on a (2R+1)² kernel; sums to 1."""
    nk = 2 * radius + 1
    k = np.zeros((nk, nk))
    alpha = math.radians(angular_radius_deg)
    if alpha <= 0:
        k[radius, radius] = 1.0
        return k
    u1, u2 = _plane_basis(L)
    # stratified points on the disk of directions
    g = (np.arange(n) + 0.5) / n * 2 - 1
    gx, gy = np.meshgrid(g, g, indexing="ij")
    inside = gx**2 + gy**2 <= 1
    gx, gy = gx[inside], gy[inside]
    t = math.tan(alpha)
    dirs = L[None] + t * (gx[:, None] * u1 + gy[:, None] * u2)
    dirs /= np.linalg.norm(dirs, axis=-1, keepdims=True)
    tt = step / (dirs @ s)
    off = tt[:, None] * dirs - (step / float(s @ L)) * L[None]
    ou = np.clip(off @ a / texel, -radius, radius)
    ov = np.clip(off @ b / texel, -radius, radius)
    iu0, iv0 = np.floor(ou).astype(int), np.floor(ov).astype(int)
    fu, fv = ou - iu0, ov - iv0
    for du in (0, 1):
        for dv in (0, 1):
            wgt = (fu if du else 1 - fu) * (fv if dv else 1 - fv)
            np.add.at(k, (np.clip(iu0 + du + radius, 0, nk - 1),
                          np.clip(iv0 + dv + radius, 0, nk - 1)), wgt)
    return k / k.sum()


def build_sheets(scene: Scene, lattice, tris, camera, *, sheets: int | None, supersample: int,
               back_window: int, forward: bool, soft: bool, shadow_texel: float | None,
               quadrature: int, kernel_radius: int, occluder_thickness: str,
               thickness_scale: float) -> tuple[SheetGeometry, dict]:
    """The static sheets of one camera's pass (host side) and a summary of them."""
    t_start = time.perf_counter()
    sun = scene.sun
    sdir = _unit(sun.direction)
    L = -sdir
    e, _, _ = camera_basis(camera)
    f2b = bool(e @ L >= 0.0)
    s = _unit(L + e) if f2b else _unit(L - e)
    a, b = _plane_basis(s)
    sL = float(s @ L)
    h = float(lattice.h)
    origin = np.asarray(lattice.origin, np.float64)
    dens = np.asarray(lattice.density, np.float32)
    # upward column density ∫_z^top density dz (midpoint rule), for the ambient sky
    dup = (np.cumsum(dens[:, :, ::-1], axis=2)[:, :, ::-1] - 0.5 * dens) * h
    pos = lattice.node_positions()

    # --- the sheets: range along s of the volume (and of the polygons for soft shadows) -------
    zs = []
    occupied = dens > 0
    if occupied.any():
        zv = pos[occupied] @ s
        zs += [zv.min() - h, zv.max() + h]  # tent kernel support: one voxel either side
    if len(tris) and (soft or not zs):
        zp = tris.corners.reshape(-1, 3) @ s
        zs += [zp.min() - 1e-6, zp.max() + 1e-6]
    if not zs:
        raise SceneError(f"scene '{scene.title}' has neither fog nor shapes: nothing to splat")
    z_lo, z_hi = min(zs), max(zs)
    K = int(sheets) if sheets else max(1, int(math.ceil((z_hi - z_lo) / h)))
    dz = (z_hi - z_lo) / K
    W = int(back_window)

    # --- the shadow buffer: light rays u·a + v·b + t·L covering the lattice box and polygons --
    lo = origin
    hi = origin + h * np.asarray(lattice.shape)
    box = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1])
                    for z in (lo[2], hi[2])])
    pts = np.concatenate([box, tris.corners.reshape(-1, 3)]) if len(tris) else box
    proj = pts - (pts @ s / sL)[:, None] * L[None]
    texel = float(shadow_texel or h)
    R = int(kernel_radius)
    pad = (R + 1) * texel
    u_min, v_min = (proj @ a).min() - pad, (proj @ b).min() - pad
    hs = int(math.ceil(((proj @ a).max() + pad - u_min) / texel))
    ws = int(math.ceil(((proj @ b).max() + pad - v_min) / texel))
    uu = u_min + (np.arange(hs) + 0.5) * texel
    vv = v_min + (np.arange(ws) + 0.5) * texel
    P0 = uu[:, None, None] * a + vv[None, :, None] * b  # (hs, ws, 3) on the plane s·x = 0

    def to_uv(x):
        """Continuous buffer index coordinates (…, 2) of points x (…, 3) (projected along L)."""
        xp = x - (x @ s / sL)[..., None] * L
        return np.stack([(xp @ a - u_min) / texel - 0.5, (xp @ b - v_min) / texel - 0.5], -1)

    gl_x, gl_w = np.polynomial.legendre.leggauss(int(quadrature))
    gl_x, gl_w = jnp.asarray(0.5 * (gl_x + 1)), jnp.asarray(0.5 * gl_w)
    vol = jnp.asarray(dens)
    dupj = jnp.asarray(dup, jnp.float32)
    org = jnp.asarray(origin, jnp.float32)

    # light footprints per slab: t along L with s·x = z ⇒ t = z / (s·L) from P0
    o_l = jnp.asarray(P0.reshape(-1, 3), jnp.float32)
    d_l = jnp.broadcast_to(jnp.asarray(L, jnp.float32), o_l.shape)
    light_D = np.zeros((K + W + 1, hs, ws), np.float32)
    for k in range(K):
        t0 = np.full(hs * ws, (z_lo + k * dz) / sL, np.float32)
        t1 = np.full(hs * ws, (z_lo + (k + 1) * dz) / sL, np.float32)
        D, _, _ = _segment_integrals(vol, dupj, org, h, o_l, d_l, jnp.asarray(t0),
                                     jnp.asarray(t1), gl_x, gl_w)
        light_D[k] = np.asarray(D).reshape(hs, ws)

    # light z-buffer: the first polygon along each texel's light ray, and its thickness
    far = 4.0 * float(np.linalg.norm(hi - lo)) + 4.0 * float(np.abs(pts).max())
    never = K + W + 10
    occ_first = np.full((hs, ws), never, np.int32)
    occ_sheets = np.zeros((hs, ws), np.int32)
    if len(tris):
        start = P0.reshape(-1, 3) + ((z_lo - far) / sL) * L
        tl, fl, _, _ = cast_rays(tris, start, np.broadcast_to(L, start.shape))
        hitl = np.isfinite(tl)
        xl = start + np.where(hitl, tl, 0.0)[:, None] * L  # no inf·0 where a ray misses
        zl = xl @ s
        first = np.where(hitl, np.floor((zl - z_lo) / dz), never).astype(np.int64)
        occ_first = np.clip(first, -1, never).astype(np.int32).reshape(hs, ws)
        dl = dz / sL  # path along L per slab
        if occluder_thickness == "exact":
            # the occluder's own extent along the light: the next hit if it is the same shape
            t2, f2, _, _ = cast_rays(tris, np.where(hitl[:, None], xl, start),
                                     np.broadcast_to(L, start.shape), t_min=1e-7)
            same = hitl & (f2 >= 0) & (tris.shape[np.maximum(f2, 0)] == tris.shape[
                np.maximum(fl, 0)])
            thick = np.where(same, t2, dl)
        else:
            # §5: a thickness proportional to the reciprocal of the gradient of the light depth
            depth = np.where(hitl, tl, np.nan).reshape(hs, ws)
            gu, gv = np.gradient(depth, texel)
            grad = np.hypot(np.nan_to_num(gu, nan=np.inf), np.nan_to_num(gv, nan=np.inf))
            thick = np.where(hitl, thickness_scale * texel / np.maximum(grad.reshape(-1), 1e-6),
                             dl)
            thick = np.minimum(thick, np.linalg.norm(hi - lo))
        occ_sheets = np.where(hitl, np.maximum(1, np.ceil(thick / dl)), 0).astype(
            np.int32).reshape(hs, ws)

    # --- eye rays, polygons w.r.t. the eye ---------------------------------------------------
    o, d = camera_rays(camera, supersample)
    H, Wd, S, _ = o.shape
    o, d = o.reshape(-1, 3), d.reshape(-1, 3)
    Pn = len(o)
    # the eye's z-buffer and the shadow test, exactly: the first hit on the exact shapes (the
    # same hits as the sweep's cameras) and a shadow ray towards the sun from it
    eh = first_hits(scene, o, d)
    th, hit, n = eh.t, eh.hit, eh.normal
    xh = o + np.where(hit, th, 0.0)[:, None] * d
    vis = np.ones(Pn)
    if hit.any():
        eps = 1e-7 * float(np.linalg.norm(hi - lo))
        vis[hit] = (~first_hits(scene, xh[hit] + eps * n[hit],
                                np.broadcast_to(sdir, (hit.sum(), 3)), t_min=eps).hit
                    ).astype(float)
    zh = xh @ s
    ksh = np.floor((zh - z_lo) / dz)
    hit_sheet = np.where(hit, np.clip(ksh, -1, K), K + 1).astype(np.int32)
    hit_frac = np.where(hit, np.clip((zh - z_lo) / dz - ksh, 0, 1), 0.0)
    hit_up = np.asarray(_trilinear_jit(dupj, org, h, jnp.asarray(xh, jnp.float32)))

    # eye footprints per slab, clipped to [0, t_hit]
    o_j, d_j = jnp.asarray(o, jnp.float32), jnp.asarray(d, jnp.float32)
    so, sd = o @ s, d @ s
    eye_D = np.zeros((K, Pn), np.float32)
    eye_up = np.zeros((K, Pn), np.float32)
    eye_uv = np.zeros((K, Pn, 2), np.float32)
    for k in range(K):
        ta = (z_lo + k * dz - so) / sd
        tb = (z_lo + (k + 1) * dz - so) / sd
        t0 = np.maximum(np.minimum(ta, tb), 0.0)
        t1 = np.minimum(np.maximum(ta, tb), th)
        t1 = np.maximum(t1, t0)
        D, up, mid = _segment_integrals(vol, dupj, org, h, o_j, d_j, jnp.asarray(t0, jnp.float32),
                                        jnp.asarray(t1, jnp.float32), gl_x, gl_w)
        eye_D[k], eye_up[k] = np.asarray(D), np.asarray(up)
        eye_uv[k] = to_uv(np.asarray(mid, np.float64))

    fb, fmu, fw = _hemisphere_bins(s, L, a, b, dz, texel, R, +1)
    bb, bmu, bw = _hemisphere_bins(s, L, a, b, dz, texel, R, -1)
    pen = _penumbra_kernel(s, L, a, b, dz, texel, R, sun.angular_radius_deg if soft else 0.0)
    sky_d, sky_w = sky_quadrature(8, 16)
    info = {
        "sheets": K, "sheet_spacing": dz, "half_way": s.tolist(),
        "order": "front-to-back" if f2b else "back-to-front",
        "shadow_buffer": [hs, ws], "texel": texel, "back_window": W,
        "regions": {"front": int((hit_sheet == -1).sum()), "inside": int(
            ((hit_sheet >= 0) & (hit_sheet < K)).sum()), "behind": int((hit_sheet == K).sum())},
        "setup_s": time.perf_counter() - t_start,
        # the geometry, for light_at: sheet k spans s·x ∈ z_lo + [k, k+1]·dz; a point's texel
        # coordinates are those of its projection along L onto the plane s·x = 0
        "geometry": {"s": s.tolist(), "a": a.tolist(), "b": b.tolist(), "L": L.tolist(),
                     "z_lo": float(z_lo), "dz": float(dz), "u_min": float(u_min),
                     "v_min": float(v_min)},
    }
    f32 = lambda x: jnp.asarray(x, jnp.float32)  # noqa: E731
    return SheetGeometry(
        light_D=f32(light_D), occ_first=jnp.asarray(occ_first), occ_sheets=jnp.asarray(occ_sheets),
        eye_D=f32(eye_D), eye_up=f32(eye_up), eye_uv=f32(eye_uv), eye_dir=f32(d),
        hit_sheet=jnp.asarray(hit_sheet), hit_frac=f32(hit_frac), hit_uv=f32(to_uv(xh)),
        hit_shape=jnp.asarray(np.where(hit, eh.shape, 0).astype(np.int32)),
        hit_cos_sun=f32(np.maximum(0.0, n @ sdir)), hit_cos_back=f32(np.maximum(0.0, -(n @ sdir))),
        hit_sky=f32((1.0 + n[:, 2]) / 2.0), hit_vis=f32(vis), hit_up=f32(hit_up),
        sky_escape=f32((~hit) & (d[:, 2] > 0)),
        fwd_bins=f32(fb), fwd_mu=f32(fmu), fwd_w=f32(fw),
        back_bins=f32(bb), back_mu=f32(bmu), back_w=f32(bw), pen_kernel=f32(pen),
        sky_dirs=f32(sky_d), sky_w=f32(sky_w),
        K=K, W=W, radius=R, front_to_back=f2b, image_hw=(H, Wd), samples=S,
        buffer_hw=(hs, ws), sun_dir=tuple(float(x) for x in sdir), forward=bool(forward),
        soft=bool(soft),
        frame=SheetFrame(tuple(map(float, s)), tuple(map(float, a)), tuple(map(float, b)),
                         tuple(map(float, L)), float(z_lo), float(dz), float(u_min),
                         float(v_min), float(texel)),
    ), info
