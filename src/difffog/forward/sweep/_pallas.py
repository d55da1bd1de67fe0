"""The isotropic step scheme's slab step as one Pallas kernel (the GPU's face sweep, issue 20).

``_sweep_face_batched`` does a slab step as about four passes over the carried radiance
(M, D, nu, nv): the shift (a vmapped ``dynamic_slice`` of a padded copy), the fog step, the
blocking, and the reductions over directions for Λ and E.  Here one kernel does all of it in
one pass: each program takes one plane m of the slab, a tile of (TU, TV) nodes and a block of
``2M + 1`` directions; for each direction it reads the carry shifted by (p, q) (open sides:
``bc``; periodic: wrapped), applies the same arithmetic as the batched program (the module
doc of ``_kernel.py``: the step update in two half-segments, Λ from the segment's mean
radiance, a blocked arrival carrying B), writes the radiance leaving, and sums Λ and E over
its directions.  Each direction block writes its own partial Λ and E; XLA adds the blocks in
a fixed order, so the result does not depend on scheduling (deterministic, like the rest).

On a GPU (CUDA or ROCm) the kernel goes through Pallas's Triton backend; on a CPU, which
Pallas cannot compile for, it runs in Pallas's interpret mode, slowly, so that the tests
check it against the batched program (the reference) on any machine.  Values only: the
derivatives of ``sweep_face`` come from the batched program, as for the other kernels.

Scope: the isotropic step scheme (no moments, no linear source, no sub-steps),
on one device's whole plane (no halo).  Elsewhere ``sweep_face`` runs the batched program.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np
from jax.experimental import pallas as pl
from jax.experimental.pallas import triton as plt

#: nodes per program: TILE_U rows × TILE_V columns of the plane (powers of two, as Triton's
#: tensors must be); a program loops over one block of 2M + 1 directions.
TILE_U = 16
TILE_V = 32


def interpret_mode(backend: str | None = None) -> bool:
    """Pallas compiles for GPUs (Triton); anywhere else the kernel runs interpreted."""
    return (backend or jax.default_backend()) not in ("gpu", "cuda", "rocm")


def _ome(tau):
    """(1 − e^{−τ})/τ as ``_numerics.one_minus_exp_over`` (same series below 1e-3)."""
    small = jnp.abs(tau) < 1e-3
    ts = jnp.where(small, 1.0, tau)
    series = 1.0 - tau / 2.0 + tau * tau / 6.0 - tau * tau * tau / 24.0
    return jnp.where(small, series, -jnp.expm1(-ts) / ts)


def _kernel(pq_ref, len_ref, w_ref, bc_ref, unit_ref, carry_ref, q_ref, b_ref, t_ref,
            keep_ref, n_ref, bits_ref, out_ref, lam_ref, irr_ref, *, M: int, nu: int, nv: int,
            per_u: bool, per_v: bool, surfaces: bool, fluence: bool):
    P = 2 * M + 1
    m = pl.program_id(0)
    u = pl.program_id(1) * TILE_U + jax.lax.broadcasted_iota(jnp.int32, (TILE_U, 1), 0)
    v = pl.program_id(2) * TILE_V + jax.lax.broadcasted_iota(jnp.int32, (1, TILE_V), 1)
    blk = pl.program_id(3)
    inside = (u < nu) & (v < nv)
    uc = jnp.minimum(u, nu - 1)
    vc = jnp.minimum(v, nv - 1)
    q = q_ref[m, uc, vc]
    ts = t_ref[m, uc, vc]
    keep = keep_ref[m, uc, vc] != 0
    dt = q.dtype
    if surfaces:
        bsurf = b_ref[m, uc, vc]
        nrm = [n_ref[c, m, uc, vc] for c in range(3)]

    def shifted(x, s, n, periodic):
        """Index x − s on an axis of n nodes: wrapped, or clamped with an in-range flag."""
        y = x - s
        if periodic:  # |s| ≤ M ≤ n
            return jnp.where(y < 0, y + n, jnp.where(y >= n, y - n, y)), None
        ok = (y >= 0) & (y < n)
        return jnp.minimum(jnp.maximum(y, 0), n - 1), ok

    def body(k, acc):
        lam, irr = acc
        d = blk * P + k
        su, oku = shifted(uc, pq_ref[d, 0], nu, per_u)
        sv, okv = shifted(vc, pq_ref[d, 1], nv, per_v)
        r_mid = carry_ref[m, d, su, sv]
        ok = oku if okv is None else (okv if oku is None else oku & okv)
        if ok is not None:  # open sides: the radiance entering from outside the domain
            r_mid = jnp.where(ok, r_mid, bc_ref[d])
        tau = ts * len_ref[d]
        em = jnp.expm1(-tau)
        r_arr = r_mid + em * (r_mid - q)
        r_avg = q + (r_mid - q) * _ome(2.0 * tau)
        if surfaces:
            blocked = ((bits_ref[m, d // 8, uc, vc].astype(jnp.int32) >> (d % 8)) & 1) > 0
            r_arr = jnp.where(blocked, bsurf, r_arr)
            r_avg = jnp.where(blocked, q + (bsurf - q) * _ome(tau), r_avg)
        w = w_ref[d]
        if fluence:
            lam = lam + r_avg * w
        r_through = r_arr + em * (r_arr - q)
        if surfaces:
            ldotn = nrm[0] * unit_ref[d, 0] + nrm[1] * unit_ref[d, 1] + nrm[2] * unit_ref[d, 2]
            irr = irr + r_arr * jnp.maximum(-ldotn, 0.0) * w
        plt.store(out_ref.at[m, d, u, v], jnp.where(keep, r_through, 0.0).astype(dt), mask=inside)
        return lam, irr

    zero = jnp.zeros((TILE_U, TILE_V), dt)
    lam, irr = jax.lax.fori_loop(0, P, body, (zero, zero))
    plt.store(lam_ref.at[blk, m, u, v], lam, mask=inside)
    plt.store(irr_ref.at[blk, m, u, v], irr, mask=inside)


@functools.lru_cache(maxsize=None)
def _call(M: int, nu: int, nv: int, dtype: str, per_u: bool, per_v: bool, surfaces: bool,
          fluence: bool, interpret: bool):
    P = 2 * M + 1
    D = P * P
    dt = np.dtype(dtype)
    grid = (M, -(-nu // TILE_U), -(-nv // TILE_V), P)
    kern = functools.partial(_kernel, M=M, nu=nu, nv=nv, per_u=per_u, per_v=per_v,
                             surfaces=surfaces, fluence=fluence)
    out_shape = (jax.ShapeDtypeStruct((M, D, nu, nv), dt),
                 jax.ShapeDtypeStruct((P, M, nu, nv), dt),
                 jax.ShapeDtypeStruct((P, M, nu, nv), dt))
    params = {}
    if not interpret:
        params["compiler_params"] = plt.CompilerParams(num_warps=4, num_stages=1)
    return pl.pallas_call(kern, out_shape=out_shape, grid=grid, interpret=interpret,
                           name="difffog_slab_step", **params)


def slab_step(carry, slab, *, pq, length, weight, bc, unit, M: int, periodic_uv, surfaces: bool,
              fluence: bool, interpret: bool | None = None):
    """One slab step of the batched program (``_sweep_face_batched``'s ``step``), one kernel.

    carry: (M, D, nu, nv) the radiance leaving the previous slab's planes; slab: the step's
    (Q, B, τ/2 per |L|, free, surf, normal (3, M, nu, nv), blocking bytes (M, ⌈D/8⌉, nu, nv)),
    as the batched program slices them.  Returns (carry', (Λ, E)), Λ and E (M, nu, nv).
    """
    Qs, Bs, ts, fs, ss, ns, bits = slab
    _, D, nu, nv = carry.shape
    dt = carry.dtype
    if interpret is None:
        interpret = interpret_mode()
    keep = (fs | ss) if surfaces else fs
    call = _call(M, nu, nv, dt.name, bool(periodic_uv[0]), bool(periodic_uv[1]),
                 bool(surfaces), bool(fluence), bool(interpret))
    out, lam, irr = call(pq.astype(jnp.int32), length.astype(dt), weight.astype(dt),
                         bc.astype(dt), unit.astype(dt), carry, Qs.astype(dt), Bs.astype(dt),
                         ts.astype(dt), keep.astype(jnp.uint8), ns.astype(dt),
                         bits.astype(jnp.uint8))
    # the direction blocks' partial sums, added in a fixed order
    return out, (lam.sum(0), irr.sum(0))
