"""A face sweep's slab step as one Pallas kernel (the GPU's face sweep, issue 20).

``_sweep_face_batched`` does a slab step as about four passes over the carried radiance
(M, D, nu, nv): the shift (a vmapped ``dynamic_slice`` of a padded copy), the fog step, the
blocking, and the reductions over directions for Λ and E.  Here one kernel does all of it in
one pass: each program takes one plane m of the slab, a tile of (TU, TV) nodes and a block of
about 32 directions (``direction_block``); for each direction it reads the carry shifted by
(p, q) (open sides: ``bc``; periodic: wrapped), applies the same arithmetic as the batched
program (the module doc of ``_kernel.py``: the step update in two half-segments, Λ from the
segment's mean radiance, a blocked arrival carrying B; the linear scheme's three-part node
update; a direction's source from the moments' and the sun's channels), writes the radiance
leaving, and sums Λ (and its moments) and E over its directions.  Each direction block writes
its own partial Λ and E; XLA adds the blocks in a fixed order, so the result does not depend
on scheduling (deterministic, like the rest).

On a GPU (CUDA or ROCm) the kernel goes through Pallas's Triton backend; on a CPU, which
Pallas cannot compile for, it runs in Pallas's interpret mode, slowly, so that the tests
check it against the batched program (the reference) on any machine.  Values only: the
derivatives of ``sweep_face`` come from the batched program, as for the other kernels.

Scope: the step and linear schemes, isotropic fog or with moments (δ-M) and the sun's phase
channel, on one device's whole plane.  The sub-stepped scheme and a device mesh's halo run
the batched program.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np
from jax.experimental import pallas as pl
from jax.experimental.pallas import triton as plt

from ..._numerics import linear_source_terms, one_minus_exp_over
from ._kernel import _linear_node

#: nodes per program: TILE_U rows × TILE_V columns of the plane (powers of two, as Triton's
#: tensors must be)
TILE_U = 16
TILE_V = 32
#: directions per program, about: whole rows of 2M + 1 directions (p fixed).  Each block
#: re-reads the tile's node data (source channels, τ, B, normal) and writes its partial Λ
#: (1 + K channels) and E, so fewer, larger blocks cost less traffic; more blocks give the GPU
#: more programs (N = 128, M = 5: 5 planes × 45 tiles × 4 blocks of 33 = 900)
DIRECTIONS_PER_PROGRAM = 32


def direction_block(M: int) -> int:
    """Directions per program at half-width M: whole rows of 2M + 1, about
    ``DIRECTIONS_PER_PROGRAM`` (M = 2: all 25; M = 3: 35; M = 5: 33)."""
    P = 2 * M + 1
    return P * min(P, max(1, -(-DIRECTIONS_PER_PROGRAM // P)))


def interpret_mode(backend: str | None = None) -> bool:
    """Pallas compiles for GPUs (Triton); anywhere else the kernel runs interpreted."""
    return (backend or jax.default_backend()) not in ("gpu", "cuda", "rocm")


def _kernel(pq_ref, len_ref, w_ref, bc_ref, unit_ref, table_ref, slope_ref, carry_ref, q_ref,
            b_ref, t_ref, keep_ref, n_ref, bits_ref, out_ref, lam_ref, irr_ref, *, M: int,
            nu: int, nv: int, per_u: bool, per_v: bool, surfaces: bool, fluence: bool, nj: int,
            nk: int, linear: bool):
    """One program: plane m of the slab, a (TILE_U, TILE_V) tile, directions
    [blk·BD, min((blk+1)·BD, D)) (BD = ``direction_block(M)``).  q_ref: (1 + nj [+ 3], M, nu, nv) the source channels (the
    isotropic source; those direction d weights by ``table_ref[d]``, the moments' nk first;
    with the linear scheme the slope h∇Q); lam_ref: (blocks, 1 + nk, M, nu, nv)."""
    D = (2 * M + 1) ** 2
    BD = direction_block(M)
    m = pl.program_id(0)
    u = pl.program_id(1) * TILE_U + jax.lax.broadcasted_iota(jnp.int32, (TILE_U, 1), 0)
    v = pl.program_id(2) * TILE_V + jax.lax.broadcasted_iota(jnp.int32, (1, TILE_V), 1)
    blk = pl.program_id(3)
    inside = (u < nu) & (v < nv)
    uc = jnp.minimum(u, nu - 1)
    vc = jnp.minimum(v, nv - 1)
    qch = [q_ref[c, m, uc, vc] for c in range(1 + nj + (3 if linear else 0))]
    ts = t_ref[m, uc, vc]
    keep = keep_ref[m, uc, vc] != 0
    dt = ts.dtype
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
        d = blk * BD + k
        su, oku = shifted(uc, pq_ref[d, 0], nu, per_u)
        sv, okv = shifted(vc, pq_ref[d, 1], nv, per_v)
        r_mid = carry_ref[m, d, su, sv]
        ok = oku if okv is None else (okv if oku is None else oku & okv)
        if ok is not None:  # open sides: the radiance entering from outside the domain
            r_mid = jnp.where(ok, r_mid, bc_ref[d])
        q = qch[0]
        for j in range(nj):  # this direction's source: the moments', the sun's phase
            q = q + qch[1 + j] * table_ref[d, j]
        tau = ts * len_ref[d]
        em = jnp.expm1(-tau)
        if linear:  # the source linear along the segment
            sl = sum(qch[1 + nj + c] * slope_ref[d, c] for c in range(3))
            phi, psi = linear_source_terms(tau)[:2]
            r_arr, r_through, r_avg = _linear_node(r_mid, q, sl, em, 0.5 * tau * psi, phi, psi)
        else:
            r_arr = r_mid + em * (r_mid - q)
            r_avg = q + (r_mid - q) * one_minus_exp_over(2.0 * tau)
        if surfaces:
            blocked = ((bits_ref[m, d // 8, uc, vc].astype(jnp.int32) >> (d % 8)) & 1) > 0
            r_arr = jnp.where(blocked, bsurf, r_arr)
            r_avg = jnp.where(blocked, q + (bsurf - q) * one_minus_exp_over(tau), r_avg)
            if linear:  # blocked: a constant source in the departure half
                r_through = jnp.where(blocked, bsurf + em * (bsurf - q), r_through)
        if not linear:
            r_through = r_arr + em * (r_arr - q)
        w = w_ref[d]
        if fluence:
            wa = r_avg * w
            lam = (lam[0] + wa,) + tuple(lam[1 + c] + wa * table_ref[d, c] for c in range(nk))
        if surfaces:
            ldotn = nrm[0] * unit_ref[d, 0] + nrm[1] * unit_ref[d, 1] + nrm[2] * unit_ref[d, 2]
            irr = irr + r_arr * jnp.maximum(-ldotn, 0.0) * w
        plt.store(out_ref.at[m, d, u, v], jnp.where(keep, r_through, 0.0).astype(dt),
                  mask=inside)
        return lam, irr

    zero = jnp.zeros((TILE_U, TILE_V), dt)
    count = jnp.minimum(BD, D - blk * BD)  # the last block may be shorter
    lam, irr = jax.lax.fori_loop(0, count, body, ((zero,) * (1 + nk), zero))
    for c in range(1 + nk):
        plt.store(lam_ref.at[blk, c, m, u, v], lam[c], mask=inside)
    plt.store(irr_ref.at[blk, m, u, v], irr, mask=inside)


@functools.lru_cache(maxsize=None)
def _call(M: int, nu: int, nv: int, dtype: str, per_u: bool, per_v: bool, surfaces: bool,
          fluence: bool, interpret: bool, nj: int = 0, nk: int = 0, linear: bool = False):
    D = (2 * M + 1) ** 2
    nblk = -(-D // direction_block(M))
    dt = np.dtype(dtype)
    grid = (M, -(-nu // TILE_U), -(-nv // TILE_V), nblk)
    kern = functools.partial(_kernel, M=M, nu=nu, nv=nv, per_u=per_u, per_v=per_v,
                             surfaces=surfaces, fluence=fluence, nj=nj, nk=nk, linear=linear)
    out_shape = (jax.ShapeDtypeStruct((M, D, nu, nv), dt),
                 jax.ShapeDtypeStruct((nblk, 1 + nk, M, nu, nv), dt),
                 jax.ShapeDtypeStruct((nblk, M, nu, nv), dt))
    params = {}
    if not interpret:
        params["compiler_params"] = plt.CompilerParams(num_warps=4, num_stages=1)
    return pl.pallas_call(kern, out_shape=out_shape, grid=grid, interpret=interpret,
                          name="difffog_slab_step", **params)


def slab_step(carry, slab, *, pq, length, weight, bc, unit, M: int, periodic_uv, surfaces: bool,
              fluence: bool, table=None, nk: int = 0, slope=None, interpret: bool | None = None):
    """One slab step of the batched program (``_sweep_face_batched``'s ``step``), one kernel.

    carry: (M, D, nu, nv) the radiance leaving the previous slab's planes; slab: the step's
    (Q, B, τ/2 per |L|, free, surf, normal (3, M, nu, nv), blocking bytes (M, ⌈D/8⌉, nu, nv)),
    as the batched program slices them: Q (M, nu, nv) for an isotropic fog with the step
    scheme, else (M, nu, nv, 1 + J [+ 3]) with ``table`` (D, J) the per-direction weights of
    its J channels (the nk moments first; ``_kernel._source_table``) and ``slope`` (D, 3) the
    linear scheme's lattice vectors.  Returns (carry', (Λ, E)): Λ (M, nu, nv), or
    (M, nu, nv, 1 + nk) with moments, E (M, nu, nv).
    """
    Qs, Bs, ts, fs, ss, ns, bits = slab
    _, D, nu, nv = carry.shape
    dt = carry.dtype
    if interpret is None:
        interpret = interpret_mode()
    nj = 0 if table is None else int(table.shape[1])
    linear = slope is not None
    qch = Qs[None] if Qs.ndim == 3 else jnp.moveaxis(Qs, -1, 0)
    keep = (fs | ss) if surfaces else fs
    call = _call(M, nu, nv, dt.name, bool(periodic_uv[0]), bool(periodic_uv[1]),
                 bool(surfaces), bool(fluence), bool(interpret), nj, int(nk), linear)
    table = jnp.zeros((D, 1), dt) if table is None or nj == 0 else table.astype(dt)
    slope = jnp.zeros((D, 3), dt) if slope is None else slope.astype(dt)
    out, lam, irr = call(pq.astype(jnp.int32), length.astype(dt), weight.astype(dt),
                         bc.astype(dt), unit.astype(dt), table, slope, carry, qch.astype(dt),
                         Bs.astype(dt), ts.astype(dt), keep.astype(jnp.uint8), ns.astype(dt),
                         bits.astype(jnp.uint8))
    # the direction blocks' partial sums, added in a fixed order
    lam = lam.sum(0)
    lam = lam[0] if Qs.ndim == 3 or nk == 0 else jnp.moveaxis(lam, 0, -1)
    return out, (lam, irr.sum(0))
