"""The splat solver: Zhang & Crawfis, *Light propagation for mixed polygonal and volumetric data
using splatting* (``shared/papers/zhang-crawfis-splatting-mixed-polygon-volume.md``).

One pass over sheets renders one camera; no 3-D light volume is needed.

Sheets (§4.1, Figs. 5 and 14)
    The volume is sliced perpendicular to the half-way vector ``s`` between the eye vector ``e``
    (the camera's forward axis) and the light vector ``L = -sun_dir`` (the direction the light
    travels): ``s = normalize(L + e)`` when both point the same way (front-to-back rendering),
    else ``s = normalize(L - e)`` (back-to-front, the paper's Fig. 12).  Either way the sheets
    are processed in the light's order, ``lax.scan`` over sheets carrying the 2-D **shadow
    buffer** (light intensity per light ray) and the eye-aligned **image buffer** (radiance and
    transmittance per pixel).  Both |s·e| and |s·L| are ≥ cos 45°, so no ray crosses a sheet at
    a grazing angle.

Footprints
    Each voxel is a reconstruction kernel: the tent (trilinear) kernel of the lattice, whose sum
    over voxels is the trilinearly interpolated density.  A sheet buffer pixel holds the
    integral of Σ_v d_v·h(x − x_v) over its ray's segment inside the slab (the kernel's
    footprint clipped to the slab, §2.1 image-aligned sheet buffers), computed per pixel with
    Gauss–Legendre points (a gather: the sum a push splatter accumulates, evaluated in image
    order).  The density is static, so the sheets of footprints — for the eye rays of every
    pixel and for the light rays of every shadow-buffer texel — are built once per camera;
    the traced part scales them by ζ + γ.

The shadow buffer is parallel to the slices (§5): texel (i, j) is the light ray
``u_i·a + v_j·b + t·L`` (a, b spanning the slice plane), so moving the light from one sheet to
the next needs no resampling; a point x is looked up at its projection along L.

Light transport per sheet (§3), with T_k = exp(−τ_k) the transparency of slab k along the
light and s_k = a·(1 − T_k) = ζ·D_k·(1 − e^{−τ_k})/τ_k the fraction it scatters:
    direct            Fd_{k+1} = T_k·Fd_k                                  (attenuation)
    forward (eq. 3)   Fs_{k+1} = T_k·Fs_k + K_A ∗ (s_k·(Fd_k + Fs_k))      (I_k = g_{k-1} + T·I_{k-1})
    back (eq. 4)      b_k = K_B ∗ (s_k·F_k): light sent back towards the light; the back stream
                      reaching sheet k is B_k = Σ_{j=k+1}^{k+W} (Π_{k<i<j} T_i)·b_j over the W
                      stored sheets below it (the light pass runs W sheets ahead of the image);
                      sheet k adds what its back stream scatters forward, K_B ∗ (s_k·B_k), to
                      the stored intensity of the sheets below it ("bounce back").
K_A, K_B: the Henyey–Greenstein phase over the forward / backward hemisphere projected onto
the next / previous sheet (exact offsets of each quadrature direction, binned on the buffer
texels; traced in g), normalized to the hemisphere fractions so that K_A + K_B sum to 1.

Polygons (§4): rasterized w.r.t. the eye (shape, normal, depth) and the light (depth) once on
the host (``_raster``).  In sheet k a pixel whose eye ray hits a polygon in slab k integrates
the volume only up to the polygon (Fig. 7), then adds the polygon's shaded radiance and becomes
opaque; a light ray whose first polygon hit lies in slab k is blocked for the occluder's
thickness.  Polygons in front of / behind the volume's sheets (regions 1 / 3, Table 1) are shaded
before / after the scan with the shadow z-buffer / the final shadow buffer and the z-buffer, and
the sheets there are skipped (air).  Soft shadows (§5): the scan range covers the polygons too,
the direct light is convolved per sheet with the sun disk's footprint over one sheet spacing,
and occluders are solid for the paper's thickness estimate ∝ 1/|∇z_light|.

Departures (see README "Splat solver"): the sky is an ambient term; surfaces do not light each
other or the fog; every camera is its own pass (the half-way vector depends on the eye).
"""

from __future__ import annotations

