"""A diffusion preconditioner for the light solve's GMRES (diffusion synthetic acceleration).

Near albedo 1 in optically thick fog the one-bounce operator K of x = Kx + b has eigenvalues
close to 1 whose modes are smooth in space: light diffusing through many mean free paths before
it is absorbed or leaves.  The sweeps move such a mode by about one mean free path per bounce,
so Jacobi needs ~1/(1 − albedo) bounces and GMRES still dozens (bench_krylov.py, bench_dsa.py).
A diffusion equation captures exactly these modes, at the cost of a few stencil sweeps.  After
one bounce from a fluence φ the error of φ½ = Kφ + b solves, in the diffusion approximation,

    −∇·(D ∇f) + σ_a f = σ_s (φ½ − φ),       D = 1/(3σ_t),

so φ + (I + C)·r with C = (−∇·D∇ + σ_a)⁻¹ σ_s and r = φ½ − φ is source iteration with
diffusion synthetic acceleration (Alcouffe 1977; Larsen 1982).  Here I + C preconditions GMRES
on (I − K)x = b from the right, in its flexible form (``_krylov.py``), so the residual GMRES
reports is exact whatever the inner solve returns: the preconditioner decides how fast, never
the answer (Warsa, Wareing & Morel 2004 showed Krylov methods keep DSA effective where the
diffusion operator is not exactly the transport scheme's own, as here).  It acts on the fluence
part of the state (Λ at fog nodes); the surfaces' irradiance passes through unchanged.

Discretization: the 7-point stencil on the lattice's fog nodes (σ_t > 0, not solid), face
coefficients 2D_iD_j/(D_i + D_j)/h² (harmonic mean), and at a face to a node without fog the
Marshak condition of a vacuum boundary: the flux D f/(h/2 + 2D) (f extrapolated to 0 at 2D
beyond the face).  Surfaces count as vacuum too: the light they reflect is the other part of
the state (E), which the preconditioner leaves to GMRES; with the walls' albedo in a
partial-current condition instead, the furnace (walls 0.5, ζ = 20) took 42 GMRES steps against
23 without any preconditioner, and 22 with vacuum walls.

The diffusion coefficient is the transport scheme's own where a lattice step is optically
thick: a node many mean free paths deep couples to its neighbour h|L| away along each lattice
direction only through the 1/(2τ) part of its segment-averaged fluence (``_kernel.py``), a
random walk of step h|L| taken with probability ~1/(σ_t h|L|), whose diffusion coefficient is
h|L|/6 rather than 1/(3σ_t).  So D = 1/(3σ_t) + h·mean|L|/6: the first term in thin cells, the
second in thick ones (issue 14's cube at N = 40, τ = 100, albedo 0.9999: 23 GMRES steps against
29 with 1/(3σ_t) alone).  The linear-source scheme (``SweepSolver.scheme``) has the true
coefficient, yet the same D preconditions it better than 1/(3σ_t) alone (measured, issue 14's
cube at N = 32, float32: ζ = 1000 47 GMRES steps against 90, ζ = 10000 63 against no
convergence in 600, where the flexible GMRES's error estimate drifted upward).  σ_t is floored
at one mean free path per lattice extent (a fog that thin needs no acceleration, and an unbounded D would make the inner solve ill-conditioned).
The inner solve is Jacobi-preconditioned conjugate gradients to a relative residual of
``CG_RTOL`` (the operator is symmetric positive definite).
"""

from __future__ import annotations

import dataclasses

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ..._numerics import safe_div
from ...geometry._directions import direction_set
from ._implicit import Preconditioner

#: relative residual of the inner diffusion solve: the preconditioner need not be exact or even
#: linear (flexible GMRES keeps the outer residual exact whatever it returns); on issue 14's cube
#: at N = 40 (τ 30-100, albedo 0.9999) 1e-2 took the same outer iterations as 1e-4 (16, 23) in
#: half the time, 1e-1 one more
CG_RTOL = 1e-2
#: cap on the inner solve's conjugate-gradient steps
CG_MAX_STEPS = 400


def neighbour(x, axis: int, s: int, periodic: bool):
    """x at the node +s (±1) along ``axis``: wrapped on a periodic axis, else 0 (False)
    beyond the lattice."""
    if periodic:
        return jnp.roll(x, -s, axis=axis)
    n = x.shape[axis]
    pad = [(0, 0)] * x.ndim
    pad[axis] = (0, 1) if s > 0 else (1, 0)
    xp = jnp.pad(x, pad)
    return jax.lax.slice_in_dim(xp, 1, n + 1, axis=axis) if s > 0 else (
        jax.lax.slice_in_dim(xp, 0, n, axis=axis))


def _mean_length(M: int) -> float:
    """The weighted mean lattice segment length Σ w_L |L| / Σ w_L, in units of h."""
    ds = direction_set(M)
    w = np.asarray(ds.weights)
    return float(np.sum(w * ds.length[None]) / np.sum(w))


