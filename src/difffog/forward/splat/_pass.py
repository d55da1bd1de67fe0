"""The splat solver: C. Zhang and R. Crawfis, *Light Propagation for Mixed Polygonal and
Volumetric Data Using Splatting* (The Ohio State University); section numbers below are the
paper's.

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

import jax
import jax.numpy as jnp

from ..._numerics import FOUR_PI, bilinear, one_minus_exp_over
from ...scene._params import Params
from .._camera import hg_phase
from ._sheets import SheetGeometry

#: slabs a polygon occluder starts late in the shadow buffer (see ``splat_pass.blocked``)
SHADOW_BIAS = 1

_phi = one_minus_exp_over


# --------------------------------------------------------------------------------------------
# the traced pass
# --------------------------------------------------------------------------------------------
def _hg_total_forward(g):
    """Fraction of the HG phase in the forward hemisphere, (1+g)/(√(1+g²)(√(1+g²)+1−g))."""
    r = jnp.sqrt(1.0 + g * g)
    return (1.0 + g) / (r * (r + 1.0 - g))


def _kernels(plan: SheetGeometry, g, dtype):
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
    """Bilinear lookup of (..., hs, ws) buffers at continuous index coords uv (..., 2), clamped."""
    return bilinear(buf, uv[..., 0], uv[..., 1])


def splat_pass(plan: SheetGeometry, params: Params, *, scattered_phase: str = "hg",
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