import math
import time
import warnings

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ._camera import camera_basis, camera_rays, hg_phase
from ._errors import SceneError
from ._lattice import voxelize
from ._params import Params
from ._raster import cast_rays, hit_normals, scene_triangles
from ._render import Rendered
from ._scene import Scene
from ._uncollided import sky_quadrature

__all__ = ["SplatRenderer", "SplatPlan", "splat_plan"]

FOUR_PI = 4.0 * math.pi
#: slabs a polygon occluder starts late in the shadow buffer (see ``splat_pass.blocked``)
SHADOW_BIAS = 1


# --------------------------------------------------------------------------------------------
# small helpers
# --------------------------------------------------------------------------------------------
def _phi(tau):
    """(1 − e^{−τ})/τ, finite with finite derivatives at τ = 0."""
    small = jnp.abs(tau) < 1e-4
    ts = jnp.where(small, 1.0, tau)
    return jnp.where(small, 1.0 - tau / 2.0 + tau * tau / 6.0, -jnp.expm1(-ts) / ts)


def _unit(v):
    v = np.asarray(v, np.float64)
    return v / np.linalg.norm(v)


def _plane_basis(s):
    ref = np.array([0.0, 0.0, 1.0]) if abs(s[2]) < 0.9 else np.array([0.0, 1.0, 0.0])
    a = _unit(np.cross(ref, s))
    return a, np.cross(s, a)


@jax.jit
def _trilinear_jit(vol, origin, h, pts):
    return _trilinear_np_jax(vol, origin, h, pts)


def _trilinear_np_jax(vol, origin, h, pts):
    """Trilinear sample of a node-centred (nx, ny, nz) field at points (..., 3); 0 outside."""
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


@jax.jit
def _segment_integrals(vol, dup, origin, h, o, d, t0, t1, gl_x, gl_w):
    """∫ density over [t0, t1] of rays o + t·d (Gauss–Legendre), and the upward column density
    at the segment midpoint.  o, d: (P, 3); t0, t1: (P,)."""
    ln = jnp.maximum(t1 - t0, 0.0)
    tq = t0[None] + ln[None] * gl_x[:, None]  # (Q, P)
    pts = o[None] + tq[..., None] * d[None]
    dens = _trilinear_np_jax(vol, origin, h, pts)  # (Q, P)
    mid = o + (0.5 * (t0 + t1))[:, None] * d
    return ln * (gl_w[:, None] * dens).sum(0), _trilinear_np_jax(dup, origin, h, mid), mid


# --------------------------------------------------------------------------------------------
# the static plan of one camera
# --------------------------------------------------------------------------------------------
class SplatPlan(eqx.Module):
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


