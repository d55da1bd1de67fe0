"""The linear-source scheme's diffusion length in thick fog: a model of the lattice, and the solver.

Deep inside a thick, nearly conservative slab the collided light falls as e^(−κz).  The exact
κ (isotropic scattering, albedo a) solves a·artanh(k)/k = 1 with k = κ/σ_t.  The light solve's
linear-source scheme (``forward/sweep/_kernel._linear_node``: each node's segment of M planes
along a lattice vector L, the source linear along it with the slope L·G, G = h∇Λ by central
differences) has its own κ for the same mode: every quantity of the sweep is then a multiple
of e^(κz), so each direction's segment update can be solved for it exactly (here, in NumPy,
over the lattice's own direction set and weights), and Λ/(4πq) as a function of κ gives the
scheme's dispersion relation a·Λ(κ)/(4πq) = 1.  The light through the slab is off by about
e^(−(κ_scheme − κ)·τ).

Why the scheme's κ is too large where a segment spans a diffusion length: along a chain of a
direction's nodes (spacing ℓ = |L|h), the source's end values from two neighbouring nodes
(q_k + s_k/2 against q_(k+1) − s_(k+1)/2) do not meet; summed over a direction and its
opposite this leaves a leakage ∝ (κh)⁴·(m⁴/12 + m²/6) (m = L_z planes per segment) next to the
true diffusion term ∝ (κh)²·m²/(σ_t|L|h): relative to it, (κh)²·σ_t h·(M³/24 + M/12) for the
vertical directions, 12% at N = 32, M = 2 and 33% at M = 3 in a slab of τ = 64, albedo 0.99.
Diffusion is weakened, κ grows, and too little light gets through.

``--measure`` also runs the light solve (``SweepSolver(scheme="linear")``, a periodic slab,
float64, a sun overhead) and fits κ to its Λ over the slab's middle half (the mode and its
reflection from the bottom, A·e^(−κz) + B·e^(κ(z − τ))).

    python benchmarks/linear_dispersion.py [--measure] [--out benchmarks/results]
"""

from __future__ import annotations

import argparse
import functools
import math
from pathlib import Path

import numpy as np

import _common as C


def _lattice_vectors(M: int):
    """(vectors (n, 3) with major component ±M, weights (n,)) over the six faces' directions
    (edge and corner directions appear on each of their faces with that face's share)."""
    from difffog.geometry._directions import direction_set

    ds = direction_set(M)
    v = ds.vectors.reshape(-1, 3)
    return v / np.max(np.abs(v), axis=1, keepdims=True) * M, ds.weights.reshape(-1)


@functools.lru_cache(maxsize=None)
def _segments(sth: float, M: int):
    """Per direction of the lattice (each face's share): (m = L_z, the half-segment terms em,
    (1 − φ)/2, φ, ψ of ``linear_source_terms`` at τ = σ_t·h·|L|/2, the weight), float64."""
    import jax
    import jax.numpy as jnp

    from difffog._numerics import linear_source_terms

    V, W = _lattice_vectors(M)
    th = 0.5 * sth * np.linalg.norm(V, axis=1)  # each half of the node's segment
    with jax.enable_x64(True):
        phi, psi = (np.asarray(t, np.float64) for t in linear_source_terms(jnp.asarray(th))[:2])
    return V[:, 2], np.expm1(-th), 0.5 * (1.0 - phi), phi, psi, W


def scheme_ratio(x: float, sth: float, M: int, g_slope=math.sinh) -> float:
    """Λ/(4πq) of the linear scheme for q ∝ e^(κz): x = κh, sth = σ_t·h; the slope's z
    component G_z/q = ``g_slope(x)`` (central differences: sinh x).  Each direction's node
    update is the kernel's own (``_kernel._linear_node``); the radiance a node receives is its
    chain's previous node's, c·q_(k−1), and c is the chain's fixed point (for a direction in
    the plane, m = 0, an infinite layer: c = 1, R̄ = q)."""
    from difffog.forward.sweep._kernel import _linear_node

    m, em, omp_half, phi, psi, W = _segments(float(sth), int(M))
    s = m * g_slope(x)

    def through(c):  # (r_node, r_out, R̄) per q_k when the node receives c·q_(k−1)
        return _linear_node(c * np.exp(-m * x), 1.0, s, em, omp_half, phi, psi)

    o0, o1 = through(0.0)[1], through(1.0)[1]  # r_out is affine in c
    return float(np.sum(W * through(o0 / (1.0 - (o1 - o0)))[2])) / (4.0 * math.pi)


def _root(f, lo: float, hi: float, n: int = 400) -> float:
    from scipy.optimize import brentq

    ks = np.linspace(lo, hi, n)
    v = [f(k) for k in ks]
    for i in range(n - 1):
        if (v[i] <= 0 < v[i + 1]) or (v[i] >= 0 > v[i + 1]):
            return brentq(f, ks[i], ks[i + 1])
    return math.nan


