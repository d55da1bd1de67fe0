"""The sweep solver: coordinate evolution on the light-ray manifold (Langer, Breton & Zucker).

For each of the six cube faces F we sweep the lattice plane by plane along F's axis.  The local
coordinate system C_i^F holds, for every node of plane i, the radiance arriving there along each
of F's (2M+1)² directions L = (p, q, M).  The paper's Local_Transformation C_i^F → C_{i+M}^F is a
*static* shift by (p, q) in the plane, so we process M planes at once: ``lax.scan`` runs over
slabs of M planes and carries the radiance of the previous slab (shape (M, D, nu, nv)).

Node cases for the node z = y − L a ray left before arriving at y (the paper's ``case {x − L}``):
  SOLID   → the ray starts at the surface between z and y: it arrives at y with y's radiosity B(y)
            (implemented with a negative sentinel, since radiance is otherwise never negative);
  FREE    → the arriving radiance, attenuated through the fog;
  SURFACE → 0 if the step reaches the surface ahead of z (−L·N(z) ≥ d(z), with d = sdf/h the
            node's distance to the surface in nodes: this stops rays jumping over thin solids),
            else the arriving radiance through the fog, as at a FREE node.
The paper's rule (B(z) if L·N(z) > 0, else 0) makes the M-node shell opaque: nodes deep in the
shell are shadowed by shallower ones (the innermost, which a camera sees, get ~70% of their
irradiance), rays near edges that leave the other wall arrive as 0, and the geometry grows by
up to M nodes.  Starting rays where they actually leave a solid keeps the surface where it is
and lets grazing rays pass through the shell fog.
Each node owns half of each segment it touches, with its own extinction σ_t and source; over a
half-segment of optical depth τ = σ_t·h·|L|/2 the exact step ("step characteristic") update is
    R ← T·R + (1 − T)·Q,   T = exp(−τ),
written as R + expm1(−τ)·(R − Q) so it stays exact and differentiable as τ → 0 and never goes
negative (the paper's first-order factor (1 − γ − ζ) does, once a step is optically thick).
Q = (ζ/(ζ+γ))·J is the source radiance, J the mean radiance (Λ/4π) of the previous iteration plus
the first-collision source of the sun.

Λ(y) += Σ_L w_L R(y, L) accumulates the fluence at FREE nodes (the paper's "isotropic
luminescence"); E(y) += c(y) Σ_L w_L R(y, L) max(0, −L̂·N(y)) the irradiance of SURFACE nodes with
the per-node cosine normalization c (so that a Lambertian hemisphere integrates to π).  One
Jacobi iteration = six sweeps = one more bounce.
"""

from __future__ import annotations

import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ._directions import FACE_AXES, DirectionSet, face_plane_axes

FOUR_PI = 4.0 * math.pi
_SOLID = -1.0  # sentinel radiance leaving a SOLID node (real radiance is never negative)


def to_face(x, axis: int, sign: int):
    """(nx, ny, nz, ...) → (nw, nu, nv, ...) with w the sweep axis, oriented along the sweep."""
    u, v = face_plane_axes(axis)
    y = jnp.moveaxis(x, (axis, u, v), (0, 1, 2))
    return y[::-1] if sign < 0 else y


def from_face(y, axis: int, sign: int):
    u, v = face_plane_axes(axis)
    if sign < 0:
        y = y[::-1]
    return jnp.moveaxis(y, (0, 1, 2), (axis, u, v))


def _shift_plane(x, bc, M: int, periodic_u: bool, periodic_v: bool):
    """y[m, p, q, u, v] = x[m, p, q, u − p, v − q] for p, q ∈ [−M, M] (indices p+M, q+M).

    x: (m, P, Q, nu, nv); bc: (P, Q) radiance entering from outside the plane (open sides).
    The graph holds 2·(2M+1) static slices, so it does not grow with the (2M+1)² directions.
    """
    m, P, Q, nu, nv = x.shape

    def pad(a, axis, periodic):
        widths = [(0, 0)] * 5
        widths[axis] = (M, M)
        if periodic:
            return jnp.pad(a, widths, mode="wrap")
        shape = list(a.shape)
        shape[axis] = M
        fill = jnp.broadcast_to(bc[None, :, :, None, None], shape).astype(a.dtype)
        return jnp.concatenate([fill, a, fill], axis=axis)

    xp = pad(x, 3, periodic_u)
    x = jnp.stack([xp[:, i, :, 2 * M - i : 2 * M - i + nu, :] for i in range(P)], axis=1)
    xp = pad(x, 4, periodic_v)
    return jnp.stack([xp[:, :, j, :, 2 * M - j : 2 * M - j + nv] for j in range(Q)], axis=2)


class FaceGeometry(eqx.Module):
    """Static, per-face view of the lattice (arrays in the face frame (nw, nu, nv))."""

    free: jax.Array  # bool
    surf: jax.Array  # bool
    normal: jax.Array  # (nw, nu, nv, 3) normal in the face frame (u, v, w)
    depth: jax.Array  # distance of SURFACE nodes to the surface, in nodes (sdf/h)


class SweepConsts(eqx.Module):
    """Per-face direction constants, in the face frame."""

    unit: jax.Array  # (D, 3) L̂ in (u, v, w) components
    length: jax.Array  # (D,) |L| in lattice units
    weight: jax.Array  # (D,) solid-angle weights


