"""One face sweep: coordinate evolution on the light-ray manifold (M. S. Langer, P. Breton and
S. W. Zucker, *Massively Parallel Radiosity in the Presence of Multiple Isotropic Volume
Scattering*, McGill University).

For each of the six cube faces F we sweep the lattice plane by plane along F's axis.  The local
coordinate system C_i^F holds, for every node of plane i, the radiance arriving there along each
of F's (2M+1)² directions L = (p, q, M).  The paper's Local_Transformation C_i^F → C_{i+M}^F is a
*static* shift by (p, q) in the plane, so we process M planes at once: ``lax.scan`` runs over
slabs of M planes and carries the radiance of the previous slab (shape (M, D, nu, nv)).

Node cases for the node z = y − L a ray left before arriving at y (the paper's ``case {x − L}``):
  FREE or SURFACE z → the arriving radiance, attenuated through the fog (shell nodes hold fog too);
  blocked segment   → if the segment z → y crosses a SOLID node (``segment_blocking``, computed
                      once on the host), the ray was emitted by the surface between them: it
                      arrives at y with y's radiosity B(y).  (A SOLID z always blocks: the segment's
                      samples include z.  SOLID nodes send 0, which no node reads unblocked —
                      FREE nodes lie more than M nodes from any solid — so the sweep is linear
                      in (Q, B, boundary radiance) also for signed inputs, as a Krylov solver
                      needs; an earlier −1 sentinel tested by sign was not.)
The paper's rule (SURFACE z emits B(z) if L·N(z) > 0, else 0) makes the M-node shell opaque:
nodes deep in the shell are shadowed by shallower ones (the innermost, which a camera sees, get
~70% of their irradiance) and the geometry grows by up to M nodes.  Tangent-plane tests at z or
y (which we tried) fail at convex edges — the rim of an open box, where all the sky enters — and
on small spheres; testing the segment against the solid nodes is exact for the lattice's geometry.
Each node owns half of each segment it touches, with its own extinction σ_t and source; over a
half-segment of optical depth τ = σ_t·h·|L|/2 the exact step ("step characteristic") update is
    R ← T·R + (1 − T)·Q,   T = exp(−τ),
written as R + expm1(−τ)·(R − Q) so it stays exact and differentiable as τ → 0 and never goes
negative (the paper's first-order factor (1 − γ − ζ) does, once a step is optically thick).
Q = (ζ/(ζ+γ))·J is the source radiance, J the mean radiance (Λ/4π) of the previous iteration plus
the first-collision source of the sun.

Λ(y) += Σ_L w_L R̄(y, L) accumulates the fluence at FREE nodes (the paper's "isotropic
luminescence") from the radiance averaged over the node's segment,
    R̄ = Q + (R_in − Q)·(1 − e^(−2τ))/(2τ)      (R_in entering the node's segment of depth 2τ),
not from the radiance at the node: the step update gives R_out − R_in = 2τ·(Q − R̄) exactly, and
the chains of direction L through the lattice carry a cross-section h²/|L| each, so the power a
node's beams lose is σ_t h³ Σ_L w_L (R̄ − Q) whatever |L|; with Q = (ζ/σ_t)·Λ/4π a purely
scattering node then re-emits exactly what it removes, for any step optical depth.  (With the
point value R(y, L) a thick node (τ ≫ 1) saw its own source from every direction, Λ → 4πQ, and
a conservative medium's light grew without bound: ×11 at ζ = 100, N = 12.)  The first-collision
source adds the uncollided sun and sky averaged over the node's segment the same way
(``_uncollided.py``).  After a blocked arrival only the departure half lies in the fog: R̄ = Q + (B − Q)(1 − e^(−τ))/τ.  E(y) += c(y) Σ_L w_L R(y, L) max(0, −L̂·N(y)) the irradiance of SURFACE nodes with
the per-node cosine normalization c (so that a Lambertian hemisphere integrates to π).  One
Jacobi iteration = six sweeps = one more bounce.
"""

from __future__ import annotations

import functools
import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ..._errors import SolverError
from ..._numerics import linear_source_terms, one_minus_exp_over
from ...geometry._directions import FACE_AXES, DirectionSet, direction_set, face_plane_axes
from . import _native

# Rows of the plane processed per tile (see sweep_face): a tile's per-node data and expm1 table
# (~(K + 12)·M·16·nv floats) then stay in L2 while the loop runs over all directions.
_TILE_ROWS = 16
_I0 = np.int32(0)  # index literal (dynamic_slice wants one integer type, also under x64)


def to_face(x, axis: int, sign: int):
    """(nx, ny, nz, ...) → (nw, nu, nv, ...) with w the sweep axis, oriented along the sweep
    (a JAX or a NumPy array: ``_native.world_strides`` reads the map off node numbers on the
    host)."""
    u, v = face_plane_axes(axis)
    y = x.transpose((axis, u, v) + tuple(range(3, x.ndim)))
    return y[::-1] if sign < 0 else y


def from_face(y, axis: int, sign: int):
    u, v = face_plane_axes(axis)
    if sign < 0:
        y = y[::-1]
    return jnp.moveaxis(y, (0, 1, 2), (axis, u, v))


def _pad_plane(x, M: int, periodic_u: bool, periodic_v: bool, fill):
    """Pad the last two axes (u, v) by M: wrapped on periodic sides, ``fill`` elsewhere (``fill``
    broadcasts against the padded array, e.g. (D, 1, 1, 1) boundary radiance per direction)."""
    lead = [(0, 0)] * (x.ndim - 2)
    if periodic_u:
        x = jnp.pad(x, lead + [(M, M), (0, 0)], mode="wrap")
    if periodic_v:
        x = jnp.pad(x, lead + [(0, 0), (M, M)], mode="wrap")
    wu = (0, 0) if periodic_u else (M, M)
    wv = (0, 0) if periodic_v else (M, M)
    if wu == wv == (0, 0):
        return x
    xp = jnp.pad(x, lead + [wu, wv])
    inside = np.zeros(xp.shape[-2:], bool)
    inside[wu[0] : wu[0] + x.shape[-2], wv[0] : wv[0] + x.shape[-1]] = True
    return jnp.where(inside, xp, jnp.asarray(fill, x.dtype))


def _fold_plane(x, M: int, periodic_u: bool, periodic_v: bool):
    """The transpose of ``_pad_plane`` with a zero fill: the last two axes (padded by M) back
    to their nodes, a periodic side's margins added into the nodes they wrap to, an open
    side's dropped."""
    for axis, per in ((x.ndim - 2, periodic_u), (x.ndim - 1, periodic_v)):
        n = x.shape[axis] - 2 * M
        if per:
            idx = (np.arange(n + 2 * M) - M) % n
            xm = jnp.moveaxis(x, axis, 0)
            x = jnp.moveaxis(jnp.zeros((n,) + xm.shape[1:], x.dtype).at[idx].add(xm), 0, axis)
        else:
            x = jax.lax.slice_in_dim(x, M, M + n, axis=axis)
    return x


def _initial_carry(q0, table, bc, D: int, M: int, periodic: tuple[bool, bool, bool],
                   halo=None):
    """The direction loops' padded carry before the first slab (D, M, nu + 2M, nv + 2M): on a
    periodic sweep axis each direction's source of the first slab ``q0`` ((M, nu, nv), or
    channels first (1 + J, M, nu, nv) with ``table`` (D, J)), the equilibrium guess for
    horizontal rays that never leave the domain; else the boundary radiance ``bc`` (D,).
    Padded with ``bc`` on open sides, wrapped on periodic ones."""
    per_w, per_u, per_v = periodic
    bc4 = bc[:, None, None, None]
    shape = (D,) + q0.shape[-3:]
    if per_w and table is not None:
        nj = table.shape[1]
        init = (q0[0][None] + jnp.einsum("dk,kmuv->dmuv", table, q0[1 : 1 + nj])).astype(bc.dtype)
    elif per_w:
        init = jnp.broadcast_to(q0[None], shape).astype(bc.dtype)
    else:
        init = jnp.broadcast_to(bc4, shape)
    if halo is not None:
        return halo.pad(init, M, per_u, per_v, bc4)
    return _pad_plane(init, M, per_u, per_v, bc4)


def _wrap_border(x, axis: int, n: int, M: int):
    """Rewrite the M border planes on each side of ``axis`` (interior [M, M+n)) by wrapping."""
    if n >= M:
        lo = jax.lax.slice_in_dim(x, n, n + M, axis=axis)
        hi = jax.lax.slice_in_dim(x, M, 2 * M, axis=axis)
    else:  # a plane thinner than the border wraps several times
        lo = jnp.take(x, (np.arange(-M, 0) % n) + M, axis=axis)
        hi = jnp.take(x, (np.arange(n, n + M) % n) + M, axis=axis)
    x = jax.lax.dynamic_update_slice_in_dim(x, lo, 0, axis=axis)
    return jax.lax.dynamic_update_slice_in_dim(x, hi, n + M, axis=axis)


class Halo(eqx.Module):
    """The plane's border exchange when (u, v) is split over a device mesh (inside ``shard_map``).

    Each device holds a (nu, nv) block of the plane; a slab's radiance is kept padded by M on
    both sides of u and v.  After a slab the M border rows/columns are rewritten from the
    neighbouring devices' interiors (``ppermute``: the MasPar's local communication), toroidally
    on periodic sides; on an open side the devices at the domain's edge keep the entering
    boundary radiance that the padding put there.  With one device along an axis this is the
    single-device wrap (periodic) or nothing (open).  ``None`` names an axis that is not split.
    """

    u_axis: str | None = eqx.field(static=True)
    v_axis: str | None = eqx.field(static=True)
    nu_dev: int = eqx.field(static=True)  # devices along u
    nv_dev: int = eqx.field(static=True)

    def refresh(self, xp, M: int, periodic_u: bool, periodic_v: bool):
        """Rewrite the M border planes of the last two axes of the padded array ``xp``."""
        xp = self._axis(xp, xp.ndim - 2, M, self.u_axis, self.nu_dev, periodic_u)
        return self._axis(xp, xp.ndim - 1, M, self.v_axis, self.nv_dev, periodic_v)

    def pad(self, x, M: int, periodic_u: bool, periodic_v: bool, fill):
        """Pad the last two axes by M with ``fill``, then fill the borders from the neighbours."""
        return self.refresh(_pad_plane(x, M, False, False, fill), M, periodic_u, periodic_v)

    @staticmethod
    def _axis(xp, axis: int, M: int, name, ndev: int, periodic: bool):
        n = xp.shape[axis] - 2 * M
        if ndev == 1:
            return _wrap_border(xp, axis, n, M) if periodic else xp
        if n < M:
            raise ValueError(f"a device's block ({n} nodes) is thinner than M = {M}")
        first = jax.lax.slice_in_dim(xp, M, 2 * M, axis=axis)  # → the previous device's top
        last = jax.lax.slice_in_dim(xp, n, n + M, axis=axis)  # → the next device's bottom
        up = [(i, i + 1) for i in range(ndev - 1)] + ([(ndev - 1, 0)] if periodic else [])
        down = [(i + 1, i) for i in range(ndev - 1)] + ([(0, ndev - 1)] if periodic else [])
        lo = jax.lax.ppermute(last, name, up)
        hi = jax.lax.ppermute(first, name, down)
        if not periodic:  # the domain's edge keeps the boundary radiance
            i = jax.lax.axis_index(name)
            lo = jnp.where(i == 0, jax.lax.slice_in_dim(xp, 0, M, axis=axis), lo)
            hi = jnp.where(i == ndev - 1, jax.lax.slice_in_dim(xp, n + M, n + 2 * M, axis=axis), hi)
        xp = jax.lax.dynamic_update_slice_in_dim(xp, lo, 0, axis=axis)
        return jax.lax.dynamic_update_slice_in_dim(xp, hi, n + M, axis=axis)


def _tile_rows(nu: int, target: int = _TILE_ROWS) -> int:
    """Rows per tile of the plane: the largest divisor of nu that is <= target."""
    return max(t for t in range(1, min(nu, target) + 1) if nu % t == 0)


def _shift_plane(x, bc, pq, M: int, periodic_u: bool, periodic_v: bool, halo=None):
    """y[m, d, u, v] = x[m, d, u − p_d, v − q_d]: the plane-to-plane step of every direction.

    x: (m, D, nu, nv); bc: (D,) radiance entering from outside the plane on open sides;
    pq: (D, 2) int steps.  The plane is padded by M (with bc, or wrapped) and each direction
    reads its window with a vmapped ``dynamic_slice``: one batched op, so neither the compiled
    graph nor the compile time grows with the (2M+1)² directions, and it runs at copy speed.
    """
    m, D, nu, nv = x.shape
    widths = ((0, 0), (0, 0), (M, M), (M, M))
    if halo is not None:
        xp = halo.pad(x, M, periodic_u, periodic_v, bc[None, :, None, None].astype(x.dtype))
    elif periodic_u and periodic_v:
        xp = jnp.pad(x, widths, mode="wrap")
    else:
        if periodic_u:
            x = jnp.pad(x, ((0, 0), (0, 0), (M, M), (0, 0)), mode="wrap")
        if periodic_v:
            x = jnp.pad(x, ((0, 0), (0, 0), (0, 0), (M, M)), mode="wrap")
        wu = (0, 0) if periodic_u else (M, M)
        wv = (0, 0) if periodic_v else (M, M)
        xp = jnp.pad(x, ((0, 0), (0, 0), wu, wv))
        inside = np.zeros(xp.shape[2:], bool)
        inside[wu[0] : wu[0] + x.shape[2], wv[0] : wv[0] + x.shape[3]] = True
        xp = jnp.where(inside, xp, bc[None, :, None, None].astype(x.dtype))

    def window(a, su, sv):
        return jax.lax.dynamic_slice(a, (jnp.zeros_like(su), su, sv), (m, nu, nv))

    start = M - pq
    return jax.vmap(window, in_axes=(1, 0, 0), out_axes=1)(xp, start[:, 0], start[:, 1])


class FaceGeometry(eqx.Module):
    """Static, per-face view of the lattice (arrays in the face frame (nw, nu, nv))."""

    free: jax.Array  # bool
    surf: jax.Array  # bool
    normal: jax.Array  # (nw, nu, nv, 3) normal in the face frame (u, v, w)
    blocked: jax.Array  # (nw, nu, nv, ceil(D/8)) uint8: bit d set if the segment of direction d
    #                     arriving at this node crosses a SOLID node (SURFACE nodes only)
    wscale: jax.Array | None = None  # (nw, nu, nv) float32: the sub-stepped scheme's per-node
    #                                  renormalization (``substep_weight_scale``); else None


class SweepConsts(eqx.Module):
    """Per-face direction constants, in the face frame."""

    unit: jax.Array  # (D, 3) L̂ in (u, v, w) components
    pq: jax.Array  # (D, 2) int in-plane steps (p, q)
    length: jax.Array  # (D,) |L| in lattice units
    weight: jax.Array  # (D,) solid-angle weights
    harm: jax.Array | None = None  # (D, K) the anisotropic basis Ỹ_k at each direction
    #                                (``_harmonics.Basis``; None or K = 0: isotropic)
    sun_phase: jax.Array | None = None  # (D,) the sun's phase function averaged over each
    #                                     direction's cell (the first-collision sun's channel)
    slope: jax.Array | None = None  # (D, 3) the lattice vectors L in world (x, y, z)
    #                                 components: the linear-source scheme (None: step scheme)
    sub: jax.Array | None = None  # (M − 1, D, 2) int: the sub-stepped scheme's in-plane
    #                               offsets of each direction's intermediate points from the
    #                               node it arrives at (``substep_offsets``); None: not it