def splat_plan(scene: Scene, lattice, tris, camera, *, sheets: int | None, supersample: int,
               back_window: int, forward: bool, soft: bool, shadow_texel: float | None,
               quadrature: int, kernel_radius: int, occluder_thickness: str,
               thickness_scale: float) -> tuple[SplatPlan, dict]:
    """Build the static plan of one camera (host side) and a summary of it."""
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
    if len(tris):
        th, fh, b1, b2 = cast_rays(tris, o, d)
    else:
        th, fh = np.full(Pn, np.inf), np.full(Pn, -1)
        b1 = b2 = np.zeros(Pn)
    hit = np.isfinite(th)
    xh = o + np.where(hit, th, 0.0)[:, None] * d
    n = hit_normals(tris, fh, b1, b2) if len(tris) else np.zeros((Pn, 3))
    n = np.where(((n * d).sum(-1) > 0)[:, None], -n, n)  # the side facing the viewer
    # the shadow z-buffer test, done exactly: a shadow ray towards the sun from the hit
    vis = np.ones(Pn)
    if len(tris) and hit.any():
        eps = 1e-5 * float(np.linalg.norm(hi - lo))
        ts, _, _, _ = cast_rays(tris, xh[hit] + eps * n[hit], np.broadcast_to(sdir, (hit.sum(), 3)))
        vis[hit] = (~np.isfinite(ts)).astype(float)
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
        "plan_s": time.perf_counter() - t_start,
        # the geometry, for light_at: sheet k spans s·x ∈ z_lo + [k, k+1]·dz; a point's texel
        # coordinates are those of its projection along L onto the plane s·x = 0
        "geometry": {"s": s.tolist(), "a": a.tolist(), "b": b.tolist(), "L": L.tolist(),
                     "z_lo": float(z_lo), "dz": float(dz), "u_min": float(u_min),
                     "v_min": float(v_min)},
    }
    f32 = lambda x: jnp.asarray(x, jnp.float32)  # noqa: E731
    return SplatPlan(
        light_D=f32(light_D), occ_first=jnp.asarray(occ_first), occ_sheets=jnp.asarray(occ_sheets),
        eye_D=f32(eye_D), eye_up=f32(eye_up), eye_uv=f32(eye_uv), eye_dir=f32(d),
        hit_sheet=jnp.asarray(hit_sheet), hit_frac=f32(hit_frac), hit_uv=f32(to_uv(xh)),
        hit_shape=jnp.asarray(np.where(hit, tris.shape[np.maximum(fh, 0)] if len(tris) else 0,
                                       0).astype(np.int32)),
        hit_cos_sun=f32(np.maximum(0.0, n @ sdir)), hit_cos_back=f32(np.maximum(0.0, -(n @ sdir))),
        hit_sky=f32((1.0 + n[:, 2]) / 2.0), hit_vis=f32(vis), hit_up=f32(hit_up),
        sky_escape=f32((~hit) & (d[:, 2] > 0)),
        fwd_bins=f32(fb), fwd_mu=f32(fmu), fwd_w=f32(fw),
        back_bins=f32(bb), back_mu=f32(bmu), back_w=f32(bw), pen_kernel=f32(pen),
        sky_dirs=f32(sky_d), sky_w=f32(sky_w),
        K=K, W=W, radius=R, front_to_back=f2b, image_hw=(H, Wd), samples=S,
        buffer_hw=(hs, ws), sun_dir=tuple(float(x) for x in sdir), forward=bool(forward),
        soft=bool(soft),
    ), info


# --------------------------------------------------------------------------------------------
# the traced pass
# --------------------------------------------------------------------------------------------
def _hg_total_forward(g):
    """Fraction of the HG phase in the forward hemisphere, (1+g)/(√(1+g²)(√(1+g²)+1−g))."""
    r = jnp.sqrt(1.0 + g * g)
    return (1.0 + g) / (r * (r + 1.0 - g))


def _kernels(plan: SplatPlan, g, dtype):
    """(K_A, K_B, K_bounce) as cross-correlation weights (nk, nk), traced in g.

    K_A: forward stream → forward hemisphere, landing on the next sheet (sums to the
    hemisphere fraction f_A); K_B: forward stream → backward hemisphere, landing on the previous
    sheet (1 − f_A); K_bounce: back stream → its backward hemisphere (travelling with the light
    again), landing on the next sheet (1 − f_A).
    """
    nk = 2 * plan.radius + 1
    fa = _hg_total_forward(g)
    fmu, fw, fbins = (plan.fwd_mu.astype(dtype), plan.fwd_w.astype(dtype),
                      plan.fwd_bins.astype(dtype))
    bmu, bw, bbins = (plan.back_mu.astype(dtype), plan.back_w.astype(dtype),
                      plan.back_bins.astype(dtype))
    kf = (hg_phase(fmu, g) * fw) @ fbins
    kb = (hg_phase(-bmu, g) * bw) @ bbins
    ko = (hg_phase(-fmu, g) * fw) @ fbins
    kf = kf / jnp.sum(kf) * fa
    kb = kb / jnp.sum(kb) * (1.0 - fa)
    ko = ko / jnp.sum(ko) * (1.0 - fa)
    # bins hold target − source offsets; lax.conv correlates: out(x) = Σ_o w(o)·in(x + o)
    return tuple(k.reshape(nk, nk)[::-1, ::-1] for k in (kf, kb, ko))


def _conv(x, k):
    """Correlate a (hs, ws) buffer with a (nk, nk) kernel; edge-replicated borders (the light
    outside the buffer is as at its edge)."""
    r = k.shape[0] // 2
    xp = jnp.pad(x, r, mode="edge")
    out = jax.lax.conv_general_dilated(xp[None, None], k[None, None].astype(x.dtype), (1, 1),
                                       "VALID")
    return out[0, 0]


