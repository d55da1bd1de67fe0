"""Restarted GMRES for the light problem (I − K)x = b, with K applied matrix-free.

K is one bounce (six face sweeps + the scatter/reflect step), linear in the state; Jacobi
iterates x ← Kx + b and needs ~ln(1/tol)/(1 − ρ) applications when K's spectral radius ρ is near
1 (albedo near 1); GMRES builds the Krylov space of K instead and needs far fewer.

Written here rather than taken from ``lineax.GMRES`` because the sweep solver's stopping rule,
progress line and residual history need the residual after every application of K, each of
which is a full set of six sweeps: lineax checks convergence only at restarts (every
``restart`` applications) and returns no per-step residual.  The algorithm is the textbook one
(Saad, *Iterative Methods for Sparse Linear Systems*, §6.5): Arnoldi with classical Gram–Schmidt
applied twice (CGS2: orthogonal to working precision, also in float32), Givens rotations on the
Hessenberg matrix so that the residual norm is known after every step, restart after
``restart`` steps with the true residual recomputed.

Stopping rule: the remaining relative error is estimated as 4‖r‖ / (σ·‖x‖), with σ the smallest
singular value of the Hessenberg matrices seen so far — an estimate of σ_min(I − K) from above
(the Krylov space quickly captures the slowly decaying mode that makes Jacobi slow) — so the
bound ‖e‖ ≤ ‖r‖/σ_min(I − K) is an estimate rather than a guarantee, like Jacobi's
change·ρ/(1 − ρ).  Norms are 2-norms over the state vector; the factor 4 covers the gap to the
max-norm error that ``tol`` means (measured up to 4.5×, see ``_SAFETY``).
"""

from __future__ import annotations

from typing import Callable

import jax
import jax.numpy as jnp

from ..._numerics import safe_div


# ‖r‖/(σ‖x‖) is a 2-norm estimate; the solver's tolerance means the max-norm relative error of
# Λ and E, which it under-read by up to 4.5× (fog-balls, N = 12, M = 2, float64): scale it.
_SAFETY = 4.0


def _unbatched(fn: Callable) -> Callable:
    """``fn`` that, batched (vmapped), runs as a loop of unbatched calls
    (``jax.custom_batching.sequential_vmap``).

    For the Hessenberg matrix's SVD and triangular solve (LAPACK through jaxlib on a CPU): a
    batched LAPACK call in jaxlib 0.10 hands its batch to XLA's intra-op thread pool and blocks
    its own pool thread until the pieces are done, so two such calls at once on a 2-thread pool
    deadlock.  That is what hung batched light solves on a mesh of 2 host devices (both devices'
    copies of a vmapped GMRES step in ``lapack_sgesdd_ffi`` → ``jax::ParallelBatchMap`` →
    ``BlockingCounter::Wait``, every pool thread waiting, seen with gdb at stop 62:
    ``render_batch`` of 2 sets and a fit's Jacobian, fog-balls N = 10).  Unbatched, a call runs
    on its own thread.  The matrices are (restart + 1) × restart: the loop costs nothing beside
    a sweep.  On a CPU only (decided when traced, by JAX's default backend): a GPU's batched
    solvers do not share that pool, and stay batched."""
    one_by_one = jax.custom_batching.sequential_vmap(fn)

    def call(*args):
        return one_by_one(*args) if jax.default_backend() == "cpu" else fn(*args)

    return call


@_unbatched
def _smallest_singular_value(a):
    return jnp.linalg.svd(a, compute_uv=False)[-1]


@_unbatched
def _upper_triangular_solve(r, b):
    return jax.scipy.linalg.solve_triangular(r, b, lower=False)


def _err(rel, sig):
    """SAFETY·rel/sig, infinite (not 0) when sig = 0 < rel: a singular operator has not
    converged."""
    return jnp.where(sig > 0, _SAFETY * safe_div(rel, sig), jnp.where(rel > 0, jnp.inf, 0.0))


def _native_gram_schmidt(dtype, native: bool) -> bool:
    """Whether the Arnoldi steps' Gram–Schmidt is the native CPU kernel's
    (``_native.gram_schmidt``: the live rows of the basis only): asked for (``native``: one
    device, not a mesh's sharded state) and where the native kernels serve (``_native.serves``:
    a CPU, float32 or float64, the library built)."""
    from . import _native

    return native and _native.serves(dtype)


def _cgs2(V, a, j):
    """(h, w, ‖w‖): classical Gram–Schmidt applied twice of ``a`` against the rows [0, j] of V
    (h zero beyond them), by XLA's products over all rows."""
    live = jnp.arange(V.shape[0]) <= j
    h1 = jnp.where(live, V @ a, 0.0)
    w = a - h1 @ V
    h2 = jnp.where(live, V @ w, 0.0)
    w = w - h2 @ V
    return h1 + h2, w, jnp.linalg.norm(w)


