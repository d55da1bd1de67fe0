"""What the terms save: the same scene solved with only the terms it needs (terms="auto", the
solver's "plan", ``SweepGeometry.terms``) and with every term forced on (terms="all").

    python benchmarks/bench_plan.py                # N = 48, M = 3, float32
    python benchmarks/bench_plan.py --N 64
    python benchmarks/bench_plan.py --quick --out /tmp/plan   # N = 16, M = 2

Cases:
- ring-box (no fog) vs the same scene with a zero-density fog forced on (ζ = γ = 0, all terms):
  no fog step, no Λ;
- translucent-cube (fog in a sub-box, 12% of the lattice at N = 32) vs no region restriction;
- furnace (no sun, no sky) vs every pass on;
- translucent-cube with ζ = 0 and every albedo 0 (nothing scatters or reflects) → one pass
  vs iterating.
For each: the warm time of 10 Jacobi iterations (fixed work: the per-iteration saving), the
warm time of a default solve (GMRES to 1e-4, sun and sky passes included), and the largest
difference between the two light fields (they must agree).  Writes plan.md (with the
machine: JAX backend and devices, copy bandwidth, measured in the same run) to ``--out``
(default benchmarks/results).  Public API only, and the renderer's vacuum margin.
"""

from __future__ import annotations

import argparse
import os
from pathlib import Path

import jax.numpy as jnp
import numpy as np

import _common as C
from difffog import Fog, Params, SweepSolver, load_scene, voxelize
from difffog.geometry._lattice import VACUUM_MARGIN


def timed(solver, scene, lat, p):
    g = solver.prepare(scene, lat)
    c, _ = C.compile_timed(solver.solve, g, p)
    t = C.time_calls(lambda: c(g, p), 2)
    return t.best, t.value, g


def case(title, scene_auto, scene_all, N, M):
    # the renderer's vacuum margin (two nodes since stop 82, M + 1 before)
    lat_a = voxelize(scene_auto, N, M, margin=VACUUM_MARGIN)
    lat_f = voxelize(scene_all, N, M, margin=VACUUM_MARGIN)
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
            row["terms"] = "; ".join(ln.split(None, 1)[1]
                                     for ln in ga.terms.lines(lat_a.shape)[1:3])
    print(row, flush=True)
    return row


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--N", type=int, default=None, help="default 48; with --quick 16")
    ap.add_argument("--M", type=int, default=None, help="default 3; with --quick 2")
    ap.add_argument("--out", type=Path, default=C.RESULTS, help="folder of the report")
    C.add_quick(ap)
    args = C.parse(ap, argv)
    N = args.N or (16 if args.quick else 48)
    M = args.M or (2 if args.quick else 3)
    info = C.machine()
    C.print_machine(info)
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
        "# What the terms save (benchmarks/bench_plan.py)",
        "",
        f"N = {N}, M = {M}, float32, warm times (best of 2, compilation excluded); load average "
        f"{load:.1f} at start on a CPU shared with other jobs, so compare within a row. "
        "'all' = SweepSolver(terms='all'): every term built; 'plan' = terms='auto'. Difference "
        "= max relative difference of B and of the fluence at fog nodes between the two.",
        "",
        *C.machine_lines(info),
        "",
    ]
    table = []
    for r in rows:
        (ia, if_), (sa, sf) = r["iter10"], r["solve"]
        table.append([r["case"], f"{ia:.2f} / {if_:.2f}", f"{if_ / ia:.1f}×",
                      f"{sa:.2f} / {sf:.2f}", f"{r['iterations'][0]} / {r['iterations'][1]}",
                      f"{sf / sa:.1f}×", f"{r['diff']:.1e}"])
    lines += C.md_table(["case", "10 iterations: plan / all (s)", "saving",
                         "solve to 1e-4: plan / all (s)", "iterations", "saving", "difference"],
                        table)
    C.write_text(args.out / "plan.md", lines)
    print("\n".join(lines))


if __name__ == "__main__":
    main()
