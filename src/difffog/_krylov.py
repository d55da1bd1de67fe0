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

Stopping rule: the remaining relative error is estimated as ‖r‖ / (σ·‖x‖), with σ the smallest
singular value of the Hessenberg matrices seen so far — an estimate of σ_min(I − K) from above
(the Krylov space quickly captures the slowly decaying mode that makes Jacobi slow) — so the
bound ‖e‖ ≤ ‖r‖/σ_min(I − K) is an estimate rather than a guarantee, like Jacobi's
change·ρ/(1 − ρ).  Norms are 2-norms over the state vector.
"""

from __future__ import annotations

from typing import Callable

import jax
import jax.numpy as jnp


def _safe_div(a, b):
    ok = b != 0
    return jnp.where(ok, a / jnp.where(ok, b, 1.0), 0.0)


def gmres(apply_k: Callable, b, *, restart: int, max_matvecs: int, tol: float, used: int = 1,
          hist=None, progress: Callable | None = None):
    """Solve (I − K)x = b for a flat vector b; K = ``apply_k`` (linear).

    restart: Krylov steps per cycle; max_matvecs: cap on applications of K, counting ``used``
    already spent by the caller (computing b); tol: stop once the estimated relative error
    ≤ tol (0: run to the cap).  hist: (max_matvecs,) array recording the relative residual
    ‖r‖/‖x‖ (the change one more Jacobi step would make) after every application.
    Returns (x, hist, applications, error estimate).
    """
    dt = b.dtype
    m = int(restart)
    n = b.shape[0]
    idx = jnp.arange(m)
    tiny = jnp.finfo(dt).tiny
    if hist is None:
        hist = jnp.full((max_matvecs,), jnp.nan, dt)

    def matvec(v):
        return v - apply_k(v)

    def cycle_cond(c):
        _, _, k, _, err, _, stop = c
        return (k < max_matvecs) & ~stop

    def cycle(c):
        x0, r0, k, sig, err, hist, _ = c
        beta = jnp.linalg.norm(r0)
        V = jnp.zeros((m + 1, n), dt).at[0].set(_safe_div(r0, beta))
        H = jnp.zeros((m + 1, m), dt)  # Hessenberg (unrotated), for σ_min
        R = jnp.zeros((m, m), dt)  # rotated: upper triangular
        cs = jnp.zeros((m,), dt)
        sn = jnp.zeros((m,), dt)
        g = jnp.zeros((m + 1,), dt).at[0].set(beta)

        def solve_y(R, g, j):
            live = idx <= j
            Rp = jnp.where(live[None, :] & live[:, None], R, jnp.eye(m, dtype=dt))
            return jax.scipy.linalg.solve_triangular(Rp, jnp.where(live, g[:m], 0.0), lower=False)

        def step_cond(s):
            _, _, _, _, _, _, j, k, _, _, _, stop = s
            return (j < m) & (k < max_matvecs) & ~stop

        def step(s):
            V, H, R, cs, sn, g, j, k, sig, err, hist, _ = s
            w = matvec(V[j])
            h1 = V @ w  # rows > j of V are zero
            w = w - h1 @ V
            h2 = V @ w
            w = w - h2 @ V
            h = (h1 + h2)
            hn = jnp.linalg.norm(w)
            V = V.at[j + 1].set(_safe_div(w, hn))
            h = h.at[j + 1].set(hn)
            H = H.at[:, j].set(h)

            def rot(i, h):  # apply the earlier rotations to the new column
                a, b_ = h[i], h[i + 1]
                return h.at[i].set(cs[i] * a + sn[i] * b_).at[i + 1].set(-sn[i] * a + cs[i] * b_)

            h = jax.lax.fori_loop(0, j, rot, h)
            a, b_ = h[j], h[j + 1]
            den = jnp.hypot(a, b_)
            c_ = jnp.where(den > tiny, _safe_div(a, den), 1.0)
            s_ = jnp.where(den > tiny, _safe_div(b_, den), 0.0)
            cs, sn = cs.at[j].set(c_), sn.at[j].set(s_)
            R = R.at[:, j].set(h[:m].at[j].set(den))
            g = g.at[j + 1].set(-s_ * g[j]).at[j].set(c_ * g[j])
            resid = jnp.abs(g[j + 1])
            # σ_min of the active (j+2) × (j+1) block; unused columns padded beyond its norm
            live_c = idx <= j
            pad = jnp.linalg.norm(H) + 1.0
            Hp = jnp.where(live_c[None, :], H, 0.0) + jnp.where(
                (jnp.arange(m + 1)[:, None] == idx[None, :]) & ~live_c[None, :], pad, 0.0)
            sig = jnp.minimum(sig, jnp.linalg.svd(Hp, compute_uv=False)[-1])
            xn = jnp.linalg.norm(x0 + solve_y(R, g, j) @ V[:m])
            rel = _safe_div(resid, xn)
            err = _safe_div(rel, sig)
            k = k + 1
            hist = hist.at[k - 1].set(rel)
            if progress is not None:
                jax.debug.callback(progress, k, rel, err)
            stop = ((err <= tol) & (k >= 2)) | (resid == 0)
            return V, H, R, cs, sn, g, j + 1, k, sig, err, hist, stop

        s = (V, H, R, cs, sn, g, jnp.asarray(0), k, sig, err, hist, jnp.asarray(False))
        V, H, R, cs, sn, g, j, k, sig, err, hist, stop = jax.lax.while_loop(step_cond, step, s)
        x = x0 + solve_y(R, g, j - 1) @ V[:m]
        # restart: the true residual (one more application) unless done
        done = stop | (k >= max_matvecs)
        r = jax.lax.cond(done, lambda: r0 * 0, lambda: b - matvec(x))
        hist = jnp.where(done, hist, hist.at[k].set(_safe_div(jnp.linalg.norm(r),
                                                               jnp.linalg.norm(x))))
        k = jnp.where(done, k, k + 1)
        return x, r, k, sig, err, hist, stop

    init = (jnp.zeros_like(b), b, jnp.asarray(used), jnp.asarray(jnp.inf, dt),
            jnp.asarray(jnp.inf, dt), hist, jnp.asarray(False))
    x, _, k, _, err, hist, _ = jax.lax.while_loop(cycle_cond, cycle, init)
    return x, hist, k, err