def gmres(apply_k: Callable, b_shape, dtype, *, restart: int, max_matvecs: int, tol: float,
          progress: Callable | None = None, precondition: Callable | None = None, x0=None,
          native: bool = True):
    """Solve (I − K)x = b for flat vectors, with every application of the operator at one site.

    ``apply_k(u, with_sources)`` returns Ku + b if ``with_sources`` (a traced bool) else Ku: the
    right-hand side b is ``apply_k(0, True)``.  One call site (rather than separate ones for b,
    the Arnoldi steps and the residuals at restarts) keeps a single copy of the six sweeps in
    the compiled program.  The iteration starts from x₁ = Kx₀ + b, Jacobi's first iterate
    from ``x0`` (a guess, e.g. the solution of a nearby problem; default 0, so that x₁ = b and
    one application gives what one Jacobi iteration gives), whose residual b − (I − K)x₀ is
    x₁ − x₀; each restart spends one application on the true residual at x, b − (I − K)x =
    (x₁ − x₀) − (I − K)(x − x₀), which needs neither b nor Kx₀ apart.  The stopping test is
    relative to the solution (‖x‖), not to the first residual, so a guess close to the
    solution stops sooner.

    restart: Krylov steps per cycle; max_matvecs: cap on applications of K (b included); tol:
    stop once the estimated relative error ≤ tol (0: run to the cap).
    precondition: a map P ≈ (I − K)⁻¹ (or None), applied to each Krylov vector: flexible GMRES
    (Saad 1993) keeps z_j = P(v_j) and updates x by Σ y_j z_j, so the Arnoldi relation
    (I − K)Z = VH, and with it the residual GMRES reports, stays exact also when P is an
    inexact inner solve (not quite linear).  Memory: restart more state vectors.  The error
    bound ‖e‖ ≤ ‖r‖/σ_min(I − K) is estimated with σ_min(H)/max‖z_j‖.
    native: orthogonalize with the native CPU kernel where it serves
    (:func:`_native_gram_schmidt`; False on a device mesh, whose state is sharded): each of its
    three passes reads the j + 1 live rows of the basis, where XLA's four products read all
    restart + 1 (cloud-plane's default light solve: ~135 ms per step on a 2-core CPU at any j).
    Returns (x, hist, applications, error estimate); ``hist[k]`` is the relative residual
    ‖r‖/‖x‖ after application k + 1 (the change one more Jacobi step would make; 1 for b).
    """
    dt = dtype
    m = int(restart)
    if _native_gram_schmidt(dt, native):
        from ._native import gram_schmidt

        def orthogonalize(V, a, j):
            return gram_schmidt(V, a, j + 1)
    else:
        orthogonalize = _cgs2
    (n,) = b_shape
    idx = jnp.arange(m)
    idx1 = jnp.arange(m + 1)
    tiny = jnp.finfo(dt).tiny
    zn = jnp.zeros((n,), dt)
    xg = zn if x0 is None else jnp.asarray(x0, dt)  # the guess x₀

    def solve_y(R, g, j):  # y of the current cycle (entries > j zero)
        live = idx <= j
        Rp = jnp.where(live[None, :] & live[:, None], R, jnp.eye(m, dtype=dt))
        return _upper_triangular_solve(Rp, jnp.where(live, g[:m], 0.0))

    def cond(c):
        return ~c["stop"] & (c["k"] < max_matvecs)

    def body(c):
        phase, j, x, b, V = c["phase"], c["j"], c["x"], c["b"], c["V"]
        is0, is1 = phase == 0, phase == 1  # phase 2: a restart (neither)
        if precondition is not None:
            z = precondition(V[j])
            Z = c["Z"].at[jnp.minimum(j, m - 1)].set(jnp.where(is1, z, c["Z"][jnp.minimum(j, m - 1)]))
        else:
            z, Z = V[j], None
        pn = jnp.where(is1, jnp.maximum(c["pn"], jnp.linalg.norm(z)), c["pn"])
        u = jnp.where(is1, z, x - xg)  # phase 2: (I − K)(x − x₀), see above
        u = jnp.where(is0, xg, u)
        y = apply_k(u, is0)
        k = c["k"] + 1
        Au = u - y  # (I − K)u

        # -- phase 1: one Arnoldi step (CGS2) and its Givens rotation
        h, w, hn = orthogonalize(V, Au, j)
        h = h.at[j + 1].set(hn)
        H = c["H"].at[:, j].set(h)
        cs, sn = c["cs"], c["sn"]

        def rot(i, h):
            a, b_ = h[i], h[i + 1]
            return h.at[i].set(cs[i] * a + sn[i] * b_).at[i + 1].set(-sn[i] * a + cs[i] * b_)

        h = jax.lax.fori_loop(0, j, rot, h)
        a, b_ = h[j], h[j + 1]
        den = jnp.hypot(a, b_)
        c_ = jnp.where(den > tiny, safe_div(a, den), 1.0)
        s_ = jnp.where(den > tiny, safe_div(b_, den), 0.0)
        cs1, sn1 = cs.at[j].set(c_), sn.at[j].set(s_)
        R1 = c["R"].at[:, j].set(h[:m].at[j].set(den))
        g = c["g"]
        g1 = g.at[j + 1].set(-s_ * g[j]).at[j].set(c_ * g[j])
        # den = 0: the new Hessenberg column vanishes (I − K is singular on the Krylov space,
        # e.g. a conservative region that keeps its light): no progress, not convergence
        singular = den <= tiny
        resid = jnp.where(singular, jnp.abs(g[j]), jnp.abs(g1[j + 1]))
        live_c = idx <= j
        pad = jnp.linalg.norm(H) + 1.0
        Hp = jnp.where(live_c[None, :], H, 0.0) + jnp.where(
            (idx1[:, None] == idx[None, :]) & ~live_c[None, :], pad, 0.0)
        sig1 = jnp.minimum(c["sig"], _smallest_singular_value(Hp) / pn)
        yv = solve_y(R1, g1, j)
        vnew = safe_div(w, hn)
        cx = c["cx"].at[j + 1].set(vnew @ x)  # V·x₀, for ‖x₀ + Vy‖ without another pass
        xn1 = jnp.sqrt(jnp.maximum(c["x0n2"] + 2.0 * (cx[:m] @ yv) + yv @ yv, 0.0))
        rel1 = safe_div(resid, xn1)
        err1 = _err(rel1, sig1)
        stop1 = ((err1 <= tol) & (k >= 2)) | (resid == 0) | singular
        finish = stop1 | (j + 1 == m) | (k >= max_matvecs)

        # -- phase 2: true residual at x, start a cycle from it
        r = b - Au
        beta = jnp.linalg.norm(r)
        v0 = safe_div(r, beta)
        x0n2 = x @ x
        rel2 = safe_div(beta, jnp.sqrt(x0n2))
        err2 = jnp.where(jnp.isfinite(c["sig"]), _err(rel2, c["sig"]), jnp.inf)
        # an exactly zero residual (Kb = 0: nothing scatters or reflects) is the solution: no
        # error left, not a stagnation.  (All entries zero, not beta = 0, which a tiny residual
        # can reach by underflow in float32.)
        err2 = jnp.where(jnp.all(r == 0), jnp.zeros_like(err2), err2)
        stop2 = (beta == 0) | (err2 <= tol)

        # -- assemble by phase (phase 0: b = x = Kb·0 + b, then a residual)
        row = jnp.where(is1, j + 1, 0)
        V = V.at[row].set(jnp.where(is1, vnew, v0))
        x_new = jax.lax.cond(is1 & finish, lambda: x + yv @ (V[:m] if Z is None else Z), lambda: x)
        x_new = jnp.where(is0, y, x_new)
        out = dict(
            phase=jnp.where(is1, jnp.where(finish, 2, 1), jnp.where(is0, 2, 1)),
            j=jnp.where(is1, j + 1, 0),
            x=x_new,
            b=jnp.where(is0, y - xg, b),  # the residual at x₀
            V=V,
            H=jnp.where(is1, H, 0.0),
            R=jnp.where(is1, R1, 0.0),
            cs=jnp.where(is1, cs1, 0.0),
            sn=jnp.where(is1, sn1, 0.0),
            g=jnp.where(is1, g1, jnp.zeros_like(g).at[0].set(beta)),
            cx=jnp.where(is1, cx, jnp.zeros_like(cx).at[0].set(v0 @ x)),
            x0n2=jnp.where(is1, c["x0n2"], x0n2),
            sig=jnp.where(is1, sig1, c["sig"]),
            pn=pn,
            k=k,
            **({} if Z is None else {"Z": Z}),
        )
        rel = jnp.where(is0, 1.0, jnp.where(is1, rel1, rel2)).astype(dt)
        out["err"] = jnp.where(is0, jnp.inf, jnp.where(is1, err1, err2)).astype(dt)
        out["stop"] = jnp.where(is0, False, jnp.where(is1, stop1, stop2))
        out["hist"] = c["hist"].at[k - 1].set(rel)
        if progress is not None:
            jax.debug.callback(progress, k, rel, out["err"])
        return out

    init = dict(
        phase=jnp.asarray(0), j=jnp.asarray(0), x=zn, b=zn, V=jnp.zeros((m + 1, n), dt),
        H=jnp.zeros((m + 1, m), dt), R=jnp.zeros((m, m), dt), cs=jnp.zeros((m,), dt),
        sn=jnp.zeros((m,), dt), g=jnp.zeros((m + 1,), dt), cx=jnp.zeros((m + 1,), dt),
        x0n2=jnp.zeros((), dt), sig=jnp.asarray(jnp.inf, dt), pn=jnp.asarray(1.0, dt),
        k=jnp.asarray(0),
        err=jnp.asarray(jnp.inf, dt), stop=jnp.asarray(False),
        hist=jnp.full((max_matvecs,), jnp.nan, dt),
    )
    if precondition is not None:
        init["Z"] = jnp.zeros((m, n), dt)
    c = jax.lax.while_loop(cond, body, init)
    return c["x"], c["hist"], c["k"], c["err"]