class DiffusionOperator:
    """The lattice's diffusion operator A = −∇·D∇ + σ_a on fog nodes (identity elsewhere) and
    the scattering coefficient σ_s, for the preconditioner I + A⁻¹σ_s."""

    def __init__(self, sigma_t, ssa, solid, h: float, periodic_xy: bool, M: int, mu_bar=0.0):
        dt = sigma_t.dtype
        self.fog = (sigma_t > 0) & ~solid
        shape = sigma_t.shape
        size = max(shape) * h
        # transport-corrected with an anisotropic phase (mean cosine mu_bar of the scaled phase)
        sig = jnp.maximum(sigma_t * (1.0 - ssa * mu_bar), 1.0 / size)
        D = jnp.where(self.fog, 1.0 / (3.0 * sig) + h * _mean_length(M) / 6.0, 0.0)
        self.sigma_s = jnp.where(self.fog, ssa * sigma_t, 0.0)
        sigma_a = jnp.where(self.fog, (1.0 - ssa) * sigma_t, 0.0)
        self.periodic = (periodic_xy, periodic_xy, False)
        self.couplings = []  # (axis, shift, coefficient to the neighbour at +shift)
        diag = sigma_a
        for axis in range(3):
            for s in (1, -1):
                Dn = self._neighbour(D, axis, s)
                fog_n = self._neighbour(self.fog.astype(dt), axis, s) > 0
                inner = safe_div(2.0 * D * Dn, D + Dn) / h**2
                edge = safe_div(D, h * (h / 2.0 + 2.0 * D))
                c = jnp.where(self.fog & fog_n, inner, 0.0)
                diag = diag + jnp.where(self.fog, jnp.where(fog_n, inner, edge), 0.0)
                self.couplings.append((axis, s, c))
        # identity off the fog (the right-hand side is 0 there, so f stays 0)
        self.diag = jnp.where(self.fog, diag, 1.0)

    def _neighbour(self, x, axis: int, s: int):
        return neighbour(x, axis, s, self.periodic[axis])

    def apply(self, f):
        out = self.diag * f
        for axis, s, c in self.couplings:
            out = out - c * self._neighbour(f, axis, s)
        return out

    def solve(self, rhs):
        """A⁻¹ rhs by Jacobi-preconditioned conjugate gradients."""
        inv = 1.0 / self.diag
        bn = jnp.sqrt(jnp.sum(rhs * rhs))
        x0 = jnp.zeros_like(rhs)
        r0 = rhs
        z0 = inv * r0
        tiny = jnp.finfo(rhs.dtype).tiny

        def cond(c):
            _, r, _, _, k = c
            return (k < CG_MAX_STEPS) & (jnp.sqrt(jnp.sum(r * r)) > CG_RTOL * bn)

        def body(c):
            x, r, p, rz, k = c
            Ap = self.apply(p)
            alpha = rz / jnp.maximum(jnp.sum(p * Ap), tiny)
            x = x + alpha * p
            r = r - alpha * Ap
            z = inv * r
            rz_new = jnp.sum(r * z)
            p = z + (rz_new / jnp.maximum(rz, tiny)) * p
            return x, r, p, rz_new, k + 1

        x, *_ = jax.lax.while_loop(cond, body, (x0, r0, z0, jnp.sum(r0 * z0), jnp.asarray(0)))
        return jnp.where(self.fog, x, 0.0)

    def precondition(self, lam):
        """(I + A⁻¹σ_s) applied to the fluence part ``lam``."""
        return lam + self.solve(self.sigma_s * lam)

    def precondition_transposed(self, lam):
        """(I + A⁻¹σ_s)ᵀ = I + σ_s A⁻¹ (A is symmetric) applied to the fluence part ``lam``:
        the adjoint light solve's preconditioner."""
        return lam + self.sigma_s * self.solve(jnp.where(self.fog, lam, 0.0))


def on_fluence(fn, lam, channels: bool):
    """``fn`` applied to Λ, the fluence part of the light state's ``lam`` (channel 0 with an
    anisotropic phase; the moments pass through)."""
    return fn(lam) if not channels else lam.at[..., 0].set(fn(lam[..., 0]))


class DiffusionPreconditioner(Preconditioner):
    """``DiffusionOperator``'s I + A⁻¹σ_s (or its transpose) on the light state (Λ, E) of the
    tangent and adjoint solves (``_implicit.fixed_point``): the state's fluence (channel 0
    with moments) is preconditioned, the moments and the surfaces' irradiance pass through,
    as in the forward solve's GMRES.  Without it a gradient's adjoint solve in thick fog took
    the forward's unpreconditioned step count (benchmarks/bench_dsa.py --adjoint)."""

    sigma_t: jax.Array
    ssa: jax.Array
    solid: jax.Array
    mu_bar: jax.Array | float
    h: float = eqx.field(static=True)
    periodic_xy: bool = eqx.field(static=True)
    M: int = eqx.field(static=True)
    channels: bool = eqx.field(static=True)
    transposed: bool = eqx.field(static=True, default=False)

    def apply(self, tree):
        lam, irr = tree
        dsa = DiffusionOperator(self.sigma_t, self.ssa, self.solid, self.h, self.periodic_xy,
                                self.M, mu_bar=self.mu_bar)
        fn = dsa.precondition_transposed if self.transposed else dsa.precondition
        return on_fluence(fn, lam, self.channels), irr

    def transpose(self):
        return dataclasses.replace(self, transposed=not self.transposed)