def _source_table(consts: SweepConsts, dt):
    """(D, J) per-direction coefficients of the source channels beyond the isotropic one: the
    K moments' basis, then the sun's phase when there is one; and K.  (The linear scheme's
    three slope channels follow these J in Q; their table is ``consts.slope``.)"""
    D = consts.weight.shape[0]
    harm = jnp.zeros((D, 0), dt) if consts.harm is None else consts.harm.astype(dt)
    if consts.sun_phase is None:
        return harm, harm.shape[1]
    return jnp.concatenate([harm, consts.sun_phase.astype(dt)[:, None]], axis=1), harm.shape[1]


def _linear_node(r_mid, q, s, em, omp_half, phi, psi):
    """A node's segment (two halves of optical depth τ each) with the source linear along it:
    q − s/2 where the segment enters, q at the node, q + s/2 where it leaves (q: the node's
    source for this direction; s = L·G its change over the segment, G = h∇Q).  r_mid: the
    radiance entering.  The tables are those of ``linear_source_terms(τ)``: em = e^{−τ} − 1,
    omp_half = τψ/2 = (1 − φ)/2, φ, ψ.  Returns (radiance at the node, radiance leaving, the
    segment's mean radiance R̄).

    Each half's exact update (``_numerics.linear_source_terms``), with a = r_mid − (q − s/2)
    entering the arrival half and b = R_node − q entering the departure half:
    R_node = r_mid + em·a + s(1 − φ)/2, R_out = R_node + em·b + s(1 − φ)/2,
    R̄ = q + φ(a + b)/2 − ψs/2.  The slope integrates to 0 over the segment, so the balance
    R_out − R_in = 2τ(q − R̄) of the step scheme holds (energy is conserved); with s = 0 these
    are the step scheme's updates."""
    a = r_mid - q + 0.5 * s
    r_node = r_mid + em * a + omp_half * s
    b = r_node - q
    r_out = r_node + em * b + omp_half * s
    r_avg = q + 0.5 * phi * (a + b) - 0.5 * psi * s
    return r_node, r_out, r_avg


#: The programs of one face sweep (same arithmetic, same values and derivatives): "loop"
#: (``_sweep_face_loop``, cache-tiled loops: 2-3x faster on a CPU), "batched"
#: (``_sweep_face_batched``, all directions of a slab in one array: on an H100 130x faster than
#: "loop", whose ~150,000 small loop bodies per iteration take ~18 µs each there) and "pallas"
#: (the batched program with each slab step as one Pallas kernel, ``_pallas.py``: one pass
#: over the carry instead of about four; Triton on a GPU, interpreted (slowly) elsewhere; its
#: GPU speed not yet measured, so "auto" does not pick it).
KERNELS = ("auto", "loop", "batched", "pallas")


def _distinct_lengths(consts: SweepConsts, M: int, dt):
    """(length_k (K,), kidx (D,) int32): the distinct |L| of the face's directions (|L|² =
    p² + q² + M²: 6 / 10 / 20 values at M = 2 / 3 / 5) and each direction's index into them,
    so that a node's factors e^(−τ|L|) are computed once per distinct |L|, not per direction.
    (The host-side direction order d = (p+M)(2M+1) + (q+M), as in ``DirectionSet``.)"""
    pq_host = direction_set(M).pq
    ssq = pq_host[:, 0] ** 2 + pq_host[:, 1] ** 2
    uniq, kidx = np.unique(ssq, return_inverse=True)
    first = np.array([np.flatnonzero(ssq == v)[0] for v in uniq])
    return consts.length.astype(dt)[first], jnp.asarray(kidx, jnp.int32)


def kernel_for(backend: str | None = None) -> str:
    """The face-sweep program ``kernel="auto"`` stands for on ``backend`` (default: JAX's
    default backend): "loop" on a CPU, "batched" on an accelerator."""
    backend = backend or jax.default_backend()
    return "loop" if backend == "cpu" else "batched"


def sweep_face(Q, B, tau_half_unit, bc, geo: FaceGeometry, consts: SweepConsts, *, M: int,
               periodic: tuple[bool, bool, bool], warmup: int, surfaces: bool,
               attenuate: bool = True, fluence: bool = True,
               vol_range: tuple[int, int] | None = None, halo: Halo | None = None,
               kernel: str = "loop", recompute: bool = False):
    """One sweep over a face.  All arrays are in the face frame (nw, nu, nv).

    Q: source radiance at FREE nodes; B: radiosity at SURFACE nodes; tau_half_unit: σ_t·h/2 (the
    half-segment optical depth per unit |L|); bc: (D,) radiance entering through the domain
    boundary.  Returns (Λ, E, exit) where Λ and E are (nw, nu, nv) and ``exit`` is the carry
    after the last slab: (M, D, nu, nv), the radiance leaving the last M planes.

    kernel: the program that computes the values (``KERNELS``; resolved, not "auto"):
    "loop" (``_sweep_face_loop``, a loop over directions, 2-3× faster on a CPU) or "batched"
    (``_sweep_face_batched``, all directions at once: what a GPU wants).  Derivatives (JVPs, and
    through them the transposes the implicit adjoint needs) always come from the batched
    program, whose transpose stays compact (the loop's would scatter every direction's block
    into a full-size carry).  The batched program does the fog step everywhere (``attenuate``
    and ``vol_range`` only save work; the values are the same).

    The plan's switches (``_plan.py``): ``attenuate`` False (no fog) skips the fog step (rays
    just move), ``fluence`` False (no fog scattering) skips the Λ accumulation (Λ is returned
    as 0), and ``vol_range`` = [lo, hi) planes along the sweep restricts the fog work to the
    slabs that hold fog (outside, σ_t = 0 and Λ is not needed).  Derivatives honour
    ``fluence``; they compute the fog step everywhere (same values).

    halo: inside ``shard_map`` over a device mesh that splits the plane, the border exchange
    (see ``Halo``); the arrays are then this device's block of the plane.

    recompute: the derivatives' batched program keeps only each slab step's inputs (its carry
    and slab, ``jax.checkpoint``) and recomputes the step's coefficients (e^{−τ}, the linear
    scheme's φ, ψ, the blocking) wherever its linearization is applied: a linearised Jacobi
    step then holds 4-4.5× less, 195-631 B per node and direction instead of 826-1960
    (measured, ``SweepSolver.sweep_residuals``), at the price of the step's primal work in
    every product.
    """
    if kernel not in KERNELS[1:]:
        raise SolverError(f"sweep kernel must be one of {', '.join(KERNELS[1:])}, got {kernel!r}")
    vol = (bool(attenuate), bool(fluence), None if vol_range is None else tuple(vol_range))
    return _sweep_face(M, tuple(periodic), int(warmup), bool(surfaces), vol, halo, kernel,
                       bool(recompute), Q, B, tau_half_unit, bc, geo, consts)


@functools.partial(jax.custom_jvp, nondiff_argnums=(0, 1, 2, 3, 4, 5, 6, 7))
def _sweep_face(M, periodic, warmup, surfaces, vol, halo, kernel, recompute, Q, B, tau_half_unit,
                bc, geo, consts):
    del recompute  # the values' programs keep nothing
    if consts.sub is not None:  # the sub-stepped scheme's two programs
        kw = dict(M=M, periodic=periodic, warmup=warmup, surfaces=surfaces, fluence=vol[1])
        if kernel == "loop" and halo is None and _native_applies(halo, Q.dtype):
            return _native_substep_call(Q, B, tau_half_unit, bc, geo, consts, **kw, vol=vol)
        if kernel == "loop" and halo is None:
            return _sweep_face_substep_loop(Q, B, tau_half_unit, bc, geo, consts, **kw,
                                            vol=vol)
        return _sweep_face_substep(Q, B, tau_half_unit, bc, geo, consts, halo=halo, **kw)
    if kernel in ("batched", "pallas"):
        return _sweep_face_batched(Q, B, tau_half_unit, bc, geo, consts, M=M, periodic=periodic,
                                   warmup=warmup, surfaces=surfaces, fluence=vol[1], halo=halo,
                                   pallas=kernel == "pallas")
    return _sweep_face_loop(Q, B, tau_half_unit, bc, geo, consts, M=M, periodic=periodic,
                            warmup=warmup, surfaces=surfaces, vol=vol, halo=halo)


@_sweep_face.defjvp
def _sweep_face_jvp(M, periodic, warmup, surfaces, vol, halo, kernel, recompute, primals,
                    tangents):
    out = _sweep_face(M, periodic, warmup, surfaces, vol, halo, kernel, recompute, *primals)
    if primals[-1].sub is not None:
        batched = functools.partial(_sweep_face_substep, M=M, periodic=periodic, warmup=warmup,
                                    surfaces=surfaces, fluence=vol[1], halo=halo,
                                    recompute=recompute)
    else:
        batched = functools.partial(_sweep_face_batched, M=M, periodic=periodic, warmup=warmup,
                                    surfaces=surfaces, fluence=vol[1], halo=halo,
                                    recompute=recompute)
    _, t_out = jax.jvp(batched, primals, tangents)
    return out, t_out


def _slab_planes(nw: int, M: int, periodic_w: bool, warmup: int):
    """(total, order): the planes a face sweep visits, in sweep order: on a periodic sweep axis
    ``order`` (total,) in wrap order, ending with planes 0..nw-1 after a warm-up of at least
    ``warmup`` planes; on an open one planes 0..nw-1 then zero padding to ``total``, a multiple
    of M (``order`` None)."""
    if periodic_w:
        total = int(math.ceil((nw + warmup) / M) * M)
        return total, np.arange(nw - total, nw) % nw
    return int(math.ceil(nw / M) * M), None


def _slabber(nw: int, M: int, periodic_w: bool, warmup: int):
    """(slabs, ns): ``slabs(a)`` reshapes a face-frame array (nw, ...) into ns slabs of M planes
    in sweep order.  Open: zero-padded at the end to a multiple of M.  Periodic: the planes in
    wrap order, ending with planes 0..nw-1, preceded by a warm-up long enough for every
    non-horizontal ray to have entered through an open side."""
    total, order = _slab_planes(nw, M, periodic_w, warmup)
    if periodic_w:
        def pick(a):
            return jnp.take(a, order, axis=0)
    else:
        pad = total - nw

        def pick(a):
            return jnp.pad(a, [(0, pad)] + [(0, 0)] * (a.ndim - 1))

    ns = total // M

    def slabs(a):
        return pick(a).reshape((ns, M) + a.shape[1:])

    return slabs, ns


def _native_applies(halo, dt) -> bool:
    """Whether the loop kernel's values come from the native CPU kernel (``_native``): the
    step and linear schemes (``_sweep_face_loop``), isotropic or with moments (its general
    form where Q has channels), and the sub-stepped one (``_sweep_face_substep_loop``), on one
    device's whole plane, float32 or float64, on a CPU, where the kernel is built (and
    ``DIFFFOG_NATIVE`` does not turn it off)."""
    return halo is None and _native.serves(dt)


def _native_common(Q, tau_half_unit, geo: FaceGeometry, consts: SweepConsts, M: int,
                   periodic_w: bool, warmup: int, surfaces: bool):
    """What both native kernels' calls derive alike: (ns, length_k, kidx, normal, blocked,
    table or None, nk), the geometry's normal and blocking bytes dummies without surfaces."""
    dt = Q.dtype
    _, ns = _slabber(tau_half_unit.shape[0], M, periodic_w, warmup)
    length_k, kidx = _distinct_lengths(consts, M, dt)
    table, nk = _source_table(consts, dt) if Q.ndim == 4 else (None, 0)
    return (ns, length_k, kidx,
            geo.normal if surfaces else jnp.zeros((1,), dt),
            geo.blocked if surfaces else jnp.zeros((1,), jnp.uint8),
            table if table is not None and table.shape[1] else None, nk)


def _native_call(Q, B, tau_half_unit, bc, geo: FaceGeometry, consts: SweepConsts, *, M: int,
                 periodic: tuple[bool, bool, bool], warmup: int, surfaces: bool,
                 vol=(True, True, None), frame: tuple[int, int] | None = None, records=None,
                 exits: bool = True):
    """``_sweep_face_loop``'s values from the native kernel (``_native.sweep_face``); with
    ``frame`` = (axis, sign), Q and B in the world frame and Λ, E returned in it
    (``sweep_face_world``); ``records``: the plan's surface records (``_native.
    surface_records``) or None; ``exits`` False: the radiance leaving is not made (None)."""
    dt = Q.dtype
    ns, length_k, kidx, normal, blocked, table, nk = _native_common(
        Q, tau_half_unit, geo, consts, M, periodic[0], warmup, surfaces)
    s0, s1, fog_on = _fog_slabs(vol, ns, M, periodic[0])
    return _native.sweep_face(
        Q, B, tau_half_unit, normal, blocked, geo.free, geo.surf if surfaces else geo.free,
        bc.astype(dt), length_k, kidx, consts.weight.astype(dt), consts.unit.astype(dt),
        M - jnp.asarray(consts.pq, jnp.int32), M=M, ns=ns,
        segment=(s0, s1, fog_on, vol[1]), surfaces=surfaces, periodic=periodic,
        table=table, nk=nk,
        slope=consts.slope.astype(dt) if consts.slope is not None else None, frame=frame,
        records=records, exits=exits)


def _native_substep_call(Q, B, tau_half_unit, bc, geo: FaceGeometry, consts: SweepConsts, *,
                         M: int, periodic: tuple[bool, bool, bool], warmup: int,
                         surfaces: bool, fluence: bool = True, vol=(True, True, None)):
    """``_sweep_face_substep_loop``'s values from the native kernel
    (``_native.sweep_substep``)."""
    if consts.slope is not None:
        raise SolverError("the sub-stepped scheme has no linear-source variant")
    dt = Q.dtype
    ns, length_k, kidx, normal, blocked, table, nk = _native_common(
        Q, tau_half_unit, geo, consts, M, periodic[0], warmup, surfaces)
    s0, s1, fog_on = _substep_fog_slabs(vol, ns, M, periodic[0])
    return _native.sweep_substep(
        Q, B, tau_half_unit, normal, blocked, geo.free, geo.surf, bc.astype(dt), length_k,
        kidx, consts.weight.astype(dt), consts.unit.astype(dt),
        M - jnp.asarray(consts.pq, jnp.int32), M - jnp.asarray(consts.sub, jnp.int32), M=M,
        ns=ns, segment=(s0, s1, fog_on, fluence), surfaces=surfaces, periodic=periodic,
        table=table, nk=nk)


def _fog_slabs(vol, ns: int, M: int, periodic_w: bool) -> tuple[int, int, bool]:
    """(s0, s1, fog step?): the slabs [s0, s1) that hold fog do the fog step (and Λ), the others
    neither (``vol`` = (attenuate, fluence, vol_range))."""
    attenuate, _, vol_range = vol
    if vol_range is None or periodic_w or not attenuate:
        return 0, ns, attenuate
    return vol_range[0] // M, min(ns, -(-vol_range[1] // M)), True


