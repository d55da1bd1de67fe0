"""Where the sweep's error on thin forward-scattering slabs comes from: its direction set.

Issue 15's slabs (g = 0.85, collimated sun, N = 32, M = 3, L = 3) read R 2–4% high at τ = 1
(``benchmarks/slab_anisotropic.py``), and the same at N = 64 and 128, so the error is
angular.  This script takes it apart with two plane-parallel solvers that share nothing with
the sweep's kernels (NumPy; the laterally infinite slab depends on depth only, so each is a
one-dimensional transport problem, exact in depth on a fine grid):

* ``exact``: discrete ordinates in μ (Gauss, the azimuth-averaged Henyey–Greenstein phase),
  solved order of scattering by order; it reproduces the adding-doubling table
  (``difffog/data/references/slab_adding_doubling.csv``) to 1e-5 and says what each order of
  scattering contributes.
* ``emulate``: the slab on the sweep's own direction set (``direction_set(M)``, its weights,
  the Löwdin basis ``Basis(L, M)``, the δ-M coefficients, the sun's first collision as the
  cell-averaged exact phase of ``_solver._sun_cells``), read by a camera in continuous μ as
  ``study._slab.slab_reflectance`` reads the sweep; only the depth is fine.  It reproduces the
  sweep's slab errors to ~0.1 point, so it isolates the angular discretization, and it lets
  one part of the scheme be swapped at a time:

  - ``dm``: the δ-M model itself in continuous μ (no direction set at all);
  - ``first-exact``: the once-scattered light (the sun's first collision, transported) in
    continuous directions, its moments in the continuous harmonics; every later order on
    the direction set;
  - ``first-M<k>``: the once-scattered light on the direction set of half-width k instead;
  - ``cell-power``: the first collision's power per cell from the cell's solid angle
    (W_d P_d = ∫_cell p dΩ) instead of the cell average normalized over the flux-corrected
    weights;
  - ``cell-moments``: the once-scattered light's moments weighted, per cell, by the phase's
    shape inside the cell (Σ_d w_d Z_d R̄_d with Z_d the phase-weighted cell mean of Ỹ)
    instead of the cell centre's Ỹ_d;
  - ``degreewise``: every order after the first scattered with the δ-M phase applied degree
    by degree on the harmonics' own moments (a = T⁻¹·m, source Ỹ·T⁻¹·(g' ⊙ a)), as
    ``SweepSolver(once_M=...)`` does for the once-scattered light, instead of the solve's g'_k
    on each (degree-mixing) Löwdin function; ``degreewise+first-M<k>`` both;
  - ``clip<c>``: the sun's phase flattened within c/M radians of the forward direction and
    the clipped power left in the beam (its extinction σ − f₁ζ), the cameras' single
    scattering with the same clipped phase (a δ-fit of the first collision).

    python benchmarks/slab_directions.py [--m 3] [--variants emulate dm first-exact first-M6
        first-M9 cell-power] [--sweep] [--out benchmarks/results/slab_directions.md]

``--sweep`` adds the sweep's own figure (N = 32, float64) beside the emulator's.
"""

from __future__ import annotations

import argparse
import math
import time

import numpy as np

import _common as C

G = 0.85


def hg(cos, g):
    """Henyey–Greenstein phase, normalized to 1 over 4π."""
    return (1 - g * g) / (4 * math.pi * (1 + g * g - 2 * g * cos) ** 1.5)


def hg_azimuth_mean(mu, mup, g, nphi=2048):
    """(len(mu), len(mup)) the phase between μ and μ' averaged over their azimuth difference."""
    phi = (np.arange(nphi) + 0.5) * math.pi / nphi
    s = np.sqrt(np.clip(1 - mu[:, None] ** 2, 0, None) * np.clip(1 - mup[None] ** 2, 0, None))
    out = np.zeros((len(mu), len(mup)))
    for k in range(0, nphi, 256):
        c = mu[:, None, None] * mup[None, :, None] + s[..., None] * np.cos(phi[k:k + 256])
        out += hg(np.clip(c, -1, 1), g).sum(-1)
    return out / nphi


def transport(J, mu, dtau):
    """Radiance (nz+1, D) of sources J (per unit optical depth, linear between the depth
    nodes) along directions of cosine ``mu`` (> 0 up); no light enters the slab.  A
    horizontal direction never leaves a laterally infinite slab: its radiance is J."""
    I = np.zeros_like(J)
    m = np.abs(mu)
    flat = m < 1e-12
    x = dtau / np.where(flat, 1.0, m)
    E = np.exp(-x)
    a, b = 1 - (1 - E) / x, (1 - E) / x - E  # weights of the near and the far end's source
    up, dn = mu > 1e-12, mu < -1e-12
    for i in range(J.shape[0] - 2, -1, -1):
        I[i, up] = I[i + 1, up] * E[up] + J[i, up] * a[up] + J[i + 1, up] * b[up]
    for i in range(J.shape[0] - 1):
        I[i + 1, dn] = I[i, dn] * E[dn] + J[i + 1, dn] * a[dn] + J[i, dn] * b[dn]
    I[:, flat] = J[:, flat]
    return I


