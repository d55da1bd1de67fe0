"""Angular moments for anisotropic (Henyey–Greenstein) scattering in the sweep.

The sweep carries the radiance of a node along each lattice direction; an isotropic fog needs
only its fluence Λ = Σ_d w_d R̄_d.  A Henyey–Greenstein fog scatters with
    p(μ) = Σ_l (2l + 1)/(4π) g^l P_l(μ),
and by the addition theorem ∫ p(ω·ω') I(ω') dω' = Σ_lm g^l Y_lm(ω) ∫ Y_lm I, so the in-scatter
source of every direction follows from the radiance's real spherical-harmonic moments
m_lm = Σ_d w_d Y_lm(d) R̄_d.  The series is cut at order L with the δ-M scaling (Wiscombe
1977): the forward peak f = g^(L+1) is treated as unscattered (ζ' = ζ(1 − f)) and the rest
scatters with the Legendre coefficients g'_l = (g^l − f)/(1 − f), l ≤ L.  L = 0 is the
δ-isotropic scaling (f = g).

On the discrete direction set the basis is made exactly orthonormal under the lattice's own
quadrature (weights w_d): the harmonics of order ≥ 1 have their weighted mean removed (so a
scattering node re-emits exactly the power it removes: Σ_d w_d Q_d = 4π Q_0, whatever the
moments) and are orthonormalized symmetrically (Löwdin), so that the discrete phase matrix
Σ_k g'_k Ỹ_k(d) Ỹ_k(d') w_d' reproduces the moments it is given.  The same linear map
evaluates the basis at any other direction (the sun, the sky's quadrature, camera rays).
"""

from __future__ import annotations

import functools
import math

import numpy as np

from ...geometry._directions import direction_set

#: the largest expansion order the sweep accepts (K = (L+1)² − 1 moments per node)
MAX_ORDER = 7


def order_of(k: int) -> int:
    """The degree l of basis function k (k = l² + l + m, k ≥ 1 here counts from 1)."""
    return int(math.isqrt(k))


def real_sh(vectors, L: int, xp=np):
    """Real orthonormal spherical harmonics Y_lm of unit ``vectors`` (..., 3), 0 ≤ l ≤ L, in
    the order k = l² + l + m: (..., (L+1)²).  ``xp``: numpy or jax.numpy."""
    x, y, z = vectors[..., 0], vectors[..., 1], vectors[..., 2]
    out = [None] * ((L + 1) ** 2)
    # (x + iy)^m = r_xy^m e^{imφ}; P̃_l^m(z) = P_l^m(z) / (1 − z²)^{m/2} is a polynomial
    cm, sm = xp.ones_like(z), xp.zeros_like(z)
    for m in range(L + 1):
        if m > 0:
            cm, sm = x * cm - y * sm, x * sm + y * cm
        pmm = xp.full_like(z, _double_factorial(2 * m - 1))
        prev, cur = None, pmm
        for l in range(m, L + 1):
            if l == m + 1:
                prev, cur = cur, z * (2 * m + 1) * pmm
            elif l > m + 1:
                prev, cur = cur, ((2 * l - 1) * z * cur - (l + m - 1) * prev) / (l - m)
            norm = math.sqrt((2 * l + 1) / (4 * math.pi)
                             * math.factorial(l - m) / math.factorial(l + m))
            if m == 0:
                out[l * l + l] = norm * cur
            else:
                out[l * l + l + m] = math.sqrt(2.0) * norm * cur * cm
                out[l * l + l - m] = math.sqrt(2.0) * norm * cur * sm
    return xp.stack(out, axis=-1)


def _double_factorial(n: int) -> float:
    return float(np.prod(np.arange(n, 0, -2))) if n > 0 else 1.0


class Basis:
    """The sweep's basis of order L on the direction set of half-width M (see the module doc).

    ``evaluate(vectors)`` → Ỹ_k (..., K) for k = 1..K (order ≥ 1; the isotropic part is
    carried as Λ), ``degree`` (K,) the l of each, ``faces`` (6, D, K) the basis at every face
    direction (propagation directions, world frame).
    """

    def __init__(self, L: int, M: int):
        self.L, self.M = int(L), int(M)
        ds = direction_set(M)
        vec = ds.vectors.reshape(-1, 3)
        w = ds.weights.reshape(-1)
        Y = real_sh(vec, self.L)[:, 1:]  # (6D, K)
        self.mean = (w @ Y) / w.sum()
        Yc = Y - self.mean
        G = Yc.T @ (w[:, None] * Yc)
        evals, evecs = np.linalg.eigh(G)
        if evals.size and evals.min() <= 1e-8 * evals.max():
            raise ValueError(f"the direction set of M = {M} cannot resolve harmonics of order "
                             f"{L}; use a smaller order or a larger M")
        self.transform = (evecs / np.sqrt(evals)) @ evecs.T  # G^(-1/2)
        self.degree = np.array([order_of(k) for k in range(1, (self.L + 1) ** 2)], np.int64)
        self.faces = self.evaluate(ds.vectors)  # (6, D, K)

    @property
    def K(self) -> int:
        return (self.L + 1) ** 2 - 1

    def evaluate(self, vectors, xp=np):
        """Ỹ_k at unit ``vectors`` (..., 3) (numpy or jax arrays) → (..., K)."""
        if self.K == 0:
            return xp.zeros(vectors.shape[:-1] + (0,), vectors.dtype)
        Y = real_sh(vectors, self.L, xp)[..., 1:]
        mean = xp.asarray(self.mean, Y.dtype)
        return (Y - mean) @ xp.asarray(self.transform, Y.dtype)


@functools.lru_cache(maxsize=None)
def basis(L: int, M: int) -> Basis:
    return Basis(L, M)


def moment_coefficients(g, L: int, M: int, xp=np):
    """(f, (K,) the δ-M coefficient g'_l of each moment of ``basis(L, M)``) (see ``delta_m``)."""
    f, coef = delta_m(g, L, xp)
    return f, (coef[basis(L, M).degree - 1] if L > 0 else coef)


def delta_m(g, L: int, xp=np):
    """δ-M scaling of a Henyey–Greenstein phase cut at order L: (f, coefficients) with f =
    g^(L+1) the forward-peak fraction (ζ' = ζ(1 − f)) and the coefficients (L,) the scaled
    Legendre moments g'_l = (g^l − f)/(1 − f) of orders 1..L (differentiable in g)."""
    f = g ** (L + 1)
    coef = [(g ** l - f) / (1.0 - f) for l in range(1, L + 1)]
    return f, (xp.stack(coef) if coef else xp.zeros((0,), xp.asarray(g).dtype))


@functools.lru_cache(maxsize=None)
def harmonic_moments(L: int, M: int) -> np.ndarray:
    """(K, K) T⁻¹ (symmetric): the moments m of ``basis(L, M)`` → the real harmonics' own
    moments a = T⁻¹·m = Σ_d w_d (Y(d) − μ) R̄_d (the direction set's quadrature of ∫ Y R dΩ,
    without the basis's orthonormalization), and back: the coefficients on Ỹ = (Y − μ)·T of
    Σ_k a_k (Y_k − μ_k) are T⁻¹·a."""
    if L == 0:
        return np.zeros((0, 0))
    return np.linalg.inv(basis(L, M).transform)