def exact_kappa(a: float) -> float:
    """κ/σ_t of the slowest mode of an isotropic medium of albedo a: a·artanh(k)/k = 1."""
    return _root(lambda k: a * math.atanh(k) / k - 1.0, 1e-9, 0.999999)


def scheme_kappa(a: float, sth: float, M: int, g_slope=math.sinh) -> float:
    """κ/σ_t of the same mode in the linear scheme at σ_t·h = ``sth`` (NaN: no decaying
    mode below κh = 0.9·σ_t h)."""
    return _root(lambda k: a * scheme_ratio(k * sth, sth, M, g_slope) - 1.0, 1e-6, 0.9)


def measured_kappa(tau: float, albedo: float, N: int, M: int) -> float:
    """κ/σ_t fitted to the light solve's Λ over the middle half of a slab of ``N`` nodes (the
    linear scheme, a sun overhead, float64)."""
    import jax
    import jax.numpy as jnp

    jax.config.update("jax_enable_x64", True)
    from difffog import Params
    from difffog.forward.sweep._solver import SweepSolver
    from difffog.study._slab import slab_problem

    scene, lat, margin = slab_problem(tau, albedo, N, M, sky=0.0, sun=(1.0, 0.0))
    solver = SweepSolver(M=M, max_iterations=20000, tol=1e-11, scheme="linear")
    geom = solver.prepare(scene, lat)
    light = jax.jit(solver.solve)(geom, Params.from_scene(scene, jnp.float64))
    lam = np.asarray(light.fluence, np.float64)[0, 0]
    lam = lam if lam.ndim == 1 else lam[:, 0]
    fog = lam[margin:margin + N]
    z = (np.arange(N) + 0.5) * (tau / N)
    keep = (np.arange(N) >= N // 4) & (np.arange(N) < 3 * N // 4) & (fog > 1e-250)
    if keep.sum() < 4:  # the light is spent before mid-depth (it underflows)
        return math.nan
    z, y = z[keep], fog[keep]

    def misfit(k):  # Λ ≈ A e^(−κz) + B e^(κ(z − τ)): the mode and its reflection at the bottom
        basis = np.stack([np.exp(-k * z), np.exp(k * (z - tau))], axis=1) / y[:, None]
        coef = np.linalg.lstsq(basis, np.ones_like(y), rcond=None)[0]
        return float(np.sum((basis @ coef - 1.0) ** 2))

    from scipy.optimize import minimize_scalar

    k0 = abs(np.polyfit(z, np.log(y), 1)[0])
    return float(minimize_scalar(misfit, bounds=(0.3 * k0, 3.0 * k0), method="bounded",
                                 options={"xatol": 1e-9 * k0}).x)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--tau", type=float, default=64.0)
    ap.add_argument("--albedos", type=float, nargs="+", default=[0.9, 0.99, 0.999])
    ap.add_argument("--n", type=int, nargs="+", default=[32, 64, 128])
    ap.add_argument("--m", type=int, nargs="+", default=[2, 3])
    ap.add_argument("--measure", action="store_true", help="fit κ to the light solve's Λ too")
    ap.add_argument("--out", type=Path, default=C.RESULTS)
    ap.add_argument("--name", default="linear_dispersion")
    a = ap.parse_args(argv)
    rows = []
    for alb in a.albedos:
        ke = exact_kappa(alb)
        for N in a.n:
            sth = a.tau / N
            for M in a.m:
                ks = scheme_kappa(alb, sth, M)
                kx = scheme_kappa(alb, sth, M, lambda x: x)  # the slope's exact derivative
                km = measured_kappa(a.tau, alb, N, M) if a.measure else math.nan
                row = [f"{alb:g}", N, M, f"{sth:g}", f"{ke * sth:.3f}", f"{ke:.5f}",
                       f"{100 * (ks / ke - 1):+.2f}%", f"{math.exp(-(ks - ke) * a.tau):.3g}",
                       f"{100 * (kx / ke - 1):+.2f}%"]
                if a.measure:
                    row.append(f"{100 * (km / ke - 1):+.2f}%")
                rows.append(row)
                print(" ".join(map(str, row)), flush=True)
    head = ["a", "N", "M", "σ_t h", "κh (exact)", "κ/σ_t exact", "scheme κ", "T factor e^(−Δκτ)",
            "κ with exact slopes"] + (["κ from the solve's Λ"] if a.measure else [])
    lines = ["# The linear scheme's diffusion length in thick fog", "",
             f"`python benchmarks/linear_dispersion.py{' --measure' if a.measure else ''}` "
             f"(module docstring): a slab of τ = {a.tau:g} over N nodes; κ of the slowest "
             "mode, the scheme's against the exact, and the factor it puts on the light "
             "through the slab.", "", *C.md_table(head, rows), "", "## Machine", "",
             *C.machine_lines(C.machine(bandwidth=False))]
    print("wrote", C.write_text(a.out / f"{a.name}.md", "\n".join(lines) + "\n"))
    return rows


if __name__ == "__main__":
    main()