def gauss_sphere(nmu, nphi):
    """Unit vectors (n, 3) and weights (sum 4π) of a Gauss(μ) × uniform(φ) product rule."""
    x, w = np.polynomial.legendre.leggauss(nmu)
    cm = np.concatenate([0.5 * (x + 1), -0.5 * (x + 1)])
    wm = np.concatenate([0.5 * w, 0.5 * w])
    phi = 2 * math.pi * (np.arange(nphi) + 0.5) / nphi
    sn = np.sqrt(1 - cm**2)
    om = np.stack([sn[:, None] * np.cos(phi), sn[:, None] * np.sin(phi),
                   np.broadcast_to(cm[:, None], (2 * nmu, nphi))], -1).reshape(-1, 3)
    return om, (wm[:, None] * np.full(nphi, 2 * math.pi / nphi)).reshape(-1)


def exact(tau, albedo, g, mu0, *, nmu=64, nz=400, orders=500, delta_m=None):
    """(R per order, T_scattered per order) of the slab under a sun of cosine ``mu0``.

    ``delta_m`` = L: the sweep's model instead, in continuous μ: the sun's beam attenuated by
    the true extinction and scattered once with the exact phase, everything after with the
    δ-M phase of order L (f = g^(L+1) left unscattered: extinction σ(1 − a f))."""
    x, w = np.polynomial.legendre.leggauss(nmu)
    mu = np.concatenate([(x + 1) / 2, -(x + 1) / 2])
    wt = np.concatenate([w / 2, w / 2])
    f = 0.0 if delta_m is None else g ** (delta_m + 1)
    if delta_m is None:
        P = hg_azimuth_mean(mu, mu, g) * 4 * math.pi
        P /= 0.5 * (P * wt).sum(1, keepdims=True)  # (1/2) Σ_j w_j P_ij = 1
    else:
        leg = [np.polynomial.legendre.legval(mu, np.eye(delta_m + 1)[l])
               for l in range(delta_m + 1)]
        P = sum((2 * l + 1) * (g**l - f) / (1 - f) * np.outer(leg[l], leg[l])
                for l in range(delta_m + 1))
    psun = hg_azimuth_mean(mu, np.array([-mu0]), g)[:, 0]
    ext = tau * (1 - albedo * f)  # the optical depth light travels through
    z = np.linspace(0, 1, nz + 1)
    J = albedo * tau / ext * np.exp(-tau * z / mu0)[:, None] * psun[None]
    rescatter = albedo * tau * (1 - f) / ext
    up = mu > 0
    R, T = [], []
    for _ in range(orders):
        I = transport(J, mu, ext / nz)
        R.append(2 * math.pi * (I[0, up] * mu[up] * wt[up]).sum() / mu0)
        T.append(2 * math.pi * (I[-1, ~up] * -mu[~up] * wt[~up]).sum() / mu0)
        J = rescatter / 2 * (I * wt) @ P.T
        if R[-1] < 1e-13 * R[0] and len(R) > 3:
            break
    return np.array(R), np.array(T)


def _continuous_basis(L):
    from difffog.forward.sweep._harmonics import real_sh

    return lambda v: real_sh(np.asarray(v, np.float64), L)[..., 1:]


def _first_collision(ds, sun_dir, g, power="average", phase=None, basis=None):
    """(D,) the sweep's per-direction first-collision phase P (Σ_d w_d P_d = 1); with
    ``basis``, also (D, K) the phase-weighted cell means of ``basis``."""
    from difffog.forward.sweep._solver import _sun_cells

    vec, wt = (np.asarray(a, np.float64) for a in _sun_cells(ds))
    W = ds.weights.reshape(-1)
    if power == "solid-angle":  # W_d P_d = the cell's own ∫ p dΩ
        wt = wt * (ds.raw_weights / ds.weights)[..., None]
    ps = wt * (hg(vec @ sun_dir, g) if phase is None else phase(vec @ sun_dir))
    P = ps.sum(-1).reshape(-1)
    P = P / (W * P).sum()
    if basis is None:
        return P
    Z = (ps[..., None] * basis(vec)).sum(-2) / ps.sum(-1)[..., None]
    return P, Z.reshape(P.size, -1)


