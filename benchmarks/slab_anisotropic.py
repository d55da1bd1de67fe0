"""Henyey–Greenstein slabs (g = 0.85) against the adding-doubling table, per phase order L.

For each L, N, M: R and T of laterally infinite slabs (τ ∈ {1, 2, 4, 16}, albedo ∈ {0.9, 0.99})
under a diffuse sky and a collimated sun at zenith 0° and 60°, as a camera integrating over
the hemisphere would measure them (``difffog.study._slab.slab_reflectance``: the lattice's
scattered light from its moments, plus the sun's single scattering with the exact phase),
relative to the table (``difffog/data/references/slab_adding_doubling.csv``), float64.

    python benchmarks/slab_anisotropic.py [--n 32] [--m 3] [--orders 0 1 2 3 4]
        [--first-collision beam|deposit] [--scheme auto|step|linear|substep]
        [--out benchmarks/results/slab_anisotropic.md]
"""

from __future__ import annotations

import argparse
import csv
import time

import _common as C

CASES = [("diffuse", None), ("collimated", 0.0), ("collimated", 60.0)]


def slab(tau, albedo, g, N, M, L, illumination, zenith, first_collision="beam", scheme="auto",
         once_M=None):
    import jax
    import jax.numpy as jnp
    import numpy as np

    from difffog import Params
    from difffog.forward.sweep._harmonics import basis
    from difffog.forward.sweep._solver import SweepSolver, source_field
    from difffog.study._slab import slab_problem, slab_reflectance, sun_scatter_terms

    sun = None if illumination == "diffuse" else (1.0, zenith)
    solver = SweepSolver(M=M, max_iterations=4000, tol=1e-8, phase_order=L,
                         first_collision=first_collision, scheme=scheme, once_M=once_M)
    scene, lat, margin = slab_problem(tau, albedo, N, M, sun=sun, sky=0.0 if sun else 1.0, g=g)
    if solver.lattice_M(scene) > M:  # the once-scattered light's directions: a wider shell
        scene, lat, margin = slab_problem(tau, albedo, N, solver.lattice_M(scene),
                                          sun=sun, sky=0.0 if sun else 1.0, g=g)
    geom = solver.prepare(scene, lat)

    @jax.jit
    def run(p):
        light = solver.solve(geom, p)
        pb = solver.problem(geom, p)
        exact_sun = sun is not None and L > 0  # L = 0: the sun scatters as the lattice's
        return light, pb.sigma_t, source_field(pb, light, sun=not exact_sun)

    light, sigma, q = run(Params.from_scene(scene, jnp.float64))
    dens = np.asarray(lat.density)[0, 0]
    q, slope = np.asarray(q)[0, 0], None
    if geom.linear:  # thick steps take the linear scheme: its slope channels (x, y, z) come last
        q, slope = q[..., :-3], q[..., -1]
    ss = None
    if sun is not None and L > 0:
        ss = sun_scatter_terms(light, albedo, tau, g, dens)
    R, T = slab_reflectance(np.asarray(sigma)[0, 0], q, None, margin, lat.h,
                            sky=0.0 if sun else 1.0, sun=sun,
                            basis=basis(L, M) if L else None, sun_scatter=ss, slope=slope)
    ran = "linear" if geom.linear else "substep" if geom.substep else "step"
    return R, T, int(light.iterations), ran


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, nargs="+", default=[32])
    ap.add_argument("--m", type=int, nargs="+", default=[3])
    ap.add_argument("--orders", type=int, nargs="+", default=[0, 1, 2, 3, 4])
    ap.add_argument("--taus", type=float, nargs="+", default=[1.0, 2.0, 4.0, 16.0])
    ap.add_argument("--albedos", type=float, nargs="+", default=[0.9, 0.99])
    ap.add_argument("--g", type=float, default=0.85)
    ap.add_argument("--first-collision", default="beam", choices=["beam", "deposit"],
                    help="SweepSolver.first_collision")
    ap.add_argument("--scheme", default="auto", choices=["auto", "step", "linear", "substep"],
                    help="SweepSolver.scheme")
    ap.add_argument("--collimated-only", action="store_true",
                    help="only the sunlit rows (what --once-m changes)")
    ap.add_argument("--once-m", type=int, default=None,
                    help="SweepSolver.once_M: the sun's once-scattered light on this direction set")
    ap.add_argument("--out", default=None)
    a = ap.parse_args(argv)
    import jax

    jax.config.update("jax_enable_x64", True)
    from difffog.study import references

    table = references.slab_table()

    def ref(albedo, tau, ill, zen):
        for r in table:
            if (r["albedo"] == albedo and r["tau"] == tau and r["g"] == a.g
                    and r["illumination"] == ill
                    and (zen is None or r["zenith_deg"] == zen)):
                return r["R_total"], r["T_total"]
        raise KeyError((albedo, tau, ill, zen))

    rows = []
    for N in a.n:
        for M in a.m:
            for L in a.orders:
                for ill, zen in [c for c in CASES
                                 if not (a.collimated_only and c[0] == "diffuse")]:
                    for albedo in a.albedos:
                        for tau in a.taus:
                            t = time.perf_counter()
                            R, T, k, scheme = slab(tau, albedo, a.g, N, M, L, ill, zen,
                                                   a.first_collision, a.scheme, a.once_m)
                            Rr, Tr = ref(albedo, tau, ill, zen)
                            row = dict(N=N, M=M, L=L, illumination=ill + ("" if zen is None
                                                                          else f" {zen:g}°"),
                                       albedo=albedo, tau=tau, R=R, T=T, R_ref=Rr, T_ref=Tr,
                                       R_err=R / Rr - 1, T_err=T / Tr - 1, iterations=k,
                                       scheme=scheme,
                                       s=time.perf_counter() - t)
                            rows.append(row)
                            print(f"N={N} M={M} L={L} {row['illumination']:15s} a={albedo} "
                                  f"τ={tau:g}: R {100 * row['R_err']:+6.1f}% "
                                  f"T {100 * row['T_err']:+6.1f}% ({scheme})", flush=True)
    lines = ["# Henyey–Greenstein slabs against adding-doubling", "",
             f"g = {a.g}; relative error of R / T in % (float64); "
             "`python benchmarks/slab_anisotropic.py`"
             + ("" if a.first_collision == "beam"
                else f"; first collision: {a.first_collision}")
             + ("" if a.scheme == "auto" else f"; `--scheme {a.scheme}`")
             + ("" if a.once_m is None else f"; `--once-m {a.once_m}`"), ""]
    lines += C.machine_lines(C.machine(bandwidth=False)) + [""]
    taus = a.taus
    head = ["N", "M", "L", "illumination", "albedo"] + [f"τ = {t:g}" for t in taus]
    body = []
    keys = sorted({(r["N"], r["M"], r["L"], r["illumination"], r["albedo"]) for r in rows},
                  key=lambda k: (k[0], k[1], k[2], k[3], k[4]))
    for key in keys:
        cells = []
        for t in taus:
            r = next(r for r in rows
                     if (r["N"], r["M"], r["L"], r["illumination"], r["albedo"]) == key
                     and r["tau"] == t)
            mark = {"linear": " ˡ", "substep": " ˢ"}.get(r["scheme"], "")
            cells.append(f"{100 * r['R_err']:+.1f} / {100 * r['T_err']:+.1f}{mark}")
        body.append(list(key) + cells)
    lines += C.md_table(head, body, "rrrlr" + "r" * len(taus))
    if any(r["scheme"] == "linear" for r in rows):
        lines += ["", "ˡ: the solver chose the linear scheme (optically thick steps)."]
    if any(r["scheme"] == "substep" for r in rows):
        lines += ["", "ˢ: the sub-stepped scheme."]
    worst = {}
    for r in rows:
        if r["tau"] <= 4:
            k = (r["N"], r["M"], r["L"])
            worst[k] = max(worst.get(k, 0.0), abs(r["R_err"]), abs(r["T_err"]))
    lines += ["", "Largest |error| over τ ≤ 4 (R and T): " + "; ".join(
        f"N={k[0]} M={k[1]} L={k[2]}: {100 * v:.1f}%" for k, v in sorted(worst.items()))]
    text = "\n".join(lines)
    print(text)
    if a.out:
        with open(a.out, "w") as f:
            f.write(text + "\n")
        with open(a.out.replace(".md", ".csv"), "w", newline="") as f:
            w = csv.DictWriter(f, fieldnames=list(rows[0]))
            w.writeheader()
            w.writerows(rows)


if __name__ == "__main__":
    main()
