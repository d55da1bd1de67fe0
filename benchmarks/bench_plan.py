"""What the plan saves: the same scene solved with the plan (terms="auto") and with every term
forced on (terms="all").

    python benchmarks/bench_plan.py                # N = 48, M = 3, float32
    python benchmarks/bench_plan.py --N 64

Cases:
- ring-box (no fog) vs the same scene with a zero-density fog forced on (ζ = γ = 0, all terms):
  no fog step, no Λ;
- translucent-cube (fog in a sub-box, 12% of the lattice at N = 32) vs no region restriction;
- furnace (no sun, no sky) vs every pass on;
- translucent-cube with ζ = 0 and every albedo 0 (nothing scatters or reflects) → one pass
  vs iterating.
For each: the warm time of 10 Jacobi iterations (fixed work: the per-iteration saving), the
warm time of a default solve (GMRES to 1e-4, sun and sky passes included), and the largest
difference between the two light fields (they must agree).  Writes
benchmarks/results/plan.md.
"""

from __future__ import annotations

import argparse
import os
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from difffog import Params, SweepSolver, load_scene, voxelize
from difffog._scene import Fog

OUT = Path(__file__).resolve().parent / "results"


def timed(solver, scene, lat, p):
    g = solver.prepare(scene, lat)
    c = jax.jit(solver.solve).lower(g, p).compile()
    jax.block_until_ready(c(g, p))
    best = np.inf
    for _ in range(2):
        t = time.perf_counter()
        light = jax.block_until_ready(c(g, p))
        best = min(best, time.perf_counter() - t)
    return best, light, g


def case(title, scene_auto, scene_all, N, M):
    lat_a = voxelize(scene_auto, N, M, margin=M + 1)
    lat_f = voxelize(scene_all, N, M, margin=M + 1)
    pa = Params.from_scene(scene_auto, jnp.float32)
    pf = Params.from_scene(scene_all, jnp.float32)
    row = {"case": title}
    for label, kw in (("iter10", dict(method="jacobi", tol=0.0, max_iterations=10)),
                      ("solve", dict())):
        ta, la, ga = timed(SweepSolver(M=M, terms="auto", **kw), scene_auto, lat_a, pa)
        tf, lf, _ = timed(SweepSolver(M=M, terms="all", **kw), scene_all, lat_f, pf)
        row[label] = (ta, tf)
        if label == "solve":
            surf = np.asarray(ga.surf)
            d = [np.max(np.abs(np.asarray(la.radiosity) - np.asarray(lf.radiosity))[surf])
                 / max(np.max(np.abs(np.asarray(lf.radiosity))), 1e-30) if surf.any() else 0.0]
            dens = np.asarray(lat_a.density) > 0
            if dens.any():
                fa = np.asarray(la.fluence + la.sky_fluence)[dens]
                ff = np.asarray(lf.fluence + lf.sky_fluence)[dens]
                d.append(np.max(np.abs(fa - ff)) / max(np.max(np.abs(ff)), 1e-30))
            row["diff"] = float(max(d))
            row["iterations"] = (int(la.iterations), int(lf.iterations))
            row["plan"] = "; ".join(ln.split(None, 1)[1] for ln in ga.plan.lines(lat_a.shape)[1:3])
    print(row, flush=True)
    return row


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--N", type=int, default=48)
    ap.add_argument("--M", type=int, default=3)
    args = ap.parse_args()
    N, M = args.N, args.M
    load = os.getloadavg()[0]
    rows = []
    rb = load_scene("ring-box")
    rows.append(case("ring-box: no fog vs zero-density fog forced on", rb,
                     rb.replace(fog=Fog(scattering=0.0, absorption=0.0)), N, M))
    tc = load_scene("translucent-cube")
    rows.append(case("translucent-cube: fog restricted to its box vs whole lattice", tc, tc, N, M))
    fu = load_scene("furnace")
    rows.append(case("furnace (no sky): no sky pass vs a sky pass of zero radiance", fu, fu, N, M))
    dark = load_scene("translucent-cube", ["fog.scattering=0", "shape.ground.albedo=0",
                                           "shape.ring.albedo=0"])
    rows.append(case("translucent-cube, ζ = 0, albedo 0: one pass vs iterating", dark, dark, N, M))
    lines = [
        "# What the plan saves (benchmarks/bench_plan.py)",
        "",
        f"N = {N}, M = {M}, float32, warm times (best of 2, compilation excluded); load average "
        f"{load:.1f} at start on a 2-core CPU shared with other jobs, so compare within a row. "
        "'all' = SweepSolver(terms='all'): every term built. Difference = max relative "
        "difference of B and of the fluence at fog nodes between the two.",
        "",
        "| case | 10 iterations: plan / all (s) | saving | solve to 1e-4: plan / all (s) | "
        "iterations | saving | difference |",
        "|---|---:|---:|---:|---:|---:|---:|",
    ]
    for r in rows:
        (ia, if_), (sa, sf) = r["iter10"], r["solve"]
        lines.append(f"| {r['case']} | {ia:.2f} / {if_:.2f} | {if_ / ia:.1f}× | {sa:.2f} / {sf:.2f} | "
                     f"{r['iterations'][0]} / {r['iterations'][1]} | {sf / sa:.1f}× | "
                     f"{r['diff']:.1e} |")
    OUT.mkdir(exist_ok=True)
    (OUT / "plan.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