def emulate(tau, albedo, g, zenith, M=3, L=3, *, variant="emulate", nz=400, nmu=64,
            nphi=64):
    """(R, T_scattered) of the slab on the sweep's direction set (module doc)."""
    from difffog.forward.sweep._harmonics import Basis
    from difffog.geometry._directions import direction_set

    degreewise = variant.startswith("degreewise")
    if degreewise:
        variant = variant[len("degreewise+"):] if "+" in variant else "emulate"

    ds = direction_set(M)
    V, W = ds.vectors.reshape(-1, 3), ds.weights.reshape(-1)
    B = Basis(L, M)
    Y = B.evaluate(V)
    f = g ** (L + 1)
    gl = (g ** np.asarray(B.degree) - f) / (1 - f)
    Tinv = np.linalg.inv(B.transform)

    def phase(m):  # the moments' source coefficients on Ỹ: per function, or degree by degree
        return ((m @ Tinv) * gl) @ Tinv if degreewise else m * gl
    ext = tau * (1 - albedo * f)
    rescatter = albedo * tau * (1 - f) / ext
    mu0 = math.cos(math.radians(zenith))
    sun = np.array([math.sin(math.radians(zenith)), 0.0, -mu0])  # the light's direction
    z = np.linspace(0, 1, nz + 1)
    beam = np.exp(-tau * z / mu0)
    first_src = albedo * tau / ext * beam  # per unit optical depth, times the phase
    single = first_src  # the cameras' single scattering, times the (unnormalized) phase
    extra_t = 0.0  # light the beam carries beyond the unscattered sun (clip: its cone)
    dz = ext / nz
    cont = _continuous_basis(L)
    lam1 = mom1 = None  # the once-scattered light in the continuous harmonics
    if variant == "first-exact" or variant.startswith("first-M"):
        if variant == "first-exact":
            om, wq = gauss_sphere(48, 96)
            p = hg(om @ sun, g)
            p /= (wq * p).sum()
        else:
            d1 = direction_set(int(variant[len("first-M"):]))
            om, wq = d1.vectors.reshape(-1, 3), d1.weights.reshape(-1)
            p = _first_collision(d1, sun, g)
        I1 = transport(first_src[:, None] * p[None], om[:, 2], dz)
        Yq = cont(om)
        if variant != "first-exact":  # the mean-free harmonics of that direction set
            Yq = Yq - (wq @ Yq) / wq.sum()
        lam1, mom1 = I1 @ wq, I1 @ (wq[:, None] * Yq)
        Yc = cont(V)
        Yc = Yc - (W @ Yc) / W.sum()  # re-emitting exactly its power on the lattice
        J = rescatter * (lam1[:, None] / (4 * math.pi) + (mom1 * gl) @ Yc.T)
    elif variant.startswith("clip"):
        c = math.cos(float(variant[len("clip"):]) / M)
        p_c = hg(c, g)
        # the power within the cone above p(c), (1/2)∫_c^1 4π(p − p_c) dμ, stays in the beam
        f1 = 0.5 * (1 - g * g) / g * ((1 + g * g - 2 * g) ** -0.5
                                      - (1 + g * g - 2 * g * c) ** -0.5) \
            - 0.5 * (1 - c) * 4 * math.pi * p_c
        phase = lambda cos: np.where(cos > c, p_c, hg(np.minimum(cos, c), g))  # noqa: E731
        beam = np.exp(-tau * (1 - albedo * f1) * z / mu0)
        first_src = albedo * tau * (1 - f1) / ext * beam
        single = albedo * tau / ext * beam
        extra_t = math.exp(-tau * (1 - albedo * f1) / mu0) - math.exp(-tau / mu0)
        J = first_src[:, None] * _first_collision(ds, sun, g, phase=phase)[None]
    else:
        power = "solid-angle" if variant == "cell-power" else "average"
        J = first_src[:, None] * _first_collision(ds, sun, g, power)[None]
    Z = Y
    if variant == "cell-moments":
        P, Z = _first_collision(ds, sun, g, basis=B.evaluate)
        J = first_src[:, None] * P[None]
    lam = np.zeros(nz + 1)
    mom = np.zeros((nz + 1, Y.shape[1]))
    for k in range(500):
        I = transport(J, V[:, 2], dz)
        lam_k, mom_k = I @ W, I @ (W[:, None] * (Z if k == 0 else Y))
        lam, mom = lam + lam_k, mom + mom_k
        J = rescatter * (lam_k[:, None] / (4 * math.pi) + phase(mom_k) @ Y.T)
        if np.abs(I).max() < 1e-14:
            break
    # the camera: continuous μ, the source azimuth-averaged (slab_reflectance's reading)
    x, w = np.polynomial.legendre.leggauss(nmu)
    cm, wm = 0.5 * (x + 1), 0.5 * w
    phi = 2 * math.pi * (np.arange(nphi) + 0.5) / nphi
    sn = np.sqrt(1 - cm**2)
    out = []
    for sign in (1.0, -1.0):
        om = np.stack([sn[:, None] * np.cos(phi), sn[:, None] * np.sin(phi),
                       sign * np.broadcast_to(cm[:, None], (nmu, nphi))], -1)
        Jc = rescatter * (lam[:, None] / (4 * math.pi) + phase(mom) @ B.evaluate(om).mean(1).T)
        # the sun's single scattering
        Jc += single[:, None] * (phase(om @ sun) if variant.startswith("clip")
                                    else hg(om @ sun, g)).mean(1)[None]
        if lam1 is not None:
            Jc += rescatter * (lam1[:, None] / (4 * math.pi)
                               + (mom1 * gl) @ cont(om).mean(1).T)
        Ic = transport(Jc, sign * cm, dz)
        out.append(2 * math.pi * (Ic[0 if sign > 0 else -1] * cm * wm).sum() / mu0)
    return out[0], out[1] + extra_t