def sweep_face(Q, B, tau_half_unit, bc, geo: FaceGeometry, consts: SweepConsts, *, M: int,
               periodic: tuple[bool, bool, bool], warmup: int, surfaces: bool):
    """One sweep over a face.  All arrays are in the face frame (nw, nu, nv).

    Q: source radiance at FREE nodes; B: radiosity at SURFACE nodes; tau_half_unit: σ_t·h/2 (the
    half-segment optical depth per unit |L|); bc: (D,) radiance entering through the domain
    boundary.  Returns (Λ, E, exit) where Λ and E are (nw, nu, nv) and ``exit`` is the carry
    after the last slab: (M, D, nu, nv), the radiance leaving the last M planes.
    """
    nw, nu, nv = Q.shape
    P = 2 * M + 1
    D = P * P
    per_w, per_u, per_v = periodic
    dt = Q.dtype

    if per_w:
        # Planes in wrap order, ending with planes 0..nw-1, preceded by a warm-up long enough for
        # every non-horizontal ray to have entered through an open side.
        total = int(math.ceil((nw + warmup) / M) * M)
        order = np.arange(nw - total, nw) % nw
        pick = lambda a: jnp.take(a, order, axis=0)  # noqa: E731
    else:
        total = int(math.ceil(nw / M) * M)
        pad = total - nw

        def pick(a):
            widths = [(0, pad)] + [(0, 0)] * (a.ndim - 1)
            return jnp.pad(a, widths)

    def slabs(a):
        a = pick(a)
        return a.reshape((total // M, M) + a.shape[1:])

    xs = (slabs(Q), slabs(B), slabs(tau_half_unit), slabs(geo.free), slabs(geo.surf),
          slabs(geo.normal), slabs(geo.depth))
    unit = consts.unit.astype(dt)
    length = consts.length.astype(dt)
    weight = consts.weight.astype(dt)
    bc_pq = bc.reshape(P, P).astype(dt)

    def step(carry, slab):
        Qs, Bs, ts, fs, ss, ns, ds = slab  # (M, nu, nv); normal (M, nu, nv, 3)
        r_mid = _shift_plane(carry.reshape(M, P, P, nu, nv), bc_pq, M, per_u, per_v)
        r_mid = r_mid.reshape(M, D, nu, nv)
        # half-segment in this node (arrival): R + expm1(-τ)(R - Q); τ = 0 off the fog
        em = jnp.expm1(-ts[:, None] * length[None, :, None, None])
        r_arr = r_mid + em * (r_mid - Qs[:, None])
        if surfaces:  # a ray leaving a solid starts with the radiosity of the node it reaches
            r_arr = jnp.where(r_mid < 0, Bs[:, None], r_arr)
        lam = jnp.einsum("mdij,d->mij", r_arr, weight)
        r_through = r_arr + em * (r_arr - Qs[:, None])  # second half-segment
        if surfaces:
            ldotn = jnp.einsum("mijc,dc->mdij", ns, unit)  # L̂·N
            irr = jnp.einsum("mdij,d->mij", r_arr * jnp.maximum(-ldotn, 0.0), weight)
            # the step's displacement towards the surface, in nodes, against the distance to it
            hits = ss[:, None] & (-ldotn * length[None, :, None, None] >= ds[:, None])
            r_out = jnp.where(hits, 0.0, r_through)
            r_out = jnp.where(fs[:, None] | ss[:, None], r_out, _SOLID)
        else:
            irr = jnp.zeros_like(lam)
            r_out = jnp.where(fs[:, None], r_through, 0.0)
        return r_out, (lam, irr)

    if per_w:  # equilibrium guess for horizontal rays that never leave a periodic domain
        init = jnp.broadcast_to(xs[0][0][:, None], (M, D, nu, nv)).astype(dt)
    else:
        init = jnp.broadcast_to(bc.astype(dt)[None, :, None, None], (M, D, nu, nv))
    exit_, (lam, irr) = jax.lax.scan(step, init, xs)
    lam = lam.reshape((total,) + lam.shape[2:])
    irr = irr.reshape((total,) + irr.shape[2:])
    if per_w:
        lam, irr = lam[total - nw :], irr[total - nw :]
    else:
        lam, irr = lam[:nw], irr[:nw]
    return lam, irr, exit_


def face_consts(dirs: DirectionSet, face: int) -> SweepConsts:
    axis, sign = FACE_AXES[face]
    u, v = face_plane_axes(axis)
    vec = dirs.vectors[face]
    unit = np.stack([vec[:, u], vec[:, v], sign * vec[:, axis]], -1)  # (u, v, w) frame
    return SweepConsts(
        unit=jnp.asarray(unit), length=jnp.asarray(dirs.length), weight=jnp.asarray(dirs.weights[face])
    )


def sky_boundary(dirs: DirectionSet, face: int) -> np.ndarray:
    """(D,) fraction of the sky radiance entering along each direction of a face.

    Light travelling downward (L̂z < 0) comes from the sky; a horizontal direction's cell is half
    above the horizon.
    """
    lz = dirs.vectors[face][:, 2]
    return np.where(lz < -1e-12, 1.0, np.where(lz > 1e-12, 0.0, 0.5))