def _substep_fog_slabs(vol, ns: int, M: int, periodic_w: bool) -> tuple[int, int, bool]:
    """(s0, s1, fog?): the slabs [s0, s1) where the sub-stepped loop and its transpose (which
    must agree on it) take the fog step: ``_fog_slabs``' and the one after them, whose
    crossings finish the last fog slab's Λ; none without fog (s0 = s1 = ns)."""
    s0, s1, fog_on = _fog_slabs(vol, ns, M, periodic_w)
    return (s0, min(ns, s1 + 1), True) if fog_on else (ns, ns, False)


def world_native_applies(kernel: str, consts: SweepConsts, dt) -> bool:
    """Whether ``sweep_face_world`` serves a face: the loop kernel's values on one device, the
    native kernel built, the step or linear scheme (not the sub-stepped one)."""
    return kernel == "loop" and consts.sub is None and _native_applies(None, dt)


def substep_native_applies(kernel: str, consts: SweepConsts, dt) -> bool:
    """Whether the native kernel serves a sub-stepped face (``sweep_face``'s loop kernel on one
    device: ``_native_substep_call``)."""
    return kernel == "loop" and consts.sub is not None and _native_applies(None, dt)


def sweep_face_world(q, b, tau_half_unit, bc, geo: FaceGeometry, consts: SweepConsts, *,
                     axis: int, sign: int, M: int, periodic: tuple[bool, bool, bool],
                     warmup: int, surfaces: bool, attenuate: bool = True, fluence: bool = True,
                     vol_range: tuple[int, int] | None = None, recompute: bool = False,
                     records=None, exits: bool = True):
    """``sweep_face`` of the face (``axis``, ``sign``) with q, b, Λ and E in the world frame
    (nx, ny, nz[, ...]), the geometry, τ and the radiance leaving in the face frame: the values
    from the native kernel, which reads and writes each face node's world node, so that
    neither the face's copies of the sources nor the transposes of Λ and E back are made
    (on cloud-plane's 20 source and 16 fluence channels, this 2-core CPU, they took about half
    as long as the sweeps themselves: a light solve 9.4 → 7.4 s without them).  Derivatives
    are the face-frame path's (``sweep_face`` between ``to_face`` and ``from_face``: its
    batched program's).  Where ``world_native_applies``.  ``records``: the face's surface
    records made with the plan (``SweepGeometry.records``), or None (the kernel makes them);
    ``exits`` False: the radiance leaving the face is not made (returned as None: a light
    solve never reads it)."""
    vol = (bool(attenuate), bool(fluence), None if vol_range is None else tuple(vol_range))
    return _sweep_face_world(int(axis), int(sign), M, tuple(periodic), int(warmup),
                             bool(surfaces), vol, bool(recompute), bool(exits), q, b,
                             tau_half_unit, bc, geo, consts, records)


def _face_path(axis, sign, M, periodic, warmup, surfaces, vol, recompute, q, b, tau_half_unit, bc,
               geo, consts, records=None):
    """``sweep_face_world`` through the face frame (its derivatives' program; the records
    only spare the native kernel work)."""
    del records
    lf, ef, ex = _sweep_face(M, periodic, warmup, surfaces, vol, None, "loop", recompute,
                             to_face(q, axis, sign), to_face(b, axis, sign), tau_half_unit, bc,
                             geo, consts)
    return from_face(lf, axis, sign), from_face(ef, axis, sign), ex


@functools.partial(jax.custom_jvp, nondiff_argnums=(0, 1, 2, 3, 4, 5, 6, 7, 8))
def _sweep_face_world(axis, sign, M, periodic, warmup, surfaces, vol, recompute, exits, q, b,
                      tau_half_unit, bc, geo, consts, records):
    return _native_call(q, b, tau_half_unit, bc, geo, consts, M=M, periodic=periodic,
                        warmup=warmup, surfaces=surfaces, vol=vol, frame=(axis, sign),
                        records=records, exits=exits)


@_sweep_face_world.defjvp
def _sweep_face_world_jvp(axis, sign, M, periodic, warmup, surfaces, vol, recompute, exits,
                          primals, tangents):
    path = functools.partial(_face_path, axis, sign, M, periodic, warmup, surfaces, vol,
                             recompute)
    out, t_out = jax.jvp(path, primals, tangents)
    if not exits:
        out, t_out = (*out[:2], None), (*t_out[:2], None)
    return out, t_out