def sweep_row(tau, albedo, zenith, M, L):
    """The sweep's own (R, T_scattered) at N = 32 (``slab_anisotropic.slab``)."""
    from slab_anisotropic import slab

    R, T, _, _ = slab(tau, albedo, G, 32, M, L, "collimated", zenith)
    return R, T - math.exp(-tau / math.cos(math.radians(zenith)))


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--m", type=int, default=3)
    ap.add_argument("--order", type=int, default=3, help="the phase order L")
    ap.add_argument("--taus", type=float, nargs="+", default=[1.0, 2.0, 4.0])
    ap.add_argument("--variants", nargs="+",
                    default=["emulate", "dm", "first-exact", "first-M6", "first-M9",
                             "cell-power"])
    ap.add_argument("--sweep", action="store_true", help="the sweep's own figure beside")
    ap.add_argument("--out", default=None)
    a = ap.parse_args(argv)
    import jax

    jax.config.update("jax_enable_x64", True)
    info = C.machine()
    C.print_machine(info)
    from difffog.study import references

    ref = {(r["albedo"], r["tau"], r["zenith_deg"]): (r["R_total"], r["T_scattered"])
           for r in references.slab_table()
           if r["g"] == G and r["illumination"] == "collimated"}
    t0 = time.perf_counter()
    rows, checks, worst = [], [], {}
    cols = (["sweep N=32"] if a.sweep else []) + a.variants
    for zen in (0.0, 60.0):
        for alb in (0.9, 0.99):
            for tau in a.taus:
                Rr, Tr = ref[(alb, tau, zen)]
                Ro, To = exact(tau, alb, G, math.cos(math.radians(zen)))
                checks.append(max(abs(Ro.sum() / Rr - 1), abs(To.sum() / Tr - 1)))
                cells = [f"{zen:g}°", f"{alb:g}", f"{tau:g}", f"{Rr:.5f}",
                         f"{Ro[0] / Ro.sum():.2f} / {Ro[1] / Ro.sum():.2f}"]
                for col in cols:
                    if col == "sweep N=32":
                        R, T = sweep_row(tau, alb, zen, a.m, a.order)
                    elif col == "dm":
                        R, T = (v.sum() for v in exact(tau, alb, G,
                                                       math.cos(math.radians(zen)),
                                                       delta_m=a.order))
                    else:
                        R, T = emulate(tau, alb, G, zen, a.m, a.order, variant=col)
                    eR, eT = 100 * (R / Rr - 1), 100 * (T / Tr - 1)
                    worst[col] = max(worst.get(col, 0.0), abs(eR), abs(eT))
                    cells.append(f"{eR:+.2f} / {eT:+.2f}")
                rows.append(cells)
                print(" | ".join(cells), flush=True)
    lines = [f"# The sweep's direction set on thin g = {G} slabs (M = {a.m}, L = {a.order})", "",
             "R / T_scattered error in % against adding-doubling, collimated sun; `python "
             "benchmarks/slab_directions.py` (module docstring: what each column swaps)."
             f" The exact solver's own largest difference from the table: "
             f"{100 * max(checks):.4f}%.", "",
             *C.machine_lines(info), "",
             *C.md_table(["sun", "albedo", "τ", "R (table)",
                          "orders 1 / 2 of R", *cols], rows), "",
             "Largest |error| over these rows: "
             + "; ".join(f"{c} {worst[c]:.2f}%" for c in cols),
             f"({time.perf_counter() - t0:.0f} s)"]
    print("\n".join(lines[-2:]))
    if a.out:
        C.write_text(a.out, "\n".join(lines) + "\n")


if __name__ == "__main__":
    main()