def _bilinear(buf, uv):
    """Bilinear lookup of (hs, ws) buffers at continuous index coords uv (..., 2), clamped."""
    hs, ws = buf.shape[-2:]
    u = jnp.clip(uv[..., 0], 0.0, hs - 1.0)
    v = jnp.clip(uv[..., 1], 0.0, ws - 1.0)
    i0 = jnp.clip(jnp.floor(u), 0, hs - 2).astype(jnp.int32)
    j0 = jnp.clip(jnp.floor(v), 0, ws - 2).astype(jnp.int32)
    fu, fv = u - i0, v - j0
    return ((1 - fu) * (1 - fv) * buf[..., i0, j0] + fu * (1 - fv) * buf[..., i0 + 1, j0]
            + (1 - fu) * fv * buf[..., i0, j0 + 1] + fu * fv * buf[..., i0 + 1, j0 + 1])


def splat_pass(plan: SplatPlan, params: Params, *, scattered_phase: str = "hg",
               similarity: bool = False, return_light: bool = False):
    """Render one camera: the (H, W) image (and with ``return_light`` the per-sheet light
    buffers (K, hs, ws) of the direct, forward-scattered and back streams).

    similarity: propagate the sheets with the similarity-scaled medium ζ* = ζ(1−g), g* = 0
    (the forward peak counted as unscattered; the kernels become the two isotropic
    hemispheres), see the scattered streams as diffuse (fluence 2× their flux, isotropic
    phase, ζ*) and the direct stream through the true ζ·p_HG.  Off: the paper's kernels.
    """
    dtype = params.scattering.dtype
    zeta_true, gam, g_true = params.scattering, params.absorption, params.g
    if similarity:
        zeta, g = zeta_true * (1.0 - g_true), jnp.zeros_like(g_true)
    else:
        zeta, g = zeta_true, g_true
    sig = zeta + gam
    K, W = plan.K, plan.W
    hs, ws = plan.buffer_hw
    f = lambda x: x.astype(dtype)  # noqa: E731
    light_D = f(plan.light_D)
    kA, kB, kO = _kernels(plan, g, dtype)
    pen = f(plan.pen_kernel)
    sdir = jnp.asarray(plan.sun_dir, dtype)
    E0 = params.sun_irradiance
    back = W > 0

    # camera phase values per eye sample: light travelling along L = −sun_dir (forward stream)
    # or along +sun_dir (back stream) scattered towards the eye (along −d)
    d = f(plan.eye_dir)
    cos_f = d @ sdir
    # radiance scattered towards the eye per unit density footprint: ζ·p for each stream
    p_dir = zeta_true * hg_phase(cos_f, g_true)
    if similarity:
        p_fs = p_b = jnp.full_like(cos_f, 2.0 / FOUR_PI) * zeta
    elif scattered_phase == "hg":
        p_fs, p_b = p_dir, zeta * hg_phase(-cos_f, g)
    elif scattered_phase == "isotropic":
        p_fs = p_b = jnp.full_like(cos_f, 1.0 / FOUR_PI) * zeta
    else:
        raise ValueError(f"scattered_phase must be 'hg' or 'isotropic', got {scattered_phase!r}")
    # in-scattered sky: ζ·sky·∫_{upper hemisphere} p(ω·d) dω
    sky = params.sky_radiance
    sky_in = zeta_true * sky * (hg_phase(d @ f(plan.sky_dirs).T, g_true) @ f(plan.sky_w))
    sig_sky = zeta_true * (1.0 - g_true) + gam  # δ-scaled extinction of the ambient sky
    fa = _hg_total_forward(g)

    def blocked(m):
        """Light rays whose polygon occluder covers slab m−1 → m: opaque from the slab after
        its first hit (a one-slab shadow bias: surfaces sloping across the sheets must not read
        their neighbours' blocked texels) for its thickness."""
        first = plan.occ_first + SHADOW_BIAS
        return (first < m) & (m <= first + plan.occ_sheets)

    def light_step(Fd, Fs, D, m_next):
        """Light entering slab m (Fd, Fs, density footprint D) → entering slab m + 1."""
        tau = sig * D
        T = jnp.exp(-tau)
        sc = zeta * D * _phi(tau)
        Fd2 = T * Fd
        Fs2 = T * Fs
        if plan.forward:
            Fs2 = Fs2 + _conv(sc * (Fd + Fs), kA)
        bl = blocked(m_next)
        Fd2 = jnp.where(bl, 0.0, Fd2)
        Fs2 = jnp.where(bl, 0.0, Fs2)
        if plan.soft:
            Fd2 = _conv(Fd2, pen)
        return Fd2, Fs2

    def back_emit(Fd, Fs, D):
        tau = sig * D
        return _conv(zeta * D * _phi(tau) * (Fd + Fs), kB)

    # --- warm-up: the light pass runs W sheets ahead of the image ----------------------------
    Fd0 = jnp.where(blocked(0), 0.0, jnp.full((hs, ws), 1.0, dtype) * E0)
    Fs0 = jnp.zeros((hs, ws), dtype)
    if back:
        def warm(c, m):
            Fd1, Fs1 = light_step(c[0], c[1], light_D[m], m + 1)
            return (Fd1, Fs1), (Fd1, Fs1, back_emit(Fd1, Fs1, light_D[m + 1]))

        _, (wd, wsf, ringb) = jax.lax.scan(warm, (Fd0, Fs0), jnp.arange(W))
        ringd = jnp.concatenate([Fd0[None], wd])
        rings = jnp.concatenate([Fs0[None], wsf])
    else:
        ringd, rings, ringb = Fd0[None], Fs0[None], jnp.zeros((0, hs, ws), dtype)

    # --- polygons: shaded radiance at a hit given the light buffers at its slab --------------
    albedo = params.albedo[plan.hit_shape] if params.albedo.shape[0] else jnp.zeros_like(cos_f)
    emis = params.emission[plan.hit_shape] if params.emission.shape[0] else jnp.zeros_like(cos_f)
    sky_surf = jnp.pi * sky * f(plan.hit_sky) * jnp.exp(-sig_sky * f(plan.hit_up))

    def poly_radiance(Fd, Fs, B, D, vis):
        tau = _bilinear(sig * D, plan.hit_uv)
        fr = f(plan.hit_frac)
        fwd = (_bilinear(Fd, plan.hit_uv) * vis + _bilinear(Fs, plan.hit_uv)) * jnp.exp(-tau * fr)
        bk = _bilinear(B, plan.hit_uv) * jnp.exp(-tau * (1.0 - fr))
        E = f(plan.hit_cos_sun) * fwd + f(plan.hit_cos_back) * bk + sky_surf
        return albedo / jnp.pi * E + emis

    vis = f(plan.hit_vis)
    vis_buf = jnp.ones_like(vis) if plan.soft else vis  # soft: the shadow buffer alone
    zero_buf = jnp.zeros((hs, ws), dtype)
    P = cos_f.shape[0]

    def combine(acc, E, T):
        Lr, Tr = acc
        if plan.front_to_back:
            return Lr + Tr * E, Tr * T
        return E + T * Lr, Tr * T

    # region 1 (in front of the sheets along the light): the shadow z-buffer alone
    rad1 = poly_radiance(jnp.full((hs, ws), 1.0, dtype) * E0, zero_buf, zero_buf, zero_buf, vis)
    in1 = plan.hit_sheet == -1
    esc = f(plan.sky_escape) * sky
    if plan.front_to_back:
        acc = (jnp.where(in1, rad1, 0.0), jnp.where(in1, 0.0, 1.0).astype(dtype))
    else:  # the eye sees these last: start from them (or from the sky behind everything)
        acc = (jnp.where(in1, rad1, esc), jnp.ones(P, dtype))

    def body(carry, xs):
        ringd, rings, ringb, acc = carry
        k, De, up, uv, Dk, Dnext = xs
        Fd, Fs = ringd[0], rings[0]
        # the back stream reaching sheet k from the W stored sheets below it
        if back:
            Dw = jax.lax.dynamic_slice_in_dim(light_D, k + 1, W)
            tw = sig * Dw
            Tw = jnp.exp(-tw)
            # going up, a sheet passes its unscattered light and what it scatters onwards
            # (forward with respect to the back stream)
            Uw = Tw + fa * zeta * Dw * _phi(tw)
            B = ringb[W - 1]
            for j in range(W - 2, -1, -1):
                B = Uw[j] * B + ringb[j]
        else:
            B = zero_buf
        # illuminate sheet k: mean light within the slab, looked up at each eye segment
        tau_l = sig * Dk
        phl = _phi(tau_l)
        lit = jnp.stack([Fd * phl, Fs * phl, B * phl])
        md, ms, mb = _bilinear(lit, uv)
        tau_e = sig * De
        src = p_dir * md + p_fs * ms + p_b * mb + sky_in * jnp.exp(-sig_sky * up)
        E = De * _phi(tau_e) * src
        Te = jnp.exp(-tau_e)
        here = plan.hit_sheet == k
        rad = poly_radiance(Fd, Fs, B, Dk, vis_buf)
        E = E + jnp.where(here, Te * rad, 0.0)
        Te = jnp.where(here, 0.0, Te)
        acc = combine(acc, E, Te)
        # bounce: the back stream scattered forward again at sheet k, carried down the window
        if back:
            bounce = _conv(zeta * Dk * phl * B, kO)
            Tcum = jnp.concatenate([jnp.ones((1, hs, ws), dtype), jnp.cumprod(Tw[:-1], 0)])
            rings = rings.at[1:].add(Tcum * bounce[None])
        # advance the light front to sheet k + W + 1
        Fd1, Fs1 = light_step(ringd[-1], rings[-1], Dnext[0], k + W + 1)
        ringd = jnp.concatenate([ringd[1:], Fd1[None]])
        rings = jnp.concatenate([rings[1:], Fs1[None]])
        if back:
            ringb = jnp.concatenate([ringb[1:], back_emit(Fd1, Fs1, Dnext[1])[None]])
        ys = (Fd, Fs, B) if return_light else None
        return (ringd, rings, ringb, acc), ys

    ks = jnp.arange(K)
    # Dnext: footprints of the front sheet (k + W) and of the new one (k + W + 1)
    Dnext = jnp.stack([light_D[W:K + W], light_D[W + 1:K + W + 1]], 1)
    xs = (ks, f(plan.eye_D), f(plan.eye_up), plan.eye_uv.astype(dtype), light_D[:K], Dnext)
    (ringd, rings, ringb, acc), ys = jax.lax.scan(body, (ringd, rings, ringb, acc), xs)

    # region 3 (behind the sheets): the final shadow buffer and the shadow z-buffer
    rad3 = poly_radiance(ringd[0], rings[0], zero_buf, zero_buf, vis)
    in3 = plan.hit_sheet == K
    Lr, Tr = acc
    if plan.front_to_back:
        Lr = Lr + Tr * (jnp.where(in3, rad3, 0.0) + esc)
    else:
        Lr = jnp.where(in3, rad3, Lr)
    H, Wd = plan.image_hw
    img = Lr.reshape(H, Wd, plan.samples).mean(-1)
    if return_light:
        return img, ys
    return img