def _sweep_face_loop(Q, B, tau_half_unit, bc, geo: FaceGeometry, consts: SweepConsts, *,
                     M: int, periodic: tuple[bool, bool, bool], warmup: int, surfaces: bool,
                     vol=(True, True, None), halo: Halo | None = None):
    """``sweep_face`` (same arguments and results) as loops that keep the work in cache.

    On a CPU the values come from the native kernel instead (``_native``: the same sweep in
    C++, equal to rounding), where it is built; the loops below serve a device mesh's halo (and
    a CPU without a compiler, or ``DIFFFOG_NATIVE=0``).

    Loop structure (what makes it fast on a CPU; the arithmetic is the module's step update):
    ``lax.scan`` over slabs → ``fori_loop`` over row tiles of the plane → ``fori_loop`` over
    the D directions.  The innermost body works on one direction's (M, rows, nv) block: a
    ``dynamic_slice`` of the previous slab's padded radiance at offset −(p, q) (the shift),
    elementwise updates, Λ and E accumulated in place (Λ + iE in one complex accumulator when
    there are surfaces, so one fused loop serves both), and a ``dynamic_update_slice`` into
    the other of two carry buffers.  Compared with one vmapped shift over all directions this
    keeps every intermediate in cache and avoids XLA's gather and leading-axis reductions
    (measured 2-3× faster, benchmarks/bench_sweep.py); the graph does not grow with D.
    expm1(−τ|L|) is evaluated once per node and distinct |L| (6/10/20 values at M = 2/3/5
    instead of 25/49/121).  The padded carry's border holds ``bc`` (open sides) and is never
    written, or is refreshed by wrapping (periodic sides).
    """
    dt = Q.dtype
    if _native_applies(halo, dt):  # the same sweep as one custom call
        return _native_call(Q, B, tau_half_unit, bc, geo, consts, M=M, periodic=periodic,
                            warmup=warmup, surfaces=surfaces, vol=vol)

    # (XLA's loops from here)
    nw, nu, nv = Q.shape[:3]
    P = 2 * M + 1
    D = P * P
    per_w, per_u, per_v = periodic
    # Anisotropic: Q (nw, nu, nv, 1 + J [+ 3]), the isotropic part, then the sources that
    # direction d weights by ``_source_table``'s row d (the K moments', then the sun's), then
    # with the linear scheme the source's slope h∇Q (3 channels); Λ gets K moments
    aniso = Q.ndim == 4
    linear = consts.slope is not None
    nk = nj = 0

    slabs, ns = _slabber(nw, M, per_w, warmup)
    total = ns * M  # planes swept (warm-up or padding included)

    # Direction constants.  The host-side direction order (d = (p+M)(2M+1) + (q+M), as in
    # DirectionSet) gives the distinct |L|² = p² + q² + M²; the values come from ``consts``.
    length_k, kidx = _distinct_lengths(consts, M, dt)  # (K,) distinct |L|; each d's index
    unit = consts.unit.astype(dt)
    weight = consts.weight.astype(dt)
    bc_d = bc.astype(dt)
    start = M - jnp.asarray(consts.pq, jnp.int32)  # window origin in the padded plane

    attenuate, fluence, _ = vol
    s0, s1, fog_on = _fog_slabs(vol, ns, M, per_w)

    # the slabbed inputs, then the scans
    byte_of = jnp.asarray(np.arange(D) // 8, jnp.int32)
    bit_of = jnp.asarray((np.arange(D) % 8).astype(np.uint8))

    Qs, Bs, ts = slabs(Q), slabs(B), slabs(tau_half_unit)
    if aniso:  # channels first: (ns, 1 + J, M, nu, nv)
        Qs = jnp.moveaxis(Qs, -1, 1)
        table, nk = _source_table(consts, dt)  # (D, J)
        nj = table.shape[1]
        wharm = table[:, :nk] * weight[:, None]
        if linear:
            slope_in = consts.slope.astype(dt)  # (D, 3): L in world components
    passes = (slabs(geo.free) | slabs(geo.surf)) if surfaces else slabs(geo.free)
    if surfaces:
        ns_ = jnp.moveaxis(slabs(geo.normal), -1, 1)  # (ns, 3, M, nu, nv)
        bits = jnp.moveaxis(slabs(geo.blocked), -1, 1)  # (ns, ceil(D/8), M, nu, nv)
    else:
        ns_ = jnp.zeros((ns, 1), dt)
        bits = jnp.zeros((ns, 1), jnp.uint8)
    tu = _tile_rows(nu)

    def step(carry, slab, attenuate=attenuate, fluence=fluence):
        src, dst = carry  # (D, M, nu + 2M, nv + 2M): previous slab's radiance / next slab's
        Qs_, Bs_, ts_, ns_s, bits_s, pass_s = slab
        both = fluence and surfaces  # Λ + iE in one complex accumulator

        def tile(t, c):
            dst, lam_s, irr_s, mom_s = c
            u0 = jnp.asarray(t * tu, jnp.int32)  # int32 indices also under jax_enable_x64
            rows = lambda a: jax.lax.dynamic_slice_in_dim(a, u0, tu, axis=a.ndim - 2)  # noqa
            Qt, Bt, pt = rows(Qs_), rows(Bs_), rows(pass_s)
            if aniso:  # (1 + J [+ 3], M, tu, nv): the isotropic source and the others
                Qa, Qt = Qt[1:], Qt[0]
            # half-segment factor expm1(-τ|L|) for each distinct |L|: (K, M, tu, nv)
            if attenuate:
                tau_k = rows(ts_)[None] * length_k[:, None, None, None]  # half-segment depth
                em_k = jnp.expm1(-tau_k)
                # segment averages (Λ): the whole node segment [2τ], or its departure half [τ]
                # after a blocked arrival
                if linear:
                    avg1_k, psi_k = linear_source_terms(tau_k)[:2]
                    omp_k = 0.5 * tau_k * psi_k
                else:
                    avg2_k, avg1_k = one_minus_exp_over(2.0 * tau_k), one_minus_exp_over(tau_k)
            if surfaces:
                nt, bt = rows(ns_s), rows(bits_s)
            zero = jnp.zeros((M, tu, nv), dt)
            acc0 = jax.lax.complex(zero, zero) if both else zero
            macc0 = jnp.zeros((nk, M, tu, nv), dt)
            c_Qt = Qt

            def direction(d, c):
                dst, acc, macc = c
                d = jnp.asarray(d, jnp.int32)
                r_mid = jax.lax.dynamic_slice(src, (d, _I0, u0 + start[d, 0], start[d, 1]),
                                              (1, M, tu, nv))[0]
                Qt = c_Qt  # this direction's source: Q_0 + Σ_j table[d, j] Q_j
                if aniso and nj:
                    hd = jax.lax.dynamic_index_in_dim(table, d, 0, keepdims=False)
                    Qt = c_Qt + sum(hd[k] * Qa[k] for k in range(nj))
                at_k = lambda a: jax.lax.dynamic_index_in_dim(a, kidx[d], 0, keepdims=False)  # noqa
                if attenuate and linear:  # the source linear along the node's segment
                    sd = jax.lax.dynamic_index_in_dim(slope_in, d, 0, keepdims=False)
                    sl = sd[0] * Qa[nj] + sd[1] * Qa[nj + 1] + sd[2] * Qa[nj + 2]
                    em = at_k(em_k)
                    r_arr, r_through, r_avg = _linear_node(
                        r_mid, Qt, sl, em, at_k(omp_k), at_k(avg1_k), at_k(psi_k))
                elif attenuate:
                    em = at_k(em_k)
                    # half-segment in this node (arrival): R + expm1(-τ)(R - Q); τ = 0 off fog
                    r_arr = r_mid + em * (r_mid - Qt)
                    # the radiance averaged over the node's segment, for Λ (conservative)
                    r_avg = Qt + (r_mid - Qt) * at_k(avg2_k)
                else:
                    r_arr = r_avg = r_mid
                w = weight[d]
                if surfaces:
                    byte = jax.lax.dynamic_index_in_dim(bt, byte_of[d], 0, keepdims=False)
                    blocked = (byte >> bit_of[d]) & 1
                    r_arr = jnp.where(blocked > 0, Bt, r_arr)
                    if attenuate and fluence:  # blocked: only the departure half is in fog
                        r_avg = jnp.where(blocked > 0, Qt + (Bt - Qt) * at_k(avg1_k), r_avg)
                    else:
                        r_avg = r_arr
                    if attenuate and linear:  # blocked: a constant source in the departure half
                        r_through = jnp.where(blocked > 0, Bt + em * (Bt - Qt), r_through)
                    ldotn = nt[0] * unit[d, 0] + nt[1] * unit[d, 1] + nt[2] * unit[d, 2]
                    cos_w = jnp.maximum(-ldotn, 0.0) * w
                    if both:
                        acc = acc + jax.lax.complex(r_avg * w, r_arr * cos_w)
                    else:
                        acc = acc + r_arr * cos_w
                elif fluence:
                    acc = acc + r_avg * w
                if aniso and fluence and nk:  # the moments Σ_d w_d Ỹ_k(d) R̄_d
                    wh = jax.lax.dynamic_index_in_dim(wharm, d, 0, keepdims=False)
                    macc = macc + wh[:, None, None, None] * r_avg[None]
                # second half-segment
                if not (attenuate and linear):
                    r_through = r_arr + em * (r_arr - Qt) if attenuate else r_arr
                r_out = jnp.where(pt, r_through, 0.0)
                dst = jax.lax.dynamic_update_slice(dst, r_out[None], (d, _I0, M + u0, _I0 + M))
                return dst, acc, macc

            dst, acc, macc = jax.lax.fori_loop(0, D, direction, (dst, acc0, macc0))
            if both:
                lam, irr = jnp.real(acc), jnp.imag(acc)
            else:
                lam, irr = (zero, acc) if surfaces else ((acc, zero) if fluence else (zero, zero))
            lam_s = jax.lax.dynamic_update_slice_in_dim(lam_s, lam, u0, axis=1)
            irr_s = jax.lax.dynamic_update_slice_in_dim(irr_s, irr, u0, axis=1)
            mom_s = jax.lax.dynamic_update_slice_in_dim(mom_s, macc, u0, axis=2)
            return dst, lam_s, irr_s, mom_s

        zs = jnp.zeros((M, nu, nv), dt)
        zm = jnp.zeros((nk, M, nu, nv), dt)
        dst, lam, irr, mom = jax.lax.fori_loop(0, nu // tu, tile, (dst, zs, zs, zm))
        if nk:  # (M, nu, nv, 1 + K): Λ, then the moments
            lam = jnp.concatenate([lam[..., None], jnp.moveaxis(mom, 0, -1)], axis=-1)
        if halo is not None:  # border rows, then columns (corners included), from neighbours
            dst = halo.refresh(dst, M, per_u, per_v)
        else:  # refresh the wrapped border rows, then columns (corners included)
            if per_u:
                dst = _wrap_border(dst, 2, nu, M)
            if per_v:
                dst = _wrap_border(dst, 3, nv, M)
        return (dst, src), (lam, irr)

    init = _initial_carry(Qs[0], table if aniso else None, bc_d, D, M, periodic, halo)
    # unroll=2: the two carry buffers swap roles every slab; unrolled, they keep their buffers
    # (no copy of the carry per slab).
    xs = (Qs, Bs, ts, ns_, bits, passes)
    segments = [seg for seg in ((0, s0, False, False), (s0, s1, fog_on, fluence),
                                (s1, ns, False, False)) if seg[1] > seg[0]]
    carry, outs = (init, init), []
    for a, b, on, fl in segments:
        fn = functools.partial(step, attenuate=on, fluence=fl)
        carry, out = jax.lax.scan(fn, carry, jax.tree.map(lambda x: x[a:b], xs), unroll=2)
        outs.append(out)
    last = carry[0]
    lam = jnp.concatenate([o[0] for o in outs]) if len(outs) > 1 else outs[0][0]
    irr = jnp.concatenate([o[1] for o in outs]) if len(outs) > 1 else outs[0][1]
    exit_ = jnp.swapaxes(last[..., M : M + nu, M : M + nv], 0, 1)
    lam = lam.reshape((total,) + lam.shape[2:])
    irr = irr.reshape((total,) + irr.shape[2:])
    if per_w:
        lam, irr = lam[total - nw :], irr[total - nw :]
    else:
        lam, irr = lam[:nw], irr[:nw]
    return lam, irr, exit_


def _sweep_face_batched(Q, B, tau_half_unit, bc, geo: FaceGeometry, consts: SweepConsts, *,
                        M: int, periodic: tuple[bool, bool, bool], warmup: int, surfaces: bool,
                        fluence: bool = True, halo: Halo | None = None, recompute: bool = False,
                        pallas: bool = False):
    """``sweep_face`` with every direction of a slab in one batched array: the shift is one
    vmapped ``dynamic_slice`` over the padded carry (M, D, nu, nv).  Slower forward than
    ``_sweep_face_loop`` but its linearization transposes into an equally compact program, so
    ``sweep_face`` uses it for derivatives (the implicit adjoint transposes the Jacobi map).

    pallas: each slab step (on one device's whole plane) is the Pallas kernel
    ``_pallas.slab_step`` (values only; same arithmetic, one pass over the carry).
    """
    nw, nu, nv = Q.shape[:3]
    P = 2 * M + 1
    D = P * P
    per_w, per_u, per_v = periodic
    dt = Q.dtype
    aniso = Q.ndim == 4  # Q (nw, nu, nv, 1 + J): see ``_sweep_face_loop``

    slabs, ns = _slabber(nw, M, per_w, warmup)
    total = ns * M  # planes swept (warm-up or padding included)

    xs = (slabs(Q), slabs(B), slabs(tau_half_unit), slabs(geo.free), slabs(geo.surf),
          jnp.moveaxis(slabs(geo.normal), -1, 0).swapaxes(0, 1), jnp.moveaxis(slabs(geo.blocked), -1, 2))
    unit = consts.unit.astype(dt)
    length = consts.length.astype(dt)
    weight = consts.weight.astype(dt)
    bc_d = bc.astype(dt)
    pq = jnp.asarray(consts.pq, jnp.int32)

    byte_of = np.arange(D) // 8
    bit_of = jnp.asarray((np.arange(D) % 8).astype(np.uint8))[None, :, None, None]
    w4 = weight[None, :, None, None]
    linear = consts.slope is not None
    if aniso:
        table, nk = _source_table(consts, dt)  # (D, J)
        nj = table.shape[1]
        harm = table[:, :nk]
        if linear:
            slope_in = consts.slope.astype(dt)  # (D, 3): L in world components

    def source(Qs):  # (M, nu, nv[, 1 + J [+ 3]]) → per node and direction (M, D or 1, nu, nv)
        if not aniso:
            return Qs[:, None]
        return Qs[..., 0][:, None] + jnp.einsum("muvk,dk->mduv", Qs[..., 1 : 1 + nj], table)
    len4 = length[None, :, None, None]
    u4 = [unit[None, :, c, None, None] for c in range(3)]

    def step(carry, slab):
        Qs, Bs, ts, fs, ss, ns, bits = slab  # (M, nu, nv); normal (3, M, nu, nv)
        r_mid = _shift_plane(carry, bc_d, pq, M, per_u, per_v, halo)
        # half-segment in this node (arrival): R + expm1(-τ)(R - Q); τ = 0 off the fog.
        # (Written with broadcasts rather than einsum: XLA on CPU then fuses each reduction
        # with the elementwise work, 2-3x faster than dot_general here.)
        tau = ts[:, None] * len4
        em = jnp.expm1(-tau)
        q4 = source(Qs)
        if linear:  # the source linear along the node's segment (``_linear_node``)
            sl = jnp.einsum("muvk,dk->mduv", Qs[..., 1 + nj :], slope_in)
            phi, psi = linear_source_terms(tau)[:2]
            r_arr, r_through, r_avg = _linear_node(r_mid, q4, sl, em, 0.5 * tau * psi, phi, psi)
        else:
            r_arr = r_mid + em * (r_mid - q4)
            # Λ from the radiance averaged over the node's segment (conservative; module doc)
            r_avg = q4 + (r_mid - q4) * one_minus_exp_over(2.0 * tau)
        if surfaces:
            blocked = (jnp.take(bits, byte_of, axis=1) >> bit_of) & 1
            r_arr = jnp.where(blocked > 0, Bs[:, None], r_arr)
            r_avg = jnp.where(blocked > 0, q4 + (Bs[:, None] - q4) * one_minus_exp_over(tau), r_avg)
            if linear:  # blocked: a constant source in the departure half
                r_through = jnp.where(blocked > 0, Bs[:, None] + em * (Bs[:, None] - q4),
                                      r_through)
        if fluence:
            lam = (r_avg * w4).sum(1)
            if aniso and nk:
                mom = jnp.einsum("mduv,dk->muvk", r_avg * w4, harm)
                lam = jnp.concatenate([lam[..., None], mom], axis=-1)
        else:
            lam = jnp.zeros(Qs.shape[:3] + ((1 + nk,) if aniso and nk else ()), dt)
        if not linear:
            r_through = r_arr + em * (r_arr - q4)  # second half-segment
        if surfaces:
            ldotn = ns[0][:, None] * u4[0] + ns[1][:, None] * u4[1] + ns[2][:, None] * u4[2]
            irr = (r_arr * jnp.maximum(-ldotn, 0.0) * w4).sum(1)
            r_out = jnp.where(fs[:, None] | ss[:, None], r_through, 0.0)
        else:
            irr = jnp.zeros(lam.shape[:3], dt)
            r_out = jnp.where(fs[:, None], r_through, 0.0)
        return r_out, (lam, irr)

    if pallas and halo is None:
        from . import _pallas  # Pallas is imported only where it runs (0.3 s)

        step = functools.partial(_pallas.slab_step, pq=pq, length=length, weight=weight,
                                 bc=bc_d, unit=unit, M=M, periodic_uv=(per_u, per_v),
                                 surfaces=surfaces, fluence=fluence,
                                 table=table if aniso else None, nk=nk if aniso else 0,
                                 slope=slope_in if linear else None)
    if per_w:  # equilibrium guess for horizontal rays that never leave a periodic domain
        init = jnp.broadcast_to(source(xs[0][0]), (M, D, nu, nv)).astype(dt)
    else:
        init = jnp.broadcast_to(bc.astype(dt)[None, :, None, None], (M, D, nu, nv))
    body = jax.checkpoint(step, prevent_cse=False) if recompute else step
    exit_, (lam, irr) = jax.lax.scan(body, init, xs)
    lam = lam.reshape((total,) + lam.shape[2:])
    irr = irr.reshape((total,) + irr.shape[2:])
    if per_w:
        lam, irr = lam[total - nw :], irr[total - nw :]
    else:
        lam, irr = lam[:nw], irr[:nw]
    return lam, irr, exit_


def _unslabs(x, nw: int, periodic_w: bool):
    """The transpose of ``_slabber``'s ``slabs``: x (ns, M, ...) → (nw, ...), the planes a
    periodic sweep visits more than once (its warm-up) summed, the open sweep's padding
    dropped."""
    total = x.shape[0] * x.shape[1]
    x = x.reshape((total,) + x.shape[2:])
    if periodic_w:
        order = np.arange(nw - total, nw) % nw
        return jnp.zeros((nw,) + x.shape[1:], x.dtype).at[order].add(x)
    return x[:nw]


def sweep_face_transposed(lam_bar, irr_bar, tau_half_unit, geo: FaceGeometry,
                          consts: SweepConsts, *, M: int, periodic: tuple[bool, bool, bool],
                          warmup: int, surfaces: bool, fluence: bool = True,
                          q_channels: int = 0, vol_range: tuple[int, int] | None = None,
                          attenuate: bool = True):
    """The transpose of one face sweep's linear map (Q, B) → (Λ, E) at fixed τ and zero
    boundary radiance (the map a light solve's adjoint needs, ``_solver._jacobi_transposed``):
    (Λ̄, Ē) → (Q̄, B̄), the step scheme (``_sweep_face_batched``'s arithmetic, whose transpose
    by JAX it equals to rounding) as a loop like ``_sweep_face_loop``: the slabs in reverse,
    each direction's radiance cotangent carried back one slab (the shift's transpose: written
    into the previous slab's padded plane at the window the forward read, periodic margins
    folded back), per row tile and direction the node's update transposed.  Nothing is kept
    between calls (the JAX transpose of a linearised sweep keeps ~0.8-1.6 KB per node and
    direction, or recomputes the step's factors per product).

    ``q_channels``: 0 for an isotropic source Q (nw, nu, nv), else 1 + J (the channels of
    ``_source_table``); Λ̄ then has 1 + K channels when the table has K moments.  The
    sub-stepped scheme (``consts.sub``) goes to ``_sweep_face_substep_transposed``, which
    takes ``vol_range`` (the planes that hold fog) and ``attenuate`` (False: no fog at all) as
    its forward loop does; the linear-source scheme has none."""
    nw, nu, nv = tau_half_unit.shape
    P = 2 * M + 1
    D = P * P
    per_w, per_u, per_v = periodic
    dt = tau_half_unit.dtype
    aniso = q_channels > 0
    if consts.sub is not None:
        return _sweep_face_substep_transposed(
            lam_bar, irr_bar, tau_half_unit, geo, consts, M=M, periodic=periodic, warmup=warmup,
            surfaces=surfaces, fluence=fluence, q_channels=q_channels, vol_range=vol_range,
            attenuate=attenuate)
    if consts.slope is not None:
        raise SolverError("sweep_face_transposed: the step and sub-stepped schemes only")
    slabs, ns = _slabber(nw, M, per_w, warmup)
    total = ns * M
    length_k, kidx = _distinct_lengths(consts, M, dt)  # (K,) distinct |L|; each d's index
    unit = consts.unit.astype(dt)
    weight = consts.weight.astype(dt)
    start = M - jnp.asarray(consts.pq, jnp.int32)
    byte_of = jnp.asarray(np.arange(D) // 8, jnp.int32)
    bit_of = jnp.asarray((np.arange(D) % 8).astype(np.uint8))
    nk = nj = 0
    if aniso:
        table, nk = _source_table(consts, dt)  # (D, J)
        nj = table.shape[1]
        if 1 + nj != q_channels:
            raise SolverError(f"sweep_face_transposed: {q_channels} source channels, the "
                              f"table has {1 + nj}")
        wharm = table[:, :nk] * weight[:, None]
    tu = _tile_rows(nu)

    # the outputs' cotangents over the planes swept (warm-up and padding get none)
    def full(x):
        z = jnp.zeros((total,) + x.shape[1:], dt)
        return z.at[total - nw :].set(x) if per_w else z.at[:nw].set(x)

    lam_bar = lam_bar.astype(dt) if fluence else jnp.zeros(lam_bar.shape, dt)
    if aniso and nk:  # channels first: (ns, 1 + K, M, nu, nv)
        lbs = jnp.moveaxis(full(lam_bar).reshape((ns, M) + lam_bar.shape[1:]), -1, 1)
    else:
        lbs = full(lam_bar).reshape((ns, M, nu, nv))
    ebs = full(irr_bar.astype(dt)).reshape((ns, M, nu, nv))
    ts = slabs(tau_half_unit)
    passes = (slabs(geo.free) | slabs(geo.surf)) if surfaces else slabs(geo.free)
    if surfaces:
        nrm = jnp.moveaxis(slabs(geo.normal), -1, 1)
        bits = jnp.moveaxis(slabs(geo.blocked), -1, 1)
    else:
        nrm = jnp.zeros((ns, 1), dt)
        bits = jnp.zeros((ns, 1), jnp.uint8)
    nq = q_channels if aniso else 1

    def step(abar, slab):
        lb, eb, ts_, nrm_s, bits_s, pass_s = slab
        # (D, M, nu, nv): the cotangent of this slab's outgoing radiance (its padded carry's
        # margins are copies of the interior on periodic sides, the boundary's on open ones)
        rbo = _fold_plane(abar, M, per_u, per_v)
        tau_k = ts_[None] * length_k[:, None, None, None]
        em_k = jnp.expm1(-tau_k)
        avg2_k, avg1_k = one_minus_exp_over(2.0 * tau_k), one_minus_exp_over(tau_k)
        nxt0 = jnp.zeros((D, M, nu + 2 * M, nv + 2 * M), dt)
        qb0 = jnp.zeros((nq, M, nu, nv), dt)
        bb0 = jnp.zeros((M, nu, nv), dt)

        def tile(t, c):
            nxt, qb_s, bb_s = c
            u0 = jnp.asarray(t * tu, jnp.int32)
            rows = lambda a: jax.lax.dynamic_slice_in_dim(a, u0, tu, axis=a.ndim - 2)  # noqa
            pt, lt, et = rows(pass_s), rows(lb), rows(eb)
            em_t, a2_t, a1_t = rows(em_k), rows(avg2_k), rows(avg1_k)
            if surfaces:
                nt, bt = rows(nrm_s), rows(bits_s)
            blk = (M, tu, nv)

            def direction(d, c):
                nxt, qb, bb = c
                d = jnp.asarray(d, jnp.int32)
                k = kidx[d]
                at_k = lambda a: jax.lax.dynamic_index_in_dim(a, k, 0, keepdims=False)  # noqa
                em, a2 = at_k(em_t), at_k(a2_t)
                ro = jax.lax.dynamic_slice(rbo, (d, _I0, u0, _I0), (1,) + blk)[0]
                r_through = jnp.where(pt, ro, 0.0)
                r_arr = r_through + em * r_through
                qd = -em * r_through
                w = weight[d]
                if aniso and nk:
                    wh = jax.lax.dynamic_index_in_dim(wharm, d, 0, keepdims=False)
                    r_avg = w * lt[0] + sum(wh[j] * lt[1 + j] for j in range(nk))
                else:
                    r_avg = w * lt
                if surfaces:
                    ldotn = nt[0] * unit[d, 0] + nt[1] * unit[d, 1] + nt[2] * unit[d, 2]
                    r_arr = r_arr + et * jnp.maximum(-ldotn, 0.0) * w
                    byte = jax.lax.dynamic_index_in_dim(bt, byte_of[d], 0, keepdims=False)
                    blocked = ((byte >> bit_of[d]) & 1) > 0
                    a1 = at_k(a1_t)
                    bb = bb + jnp.where(blocked, r_arr + a1 * r_avg, 0.0)
                    qd = qd + jnp.where(blocked, (1.0 - a1) * r_avg,
                                        -em * r_arr + (1.0 - a2) * r_avg)
                    r_mid = jnp.where(blocked, 0.0, r_arr + em * r_arr + a2 * r_avg)
                else:
                    qd = qd - em * r_arr + (1.0 - a2) * r_avg
                    r_mid = r_arr + em * r_arr + a2 * r_avg
                if aniso:
                    hd = jax.lax.dynamic_index_in_dim(table, d, 0, keepdims=False)
                    qb = qb + jnp.stack([qd] + [hd[j] * qd for j in range(nj)])
                else:
                    qb = qb + qd[None]
                nxt = jax.lax.dynamic_update_slice(
                    nxt, r_mid[None], (d, _I0, u0 + start[d, 0], start[d, 1]))
                return nxt, qb, bb

            c0 = (nxt, jnp.zeros((nq,) + blk, dt), jnp.zeros(blk, dt))
            nxt, qb, bb = jax.lax.fori_loop(0, D, direction, c0)
            qb_s = jax.lax.dynamic_update_slice_in_dim(qb_s, qb, u0, axis=2)
            bb_s = jax.lax.dynamic_update_slice_in_dim(bb_s, bb, u0, axis=1)
            return nxt, qb_s, bb_s

        nxt, qb, bb = jax.lax.fori_loop(0, nu // tu, tile, (nxt0, qb0, bb0))
        return nxt, (qb, bb)

    a_last = jnp.zeros((D, M, nu + 2 * M, nv + 2 * M), dt)  # the exits: no cotangent
    xs = (lbs, ebs, ts, nrm, bits, passes)
    a_init, (qbs, bbs) = jax.lax.scan(step, a_last, xs, reverse=True)
    if per_w:  # the periodic sweep's initial guess: each direction's source of the first slab
        r0 = _fold_plane(a_init, M, per_u, per_v)  # (D, M, nu, nv)
        if aniso:
            add = jnp.concatenate([r0.sum(0)[None], jnp.einsum("dk,dmuv->kmuv", table, r0)])
        else:
            add = r0.sum(0)[None]
        qbs = qbs.at[0].add(add)
    q_bar = _unslabs(jnp.moveaxis(qbs, 1, -1), nw, per_w)  # (nw, nu, nv, nq)
    if not aniso:
        q_bar = q_bar[..., 0]
    return q_bar, _unslabs(bbs, nw, per_w)


def substep_offsets(pq: np.ndarray, M: int) -> np.ndarray:
    """(M − 1, D, 2) int: for j = 1 … M − 1, the in-plane offset from a node y of the point
    where direction (p, q, M)'s segment arriving at y crosses the plane M − j before y's:
    (p, q)·(M − j)/M, rounded half away from zero (the nearest node; symmetric in ±p)."""
    pq = np.asarray(pq, np.int64)
    j = np.arange(1, M)[:, None, None]
    return (np.sign(pq)[None] * ((2 * np.abs(pq)[None] * (M - j) + M) // (2 * M))).astype(
        np.int32)


def substep_weight_scale(free, surf, blocked, pq, sub, weight, *, M: int,
                         periodic: tuple[bool, bool, bool], warmup: int,
                         surfaces: bool) -> np.ndarray:
    """(nw, nu, nv) float64: the sub-stepped programs' per-node renormalization Σ_d w_d / W,
    W the weight of the node's sub-steps whose light is known (0 where none is): the last
    channel of their Λ accumulator, which depends on the geometry alone.  Computed once on the
    host (NumPy, the programs' slab order, blocking and margins) for the transposed sweep
    (``_sweep_face_substep_transposed``), which needs it before the forward sweep would have
    finished it.  Arguments in the face frame: ``free``, ``surf`` (nw, nu, nv) bool,
    ``blocked`` (nw, nu, nv, ceil(D/8)) uint8, ``pq`` (D, 2), ``sub`` (M − 1, D, 2),
    ``weight`` (D,)."""
    free, surf = np.asarray(free, bool), np.asarray(surf, bool)
    blocked = np.asarray(blocked, np.uint8)
    pq, sub = np.asarray(pq, np.int64), np.asarray(sub, np.int64)
    weight = np.asarray(weight, np.float64)
    nw, nu, nv = free.shape
    D = len(weight)
    per_w, per_u, per_v = periodic
    total, order = _slab_planes(nw, M, per_w, warmup)

    def pick(a):  # ``_slabber``'s order, on the host
        if per_w:
            return a[order]
        return np.concatenate([a, np.zeros((total - nw,) + a.shape[1:], a.dtype)])
    ns = total // M
    solid = pick(~(free | surf)).reshape((ns, M, nu, nv))
    surf_s = pick(surf).reshape((ns, M, nu, nv))
    bits = pick(blocked).reshape((ns, M, nu, nv, -1))

    def padded(x):  # (m, nu, nv) → (m, nu + 2M, nv + 2M): wrapped on periodic sides, else 0
        x = np.pad(x, [(0, 0), (M, M) if per_u else (0, 0), (M, M) if per_v else (0, 0)],
                   mode="wrap")
        return np.pad(x, [(0, 0), (0, 0) if per_u else (M, M), (0, 0) if per_v else (M, M)])

    def fold(xp):  # the transpose of ``padded``
        for axis, per, n in ((1, per_u, nu), (2, per_v, nv)):
            xm = np.moveaxis(xp, axis, 0)
            if per:
                out = np.zeros((n,) + xm.shape[1:])
                np.add.at(out, (np.arange(n + 2 * M) - M) % n, xm)
            else:
                out = xm[M : M + n]
            xp = np.moveaxis(out, 0, axis)
        return xp

    def at(xp, off):  # x[u − off_u, v − off_v] of the padded x
        return xp[:, M - off[0] : M - off[0] + nu, M - off[1] : M - off[1] + nv]

    def step(solid_prev, solid_s, surf_s_, bits_s):
        swp = padded(np.concatenate([solid_prev, solid_s]).astype(np.float64))
        surf_f = surf_s_.astype(np.float64)
        acc = np.zeros((2 * M, nu + 2 * M, nv + 2 * M))
        for d in range(D):
            valid = 1.0 - at(swp[:M], pq[d])  # the chain left a fluid node
            if surfaces:
                blk = ((bits_s[..., d // 8] >> (d % 8)) & 1) > 0
                valid = np.where(blk, 1.0, valid)
            for j in range(1, M):
                off = sub[j - 1, d]
                if surfaces:
                    valid = np.where(at(swp[j : j + M], off) > 0, surf_f, valid)
                win = acc[j : j + M, M - off[0] : M - off[0] + nu, M - off[1] : M - off[1] + nv]
                win += valid * (weight[d] / M)
        lam_w = fold(acc)
        lam_w[M:] += weight.sum() / M
        return lam_w

    prev = np.zeros((M, nu, nv), bool)
    part = np.zeros((M, nu, nv))
    done = []
    for s in range(ns):
        lam_w = step(prev, solid[s], surf_s[s], bits[s])
        done.append(part + lam_w[:M])
        part, prev = lam_w[M:], solid[s]
    if per_w:  # the slab after the last, in wrap order, finishes the last slab's
        first = np.arange(M) % nw
        part = part + step(prev, ~(free | surf)[first], surf[first], blocked[first])[:M]
    wsum = np.concatenate(done[1:] + [part]).reshape((total, nu, nv))
    wsum = wsum[total - nw :] if per_w else wsum[:nw]
    return np.where(wsum > 0, weight.sum() / np.where(wsum > 0, wsum, 1.0), 0.0)


def _sweep_face_substep(Q, B, tau_half_unit, bc, geo: FaceGeometry, consts: SweepConsts, *,
                        M: int, periodic: tuple[bool, bool, bool], warmup: int, surfaces: bool,
                        fluence: bool = True, halo: Halo | None = None, recompute: bool = False):
    """``sweep_face`` with each segment (y − L → y, across M planes) in M sub-steps, one per
    plane it crosses: at the M − 1 planes between its end nodes the ray takes the extinction
    and source of the node nearest to where it crosses (``substep_offsets``) over one plane's
    length |L|/M, and that node's Λ gets the radiance averaged over it; the end nodes own half
    a plane's length each.  Every node then owns, per direction, M sub-steps of volume h³/M
    (its own two halves and one crossing of each of M − 1 other chains: the nearest-node map
    of a plane is a shift, one to one), so a purely scattering node re-emits what its
    sub-steps remove and the transport resolves the lattice's spacing h, not the segment's
    M·h.  ``tau_half_unit`` is then the node's own σ_t·h/2 (not box-filtered).  Λ of a
    slab's planes is finished one slab later (the next slab's segments cross them), so the
    scan carries the previous slab's fields and partial Λ (and on a periodic sweep axis one
    more slab, the first in wrap order, finishes the last).  Blocked segments (a solid between
    y − L and y): the radiance starts from B(y) at the first intermediate plane (and again
    after each solid node it crosses) and arrives as B(y), as in the step scheme.  A chain
    whose light is unknown (it left a solid node, or crossed one on its way to a node that is
    not a surface) deposits nothing, and each node's Λ is taken over the sub-steps whose
    light is known (their weight is a last channel of the accumulator).  Values and
    derivatives come from this one program."""
    nw, nu, nv = Q.shape[:3]
    P = 2 * M + 1
    D = P * P
    per_w, per_u, per_v = periodic
    dt = Q.dtype
    aniso = Q.ndim == 4
    if consts.slope is not None:
        raise SolverError("the sub-stepped scheme has no linear-source variant")
    if halo is not None:
        raise SolverError("the sub-stepped scheme does not run on a device mesh yet")

    slabs, ns = _slabber(nw, M, per_w, warmup)
    xs = (slabs(Q), slabs(B), slabs(tau_half_unit), slabs(geo.free), slabs(geo.surf),
          jnp.moveaxis(slabs(geo.normal), -1, 0).swapaxes(0, 1),
          jnp.moveaxis(slabs(geo.blocked), -1, 2))
    unit = consts.unit.astype(dt)
    length = consts.length.astype(dt)
    weight = consts.weight.astype(dt)
    bc_d = bc.astype(dt)
    pq = jnp.asarray(consts.pq, jnp.int32)
    sub = jnp.asarray(consts.sub, jnp.int32)  # (M − 1, D, 2)
    byte_of = np.arange(D) // 8
    bit_of = jnp.asarray((np.arange(D) % 8).astype(np.uint8))[None, :, None, None]
    w4 = weight[None, :, None, None]
    nk = 0
    if aniso:
        table, nk = _source_table(consts, dt)
        nj = table.shape[1]
        harm = table[:, :nk]
    # Λ's channels per direction: the fluence weight, then the moments' (D, 1 + K)
    chan = weight[:, None] if not nk else jnp.concatenate(
        [weight[:, None], weight[:, None] * harm], axis=1)
    nc = 1 + nk

    def source(Qs):  # (m, nu, nv[, 1 + J]) → (m, D or 1, nu, nv)
        if not aniso:
            return Qs[:, None]
        return Qs[..., 0][:, None] + jnp.einsum("muvk,dk->mduv", Qs[..., 1 : 1 + nj], table)
    len4 = length[None, :, None, None]
    u4 = [unit[None, :, c, None, None] for c in range(3)]
    zero_d = jnp.zeros((D,), dt)

    def shifted(x, off):  # x (m, D, nu, nv) → x[m, d, u − off_u, v − off_v] (0 / wrap outside)
        return _shift_plane(x, zero_d, off, M, per_u, per_v)

    def per_d(x):  # (m, 1 or D, nu, nv) → (m, D, nu, nv)
        return jnp.broadcast_to(x, (x.shape[0], D) + x.shape[2:])

    def node_field(x, off):  # x (m, nu, nv), one value per node → x[m, u − off_u, v − off_v]
        # for every direction (m, D, nu, nv): one padded copy of the plane, read D times
        xp = _pad_plane(x, M, per_u, per_v, jnp.zeros((), x.dtype))
        start = M - off

        def window(su, sv):
            return jax.lax.dynamic_slice(xp, (jnp.zeros_like(su), su, sv), x.shape)

        return jax.vmap(window, out_axes=1)(start[:, 0], start[:, 1])

    def step(carry, slab):
        r_prev, t_prev, q_prev, solid_prev, lam_prev = carry
        Qs, Bs, ts, fs, ss, ns_, bits = slab
        solid = ~(fs | ss)
        r = _shift_plane(r_prev, bc_d, pq, M, per_u, per_v)  # leaving y − L, arriving here
        # a chain is valid where its radiance is known: it left a fluid node, or a surface
        # emitted it (blocked: y's radiosity)
        valid = 1.0 - node_field(solid_prev.astype(dt), pq)
        q4 = source(Qs)
        b4 = Bs[:, None]
        surf4 = ss[:, None]
        if surfaces:
            blocked = (jnp.take(bits, byte_of, axis=1) >> bit_of) & 1
            r = jnp.where(blocked > 0, b4, r)
            valid = jnp.where(blocked > 0, 1.0, valid)
        tw = jnp.concatenate([t_prev, ts])  # (2M, nu, nv): the previous slab's planes, then these
        qw = (jnp.concatenate([q_prev, q4]) if not aniso  # (2M, 1 or D, nu, nv)
              else jnp.concatenate([per_d(q_prev), per_d(q4)]))
        sw = jnp.concatenate([solid_prev, solid]).astype(dt)
        lam_w = jnp.zeros((2 * M, nu, nv, nc + 1), dt)
        for j in range(1, M):  # the plane M − j before the arrival: window plane m + j
            off = sub[j - 1]
            if surfaces:  # crossing a solid node: inside a shape; a surface arrival's chain
                # leaves it with y's radiosity, any other is unknown until it arrives
                sj = node_field(sw[j : j + M], off) > 0
                r = jnp.where(sj & surf4, b4, r)
                valid = jnp.where(sj, surf4.astype(dt), valid)
            tj = node_field(tw[j : j + M], off) * (2.0 / M) * len4  # sub-step depth
            qj = (node_field(qw[j : j + M, 0], off) if not aniso
                  else shifted(qw[j : j + M], off))
            rbar = qj + (r - qj) * one_minus_exp_over(tj)
            r = r + jnp.expm1(-tj) * (r - qj)
            if fluence:  # deposited at the node crossed: the shift back (−off); its weight too
                dep = jnp.einsum("mduv,dc->muvc", shifted(valid * rbar, -off), chan) / M
                wdep = jnp.einsum("mduv,d->muv", shifted(valid, -off), weight) / M
                lam_w = lam_w.at[j : j + M].add(jnp.concatenate([dep, wdep[..., None]], -1))
        tau = ts[:, None] * len4 / M  # the node's own half sub-steps
        em = jnp.expm1(-tau)
        r_arr = r + em * (r - q4)
        r_avg = q4 + (r - q4) * one_minus_exp_over(2.0 * tau)
        if surfaces:
            r_arr = jnp.where(blocked > 0, b4, r_arr)
            r_avg = jnp.where(blocked > 0, q4 + (b4 - q4) * one_minus_exp_over(tau), r_avg)
        r_through = r_arr + em * (r_arr - q4)
        if fluence:
            own = jnp.einsum("mduv,dc->muvc", r_avg, chan) / M
            wown = jnp.broadcast_to(weight.sum() / M, own.shape[:-1] + (1,)).astype(dt)
            lam_w = lam_w.at[M:].add(jnp.concatenate([own, wown], -1))
        done = lam_prev + lam_w[:M]  # the previous slab's planes: no later segment crosses them
        if surfaces:
            ldotn = ns_[0][:, None] * u4[0] + ns_[1][:, None] * u4[1] + ns_[2][:, None] * u4[2]
            irr = (r_arr * jnp.maximum(-ldotn, 0.0) * w4).sum(1)
            r_out = jnp.where(fs[:, None] | ss[:, None], r_through, 0.0)
        else:
            irr = jnp.zeros(ts.shape, dt)
            r_out = jnp.where(fs[:, None], r_through, 0.0)
        return (r_out, ts, q4, solid, lam_w[M:]), (done, irr)

    Qs0 = xs[0][0]
    q_shape = source(Qs0).shape
    if per_w:
        r0 = jnp.broadcast_to(source(Qs0), (M, D, nu, nv)).astype(dt)
    else:
        r0 = jnp.broadcast_to(bc_d[None, :, None, None], (M, D, nu, nv))
    init = (r0, jnp.zeros((M, nu, nv), dt), jnp.zeros(q_shape, dt),
            jnp.zeros((M, nu, nv), bool), jnp.zeros((M, nu, nv, nc + 1), dt))
    body = jax.checkpoint(step, prevent_cse=False) if recompute else step
    carry, (lam, irr) = jax.lax.scan(body, init, xs)
    exit_, lam_last = carry[0], carry[4]
    if per_w:  # the rays go on past the last slab (wrapping): its planes' Λ is finished by
        # the crossings of the slab after it, the first M planes in wrap order
        order = np.arange(M) % nw
        nxt = tuple(jnp.take(a, order, axis=0) for a in (
            Q, B, tau_half_unit, geo.free, geo.surf))
        nxt = nxt + (jnp.moveaxis(jnp.take(geo.normal, order, axis=0), -1, 0),
                     jnp.moveaxis(jnp.take(geo.blocked, order, axis=0), -1, 1))
        _, (lam_last, _) = body(carry, nxt)
    lam = jnp.concatenate([lam[1:], lam_last[None]])  # step s finished slab s − 1's Λ
    return _substep_outputs(lam, irr, exit_, weight, nk, nw, per_w)


def _substep_outputs(lam, irr, exit_, weight, nk: int, nw: int, per_w: bool, wscale=None):
    """The sub-stepped programs' results from their per-slab Λ (ns, M, nu, nv, 2 + K: the
    fluence, the K moments, the weight of the sub-steps whose light is known) and E: each
    node's Λ over the sub-steps whose radiance is known (per direction M of them, its own two
    halves and M − 1 crossings, weigh Σ_d w_d; a crossing of a chain inside a shape does not
    count, and the others stand in for it), then the swept planes' part.  With ``wscale``
    (the geometry's ``substep_weight_scale``, (nw, nu, nv)) Λ has no weight channel and the
    scale is applied to the swept planes."""
    nc = 1 + nk
    total = lam.shape[0] * lam.shape[1]
    lam = lam.reshape((total,) + lam.shape[2:])
    irr = irr.reshape((total,) + irr.shape[2:])
    if wscale is None:
        wsum = lam[..., nc:]
        lam = lam[..., :nc] * jnp.where(
            wsum > 0, weight.sum() / jnp.where(wsum > 0, wsum, 1.0), 0.0)
    sel = slice(total - nw, total) if per_w else slice(0, nw)
    lam, irr = lam[sel, ..., :nc], irr[sel]
    if wscale is not None:
        lam = lam * wscale.astype(lam.dtype)[..., None]
    return (lam[..., 0] if not nk else lam), irr, exit_


def _substep_factors(t_prev, ts, len_k4, M: int, pad, surfaces: bool):
    """A slab's sub-step factors for the sub-stepped loop and its transpose, per distinct |L|
    (``len_k4`` (K, 1, 1, 1)): over the padded window of the 2M planes a segment can cross (the
    previous slab's τ ``t_prev``, then this one's ``ts``; ``pad`` pads a plane's margins) a
    crossing's e^(−τ) − 1 and (1 − e^(−τ))/τ (K, 2M, nu + 2M, nv + 2M), and the node's own
    half sub-steps' e^(−τ) − 1, (1 − e^(−2τ))/(2τ) and, with surfaces, (1 − e^(−τ))/τ
    (K, M, nu, nv; else None)."""
    tk = (pad(jnp.concatenate([t_prev, ts])) * (2.0 / M))[None] * len_k4
    own = ts[None] * len_k4 / M
    return (jnp.expm1(-tk), one_minus_exp_over(tk), jnp.expm1(-own),
            one_minus_exp_over(2.0 * own), one_minus_exp_over(own) if surfaces else None)


def _substep_chain(swp, st, sft, bt, d, su, sv, u0, sub_start, byte_of, bit_of, M: int, blk,
                   surfaces: bool):
    """The geometry of direction ``d``'s segments arriving at a row tile's nodes, for the
    sub-stepped loop and its transpose (which must agree on it): the window origins of the
    M − 1 crossings in the padded two-slab window (``u0``: the tile's first row; ``sub_start``
    (M − 1, D, 2)), whether each segment is blocked (``bt``: the tile's blocked bits; None
    without surfaces), and per crossing whether the chain restarts there with y's radiosity
    (it crossed a solid node on its way to a surface node ``st``) and whether its light is
    known there (it left a fluid node, was emitted by a surface, and has not crossed into a
    shape on its way to a node that is not a surface: ``sft`` its float).  ``swp``: the padded
    solid flags of the 2M planes; (``su``, ``sv``) the arrival's window origin."""
    crossing = [(jnp.asarray(j, jnp.int32), u0 + sub_start[j - 1, d, 0],
                 sub_start[j - 1, d, 1]) for j in range(1, M)]
    valid = 1.0 - jax.lax.dynamic_slice(swp, (_I0, su, sv), blk)
    blocked = None
    if surfaces:
        byte = jax.lax.dynamic_index_in_dim(bt, byte_of[d], 0, keepdims=False)
        blocked = ((byte >> bit_of[d]) & 1) > 0
        valid = jnp.where(blocked, 1.0, valid)
    valids, restarts = [], []
    for o in crossing:
        if surfaces:
            sj = jax.lax.dynamic_slice(swp, o, blk) > 0
            restarts.append(sj & st)
            valid = jnp.where(sj, sft, valid)
        valids.append(valid)
    return crossing, blocked, restarts, valids


def _sweep_face_substep_transposed(lam_bar, irr_bar, tau_half_unit, geo: FaceGeometry,
                                  consts: SweepConsts, *, M: int,
                                  periodic: tuple[bool, bool, bool], warmup: int,
                                  surfaces: bool, fluence: bool = True, q_channels: int = 0,
                                  vol_range: tuple[int, int] | None = None,
                                  attenuate: bool = True):
    """``sweep_face_transposed`` for the sub-stepped scheme: the transpose of
    ``_sweep_face_substep``'s linear map (Q, B) → (Λ, E) at fixed τ and zero boundary radiance
    (to rounding), as ``_sweep_face_substep_loop``'s direction loop run backwards.  Λ̄ first
    takes the per-node renormalization (``geo.wscale``, ``substep_weight_scale``: geometry
    only, so the map stays linear); the slabs then run in reverse, each carrying back the
    cotangent of the radiance it read (written at the window the forward read it from, as the
    step scheme's transpose does) and the source cotangent its crossings scattered into the
    previous slab's planes.  Per direction the chain is replayed backwards: the node's own
    half sub-steps, then its crossings from the last to the first, each taking the cotangent
    of its deposit from the padded Λ̄ window of the two slabs' planes at its offset and adding
    its source's cotangent into a padded window at the same offset (margins folded back after
    the loop); a chain's validity and surface restarts (geometry) are replayed forwards
    first.  With ``vol_range`` it transposes the forward loop's restriction to the slabs that
    hold fog (``_sweep_face_substep_loop``'s ``vol``): the other slabs carry the radiance's
    cotangent back through the shift, the blocked arrivals and the restarts only (their Λ̄ and
    Q̄ are not used: Λ = 0 and no fog there)."""
    nw, nu, nv = tau_half_unit.shape
    P = 2 * M + 1
    D = P * P
    per_w, per_u, per_v = periodic
    dt = tau_half_unit.dtype
    aniso = q_channels > 0
    if geo.wscale is None:
        raise SolverError("the sub-stepped sweep's transpose needs the geometry's weight scale "
                          "(FaceGeometry.wscale, made by prepare_sweep(substep=True))")
    slabs, ns = _slabber(nw, M, per_w, warmup)
    total = ns * M
    length_k, kidx = _distinct_lengths(consts, M, dt)  # (K,) distinct |L|; each d's index
    len_k4 = length_k[:, None, None, None]
    unit = consts.unit.astype(dt)
    weight = consts.weight.astype(dt)
    start = M - jnp.asarray(consts.pq, jnp.int32)
    sub_start = M - jnp.asarray(consts.sub, jnp.int32)  # (M − 1, D, 2) crossings' origins
    byte_of = jnp.asarray(np.arange(D) // 8, jnp.int32)
    bit_of = jnp.asarray((np.arange(D) % 8).astype(np.uint8))
    nk = nj = 0
    table = None
    if aniso:
        table, nk = _source_table(consts, dt)  # (D, J)
        nj = table.shape[1]
        if 1 + nj != q_channels:
            raise SolverError(f"sweep_face_transposed: {q_channels} source channels, the "
                              f"table has {1 + nj}")
    chan = weight[:, None] if not nk else jnp.concatenate(
        [weight[:, None], weight[:, None] * table[:, :nk]], axis=1)
    nc = 1 + nk
    nq = 1 + nj if aniso else 1
    zero = jnp.zeros((), dt)
    tu = _tile_rows(nu)

    def pad(x):  # the transpose of the forward's fold: wrapped on periodic sides, else 0
        return _pad_plane(x, M, per_u, per_v, zero)

    def full(x):  # the outputs' cotangents over the planes swept (warm-up, padding: none)
        z = jnp.zeros((total,) + x.shape[1:], dt)
        return z.at[total - nw :].set(x) if per_w else z.at[:nw].set(x)

    def prev(a):  # the previous slab's (zeros before the first: the forward's initial carry)
        return jnp.concatenate([jnp.zeros_like(a[:1]), a[:-1]])

    if fluence:  # Λ of the raw accumulator: the renormalization is per node
        scale = geo.wscale.astype(dt)
        lam_bar = lam_bar.astype(dt) * (scale[..., None] if nk else scale)
    else:
        lam_bar = jnp.zeros(lam_bar.shape, dt)
    if _native_applies(None, dt):  # the native kernel's transpose (same values)
        s0, s1, fog_on = _substep_fog_slabs((attenuate, fluence, vol_range), ns, M, per_w)
        none = jnp.zeros((1,), dt), jnp.zeros((1,), jnp.uint8)
        q_bar, b_bar = _native.sweep_substep_transposed(
            lam_bar, irr_bar.astype(dt), tau_half_unit, geo.normal if surfaces else none[0],
            geo.blocked if surfaces else none[1], geo.free, geo.surf, length_k, kidx, weight,
            unit, start, sub_start, M=M, ns=ns, segment=(s0, s1, fog_on), surfaces=surfaces,
            periodic=periodic, table=table if aniso and nj else None, nk=nk)
        return (q_bar[..., None] if aniso and not nj else q_bar), b_bar
    lb = full(lam_bar).reshape((ns, M, nu, nv) + ((nc,) if nk else ()))
    lb = jnp.moveaxis(lb, -1, 1) if nk else lb[:, None]  # (ns, nc, M, nu, nv)
    eb = full(irr_bar.astype(dt)).reshape((ns, M, nu, nv))
    ts = slabs(tau_half_unit)
    fs, ss = slabs(geo.free), slabs(geo.surf)
    solid = ~(fs | ss)
    if surfaces:
        nrm = jnp.moveaxis(slabs(geo.normal), -1, 1)
        bits = jnp.moveaxis(slabs(geo.blocked), -1, 1)
    else:
        nrm = jnp.zeros((ns, 1), dt)
        bits = jnp.zeros((ns, 1), jnp.uint8)

    def expand(q, d):  # a direction's source cotangent → its channels' (nq, ...)
        if not aniso:
            return q[None]
        hd = jax.lax.dynamic_index_in_dim(table, d, 0, keepdims=False)
        return jnp.stack([q] + [hd[j] * q for j in range(nj)])

    def step(carry, slab):
        abar, q_next = carry  # the cotangents of this slab's padded output, of its Q (crossed
        lbp, lbc, eb_s, ts_, tp_, fs_, ss_, sp_, nrm_s, bits_s = slab  # by the next slab's)
        solid_s = ~(fs_ | ss_)
        pass_s = (fs_ | ss_) if surfaces else fs_
        surf_f = ss_.astype(dt)
        rbo = _fold_plane(abar, M, per_u, per_v)  # (D, M, nu, nv)
        em_w, avg_w, em_own, avg2_own, avg1_own = _substep_factors(tp_, ts_, len_k4, M, pad,
                                                                   surfaces)
        swp = pad(jnp.concatenate([sp_, solid_s]).astype(dt))
        lwp = pad(jnp.concatenate([lbp, lbc], axis=1)) / M  # (nc, 2M, ...): the deposits'
        nxt0 = jnp.zeros((D, M, nu + 2 * M, nv + 2 * M), dt)
        qwin0 = jnp.zeros((nq, 2 * M, nu + 2 * M, nv + 2 * M), dt)
        qb0 = jnp.zeros((nq, M, nu, nv), dt)
        bb0 = jnp.zeros((M, nu, nv), dt)

        def tile(t, c):
            nxt, qwin, qb_s, bb_s = c
            u0 = jnp.asarray(t * tu, jnp.int32)
            rows = lambda a: jax.lax.dynamic_slice_in_dim(a, u0, tu, axis=a.ndim - 2)  # noqa
            pt, st, sft, et = rows(pass_s), rows(ss_), rows(surf_f), rows(eb_s)
            lct = rows(lbc) / M  # the own sub-steps' Λ̄ (nc, M, tu, nv)
            em_t, a2_t = rows(em_own), rows(avg2_own)
            if surfaces:
                a1_t, nt, bt = rows(avg1_own), rows(nrm_s), rows(bits_s)
            blk = (M, tu, nv)

            def direction(d, c):
                nxt, qwin, qb, bb = c
                d = jnp.asarray(d, jnp.int32)
                k = kidx[d]
                at_k = lambda a: jax.lax.dynamic_index_in_dim(a, k, 0, keepdims=False)  # noqa
                su, sv = u0 + start[d, 0], start[d, 1]
                # the chain forwards: its validity at each crossing and its restarts (geometry)
                crossing, blocked, restarts, valids = _substep_chain(
                    swp, st, sft, bt if surfaces else None, d, su, sv, u0, sub_start, byte_of,
                    bit_of, M, blk, surfaces)
                # backwards: the node's own half sub-steps
                ro = jax.lax.dynamic_slice(rbo, (d, _I0, u0, _I0), (1,) + blk)[0]
                r_through = jnp.where(pt, ro, 0.0)
                em = at_k(em_t)
                a2 = at_k(a2_t)
                r_arr = r_through + em * r_through
                q4 = -em * r_through
                r_avg = sum(chan[d, c] * lct[c] for c in range(nc))
                if surfaces:
                    ldotn = nt[0] * unit[d, 0] + nt[1] * unit[d, 1] + nt[2] * unit[d, 2]
                    r_arr = r_arr + et * jnp.maximum(-ldotn, 0.0) * weight[d]
                    a1 = at_k(a1_t)
                    bb = bb + jnp.where(blocked, r_arr + a1 * r_avg, 0.0)
                    q4 = q4 + jnp.where(blocked, (1.0 - a1) * r_avg,
                                        -em * r_arr + (1.0 - a2) * r_avg)
                    r = jnp.where(blocked, 0.0, r_arr + em * r_arr + a2 * r_avg)
                else:
                    q4 = q4 - em * r_arr + (1.0 - a2) * r_avg
                    r = r_arr + em * r_arr + a2 * r_avg
                qb = qb + expand(q4, d)
                for i in reversed(range(M - 1)):  # the crossings, last first
                    o = crossing[i]
                    em = jax.lax.dynamic_slice(em_w, (k,) + o, (1,) + blk)[0]
                    av = jax.lax.dynamic_slice(avg_w, (k,) + o, (1,) + blk)[0]
                    lw = jax.lax.dynamic_slice(lwp, (_I0,) + o, (nc,) + blk)
                    rho = valids[i] * sum(chan[d, c] * lw[c] for c in range(nc))
                    qj = (1.0 - av) * rho - em * r
                    r = r + em * r + av * rho
                    oq = (_I0,) + o
                    qwin = jax.lax.dynamic_update_slice(
                        qwin, jax.lax.dynamic_slice(qwin, oq, (nq,) + blk) + expand(qj, d), oq)
                    if surfaces:
                        bb = bb + jnp.where(restarts[i], r, 0.0)
                        r = jnp.where(restarts[i], 0.0, r)
                if surfaces:
                    bb = bb + jnp.where(blocked, r, 0.0)
                    r = jnp.where(blocked, 0.0, r)
                nxt = jax.lax.dynamic_update_slice(nxt, r[None], (d, _I0, su, sv))
                return nxt, qwin, qb, bb

            c0 = (nxt, qwin, jnp.zeros((nq,) + blk, dt), jnp.zeros(blk, dt))
            nxt, qwin, qb, bb = jax.lax.fori_loop(0, D, direction, c0)
            qb_s = jax.lax.dynamic_update_slice_in_dim(qb_s, qb, u0, axis=2)
            bb_s = jax.lax.dynamic_update_slice_in_dim(bb_s, bb, u0, axis=1)
            return nxt, qwin, qb_s, bb_s

        nxt, qwin, qb, bb = jax.lax.fori_loop(0, nu // tu, tile, (nxt0, qwin0, qb0, bb0))
        qw = _fold_plane(qwin, M, per_u, per_v)  # (nq, 2M, nu, nv)
        return (nxt, qw[:, :M]), (qb + qw[:, M:] + q_next, bb)

    def vacuum(carry, slab):  # the forward's move-only slab, transposed
        abar, q_next = carry
        _, _, eb_s, _, _, fs_, ss_, sp_, nrm_s, bits_s = slab
        solid_s = ~(fs_ | ss_)
        pass_s = (fs_ | ss_) if surfaces else fs_
        surf_f = ss_.astype(dt)
        rbo = _fold_plane(abar, M, per_u, per_v)  # (D, M, nu, nv)
        swp = pad(jnp.concatenate([sp_, solid_s]).astype(dt)) if surfaces else None

        def tile(t, c):
            nxt, bb_s = c
            u0 = jnp.asarray(t * tu, jnp.int32)
            rows = lambda a: jax.lax.dynamic_slice_in_dim(a, u0, tu, axis=a.ndim - 2)  # noqa
            pt, st, sft, et = rows(pass_s), rows(ss_), rows(surf_f), rows(eb_s)
            if surfaces:
                nt, bt = rows(nrm_s), rows(bits_s)
            blk = (M, tu, nv)

            def direction(d, c):
                nxt, bb = c
                d = jnp.asarray(d, jnp.int32)
                su, sv = u0 + start[d, 0], start[d, 1]
                ro = jax.lax.dynamic_slice(rbo, (d, _I0, u0, _I0), (1,) + blk)[0]
                r = jnp.where(pt, ro, 0.0)
                if surfaces:
                    _, blocked, restarts, _ = _substep_chain(
                        swp, st, sft, bt, d, su, sv, u0, sub_start, byte_of, bit_of, M, blk,
                        surfaces)
                    ldotn = nt[0] * unit[d, 0] + nt[1] * unit[d, 1] + nt[2] * unit[d, 2]
                    r = r + et * jnp.maximum(-ldotn, 0.0) * weight[d]
                    for cut in restarts[::-1] + [blocked]:  # the forward's, reversed
                        bb = bb + jnp.where(cut, r, 0.0)
                        r = jnp.where(cut, 0.0, r)
                nxt = jax.lax.dynamic_update_slice(nxt, r[None], (d, _I0, su, sv))
                return nxt, bb

            nxt, bb = jax.lax.fori_loop(0, D, direction, (nxt, jnp.zeros(blk, dt)))
            return nxt, jax.lax.dynamic_update_slice_in_dim(bb_s, bb, u0, axis=1)

        nxt0 = jnp.zeros((D, M, nu + 2 * M, nv + 2 * M), dt)
        nxt, bb = jax.lax.fori_loop(0, nu // tu, tile, (nxt0, jnp.zeros((M, nu, nv), dt)))
        return (nxt, jnp.zeros_like(q_next)), (q_next, bb)

    xs = (prev(lb), lb, eb, ts, prev(ts), fs, ss, prev(solid), nrm, bits)
    init = (jnp.zeros((D, M, nu + 2 * M, nv + 2 * M), dt), jnp.zeros((nq, M, nu, nv), dt))
    # the forward loop's slabs: the fog step over [s0, s1), the rays only moved elsewhere
    s0, s1, fog_on = _substep_fog_slabs((attenuate, fluence, vol_range), ns, M, per_w)
    first = np.arange(M) % nw
    if per_w:  # the slab after the last, in wrap order, finished the last slab's Λ
        take = lambda a: jnp.take(a, first, axis=0)  # noqa
        fs_e, ss_e = take(geo.free), take(geo.surf)
        extra = (lb[-1], jnp.zeros_like(lb[-1]), jnp.zeros((M, nu, nv), dt),
                 take(tau_half_unit), ts[-1], fs_e, ss_e, solid[-1],
                 jnp.moveaxis(take(geo.normal), -1, 0) if surfaces else nrm[0],
                 jnp.moveaxis(take(geo.blocked), -1, 0) if surfaces else bits[0])
        init, (q_e, b_e) = (step if fog_on else vacuum)(init, extra)
    carry, outs = init, []
    for a, b, fn in ((s1, ns, vacuum), (s0, s1, step), (0, s0, vacuum)):
        if b > a:
            carry, out = jax.lax.scan(fn, carry, jax.tree.map(lambda x: x[a:b], xs),
                                      reverse=True)
            outs.insert(0, out)
    (a_first, _) = carry
    qbs, bbs = (jnp.concatenate(parts) if len(parts) > 1 else parts[0] for parts in zip(*outs))
    if per_w:  # the periodic sweep's initial guess: each direction's source of the first slab
        r0 = _fold_plane(a_first, M, per_u, per_v)  # (D, M, nu, nv)
        add = r0.sum(0)[None]
        if aniso:
            add = jnp.concatenate([add, jnp.einsum("dk,dmuv->kmuv", table, r0)])
        qbs = qbs.at[0].add(add)
    q_bar = _unslabs(jnp.moveaxis(qbs, 1, -1), nw, per_w)  # (nw, nu, nv, nq)
    b_bar = _unslabs(bbs, nw, per_w)
    if per_w:
        q_bar = q_bar.at[first].add(jnp.moveaxis(q_e, 0, -1))
        b_bar = b_bar.at[first].add(b_e)
    return (q_bar if aniso else q_bar[..., 0]), b_bar


def _sweep_face_substep_loop(Q, B, tau_half_unit, bc, geo: FaceGeometry, consts: SweepConsts,
                             *, M: int, periodic: tuple[bool, bool, bool], warmup: int,
                             surfaces: bool, fluence: bool = True, vol=None):
    """``_sweep_face_substep``'s values (same arguments and results, to rounding) as a loop
    over the D directions, each on its own (M, nu, nv) block, as ``_sweep_face_loop`` does for
    the step scheme: what a CPU wants.  Per slab the 2M planes a segment can cross (the
    previous slab's, then this one's) are padded once: the sub-step factors e^(−τ) − 1 and
    (1 − e^(−τ))/τ of every distinct |L| (10 at M = 3 instead of one per direction and
    crossing), the source, the solid flags; a crossing then reads its block of each at its
    offset with a ``dynamic_slice`` and adds its deposit into a padded Λ window at the same
    offset (on periodic sides the window's margins are folded back after the loop).  The
    batched program (``_sweep_face_substep``) gives the derivatives.

    ``vol`` = (attenuate, fluence, vol_range), as ``_sweep_face_loop`` takes it: the slabs
    [s0, s1) that hold fog (``_fog_slabs``) and the one after them (whose crossings finish
    the last fog slab's Λ) take the sub-stepped fog step; the others only move the rays (the
    shift, a blocked arrival's and a chain's restarts' radiosity, E) and return Λ = 0 (no fog
    there: τ = 0 and no source, so the rays are the same; a vacuum node's Λ is not needed, as
    with the step scheme's ``vol_range``)."""
    nw, nu, nv = Q.shape[:3]
    P = 2 * M + 1
    D = P * P
    per_w, per_u, per_v = periodic
    dt = Q.dtype
    aniso = Q.ndim == 4
    if consts.slope is not None:
        raise SolverError("the sub-stepped scheme has no linear-source variant")

    slabs, ns = _slabber(nw, M, per_w, warmup)
    length_k, kidx = _distinct_lengths(consts, M, dt)  # (K,) distinct |L|; each d's index
    len_k4 = length_k[:, None, None, None]
    unit = consts.unit.astype(dt)
    weight = consts.weight.astype(dt)
    bc_d = bc.astype(dt)
    start = M - jnp.asarray(consts.pq, jnp.int32)  # arrival window origin in the padded plane
    sub_start = M - jnp.asarray(consts.sub, jnp.int32)  # (M − 1, D, 2) crossings' origins
    byte_of = jnp.asarray(np.arange(D) // 8, jnp.int32)
    bit_of = jnp.asarray((np.arange(D) % 8).astype(np.uint8))
    nk = nj = 0
    table = None
    if aniso:
        table, nk = _source_table(consts, dt)  # (D, J)
        nj = table.shape[1]
    # Λ's channels per direction: the fluence weight, then the moments' (D, 1 + K)
    chan = weight[:, None] if not nk else jnp.concatenate(
        [weight[:, None], weight[:, None] * table[:, :nk]], axis=1)
    nc = 1 + nk
    # with the geometry's weight scale no channel accumulates the known sub-steps' weight
    nw_chan = 0 if geo.wscale is not None else 1
    zero = jnp.zeros((), dt)
    tu = _tile_rows(nu)

    def pad(x):  # (..., nu, nv) → (..., nu + 2M, nv + 2M): wrapped on periodic sides, else 0
        return _pad_plane(x, M, per_u, per_v, zero)

    def source_d(q, d):  # q (1 + J, m, ...) channels → direction d's source (m, ...)
        if not aniso:
            return q
        hd = jax.lax.dynamic_index_in_dim(table, d, 0, keepdims=False)
        return q[0] + jnp.tensordot(hd, q[1:], axes=1)

    Qs, Bs, ts = slabs(Q), slabs(B), slabs(tau_half_unit)
    if aniso:  # channels first: (ns, 1 + J, M, nu, nv)
        Qs = jnp.moveaxis(Qs, -1, 1)[:, : 1 + nj]
    fs, ss = slabs(geo.free), slabs(geo.surf)
    if surfaces:
        nrm = jnp.moveaxis(slabs(geo.normal), -1, 1)  # (ns, 3, M, nu, nv)
        bits = jnp.moveaxis(slabs(geo.blocked), -1, 1)  # (ns, ceil(D/8), M, nu, nv)
    else:
        nrm = jnp.zeros((ns, 1), dt)
        bits = jnp.zeros((ns, 1), jnp.uint8)

    def step(carry, slab):
        (src, dst), t_prev, q_prev, solid_prev, lam_prev = carry
        Qs_, Bs_, ts_, fs_, ss_, nrm_s, bits_s = slab
        solid = ~(fs_ | ss_)
        pass_s = (fs_ | ss_) if surfaces else fs_
        surf_f = ss_.astype(dt)
        # the window of 2M planes the crossings read: previous slab's planes, then these
        em_w, avg_w, em_own, avg2_own, avg1_own = _substep_factors(t_prev, ts_, len_k4, M,
                                                                   pad, surfaces)
        qwp = pad(jnp.concatenate([q_prev, Qs_], axis=-3))  # ([1 + J,] 2M, ...)
        swp = pad(jnp.concatenate([solid_prev, solid]).astype(dt))
        lamp0 = tuple(jnp.zeros((2 * M, nu + 2 * M, nv + 2 * M), dt)
                      for _ in range(nc + nw_chan))
        acc0 = jnp.zeros((nc, M, nu, nv), dt)
        irr0 = jnp.zeros((M, nu, nv), dt)

        def tile(t, c):  # rows [u0, u0 + tu) of the arrival plane, every direction
            dst, lamp, acc_s, irr_s = c
            u0 = jnp.asarray(t * tu, jnp.int32)
            rows = lambda a: jax.lax.dynamic_slice_in_dim(a, u0, tu, axis=a.ndim - 2)  # noqa
            Bt, st, sft, pt = rows(Bs_), rows(ss_), rows(surf_f), rows(pass_s)
            Qt = rows(Qs_)
            em_t, avg2_t = rows(em_own), rows(avg2_own)
            if surfaces:
                avg1_t, nt, bt = rows(avg1_own), rows(nrm_s), rows(bits_s)
            blk = (M, tu, nv)
            if aniso:  # the rows of the 2M-plane window this tile's crossings can read
                qwin = jax.lax.dynamic_slice(qwp, (_I0, _I0, u0, _I0),
                                             (1 + nj, 2 * M, tu + 2 * M, nv + 2 * M))

            def direction(d, c):
                dst, lamp, acc, irr = c
                d = jnp.asarray(d, jnp.int32)
                k = kidx[d]
                su, sv = u0 + start[d, 0], start[d, 1]
                r = jax.lax.dynamic_slice(src, (d, _I0, su, sv), (1,) + blk)[0]
                crossing, blocked, restarts, valids = _substep_chain(
                    swp, st, sft, bt if surfaces else None, d, su, sv, u0, sub_start, byte_of,
                    bit_of, M, blk, surfaces)
                if surfaces:
                    r = jnp.where(blocked, Bt, r)
                if aniso:  # direction d's source over the window: one contraction, not one
                    # per crossing (each of which XLA would run as several small programs)
                    qd = source_d(qwin, d)
                for i, o in enumerate(crossing):
                    if surfaces:
                        r = jnp.where(restarts[i], Bt, r)
                    valid = valids[i]
                    em = jax.lax.dynamic_slice(em_w, (k,) + o, (1,) + blk)[0]
                    av = jax.lax.dynamic_slice(avg_w, (k,) + o, (1,) + blk)[0]
                    if aniso:
                        qj = jax.lax.dynamic_slice(qd, (o[0], o[1] - u0, o[2]), blk)
                    else:
                        qj = jax.lax.dynamic_slice(qwp, o, blk)
                    rbar = qj + (r - qj) * av
                    r = r + em * (r - qj)
                    if fluence:  # deposited at the node crossed (y − offset): the same window
                        x = valid * rbar
                        adds = [chan[d, c] * x for c in range(nc)] + (
                            [weight[d] * valid] if nw_chan else [])
                        lamp = tuple(
                            jax.lax.dynamic_update_slice(
                                a, jax.lax.dynamic_slice(a, o, blk) + v / M, o)
                            for a, v in zip(lamp, adds))
                # the arrival plane's source: this slab's planes in the window already hold it
                q4 = qd[M:, M : M + tu, M : M + nv] if aniso else Qt
                at_k = lambda a: jax.lax.dynamic_index_in_dim(a, k, 0, keepdims=False)  # noqa
                em = at_k(em_t)
                r_arr = r + em * (r - q4)
                r_avg = q4 + (r - q4) * at_k(avg2_t)
                if surfaces:
                    r_arr = jnp.where(blocked, Bt, r_arr)
                    r_avg = jnp.where(blocked, q4 + (Bt - q4) * at_k(avg1_t), r_avg)
                    ldotn = nt[0] * unit[d, 0] + nt[1] * unit[d, 1] + nt[2] * unit[d, 2]
                    irr = irr + r_arr * jnp.maximum(-ldotn, 0.0) * weight[d]
                r_through = r_arr + em * (r_arr - q4)
                if fluence:
                    acc = acc + chan[d][:, None, None, None] * r_avg[None]
                r_out = jnp.where(pt, r_through, 0.0)
                dst = jax.lax.dynamic_update_slice(dst, r_out[None], (d, _I0, M + u0, _I0 + M))
                return dst, lamp, acc, irr

            c0 = (dst, lamp, jnp.zeros((nc,) + blk, dt), jnp.zeros(blk, dt))
            dst, lamp, acc, irr = jax.lax.fori_loop(0, D, direction, c0)
            acc_s = jax.lax.dynamic_update_slice_in_dim(acc_s, acc, u0, axis=2)
            irr_s = jax.lax.dynamic_update_slice_in_dim(irr_s, irr, u0, axis=1)
            return dst, lamp, acc_s, irr_s

        dst, lamp, acc, irr = jax.lax.fori_loop(0, nu // tu, tile, (dst, lamp0, acc0, irr0))
        lam_w = _fold_plane(jnp.stack(lamp), M, per_u, per_v)  # (nc [+ 1], 2M, nu, nv)
        wown = jnp.full((nw_chan, M, nu, nv), weight.sum() / M, dt)
        lam_w = lam_w.at[:, M:].add(jnp.concatenate([acc / M, wown]))
        done = lam_prev + lam_w[:, :M]  # the previous slab's planes: no later segment crosses
        if per_u:
            dst = _wrap_border(dst, 2, nu, M)
        if per_v:
            dst = _wrap_border(dst, 3, nv, M)
        return ((dst, src), ts_, Qs_, solid, lam_w[:, M:]), (done, irr)

    def vacuum(carry, slab):  # no fog in this slab's window: the rays only move
        (src, dst), _, _, solid_prev, lam_prev = carry
        Qs_, Bs_, ts_, fs_, ss_, nrm_s, bits_s = slab
        solid = ~(fs_ | ss_)
        pass_s = (fs_ | ss_) if surfaces else fs_
        surf_f = ss_.astype(dt)
        swp = pad(jnp.concatenate([solid_prev, solid]).astype(dt)) if surfaces else None

        def tile(t, c):
            dst, irr_s = c
            u0 = jnp.asarray(t * tu, jnp.int32)
            rows = lambda a: jax.lax.dynamic_slice_in_dim(a, u0, tu, axis=a.ndim - 2)  # noqa
            Bt, st, sft, pt = rows(Bs_), rows(ss_), rows(surf_f), rows(pass_s)
            if surfaces:
                nt, bt = rows(nrm_s), rows(bits_s)
            blk = (M, tu, nv)

            def direction(d, c):
                dst, irr = c
                d = jnp.asarray(d, jnp.int32)
                su, sv = u0 + start[d, 0], start[d, 1]
                r = jax.lax.dynamic_slice(src, (d, _I0, su, sv), (1,) + blk)[0]
                if surfaces:
                    _, blocked, restarts, _ = _substep_chain(
                        swp, st, sft, bt, d, su, sv, u0, sub_start, byte_of, bit_of, M, blk,
                        surfaces)
                    r = jnp.where(blocked, Bt, r)
                    for restart in restarts:
                        r = jnp.where(restart, Bt, r)
                    ldotn = nt[0] * unit[d, 0] + nt[1] * unit[d, 1] + nt[2] * unit[d, 2]
                    irr = irr + r * jnp.maximum(-ldotn, 0.0) * weight[d]
                r_out = jnp.where(pt, r, 0.0)
                dst = jax.lax.dynamic_update_slice(dst, r_out[None], (d, _I0, M + u0, _I0 + M))
                return dst, irr

            dst, irr = jax.lax.fori_loop(0, D, direction, (dst, jnp.zeros(blk, dt)))
            return dst, jax.lax.dynamic_update_slice_in_dim(irr_s, irr, u0, axis=1)

        dst, irr = jax.lax.fori_loop(0, nu // tu, tile, (dst, jnp.zeros((M, nu, nv), dt)))
        if per_u:
            dst = _wrap_border(dst, 2, nu, M)
        if per_v:
            dst = _wrap_border(dst, 3, nv, M)
        # the previous slab's Λ as it stands (no crossing of this slab adds to it)
        return ((dst, src), ts_, Qs_, solid, jnp.zeros_like(lam_prev)), (lam_prev, irr)

    r0 = _initial_carry(Qs[0], table, bc_d, D, M, periodic)
    q_shape = Qs.shape[1:]
    init = ((r0, r0), jnp.zeros((M, nu, nv), dt), jnp.zeros(q_shape, dt),
            jnp.zeros((M, nu, nv), bool), jnp.zeros((nc + nw_chan, M, nu, nv), dt))
    xs = (Qs, Bs, ts, fs, ss, nrm, bits)
    s0, s1, fog_on = _substep_fog_slabs((True, fluence, None) if vol is None else vol, ns, M,
                                        per_w)
    if s0 == 0 and s1 == ns:
        body = step
    else:  # one scan, each slab's step chosen by a flag: each body compiled once (cloud-tomo,
        # N = 64: a Jacobi iteration compiled in 3.4 s against 9.0 s as three scans, the same
        # time per iteration; the transpose keeps its three scans, which ran faster there)
        fog = jnp.asarray((np.arange(ns) >= s0) & (np.arange(ns) < s1))
        xs = (fog, xs)

        def body(carry, x):
            return jax.lax.cond(x[0], step, vacuum, carry, x[1])
    carry, (lam, irr) = jax.lax.scan(body, init, xs, unroll=2)
    lam_last = carry[4]
    if per_w:  # the slab after the last, in wrap order, finishes the last slab's Λ
        order = np.arange(M) % nw
        take = lambda a: jnp.take(a, order, axis=0)  # noqa
        qn = take(Q)
        if aniso:
            qn = jnp.moveaxis(qn, -1, 0)[: 1 + nj]
        nxt = (qn, take(B), take(tau_half_unit), take(geo.free), take(geo.surf),
               jnp.moveaxis(take(geo.normal), -1, 0) if surfaces else nrm[0],
               jnp.moveaxis(take(geo.blocked), -1, 0) if surfaces else bits[0])
        _, (lam_last, _) = (step if fog_on else vacuum)(carry, nxt)
    exit_ = jnp.swapaxes(carry[0][0][..., M : M + nu, M : M + nv], 0, 1)
    lam = jnp.concatenate([lam[1:], lam_last[None]])  # step s finished slab s − 1's Λ
    return _substep_outputs(jnp.moveaxis(lam, 1, -1), irr, exit_, weight, nk, nw, per_w,
                            geo.wscale)


def face_consts(dirs: DirectionSet, face: int, harm: np.ndarray | None = None,
                linear: bool = False, substep: bool = False) -> SweepConsts:
    """The constants of ``face``; ``harm``: (6, D, K) the anisotropic basis at every face's
    directions (``_harmonics.Basis.faces``), or None (isotropic); ``linear``: the
    linear-source scheme's slope table."""
    axis, sign = FACE_AXES[face]
    u, v = face_plane_axes(axis)
    vec = dirs.vectors[face]
    unit = np.stack([vec[:, u], vec[:, v], sign * vec[:, axis]], -1)  # (u, v, w) frame
    return SweepConsts(
        unit=jnp.asarray(unit),
        pq=jnp.asarray(dirs.pq, jnp.int32),
        length=jnp.asarray(dirs.length),
        weight=jnp.asarray(dirs.weights[face]),
        harm=None if harm is None else jnp.asarray(harm[face]),
        slope=jnp.asarray(vec * np.asarray(dirs.length)[:, None]) if linear else None,
        sub=jnp.asarray(substep_offsets(dirs.pq, dirs.M)) if substep and dirs.M > 1 else None,
    )


def cell_samples(dirs: DirectionSet, face: int, n: int = 8):
    """(vectors (D, n², 3), weights (D, n²)): n × n points over each direction's cell of the
    cube face (clipped to the face), as unit world vectors, with their solid angles
    normalized to 1 per cell — to average a function of direction over the cell."""
    axis, sign = FACE_AXES[face]
    u, v = face_plane_axes(axis)
    M = dirs.M
    lo = np.maximum(dirs.pq - 0.5, -M)  # (D, 2)
    hi = np.minimum(dirs.pq + 0.5, M)
    t = (np.arange(n) + 0.5) / n
    pu = lo[:, 0, None] + t[None] * (hi[:, 0] - lo[:, 0])[:, None]  # (D, n)
    pv = lo[:, 1, None] + t[None] * (hi[:, 1] - lo[:, 1])[:, None]
    gu = np.repeat(pu, n, axis=1)
    gv = np.tile(pv, (1, n))
    vec = np.zeros(gu.shape + (3,))
    vec[..., axis] = sign * M
    vec[..., u], vec[..., v] = gu, gv
    r = np.linalg.norm(vec, axis=-1)
    wt = M / r**3  # solid angle per unit face area
    return vec / r[..., None], wt / wt.sum(1, keepdims=True)


def sky_boundary(dirs: DirectionSet, face: int) -> np.ndarray:
    """(D,) fraction of the sky radiance entering along each direction of a face.

    Light travelling downward (L̂z < 0) comes from the sky; a horizontal direction's cell is half
    above the horizon.
    """
    lz = dirs.vectors[face][:, 2]
    return np.where(lz < -1e-12, 1.0, np.where(lz > 1e-12, 0.0, 0.5))



def sweep_face_mesh(args, mesh, *, stacked: bool, M: int, periodic: tuple[bool, bool, bool],
                    warmup: int, surfaces: bool, attenuate: bool = True, fluence: bool = True,
                    kernel: str = "loop", recompute: bool = False):
    """``sweep_face`` on a ("face", "u", "v") device mesh (``shard_map``).

    args: ``(Q, B, tau_half_unit, bc, geo, consts)`` as for ``sweep_face``, each with a leading
    axis of 2 (the + and − faces of one axis) when ``stacked`` — split over "face" — or without
    it.  The plane (u, v) is split over the mesh's "u" and "v" axes; each device sweeps its block
    and exchanges M-wide borders with its neighbours after every slab (``Halo``).  A plane whose
    size is not a multiple of the devices along an open side is padded with vacuum (FREE nodes,
    no fog, no source: radiance crosses them unchanged, so the padding changes nothing) and the
    results cropped; a periodic side must divide evenly.
    """
    from jax.sharding import PartitionSpec as P

    Q, B, tau, bc, geo, consts = args
    nfd, npu, npv = (mesh.shape[a] for a in ("face", "u", "v"))
    lead = 1 if stacked else 0
    nw, nu, nv = Q.shape[lead:]
    _, per_u, per_v = periodic
    pads = []
    for n, nd, per, name in ((nu, npu, per_u, "u"), (nv, npv, per_v, "v")):
        extra = -n % nd
        if extra and per:
            raise SolverError(
                f"the periodic {name} side of the sweep plane ({n} nodes) does not split evenly "
                f"over {nd} devices; choose a resolution or device mesh that divides it"
            )
        if (n + extra) // nd < M:
            raise SolverError(
                f"the sweep plane's {name} side ({n} nodes) over {nd} devices leaves blocks "
                f"thinner than M = {M}; use fewer devices along {name}"
            )
        pads.append(extra)
    pu, pv = pads

    def pad(x, fill, u_ax):  # u_ax: position of u in x (v follows)
        if not (pu or pv):
            return x
        w = [(0, 0)] * x.ndim
        w[u_ax], w[u_ax + 1] = (0, pu), (0, pv)
        return jnp.pad(x, w, constant_values=fill)

    a = lead + 1  # u position in (lead, nw, nu, nv, ...)
    Q, B, tau = pad(Q, 0, a), pad(B, 0, a), pad(tau, 0, a)
    geo = FaceGeometry(free=pad(geo.free, True, a), surf=pad(geo.surf, False, a),
                       normal=pad(geo.normal, 0, a), blocked=pad(geo.blocked, 0, a))
    f = ("face",) if stacked else ()
    plane = P(*f, None, "u", "v")
    specs_in = (plane, plane, plane, P(*f), FaceGeometry(free=plane, surf=plane,
                                                         normal=P(*f, None, "u", "v", None),
                                                         blocked=P(*f, None, "u", "v", None)),
                jax.tree.map(lambda _: P(*f), consts))
    specs_out = (plane, plane, P(*f, None, None, "u", "v"))
    # a plane split over devices exchanges its borders; a whole plane (only the ± faces split)
    # needs no exchange (a Halo of one device per axis is the plain wrap), and without one a
    # CPU's values come from the native kernel like one device's
    halo = Halo(u_axis="u", v_axis="v", nu_dev=npu, nv_dev=npv) if npu * npv > 1 else None

    def local(Q, B, tau, bc, geo, consts):
        if stacked:
            Q, B, tau, bc, geo, consts = jax.tree.map(lambda x: x[0],
                                                      (Q, B, tau, bc, geo, consts))
        out = sweep_face(Q, B, tau, bc, geo, consts, M=M, periodic=periodic, warmup=warmup,
                         surfaces=surfaces, attenuate=attenuate, fluence=fluence, halo=halo,
                         kernel=kernel, recompute=recompute)
        return jax.tree.map(lambda x: x[None], out) if stacked else out

    if not stacked and nfd > 1:
        raise SolverError("a mesh with a 'face' axis of 2 needs stacked ± face arguments")
    lam, irr, ex = jax.shard_map(local, mesh=mesh, in_specs=specs_in, out_specs=specs_out,
                                 check_vma=False)(Q, B, tau, bc, geo, consts)
    if pu or pv:
        lam = lam[..., :nu, :nv, :] if lam.ndim > irr.ndim else lam[..., :nu, :nv]
        irr = irr[..., :nu, :nv]
        ex = ex[..., :nu, :nv]
    return lam, irr, ex