# --------------------------------------------------------------------------------------------
# the renderer
# --------------------------------------------------------------------------------------------
class SplatRenderer:
    """A scene prepared for splat renders: ``renderer(params)`` → {camera: (H, W) image}.

    resolution: lattice nodes along the longest domain axis (the voxels that are splatted);
    sheets: slices per camera pass (default: one per voxel spacing along the half-way vector) —
    the accuracy knob; supersample: s×s rays per pixel (box filter); forward_scatter,
    back_scatter: the §3 multiple scattering terms (both off: attenuation only);
    soft_shadows: §5 (the sun's ``angular_radius_deg`` sets the penumbra; also widens the
    sheets to cover the polygons); back_window: W, the stored sheets below a sheet that scatter
    back into it; shadow_texel: shadow-buffer texel size (default the voxel size);
    quadrature: Gauss–Legendre points per footprint segment; kernel_radius: scattering kernels
    of (2R+1)² texels; occluder_thickness: "paper" (∝ 1/|∇z_light|, §5, scaled by
    ``thickness_scale`` texels) or "exact" (the occluder's own extent along the light);
    scattered_phase: "hg" (the paper: scattered light seen through the fog's phase about the
    light direction) or "isotropic"; similarity (default): propagate the sheets with ζ(1−g) and
    isotropic kernels (see :func:`splat_pass`); False: the paper's HG kernels (cloud-plane vs
    Mitsuba: 13% / 37% error with it, 26% / 57% without).
    """

    def __init__(self, scene: Scene, *, resolution: int = 64, sheets: int | None = None,
                 cameras: list[str] | None = None, supersample: int = 1,
                 forward_scatter: bool = True, back_scatter: bool = True,
                 soft_shadows: bool = True, back_window: int = 6,
                 shadow_texel: float | None = None, quadrature: int = 2, kernel_radius: int = 3,
                 occluder_thickness: str = "paper", thickness_scale: float = 4.0,
                 scattered_phase: str = "hg", similarity: bool = True):
        if scene.domain.boundary != "open":
            raise SceneError(f"scene '{scene.title}': boundary '{scene.domain.boundary}' is not "
                             "supported by the splat solver (its sheets are finite); use "
                             "boundary = \"open\" or --solver sweep")
        if scene.sun is None:
            raise SceneError(f"scene '{scene.title}' has no [sun]: the splat solver propagates "
                             "one directional light (Zhang & Crawfis); add a [sun] or use "
                             "--solver sweep")
        for name, v, lo in (("resolution", resolution, 2), ("supersample", supersample, 1),
                            ("quadrature", quadrature, 1), ("kernel_radius", kernel_radius, 1),
                            ("back_window", back_window, 1)):
            if not isinstance(v, (int, np.integer)) or v < lo:
                raise SceneError(f"{name} must be an integer ≥ {lo}, got {v!r}")
        if sheets is not None and (not isinstance(sheets, (int, np.integer)) or sheets < 1):
            raise SceneError(f"sheets must be a positive integer (or None for one per voxel), "
                             f"got {sheets!r}")
        if occluder_thickness not in ("paper", "exact"):
            raise SceneError(f"occluder_thickness must be 'paper' or 'exact', got "
                             f"{occluder_thickness!r}")
        if scattered_phase not in ("hg", "isotropic"):
            raise SceneError(f"scattered_phase must be 'hg' or 'isotropic', got "
                             f"{scattered_phase!r}")
        self.scene = scene
        self.resolution = int(resolution)
        self.sheets = None if sheets is None else int(sheets)
        self.supersample = int(supersample)
        self.options = dict(forward_scatter=bool(forward_scatter), back_scatter=bool(back_scatter),
                            soft_shadows=bool(soft_shadows), back_window=int(back_window),
                            shadow_texel=shadow_texel, quadrature=int(quadrature),
                            kernel_radius=int(kernel_radius),
                            occluder_thickness=occluder_thickness,
                            thickness_scale=float(thickness_scale),
                            scattered_phase=scattered_phase, similarity=bool(similarity))
        names = [c.name for c in scene.cameras] if cameras is None else list(cameras)
        self.cameras = [scene.camera(n) for n in names]
        self.timings: dict[str, float] = {}
        t = time.perf_counter()
        with warnings.catch_warnings():
            # the lattice only carries the fog density here (fog minus solids); the polygons are
            # rasterized, so the voxelizer's "shape thinner than a voxel" warning does not apply
            warnings.filterwarnings("ignore", message="shape .* thick, less than one voxel")
            self.lattice = voxelize(scene, self.resolution, 1, margin=1)
        self.triangles = scene_triangles(scene)
        self.timings["voxelize_s"] = time.perf_counter() - t
        t = time.perf_counter()
        built = {
            c.name: splat_plan(scene, self.lattice, self.triangles, c, sheets=self.sheets,
                               supersample=self.supersample,
                               back_window=self.options["back_window"] if back_scatter else 0,
                               forward=forward_scatter, soft=soft_shadows,
                               shadow_texel=shadow_texel, quadrature=quadrature,
                               kernel_radius=kernel_radius,
                               occluder_thickness=occluder_thickness,
                               thickness_scale=thickness_scale)
            for c in self.cameras
        }
        self.plans = {n: v[0] for n, v in built.items()}
        self.plan_info = {n: v[1] for n, v in built.items()}
        self.timings["prepare_s"] = time.perf_counter() - t
        self._forward = jax.jit(self._forward_impl)

    def params(self, dtype=None) -> Params:
        return Params.from_scene(self.scene, dtype)

    def _pass_options(self):
        return {"scattered_phase": self.options["scattered_phase"],
                "similarity": self.options["similarity"]}

    def _forward_impl(self, plans, params: Params):
        return {n: splat_pass(p, params, **self._pass_options()) for n, p in plans.items()}

    def __call__(self, params: Params | None = None) -> dict[str, jax.Array]:
        """Differentiable (and jitted): images of every camera for these parameters."""
        return self._forward(self.plans, self.params() if params is None else params)

    def light_buffers(self, params: Params | None = None, camera: str | None = None):
        """The light of one camera's pass as a 3-D export: (direct, forward-scattered, back)
        buffers (K, hs, ws) entering each sheet, and that plan (its ``info`` gives the sheet
        geometry).  Not needed for images; for inspection and tests."""
        params = self.params() if params is None else params
        name = camera or self.cameras[0].name
        plan = self.plans[name]
        _, ys = jax.jit(lambda p, q: splat_pass(p, q, return_light=True,
                                                **self._pass_options()))(plan, params)
        return ys, plan, self.plan_info[name]

    def light_at(self, points, params: Params | None = None, camera: str | None = None):
        """The 3-D light export: (direct, forward-scattered, back) light intensity at world
        points (N, 3), read from one camera pass's sheet buffers (each camera's pass has its own
        sheets; the light is the same up to their discretization).  Points before the first
        sheet read it unattenuated, points past the last read the last slab's exit.  Returns
        three (N,) NumPy arrays (units of the sun's irradiance)."""
        params = self.params() if params is None else params
        (Fd, Fs, B), plan, info = self.light_buffers(params, camera)
        gm = info["geometry"]
        s, a, b, L = (np.asarray(gm[k]) for k in ("s", "a", "b", "L"))
        x = np.asarray(points, np.float64).reshape(-1, 3)
        z = (x @ s - gm["z_lo"]) / gm["dz"]
        k = np.clip(np.floor(z), 0, plan.K - 1).astype(np.int32)
        fr = np.clip(z - k, 0.0, 1.0)
        xp = x - (x @ s / float(s @ L))[:, None] * L
        uv = np.stack([(xp @ a - gm["u_min"]) / info["texel"] - 0.5,
                       (xp @ b - gm["v_min"]) / info["texel"] - 0.5], -1)
        sig = float(params.scattering + params.absorption)
        if self.options["similarity"]:
            sig = float(params.scattering * (1 - params.g) + params.absorption)
        tau = sig * plan.light_D[:plan.K]
        hs, ws = plan.buffer_hw
        u = np.clip(uv[:, 0], 0.0, hs - 1.0)
        v = np.clip(uv[:, 1], 0.0, ws - 1.0)
        i0 = np.clip(np.floor(u), 0, hs - 2).astype(np.int64)
        j0 = np.clip(np.floor(v), 0, ws - 2).astype(np.int64)
        fu, fv = u - i0, v - j0

        def at(buf):
            buf = np.asarray(buf, np.float64)
            return ((1 - fu) * (1 - fv) * buf[k, i0, j0] + fu * (1 - fv) * buf[k, i0 + 1, j0]
                    + (1 - fu) * fv * buf[k, i0, j0 + 1] + fu * fv * buf[k, i0 + 1, j0 + 1])

        t = at(tau)
        return (at(Fd) * np.exp(-t * fr), at(Fs) * np.exp(-t * fr), at(B) * np.exp(-t * (1 - fr)))

    def render(self, params: Params | None = None) -> Rendered:
        """Render every camera, timing compilation and the warm run apart."""
        params = self.params() if params is None else params
        timings = dict(self.timings)
        t = time.perf_counter()
        compiled = self._forward.lower(self.plans, params).compile()
        timings["render_compile_s"] = time.perf_counter() - t
        t = time.perf_counter()
        imgs = jax.block_until_ready(compiled(self.plans, params))
        timings["render_s"] = time.perf_counter() - t
        images = {k: np.asarray(v, np.float32) for k, v in imgs.items()}
        for k, v in images.items():
            if not np.all(np.isfinite(v)):
                raise SceneError(f"camera '{k}': the image has non-finite values (a solver bug?)")
        light = dict(self.plan_info)
        return Rendered(images=images, light=light, timings=timings, settings=self.settings())

    def settings(self) -> dict:
        lat = self.lattice
        return {
            "scene": self.scene.title,
            "solver": "splat",
            "solver_options": {"sheets": self.sheets, **self.options},
            "resolution": self.resolution,
            "lattice_shape": list(lat.shape),
            "voxel_size": lat.h,
            "triangles": len(self.triangles),
            "supersample": self.supersample,
            "cameras": [c.name for c in self.cameras],
            "passes": self.plan_info,
            "dtype": str(jnp.result_type(float)),
        }
